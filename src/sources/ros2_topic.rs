//! The ROS 2 source: a topic by name, as a ROS 2 subscriber over rmw_zenoh receives it, with no
//! key to look up. `kind = "ros2"`, `topic = "/camera/points"`: `sensor_msgs/msg/PointCloud2`, or a
//! depth `sensor_msgs/msg/Image` unprojected with the latest `CameraInfo` of `camera_info_topic`.
//!
//! It subscribes on the topic's key with any type and any type hash (a Humble, Jazzy or Rolling
//! publisher computes its own) and declares its subscription token (MS) of the configured type
//! (`message_type`) at once; then it watches the graph's liveliness for the topic's publishers:
//! for each other type and hash one advertises, it declares a matching token, so that a publisher
//! that waits for subscribers starts sending; only for the types it reads (PointCloud2, Image;
//! CameraInfo on the info topic). Each sample must carry rmw_zenoh's
//! attachment; a sample of another type, or without a valid attachment, is a counted rejection.

use std::sync::{Arc, Mutex};

use zenoh::sample::{Sample, SampleKind};
use zenoh::Wait;

use crate::cloud::{PointCloud, Unit};
use crate::ros2::graph::{self, EntityKind, Qos};
use crate::ros2::{msg, Participant};
use crate::sources::outlet::{Intake, Outlet};
use crate::sources::ros2::{decode_camera_info, decode_depth_image, decode_point_cloud2, CameraIntrinsics};

/// `kind = "ros2"`: a ROS 2 topic.
#[derive(Debug, Clone, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct Ros2TopicSettings {
    /// The topic, e.g. "/camera/points" (relative names resolve in `[publish.ros2] namespace`).
    pub topic: String,
    /// A depth image's CameraInfo topic (default: `<image topic's parent>/camera_info`).
    #[serde(default)]
    pub camera_info_topic: Option<String>,
    /// Depth images: keep every `depth_step`-th pixel in each direction.
    #[serde(default = "super::recording::default_depth_step")]
    pub depth_step: usize,
    /// The ROS 2 domain (default: `[publish.ros2] domain_id`).
    #[serde(default)]
    pub domain_id: Option<u32>,
    /// The type the topic carries, whose subscription is declared when the node starts (so that
    /// `ros2 node info` shows it before any publisher exists): "sensor_msgs/msg/PointCloud2" (the
    /// default) or "sensor_msgs/msg/Image". Either is read whatever this says.
    #[serde(default)]
    pub message_type: InputType,
}

/// The message a ROS 2 input topic carries.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
pub enum InputType {
    #[default]
    #[serde(rename = "sensor_msgs/msg/PointCloud2")]
    PointCloud2,
    #[serde(rename = "sensor_msgs/msg/Image")]
    Image,
}

/// A ROS 2 topic name: segments of letters, digits and underscores, not starting with a digit.
fn is_topic(name: &str) -> bool {
    !name.is_empty()
        && name.trim_start_matches('/').split('/').all(|part| {
            part.chars().next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
                && part.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
        })
}

impl Ros2TopicSettings {
    pub fn validate(&self) -> Result<(), String> {
        for name in std::iter::once(&self.topic).chain(&self.camera_info_topic) {
            if !is_topic(name) {
                return Err(format!(
                    "'{name}' is not a ROS 2 topic name like \"/camera/points\" (letters, digits, underscores)"
                ));
            }
        }
        if self.depth_step == 0 {
            return Err("depth_step must be at least 1".into());
        }
        if self.domain_id.is_some_and(|d| d > 232) {
            return Err("domain_id must be within 0..=232".into());
        }
        Ok(())
    }
}

/// The subscriptions of one ROS 2 source; they end when it is dropped.
pub struct Ros2Subscription {
    _data: Vec<zenoh::pubsub::Subscriber<()>>,
    _camera_info: zenoh::pubsub::Subscriber<()>,
    _publishers: zenoh::pubsub::Subscriber<()>,
    _tokens: Arc<Mutex<Vec<(String, zenoh::liveliness::LivelinessToken)>>>,
}

/// The topics a source reads: its data topic and the CameraInfo topic of a depth image, absolute.
pub fn topics(participant: &Participant, settings: &Ros2TopicSettings) -> (String, String) {
    let node = participant.node();
    let topic = node.resolve(&settings.topic);
    let info = match &settings.camera_info_topic {
        Some(info) => node.resolve(info),
        None => format!("{}/camera_info", topic.rsplit_once('/').map(|(p, _)| p).unwrap_or("")),
    };
    (topic, info)
}

pub fn subscribe(
    participant: Arc<Participant>,
    intake: &Intake,
    settings: &Ros2TopicSettings,
    outlet: Outlet,
) -> Result<Ros2Subscription, zenoh::Error> {
    let (topic, info_topic) = topics(&participant, settings);
    let domain = participant.node().domain;
    let session = participant.session().clone();
    let intrinsics: Arc<Mutex<Option<Arc<CameraIntrinsics>>>> = Arc::default();

    let camera_info = {
        let intrinsics = intrinsics.clone();
        let key = graph::topic_key_any_hash(domain, &info_topic, "sensor_msgs", "CameraInfo");
        session
            .declare_subscriber(key)
            .callback(move |sample: Sample| {
                if graph::parse_attachment(&attachment_bytes(&sample)).is_err() {
                    return;
                }
                match decode_camera_info(&sample.payload().to_bytes()) {
                    Ok((_, k)) => *intrinsics.lock().unwrap_or_else(|e| e.into_inner()) = Some(Arc::new(k)),
                    Err(e) => log::warn!("CameraInfo on {} ignored: {e}", sample.key_expr()),
                }
            })
            .wait()?
    };

    // The classic data key, and a buffer-aware publisher's CPU key (`<key>/_buf_cpu`, rmw_zenoh
    // 0.10.5 on: the same CDR, sent there only while every subscriber it matches is
    // buffer-aware). Its per-subscriber keys (`<key>/_buf/<gid>`) are for others.
    let outlet = Arc::new(Mutex::new(outlet));
    let mut data = Vec::new();
    for suffix in ["", "/_buf_cpu"] {
        let (max_points, depth_step, unit) = (
            intake.max_points,
            settings.depth_step,
            intake.unit.unwrap_or(Unit::Metre),
        );
        let (outlet, intrinsics, topic) = (outlet.clone(), intrinsics.clone(), topic.clone());
        data.push(
            session
                .declare_subscriber(format!("{domain}/{}/*/*{suffix}", topic.trim_matches('/')))
                .callback(move |sample: Sample| {
                    let decoded = decode(&sample, &intrinsics, max_points, depth_step);
                    let Ok(mut outlet) = outlet.lock() else { return };
                    match decoded {
                        Ok((stamp, points, dropped, frame_id)) => {
                            outlet.sensor_frame(&frame_id);
                            outlet.frame(PointCloud { points }, unit, Some(stamp), dropped);
                        }
                        Err(reason) => {
                            outlet.reject(format!("ROS 2 sample on {topic}: {reason}"), None);
                        }
                    }
                })
                .wait()?,
        );
    }

    // Subscription tokens: the configured type's now (Jazzy's hash), then one per other (topic,
    // type, hash) a publisher advertises.
    let tokens: Arc<Mutex<Vec<(String, zenoh::liveliness::LivelinessToken)>>> = Arc::default();
    let expected: &[(&str, &graph::MessageType)] = match settings.message_type {
        InputType::PointCloud2 => &[(&topic, &msg::POINT_CLOUD2)],
        InputType::Image => &[(&topic, &msg::IMAGE), (&info_topic, &msg::CAMERA_INFO)],
    };
    for (topic, message) in expected {
        declare_subscription(&participant, &tokens, topic, &message.dds_name(), message.hash);
    }
    let publishers = {
        let (tokens, participant) = (tokens.clone(), participant.clone());
        let watched = [graph::mangle(&topic), graph::mangle(&info_topic)];
        session
            .liveliness()
            .declare_subscriber(format!("{}/{domain}/**", graph::ADMIN_SPACE))
            .history(true)
            .callback(move |sample: Sample| {
                if sample.kind() != SampleKind::Put {
                    return;
                }
                let key = sample.key_expr().as_str();
                let parts: Vec<&str> = key.split('/').collect();
                // @ros2_lv/domain/zid/nid/id/MP/enclave/ns/node/topic/type/hash/qos
                if parts.len() < 13 || parts[5] != "MP" || !watched.contains(&parts[9].to_string()) {
                    return;
                }
                let (topic, dds_type, hash) = (parts[9].replace('%', "/"), parts[10], parts[11]);
                // Only the types the node reads: a publisher of another type on the topic gets no
                // subscription (it would list the node with that type, long after it has gone).
                let reads = if parts[9] == watched[1] {
                    dds_type == msg::CAMERA_INFO.dds_name()
                } else {
                    dds_type == msg::POINT_CLOUD2.dds_name() || dds_type == msg::IMAGE.dds_name()
                };
                if !reads {
                    return;
                }
                declare_subscription(&participant, &tokens, &topic, dds_type, hash);
            })
            .wait()?
    };

    Ok(Ros2Subscription {
        _data: data,
        _camera_info: camera_info,
        _publishers: publishers,
        _tokens: tokens,
    })
}

/// Declares the node's subscription to `topic` of a type (DDS name and hash), unless it has one.
fn declare_subscription(
    participant: &Participant,
    tokens: &Mutex<Vec<(String, zenoh::liveliness::LivelinessToken)>>,
    topic: &str,
    dds_type: &str,
    hash: &str,
) {
    let id = format!("{topic} {dds_type} {hash}");
    let mut tokens = tokens.lock().unwrap_or_else(|e| e.into_inner());
    if tokens.iter().any(|(known, _)| *known == id) {
        return;
    }
    // Best effort, keep last 10: compatible with any publisher's reliability.
    let qos = Qos {
        reliable: false,
        transient_local: false,
        depth: 10,
    };
    let token_key = participant.node().entity_token_of(
        EntityKind::Subscription,
        participant.next_id(),
        topic,
        dds_type,
        hash,
        &qos,
    );
    match participant.session().liveliness().declare_token(token_key).wait() {
        Ok(token) => {
            log::info!("ROS 2: subscribed to {topic} ({dds_type})");
            tokens.push((id, token));
        }
        Err(e) => log::warn!("ROS 2: declaring a subscription token for {topic}: {e}"),
    }
}

fn attachment_bytes(sample: &Sample) -> Vec<u8> {
    sample.attachment().map(|a| a.to_bytes().to_vec()).unwrap_or_default()
}

/// One data sample: its attachment checked, its type read from its key, its payload decoded.
fn decode(
    sample: &Sample,
    intrinsics: &Mutex<Option<Arc<CameraIntrinsics>>>,
    max_points: usize,
    depth_step: usize,
) -> Result<(u64, Vec<[f32; 3]>, usize, String), String> {
    graph::parse_attachment(&attachment_bytes(sample))?;
    let key = sample.key_expr().as_str();
    let key = key.strip_suffix("/_buf_cpu").unwrap_or(key);
    let dds_type = key.rsplit('/').nth(1).unwrap_or("");
    let payload = sample.payload().to_bytes();
    if dds_type == msg::POINT_CLOUD2.dds_name() {
        let cloud = decode_point_cloud2(&payload, max_points).map_err(|e| e.to_string())?;
        Ok((
            cloud.header.stamp_ns,
            cloud.points,
            cloud.dropped_non_finite,
            cloud.header.frame_id,
        ))
    } else if dds_type == msg::IMAGE.dds_name() {
        let k = intrinsics
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
            .ok_or("depth image before any CameraInfo")?;
        let cloud = decode_depth_image(&payload, &k, depth_step, max_points).map_err(|e| e.to_string())?;
        Ok((
            cloud.header.stamp_ns,
            cloud.points,
            cloud.dropped_non_finite,
            cloud.header.frame_id,
        ))
    } else {
        Err(format!(
            "type {dds_type} is not one the node reads ({} or {})",
            msg::POINT_CLOUD2.ros_name(),
            msg::IMAGE.ros_name()
        ))
    }
}
