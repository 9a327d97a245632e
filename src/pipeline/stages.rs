//! The stage bodies, each run on its own thread(s) by `pipeline::run`: ingest (tickets), prepare,
//! batcher, encode, track (ticket order, the stream's filters, the published state).

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Select, Sender};

use super::work::*;
use crate::config::Config;
use crate::contain::contained;
use crate::encoding::Encoding;
use crate::prepare::{Prepared, Preparer, STEPS};
use crate::runtime::Encoder;
use crate::sources::Ingest;
use crate::state::{self, Output};
use crate::stats::Stats;
use crate::track::association::{AssociationSettings, Candidate, TrackEvent};
use crate::track::{step_dt, ObjectTracks, Observed, StreamTracker};

/// Reads every source channel; gives each item its ticket. Ends when every source has ended, or
/// after stop once the live sources' queues are empty.
pub(super) fn ingest(
    mut channels: Vec<(bool, Receiver<Ingest>)>,
    out: Sender<Ticketed<Ingest>>,
    stop: &AtomicBool,
    first: &std::sync::OnceLock<(Instant, u64)>,
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
                first.get_or_init(|| (Instant::now(), crate::cpu::process_ns()));
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

/// Prepares each frame: its largest cluster, or with `objects` (`[track.objects]` enabled) every
/// cluster that could be an object; a frame with none is rejected.
pub(super) fn prepare(
    rx: Receiver<Ticketed<Ingest>>,
    tx: Sender<Ticketed<Work>>,
    preparer: &Preparer,
    objects: Option<&AssociationSettings>,
    stats: &Stats,
) {
    for (ticket, item) in rx {
        let work = match item {
            Ingest::Rejected(r) => Work::Rejected(r),
            Ingest::Frame(frame) => {
                let start = Instant::now();
                let mut cpu = [0; STEPS.len()];
                let result = contained("prepare", || match objects {
                    None => preparer.prepare_measured(&frame, &mut cpu).map(|p| vec![p]),
                    Some(o) => preparer.prepare_all_measured(&frame, o.max_extent_m, o.max_objects, &mut cpu),
                });
                let prepare_ms = ms_since(start);
                stats.record("prepare", prepare_ms);
                stats.add_cpu(&std::array::from_fn::<_, { STEPS.len() }, _>(|i| (STEPS[i], cpu[i])));
                match result {
                    Err(message) => Work::Rejected(origin_of(&frame).reject("prepare", message)),
                    Ok(Ok(found)) if found.is_empty() => Work::Rejected(origin_of(&frame).reject(
                        "prepare",
                        format!(
                            "{} points received: no object (no cluster of at least {} points within {} m)",
                            frame.cloud.len(),
                            preparer.min_points(),
                            objects.map_or(f32::INFINITY, |o| o.max_extent_m)
                        ),
                    )),
                    Ok(Ok(found)) => Work::Frame(PreparedFrame {
                        origin: origin_of(&frame),
                        objects: found,
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

/// A stream that sent a frame within this long is expected to send another: the batcher waits for
/// it (up to `max_wait`) rather than send a batch without it.
const STREAM_ACTIVE: Duration = Duration::from_secs(1);

/// Groups prepared frames into batches of up to `max_batch`, waiting at most `max_wait` after the
/// first frame of a batch for more. A batch is sent at once when nothing more is queued and it
/// already holds a frame of every stream active within [`STREAM_ACTIVE`]: the next frame of any of
/// them is a sensor period away, so waiting would only add latency (one live stream at 30 Hz is
/// encoded frame by frame, with no `max_wait` in its latency).
pub(super) fn batcher(
    rx: Receiver<Ticketed<Work>>,
    batches: Sender<Vec<Ticketed<PreparedFrame>>>,
    done: Sender<Ticketed<Done>>,
    max_batch: usize,
    max_wait: Duration,
    stats: &Stats,
) {
    let mut batch: Vec<Ticketed<PreparedFrame>> = Vec::with_capacity(max_batch);
    let mut deadline = None;
    let mut last_seen: HashMap<String, Instant> = HashMap::new();
    loop {
        let received = match deadline {
            None => rx.recv().map_err(|_| true),
            Some(deadline) => rx.recv_deadline(deadline).map_err(|e| e.is_disconnected()),
        };
        let (send, disconnected) = match received {
            Ok((ticket, Work::Rejected(r))) => {
                if done.send((ticket, Done::Rejected(r))).is_err() {
                    return;
                }
                continue;
            }
            Ok((ticket, Work::Frame(frame))) => {
                let now = Instant::now();
                if batch.is_empty() {
                    deadline = Some(now + max_wait);
                }
                match last_seen.get_mut(&frame.origin.stream) {
                    Some(seen) => *seen = now,
                    None => {
                        last_seen.insert(frame.origin.stream.clone(), now);
                    }
                }
                batch.push((ticket, frame));
                let complete = batch.len() >= max_batch
                    || rx.is_empty() && {
                        last_seen.retain(|_, seen| now.duration_since(*seen) < STREAM_ACTIVE);
                        last_seen
                            .keys()
                            .all(|stream| batch.iter().any(|(_, f)| &f.origin.stream == stream))
                    };
                (complete, false)
            }
            // The deadline passed, or every sender is gone.
            Err(disconnected) => (true, disconnected),
        };
        if send {
            if !batch.is_empty() {
                stats.record_batch(batch.len());
                if batches.send(std::mem::take(&mut batch)).is_err() {
                    return;
                }
            }
            deadline = None;
        }
        if disconnected {
            return;
        }
    }
}

pub(super) fn encode(
    rx: Receiver<Vec<Ticketed<PreparedFrame>>>,
    tx: Sender<Ticketed<Done>>,
    mut encoder: Encoder,
    stats: &Stats,
) {
    for batch in rx {
        let start = Instant::now();
        // Every candidate object of every frame in one call.
        let clouds: Vec<&[[f32; 3]]> = batch
            .iter()
            .flat_map(|(_, f)| f.objects.iter().map(|p| p.points.as_slice()))
            .collect();
        let mut cpu = crate::cpu::ThreadLap::start();
        let result = contained("encode", || encoder.encode(&clouds)).and_then(|r| r.map_err(|e| e.to_string()));
        let encode_ms = ms_since(start);
        stats.record("encode", encode_ms);
        // One item a batch: the CPU table divides by frames, not by items.
        stats.add_cpu(&[("encode", cpu.lap())]);
        let mut encodings = match result {
            Ok(encodings) => encodings.into_iter(),
            Err(e) => {
                for (ticket, frame) in batch {
                    let rejection = frame.origin.reject("encode", e.clone());
                    if tx.send((ticket, Done::Rejected(rejection))).is_err() {
                        return;
                    }
                }
                continue;
            }
        };
        for (ticket, frame) in batch {
            let objects: Vec<(Prepared, Encoding)> = frame.objects.into_iter().zip(encodings.by_ref()).collect();
            let done = if objects.iter().any(|(_, e)| !e.is_finite()) {
                Done::Rejected(
                    frame
                        .origin
                        .reject("encode", "the encoder's output is not finite".into()),
                )
            } else {
                let queue_ms = (start - frame.prepared_at).as_secs_f32() * 1000.0;
                stats.record("queue", queue_ms);
                Done::Encoded(Box::new(EncodedFrame {
                    origin: frame.origin,
                    objects,
                    prepare_ms: frame.prepare_ms,
                    queue_ms,
                    encode_ms,
                }))
            };
            if tx.send((ticket, done)).is_err() {
                return;
            }
        }
    }
}

/// Per-stream state of the track stage: the filters and the bookkeeping around them.
pub(super) struct Stream {
    /// The one object's filters (unless several objects are tracked).
    tracker: StreamTracker,
    /// The tracks and their filters, with `[track.objects] enabled`.
    objects: Option<ObjectTracks>,
    last_stamp_ns: Option<u64>,
    rejections_logged: u64,
}

pub(super) fn track(
    rx: Receiver<Ticketed<Done>>,
    tx: Sender<(Output, Instant, Instant)>,
    config: &Config,
    stats: &Stats,
) {
    let mut pending: BTreeMap<u64, Done> = BTreeMap::new();
    let mut next = 0u64;
    let mut trackers: HashMap<String, Stream> = HashMap::new();
    let settings = &config.track;
    let node = config.node.name.clone();
    for (ticket, done) in rx {
        pending.insert(ticket, done);
        while let Some(done) = pending.remove(&next) {
            next += 1;
            let start = Instant::now();
            let mut cpu = crate::cpu::ThreadLap::start();
            let (stream, ingested) = match &done {
                Done::Encoded(f) => (f.origin.stream.clone(), f.origin.ingested),
                Done::Rejected(r) => (r.stream.clone(), r.ingested),
            };
            let tracker = trackers.entry(stream.clone()).or_insert_with(|| Stream {
                tracker: StreamTracker::new(settings),
                objects: settings.objects.enabled.then(|| ObjectTracks::new(settings)),
                last_stamp_ns: None,
                rejections_logged: 0,
            });
            let outputs = match done {
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
                    if let Some(objects) = tracker.objects.as_mut() {
                        // No candidates this frame: the tracks age all the same.
                        let time = seconds(r.sensor_stamp_ns, r.ingest_unix_ns);
                        let (_, events) = objects.associate(time, &[]);
                        report_events(&r.stream, r.sequence, &events, stats);
                    }
                    vec![rejected_output(&node, r)]
                }
                Done::Encoded(frame) => match tracker.objects.as_mut() {
                    Some(objects) => several_objects(objects, *frame, &node, stats),
                    None => vec![one_object(tracker, *frame, &node, settings, stats)],
                },
            };
            stats.record("track", ms_since(start));
            stats.add_cpu(&[("track", cpu.lap())]);
            for output in outputs {
                if tx.send((output, Instant::now(), ingested)).is_err() {
                    return;
                }
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

/// A frame's time (s): its sensor stamp, else when it was ingested.
fn seconds(sensor_stamp_ns: Option<u64>, ingest_unix_ns: u64) -> f64 {
    sensor_stamp_ns.unwrap_or(ingest_unix_ns) as f64 * 1e-9
}

/// What the filters see of one encoded object.
fn observed<'a>(frame: &'a EncodedFrame, prepared: &Prepared, encoding: &'a Encoding) -> Observed<'a> {
    Observed {
        stream: &frame.origin.stream,
        sequence: frame.origin.sequence,
        sensor_stamp_ns: frame.origin.sensor_stamp_ns,
        ingest_unix_ns: frame.origin.ingest_unix_ns,
        points_received: frame.origin.points_received,
        points_kept: prepared.points_kept,
        centre_m: prepared.centre_m,
        encoding,
        latency: state::StageLatency {
            prepare_ms: frame.prepare_ms,
            queue_ms: frame.queue_ms,
            encode_ms: frame.encode_ms,
            total_ms: 0.0, // measured by the publisher
        },
    }
}

/// The state of the one object of `frame` (the largest cluster), through the stream's filters.
fn one_object(
    stream: &mut Stream,
    mut frame: EncodedFrame,
    node: &str,
    settings: &crate::track::TrackSettings,
    stats: &Stats,
) -> Output {
    let gap_s = match (frame.origin.sensor_stamp_ns, stream.last_stamp_ns) {
        (Some(now), Some(last)) if now > last => Some((now - last) as f32 * 1e-9),
        _ => None,
    };
    let dt = step_dt(gap_s, 1.0 / settings.nominal_rate_hz);
    if frame.origin.sensor_stamp_ns.is_some() {
        stream.last_stamp_ns = frame.origin.sensor_stamp_ns;
    }
    let (mut prepared, encoding) = frame.objects.pop().expect("prepare passes on a frame with an object");
    let observed = observed(&frame, &prepared, &encoding);
    match contained("track", || stream.tracker.state(node, &observed, dt)) {
        Ok(mut state) => {
            state.prepared = Some(std::sync::Arc::new(std::mem::take(&mut prepared.points)));
            state.input = prepared.input.take().map(std::sync::Arc::new);
            state.sensor_frame = frame.origin.sensor_frame.clone();
            Output::State(Box::new(state))
        }
        Err(message) => {
            // The stream's filters may be half updated: start them afresh.
            stream.tracker = StreamTracker::new(settings);
            stats.stream(&frame.origin.stream).add_rejected("track");
            rejected_output(node, frame.origin.reject("track", message))
        }
    }
}

/// The states of every tracked object of `frame`: its candidates associated with the stream's
/// tracks, each confirmed track's candidate through that track's filters. A frame whose
/// candidates all belong to tentative tracks publishes nothing (counted).
fn several_objects(objects: &mut ObjectTracks, mut frame: EncodedFrame, node: &str, stats: &Stats) -> Vec<Output> {
    // The frame's decimated input cloud (prepare hands it with the first candidate) goes with the
    // first state published.
    let mut input = frame.objects.iter_mut().find_map(|(prepared, _)| prepared.input.take());
    let candidates: Vec<Candidate> = frame
        .objects
        .iter()
        .map(|(prepared, encoding)| Candidate {
            centre: prepared.position_m,
            z_i: encoding.z_i_mean.clone(),
            points: prepared.points_kept,
        })
        .collect();
    let origin = &frame.origin;
    let time = seconds(origin.sensor_stamp_ns, origin.ingest_unix_ns);
    let (tracked, events) = objects.associate(time, &candidates);
    report_events(&origin.stream, origin.sequence, &events, stats);
    if tracked.is_empty() {
        stats.stream(&origin.stream).add_untracked();
        return Vec::new();
    }
    let count = tracked.len();
    let mut outputs = Vec::with_capacity(count);
    for (index, t) in tracked.iter().enumerate() {
        let result = {
            let (prepared, encoding) = &frame.objects[t.candidate];
            let observed = observed(&frame, prepared, encoding);
            contained("track", || objects.filters(t.id).state(node, &observed, t.dt))
        };
        match result {
            Ok(mut state) => {
                state.track = Some(t.id);
                state.of_frame = Some((index, count));
                let points = std::mem::take(&mut frame.objects[t.candidate].0.points);
                state.prepared = Some(std::sync::Arc::new(points));
                state.input = input.take().map(std::sync::Arc::new);
                state.sensor_frame = frame.origin.sensor_frame.clone();
                outputs.push(Output::State(Box::new(state)));
            }
            Err(message) => {
                objects.restart(t.id);
                stats.stream(&frame.origin.stream).add_rejected("track");
                let reason = format!("track {}: {message}", t.id);
                outputs.push(rejected_output(node, frame.origin.clone().reject("track", reason)));
            }
        }
    }
    outputs
}

/// Logs and counts what happened to a stream's tracks.
fn report_events(stream: &str, sequence: u64, events: &[TrackEvent], stats: &Stats) {
    let counters = stats.stream(stream);
    for event in events {
        counters.add_track_event(event);
        match event {
            TrackEvent::Born { id } => log::info!("stream '{stream}' frame {sequence}: track {id} born"),
            TrackEvent::Reidentified { id, away_s } => {
                log::info!("stream '{stream}' frame {sequence}: track {id} back after {away_s:.1} s")
            }
            TrackEvent::Ended { id } => log::info!("stream '{stream}' frame {sequence}: track {id} ended (unseen)"),
        }
    }
}

/// The published message of a rejection (schema `gdvae.rejected/1`).
pub(super) fn rejected_output(node: &str, r: crate::sources::Rejection) -> Output {
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
