//! The ROS 2 sink: the node as a ROS 2 node over rmw_zenoh, so that `ros2 node list`,
//! `ros2 topic echo` and rviz2 see it without a bridge. Per stream, under the node's namespace:
//!
//! | topic | type | what |
//! |---|---|---|
//! | `<ns>/<stream>/pose` | geometry_msgs/msg/PoseStamped | the object's centre and filtered rotation in the gravity frame |
//! | `/tf` | tf2_msgs/msg/TFMessage | gravity frame -> `<object_frame_prefix><stream>` |
//! | `<ns>/<stream>/markers` | visualization_msgs/msg/MarkerArray | identity text, heading arrow, decoded canonical shape |
//! | `<ns>/<stream>/detections` | vision_msgs/msg/Detection3DArray | the object: id (identity), score, pose, box |
//! | `/tf_static` | tf2_msgs/msg/TFMessage | gravity frame -> each stream's sensor frame (transient local) |
//! | `<ns>/<stream>/z_e`, `.../z_i` | std_msgs/msg/Float32MultiArray | filtered pose code, fused shape code |
//! | `<ns>/<stream>/state`, `.../events`, `.../rejected` | std_msgs/msg/String | the `gdvae.state/2` JSON, identity events, rejections |
//!
//! Every publisher has its liveliness token (and the node its own), data go on the exact key a ROS 2
//! subscriber of the type uses, each sample with rmw_zenoh's attachment; tokens are withdrawn when
//! the sink is dropped (shutdown). The decoded shape comes from the bundle's `decoder.onnx` on a
//! thread of its own (`shapes.rs`), at most `shape_rate_hz` per stream: never on the pipeline's hot
//! path, so a stream's first MarkerArray (sent before its first shape is decoded) has no shape
//! marker, and every later one has the latest shape.

use std::collections::HashMap;
use std::sync::Arc;

use zenoh::qos::CongestionControl;
use zenoh::Wait;

use super::shapes::ShapeWorker;
use super::sink::{PublishError, Sink};
use crate::ros2::graph::{self, EntityKind, MessageType, Qos};
use crate::ros2::msg::{self, Header, Marker, Pose};
pub use crate::ros2::Ros2Settings;
use crate::ros2::{Participant, Participants};
use crate::state::{Output, State};

/// One ROS 2 publisher: its zenoh publisher, liveliness token, GID and sequence numbers.
struct Topic {
    publisher: zenoh::pubsub::Publisher<'static>,
    _token: zenoh::liveliness::LivelinessToken,
    gid: [u8; 16],
    sequence: i64,
}

impl Topic {
    fn put(&mut self, payload: Vec<u8>) -> Result<(), PublishError> {
        self.sequence += 1;
        let now = crate::sources::unix_now_ns() as i64;
        self.publisher
            .put(payload)
            .attachment(graph::attachment(self.sequence, now, &self.gid).to_vec())
            .wait()
            .map_err(|e| PublishError::Ros2(e.to_string()))
    }
}

/// `/tf_static`: declared as rmw_zenoh declares a reliable TRANSIENT_LOCAL publisher (an
/// AdvancedPublisher with a cache of one sample, sample-miss detection on a sporadic 500 ms
/// heartbeat, publisher detection), so that a TF listener that starts later (rviz2, tf2_echo)
/// still receives the last message. Each message holds every stream's sensor frame, as tf2's
/// static broadcaster republishes all its transforms.
struct StaticTf {
    publisher: zenoh_ext::AdvancedPublisher<'static>,
    _token: zenoh::liveliness::LivelinessToken,
    gid: [u8; 16],
    sequence: i64,
    /// Per stream: the sensor frame its clouds name and the configured sensor pose.
    frames: std::collections::BTreeMap<String, (Arc<str>, Pose)>,
}

impl StaticTf {
    fn put(&mut self, parent: &str) -> Result<(), PublishError> {
        self.sequence += 1;
        let now = crate::sources::unix_now_ns();
        let header = Header {
            stamp_ns: now,
            frame_id: parent,
        };
        let transforms: Vec<(Header, &str, Pose)> = self
            .frames
            .values()
            .map(|(child, pose)| (header, &**child, *pose))
            .collect();
        self.publisher
            .put(msg::tf_message(&transforms))
            .attachment(graph::attachment(self.sequence, now as i64, &self.gid).to_vec())
            .wait()
            .map_err(|e| PublishError::Ros2(format!("/tf_static: {e}")))
    }
}

/// The topics of one stream.
struct StreamTopics {
    pose: Topic,
    markers: Option<Topic>,
    detections: Option<Topic>,
    z_e: Topic,
    z_i: Topic,
    state: Topic,
    events: Topic,
    rejected: Topic,
    /// With several objects: the detections of the frame being published, sent with its last
    /// object (sequence, stamp, detections).
    pending: Option<(u64, u64, Vec<OwnedDetection>)>,
}

/// A detection held until its frame's last object is published.
struct OwnedDetection {
    id: String,
    score: f64,
    pose: Pose,
    size: [f64; 3],
}

pub struct Ros2Sink {
    settings: Ros2Settings,
    participant: Arc<Participant>,
    congestion: CongestionControl,
    tf: Option<Topic>,
    tf_static: Option<StaticTf>,
    /// Each stream's sensor pose (sensor -> gravity frame), where the configuration fixes it.
    sensor_poses: HashMap<String, Pose>,
    /// The bundle's model units back to metres (the detection boxes).
    metres_per_unit: f32,
    streams: HashMap<String, StreamTopics>,
    shapes: Option<Arc<ShapeWorker>>,
}

impl Ros2Sink {
    pub fn new(
        settings: &Ros2Settings,
        streams: &[String],
        shapes: Option<Arc<ShapeWorker>>,
        sensor_poses: &HashMap<String, ([[f32; 3]; 3], [f32; 3])>,
        model_units_per_metre: f64,
        participants: &Participants,
        lossless: bool,
    ) -> Result<Self, PublishError> {
        let settings = settings.clone();
        let participant = participants
            .join(settings.domain_id)
            .map_err(|e| PublishError::Ros2(format!("declaring the node's liveliness token: {e}")))?;
        let shapes = shapes.filter(|_| settings.markers && settings.shape_rate_hz > 0.0);
        log::info!(
            "ROS 2: node {}/{} in domain {} (rmw_zenoh conventions of Jazzy, Kilted, Rolling)",
            settings.namespace.trim_end_matches('/'),
            settings.node_name,
            settings.domain_id
        );
        let mut sink = Self {
            settings,
            participant,
            congestion: if lossless {
                CongestionControl::Block
            } else {
                CongestionControl::Drop
            },
            tf: None,
            tf_static: None,
            sensor_poses: sensor_poses.iter().map(|(s, p)| (s.clone(), sensor_pose(p))).collect(),
            metres_per_unit: 1.0 / model_units_per_metre as f32,
            streams: HashMap::new(),
            shapes,
        };
        if sink.settings.tf {
            let qos = Qos {
                reliable: true,
                transient_local: false,
                depth: 100,
            };
            sink.tf = Some(sink.declare("/tf", &msg::TF_MESSAGE, qos)?);
        }
        if sink.settings.tf_static {
            sink.tf_static = Some(sink.declare_static_tf()?);
        }
        // Every configured stream's topics now, so that `ros2 topic list` and `ros2 node info`
        // show them before the sensor starts (a stream that appears later gets its own then).
        for stream in streams {
            sink.stream(stream)?;
        }
        Ok(sink)
    }

    /// A publisher's liveliness token (what `ros2 topic list` sees) and its GID.
    fn publisher_token(
        &self,
        topic: &str,
        message: &MessageType,
        qos: &Qos,
    ) -> Result<(zenoh::liveliness::LivelinessToken, [u8; 16]), PublishError> {
        let node = self.participant.node();
        let token_key = node.entity_token(EntityKind::Publisher, self.participant.next_id(), topic, message, qos);
        let token = self
            .participant
            .session()
            .liveliness()
            .declare_token(token_key.clone())
            .wait()
            .map_err(|e| PublishError::Ros2(format!("declaring {topic}: {e}")))?;
        Ok((token, graph::gid(&token_key)))
    }

    fn declare(&mut self, topic: &str, message: &MessageType, qos: Qos) -> Result<Topic, PublishError> {
        let (token, gid) = self.publisher_token(topic, message, &qos)?;
        let (node, session) = (self.participant.node(), self.participant.session());
        let error = |e: zenoh::Error| PublishError::Ros2(format!("declaring {topic}: {e}"));
        let publisher = session
            .declare_publisher(graph::topic_key(node.domain, topic, message))
            .congestion_control(self.congestion)
            .wait()
            .map_err(error)?;
        Ok(Topic {
            publisher,
            _token: token,
            gid,
            sequence: 0,
        })
    }

    fn declare_static_tf(&mut self) -> Result<StaticTf, PublishError> {
        use zenoh_ext::{AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};
        let qos = Qos {
            reliable: true,
            transient_local: true,
            depth: 1,
        };
        let message = &msg::TF_MESSAGE;
        let (token, gid) = self.publisher_token("/tf_static", message, &qos)?;
        let (node, session) = (self.participant.node(), self.participant.session());
        let error = |e: zenoh::Error| PublishError::Ros2(format!("declaring /tf_static: {e}"));
        let publisher = session
            .declare_publisher(graph::topic_key(node.domain, "/tf_static", message))
            .congestion_control(CongestionControl::Drop)
            .reliability(zenoh::qos::Reliability::Reliable)
            .cache(CacheConfig::default().max_samples(1))
            .sample_miss_detection(
                MissDetectionConfig::default().sporadic_heartbeat(std::time::Duration::from_millis(500)),
            )
            .publisher_detection()
            .wait()
            .map_err(error)?;
        Ok(StaticTf {
            publisher,
            _token: token,
            gid,
            sequence: 0,
            frames: Default::default(),
        })
    }

    /// Publishes `state`'s sensor frame on /tf_static when its stream names a new one.
    fn static_tf(&mut self, state: &State) -> Result<(), PublishError> {
        let (Some(tf_static), Some(frame)) = (self.tf_static.as_mut(), state.sensor_frame.as_ref()) else {
            return Ok(());
        };
        if tf_static
            .frames
            .get(&state.stream)
            .is_some_and(|(known, _)| known == frame)
        {
            return Ok(());
        }
        let Some(pose) = self.sensor_poses.get(&state.stream) else {
            return Ok(());
        };
        log::info!(
            "ROS 2: /tf_static {} -> {frame} (stream '{}', its configured sensor pose)",
            self.settings.frame_id,
            state.stream
        );
        tf_static.frames.insert(state.stream.clone(), (frame.clone(), *pose));
        tf_static.put(&self.settings.frame_id)
    }

    fn stream(&mut self, stream: &str) -> Result<&mut StreamTopics, PublishError> {
        if !self.streams.contains_key(stream) {
            let qos = Qos {
                reliable: self.settings.reliable,
                transient_local: false,
                depth: self.settings.depth,
            };
            let topic = |what: &str| self.settings.topic(stream, what);
            let (pose, markers, detections, z_e, z_i, state, events, rejected) = (
                topic("pose"),
                topic("markers"),
                topic("detections"),
                topic("z_e"),
                topic("z_i"),
                topic("state"),
                topic("events"),
                topic("rejected"),
            );
            let topics = StreamTopics {
                pose: self.declare(&pose, &msg::POSE_STAMPED, qos)?,
                markers: if self.settings.markers {
                    Some(self.declare(&markers, &msg::MARKER_ARRAY, qos)?)
                } else {
                    None
                },
                detections: if self.settings.detections {
                    Some(self.declare(&detections, &msg::DETECTION3D_ARRAY, qos)?)
                } else {
                    None
                },
                z_e: self.declare(&z_e, &msg::FLOAT32_MULTI_ARRAY, qos)?,
                z_i: self.declare(&z_i, &msg::FLOAT32_MULTI_ARRAY, qos)?,
                state: self.declare(&state, &msg::STRING, qos)?,
                events: self.declare(&events, &msg::STRING, qos)?,
                rejected: self.declare(&rejected, &msg::STRING, qos)?,
                pending: None,
            };
            log::info!(
                "ROS 2: publishing {}/*",
                self.settings.topic(stream, "").trim_end_matches('/')
            );
            self.streams.insert(stream.to_string(), topics);
        }
        Ok(self.streams.get_mut(stream).expect("inserted above"))
    }

    fn publish_state(&mut self, state: &State) -> Result<(), PublishError> {
        let stamp_ns = state.stamps.sensor_ns.unwrap_or(state.stamps.ingest_ns);
        let frame_id = self.settings.frame_id.clone();
        let header = Header {
            stamp_ns,
            frame_id: &frame_id,
        };
        let [w, x, y, z] = state.filtered.q.map(f64::from);
        let pose = Pose {
            position: state.centre_m.map(f64::from),
            orientation: [x, y, z, w],
        };
        let child = format!("{}{}", self.settings.object_frame_prefix, state.object_name());
        let metres_per_unit = self.metres_per_unit;
        if let Some(tf) = self.tf.as_mut() {
            tf.put(msg::tf_message(&[(header, &child, pose)]))?;
        }
        self.static_tf(state)?;
        let shape = self.shapes.as_ref().and_then(|s| s.shape_for(state));
        let topics = self.stream(&state.stream)?;
        topics.pose.put(msg::pose_stamped(&header, &pose))?;
        topics.z_e.put(msg::float32_multi_array("z_e", &state.filtered.z_e))?;
        topics.z_i.put(msg::float32_multi_array("z_i", &state.shape.z_i))?;
        let json = serde_json::to_string(state).map_err(|e| PublishError::Encode(e.to_string()))?;
        topics.state.put(msg::string(&json))?;
        if let Some(event) = state.event_message() {
            let json = serde_json::to_string(&event).map_err(|e| PublishError::Encode(e.to_string()))?;
            topics.events.put(msg::string(&json))?;
        }
        if let Some(detections) = topics.detections.as_mut() {
            let detection = detection(state, &pose, metres_per_unit);
            match state.of_frame {
                None => detections.put(detection_array(&header, &[detection]))?,
                Some((index, count)) => {
                    // A frame's objects arrive one after another: one array of them all.
                    let pending = topics.pending.get_or_insert((state.sequence, stamp_ns, Vec::new()));
                    if pending.0 != state.sequence {
                        // The rest of the previous frame's objects never came (a track failed).
                        let (_, stamp_ns, earlier) = std::mem::replace(pending, (state.sequence, stamp_ns, Vec::new()));
                        let header = Header {
                            stamp_ns,
                            frame_id: &frame_id,
                        };
                        detections.put(detection_array(&header, &earlier))?;
                    }
                    pending.2.push(detection);
                    if index + 1 == count {
                        let (_, stamp_ns, all) = topics.pending.take().expect("held above");
                        let header = Header {
                            stamp_ns,
                            frame_id: &frame_id,
                        };
                        detections.put(detection_array(&header, &all))?;
                    }
                }
            }
        }
        if let Some(markers) = topics.markers.as_mut() {
            markers.put(marker_array(state, &header, &pose, shape.as_deref().map(Vec::as_slice)))?;
        }
        Ok(())
    }
}

/// The state's object as a detection: id its track (with several objects) or its identity, class
/// "object" (the node does not classify), score its confidence, pose the estimated centre and
/// rotation, box the extent of the points the encoder saw in the object's (canonical) frame.
fn detection(state: &State, pose: &Pose, metres_per_unit: f32) -> OwnedDetection {
    let [w, x, y, z] = state.filtered.q;
    let to_object = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z)).inverse();
    let mut low = [f32::INFINITY; 3];
    let mut high = [f32::NEG_INFINITY; 3];
    for p in state.prepared.as_deref().into_iter().flatten() {
        let local = to_object * nalgebra::Vector3::from(*p);
        for a in 0..3 {
            low[a] = low[a].min(local[a]);
            high[a] = high[a].max(local[a]);
        }
    }
    OwnedDetection {
        id: state.track.unwrap_or(state.shape.identity).to_string(),
        score: f64::from(state.shape.confidence.clamp(0.0, 1.0)),
        pose: *pose,
        size: std::array::from_fn(|a| f64::from(((high[a] - low[a]) * metres_per_unit).max(0.0))),
    }
}

/// One frame's detections as a `Detection3DArray`.
fn detection_array(header: &Header, detections: &[OwnedDetection]) -> Vec<u8> {
    let detections: Vec<msg::Detection> = detections
        .iter()
        .map(|d| msg::Detection {
            id: &d.id,
            class_id: "object",
            score: d.score,
            pose: d.pose,
            size: d.size,
        })
        .collect();
    msg::detection3d_array(header, &detections)
}

/// A sensor pose (rotation matrix, translation: sensor -> gravity) as the pose of the sensor's
/// frame in the gravity frame.
fn sensor_pose((rotation, translation): &([[f32; 3]; 3], [f32; 3])) -> Pose {
    let matrix = nalgebra::Matrix3::from_fn(|i, j| f64::from(rotation[i][j]));
    let q = nalgebra::UnitQuaternion::from_matrix(&matrix);
    Pose {
        position: translation.map(f64::from),
        orientation: [q.i, q.j, q.k, q.w],
    }
}

/// Identity text above the object, a heading arrow, and the decoded canonical shape at the pose.
fn marker_array(state: &State, header: &Header, pose: &Pose, shape: Option<&[[f32; 3]]>) -> Vec<u8> {
    const LIFETIME_NS: u64 = 1_000_000_000;
    let text = format!(
        "{} identity {} ({:.0} %){}",
        state.object_name(),
        state.shape.identity,
        100.0 * state.shape.confidence,
        if state.shape.inlier { "" } else { " outlier" }
    );
    let half_yaw = f64::from(state.filtered.yaw) / 2.0;
    let heading = Pose {
        position: pose.position,
        orientation: [0.0, 0.0, half_yaw.sin(), half_yaw.cos()],
    };
    let above = Pose {
        position: [pose.position[0], pose.position[1], pose.position[2] + 0.6],
        orientation: [0.0, 0.0, 0.0, 1.0],
    };
    let confidence = state.shape.confidence.clamp(0.0, 1.0);
    // Each track's markers under ids of their own (0, 1, 2 with one object per stream).
    let first_id = 3 * state.track.unwrap_or(0) as i32;
    let mut markers = vec![
        Marker {
            header: *header,
            namespace: "identity",
            id: first_id,
            kind: msg::MARKER_TEXT,
            pose: above,
            scale: [0.0, 0.0, 0.12],
            color: [1.0, 1.0, 1.0, 1.0],
            lifetime_ns: LIFETIME_NS,
            points: &[],
            text: &text,
        },
        Marker {
            header: *header,
            namespace: "heading",
            id: first_id + 1,
            kind: msg::MARKER_ARROW,
            pose: heading,
            scale: [0.6, 0.05, 0.05],
            color: [1.0 - confidence, confidence, 0.2, 1.0],
            lifetime_ns: LIFETIME_NS,
            points: &[],
            text: "",
        },
    ];
    if let Some(points) = shape {
        markers.push(Marker {
            header: *header,
            namespace: "shape",
            id: first_id + 2,
            kind: msg::MARKER_POINTS,
            pose: *pose,
            scale: [0.02, 0.02, 0.0],
            color: [0.2, 0.6, 1.0, 1.0],
            lifetime_ns: LIFETIME_NS,
            points,
            text: "",
        });
    }
    msg::marker_array(&markers)
}

impl Sink for Ros2Sink {
    fn publish(&mut self, output: &Output) -> Result<(), PublishError> {
        match output {
            Output::State(state) => self.publish_state(state),
            Output::Rejected(rejected) => {
                let json = serde_json::to_string(rejected).map_err(|e| PublishError::Encode(e.to_string()))?;
                self.stream(&rejected.stream)?.rejected.put(msg::string(&json))
            }
        }
    }
}
