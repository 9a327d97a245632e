//! Publish: states, rejections and identity events to zenoh (JSON or CBOR) and/or JSON lines.
//!
//! Key expressions: `<prefix>/<node>/<stream>/state`, `.../rejected`, `.../event`. A zenoh
//! publisher is declared per key on first use. Publishing never blocks the pipeline on a slow
//! subscriber (congestion control: drop), except in replay runs, where nothing may be lost.

use std::collections::HashMap;
use std::io::Write;

use zenoh::bytes::Encoding;
use zenoh::qos::CongestionControl;
use zenoh::{Session, Wait};

use crate::config::{Config, Format};
use crate::state::{Event, Output, EVENT_SCHEMA};

#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("JSON lines sink {path}: {source}")]
    Sink { path: String, source: std::io::Error },
    #[error("encoding a message: {0}")]
    Encode(String),
}

pub struct Publisher {
    prefix: String,
    format: Format,
    session: Option<Session>,
    congestion: CongestionControl,
    publishers: HashMap<String, zenoh::pubsub::Publisher<'static>>,
    jsonl: Option<Box<dyn Write + Send>>,
    jsonl_path: String,
    /// Set when the JSON-lines sink failed: it is closed, the other outputs go on, and the run
    /// reports the failure at the end (`flush`).
    jsonl_failed: Option<std::io::Error>,
}

impl Publisher {
    /// `lossless`: block on congestion (replay) instead of dropping (live).
    pub fn new(config: &Config, session: Option<Session>, lossless: bool) -> Result<Self, PublishError> {
        let jsonl: Option<Box<dyn Write + Send>> = match config.publish.jsonl.as_deref() {
            None => None,
            Some("-") => Some(Box::new(std::io::LineWriter::new(std::io::stdout()))),
            Some(path) => {
                let file = std::fs::File::create(path).map_err(|source| PublishError::Sink {
                    path: path.to_string(),
                    source,
                })?;
                // Line by line, so that whoever tails the file sees each state when it is published.
                Some(Box::new(std::io::LineWriter::new(file)))
            }
        };
        Ok(Self {
            prefix: format!("{}/{}", config.node.prefix, config.node.name),
            format: config.publish.format,
            session: if config.publish.zenoh { session } else { None },
            congestion: if lossless {
                CongestionControl::Block
            } else {
                CongestionControl::Drop
            },
            publishers: HashMap::new(),
            jsonl,
            jsonl_path: config.publish.jsonl.clone().unwrap_or_default(),
            jsonl_failed: None,
        })
    }

    pub fn publish(&mut self, output: &Output) -> Result<(), PublishError> {
        match output {
            Output::State(state) => {
                self.send(&state.stream, "state", state.as_ref())?;
                if let Some(event) = &state.event {
                    let event = Event {
                        schema: EVENT_SCHEMA.into(),
                        node: state.node.clone(),
                        stream: state.stream.clone(),
                        sequence: state.sequence,
                        stamps: state.stamps.clone(),
                        event: event.clone(),
                    };
                    self.send(&state.stream, "event", &event)?;
                }
            }
            Output::Rejected(rejected) => self.send(&rejected.stream, "rejected", rejected)?,
        }
        Ok(())
    }

    fn send<T: serde::Serialize>(&mut self, stream: &str, kind: &str, message: &T) -> Result<(), PublishError> {
        if let Some(sink) = self.jsonl.as_mut() {
            let line = serde_json::to_string(message).map_err(|e| PublishError::Encode(e.to_string()))?;
            if let Err(source) = writeln!(sink, "{line}") {
                self.close_jsonl(source);
            }
        }
        let Some(session) = &self.session else {
            // With no other output, a message the failed sink could not take is lost: say so.
            return match &self.jsonl_failed {
                Some(e) => Err(PublishError::Sink {
                    path: self.jsonl_path.clone(),
                    source: std::io::Error::new(e.kind(), e.to_string()),
                }),
                None => Ok(()),
            };
        };
        let key = format!("{}/{stream}/{kind}", self.prefix);
        if !self.publishers.contains_key(&key) {
            let encoding = match self.format {
                Format::Json => Encoding::APPLICATION_JSON,
                Format::Cbor => Encoding::APPLICATION_CBOR,
            };
            let publisher = session
                .declare_publisher(key.clone())
                .encoding(encoding)
                .congestion_control(self.congestion)
                .wait()
                .map_err(|e| PublishError::Zenoh(e.to_string()))?;
            self.publishers.insert(key.clone(), publisher);
        }
        let payload = encode(self.format, message)?;
        self.publishers[&key]
            .put(payload)
            .wait()
            .map_err(|e| PublishError::Zenoh(e.to_string()))
    }

    /// Closes a failed JSON-lines sink, once, with one error in the log.
    fn close_jsonl(&mut self, source: std::io::Error) {
        log::error!(
            "JSON lines sink {}: {source}; closed, {}",
            self.jsonl_path,
            if self.session.is_some() {
                "zenoh publishing goes on"
            } else {
                "nothing else publishes: the run will fail"
            }
        );
        self.jsonl = None;
        self.jsonl_failed = Some(source);
    }

    /// Flushes the JSON-lines sink; an error if it failed at any time during the run.
    pub fn flush(&mut self) -> Result<(), PublishError> {
        if let Some(sink) = self.jsonl.as_mut() {
            if let Err(source) = sink.flush() {
                self.close_jsonl(source);
            }
        }
        match self.jsonl_failed.take() {
            Some(source) => Err(PublishError::Sink {
                path: self.jsonl_path.clone(),
                source,
            }),
            None => Ok(()),
        }
    }
}

pub fn encode<T: serde::Serialize>(format: Format, message: &T) -> Result<Vec<u8>, PublishError> {
    match format {
        Format::Json => serde_json::to_vec(message).map_err(|e| PublishError::Encode(e.to_string())),
        Format::Cbor => {
            let mut bytes = Vec::new();
            ciborium::into_writer(message, &mut bytes).map_err(|e| PublishError::Encode(e.to_string()))?;
            Ok(bytes)
        }
    }
}

/// A zenoh session as configured: an embedded peer by default, or a client of routers.
pub fn open_session(config: &Config) -> Result<Session, PublishError> {
    let z = &config.zenoh;
    let mut zc = zenoh::Config::default();
    let json = |v: &Vec<String>| serde_json::to_string(v).expect("strings serialize");
    let set = |zc: &mut zenoh::Config, key: &str, value: &str| {
        zc.insert_json5(key, value)
            .map_err(|e| PublishError::Zenoh(format!("zenoh setting {key} = {value}: {e}")))
    };
    set(&mut zc, "mode", &format!("\"{}\"", z.mode))?;
    if !z.listen.is_empty() {
        set(&mut zc, "listen/endpoints", &json(&z.listen))?;
    }
    if !z.connect.is_empty() {
        set(&mut zc, "connect/endpoints", &json(&z.connect))?;
    }
    set(
        &mut zc,
        "scouting/multicast/enabled",
        if z.multicast_scouting { "true" } else { "false" },
    )?;
    zenoh::open(zc)
        .wait()
        .map_err(|e| PublishError::Zenoh(format!("opening a session: {e}")))
}

/// Watches whether the node is connected to anything it was told to connect to (`[zenoh]
/// connect`): a router outage is otherwise invisible, as zenoh accepts puts with nobody to send
/// them to. Checked at most twice a second; each change is logged once.
pub struct ConnectionWatch {
    session: Session,
    connected: bool,
    checked: std::time::Instant,
    lost_at: Option<std::time::Instant>,
}

impl ConnectionWatch {
    /// A watch when zenoh publishes and `connect` names endpoints; None otherwise (an embedded
    /// peer with nobody configured to connect to has no outage to report).
    pub fn new(config: &Config, session: Option<&Session>) -> Option<Self> {
        let session = session.filter(|_| config.publish.zenoh && !config.zenoh.connect.is_empty())?;
        let mut watch = Self {
            session: session.clone(),
            connected: true,
            checked: std::time::Instant::now() - std::time::Duration::from_secs(1),
            lost_at: None,
        };
        watch.connected();
        Some(watch)
    }

    /// Whether a router or peer is connected now (cached for 500 ms).
    pub fn connected(&mut self) -> bool {
        if self.checked.elapsed() < std::time::Duration::from_millis(500) {
            return self.connected;
        }
        self.checked = std::time::Instant::now();
        let info = self.session.info();
        let now = info.routers_zid().wait().next().is_some() || info.peers_zid().wait().next().is_some();
        match (self.connected, now) {
            (true, false) => {
                log::warn!("zenoh: no router or peer connected; states published now reach nobody there");
                self.lost_at = Some(std::time::Instant::now());
            }
            (false, true) => log::info!(
                "zenoh: connected again after {:.1} s; publishing reaches subscribers",
                self.lost_at.map(|t| t.elapsed().as_secs_f64()).unwrap_or(0.0)
            ),
            _ => {}
        }
        self.connected = now;
        now
    }
}
