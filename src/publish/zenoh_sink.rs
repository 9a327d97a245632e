//! The zenoh sink: states, rejections and identity events as JSON or CBOR on the node's own keys,
//! `<prefix>/<node>/<stream>/state`, `.../rejected`, `.../event` (schema `gdvae.state/2`). A zenoh
//! publisher is declared per key on first use.

use std::collections::HashMap;

use zenoh::bytes::Encoding;
use zenoh::qos::CongestionControl;
use zenoh::{Session, Wait};

use serde::{Deserialize, Serialize};

use super::sink::{PublishError, Sink};
use crate::state::Output;
use crate::zenoh_session::NodeSettings;

/// How states are encoded on the node's own zenoh keys (`[publish] format`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Json,
    Cbor,
}

/// `message` in `format`.
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

pub struct ZenohSink {
    prefix: String,
    format: Format,
    session: Session,
    congestion: CongestionControl,
    publishers: HashMap<String, zenoh::pubsub::Publisher<'static>>,
}

impl ZenohSink {
    /// `lossless`: block on congestion (replay) instead of dropping (live).
    pub fn new(node: &NodeSettings, format: Format, session: Session, lossless: bool) -> Self {
        Self {
            prefix: format!("{}/{}", node.prefix, node.name),
            format,
            session,
            congestion: if lossless {
                CongestionControl::Block
            } else {
                CongestionControl::Drop
            },
            publishers: HashMap::new(),
        }
    }

    fn send<T: serde::Serialize>(&mut self, stream: &str, kind: &str, message: &T) -> Result<(), PublishError> {
        let key = format!("{}/{stream}/{kind}", self.prefix);
        if !self.publishers.contains_key(&key) {
            let encoding = match self.format {
                Format::Json => Encoding::APPLICATION_JSON,
                Format::Cbor => Encoding::APPLICATION_CBOR,
            };
            let publisher = self
                .session
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
}

impl Sink for ZenohSink {
    fn publish(&mut self, output: &Output) -> Result<(), PublishError> {
        match output {
            Output::State(state) => {
                self.send(&state.stream, "state", state.as_ref())?;
                if let Some(event) = state.event_message() {
                    self.send(&state.stream, "event", &event)?;
                }
                Ok(())
            }
            Output::Rejected(rejected) => self.send(&rejected.stream, "rejected", rejected),
        }
    }
}
