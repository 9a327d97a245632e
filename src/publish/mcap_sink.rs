//! The MCAP sink (`[publish] mcap = FILE`, or `--record FILE` on `run` and `replay`): every
//! published message on its stream's channel (`/gdvae/<stream>/state`, `/events`, `/rejected`),
//! JSON-encoded under a JSON schema named after the message's schema (`gdvae.state/1`, ...), so
//! that a run opens afterwards in Foxglove or any MCAP reader, its fields ready to plot.
//!
//! Chunks are written whole: when one fills (256 KiB) and at least once a second, so a node
//! killed mid-run leaves a file readable up to its last complete chunk (the node's own recording
//! source reads such a file, as does any streaming MCAP reader); the summary and footer follow
//! when the run ends. A write error closes the sink with one log line; the others go on and the
//! run fails at its end.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::time::{Duration, Instant};

use super::sink::{PublishError, Sink};
use crate::state::{Output, Stamps, EVENT_SCHEMA, REJECTED_SCHEMA, STATE_SCHEMA};

/// A chunk is written at the latest this long after the previous one.
const FLUSH_EVERY: Duration = Duration::from_secs(1);
const CHUNK_BYTES: u64 = 256 * 1024;

pub struct McapSink {
    writer: Option<mcap::Writer<BufWriter<File>>>,
    path: String,
    schemas: HashMap<&'static str, u16>,
    /// Channel id and the next sequence number, by topic.
    channels: HashMap<String, (u16, u32)>,
    flushed: Instant,
    failed: Option<String>,
}

impl McapSink {
    pub fn create(path: &str) -> Result<Self, PublishError> {
        let fail = |e: String| PublishError::Sink {
            path: path.to_string(),
            source: std::io::Error::other(e),
        };
        let file = File::create(path).map_err(|source| PublishError::Sink {
            path: path.to_string(),
            source,
        })?;
        let writer = mcap::WriteOptions::new()
            .profile("")
            .library(concat!("gdvae-node ", env!("CARGO_PKG_VERSION")))
            .chunk_size(Some(CHUNK_BYTES))
            .compression(Some(mcap::Compression::Zstd))
            .create(BufWriter::new(file))
            .map_err(|e| fail(e.to_string()))?;
        Ok(Self {
            writer: Some(writer),
            path: path.to_string(),
            schemas: HashMap::new(),
            channels: HashMap::new(),
            flushed: Instant::now(),
            failed: None,
        })
    }

    /// Writes one message on `/gdvae/<stream>/<kind>` under `schema`.
    fn write<T: serde::Serialize>(
        &mut self,
        stream: &str,
        kind: &str,
        schema: &'static str,
        stamps: &Stamps,
        message: &T,
    ) -> Result<(), PublishError> {
        let data = serde_json::to_vec(message).map_err(|e| PublishError::Encode(e.to_string()))?;
        let topic = format!("/gdvae/{stream}/{kind}");
        if let Err(e) = self.write_bytes(&topic, schema, stamps, &data) {
            self.close(e.to_string());
        }
        Ok(())
    }

    fn write_bytes(&mut self, topic: &str, schema: &'static str, stamps: &Stamps, data: &[u8]) -> mcap::McapResult<()> {
        let Some(writer) = self.writer.as_mut() else {
            return Ok(());
        };
        let schema_id = match self.schemas.get(schema) {
            Some(id) => *id,
            None => {
                let json_schema = format!(r#"{{"title":"{schema}","type":"object"}}"#);
                let id = writer.add_schema(schema, "jsonschema", json_schema.as_bytes())?;
                self.schemas.insert(schema, id);
                id
            }
        };
        let (channel_id, sequence) = match self.channels.get_mut(topic) {
            Some(channel) => channel,
            None => {
                let id = writer.add_channel(schema_id, topic, "json", &BTreeMap::new())?;
                self.channels.entry(topic.to_string()).or_insert((id, 0))
            }
        };
        *sequence += 1;
        writer.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: *channel_id,
                sequence: *sequence,
                log_time: stamps.publish_ns,
                publish_time: stamps.sensor_ns.unwrap_or(stamps.ingest_ns),
            },
            data,
        )?;
        if self.flushed.elapsed() >= FLUSH_EVERY {
            writer.flush()?;
            self.flushed = Instant::now();
        }
        Ok(())
    }

    fn close(&mut self, reason: String) {
        log::error!(
            "MCAP sink {}: {reason}; closed (any other output goes on; the run will fail at its end)",
            self.path
        );
        self.writer = None;
        self.failed = Some(reason);
    }
}

impl Sink for McapSink {
    fn publish(&mut self, output: &Output) -> Result<(), PublishError> {
        match output {
            Output::State(state) => {
                self.write(&state.stream, "state", STATE_SCHEMA, &state.stamps, state.as_ref())?;
                if let Some(event) = state.event_message() {
                    self.write(&state.stream, "events", EVENT_SCHEMA, &state.stamps, &event)?;
                }
                Ok(())
            }
            Output::Rejected(r) => self.write(&r.stream, "rejected", REJECTED_SCHEMA, &r.stamps, r),
        }
    }

    fn is_open(&self) -> bool {
        self.writer.is_some()
    }

    /// Writes the last chunk, the summary and the footer.
    fn flush(&mut self) -> Result<(), PublishError> {
        if let Some(mut writer) = self.writer.take() {
            if let Err(e) = writer.finish() {
                self.close(e.to_string());
            }
        }
        match self.failed.take() {
            Some(reason) => Err(PublishError::Sink {
                path: self.path.clone(),
                source: std::io::Error::other(reason),
            }),
            None => Ok(()),
        }
    }
}
