//! Publish: every published message goes to each configured sink. A sink is one way out of the
//! node: zenoh JSON/CBOR on the node's own keys (`zenoh.rs`), JSON lines (`jsonl.rs`), ROS 2 over
//! rmw_zenoh (`ros2.rs`). Adding one means a module here that implements [`Sink`], its settings
//! under `[publish]`, and a line in [`Publisher::new`].
//!
//! A sink never blocks the pipeline on a slow subscriber in live runs (zenoh congestion control:
//! drop); replay runs block instead, so nothing is lost. A sink that fails for good (a JSON-lines
//! file on a full disk) closes itself with one log line; the others go on, and the run fails at
//! its end.

mod jsonl;
pub mod ros2;
mod zenoh_sink;

use zenoh::{Session, Wait};

use serde::{Deserialize, Serialize};

use crate::bundle::Bundle;
use crate::config::Config;
use crate::state::Output;

pub use ros2::Ros2Settings;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Json,
    Cbor,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct PublishSettings {
    /// Publish states on zenoh (`<prefix>/<node>/<stream>/state`).
    pub zenoh: bool,
    pub format: Format,
    /// Also write one JSON line per state: a file path, or "-" for stdout.
    pub jsonl: Option<String>,
    /// The node as a ROS 2 node over rmw_zenoh (`[publish.ros2]`).
    pub ros2: Ros2Settings,
}

impl PublishSettings {
    /// Checks every sink's settings; the message names the key.
    pub fn validate(&self) -> Result<(), String> {
        if self.jsonl.as_deref() == Some("") {
            return Err("publish.jsonl must be a file path or \"-\" (stdout)".into());
        }
        self.ros2.validate()
    }
}

impl Default for PublishSettings {
    fn default() -> Self {
        Self {
            zenoh: true,
            format: Format::Json,
            jsonl: None,
            ros2: Ros2Settings::default(),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("JSON lines sink {path}: {source}")]
    Sink { path: String, source: std::io::Error },
    #[error("encoding a message: {0}")]
    Encode(String),
    #[error("ROS 2: {0}")]
    Ros2(String),
    #[error("every output has failed; the message is lost")]
    Closed,
}

/// One way out of the node.
pub trait Sink: Send {
    /// Sends one message (a state with its identity event, or a rejection).
    fn publish(&mut self, output: &Output) -> Result<(), PublishError>;
    /// Whether it still takes messages: a sink that failed for good closes itself.
    fn is_open(&self) -> bool {
        true
    }
    /// Flushes what it buffers; an error if it failed at any time during the run.
    fn flush(&mut self) -> Result<(), PublishError> {
        Ok(())
    }
}

/// Every configured sink, fed in turn.
pub struct Publisher {
    sinks: Vec<Box<dyn Sink>>,
}

impl Publisher {
    /// The sinks `[publish]` configures. `lossless`: block on congestion (replay) instead of
    /// dropping (live). `session`: the node's zenoh session, when one is open; `participants`: the
    /// node in ROS 2 domains (on that session).
    pub fn new(
        config: &Config,
        bundle: &Bundle,
        session: Option<Session>,
        participants: Option<&crate::ros2::Participants>,
        lossless: bool,
    ) -> Result<Self, PublishError> {
        let mut sinks: Vec<Box<dyn Sink>> = Vec::new();
        if let Some(path) = config.publish.jsonl.as_deref() {
            sinks.push(Box::new(jsonl::JsonLines::create(path)?));
        }
        if config.publish.zenoh {
            let session = session
                .clone()
                .ok_or_else(|| PublishError::Zenoh("no session".into()))?;
            sinks.push(Box::new(zenoh_sink::ZenohSink::new(config, session, lossless)));
        }
        if config.publish.ros2.enabled {
            let participants = participants.ok_or_else(|| PublishError::Ros2("no zenoh session".into()))?;
            sinks.push(Box::new(ros2::Ros2Sink::new(config, bundle, participants, lossless)?));
        }
        Ok(Self { sinks })
    }

    /// Sends `output` to every open sink: an error if one failed on it, or if none is left open.
    pub fn publish(&mut self, output: &Output) -> Result<(), PublishError> {
        let mut error = None;
        let mut taken = false;
        for sink in self.sinks.iter_mut().filter(|s| s.is_open()) {
            match sink.publish(output) {
                Ok(()) => taken |= sink.is_open(),
                Err(e) => {
                    error.get_or_insert(e);
                }
            }
        }
        match error {
            Some(e) => Err(e),
            None if taken || self.sinks.is_empty() => Ok(()),
            None => Err(PublishError::Closed),
        }
    }

    /// Flushes every sink; the first error of a sink that failed during the run.
    pub fn flush(&mut self) -> Result<(), PublishError> {
        let mut first = Ok(());
        for sink in &mut self.sinks {
            if let Err(e) = sink.flush() {
                if first.is_ok() {
                    first = Err(e);
                }
            }
        }
        first
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
        let publishes = config.publish.zenoh || config.publish.ros2.enabled;
        let session = session.filter(|_| publishes && !config.zenoh.connect.is_empty())?;
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
