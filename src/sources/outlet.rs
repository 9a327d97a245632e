//! What a source hands its frames to: its `Outlet` (a bounded channel into the pipeline with the
//! stream's policy: a live source never waits, a replayed one does), the `Ingest` items it sends,
//! a `Rejection` for a frame it could not decode, and the `Intake` limits every source applies. A
//! leaf, so that each source reads only this and its own settings.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use crossbeam_channel::{Receiver, Sender, TrySendError};

use crate::cloud::{Frame, PointCloud, Unit};
use crate::stats::Stats;

/// What every source applies to its frames, from its `[[source]]`'s common keys: the largest frame
/// accepted (points; bigger ones are rejected before they are decoded) and the unit of the
/// coordinates when the source sets it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intake {
    pub max_points: usize,
    pub unit: Option<Unit>,
}

/// A frame that will not reach the encoder, and why.
#[derive(Debug, Clone)]
pub struct Rejection {
    pub stream: String,
    pub sequence: u64,
    pub stage: &'static str,
    pub reason: String,
    pub sensor_stamp_ns: Option<u64>,
    pub ingested: Instant,
    pub ingest_unix_ns: u64,
}

/// What sources send into the pipeline.
#[derive(Debug)]
pub enum Ingest {
    Frame(Frame),
    Rejected(Rejection),
}

impl Ingest {
    pub fn stream(&self) -> &str {
        match self {
            Ingest::Frame(f) => &f.stream,
            Ingest::Rejected(r) => &r.stream,
        }
    }
}

pub fn unix_now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

/// One source's entry into the pipeline.
pub struct Outlet {
    stream: String,
    live: bool,
    sender: Sender<Ingest>,
    /// Held by live outlets only, to drop the oldest queued frame.
    oldest: Option<Receiver<Ingest>>,
    sequence: u64,
    stats: Arc<Stats>,
    stop: Arc<AtomicBool>,
    /// Live outlets: silence longer than this, then an input, counts as a gap in the feed.
    feed_gap: Option<std::time::Duration>,
    last_input: Option<Instant>,
    /// The source thread's CPU between frames: reading, decompressing and decoding them.
    decode_cpu: crate::cpu::BetweenCalls,
    /// The sensor frame the input last named (shared by its frames until it names another).
    sensor_frame: Option<Arc<str>>,
}

impl Outlet {
    /// A channel of `capacity` for one stream: the outlet, and the receiving end for the pipeline.
    pub fn new(
        stream: &str,
        live: bool,
        capacity: usize,
        stats: Arc<Stats>,
        stop: Arc<AtomicBool>,
    ) -> (Self, Receiver<Ingest>) {
        let (sender, receiver) = crossbeam_channel::bounded(capacity.max(1));
        let outlet = Self {
            stream: stream.to_string(),
            live,
            sender,
            oldest: live.then(|| receiver.clone()),
            sequence: 0,
            stats,
            stop,
            feed_gap: None,
            last_input: None,
            decode_cpu: Default::default(),
            sensor_frame: None,
        };
        (outlet, receiver)
    }

    /// Counts (and logs) every time this live feed resumes after more than `gap` without input.
    pub fn with_feed_gap(mut self, gap: std::time::Duration) -> Self {
        self.feed_gap = (self.live && !gap.is_zero()).then_some(gap);
        self
    }

    pub fn stream(&self) -> &str {
        &self.stream
    }

    pub fn stopping(&self) -> bool {
        self.stop.load(Ordering::Relaxed)
    }

    /// Waits until `due` (a paced replay's next frame) in short slices, so that a stop request is
    /// seen within 50 ms however long the gap in the recording. Returns false if stopping.
    pub fn wait_until(&self, due: Instant) -> bool {
        const SLICE: std::time::Duration = std::time::Duration::from_millis(50);
        loop {
            if self.stopping() {
                return false;
            }
            let left = due.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return true;
            }
            std::thread::sleep(left.min(SLICE));
        }
    }

    /// Sends a decoded frame. Returns false when the pipeline has shut down. Points that are not
    /// finite or lie implausibly far are dropped here, for every source, and counted with those the
    /// decoder already dropped (`dropped_non_finite`).
    pub fn frame(
        &mut self,
        mut cloud: PointCloud,
        unit: Unit,
        sensor_stamp_ns: Option<u64>,
        dropped_non_finite: usize,
    ) -> bool {
        let dropped_non_finite = dropped_non_finite + crate::cloud::drop_implausible(&mut cloud.points, unit);
        self.note_frame();
        let frame = Frame {
            stream: self.stream.clone(),
            sequence: self.next_sequence(),
            sensor_stamp_ns,
            ingested: Instant::now(),
            ingest_unix_ns: unix_now_ns(),
            unit,
            cloud,
            sensor_frame: self.sensor_frame.clone(),
        };
        if dropped_non_finite > 0 {
            self.stats
                .stream(&self.stream)
                .add_non_finite(dropped_non_finite as u64);
        }
        self.stats.add_cpu(&[("decode", self.decode_cpu.lap())]);
        self.send(Ingest::Frame(frame))
    }

    /// The sensor frame the next frames' points are in (a ROS header's `frame_id`; empty: none).
    pub fn sensor_frame(&mut self, frame_id: &str) {
        if self.sensor_frame.as_deref() != Some(frame_id) {
            self.sensor_frame = (!frame_id.is_empty()).then(|| Arc::from(frame_id));
        }
    }

    /// Sends a rejection of an input the source could not decode (logged and counted downstream).
    pub fn reject(&mut self, reason: String, sensor_stamp_ns: Option<u64>) -> bool {
        let rejection = Rejection {
            stream: self.stream.clone(),
            sequence: self.next_sequence(),
            stage: "source",
            reason,
            sensor_stamp_ns,
            ingested: Instant::now(),
            ingest_unix_ns: unix_now_ns(),
        };
        self.stats.add_cpu(&[("decode", self.decode_cpu.lap())]);
        self.send(Ingest::Rejected(rejection))
    }

    /// The next sequence number: every input takes one, a rejected one too (a gap in the states'
    /// numbers is a rejection, published with that number).
    fn next_sequence(&mut self) -> u64 {
        let s = self.sequence;
        self.sequence += 1;
        self.stats.stream(&self.stream).add_received();
        s
    }

    /// Notes a usable frame: after a silence longer than `feed_gap`, the feed has resumed (inputs
    /// that are rejected do not resume it: a wrong-type sample after a pause is only a rejection).
    fn note_frame(&mut self) {
        let now = Instant::now();
        if let (Some(gap), Some(last)) = (self.feed_gap, self.last_input) {
            let silent = now - last;
            if silent > gap {
                let counters = self.stats.stream(&self.stream);
                counters.add_feed_gap(silent);
                log::warn!(
                    "{}: the feed resumed after {:.1} s without a usable frame ({} gap(s) so far)",
                    self.stream,
                    silent.as_secs_f64(),
                    counters.feed_gaps()
                );
            }
        }
        self.last_input = Some(now);
    }

    fn send(&self, item: Ingest) -> bool {
        if !self.live {
            return self.sender.send(item).is_ok();
        }
        let mut item = item;
        loop {
            match self.sender.try_send(item) {
                Ok(()) => return true,
                Err(TrySendError::Disconnected(_)) => return false,
                Err(TrySendError::Full(back)) => {
                    item = back;
                    if let Some(Ok(dropped)) = self.oldest.as_ref().map(Receiver::try_recv) {
                        let stream = self.stats.stream(&self.stream);
                        stream.add_dropped();
                        if stream.dropped() == 1 || stream.dropped() % 100 == 0 {
                            log::warn!(
                                "{}: pipeline behind, dropped the oldest queued frame ({} dropped so far)",
                                dropped.stream(),
                                stream.dropped()
                            );
                        }
                    }
                }
            }
        }
    }
}
