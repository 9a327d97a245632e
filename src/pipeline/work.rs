//! What travels between the stages: a frame's origin (stream, sequence, stamps) from ingest to
//! publish, the prepared and encoded frames, and the ticket each item carries so that `track` can
//! restore the order the pools may change.

use std::time::Instant;

use crate::encoding::Encoding;
use crate::prepare::Prepared;
use crate::sources::Rejection;

/// Metadata that travels with a frame from ingest to publish.
#[derive(Debug, Clone)]
pub(super) struct Origin {
    pub(super) stream: String,
    pub(super) sequence: u64,
    pub(super) sensor_stamp_ns: Option<u64>,
    pub(super) ingested: Instant,
    pub(super) ingest_unix_ns: u64,
    pub(super) points_received: usize,
    pub(super) sensor_frame: Option<std::sync::Arc<str>>,
}

/// A frame's candidate objects, prepared: one (the largest cluster) unless `[track.objects]` is
/// enabled.
pub(super) struct PreparedFrame {
    pub(super) origin: Origin,
    pub(super) objects: Vec<Prepared>,
    pub(super) prepare_ms: f32,
    pub(super) prepared_at: Instant,
}

pub(super) struct EncodedFrame {
    pub(super) origin: Origin,
    /// Each candidate object with its encoding, in the order prepare found them.
    pub(super) objects: Vec<(Prepared, Encoding)>,
    pub(super) prepare_ms: f32,
    pub(super) queue_ms: f32,
    pub(super) encode_ms: f32,
}

pub(super) enum Work {
    Frame(PreparedFrame),
    Rejected(Rejection),
}

pub(super) enum Done {
    Encoded(Box<EncodedFrame>),
    Rejected(Rejection),
}

pub(super) type Ticketed<T> = (u64, T);

pub(super) fn ms_since(start: Instant) -> f32 {
    start.elapsed().as_secs_f32() * 1000.0
}

impl Origin {
    pub(super) fn reject(self, stage: &'static str, reason: String) -> Rejection {
        Rejection {
            stream: self.stream,
            sequence: self.sequence,
            stage,
            reason,
            sensor_stamp_ns: self.sensor_stamp_ns,
            ingested: self.ingested,
            ingest_unix_ns: self.ingest_unix_ns,
        }
    }
}

pub(super) fn origin_of(frame: &crate::cloud::Frame) -> Origin {
    Origin {
        stream: frame.stream.clone(),
        sequence: frame.sequence,
        sensor_stamp_ns: frame.sensor_stamp_ns,
        ingested: frame.ingested,
        ingest_unix_ns: frame.ingest_unix_ns,
        points_received: frame.cloud.len(),
        sensor_frame: frame.sensor_frame.clone(),
    }
}
