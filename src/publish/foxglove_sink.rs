//! The Foxglove live view (`[publish.foxglove]`): a Foxglove WebSocket server (the Foxglove SDK's)
//! that the Foxglove app, or any client of its protocol, connects to. Per stream: the state as
//! JSON (`/gdvae/<stream>/state`, every field ready to plot), the object's frame in the gravity
//! frame (`/gdvae/<stream>/transform`: at the estimated centre, turned by the filtered heading), the
//! N_p points the encoder saw (`/gdvae/<stream>/points`, in metres in the gravity frame) and a scene
//! (`/gdvae/<stream>/scene`: a heading arrow and a label with the identity and its confidence). Off by default. The server sends each client's messages from its own queue
//! (`backlog` messages); a viewer that cannot keep up loses the oldest, never the pipeline's time.

use std::collections::HashMap;
use std::sync::Arc;

use foxglove::messages::packed_element_field::NumericType;
use foxglove::messages::{
    ArrowPrimitive, Color, FrameTransform, PackedElementField, PointCloud, Pose, Quaternion, SceneEntity, SceneUpdate,
    TextPrimitive, Timestamp, Vector3,
};
use serde::{Deserialize, Serialize};

use super::sink::{PublishError, Sink};
use crate::state::{Output, State, STATE_SCHEMA};

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
    /// The gravity frame's name (the parent of each stream's object frame).
    pub frame_id: String,
}

impl Default for FoxgloveSettings {
    fn default() -> Self {
        Self {
            enabled: false,
            bind: "127.0.0.1".into(),
            port: 8765,
            backlog: 256,
            frame_id: "gravity".into(),
        }
    }
}

impl FoxgloveSettings {
    pub fn validate(&self) -> Result<(), String> {
        if self.enabled && (self.bind.is_empty() || self.backlog == 0 || self.frame_id.is_empty()) {
            return Err("publish.foxglove: bind and frame_id must be set and backlog at least 1".into());
        }
        Ok(())
    }
}

struct StreamChannels {
    state: Arc<foxglove::RawChannel>,
    transform: foxglove::Channel<FrameTransform>,
    points: foxglove::Channel<PointCloud>,
    scene: foxglove::Channel<SceneUpdate>,
}

pub struct FoxgloveSink {
    settings: FoxgloveSettings,
    context: Arc<foxglove::Context>,
    server: Option<foxglove::WebSocketServerHandle>,
    streams: HashMap<String, StreamChannels>,
    /// The bundle's model units per metre: the prepared points back to metres.
    model_units_per_metre: f32,
}

impl FoxgloveSink {
    /// Starts the server; its channels are declared for every configured stream at once.
    pub fn start(
        settings: &FoxgloveSettings,
        streams: &[String],
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
            settings: settings.clone(),
            context,
            server: Some(server),
            streams: HashMap::new(),
            model_units_per_metre: model_units_per_metre as f32,
        };
        for stream in streams {
            sink.channels(stream)?;
        }
        Ok(sink)
    }

    fn channels(&mut self, stream: &str) -> Result<&StreamChannels, PublishError> {
        if !self.streams.contains_key(stream) {
            let topic = |what: &str| format!("/gdvae/{stream}/{what}");
            let schema = foxglove::Schema::new(
                STATE_SCHEMA,
                "jsonschema",
                format!(r#"{{"title":"{STATE_SCHEMA}","type":"object"}}"#).into_bytes(),
            );
            let state = self
                .context
                .channel_builder(topic("state"))
                .message_encoding("json")
                .schema(schema)
                .build_raw()
                .map_err(|e| PublishError::Foxglove(e.to_string()))?;
            let channels = StreamChannels {
                state,
                transform: self.context.channel_builder(topic("transform")).build(),
                points: self.context.channel_builder(topic("points")).build(),
                scene: self.context.channel_builder(topic("scene")).build(),
            };
            self.streams.insert(stream.to_string(), channels);
        }
        Ok(&self.streams[stream])
    }

    fn publish_state(&mut self, state: &State) -> Result<(), PublishError> {
        let json = serde_json::to_vec(state).map_err(|e| PublishError::Encode(e.to_string()))?;
        let parent = self.settings.frame_id.clone();
        let metres_per_unit = 1.0 / self.model_units_per_metre;
        let channels = self.channels(&state.stream)?;
        let stamp = state.stamps.sensor_ns.unwrap_or(state.stamps.ingest_ns);
        let timestamp = Some(Timestamp::new(
            (stamp / 1_000_000_000) as u32,
            (stamp % 1_000_000_000) as u32,
        ));
        channels.state.log_with_meta(
            &json,
            foxglove::PartialMetadata {
                log_time: Some(state.stamps.publish_ns),
            },
        );
        if let Some(points) = &state.prepared {
            let c = state.centre_m;
            let data: Vec<u8> = points
                .iter()
                .flat_map(|p| (0..3).flat_map(move |a| (p[a] * metres_per_unit + c[a]).to_le_bytes()))
                .collect();
            let field = |name: &str, offset: u32| PackedElementField {
                name: name.into(),
                offset,
                r#type: NumericType::Float32 as i32,
            };
            channels.points.log_with_time(
                &PointCloud {
                    timestamp,
                    frame_id: parent.clone(),
                    pose: None,
                    point_stride: 12,
                    fields: vec![field("x", 0), field("y", 4), field("z", 8)],
                    data: data.into(),
                },
                state.stamps.publish_ns,
            );
        }
        let frame = format!("gdvae/{}", state.stream);
        let half = 0.5 * state.filtered.yaw as f64;
        let c = state.centre_m;
        channels.transform.log_with_time(
            &FrameTransform {
                timestamp,
                parent_frame_id: parent,
                child_frame_id: frame.clone(),
                translation: Some(Vector3 {
                    x: c[0] as f64,
                    y: c[1] as f64,
                    z: c[2] as f64,
                }),
                rotation: Some(Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: half.sin(),
                    w: half.cos(),
                }),
            },
            state.stamps.publish_ns,
        );
        let at = |x: f64, z: f64| {
            Some(Pose {
                position: Some(Vector3 { x, y: 0.0, z }),
                orientation: Some(Quaternion {
                    x: 0.0,
                    y: 0.0,
                    z: 0.0,
                    w: 1.0,
                }),
            })
        };
        let colour = if state.shape.inlier {
            Color {
                r: 0.1,
                g: 0.8,
                b: 0.3,
                a: 1.0,
            }
        } else {
            Color {
                r: 0.9,
                g: 0.5,
                b: 0.1,
                a: 1.0,
            }
        };
        channels.scene.log_with_time(
            &SceneUpdate {
                deletions: vec![],
                entities: vec![SceneEntity {
                    timestamp,
                    frame_id: frame,
                    id: state.stream.clone(),
                    frame_locked: true,
                    arrows: vec![ArrowPrimitive {
                        pose: at(0.0, 0.0),
                        shaft_length: 0.4,
                        shaft_diameter: 0.03,
                        head_length: 0.12,
                        head_diameter: 0.08,
                        color: Some(colour),
                    }],
                    texts: vec![TextPrimitive {
                        pose: at(0.0, 0.5),
                        billboard: true,
                        font_size: 14.0,
                        scale_invariant: true,
                        color: Some(colour),
                        text: format!(
                            "{} identity {} ({}conf {:.2})",
                            state.stream,
                            state.shape.identity,
                            if state.shape.inlier { "" } else { "outlier, " },
                            state.shape.confidence
                        ),
                    }],
                    ..Default::default()
                }],
            },
            state.stamps.publish_ns,
        );
        Ok(())
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
        if let Some(server) = self.server.take() {
            // Waits for the server's tasks to end, so that the port is free when the run returns.
            server.stop().wait_blocking();
        }
        Ok(())
    }
}
