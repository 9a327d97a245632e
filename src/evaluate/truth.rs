//! Ground truth of a sim recording: the `/sim/ground_truth` channel (JSON, one message per frame),
//! read with the same memory-mapped MCAP reader the replay source uses.

use std::path::{Path, PathBuf};

use serde::Deserialize;

/// The channel the simulator writes (`sim/src/recording.rs`, `GROUND_TRUTH_TOPIC`).
pub const GROUND_TRUTH_TOPIC: &str = "/sim/ground_truth";

/// One frame's ground truth, the fields `evaluate` uses.
#[derive(Debug, Clone, Deserialize)]
pub struct TruthFrame {
    /// The sensor stamp of the frame's cloud: states are matched to truth by it.
    pub stamp_nanos: u64,
    pub frame: usize,
    pub subject: String,
    pub family: String,
    /// Heading of the subject's forward (+x at rest) about world +z, radians, unwrapped.
    pub yaw: f64,
    /// Where the subject stands (m, world frame; z = 0 on the ground).
    pub translation: [f64; 3],
    pub world_from_camera: Option<WorldFromCamera>,
}

#[derive(Debug, Clone, Copy, Deserialize)]
pub struct WorldFromCamera {
    pub translation: [f64; 3],
    pub rotation_xyzw: [f64; 4],
}

impl WorldFromCamera {
    /// The rotation as a row-major matrix (the node's `sensor_to_gravity_rotation`).
    pub fn rotation_rows(&self) -> [[f32; 3]; 3] {
        let [x, y, z, w] = self.rotation_xyzw;
        let n = (x * x + y * y + z * z + w * w).sqrt().max(1e-12);
        let (x, y, z, w) = (x / n, y / n, z / n, w / n);
        [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y - w * z),
                2.0 * (x * z + w * y),
            ],
            [
                2.0 * (x * y + w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z - w * x),
            ],
            [
                2.0 * (x * z - w * y),
                2.0 * (y * z + w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ]
        .map(|row| row.map(|v| v as f32))
    }
}

#[derive(Debug, thiserror::Error)]
pub enum TruthError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a readable MCAP file: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: ground-truth message {index} is not valid: {message}")]
    Message {
        path: PathBuf,
        index: usize,
        message: String,
    },
}

/// The ground truth of a recording (an `.mcap` file or a rosbag2 folder of them), in file order.
/// Empty when the recording has no ground-truth channel. A damaged record ends the reading of its
/// file, as it ends the replay; what came before it is kept.
pub fn read_truth(path: &Path) -> Result<Vec<TruthFrame>, TruthError> {
    let files = crate::sources::mcap::recording_files(path).map_err(|e| TruthError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let mut frames = Vec::new();
    for file in files {
        let handle = std::fs::File::open(&file).map_err(|source| TruthError::Io {
            path: file.clone(),
            source,
        })?;
        // SAFETY: read-only map of a file this process does not write (as in the replay source).
        let mapped = unsafe { memmap2::Mmap::map(&handle) }.map_err(|source| TruthError::Io {
            path: file.clone(),
            source,
        })?;
        // The same bounded reading as the replay: only the sound prefix reaches the mcap crate.
        let scanned = crate::sources::mcap::scan(&mapped).map_err(|message| TruthError::Format {
            path: file.clone(),
            message,
        })?;
        for message in crate::sources::mcap::messages(&mapped[..scanned.sound_bytes]) {
            let Ok(message) = message else { break };
            if &*message.topic != GROUND_TRUTH_TOPIC {
                continue;
            }
            let frame: TruthFrame = serde_json::from_slice(&message.data).map_err(|e| TruthError::Message {
                path: file.clone(),
                index: frames.len(),
                message: e.to_string(),
            })?;
            frames.push(frame);
        }
    }
    Ok(frames)
}
