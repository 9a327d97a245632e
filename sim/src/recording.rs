//! MCAP recordings of a scenario, in the layout rosbag2 writes (profile `ros2`, CDR messages with
//! `ros2msg` schemas), so that standard tools (ros2 bag, Foxglove, the `mcap` CLI and libraries)
//! and the node's replay source read them.
//!
//! Channels (documented in sim/README.md):
//! - [`POINTS_TOPIC`]: `sensor_msgs/msg/PointCloud2`, float32 x, y, z in the optical frame (m);
//! - [`DEPTH_TOPIC`] + [`CAMERA_INFO_TOPIC`] (optional): `sensor_msgs/msg/Image` 16UC1 millimetres
//!   and its `sensor_msgs/msg/CameraInfo`;
//! - [`GROUND_TRUTH_TOPIC`]: JSON, one [`GroundTruthMessage`] per frame.
//!
//! A metadata record named `gdvae_sim` carries the specs and the camera's pose in the world.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::time::Instant;

use mcap::records::{MessageHeader, Metadata};
use mcap::{Compression, WriteOptions};
use rayon::prelude::*;
use serde::Serialize;

use crate::ros2::{self, Stamp};
use crate::scenario::{GroundTruthMessage, Scenario, ScenarioError};

pub const POINTS_TOPIC: &str = "/camera/depth/points";
pub const DEPTH_TOPIC: &str = "/camera/depth/image_raw";
pub const CAMERA_INFO_TOPIC: &str = "/camera/depth/camera_info";
pub const GROUND_TRUTH_TOPIC: &str = "/sim/ground_truth";
pub const CAMERA_FRAME: &str = "camera_depth_optical_frame";

/// Sensor stamps start here (2023-11-14T22:13:20Z) so recordings are byte-for-byte reproducible.
pub const START_NANOS: u64 = 1_700_000_000_000_000_000;

/// Frames generated in parallel before being written in order.
const BATCH: usize = 16;

#[derive(Debug, Clone, Copy)]
pub struct RecordingOptions {
    pub depth_images: bool,
    pub compression: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct RecordingSummary {
    pub frames: usize,
    pub points_per_frame_mean: f64,
    pub points_per_frame_min: usize,
    pub bytes: u64,
    pub seconds: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    #[error("writing MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    #[error(transparent)]
    Io(#[from] std::io::Error),
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

/// Writes every frame of `scenario` to an MCAP file at `path`; `progress(done, total)` after each batch.
pub fn write_recording(
    scenario: &Scenario,
    path: &Path,
    options: RecordingOptions,
    progress: impl Fn(usize, usize),
) -> Result<RecordingSummary, RecordingError> {
    let started = Instant::now();
    let file = BufWriter::new(File::create(path)?);
    let mut writer = WriteOptions::new()
        .profile("ros2")
        .compression(options.compression.then_some(Compression::Zstd))
        .create(file)?;

    let no_metadata = BTreeMap::new();
    let points_schema = writer.add_schema(
        "sensor_msgs/msg/PointCloud2",
        "ros2msg",
        ros2::point_cloud2_schema().as_bytes(),
    )?;
    let points_channel = writer.add_channel(points_schema, POINTS_TOPIC, "cdr", &no_metadata)?;
    let image_channels = if options.depth_images {
        let image_schema = writer.add_schema("sensor_msgs/msg/Image", "ros2msg", ros2::image_schema().as_bytes())?;
        let info_schema = writer.add_schema(
            "sensor_msgs/msg/CameraInfo",
            "ros2msg",
            ros2::camera_info_schema().as_bytes(),
        )?;
        Some((
            writer.add_channel(image_schema, DEPTH_TOPIC, "cdr", &no_metadata)?,
            writer.add_channel(info_schema, CAMERA_INFO_TOPIC, "cdr", &no_metadata)?,
        ))
    } else {
        None
    };
    let truth_schema = writer.add_schema(
        "gdvae_sim/GroundTruth",
        "jsonschema",
        GROUND_TRUTH_JSON_SCHEMA.as_bytes(),
    )?;
    let truth_channel = writer.add_channel(truth_schema, GROUND_TRUTH_TOPIC, "json", &no_metadata)?;

    let camera_pose = scenario.world_from_camera();
    writer.write_metadata(&Metadata {
        name: "gdvae_sim".into(),
        metadata: BTreeMap::from([
            ("motion".into(), serde_json::to_string(&scenario.motion.spec)?),
            ("view".into(), serde_json::to_string(&scenario.view)?),
            (
                "others".into(),
                serde_json::to_string(
                    &scenario
                        .others
                        .iter()
                        .map(|o| serde_json::json!({"motion": o.motion.spec, "offset": o.offset}))
                        .collect::<Vec<_>>(),
                )?,
            ),
            ("away".into(), serde_json::to_string(&scenario.away)?),
            ("intrinsics".into(), serde_json::to_string(&scenario.camera.intrinsics)?),
            ("stereo".into(), serde_json::to_string(&scenario.camera.stereo)?),
            ("world_from_camera".into(), serde_json::to_string(&camera_pose)?),
            ("camera_frame".into(), CAMERA_FRAME.into()),
            ("units".into(), "metres; world z up, ground at z = 0".into()),
        ]),
    })?;

    let total = scenario.frame_count();
    let (mut point_sum, mut point_min) = (0usize, usize::MAX);
    let mut sequence = 0u32;
    for start in (0..total).step_by(BATCH) {
        let frames = (start..(start + BATCH).min(total))
            .into_par_iter()
            .map(|index| scenario.frame(index))
            .collect::<Result<Vec<_>, _>>()?;
        for frame in frames {
            let nanos = START_NANOS + frame.offset_nanos;
            let stamp = Stamp::from_nanos(nanos);
            let mut write = |channel_id: u16, data: &[u8]| -> Result<(), mcap::McapError> {
                sequence += 1;
                writer.write_to_known_channel(
                    &MessageHeader {
                        channel_id,
                        sequence,
                        log_time: nanos,
                        publish_time: nanos,
                    },
                    data,
                )
            };
            write(points_channel, &ros2::point_cloud2(stamp, CAMERA_FRAME, &frame.points))?;
            if let Some((image_channel, info_channel)) = image_channels {
                write(image_channel, &ros2::depth_image(stamp, CAMERA_FRAME, &frame.depth))?;
                write(
                    info_channel,
                    &ros2::camera_info(stamp, CAMERA_FRAME, &scenario.camera.intrinsics),
                )?;
            }
            let truth = GroundTruthMessage {
                stamp_nanos: nanos,
                truth: &frame.truth,
                world_from_camera: camera_pose,
                points: frame.points.len(),
                subjects: &frame.subjects,
            };
            write(truth_channel, &serde_json::to_vec(&truth)?)?;
            point_sum += frame.points.len();
            point_min = point_min.min(frame.points.len());
        }
        progress((start + BATCH).min(total), total);
    }
    writer.finish()?;
    drop(writer);
    Ok(RecordingSummary {
        frames: total,
        points_per_frame_mean: point_sum as f64 / total.max(1) as f64,
        points_per_frame_min: if total == 0 { 0 } else { point_min },
        bytes: std::fs::metadata(path)?.len(),
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// JSON Schema of the ground-truth channel (draft 2020-12).
pub const GROUND_TRUTH_JSON_SCHEMA: &str = r#"{
  "$schema": "https://json-schema.org/draft/2020-12/schema",
  "title": "gdvae_sim/GroundTruth",
  "type": "object",
  "required": ["stamp_nanos", "frame", "time", "subject", "family", "beta", "theta", "yaw", "translation", "world_from_camera"],
  "properties": {
    "stamp_nanos": {"type": "integer", "description": "sensor stamp of the frame (ns since the Unix epoch)"},
    "frame": {"type": "integer"},
    "time": {"type": "number", "description": "seconds since the start of the sequence"},
    "subject": {"type": "string", "description": "identity; changes at scripted switches"},
    "family": {"type": "string", "enum": ["quadruped", "biped"]},
    "beta": {"type": "array", "items": {"type": "number"}, "description": "intrinsic shape parameters"},
    "theta": {"type": "array", "items": {"type": "number"}, "description": "axis-angle per non-root joint (rad)"},
    "yaw": {"type": "number", "description": "heading about world +z (rad, unwrapped)"},
    "translation": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
    "gait_phase": {"type": "number"},
    "world_from_camera": {"type": "object", "properties": {
      "translation": {"type": "array", "items": {"type": "number"}},
      "rotation_xyzw": {"type": "array", "items": {"type": "number"}}}},
    "points": {"type": "integer"},
    "subjects": {"type": "array", "description": "every subject, the primary (the fields above) first", "items": {
      "type": "object",
      "required": ["id", "present", "visible_points", "subject", "family", "beta", "theta", "yaw", "translation"],
      "properties": {
        "id": {"type": "integer", "description": "0: the primary; 1..: the others, in order"},
        "present": {"type": "boolean", "description": "in the scene (false while it has left the view)"},
        "visible_points": {"type": "integer", "description": "points of this frame's cloud on the subject"},
        "subject": {"type": "string"}, "family": {"type": "string"},
        "beta": {"type": "array"}, "theta": {"type": "array"}, "yaw": {"type": "number"},
        "translation": {"type": "array"}, "gait_phase": {"type": "number"}}}}
  }
}"#;
