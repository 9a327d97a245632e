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
}
