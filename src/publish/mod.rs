//! Publish: every published message goes to each configured sink. A sink is one way out of the
//! node: zenoh JSON/CBOR on the node's own keys (`zenoh.rs`), JSON lines (`jsonl.rs`), an MCAP
//! recording (`mcap_sink.rs`), the Foxglove live view (`foxglove_sink.rs`), ROS 2 over rmw_zenoh
//! (`ros2.rs`). Adding one means a module here that implements [`Sink`], its settings
//! under `[publish]`, and a line in [`Publisher::new`].
//!
//! A sink never blocks the pipeline on a slow subscriber in live runs (zenoh congestion control:
//! drop); replay runs block instead, so nothing is lost. A sink that fails for good (a JSON-lines
//! file on a full disk) closes itself with one log line; the others go on, and the run fails at
//! its end.

mod foxglove_sink;
mod jsonl;
mod mcap_sink;
pub mod ros2;
mod shapes;
mod sink;
mod view;
mod zenoh_sink;

use std::sync::Arc;

use zenoh::Session;

use serde::{Deserialize, Serialize};

use crate::bundle::Bundle;
use crate::state::Output;

use crate::zenoh_session::NodeSettings;
pub use sink::{PublishError, Sink};
pub use zenoh_sink::{encode, Format};

pub use foxglove_sink::FoxgloveSettings;
pub use ros2::Ros2Settings;
pub use view::ViewSettings;

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct PublishSettings {
    /// Publish states on zenoh (`<prefix>/<node>/<stream>/state`).
    pub zenoh: bool,
    pub format: Format,
    /// Also write one JSON line per state: a file path, or "-" for stdout.
    pub jsonl: Option<String>,
    /// Also record every published message to this MCAP file (a channel per stream and kind).
    pub mcap: Option<String>,
    /// The node as a ROS 2 node over rmw_zenoh (`[publish.ros2]`).
    pub ros2: Ros2Settings,
    /// A Foxglove WebSocket server for a live view (`[publish.foxglove]`).
    pub foxglove: FoxgloveSettings,
    /// What the live view and the MCAP recording show of each state (`[publish.view]`).
    pub view: ViewSettings,
}

impl PublishSettings {
    /// Checks every sink's settings; the message names the key.
    pub fn validate(&self) -> Result<(), String> {
        if self.jsonl.as_deref() == Some("") {
            return Err("publish.jsonl must be a file path or \"-\" (stdout)".into());
        }
        if self.mcap.as_deref().is_some_and(|p| p.is_empty() || p == "-") {
            return Err("publish.mcap must be a file path".into());
        }
        self.foxglove.validate()?;
        self.view.validate()?;
        self.ros2.validate()
    }

    /// Whether a sink shows the view (the Foxglove live view or the MCAP recording).
    fn shows_view(&self) -> bool {
        self.foxglove.enabled || self.mcap.is_some()
    }

    /// How many points of each input cloud the sinks show (0: none, or no sink shows them).
    pub fn input_points(&self) -> usize {
        if self.shows_view() {
            self.view.input_points
        } else {
            0
        }
    }

    /// How often the sinks that draw the decoded shape want it renewed (0: none does).
    fn shape_rate_hz(&self) -> f64 {
        let view = if self.shows_view() {
            self.view.shape_rate_hz
        } else {
            0.0
        };
        let ros2 = if self.ros2.enabled && self.ros2.markers {
            self.ros2.shape_rate_hz
        } else {
            0.0
        };
        view.max(ros2)
    }
}

impl Default for PublishSettings {
    fn default() -> Self {
        Self {
            zenoh: true,
            format: Format::Json,
            jsonl: None,
            mcap: None,
            ros2: Ros2Settings::default(),
            foxglove: FoxgloveSettings::default(),
            view: ViewSettings::default(),
        }
    }
}

/// Every configured sink, fed in turn.
pub struct Publisher {
    sinks: Vec<Box<dyn Sink>>,
}

impl Publisher {
    /// The sinks `settings` (`[publish]`) configures, on the keys `node` names. `lossless`: block
    /// on congestion (replay) instead of dropping (live). `session`: the node's zenoh session, when
    /// one is open; `participants`: the node in ROS 2 domains (on that session); `onnxruntime`: the
    /// library the ROS 2 sink's shape decoder loads (`[model] onnxruntime`); `streams`: the
    /// configured streams, whose ROS 2 topics are declared at once (before their first frame);
    /// `sensor_poses`: each stream's sensor -> gravity pose where the configuration fixes it (the
    /// ROS 2 sink's /tf_static).
    pub fn new(
        settings: &PublishSettings,
        streams: &[String],
        node: &NodeSettings,
        onnxruntime: Option<&std::path::Path>,
        bundle: &Bundle,
        session: Option<Session>,
        participants: Option<&crate::ros2::Participants>,
        sensor_poses: &std::collections::HashMap<String, ([[f32; 3]; 3], [f32; 3])>,
        lossless: bool,
    ) -> Result<Self, PublishError> {
        let mut sinks: Vec<Box<dyn Sink>> = Vec::new();
        let units = bundle.manifest.units.model_units_per_metre;
        // One decoder for every sink that draws the decoded shape.
        let rate = settings.shape_rate_hz();
        let shapes = if rate > 0.0 {
            Some(Arc::new(shapes::ShapeWorker::start(bundle, onnxruntime, rate)?))
        } else {
            None
        };
        let view_shapes = shapes.clone().filter(|_| settings.view.shape_rate_hz > 0.0);
        if let Some(path) = settings.jsonl.as_deref() {
            sinks.push(Box::new(jsonl::JsonLines::create(path)?));
        }
        if let Some(path) = settings.mcap.as_deref() {
            sinks.push(Box::new(mcap_sink::McapSink::create(
                path,
                &settings.view,
                view_shapes.clone(),
                units,
            )?));
        }
        if settings.zenoh {
            let session = session
                .clone()
                .ok_or_else(|| PublishError::Zenoh("no session".into()))?;
            sinks.push(Box::new(zenoh_sink::ZenohSink::new(
                node,
                settings.format,
                session,
                lossless,
            )));
        }
        if settings.foxglove.enabled {
            sinks.push(Box::new(foxglove_sink::FoxgloveSink::start(
                &settings.foxglove,
                &settings.view,
                streams,
                view_shapes,
                units,
            )?));
        }
        if settings.ros2.enabled {
            let participants = participants.ok_or_else(|| PublishError::Ros2("no zenoh session".into()))?;
            sinks.push(Box::new(ros2::Ros2Sink::new(
                &settings.ros2,
                streams,
                shapes,
                sensor_poses,
                units,
                participants,
                lossless,
            )?));
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
