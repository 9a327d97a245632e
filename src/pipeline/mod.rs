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
//!
//! This module only wires: the stage bodies are in `stages`, what travels between them in `work`,
//! fault containment in `faults`, the status queryable and summary log in `status`; sources start
//! through `sources::start`, sinks are behind `publish::Publisher`.

mod faults;
pub mod report;
mod stages;
mod status;
mod work;

use faults::{depth_of, Queues, StageGuard};
use stages::{batcher, encode, ingest, prepare, track};
use status::{status_queryable, summary_logger};
use work::{ms_since, Done, PreparedFrame, Ticketed, Work};

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crossbeam_channel::{bounded, Receiver};
use zenoh::{Session, Wait};

use crate::bundle::Bundle;
use crate::config::Config;
use crate::prepare::Preparer;
use crate::publish::Publisher;
use crate::runtime::Encoder;
use crate::sources::{self, unix_now_ns, Ingest, Outlet};
use crate::state::Output;
use crate::stats::{Snapshot, Stats};

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
    /// The CPU time of the whole process (every thread, ONNX Runtime's included) over `busy`.
    pub busy_cpu: Duration,
    pub snapshot: Snapshot,
}

/// A source that could not start: left out (logged and listed) when optional, else the run's error.
fn cannot_start(
    source: &crate::config::SourceSettings,
    message: String,
    failed_sources: &mut Vec<(String, String)>,
) -> Result<(), PipelineError> {
    if !source.optional {
        return Err(PipelineError::Source {
            stream: source.stream.clone(),
            message: format!("cannot start: {message}"),
        });
    }
    log::error!(
        "optional source '{}' cannot start, running without it: {message}",
        source.stream
    );
    failed_sources.push((source.stream.clone(), format!("cannot start: {message}")));
    Ok(())
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
            Err(message) => cannot_start(source, message, &mut failed_sources)?,
        }
    }
    if starting.is_empty() {
        let reasons: Vec<String> = failed_sources.iter().map(|(s, m)| format!("'{s}' {m}")).collect();
        return Err(PipelineError::NoSource(reasons.join("; ")));
    }

    // Encoders first: a bundle or runtime problem fails before any source starts.
    let mut encoders = Vec::new();
    for _ in 0..m.workers {
        encoders
            .push(Encoder::load(bundle, m.onnxruntime.as_deref(), m.threads, m.spin)?.with_yaw_copies(m.yaw_copies));
    }
    let preparer = Arc::new(
        Preparer::new(
            &config.prepare,
            bundle.manifest.sizes.points,
            bundle.manifest.units.model_units_per_metre as f32,
        )
        .with_sensor_poses(config.sources.iter().map(crate::sources::SourceSettings::sensor_pose))
        .showing_input(config.publish.input_points()),
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
        let outlet = outlet.with_feed_gap(Duration::from_secs_f64(config.pipeline.feed_gap_s));
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
            Err(message) => cannot_start(source, message, &mut failed_sources)?,
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
        let objects = config.track.objects.enabled.then(|| config.track.objects.clone());
        threads.push(spawn(
            format!("prepare:{worker}"),
            Box::new(move || prepare(rx, tx, &preparer, objects.as_ref(), &stats)),
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
        let (mut config, stats) = (config.clone(), stats.clone());
        // The bundle's calibration of its z_I variances, then the config's multiplier.
        let calibration = bundle.manifest.calibration.z_i_variance_scale;
        config.track.shape_variance_scale *= calibration;
        log::info!(
            "track: z_I variances x {calibration} (bundle calibration) x {} (config) = x {}",
            config.track.shape_variance_scale / calibration,
            config.track.shape_variance_scale
        );
        // The config's z_I distances are in z_I spreads; the bundle says how wide its z_I is.
        let spread = bundle.manifest.calibration.z_i_unit();
        config.track = config.track.in_model_units(spread);
        match bundle.manifest.calibration.z_i_spread {
            Some(_) => log::info!("track: z_I distances in spreads of {spread} (bundle calibration)"),
            None => log::info!(
                "track: z_I distances in spreads of {spread} (the bundle's calibration has no z_I_spread; \
                 h200-fo-theta's is assumed)"
            ),
        }
        config.track.identity_projection = bundle.manifest.calibration.identity_directions();
        let t = &config.track;
        let detector = format!("{:?} detector, threshold {}", t.change_detector, t.change_threshold()).to_lowercase();
        match (t.identity_directions(), &t.identity_projection) {
            (Some(rows), _) => log::info!(
                "track: identity changes on the bundle's identity projection ({} directions of x_c; {detector})",
                rows.len()
            ),
            (None, Some(_)) => {
                log::info!("track: identity changes on z_I ({detector}; use_identity_projection = false)")
            }
            (None, None) => {
                log::info!("track: identity changes on z_I ({detector}; the bundle has no identity projection)")
            }
        }
        // The heading filter's noise (12 degrees) was chosen on the 4 yaw copies' fused reading;
        // for one copy 25 was (config/default.toml; docs/tracking.md "The yaw copies' scatter,
        // and a walk's vote" has what 12 does to a standing subject with one copy).
        let t = &config.track;
        if config.model.yaw_copies == 1 && t.heading == crate::config::HeadingMode::Tracker && t.heading_std_deg < 20.0
        {
            log::warn!(
                "track: heading_std_deg = {} suits yaw_copies = 4; with yaw_copies = 1 set it to about 25, \
                 or idle subjects' filtered heading may be worse than the raw reading",
                t.heading_std_deg
            );
        }
        threads.push(spawn(
            "track".into(),
            Box::new(move || track(done_rx, publish_tx, &config, &stats)),
        )?);
    }
    let streams: Vec<String> = config.sources.iter().map(|s| s.stream.clone()).collect();
    let sensor_poses = streams
        .iter()
        .filter_map(|s| preparer.sensor_pose(s).map(|pose| (s.clone(), pose)))
        .collect();
    let mut publisher = Publisher::new(
        &config.publish,
        &streams,
        &config.node,
        config.model.onnxruntime.as_deref(),
        bundle,
        session.clone(),
        participants.as_ref(),
        &sensor_poses,
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
        let status = status_queryable(session, config, bundle, stats.clone(), queues.clone(), started)
            .map_err(|e| PipelineError::Publish(crate::publish::PublishError::Zenoh(e.to_string())))?;
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
    let mut connection = crate::zenoh_session::ConnectionWatch::new(
        config.publish.zenoh || config.publish.ros2.enabled,
        &config.zenoh,
        session.as_ref(),
    );
    let mut last_publish = (Instant::now(), crate::cpu::process_ns());
    loop {
        match publish_rx.recv_timeout(Duration::from_millis(50)) {
            Ok((mut output, tracked_at, ingested)) => {
                let mut cpu = crate::cpu::ThreadLap::start();
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
                stats.add_cpu(&[("publish", cpu.lap())]);
                // The end of the busy span: when the last output went out, not when the stages'
                // threads have noticed the end (their 50 ms timeouts would count as work).
                last_publish = (Instant::now(), crate::cpu::process_ns());
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
    for (stream, message, optional) in std::mem::take(&mut *source_errors.lock().unwrap_or_else(|e| e.into_inner())) {
        if !optional {
            return Err(PipelineError::Source { stream, message });
        }
        failed_sources.push((stream, message));
    }
    Ok(RunSummary {
        failed_sources,
        wall: started.elapsed(),
        busy: first_ingest
            .get()
            .map(|f| last_publish.0.saturating_duration_since(f.0))
            .unwrap_or_default(),
        busy_cpu: first_ingest
            .get()
            .map(|f| Duration::from_nanos(last_publish.1.saturating_sub(f.1)))
            .unwrap_or_default(),
        snapshot: stats.snapshot(),
    })
}
