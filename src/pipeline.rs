//! The pipeline: a thread per stage, joined by bounded crossbeam channels.
//!
//! ```text
//! sources ─(one channel each)─> ingest ─> prepare ×P ─> batcher ─> encode ×W ─> track ─> publish
//! ```
//! - `ingest` is the only reader of the sources' channels; it gives every item (frame or
//!   rejection) a ticket. Items may overtake each other in the prepare and encode pools; `track`
//!   puts them back in ticket order, so each stream is tracked and published in order.
//! - Live sources drop their oldest frame when the pipeline is behind (see `sources::Outlet`);
//!   replayed sources wait. From ingest on, nothing is dropped: every ticket ends as one published
//!   state or one published, logged and counted rejection.
//! - Stop (SIGINT/SIGTERM, or the end of every replayed source) drains: sources stop producing,
//!   each stage finishes what it holds and closes its output, and `run` returns when the publisher
//!   has sent the last item.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{bounded, Receiver, Select, Sender};
use zenoh::{Session, Wait};

use crate::bundle::Bundle;
use crate::config::Config;
use crate::prepare::{Prepared, Preparer};
use crate::publish::Publisher;
use crate::runtime::{Encoder, Encoding};
use crate::sources::{self, unix_now_ns, Ingest, Outlet, Rejection};
use crate::state::{self, Output, State};
use crate::stats::{Snapshot, Stats};
use crate::track::{confidence_from_log_variance, StreamTracker};

#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Runtime(#[from] crate::runtime::RuntimeError),
    #[error(transparent)]
    Publish(#[from] crate::publish::PublishError),
    #[error("zenoh source '{stream}': {message}")]
    Subscribe { stream: String, message: String },
    #[error("source '{stream}' {message}")]
    Source { stream: String, message: String },
    #[error("no source could start: {0}")]
    NoSource(String),
    #[error("{0}")]
    Thread(String),
}

/// How a run behaves beyond its config.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// Publish with blocking congestion control (replay benchmarks and tests: nothing lost).
    pub lossless_publish: bool,
    /// Also hand every published message to this channel, in publish order (`evaluate` reads the
    /// states here instead of from the network). Unbounded on purpose: whoever asks for it keeps up.
    pub collect: Option<crossbeam_channel::Sender<Output>>,
}

#[derive(Debug, Clone)]
pub struct RunSummary {
    /// Optional sources that could not start or failed, and why (required ones fail the run).
    pub failed_sources: Vec<(String, String)>,
    /// From the start of `run` (loading encoders included) to the last publish.
    pub wall: Duration,
    /// From the first frame's ingest to the last publish: what throughput is measured over.
    pub busy: Duration,
    pub snapshot: Snapshot,
}

/// Metadata that travels with a frame from ingest to publish.
#[derive(Debug, Clone)]
struct Origin {
    stream: String,
    sequence: u64,
    sensor_stamp_ns: Option<u64>,
    ingested: Instant,
    ingest_unix_ns: u64,
    points_received: usize,
}

struct PreparedFrame {
    origin: Origin,
    prepared: Prepared,
    prepare_ms: f32,
    prepared_at: Instant,
}

struct EncodedFrame {
    origin: Origin,
    prepared: Prepared,
    encoding: Encoding,
    prepare_ms: f32,
    queue_ms: f32,
    encode_ms: f32,
}

enum Work {
    Frame(PreparedFrame),
    Rejected(Rejection),
}

enum Done {
    Encoded(Box<EncodedFrame>),
    Rejected(Rejection),
}

type Ticketed<T> = (u64, T);

fn ms_since(start: Instant) -> f32 {
    start.elapsed().as_secs_f32() * 1000.0
}

/// Runs the pipeline until every source has ended (replay) or `stop` is set (daemon), then drains.
pub fn run(
    config: &Config,
    bundle: &Bundle,
    session: Option<Session>,
    stop: Arc<AtomicBool>,
    stats: Arc<Stats>,
    options: RunOptions,
) -> Result<RunSummary, PipelineError> {
    let started = Instant::now();
    let queue = config.pipeline.queue;
    let m = &config.model;

    // Every source is checked before anything runs: a required one that cannot start fails the
    // run here; an optional one is left out, logged and listed in the summary.
    let mut failed_sources = Vec::new();
    let mut starting = Vec::new();
    for source in &config.sources {
        match sources::check(source) {
            Ok(found) => {
                log::info!("source '{}': {found}", source.stream);
                starting.push(source);
            }
            Err(message) if source.optional => {
                log::error!(
                    "optional source '{}' cannot start, running without it: {message}",
                    source.stream
                );
                failed_sources.push((source.stream.clone(), format!("cannot start: {message}")));
            }
            Err(message) => {
                return Err(PipelineError::Source {
                    stream: source.stream.clone(),
                    message: format!("cannot start: {message}"),
                })
            }
        }
    }
    if starting.is_empty() {
        let reasons: Vec<String> = failed_sources.iter().map(|(s, m)| format!("'{s}' {m}")).collect();
        return Err(PipelineError::NoSource(reasons.join("; ")));
    }

    // Encoders first: a bundle or runtime problem fails before any source starts.
    let mut encoders = Vec::new();
    for _ in 0..m.workers {
        encoders.push(Encoder::load(bundle, m.onnxruntime.as_deref(), m.threads, m.spin)?);
    }
    let preparer = Arc::new(
        Preparer::new(
            &config.prepare,
            bundle.manifest.sizes.points,
            bundle.manifest.units.model_units_per_metre as f32,
        )
        .with_sources(&config.sources),
    );

    // Sources, subscriptions first: if one fails, no source thread has started yet.
    let mut threads: Vec<(String, JoinHandle<()>)> = Vec::new();
    let mut source_channels: Vec<(bool, Receiver<Ingest>)> = Vec::new();
    let mut subscribers: Vec<Box<dyn std::any::Any + Send>> = Vec::new();
    // The node in ROS 2 domains, for ROS 2 sources and the ROS 2 sink alike.
    let participants = session
        .as_ref()
        .map(|s| crate::ros2::Participants::new(s.clone(), &config.publish.ros2));
    let context = sources::StartContext {
        session: session.as_ref(),
        participants: participants.as_ref(),
        default_domain: config.publish.ros2.domain_id,
        errors: Arc::default(),
    };
    let mut ordered = starting;
    ordered.sort_by_key(|s| !s.is_subscription());
    for source in ordered {
        let live = source.is_live();
        let (outlet, receiver) = Outlet::new(&source.stream, live, queue, stats.clone(), stop.clone());
        source_channels.push((live, receiver));
        stats.stream(&source.stream);
        match sources::start(source, outlet, &context) {
            Ok((running, what)) => {
                log::info!("source '{}': {what}", source.stream);
                match running {
                    sources::Running::Thread(handle) => threads.push((format!("source:{}", source.stream), handle)),
                    sources::Running::Subscription(subscription) => subscribers.push(subscription),
                }
            }
            Err(e) if source.optional => {
                log::error!(
                    "optional source '{}' cannot start, running without it: {e}",
                    source.stream
                );
                failed_sources.push((source.stream.clone(), format!("cannot start: {e}")));
            }
            Err(message) => {
                return Err(PipelineError::Source {
                    stream: source.stream.clone(),
                    message: format!("cannot start: {message}"),
                })
            }
        }
    }
    let source_errors = context.errors.clone();

    let (prepare_tx, prepare_rx) = bounded::<Ticketed<Ingest>>(queue);
    let (work_tx, work_rx) = bounded::<Ticketed<Work>>(queue);
    let (batch_tx, batch_rx) = bounded::<Vec<Ticketed<PreparedFrame>>>(m.workers * 2);
    let (done_tx, done_rx) = bounded::<Ticketed<Done>>(queue * 2);
    let (publish_tx, publish_rx) = bounded::<(Output, Instant, Instant)>(queue);
    let queues = Arc::new(Queues {
        channels: std::sync::Mutex::new(vec![
            ("prepare", depth_of(&prepare_rx)),
            ("batch", depth_of(&work_rx)),
            ("encode", depth_of(&batch_rx)),
            ("track", depth_of(&done_rx)),
            ("publish", depth_of(&publish_rx)),
        ]),
    });
    let failed: Arc<std::sync::Mutex<Vec<String>>> = Arc::default();

    let spawn = |name: String, body: Box<dyn FnOnce() + Send>| {
        let guard = StageGuard {
            name: name.clone(),
            stop: stop.clone(),
            queues: queues.clone(),
            failed: failed.clone(),
        };
        std::thread::Builder::new()
            .name(name.clone())
            .spawn(move || {
                let _guard = guard;
                body()
            })
            .map(|h| (name, h))
            .map_err(|e| PipelineError::Thread(e.to_string()))
    };

    let first_ingest = Arc::new(std::sync::OnceLock::new());
    {
        let stop = stop.clone();
        let first = first_ingest.clone();
        threads.push(spawn(
            "ingest".into(),
            Box::new(move || ingest(source_channels, prepare_tx, &stop, &first)),
        )?);
    }
    for worker in 0..config.pipeline.prepare_workers {
        let (rx, tx, preparer, stats) = (prepare_rx.clone(), work_tx.clone(), preparer.clone(), stats.clone());
        threads.push(spawn(
            format!("prepare:{worker}"),
            Box::new(move || prepare(rx, tx, &preparer, &stats)),
        )?);
    }
    drop((prepare_rx, work_tx));
    {
        let (max_batch, max_wait) = (m.max_batch, Duration::from_secs_f64(m.max_wait_ms / 1000.0));
        let (done_tx, stats) = (done_tx.clone(), stats.clone());
        threads.push(spawn(
            "batcher".into(),
            Box::new(move || batcher(work_rx, batch_tx, done_tx, max_batch, max_wait, &stats)),
        )?);
    }
    for (worker, encoder) in encoders.into_iter().enumerate() {
        let (rx, tx, stats) = (batch_rx.clone(), done_tx.clone(), stats.clone());
        threads.push(spawn(
            format!("encode:{worker}"),
            Box::new(move || encode(rx, tx, encoder, &stats)),
        )?);
    }
    drop((batch_rx, done_tx));
    {
        let (config, stats) = (config.clone(), stats.clone());
        threads.push(spawn(
            "track".into(),
            Box::new(move || track(done_rx, publish_tx, &config, &stats)),
        )?);
    }
    let mut publisher = Publisher::new(
        config,
        bundle,
        session.clone(),
        participants.as_ref(),
        options.lossless_publish,
    )?;

    // Node-level zenoh presence: a liveliness token and the status queryable.
    let mut presence = None;
    if let Some(session) = &session {
        let token = session
            .liveliness()
            .declare_token(config.liveliness_key())
            .wait()
            .map_err(|e| PipelineError::Publish(crate::publish::PublishError::Zenoh(e.to_string())))?;
        let status = status_queryable(session, config, bundle, stats.clone(), queues.clone(), started)?;
        presence = Some((token, status));
    }

    // The summary logger runs until the publisher is done.
    let finished = Arc::new(AtomicBool::new(false));
    let logger = {
        let (finished, stats, seconds) = (finished.clone(), stats.clone(), config.pipeline.summary_seconds);
        std::thread::spawn(move || summary_logger(&finished, &stats, seconds))
    };

    // Publish on this thread. Zenoh subscriptions end when stop is set.
    let mut subscribers = Some(subscribers);
    let mut connection = crate::publish::ConnectionWatch::new(config, session.as_ref());
    loop {
        match publish_rx.recv_timeout(Duration::from_millis(50)) {
            Ok((mut output, tracked_at, ingested)) => {
                let stream = match &mut output {
                    Output::State(state) => {
                        // Stamped here, so that `total_ms` is ingest to publish.
                        state.stamps.publish_ns = unix_now_ns();
                        state.latency.total_ms = ms_since(ingested);
                        state.stream.clone()
                    }
                    Output::Rejected(r) => {
                        r.stamps.publish_ns = unix_now_ns();
                        r.stream.clone()
                    }
                };
                stats.record("publish", ms_since(tracked_at));
                let counters = stats.stream(&stream);
                match publisher.publish(&output) {
                    Ok(()) if matches!(output, Output::State(_)) => {
                        stats.record("end_to_end", ms_since(ingested));
                        counters.add_published();
                        if connection.as_mut().is_some_and(|c| !c.connected()) {
                            counters.add_published_unconnected();
                        }
                    }
                    Ok(()) => {}
                    Err(e) => {
                        counters.add_publish_error();
                        let n = counters.publish_errors();
                        if n <= 10 || n % 100 == 0 {
                            log::error!("publishing on stream '{stream}' failed ({n} so far): {e}");
                        }
                    }
                }
                if let Some(collect) = &options.collect {
                    let _ = collect.send(output);
                }
            }
            Err(crossbeam_channel::RecvTimeoutError::Timeout) => {}
            Err(crossbeam_channel::RecvTimeoutError::Disconnected) => break,
        }
        if stop.load(Ordering::Relaxed) {
            subscribers.take();
        }
    }
    // A sink that failed during the run fails the run, after the stages have wound down.
    let flushed = publisher.flush();
    drop(presence);
    finished.store(true, Ordering::Relaxed);
    for (name, handle) in threads {
        if handle.join().is_err() {
            log::error!("thread {name} panicked");
        }
    }
    let _ = logger.join();
    let failed = std::mem::take(&mut *failed.lock().unwrap_or_else(|e| e.into_inner()));
    if !failed.is_empty() {
        return Err(PipelineError::Thread(format!(
            "stage thread(s) {} died; what they held was lost",
            failed.join(", ")
        )));
    }
    flushed?;
    let last_publish = Instant::now();
    for (stream, message, optional) in std::mem::take(&mut *source_errors.lock().unwrap_or_else(|e| e.into_inner())) {
        if !optional {
            return Err(PipelineError::Source { stream, message });
        }
        failed_sources.push((stream, message));
    }
    Ok(RunSummary {
        failed_sources,
        wall: started.elapsed(),
        busy: first_ingest.get().map(|f| last_publish - *f).unwrap_or_default(),
        snapshot: stats.snapshot(),
    })
}

type Depth = Box<dyn Fn() -> usize + Send + Sync>;

/// How many items wait in a channel, read by the status queryable.
fn depth_of<T: Send + 'static>(receiver: &Receiver<T>) -> Depth {
    let receiver = receiver.clone();
    Box::new(move || receiver.len())
}

/// The queue-depth observers of the status reply. Each holds a receiver of its channel, which
/// would keep the channel open after its stage died: `release` drops them all.
struct Queues {
    channels: std::sync::Mutex<Vec<(&'static str, Depth)>>,
}

impl Queues {
    fn depths(&self) -> BTreeMap<&'static str, usize> {
        let channels = self.channels.lock().unwrap_or_else(|e| e.into_inner());
        channels.iter().map(|(name, len)| (*name, len())).collect()
    }

    fn release(&self) {
        self.channels.lock().unwrap_or_else(|e| e.into_inner()).clear();
    }
}

/// The message of a caught panic.
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}

/// Runs one frame's work; a panic in it becomes an error naming the stage (the stage goes on
/// with the next frame, and the frame is a counted rejection).
pub(crate) fn contained<T>(stage: &str, work: impl FnOnce() -> T) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(work)).map_err(|payload| {
        let message = format!("internal error in {stage}: {}", panic_message(payload.as_ref()));
        log::error!("{message}");
        message
    })
}

/// Held by every stage thread: if the thread dies by a panic that per-frame containment did not
/// catch, the run is stopped (sources end, every stage drains) and the queue observers let go of
/// their channels, so no stage waits for ever on a channel only they kept open.
struct StageGuard {
    name: String,
    stop: Arc<AtomicBool>,
    queues: Arc<Queues>,
    failed: Arc<std::sync::Mutex<Vec<String>>>,
}

impl Drop for StageGuard {
    fn drop(&mut self) {
        if std::thread::panicking() {
            log::error!("stage thread {} died; stopping the node", self.name);
            self.failed
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(self.name.clone());
            self.stop.store(true, Ordering::SeqCst);
            self.queues.release();
        }
    }
}

/// Reads every source channel; gives each item its ticket. Ends when every source has ended, or
/// after stop once the live sources' queues are empty.
fn ingest(
    mut channels: Vec<(bool, Receiver<Ingest>)>,
    out: Sender<Ticketed<Ingest>>,
    stop: &AtomicBool,
    first: &std::sync::OnceLock<Instant>,
) {
    let mut ticket = 0u64;
    while !channels.is_empty() {
        if stop.load(Ordering::Relaxed) {
            channels.retain(|(live, rx)| !(*live && rx.is_empty()));
            if channels.is_empty() {
                break;
            }
        }
        let mut select = Select::new();
        for (_, rx) in &channels {
            select.recv(rx);
        }
        let Ok(operation) = select.select_timeout(Duration::from_millis(50)) else {
            continue;
        };
        let index = operation.index();
        match operation.recv(&channels[index].1) {
            Ok(item) => {
                first.get_or_init(Instant::now);
                if out.send((ticket, item)).is_err() {
                    return;
                }
                ticket += 1;
            }
            Err(_) => {
                channels.remove(index);
            }
        }
    }
}

impl Origin {
    fn reject(self, stage: &'static str, reason: String) -> Rejection {
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

fn origin_of(frame: &crate::cloud::Frame) -> Origin {
    Origin {
        stream: frame.stream.clone(),
        sequence: frame.sequence,
        sensor_stamp_ns: frame.sensor_stamp_ns,
        ingested: frame.ingested,
        ingest_unix_ns: frame.ingest_unix_ns,
        points_received: frame.cloud.len(),
    }
}

fn prepare(rx: Receiver<Ticketed<Ingest>>, tx: Sender<Ticketed<Work>>, preparer: &Preparer, stats: &Stats) {
    for (ticket, item) in rx {
        let work = match item {
            Ingest::Rejected(r) => Work::Rejected(r),
            Ingest::Frame(frame) => {
                let start = Instant::now();
                let result = contained("prepare", || preparer.prepare(&frame));
                let prepare_ms = ms_since(start);
                stats.record("prepare", prepare_ms);
                match result {
                    Err(message) => Work::Rejected(origin_of(&frame).reject("prepare", message)),
                    Ok(Ok(prepared)) => Work::Frame(PreparedFrame {
                        origin: origin_of(&frame),
                        prepared,
                        prepare_ms,
                        prepared_at: Instant::now(),
                    }),
                    Ok(Err(e)) => Work::Rejected(
                        origin_of(&frame).reject("prepare", format!("{} points received: {e}", frame.cloud.len())),
                    ),
                }
            }
        };
        if tx.send((ticket, work)).is_err() {
            return;
        }
    }
}

/// Groups prepared frames into batches of up to `max_batch`, waiting at most `max_wait` after the
/// first frame of a batch for more.
fn batcher(
    rx: Receiver<Ticketed<Work>>,
    batches: Sender<Vec<Ticketed<PreparedFrame>>>,
    done: Sender<Ticketed<Done>>,
    max_batch: usize,
    max_wait: Duration,
    stats: &Stats,
) {
    let mut batch: Vec<Ticketed<PreparedFrame>> = Vec::with_capacity(max_batch);
    let mut deadline = None;
    loop {
        let received = match deadline {
            None => rx.recv().map_err(|_| true),
            Some(deadline) => rx.recv_deadline(deadline).map_err(|e| e.is_disconnected()),
        };
        match received {
            Ok((ticket, Work::Rejected(r))) => {
                if done.send((ticket, Done::Rejected(r))).is_err() {
                    return;
                }
            }
            Ok((ticket, Work::Frame(frame))) => {
                if batch.is_empty() {
                    deadline = Some(Instant::now() + max_wait);
                }
                batch.push((ticket, frame));
            }
            Err(disconnected) => {
                if !batch.is_empty() {
                    stats.record_batch(batch.len());
                    if batches.send(std::mem::take(&mut batch)).is_err() {
                        return;
                    }
                }
                deadline = None;
                if disconnected {
                    return;
                }
                continue;
            }
        }
        if batch.len() >= max_batch {
            stats.record_batch(batch.len());
            if batches.send(std::mem::take(&mut batch)).is_err() {
                return;
            }
            deadline = None;
        }
    }
}

fn encode(rx: Receiver<Vec<Ticketed<PreparedFrame>>>, tx: Sender<Ticketed<Done>>, mut encoder: Encoder, stats: &Stats) {
    for batch in rx {
        let start = Instant::now();
        let clouds: Vec<&[[f32; 3]]> = batch.iter().map(|(_, f)| f.prepared.points.as_slice()).collect();
        let result = contained("encode", || encoder.encode(&clouds)).and_then(|r| r.map_err(|e| e.to_string()));
        let encode_ms = ms_since(start);
        stats.record("encode", encode_ms);
        match result {
            Ok(encodings) => {
                for ((ticket, frame), encoding) in batch.into_iter().zip(encodings) {
                    if !encoding.is_finite() {
                        let rejection = frame
                            .origin
                            .reject("encode", "the encoder's output is not finite".into());
                        if tx.send((ticket, Done::Rejected(rejection))).is_err() {
                            return;
                        }
                        continue;
                    }
                    let queue_ms = (start - frame.prepared_at).as_secs_f32() * 1000.0;
                    stats.record("queue", queue_ms);
                    let encoded = EncodedFrame {
                        origin: frame.origin,
                        prepared: frame.prepared,
                        encoding,
                        prepare_ms: frame.prepare_ms,
                        queue_ms,
                        encode_ms,
                    };
                    if tx.send((ticket, Done::Encoded(Box::new(encoded)))).is_err() {
                        return;
                    }
                }
            }
            Err(e) => {
                for (ticket, frame) in batch {
                    let rejection = frame.origin.reject("encode", e.clone());
                    if tx.send((ticket, Done::Rejected(rejection))).is_err() {
                        return;
                    }
                }
            }
        }
    }
}

/// Per-stream state of the track stage: the filters and the bookkeeping around them.
struct Stream {
    tracker: StreamTracker,
    last_stamp_ns: Option<u64>,
    rejections_logged: u64,
}

fn track(rx: Receiver<Ticketed<Done>>, tx: Sender<(Output, Instant, Instant)>, config: &Config, stats: &Stats) {
    let mut pending: BTreeMap<u64, Done> = BTreeMap::new();
    let mut next = 0u64;
    let mut trackers: HashMap<String, Stream> = HashMap::new();
    let settings = &config.track;
    let node = config.node.name.clone();
    let nominal_dt = 1.0 / settings.nominal_rate_hz;
    for (ticket, done) in rx {
        pending.insert(ticket, done);
        while let Some(done) = pending.remove(&next) {
            next += 1;
            let start = Instant::now();
            let (stream, ingested) = match &done {
                Done::Encoded(f) => (f.origin.stream.clone(), f.origin.ingested),
                Done::Rejected(r) => (r.stream.clone(), r.ingested),
            };
            let tracker = trackers.entry(stream.clone()).or_insert_with(|| Stream {
                tracker: StreamTracker::new(settings),
                last_stamp_ns: None,
                rejections_logged: 0,
            });
            let output = match done {
                Done::Rejected(r) => {
                    stats.stream(&r.stream).add_rejected(r.stage);
                    tracker.rejections_logged += 1;
                    let n = tracker.rejections_logged;
                    if n <= 10 || n % 100 == 0 {
                        log::warn!(
                            "stream '{}' frame {} rejected at {} ({n} so far): {}",
                            r.stream,
                            r.sequence,
                            r.stage,
                            r.reason
                        );
                    }
                    rejected_output(&node, r)
                }
                Done::Encoded(frame) => {
                    let dt = match (frame.origin.sensor_stamp_ns, tracker.last_stamp_ns) {
                        (Some(now), Some(last)) if now > last && now - last < 1_000_000_000 => {
                            (now - last) as f32 * 1e-9
                        }
                        _ => nominal_dt,
                    };
                    if frame.origin.sensor_stamp_ns.is_some() {
                        tracker.last_stamp_ns = frame.origin.sensor_stamp_ns;
                    }
                    match contained("track", || state_of(&node, &frame, &mut tracker.tracker, dt)) {
                        Ok(state) => Output::State(Box::new(state)),
                        Err(message) => {
                            // The stream's filters may be half updated: start them afresh.
                            tracker.tracker = StreamTracker::new(settings);
                            stats.stream(&frame.origin.stream).add_rejected("track");
                            rejected_output(&node, frame.origin.reject("track", message))
                        }
                    }
                }
            };
            stats.record("track", ms_since(start));
            if tx.send((output, Instant::now(), ingested)).is_err() {
                return;
            }
        }
    }
    if !pending.is_empty() {
        log::error!(
            "track: {} items never reached their turn (ticket {next} missing)",
            pending.len()
        );
    }
}

/// The published message of a rejection (schema `gdvae.rejected/1`).
fn rejected_output(node: &str, r: crate::sources::Rejection) -> Output {
    Output::Rejected(state::Rejected {
        schema: state::REJECTED_SCHEMA.into(),
        node: node.to_string(),
        stream: r.stream,
        sequence: r.sequence,
        stage: r.stage.into(),
        reason: r.reason,
        stamps: state::Stamps {
            sensor_ns: r.sensor_stamp_ns,
            ingest_ns: r.ingest_unix_ns,
            publish_ns: 0, // stamped by the publisher
        },
    })
}

fn variances(log_variance: &[f32]) -> Vec<f32> {
    log_variance.iter().map(|lv| lv.clamp(-20.0, 20.0).exp()).collect()
}

fn state_of(node: &str, frame: &EncodedFrame, tracker: &mut StreamTracker, dt: f32) -> State {
    let e = &frame.encoding;
    let tracked = tracker.update(
        (&e.z_i_mean, &e.z_i_logvar),
        e.q,
        &e.z_e_mean,
        frame.prepared.centre_m,
        dt,
    );
    let update = tracked.shape;
    if let Some(change) = update.change {
        log::info!(
            "stream '{}' frame {}: identity changed ({} -> {})",
            frame.origin.stream,
            frame.origin.sequence,
            change.previous,
            change.identity
        );
    }
    let pose = tracked.pose;
    State {
        schema: state::STATE_SCHEMA.into(),
        node: node.to_string(),
        stream: frame.origin.stream.clone(),
        sequence: frame.origin.sequence,
        stamps: state::Stamps {
            sensor_ns: frame.origin.sensor_stamp_ns,
            ingest_ns: frame.origin.ingest_unix_ns,
            publish_ns: 0, // stamped by the publisher
        },
        latency: state::StageLatency {
            prepare_ms: frame.prepare_ms,
            queue_ms: frame.queue_ms,
            encode_ms: frame.encode_ms,
            total_ms: 0.0, // measured by the publisher
        },
        points: state::Points {
            received: frame.origin.points_received,
            kept: frame.prepared.points_kept,
        },
        centre_m: frame.prepared.centre_m,
        raw: state::Raw {
            q: pose.q_raw,
            yaw: pose.yaw_raw,
            q_confidence: confidence_from_log_variance(&e.z_r_logvar),
            z_e: e.z_e_mean.clone(),
            z_e_var: variances(&e.z_e_logvar),
            z_i: e.z_i_mean.clone(),
            z_i_var: variances(&e.z_i_logvar),
        },
        filtered: state::Filtered {
            q: pose.q,
            yaw: pose.yaw,
            yaw_std: tracked.heading.map(|h| h.yaw_std as f32),
            z_e: pose.z_e,
            z_e_confidence: confidence_from_log_variance(&e.z_e_logvar),
        },
        shape: state::Shape {
            identity: tracker.shape.identity(),
            z_i: tracker.shape.mean().to_vec(),
            z_i_var: tracker.shape.variance(),
            frames_fused: tracker.shape.frames_fused(),
            inlier: update.inlier,
            distance: update.distance,
            confidence: tracker.shape.confidence(),
            change_statistic: update.statistic,
        },
        event: update.change.map(|c| state::IdentityEvent {
            kind: "identity_change".into(),
            previous: c.previous,
            identity: c.identity,
        }),
    }
}

fn status_queryable(
    session: &Session,
    config: &Config,
    bundle: &Bundle,
    stats: Arc<Stats>,
    queues: Arc<Queues>,
    started: Instant,
) -> Result<zenoh::query::Queryable<()>, PipelineError> {
    let m = &bundle.manifest;
    let fixed = serde_json::json!({
        "schema": "gdvae.status/1",
        "node": config.node.name,
        "version": env!("CARGO_PKG_VERSION"),
        "config": config,
        "bundle": {
            "folder": bundle.folder.display().to_string(),
            "regime": m.model.regime,
            "sizes": m.sizes,
            "model_units_per_metre": m.units.model_units_per_metre,
        },
    });
    session
        .declare_queryable(config.status_key())
        .callback(move |query| {
            let mut reply = fixed.clone();
            reply["uptime_s"] = serde_json::json!(started.elapsed().as_secs_f64());
            reply["counters"] = serde_json::to_value(stats.snapshot()).unwrap_or_default();
            reply["queues"] = serde_json::to_value(queues.depths()).unwrap_or_default();
            let payload = serde_json::to_vec(&reply).unwrap_or_default();
            if let Err(e) = query
                .reply(query.key_expr().clone(), payload)
                .encoding(zenoh::bytes::Encoding::APPLICATION_JSON)
                .wait()
            {
                log::warn!("status reply failed: {e}");
            }
        })
        .wait()
        .map_err(|e| PipelineError::Publish(crate::publish::PublishError::Zenoh(e.to_string())))
}

fn summary_logger(finished: &AtomicBool, stats: &Stats, seconds: f64) {
    if seconds <= 0.0 {
        return;
    }
    let mut last = Instant::now();
    while !finished.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(100));
        if last.elapsed().as_secs_f64() < seconds {
            continue;
        }
        last = Instant::now();
        let s = stats.snapshot();
        let e2e = s.stages.get("end_to_end");
        let streams: Vec<String> = s
            .streams
            .iter()
            .map(|(name, c)| {
                let rejected: u64 = c.rejected.values().sum();
                format!(
                    "{name}: {} in, {} out, {} dropped, {rejected} rejected",
                    c.received, c.published, c.dropped
                )
            })
            .collect();
        log::info!(
            "{} | latency p50 {:.1} ms, p99 {:.1} ms | mean batch {:.1}",
            streams.join("; "),
            e2e.map(|l| l.p50_ms).unwrap_or(0.0),
            e2e.map(|l| l.p99_ms).unwrap_or(0.0),
            s.mean_batch
        );
    }
}

#[cfg(test)]
mod tests {
    //! The panic containment on its own: a frame's panic is an error, a dying stage thread stops the
    //! run and lets go of the channels the status observers held.

    use super::*;

    #[test]
    fn a_panic_in_a_frame_is_an_error_naming_the_stage() {
        assert_eq!(contained("prepare", || 7), Ok(7));
        let error = contained("prepare", || -> u32 { panic!("index out of bounds") }).unwrap_err();
        assert_eq!(error, "internal error in prepare: index out of bounds");
        let error = contained("encode", || -> u32 { panic!("{} points", 3) }).unwrap_err();
        assert_eq!(error, "internal error in encode: 3 points");
    }

    #[test]
    fn a_dying_stage_stops_the_run_and_releases_the_observed_channels() {
        let (tx, rx) = bounded::<u32>(1);
        let queues = Arc::new(Queues {
            channels: std::sync::Mutex::new(vec![("work", depth_of(&rx))]),
        });
        let stop = Arc::new(AtomicBool::new(false));
        let failed: Arc<std::sync::Mutex<Vec<String>>> = Arc::default();
        tx.send(1).unwrap();
        assert_eq!(queues.depths()["work"], 1);
        // The stage that reads the channel dies outside any frame's containment.
        let guard = StageGuard {
            name: "prepare:0".into(),
            stop: stop.clone(),
            queues: queues.clone(),
            failed: failed.clone(),
        };
        let handle = std::thread::spawn(move || {
            let _guard = guard;
            let _rx = rx;
            panic!("a bug outside the per-frame work");
        });
        assert!(handle.join().is_err());
        assert!(stop.load(Ordering::SeqCst), "the run is told to stop");
        assert_eq!(*failed.lock().unwrap(), vec!["prepare:0".to_string()]);
        assert!(queues.depths().is_empty(), "the observers let go");
        // Nobody holds a receiver any more: the upstream stage sees the channel closed instead of
        // blocking for ever on a full queue.
        assert!(tx
            .send_timeout(2, Duration::from_secs(1))
            .unwrap_err()
            .is_disconnected());
    }

    #[test]
    fn a_stage_that_ends_normally_leaves_everything_as_it_was() {
        let (_tx, rx) = bounded::<u32>(1);
        let queues = Arc::new(Queues {
            channels: std::sync::Mutex::new(vec![("work", depth_of(&rx))]),
        });
        let stop = Arc::new(AtomicBool::new(false));
        let failed: Arc<std::sync::Mutex<Vec<String>>> = Arc::default();
        let guard = StageGuard {
            name: "batcher".into(),
            stop: stop.clone(),
            queues: queues.clone(),
            failed: failed.clone(),
        };
        std::thread::spawn(move || drop(guard)).join().unwrap();
        assert!(!stop.load(Ordering::SeqCst));
        assert!(failed.lock().unwrap().is_empty());
        assert_eq!(queues.depths().len(), 1);
    }
}
