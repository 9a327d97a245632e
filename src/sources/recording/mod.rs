//! The replay source: ROS 2 recordings played into the pipeline at their original timing times a
//! speed factor, or as fast as the pipeline takes them.
//!
//! A recording is an `.mcap` file, a rosbag2 sqlite3 file (`.db3`), or a rosbag2 folder (its
//! `metadata.yaml` says the storage; a folder of `.mcap` files without one is read too). Both
//! storages yield the same messages, so a bag replays to the same states whichever it is in.
//!
//! The stream is one topic: `sensor_msgs/msg/PointCloud2` (any field layout), or a depth
//! `sensor_msgs/msg/Image` unprojected with the latest `CameraInfo` of its camera. Without a
//! configured topic the first PointCloud2 topic is used. MCAP files are memory-mapped and sqlite3
//! files read row by row, so a recording of any size costs no more memory than the frames in flight.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::cloud::{PointCloud, Unit};
use crate::sources::files::file_or_folder;
use crate::sources::outlet::{Intake, Outlet};
use crate::sources::ros2::{decode_camera_info, decode_depth_image, decode_point_cloud2, CameraIntrinsics};
use rosbag2::{Sqlite3Bag, Storage};

pub mod mcap;
mod message;
pub mod rosbag2;

pub use message::RecordedMessage;

const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
const IMAGE: &str = "sensor_msgs/msg/Image";
const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";

/// `kind = "mcap"` (alias `"rosbag2"`): a recording replayed.
#[derive(Debug, Clone, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct RecordingSettings {
    /// An .mcap file, a .db3 file, or a rosbag2 folder.
    pub path: PathBuf,
    /// The PointCloud2 topic (default: the first one), or a depth Image topic.
    #[serde(default)]
    pub topic: Option<String>,
    /// A depth image's CameraInfo topic (default: `<image topic's parent>/camera_info`).
    #[serde(default)]
    pub camera_info_topic: Option<String>,
    /// Depth images: keep every `depth_step`-th pixel in each direction.
    #[serde(default = "default_depth_step")]
    pub depth_step: usize,
    /// 1 = original timing, 2 = twice as fast, 0 = as fast as the pipeline takes the frames.
    #[serde(default = "default_speed")]
    pub speed: f64,
    /// Start again at the end (a looping demo); a replay benchmark leaves it off.
    #[serde(default)]
    pub repeat: bool,
}

pub(crate) fn default_depth_step() -> usize {
    2
}

fn default_speed() -> f64 {
    1.0
}

impl RecordingSettings {
    /// A recording replayed as fast as possible, once.
    pub fn replay(path: PathBuf, speed: f64) -> Self {
        Self {
            path,
            topic: None,
            camera_info_topic: None,
            depth_step: default_depth_step(),
            speed,
            repeat: false,
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        if !(self.speed >= 0.0 && self.speed.is_finite()) {
            return Err(format!("speed = {} must be finite and >= 0", self.speed));
        }
        if self.depth_step == 0 {
            return Err("depth_step must be at least 1".into());
        }
        Ok(())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a readable recording: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Topic { path: PathBuf, message: String },
}

/// One file of a recording and how it stores its messages.
#[derive(Debug, Clone, PartialEq)]
pub struct RecordingFile {
    pub path: PathBuf,
    pub storage: Storage,
}

/// Whether `path` is a recording the replay source reads (rather than point-cloud files).
pub fn is_recording(path: &Path) -> bool {
    if path.is_dir() {
        return path.join("metadata.yaml").is_file() || recording_files(path).is_ok();
    }
    let named = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| ["mcap", "db3"].contains(&e.to_ascii_lowercase().as_str()));
    named || storage_of(path).is_ok()
}

/// How a single file stores its messages: by its first bytes, whatever its name.
fn storage_of(path: &Path) -> Result<Storage, RecordingError> {
    use std::io::Read;
    let mut head = [0u8; 16];
    let mut file = std::fs::File::open(path).map_err(|source| RecordingError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let n = file.read(&mut head).map_err(|source| RecordingError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if head[..n].starts_with(mcap::MAGIC) {
        Ok(Storage::Mcap)
    } else if rosbag2::is_sqlite(&head[..n]) {
        Ok(Storage::Sqlite3)
    } else {
        Err(RecordingError::Format {
            path: path.to_path_buf(),
            message: "neither MCAP nor SQLite (rosbag2 sqlite3) at the start of the file".into(),
        })
    }
}

/// The files of a recording, in playback order: the file itself; a rosbag2 folder's files as its
/// `metadata.yaml` lists them; or, without metadata, a folder's `.mcap` (else `.db3`) files by name.
pub fn recording_files(path: &Path) -> Result<Vec<RecordingFile>, RecordingError> {
    if path.is_dir() && path.join("metadata.yaml").is_file() {
        let metadata = rosbag2::read_metadata(path).map_err(|message| RecordingError::Format {
            path: path.to_path_buf(),
            message,
        })?;
        return Ok(metadata
            .files
            .into_iter()
            .map(|path| RecordingFile {
                path,
                storage: metadata.storage,
            })
            .collect());
    }
    if !path.is_dir() {
        let storage = storage_of(path)?;
        return Ok(vec![RecordingFile {
            path: path.to_path_buf(),
            storage,
        }]);
    }
    for (extension, storage) in [("mcap", Storage::Mcap), ("db3", Storage::Sqlite3)] {
        let files = file_or_folder(path, &[extension]).map_err(|source| RecordingError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        if !files.is_empty() {
            return Ok(files.into_iter().map(|path| RecordingFile { path, storage }).collect());
        }
    }
    Err(RecordingError::Topic {
        path: path.to_path_buf(),
        message: "folder holds no recording (no rosbag2 metadata.yaml, no .mcap or .db3 files)".into(),
    })
}

/// A recording file's topics and their schema (type) names.
pub fn topics(file: &RecordingFile) -> Result<Vec<(String, String)>, RecordingError> {
    match file.storage {
        Storage::Mcap => {
            let mapped = map(&file.path)?;
            mcap::topics(&mapped).map_err(|message| RecordingError::Format {
                path: file.path.clone(),
                message,
            })
        }
        Storage::Sqlite3 => open_sqlite(&file.path)?
            .topics()
            .map_err(|message| RecordingError::Format {
                path: file.path.clone(),
                message,
            }),
    }
}

/// Hands the messages of `wanted` topics in `file` to `each` until it returns false. Returns why
/// the file could not be read to its end (a cut or damaged rest), after handing over every message
/// before the damage; None when it was read whole (or `each` stopped it).
pub fn for_each_message(
    file: &RecordingFile,
    wanted: &[&str],
    mut each: impl FnMut(RecordedMessage<'_>) -> bool,
) -> Result<Option<String>, RecordingError> {
    match file.storage {
        Storage::Mcap => {
            let mapped = map(&file.path)?;
            // Only the sound prefix goes to the reader; what lies beyond is the damage.
            let scanned = mcap::scan(&mapped).map_err(|message| RecordingError::Format {
                path: file.path.clone(),
                message,
            })?;
            let mut outcome = Ok(scanned.damage);
            mcap::messages(&mapped[..scanned.sound_bytes]).walk(|message| match message {
                Ok(m) if !wanted.contains(&&*m.topic) => true,
                Ok(m) => {
                    let open = each(m);
                    if !open {
                        outcome = Ok(None);
                    }
                    open
                }
                Err(e) => {
                    outcome = Ok(Some(format!("unreadable record: {e}")));
                    false
                }
            });
            outcome
        }
        Storage::Sqlite3 => {
            let mut stopped = false;
            let result = open_sqlite(&file.path)?.for_each(wanted, |m| {
                stopped = !each(m);
                !stopped
            });
            Ok(result.err())
        }
    }
}

fn open_sqlite(path: &Path) -> Result<Sqlite3Bag, RecordingError> {
    Sqlite3Bag::open(path).map_err(|message| RecordingError::Format {
        path: path.to_path_buf(),
        message,
    })
}

fn map(path: &Path) -> Result<memmap2::Mmap, RecordingError> {
    let io = |source| RecordingError::Io {
        path: path.to_path_buf(),
        source,
    };
    let handle = std::fs::File::open(path).map_err(io)?;
    // SAFETY: the map is read-only; a recording changed by another process while it is replayed
    // yields undecodable messages (rejections), not undefined behaviour in safe code that only
    // reads bytes.
    unsafe { memmap2::Mmap::map(&handle) }.map_err(io)
}

enum Wanted {
    Clouds(String),
    Depth { image: String, info: String },
}

impl Wanted {
    fn topics(&self) -> Vec<&str> {
        match self {
            Wanted::Clouds(t) => vec![t],
            Wanted::Depth { image, info } => vec![image, info],
        }
    }
}

fn choose_topic(
    settings: &RecordingSettings,
    topics: &[(String, String)],
    path: &Path,
) -> Result<Wanted, RecordingError> {
    let listing = || {
        topics
            .iter()
            .map(|(t, s)| format!("{t} ({s})"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let error = |message: String| RecordingError::Topic {
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

/// What a replay checks before anything runs: the recording's files, and in each the topic it
/// will replay. A one-line description for the log and `check-config`.
pub fn check(settings: &RecordingSettings) -> Result<String, RecordingError> {
    let files = recording_files(&settings.path)?;
    let mut chosen = Vec::new();
    for file in &files {
        let topic = match choose_topic(settings, &topics(file)?, &file.path)? {
            Wanted::Clouds(t) => t,
            Wanted::Depth { image, .. } => image,
        };
        if !chosen.contains(&topic) {
            chosen.push(topic);
        }
    }
    let storage = match files[0].storage {
        Storage::Mcap => "mcap",
        Storage::Sqlite3 => "sqlite3",
    };
    Ok(format!(
        "{} recording file(s) ({storage}), topic {}",
        files.len(),
        chosen.join(", ")
    ))
}

/// The per-message half of a replay: decodes the wanted topics, paces them, sends them on.
struct Replayer<'a> {
    settings: &'a RecordingSettings,
    max_points: usize,
    outlet: &'a mut Outlet,
    unit: Unit,
    /// Original timing: message i is due at start + (log_time_i - log_time_0) / speed.
    clock: Option<(Instant, u64)>,
    intrinsics: Option<Arc<CameraIntrinsics>>,
    /// A depth image that came before its camera's first CameraInfo.
    waiting: Option<Vec<u8>>,
}

impl Replayer<'_> {
    /// Handles one message; false when the pipeline has shut down or a stop was requested.
    fn message(&mut self, file: &Path, wanted: &Wanted, message: RecordedMessage<'_>) -> bool {
        if self.outlet.stopping() {
            return false;
        }
        let settings = self.settings;
        let topic: &str = &message.topic;
        let decoded = match wanted {
            Wanted::Clouds(t) if topic == t => Some(
                decode_point_cloud2(&message.data, self.max_points)
                    .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite, c.header.frame_id)),
            ),
            Wanted::Depth { info, .. } if topic == info => {
                match decode_camera_info(&message.data) {
                    Ok((_, k)) => self.intrinsics = Some(Arc::new(k)),
                    Err(e) => log::warn!("{}: {topic}: CameraInfo ignored: {e}", file.display()),
                }
                // An image that came just before its camera's first CameraInfo goes now.
                match (&self.intrinsics, self.waiting.take()) {
                    (Some(k), Some(image)) => Some(
                        decode_depth_image(&image, k, settings.depth_step, self.max_points)
                            .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite, c.header.frame_id)),
                    ),
                    (_, image) => {
                        self.waiting = image;
                        None
                    }
                }
            }
            Wanted::Depth { image, .. } if topic == image => match &self.intrinsics {
                Some(k) => Some(
                    decode_depth_image(&message.data, k, settings.depth_step, self.max_points)
                        .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite, c.header.frame_id)),
                ),
                None => {
                    // Wait for the first CameraInfo; an image it replaces is rejected.
                    let replaced = self.waiting.replace(message.data.into_owned());
                    replaced.map(|_| {
                        Err(crate::sources::ros2::CdrError::Invalid(
                            "depth image with no CameraInfo before the next image".into(),
                        ))
                    })
                }
            },
            _ => None,
        };
        let Some(decoded) = decoded else { return true };
        if settings.speed > 0.0 {
            let (start, first) = *self.clock.get_or_insert((Instant::now(), message.log_time));
            let offset = message.log_time.saturating_sub(first) as f64 / settings.speed;
            let due = start + Duration::from_nanos(offset as u64);
            if !self.outlet.wait_until(due) {
                return false;
            }
        }
        match decoded {
            Ok((stamp, points, dropped, frame_id)) => {
                self.outlet.sensor_frame(&frame_id);
                self.outlet
                    .frame(PointCloud { points }, self.unit, Some(stamp), dropped)
            }
            Err(e) => self.outlet.reject(
                format!("{} {topic} at log time {}: {e}", file.display(), message.log_time),
                Some(message.log_time),
            ),
        }
    }
}

/// Replays the recording into `outlet`. Errors opening the recording end the source; a message
/// that does not decode is a rejection and the replay goes on; a cut or damaged rest of a file is
/// one rejection after every message before it was replayed.
pub fn run(intake: &Intake, settings: &RecordingSettings, mut outlet: Outlet) -> Result<(), RecordingError> {
    let files = recording_files(&settings.path)?;
    loop {
        let mut replayer = Replayer {
            settings,
            max_points: intake.max_points,
            outlet: &mut outlet,
            unit: intake.unit.unwrap_or(Unit::Metre),
            clock: None,
            intrinsics: None,
            waiting: None,
        };
        for file in &files {
            let wanted = choose_topic(settings, &topics(file)?, &file.path)?;
            let mut open = true;
            let damage = for_each_message(file, &wanted.topics(), |m| {
                open = replayer.message(&file.path, &wanted, m);
                open
            })?;
            if !open {
                return Ok(());
            }
            if let Some(damage) = damage {
                // The messages before the damage were replayed; the rest is one rejection.
                if !replayer
                    .outlet
                    .reject(format!("{}: rest of file skipped: {damage}", file.path.display()), None)
                {
                    return Ok(());
                }
            }
            if replayer.waiting.take().is_some()
                && !replayer.outlet.reject(
                    format!("{}: depth image with no CameraInfo after it", file.path.display()),
                    None,
                )
            {
                return Ok(());
            }
            replayer.intrinsics = None;
        }
        if !settings.repeat {
            return Ok(());
        }
    }
}
