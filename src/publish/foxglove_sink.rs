//! The Foxglove live view (`[publish.foxglove]`): a Foxglove WebSocket server (the Foxglove SDK's)
//! that the Foxglove app, or any client of its protocol, connects to. Per stream: the state as
//! JSON (`/gdvae/<stream>/state`, every field ready to plot) and the view of it (`view.rs`): the
//! object's frame (`/transform`), the input cloud (`/input`), the points the encoder saw
//! (`/points`), the decoded shape at the estimated pose (`/shape`) and the heading arrow with the
//! identity's label (`/scene`). Off by default.
//!
//! Nothing here costs the pipeline while no viewer subscribes; while one does, the publish thread
//! hands at most `max_rate_hz` states a second per stream (30: a viewer draws no faster, and a
//! replay runs far faster) to the view's own thread through a bounded queue, and a state that
//! does not fit is dropped from the view, counted and logged. The server then sends each viewer's
//! messages from its own queue (`backlog` messages): a viewer that cannot keep up loses the oldest
//! (the SDK logs "outbox for client ... full"), never the pipeline's time, and memory stays bounded.

use std::collections::HashMap;
use std::sync::Arc;

use foxglove::messages::{FrameTransform, PointCloud, SceneUpdate};
use serde::{Deserialize, Serialize};

use super::shapes::{Shape, ShapeWorker};
use super::sink::{PublishError, Sink};
use super::view::{self, ViewSettings};
use crate::state::{Output, State, STATE_SCHEMA};

/// States waiting for the view's thread; more are dropped from the view and counted.
const VIEW_QUEUE: usize = 64;

/// `[publish.foxglove]`.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct FoxgloveSettings {
    pub enabled: bool,
    /// Address the WebSocket server listens on ("127.0.0.1": this machine only).
    pub bind: String,
    /// Port (Foxglove's default 8765; 0: any free port, logged).
    pub port: u16,
    /// Messages queued per viewer before the oldest are dropped.
    pub backlog: usize,
    /// At most this many states a second per stream go to the view (a viewer draws no faster; a
    /// replay runs far faster); 0: every state.
    pub max_rate_hz: f64,
}

impl Default for FoxgloveSettings {
    fn default() -> Self {
        Self {
            enabled: false,
            bind: "127.0.0.1".into(),
            port: 8765,
            backlog: 256,
            max_rate_hz: 30.0,
        }
    }
}

impl FoxgloveSettings {
    pub fn validate(&self) -> Result<(), String> {
        if self.enabled && (self.bind.is_empty() || self.backlog == 0) {
            return Err("publish.foxglove: bind must be set and backlog at least 1".into());
        }
        if !(self.max_rate_hz >= 0.0 && self.max_rate_hz.is_finite()) {
            return Err("publish.foxglove.max_rate_hz must be finite and >= 0".into());
        }
        Ok(())
    }
}

struct StreamChannels {
    state: Arc<foxglove::RawChannel>,
    transform: foxglove::Channel<FrameTransform>,
    input: foxglove::Channel<PointCloud>,
    points: foxglove::Channel<PointCloud>,
    shape: foxglove::Channel<PointCloud>,
    scene: foxglove::Channel<SceneUpdate>,
}

impl StreamChannels {
    fn declare(context: &Arc<foxglove::Context>, stream: &str) -> Result<Self, PublishError> {
        let topic = |what: &str| view::topic(stream, what);
        let schema = foxglove::Schema::new(STATE_SCHEMA, "jsonschema", super::mcap_sink::json_schema(STATE_SCHEMA));
        let state = context
            .channel_builder(topic("state"))
            .message_encoding("json")
            .schema(schema)
            .build_raw()
            .map_err(|e| PublishError::Foxglove(e.to_string()))?;
        Ok(Self {
            state,
            transform: context.channel_builder(topic("transform")).build(),
            input: context.channel_builder(topic("input")).build(),
            points: context.channel_builder(topic("points")).build(),
            shape: context.channel_builder(topic("shape")).build(),
            scene: context.channel_builder(topic("scene")).build(),
        })
    }

    /// Whether any viewer subscribes to any of them.
    fn watched(&self) -> bool {
        self.state.has_sinks()
            || self.transform.has_sinks()
            || self.input.has_sinks()
            || self.points.has_sinks()
            || self.shape.has_sinks()
            || self.scene.has_sinks()
    }
}

type Channels = Arc<HashMap<String, StreamChannels>>;

pub struct FoxgloveSink {
    context: Arc<foxglove::Context>,
    server: Option<foxglove::WebSocketServerHandle>,
    /// Every configured stream's channels; a stream that appears later gets its own on the way.
    channels: Channels,
    queue: Option<crossbeam_channel::Sender<(State, Option<Shape>)>>,
    thread: Option<std::thread::JoinHandle<()>>,
    view: ViewSettings,
    shapes: Option<Arc<ShapeWorker>>,
    metres_per_unit: f32,
    /// The shortest time between two states of a stream sent to the view (from `max_rate_hz`).
    min_interval: std::time::Duration,
    /// When each stream's last state went to the view.
    last_sent: HashMap<String, std::time::Instant>,
    dropped: u64,
}

impl FoxgloveSink {
    /// Starts the server and the view's thread; channels are declared for every configured stream.
    pub fn start(
        settings: &FoxgloveSettings,
        view: &ViewSettings,
        streams: &[String],
        shapes: Option<Arc<ShapeWorker>>,
        model_units_per_metre: f64,
    ) -> Result<Self, PublishError> {
        let context = foxglove::Context::new();
        let server = foxglove::WebSocketServer::new()
            .name("gdvae-node")
            .bind(settings.bind.clone(), settings.port)
            .message_backlog_size(settings.backlog)
            .context(&context)
            .start_blocking()
            .map_err(|e| PublishError::Foxglove(format!("{}:{}: {e}", settings.bind, settings.port)))?;
        log::info!(
            "Foxglove: live view on ws://{}:{} (open it in the Foxglove app: Open connection, Foxglove WebSocket)",
            settings.bind,
            server.port()
        );
        let mut sink = Self {
            context,
            server: Some(server),
            channels: Arc::default(),
            queue: None,
            thread: None,
            view: view.clone(),
            shapes,
            metres_per_unit: 1.0 / model_units_per_metre as f32,
            // Three quarters of the period: a sensor at exactly max_rate_hz, with its jitter, keeps
            // every frame.
            min_interval: if settings.max_rate_hz > 0.0 {
                std::time::Duration::from_secs_f64(0.75 / settings.max_rate_hz)
            } else {
                std::time::Duration::ZERO
            },
            last_sent: HashMap::new(),
            dropped: 0,
        };
        sink.declare(streams)?;
        Ok(sink)
    }

    /// (Re)starts the view's thread over `streams`' channels and those already declared.
    fn declare(&mut self, streams: &[String]) -> Result<(), PublishError> {
        self.stop_thread();
        let mut channels = HashMap::new();
        for (stream, declared) in Arc::try_unwrap(std::mem::take(&mut self.channels)).unwrap_or_default() {
            channels.insert(stream, declared);
        }
        for stream in streams {
            if !channels.contains_key(stream) {
                channels.insert(stream.clone(), StreamChannels::declare(&self.context, stream)?);
            }
        }
        self.channels = Arc::new(channels);
        let (queue, states) = crossbeam_channel::bounded::<(State, Option<Shape>)>(VIEW_QUEUE);
        let (channels, frame_id, metres_per_unit) =
            (self.channels.clone(), self.view.frame_id.clone(), self.metres_per_unit);
        self.thread = Some(
            std::thread::Builder::new()
                .name("publish:foxglove".into())
                .spawn(move || {
                    for (state, shape) in states {
                        // The input cloud on the stream's channel, the rest on the object's.
                        let object = channels.get(state.object_name().as_ref());
                        if let (Some(object), Some(stream)) = (object, channels.get(&state.stream)) {
                            send(
                                object,
                                stream,
                                &state,
                                shape.as_deref().map(Vec::as_slice),
                                &frame_id,
                                metres_per_unit,
                            );
                        }
                    }
                })
                .map_err(|e| PublishError::Foxglove(e.to_string()))?,
        );
        self.queue = Some(queue);
        Ok(())
    }

    fn stop_thread(&mut self) {
        self.queue = None;
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }

    /// Hands `state` to the view's thread, on its object's channels (its stream's, or with several
    /// objects `/gdvae/<stream>/<track>/...`, declared when the track first shows).
    fn publish_state(&mut self, state: &State) -> Result<(), PublishError> {
        let object = state.object_name();
        let missing: Vec<String> = [object.as_ref(), state.stream.as_str()]
            .into_iter()
            .filter(|name| !self.channels.contains_key(*name))
            .map(str::to_string)
            .collect();
        if !missing.is_empty() {
            self.declare(&missing)?;
        }
        if !(self.channels[object.as_ref()].watched() || self.channels[&state.stream].input.has_sinks()) {
            return Ok(());
        }
        let now = std::time::Instant::now();
        if let Some(last) = self.last_sent.get(object.as_ref()) {
            if now.duration_since(*last) < self.min_interval {
                return Ok(());
            }
        }
        self.last_sent.insert(object.to_string(), now);
        let shape = self.shapes.as_ref().and_then(|s| s.shape_for(state));
        let queue = self
            .queue
            .as_ref()
            .expect("the view's thread runs while the sink is open");
        if queue.try_send((state.clone(), shape)).is_err() {
            self.dropped += 1;
            if self.dropped == 1 || self.dropped % 1000 == 0 {
                log::warn!(
                    "Foxglove view: {} state(s) not shown so far (the view's thread could not keep up)",
                    self.dropped
                );
            }
        }
        Ok(())
    }
}

/// One state's messages on the channels a viewer subscribes to.
fn send(
    channels: &StreamChannels,
    stream_channels: &StreamChannels,
    state: &State,
    shape: Option<&[[f32; 3]]>,
    frame_id: &str,
    metres_per_unit: f32,
) {
    let log_time = state.stamps.publish_ns;
    if channels.state.has_sinks() {
        match serde_json::to_vec(state) {
            Ok(json) => channels.state.log_with_meta(
                &json,
                foxglove::PartialMetadata {
                    log_time: Some(log_time),
                },
            ),
            Err(e) => log::warn!("Foxglove view: encoding a state: {e}"),
        }
    }
    let scene = view::scene(state, shape, frame_id, metres_per_unit);
    channels.transform.log_with_time(&scene.transform, log_time);
    channels.scene.log_with_time(&scene.scene, log_time);
    for (channel, cloud) in [
        (&stream_channels.input, &scene.input),
        (&channels.points, &scene.points),
        (&channels.shape, &scene.shape),
    ] {
        if let Some(cloud) = cloud {
            channel.log_with_time(cloud, log_time);
        }
    }
}

impl Sink for FoxgloveSink {
    fn publish(&mut self, output: &Output) -> Result<(), PublishError> {
        match output {
            Output::State(state) => self.publish_state(state),
            Output::Rejected(_) => Ok(()),
        }
    }

    fn flush(&mut self) -> Result<(), PublishError> {
        self.stop_thread();
        if self.dropped > 0 {
            log::warn!(
                "Foxglove view: {} state(s) were not shown (the view's thread could not keep up)",
                self.dropped
            );
        }
        if let Some(server) = self.server.take() {
            // Waits for the server's tasks to end, so that the port is free when the run returns.
            server.stop().wait_blocking();
        }
        Ok(())
    }
}
