//! Counters and latencies: per stream (received, dropped, rejected by reason, published) and per
//! stage (frames and latency percentiles). Shared by every stage; read by the status queryable,
//! the periodic log summary and the replay benchmark's report.
//!
//! Counters are atomics; each latency recorder sits behind its own mutex that only its stage and
//! the (rare) readers take, so the pipeline's channels stay the only hand-off between stages.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use serde::Serialize;

/// The stages whose latency is recorded, in pipeline order; `end_to_end` is ingest to publish.
pub const STAGES: [&str; 6] = ["prepare", "queue", "encode", "track", "publish", "end_to_end"];

/// Keeps the last `CAPACITY` samples (percentiles over recent frames) and totals over all.
#[derive(Debug, Clone, Default)]
pub struct Latencies {
    samples: Vec<f32>,
    next: usize,
    count: u64,
    sum_ms: f64,
    max_ms: f32,
}

const CAPACITY: usize = 1 << 16;

impl Latencies {
    pub fn record(&mut self, ms: f32) {
        if self.samples.len() < CAPACITY {
            self.samples.push(ms);
        } else {
            self.samples[self.next] = ms;
            self.next = (self.next + 1) % CAPACITY;
        }
        self.count += 1;
        self.sum_ms += ms as f64;
        self.max_ms = self.max_ms.max(ms);
    }

    pub fn summary(&self) -> LatencySummary {
        let mut sorted = self.samples.clone();
        sorted.sort_by(f32::total_cmp);
        let at = |q: f64| {
            if sorted.is_empty() {
                0.0
            } else {
                sorted[((sorted.len() - 1) as f64 * q).round() as usize]
            }
        };
        LatencySummary {
            count: self.count,
            mean_ms: if self.count > 0 {
                (self.sum_ms / self.count as f64) as f32
            } else {
                0.0
            },
            p50_ms: at(0.5),
            p90_ms: at(0.9),
            p99_ms: at(0.99),
            max_ms: self.max_ms,
        }
    }
}

#[derive(Debug, Clone, Copy, Serialize)]
pub struct LatencySummary {
    pub count: u64,
    pub mean_ms: f32,
    pub p50_ms: f32,
    pub p90_ms: f32,
    pub p99_ms: f32,
    pub max_ms: f32,
}

#[derive(Debug, Default)]
pub struct StreamCounters {
    received: AtomicU64,
    dropped: AtomicU64,
    non_finite_points: AtomicU64,
    published: AtomicU64,
    published_unconnected: AtomicU64,
    publish_errors: AtomicU64,
    feed_gaps: AtomicU64,
    feed_gap_ms: AtomicU64,
    rejected: Mutex<BTreeMap<String, u64>>,
    tracks_born: AtomicU64,
    tracks_reidentified: AtomicU64,
    tracks_ended: AtomicU64,
    untracked: AtomicU64,
}

impl StreamCounters {
    pub fn add_received(&self) {
        self.received.fetch_add(1, Ordering::Relaxed);
    }
    pub fn add_dropped(&self) {
        self.dropped.fetch_add(1, Ordering::Relaxed);
    }
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
    pub fn add_non_finite(&self, points: u64) {
        self.non_finite_points.fetch_add(points, Ordering::Relaxed);
    }
    pub fn add_published(&self) {
        self.published.fetch_add(1, Ordering::Relaxed);
    }
    /// A state put on zenoh while the node had no connection to the routers or peers it was told
    /// to connect to: it reached nobody there.
    pub fn add_published_unconnected(&self) {
        self.published_unconnected.fetch_add(1, Ordering::Relaxed);
    }
    /// A live feed that was silent for longer than `[pipeline] feed_gap_s` and came back.
    pub fn add_feed_gap(&self, silent: std::time::Duration) {
        self.feed_gaps.fetch_add(1, Ordering::Relaxed);
        self.feed_gap_ms.fetch_add(silent.as_millis() as u64, Ordering::Relaxed);
    }
    pub fn feed_gaps(&self) -> u64 {
        self.feed_gaps.load(Ordering::Relaxed)
    }
    pub fn add_publish_error(&self) {
        self.publish_errors.fetch_add(1, Ordering::Relaxed);
    }
    pub fn publish_errors(&self) -> u64 {
        self.publish_errors.load(Ordering::Relaxed)
    }
    /// A track born, re-identified or ended (`[track.objects] enabled`).
    pub fn add_track_event(&self, event: &crate::track::association::TrackEvent) {
        use crate::track::association::TrackEvent;
        let counter = match event {
            TrackEvent::Born { .. } => &self.tracks_born,
            TrackEvent::Reidentified { .. } => &self.tracks_reidentified,
            TrackEvent::Ended { .. } => &self.tracks_ended,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }
    /// A frame whose candidates all belonged to tentative tracks: encoded, no state published.
    pub fn add_untracked(&self) {
        self.untracked.fetch_add(1, Ordering::Relaxed);
    }
    pub fn add_rejected(&self, stage: &str) {
        *self
            .rejected
            .lock()
            .expect("counter lock")
            .entry(stage.to_string())
            .or_default() += 1;
    }
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct StreamSnapshot {
    pub received: u64,
    pub dropped: u64,
    pub rejected: BTreeMap<String, u64>,
    pub published: u64,
    /// Of those, states put on zenoh while none of the configured `connect` endpoints was
    /// connected (a router outage): nobody behind them received these.
    pub published_unconnected: u64,
    /// Outputs the sinks failed to send (logged).
    pub publish_errors: u64,
    pub non_finite_points: u64,
    /// Times a live feed fell silent for longer than `[pipeline] feed_gap_s` and resumed, and the
    /// seconds it was silent in all.
    pub feed_gaps: u64,
    pub feed_gap_s: f64,
    /// With `[track.objects] enabled`: tracks born, re-identified and ended, and frames encoded
    /// whose candidates all belonged to tentative tracks (no state published for them).
    pub tracks_born: u64,
    pub tracks_reidentified: u64,
    pub tracks_ended: u64,
    pub frames_untracked: u64,
}

#[derive(Debug, Default)]
pub struct Stats {
    streams: Mutex<BTreeMap<String, Arc<StreamCounters>>>,
    stages: Mutex<BTreeMap<&'static str, Latencies>>,
    batches: AtomicU64,
    batched_frames: AtomicU64,
    cpu: Mutex<BTreeMap<&'static str, CpuAccount>>,
}

/// CPU time one stage (or prepare step) spent, over all the items it handled.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq)]
pub struct CpuAccount {
    pub ns: u64,
    pub items: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct Snapshot {
    pub streams: BTreeMap<String, StreamSnapshot>,
    pub stages: BTreeMap<String, LatencySummary>,
    pub batches: u64,
    pub mean_batch: f64,
    /// CPU time per stage and prepare step (`decode`, `prepare.<step>`, `track`, `publish`), from
    /// the threads' own clocks.
    pub cpu: BTreeMap<String, CpuAccount>,
}

impl Stats {
    pub fn stream(&self, name: &str) -> Arc<StreamCounters> {
        let mut streams = self.streams.lock().expect("stats lock");
        streams.entry(name.to_string()).or_default().clone()
    }

    pub fn record(&self, stage: &'static str, ms: f32) {
        self.stages
            .lock()
            .expect("stats lock")
            .entry(stage)
            .or_default()
            .record(ms);
    }

    /// Adds CPU time to stages' accounts, each entry one item (a frame or a rejection).
    pub fn add_cpu(&self, spent: &[(&'static str, u64)]) {
        let mut cpu = self.cpu.lock().expect("stats lock");
        for (stage, ns) in spent {
            let account = cpu.entry(stage).or_default();
            account.ns += ns;
            account.items += 1;
        }
    }

    pub fn record_batch(&self, frames: usize) {
        self.batches.fetch_add(1, Ordering::Relaxed);
        self.batched_frames.fetch_add(frames as u64, Ordering::Relaxed);
    }

    pub fn snapshot(&self) -> Snapshot {
        let streams = self
            .streams
            .lock()
            .expect("stats lock")
            .iter()
            .map(|(name, c)| {
                (
                    name.clone(),
                    StreamSnapshot {
                        received: c.received.load(Ordering::Relaxed),
                        dropped: c.dropped.load(Ordering::Relaxed),
                        rejected: c.rejected.lock().expect("counter lock").clone(),
                        published: c.published.load(Ordering::Relaxed),
                        published_unconnected: c.published_unconnected.load(Ordering::Relaxed),
                        publish_errors: c.publish_errors.load(Ordering::Relaxed),
                        non_finite_points: c.non_finite_points.load(Ordering::Relaxed),
                        feed_gaps: c.feed_gaps.load(Ordering::Relaxed),
                        feed_gap_s: c.feed_gap_ms.load(Ordering::Relaxed) as f64 / 1000.0,
                        tracks_born: c.tracks_born.load(Ordering::Relaxed),
                        tracks_reidentified: c.tracks_reidentified.load(Ordering::Relaxed),
                        tracks_ended: c.tracks_ended.load(Ordering::Relaxed),
                        frames_untracked: c.untracked.load(Ordering::Relaxed),
                    },
                )
            })
            .collect();
        let stages = self
            .stages
            .lock()
            .expect("stats lock")
            .iter()
            .map(|(k, v)| (k.to_string(), v.summary()))
            .collect();
        let batches = self.batches.load(Ordering::Relaxed);
        let frames = self.batched_frames.load(Ordering::Relaxed);
        let cpu = self
            .cpu
            .lock()
            .expect("stats lock")
            .iter()
            .map(|(k, v)| (k.to_string(), *v))
            .collect();
        Snapshot {
            streams,
            stages,
            cpu,
            batches,
            mean_batch: if batches > 0 {
                frames as f64 / batches as f64
            } else {
                0.0
            },
        }
    }
}

/// CPU time the hypervisor took from this machine's virtual CPUs so far ("steal" in
/// `/proc/stat`, all CPUs together), in seconds; None off Linux or on a kernel without the field.
/// A benchmark reads it before and after: latency tails measured while the host steals time say
/// more about the neighbours than about the node. `/proc/stat` counts in USER_HZ, which Linux
/// fixes at 100 on every architecture it exports this file for.
pub fn cpu_steal_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    parse_cpu_steal(&stat)
}

/// The steal seconds of `/proc/stat`'s aggregate `cpu` line (its eighth value).
pub fn parse_cpu_steal(stat: &str) -> Option<f64> {
    let line = stat.lines().find(|l| l.starts_with("cpu "))?;
    let ticks: u64 = line.split_whitespace().nth(8)?.parse().ok()?;
    Some(ticks as f64 / 100.0)
}

/// Peak resident memory of this process (VmHWM), in MiB; None off Linux.
pub fn peak_memory_mib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}
