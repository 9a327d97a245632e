//! Sources of frames, each feeding one stream: files and folders (`files`), recordings replayed
//! (`recording`: MCAP files and rosbag2 bags, read by `mcap` and `rosbag2`), zenoh subscriptions
//! (`zenoh`), ROS 2 topics by name over rmw_zenoh (`ros2_topic`); `ros2` decodes the ROS 2 messages
//! recordings and subscriptions carry.
//!
//! A source hands its frames to an `Outlet`, its own bounded channel into the pipeline. The outlet
//! applies the stream's policy: a live source never waits (when the pipeline is behind, the oldest
//! queued frame is dropped and counted); a replayed source waits, so nothing is lost. A frame the
//! source cannot decode becomes a counted `Rejection` naming the input and the reason.

pub mod files;
pub mod mcap;
pub mod recording;
pub mod ros2;
pub mod ros2_topic;
pub mod rosbag2;
mod settings;
pub mod zenoh;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crossbeam_channel::{Receiver, Sender, TrySendError};

use crate::cloud::{Frame, PointCloud, Unit};
use crate::stats::Stats;
pub use settings::{Input, SourceKind, SourceSettings};

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

/// The path itself when it is a file (which must exist), or the files of a folder whose extension
/// (case-insensitive) is one of `extensions`, sorted by name; possibly none.
pub fn file_or_folder(path: &std::path::Path, extensions: &[&str]) -> std::io::Result<Vec<std::path::PathBuf>> {
    if !path.is_dir() {
        std::fs::metadata(path)?;
        return Ok(vec![path.to_path_buf()]);
    }
    let mut files: Vec<_> = std::fs::read_dir(path)?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| extensions.contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    files.sort();
    Ok(files)
}

/// What a source checks before anything runs: that its files exist and hold what it reads (a
/// network source is checked when it subscribes). A line saying what it found, or why it cannot start.
pub fn check(source: &SourceSettings) -> Result<String, String> {
    match &source.input {
        Input::Files(own) => own.check(),
        Input::Mcap(own) => recording::check(own).map_err(|e| e.to_string()),
        Input::Zenoh(own) => Ok(format!("zenoh key {}", own.key)),
        Input::Ros2(own) => Ok(format!("ROS 2 topic {}", own.topic)),
    }
}

/// A started source: a thread of its own (files, recordings) or a subscription, open as long as
/// it is held (zenoh, ROS 2).
pub enum Running {
    Thread(std::thread::JoinHandle<()>),
    Subscription(Box<dyn std::any::Any + Send>),
}

/// What starting a source needs besides its settings.
pub struct StartContext<'a> {
    pub session: Option<&'a ::zenoh::Session>,
    /// The node in ROS 2 domains, and the domain a ROS 2 source uses unless it names one.
    pub participants: Option<&'a crate::ros2::Participants>,
    pub default_domain: u32,
    /// Where a source thread that stops with an error says so: (stream, reason, optional).
    pub errors: Arc<Mutex<Vec<(String, String, bool)>>>,
}

/// Starts a source feeding `outlet`: its module's one way in. Returns it running and a line for
/// the log; an error if it could not start.
pub fn start(source: &SourceSettings, outlet: Outlet, context: &StartContext) -> Result<(Running, String), String> {
    let no_session = || "no zenoh session".to_string();
    match &source.input {
        Input::Files(_) | Input::Mcap(_) => {
            let settings = source.clone();
            let errors = context.errors.clone();
            let handle = std::thread::Builder::new()
                .name(format!("source:{}", source.stream))
                .spawn(move || {
                    let stream = settings.stream.clone();
                    // A panic while decoding ends this source with a logged error; the other
                    // sources and the pipeline go on.
                    let result = crate::pipeline::contained(&format!("source '{stream}'"), || match &settings.input {
                        Input::Files(own) => files::run(&settings, own, outlet).map_err(|e| e.to_string()),
                        Input::Mcap(own) => recording::run(&settings, own, outlet).map_err(|e| e.to_string()),
                        _ => unreachable!("network sources subscribe"),
                    })
                    .and_then(|r| r);
                    match result {
                        Ok(()) => log::info!("source '{stream}': finished"),
                        Err(e) => {
                            log::error!("source '{stream}' stopped: {e}");
                            errors.lock().unwrap_or_else(|e| e.into_inner()).push((
                                stream,
                                format!("stopped: {e}"),
                                settings.optional,
                            ));
                        }
                    }
                })
                .map_err(|e| e.to_string())?;
            Ok((Running::Thread(handle), "started".into()))
        }
        Input::Zenoh(own) => {
            let session = context.session.ok_or_else(no_session)?;
            let subscriber = zenoh::subscribe(session, source, own, outlet).map_err(|e| e.to_string())?;
            Ok((
                Running::Subscription(Box::new(subscriber)),
                format!("zenoh subscription to {}", own.key),
            ))
        }
        Input::Ros2(own) => {
            let participants = context.participants.ok_or_else(no_session)?;
            let domain = own.domain_id.unwrap_or(context.default_domain);
            let participant = participants.join(domain).map_err(|e| e.to_string())?;
            let (topic, _) = ros2_topic::topics(&participant, own);
            let subscription = ros2_topic::subscribe(participant, source, own, outlet).map_err(|e| e.to_string())?;
            Ok((
                Running::Subscription(Box::new(subscription)),
                format!("ROS 2 topic {topic} in domain {domain}"),
            ))
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
        let frame = Frame {
            stream: self.stream.clone(),
            sequence: self.next_sequence(),
            sensor_stamp_ns,
            ingested: Instant::now(),
            ingest_unix_ns: unix_now_ns(),
            unit,
            cloud,
        };
        if dropped_non_finite > 0 {
            self.stats
                .stream(&self.stream)
                .add_non_finite(dropped_non_finite as u64);
        }
        self.send(Ingest::Frame(frame))
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
        self.send(Ingest::Rejected(rejection))
    }

    fn next_sequence(&mut self) -> u64 {
        let s = self.sequence;
        self.sequence += 1;
        let counters = self.stats.stream(&self.stream);
        counters.add_received();
        let now = Instant::now();
        if let (Some(gap), Some(last)) = (self.feed_gap, self.last_input) {
            let silent = now - last;
            if silent > gap {
                counters.add_feed_gap(silent);
                log::warn!(
                    "{}: the feed resumed after {:.1} s without input ({} gap(s) so far)",
                    self.stream,
                    silent.as_secs_f64(),
                    counters.feed_gaps()
                );
            }
        }
        self.last_input = Some(now);
        s
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

/// One replay source per input, named after its file stem (made unique): MCAP and rosbag2 files
/// and folders replay their point clouds, other files and folders are point-cloud files. `speed` as in
/// `[[source]] speed` (0 = as fast as possible).
pub fn replay_sources(inputs: &[std::path::PathBuf], speed: f64) -> Vec<SourceSettings> {
    let mut sources: Vec<SourceSettings> = Vec::new();
    for input in inputs {
        let stem = input
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("input")
            .replace(|c: char| !(c.is_ascii_alphanumeric() || c == '-' || c == '_'), "_");
        let mut stream = stem.clone();
        let mut n = 1;
        while sources.iter().any(|s| s.stream == stream) {
            n += 1;
            stream = format!("{stem}_{n}");
        }
        let input = if recording::is_recording(input) {
            Input::Mcap(recording::RecordingSettings::replay(input.clone(), speed))
        } else {
            // Files have no timing of their own: as fast as possible.
            Input::Files(files::FilesSettings {
                path: input.clone(),
                rate_hz: 0.0,
                repeat: false,
            })
        };
        sources.push(SourceSettings::new(stream, input));
    }
    sources
}
