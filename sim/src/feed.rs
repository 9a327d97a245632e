//! The live feed: a scenario published in real time over zenoh, as a robot's depth camera would
//! publish through rmw_zenoh, so the node can be tested on a network source.
//!
//! Key expressions under a prefix (default [`DEFAULT_PREFIX`]), documented in sim/README.md:
//! - `<prefix>/points`: `sensor_msgs/msg/PointCloud2` in CDR, encoding `application/cdr` with
//!   schema `sensor_msgs/msg/PointCloud2`;
//! - `<prefix>/depth`, `<prefix>/camera_info` (optional): `Image` 16UC1 and `CameraInfo` in CDR;
//! - `<prefix>/ground_truth`: JSON, one [`GroundTruthMessage`] per frame.
//!
//! Frames are generated ahead by a producer thread into a small bounded queue; the publisher paces
//! them by the wall clock and counts frames it could not send on time. Publishers block rather than
//! drop under congestion: the feed is a test instrument, and a frame lost in transport would be
//! invisible to the node's own drop counters.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use crossbeam_channel::bounded;
use rayon::prelude::*;
use zenoh::bytes::Encoding;
use zenoh::qos::CongestionControl;
use zenoh::{Session, Wait};

use crate::ros2::{self, Stamp};
use crate::scenario::{GroundTruthMessage, Scenario, ScenarioError, SensorFrame};

pub const DEFAULT_PREFIX: &str = "sim/oak";
const CAMERA_FRAME: &str = crate::recording::CAMERA_FRAME;

/// Frames generated in parallel per batch, and batches queued ahead of the publisher.
const BATCH: usize = 8;
const QUEUED_BATCHES: usize = 2;

/// Once a data key has a subscriber, how long to wait for one on the ground-truth key too.
const GROUND_TRUTH_GRACE: Duration = Duration::from_secs(1);

#[derive(Debug, Clone)]
pub struct FeedOptions {
    pub key_prefix: String,
    pub depth_images: bool,
    /// Publish as fast as frames are made instead of at the scenario's frame rate.
    pub unpaced: bool,
    /// Before the first frame, wait up to this long for a subscriber to the points (or depth) key,
    /// then up to a second more for one to the ground-truth key.
    pub wait_for_subscriber: Option<Duration>,
}

#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct FeedSummary {
    pub published: usize,
    /// Frames sent more than one frame period after their due time.
    pub late: usize,
    pub max_lateness_ms: f64,
    pub seconds: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum FeedError {
    #[error(transparent)]
    Scenario(#[from] ScenarioError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("no subscriber to '{key}' appeared within {seconds} s")]
    NoSubscriber { key: String, seconds: f64 },
    #[error(transparent)]
    Json(#[from] serde_json::Error),
}

fn zenoh_error(error: zenoh::Error) -> FeedError {
    FeedError::Zenoh(error.to_string())
}

/// Publishes every frame of `scenario` on `session`, stopping early when `stop` is set.
/// `progress(published, total)` is called after each frame.
pub fn run_feed(
    scenario: &Scenario,
    session: &Session,
    options: &FeedOptions,
    stop: &AtomicBool,
    progress: impl Fn(usize, usize),
) -> Result<FeedSummary, FeedError> {
    let prefix = options.key_prefix.trim_end_matches('/');
    let cdr = |schema: &str| Encoding::APPLICATION_CDR.with_schema(schema);
    let declare = |key: &str, encoding: Encoding| {
        session
            .declare_publisher(format!("{prefix}/{key}"))
            .encoding(encoding)
            .congestion_control(CongestionControl::Block)
            .wait()
            .map_err(zenoh_error)
    };
    let points = declare("points", cdr("sensor_msgs/msg/PointCloud2"))?;
    let truth = declare("ground_truth", Encoding::APPLICATION_JSON)?;
    let images = if options.depth_images {
        Some((
            declare("depth", cdr("sensor_msgs/msg/Image"))?,
            declare("camera_info", cdr("sensor_msgs/msg/CameraInfo"))?,
        ))
    } else {
        None
    };

    if let Some(patience) = options.wait_for_subscriber {
        let deadline = Instant::now() + patience;
        let matched = |publisher: &zenoh::pubsub::Publisher<'_>| -> Result<bool, FeedError> {
            Ok(publisher.matching_status().wait().map_err(zenoh_error)?.matching())
        };
        // The data keys decide; then ground truth gets a moment, since a consumer that joins
        // clouds with ground truth subscribes to both, and the declarations arrive separately.
        let mut data = vec![&points];
        if let Some((depth, _)) = &images {
            data.push(depth);
        }
        loop {
            let mut any = false;
            for publisher in &data {
                any |= matched(publisher)?;
            }
            if any {
                break;
            }
            if Instant::now() > deadline || stop.load(Ordering::Relaxed) {
                return Err(FeedError::NoSubscriber {
                    key: points.key_expr().to_string(),
                    seconds: patience.as_secs_f64(),
                });
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let settle = Instant::now() + GROUND_TRUTH_GRACE;
        while !matched(&truth)? && Instant::now() < settle {
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    let total = scenario.frame_count();
    let period = Duration::from_secs_f64(1.0 / scenario.motion.spec.fps);
    let camera_pose = scenario.world_from_camera();
    let (sender, receiver) = bounded::<Result<SensorFrame, ScenarioError>>(BATCH * QUEUED_BATCHES);
    // The closure owns `receiver`: an early error return drops it, which stops the producer, so the
    // scope's join cannot deadlock on a full queue.
    std::thread::scope(move |scope| -> Result<FeedSummary, FeedError> {
        let mut summary = FeedSummary::default();
        // The clock starts at the first frame, so the producer's start-up does not make frames late.
        let mut started = Instant::now();
        scope.spawn(move || {
            for start in (0..total).step_by(BATCH) {
                if stop.load(Ordering::Relaxed) {
                    return;
                }
                let frames: Vec<_> = (start..(start + BATCH).min(total))
                    .into_par_iter()
                    .map(|index| scenario.frame(index))
                    .collect();
                for frame in frames {
                    if sender.send(frame).is_err() {
                        return;
                    }
                }
            }
        });
        for (index, frame) in receiver.iter().enumerate() {
            let frame = frame?;
            if stop.load(Ordering::Relaxed) {
                break;
            }
            if index == 0 {
                started = Instant::now();
            }
            if !options.unpaced {
                let due = started + period * index as u32;
                let now = Instant::now();
                if due > now {
                    std::thread::sleep(due - now);
                } else if now - due > period {
                    summary.late += 1;
                    summary.max_lateness_ms = summary.max_lateness_ms.max((now - due).as_secs_f64() * 1e3);
                }
            }
            // A live sensor stamps frames with the time of capture.
            let nanos = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map(|d| d.as_nanos() as u64)
                .unwrap_or_default();
            let stamp = Stamp::from_nanos(nanos);
            points
                .put(ros2::point_cloud2(stamp, CAMERA_FRAME, &frame.points))
                .wait()
                .map_err(zenoh_error)?;
            if let Some((depth, info)) = &images {
                depth
                    .put(ros2::depth_image(stamp, CAMERA_FRAME, &frame.depth))
                    .wait()
                    .map_err(zenoh_error)?;
                info.put(ros2::camera_info(stamp, CAMERA_FRAME, &scenario.camera.intrinsics))
                    .wait()
                    .map_err(zenoh_error)?;
            }
            let message = GroundTruthMessage {
                stamp_nanos: nanos,
                truth: &frame.truth,
                world_from_camera: camera_pose,
                points: frame.points.len(),
                subjects: &frame.subjects,
            };
            truth.put(serde_json::to_vec(&message)?).wait().map_err(zenoh_error)?;
            summary.published += 1;
            progress(summary.published, total);
        }
        summary.seconds = started.elapsed().as_secs_f64();
        Ok(summary)
    })
}

/// A zenoh configuration: peer mode, optional endpoints to listen on and connect to, and multicast
/// scouting switched off when asked (tests use explicit loopback endpoints).
pub fn zenoh_config(listen: &[String], connect: &[String], multicast: bool) -> Result<zenoh::Config, FeedError> {
    let mut config = zenoh::Config::default();
    let json = |values: &[String]| serde_json::to_string(values);
    if !listen.is_empty() {
        config
            .insert_json5("listen/endpoints", &json(listen)?)
            .map_err(zenoh_error)?;
    }
    if !connect.is_empty() {
        config
            .insert_json5("connect/endpoints", &json(connect)?)
            .map_err(zenoh_error)?;
    }
    config
        .insert_json5("scouting/multicast/enabled", if multicast { "true" } else { "false" })
        .map_err(zenoh_error)?;
    Ok(config)
}
