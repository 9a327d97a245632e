//! MCAP replay: ROS 2 recordings (an `.mcap` file, or a rosbag2 folder of them) played into the
//! pipeline at their original timing times a speed factor, or as fast as the pipeline takes them.
//!
//! The stream is one topic: `sensor_msgs/msg/PointCloud2` (any field layout), or a depth
//! `sensor_msgs/msg/Image` unprojected with the latest `CameraInfo` of its camera. Without a
//! configured topic the first PointCloud2 topic is used. Files are memory-mapped, so a recording
//! of any size costs no more memory than the frames in flight.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::cloud::{PointCloud, Unit};
use crate::config::SourceSettings;
use crate::sources::ros2::{decode_camera_info, decode_depth_image, decode_point_cloud2, CameraIntrinsics};
use crate::sources::Outlet;

const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
const IMAGE: &str = "sensor_msgs/msg/Image";
const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";

#[derive(Debug, thiserror::Error)]
pub enum McapSourceError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a readable MCAP file: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Topic { path: PathBuf, message: String },
}

/// The MCAP files of a path: the file itself, or a rosbag2 folder's `.mcap` files by name.
pub fn recording_files(path: &Path) -> Result<Vec<PathBuf>, McapSourceError> {
    let files = super::file_or_folder(path, &["mcap"]).map_err(|source| McapSourceError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if files.is_empty() {
        return Err(McapSourceError::Topic {
            path: path.to_path_buf(),
            message: "folder holds no .mcap files (rosbag2 must be recorded with the mcap storage plugin)".into(),
        });
    }
    Ok(files)
}

/// What a recording holds for the node: its topics and their schema names.
pub fn topics(bytes: &[u8], path: &Path) -> Result<Vec<(String, String)>, McapSourceError> {
    let format = |e: mcap::McapError| McapSourceError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    let mut found: Vec<(String, String)> = Vec::new();
    if let Some(summary) = mcap::Summary::read(bytes).map_err(format)? {
        let mut channels: Vec<_> = summary.channels.values().collect();
        channels.sort_by_key(|c| c.id);
        for c in channels {
            found.push((
                c.topic.clone(),
                c.schema.as_ref().map(|s| s.name.clone()).unwrap_or_default(),
            ));
        }
        return Ok(found);
    }
    // No summary section (e.g. a recording cut short): scan the messages.
    for message in mcap::MessageStream::new(bytes).map_err(format)? {
        let Ok(message) = message else { break };
        let topic = message.channel.topic.clone();
        if !found.iter().any(|(t, _)| *t == topic) {
            let schema = message
                .channel
                .schema
                .as_ref()
                .map(|s| s.name.clone())
                .unwrap_or_default();
            found.push((topic, schema));
        }
    }
    Ok(found)
}

enum Wanted {
    Clouds(String),
    Depth { image: String, info: String },
}

fn choose_topic(
    settings: &SourceSettings,
    topics: &[(String, String)],
    path: &Path,
) -> Result<Wanted, McapSourceError> {
    let listing = || {
        topics
            .iter()
            .map(|(t, s)| format!("{t} ({s})"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let error = |message: String| McapSourceError::Topic {
        path: path.to_path_buf(),
        message,
    };
    let schema_of = |topic: &str| topics.iter().find(|(t, _)| t == topic).map(|(_, s)| s.as_str());
    let topic = match &settings.topic {
        Some(topic) => topic.clone(),
        None => topics
            .iter()
            .find(|(_, s)| s == POINT_CLOUD2)
            .map(|(t, _)| t.clone())
            .ok_or_else(|| error(format!("no {POINT_CLOUD2} topic; set `topic` (topics: {})", listing())))?,
    };
    match schema_of(&topic) {
        Some(POINT_CLOUD2) => Ok(Wanted::Clouds(topic)),
        Some(IMAGE) => {
            let info = settings.camera_info_topic.clone().unwrap_or_else(|| {
                let parent = topic.rsplit_once('/').map(|(p, _)| p).unwrap_or("");
                format!("{parent}/camera_info")
            });
            if schema_of(&info) != Some(CAMERA_INFO) {
                return Err(error(format!(
                    "depth topic {topic} needs a {CAMERA_INFO} topic; '{info}' is not one; set `camera_info_topic` (topics: {})",
                    listing()
                )));
            }
            Ok(Wanted::Depth { image: topic, info })
        }
        Some(other) => Err(error(format!(
            "topic {topic} carries {other}; the node reads {POINT_CLOUD2} or {IMAGE}"
        ))),
        None => Err(error(format!("no topic {topic} (topics: {})", listing()))),
    }
}

/// Replays the recording into `outlet`. Errors opening the recording end the source; a message
/// that does not decode is a rejection and the replay goes on.
pub fn run(settings: &SourceSettings, mut outlet: Outlet) -> Result<(), McapSourceError> {
    let path = settings.path.clone().unwrap_or_default();
    let files = recording_files(&path)?;
    let unit = settings.unit.unwrap_or(Unit::Metre);
    loop {
        // Original timing: message i is due at start + (log_time_i - log_time_0) / speed.
        let mut clock: Option<(Instant, u64)> = None;
        for file in &files {
            let handle = std::fs::File::open(file).map_err(|source| McapSourceError::Io {
                path: file.clone(),
                source,
            })?;
            // SAFETY: the map is read-only; a recording changed by another process while it is
            // replayed yields undecodable messages (rejections), not undefined behaviour in safe code
            // that only reads bytes.
            let mapped = unsafe { memmap2::Mmap::map(&handle) }.map_err(|source| McapSourceError::Io {
                path: file.clone(),
                source,
            })?;
            let bytes: &[u8] = &mapped;
            let wanted = choose_topic(settings, &topics(bytes, file)?, file)?;
            let stream = mcap::MessageStream::new(bytes).map_err(|e| McapSourceError::Format {
                path: file.clone(),
                message: e.to_string(),
            })?;
            let mut intrinsics: Option<Arc<CameraIntrinsics>> = None;
            let mut waiting: Option<Vec<u8>> = None;
            for message in stream {
                if outlet.stopping() {
                    return Ok(());
                }
                let message = match message {
                    Ok(m) => m,
                    Err(e) => {
                        // A damaged chunk ends this file; what was read so far has been replayed.
                        outlet.reject(
                            format!("{}: unreadable record, rest of file skipped: {e}", file.display()),
                            None,
                        );
                        break;
                    }
                };
                let topic = message.channel.topic.as_str();
                let decoded = match &wanted {
                    Wanted::Clouds(t) if topic == t => Some(
                        decode_point_cloud2(&message.data, settings.max_points)
                            .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite)),
                    ),
                    Wanted::Depth { info, .. } if topic == info => {
                        match decode_camera_info(&message.data) {
                            Ok((_, k)) => intrinsics = Some(Arc::new(k)),
                            Err(e) => log::warn!("{}: {topic}: CameraInfo ignored: {e}", file.display()),
                        }
                        // An image that came just before its camera's first CameraInfo goes now.
                        match (&intrinsics, waiting.take()) {
                            (Some(k), Some(image)) => Some(
                                decode_depth_image(&image, k, settings.depth_step, settings.max_points)
                                    .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite)),
                            ),
                            (_, image) => {
                                waiting = image;
                                None
                            }
                        }
                    }
                    Wanted::Depth { image, .. } if topic == image => match &intrinsics {
                        Some(k) => Some(
                            decode_depth_image(&message.data, k, settings.depth_step, settings.max_points)
                                .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite)),
                        ),
                        None => {
                            // Wait for the first CameraInfo; an image it replaces is rejected.
                            let replaced = waiting.replace(message.data.to_vec());
                            replaced.map(|_| {
                                Err(crate::sources::ros2::CdrError::Invalid(
                                    "depth image with no CameraInfo before the next image".into(),
                                ))
                            })
                        }
                    },
                    _ => None,
                };
                let Some(decoded) = decoded else { continue };
                if settings.speed > 0.0 {
                    let (start, first) = *clock.get_or_insert((Instant::now(), message.log_time));
                    let offset = message.log_time.saturating_sub(first) as f64 / settings.speed;
                    let due = start + Duration::from_nanos(offset as u64);
                    if !outlet.wait_until(due) {
                        return Ok(());
                    }
                }
                let open = match decoded {
                    Ok((stamp, points, dropped)) => outlet.frame(PointCloud { points }, unit, Some(stamp), dropped),
                    Err(e) => outlet.reject(
                        format!("{} {topic} at log time {}: {e}", file.display(), message.log_time),
                        Some(message.log_time),
                    ),
                };
                if !open {
                    return Ok(());
                }
            }
            if waiting.take().is_some()
                && !outlet.reject(
                    format!("{}: depth image with no CameraInfo after it", file.display()),
                    None,
                )
            {
                return Ok(());
            }
        }
        if !settings.repeat {
            return Ok(());
        }
    }
}
