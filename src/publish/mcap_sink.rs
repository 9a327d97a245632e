//! The MCAP sink (`[publish] mcap = FILE`, or `--record FILE` on `run` and `replay`): every
//! published message on its stream's channel (`/gdvae/<stream>/state`, `/events`, `/rejected`),
//! JSON-encoded under a JSON schema named after the message's schema (`gdvae.state/2`, ...), and
//! the view of each state (`view.rs`: `/transform`, `/input`, `/points`, `/shape`, `/scene`) in
//! Foxglove's protobuf schemas, the same channels the live view sends; so that a run opens
//! afterwards in Foxglove as it looked live, or in any MCAP reader, its fields ready to plot.
//!
//! Chunks are written whole: when one fills (256 KiB) and at least once a second, so a node
//! killed mid-run leaves a file readable up to its last complete chunk (the node's own recording
//! source reads such a file, as does any streaming MCAP reader); the summary and footer follow
//! when the run ends. A write error closes the sink with one log line; the others go on and the
//! run fails at its end.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::sync::Arc;
use std::time::{Duration, Instant};

use foxglove::Encode;

use super::shapes::ShapeWorker;
use super::sink::{PublishError, Sink};
use super::view::{self, ViewSettings};
use crate::state::{Output, Stamps, State, EVENT_SCHEMA, REJECTED_SCHEMA, STATE_SCHEMA};

/// The JSON schema of one of the node's messages, as the recording and the live view declare it.
pub fn json_schema(name: &str) -> Vec<u8> {
    format!(r#"{{"title":"{name}","type":"object"}}"#).into_bytes()
}

/// A chunk is written at the latest this long after the previous one.
const FLUSH_EVERY: Duration = Duration::from_secs(1);
const CHUNK_BYTES: u64 = 256 * 1024;

pub struct McapSink {
    writer: Option<mcap::Writer<BufWriter<File>>>,
    path: String,
    /// Schema ids by name.
    schemas: HashMap<String, u16>,
    /// Channel id and the next sequence number, by topic.
    channels: HashMap<String, (u16, u32)>,
    flushed: Instant,
    failed: Option<String>,
    view: ViewSettings,
    shapes: Option<Arc<ShapeWorker>>,
    metres_per_unit: f32,
    buffer: Vec<u8>,
}

/// How a new channel is declared: its schema (name, encoding, data; None: no schema) and its
/// messages' encoding. Made only when a topic's first message is written.
struct Declaration {
    schema: Option<(String, String, Cow<'static, [u8]>)>,
    message_encoding: &'static str,
}

impl McapSink {
    /// Creates the file; `view`, `shapes` and `model_units_per_metre` say how each state's view
    /// is drawn.
    pub fn create(
        path: &str,
        view: &ViewSettings,
        shapes: Option<Arc<ShapeWorker>>,
        model_units_per_metre: f64,
    ) -> Result<Self, PublishError> {
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
            view: view.clone(),
            shapes,
            metres_per_unit: 1.0 / model_units_per_metre as f32,
            buffer: Vec::new(),
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
        let topic = view::topic(stream, kind);
        let declare = || Declaration {
            schema: Some((schema.to_string(), "jsonschema".into(), json_schema(schema).into())),
            message_encoding: "json",
        };
        if let Err(e) = self.write_bytes(&topic, declare, stamps, &data) {
            self.close(e.to_string());
        }
        Ok(())
    }

    /// Writes one of the view's messages on `/gdvae/<stream>/<kind>` under Foxglove's schema.
    fn write_view<T: Encode>(&mut self, stream: &str, kind: &str, stamps: &Stamps, message: &T) {
        let mut buffer = std::mem::take(&mut self.buffer);
        buffer.clear();
        if let Err(e) = message.encode(&mut buffer) {
            log::warn!("MCAP sink {}: encoding {kind}: {e}", self.path);
            return;
        }
        let declare = || Declaration {
            schema: T::get_schema().map(|s| (s.name, s.encoding, s.data)),
            message_encoding: "protobuf",
        };
        if let Err(e) = self.write_bytes(&view::topic(stream, kind), declare, stamps, &buffer) {
            self.close(e.to_string());
        }
        self.buffer = buffer;
    }

    /// The view of `state`, as the Foxglove live view draws it.
    fn write_scene(&mut self, state: &State) {
        let shape = self.shapes.as_ref().and_then(|s| s.shape_for(state));
        let scene = view::scene(
            state,
            shape.as_deref().map(Vec::as_slice),
            &self.view.frame_id,
            self.metres_per_unit,
        );
        // The input cloud is the stream's; the rest its object's (with several objects,
        // `/gdvae/<stream>/<track>/...`).
        let (object, stamps) = (state.object_name(), &state.stamps);
        if let Some(input) = &scene.input {
            self.write_view(&state.stream, "input", stamps, input);
        }
        self.write_view(&object, "transform", stamps, &scene.transform);
        for (kind, cloud) in [("points", &scene.points), ("shape", &scene.shape)] {
            if let Some(cloud) = cloud {
                self.write_view(&object, kind, stamps, cloud);
            }
        }
        self.write_view(&object, "scene", stamps, &scene.scene);
    }

    fn write_bytes(
        &mut self,
        topic: &str,
        declare: impl FnOnce() -> Declaration,
        stamps: &Stamps,
        data: &[u8],
    ) -> mcap::McapResult<()> {
        let Some(writer) = self.writer.as_mut() else {
            return Ok(());
        };
        let (channel_id, sequence) = match self.channels.get_mut(topic) {
            Some(channel) => channel,
            None => {
                let declaration = declare();
                let schema_id = match declaration.schema {
                    None => 0,
                    Some((name, _, _)) if self.schemas.contains_key(&name) => self.schemas[&name],
                    Some((name, encoding, data)) => {
                        let id = writer.add_schema(&name, &encoding, &data)?;
                        self.schemas.insert(name, id);
                        id
                    }
                };
                let id = writer.add_channel(schema_id, topic, declaration.message_encoding, &BTreeMap::new())?;
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
                self.write_scene(state);
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
