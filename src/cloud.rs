//! Point clouds as they move through the node: a frame's points plus where and when they came from.

use std::time::Instant;

/// Length unit of incoming coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Unit {
    Metre,
    Millimetre,
}

impl Unit {
    pub fn to_metres(self) -> f32 {
        match self {
            Unit::Metre => 1.0,
            Unit::Millimetre => 0.001,
        }
    }
}

/// Points (x, y, z) in the source's frame and unit.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PointCloud {
    pub points: Vec<[f32; 3]>,
}

impl PointCloud {
    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

/// One frame of one stream, with the stamps that latency is measured from.
#[derive(Debug, Clone)]
pub struct Frame {
    pub stream: String,
    pub sequence: u64,
    /// Sensor stamp (ns since the Unix epoch), when the source has one.
    pub sensor_stamp_ns: Option<u64>,
    pub ingested: Instant,
    /// Wall-clock ingest time (ns since the Unix epoch), published as the ingest stamp.
    pub ingest_unix_ns: u64,
    pub unit: Unit,
    pub cloud: PointCloud,
    /// The sensor's frame the points are in (a ROS message header's `frame_id`), when the input
    /// names one.
    pub sensor_frame: Option<std::sync::Arc<str>>,
}

/// Farthest a measured point can plausibly be (metres): no range sensor reports beyond this. A
/// coordinate past it (or not finite) comes from a corrupt or hostile input, and one such point
/// would set a bounding box or an outlier statistic for the whole frame.
pub const MAX_COORDINATE_M: f32 = 1.0e5;

/// Drops the points with a non-finite coordinate or one beyond [`MAX_COORDINATE_M`] (coordinates
/// in `unit`); returns how many were dropped.
pub fn drop_implausible(points: &mut Vec<[f32; 3]>, unit: Unit) -> usize {
    let limit = MAX_COORDINATE_M / unit.to_metres();
    // NaN fails the comparison; infinities exceed the limit.
    let plausible = |p: &[f32; 3]| p.iter().all(|c| c.abs() <= limit);
    // Nearly every frame has none: a read-only pass finds that at a fraction of retain's cost.
    if points.iter().all(plausible) {
        return 0;
    }
    let before = points.len();
    points.retain(plausible);
    before - points.len()
}
