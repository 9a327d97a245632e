//! Zenoh subscriptions: point clouds from the network, as ROS 2 PointCloud2 CDR payloads (what
//! rmw_zenoh and the sim's feed carry) or as the DepthAI harness's float32 millimetre triplets.
//!
//! Samples arrive on zenoh's threads; each is decoded there and handed to the stream's live outlet,
//! which never blocks the network (the oldest queued frame is dropped and counted when the pipeline
//! is behind). A sample that does not decode is a counted rejection naming the key and the reason.

use std::sync::Mutex;

use zenoh::sample::Sample;
use zenoh::{Session, Wait};

use crate::cloud::{PointCloud, Unit};
use serde::{Deserialize, Serialize};

use crate::sources::outlet::{Intake, Outlet};
use crate::sources::ros2::decode_point_cloud2;

/// The DepthAI harness's encoding schema (see sim/depthai_feed.py).
pub const DEPTHAI_SCHEMA: &str = "depthai/PointCloudData;xyz_f32_mm";

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum WireFormat {
    /// Decide per sample from its zenoh encoding (none, as rmw_zenoh sends: CDR).
    Auto,
    /// ROS 2 sensor_msgs/msg/PointCloud2 in CDR.
    Cdr,
    /// The DepthAI harness: float32 x, y, z in millimetres.
    Depthai,
}

/// `kind = "zenoh"`: a zenoh key expression.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSourceSettings {
    /// Key expression to subscribe to.
    pub key: String,
    #[serde(default = "auto")]
    pub format: WireFormat,
}

fn auto() -> WireFormat {
    WireFormat::Auto
}

impl ZenohSourceSettings {
    pub fn validate(&self) -> Result<(), String> {
        if self.key.is_empty() {
            return Err("a zenoh source needs `key`".into());
        }
        zenoh::key_expr::KeyExpr::try_from(self.key.as_str())
            .map(|_| ())
            .map_err(|e| format!("key '{}' is not a zenoh key expression: {e}", self.key))
    }
}

/// Subscribes `outlet` to the source's key. The subscription lives as long as the returned value.
pub fn subscribe(
    session: &Session,
    intake: &Intake,
    settings: &ZenohSourceSettings,
    outlet: Outlet,
) -> Result<zenoh::pubsub::Subscriber<()>, zenoh::Error> {
    let key = settings.key.clone();
    let format = settings.format;
    let max_points = intake.max_points;
    let unit_override = intake.unit;
    let outlet = Mutex::new(outlet);
    session
        .declare_subscriber(key)
        .callback(move |sample: Sample| {
            let decoded = decode_sample(&sample, format, max_points);
            let Ok(mut outlet) = outlet.lock() else { return };
            match decoded {
                Ok((points, unit, stamp, dropped, frame_id)) => {
                    outlet.sensor_frame(&frame_id);
                    outlet.frame(PointCloud { points }, unit_override.unwrap_or(unit), stamp, dropped);
                }
                Err(reason) => {
                    outlet.reject(format!("zenoh sample on {}: {reason}", sample.key_expr()), None);
                }
            }
        })
        .wait()
}

/// Points, their unit, the sensor's stamp, non-finite points dropped, the sensor frame (CDR only).
type Decoded = (Vec<[f32; 3]>, Unit, Option<u64>, usize, String);

/// Decodes one sample by the configured format, or by its encoding under `auto`.
pub fn decode_sample(sample: &Sample, format: WireFormat, max_points: usize) -> Result<Decoded, String> {
    let encoding = sample.encoding().to_string();
    let format = match format {
        WireFormat::Auto if encoding.contains("depthai") => WireFormat::Depthai,
        WireFormat::Auto if encoding.contains("cdr") || encoding.contains("PointCloud2") => WireFormat::Cdr,
        // rmw_zenoh sets no encoding (zenoh/bytes): its samples are CDR.
        WireFormat::Auto if sample.encoding() == &zenoh::bytes::Encoding::ZENOH_BYTES => WireFormat::Cdr,
        WireFormat::Auto => {
            return Err(format!(
                "unknown encoding '{encoding}' (expected application/cdr;sensor_msgs/msg/PointCloud2, none \
                 (rmw_zenoh) or application/octet-stream;{DEPTHAI_SCHEMA}); set the source's `format`"
            ))
        }
        chosen => chosen,
    };
    let payload = sample.payload().to_bytes();
    match format {
        WireFormat::Cdr => decode_point_cloud2(&payload, max_points)
            .map(|c| {
                (
                    c.points,
                    Unit::Metre,
                    Some(c.header.stamp_ns),
                    c.dropped_non_finite,
                    c.header.frame_id,
                )
            })
            .map_err(|e| e.to_string()),
        _ => {
            let stamp = sample
                .attachment()
                .and_then(|a| serde_json::from_slice::<serde_json::Value>(&a.to_bytes()).ok())
                .and_then(|v| v["stamp_nanos"].as_u64());
            decode_depthai(&payload, max_points)
                .map(|(points, dropped)| (points, Unit::Millimetre, stamp, dropped, String::new()))
        }
    }
}

/// float32 little-endian x, y, z triplets; non-finite points dropped and counted.
pub fn decode_depthai(payload: &[u8], max_points: usize) -> Result<(Vec<[f32; 3]>, usize), String> {
    if payload.len() % 12 != 0 {
        return Err(format!(
            "{} bytes is not a whole number of float32 x, y, z triplets",
            payload.len()
        ));
    }
    let count = payload.len() / 12;
    if count > max_points {
        return Err(format!("{count} points exceed max_points = {max_points}"));
    }
    let mut points = Vec::with_capacity(count);
    let mut dropped = 0;
    for chunk in payload.chunks_exact(12) {
        let value = |i: usize| f32::from_le_bytes(chunk[4 * i..4 * i + 4].try_into().expect("4 bytes"));
        let point = [value(0), value(1), value(2)];
        if point.iter().all(|c| c.is_finite()) {
            points.push(point);
        } else {
            dropped += 1;
        }
    }
    Ok((points, dropped))
}
