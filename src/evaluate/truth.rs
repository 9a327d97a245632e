//! Ground truth of a sim recording: the `/sim/ground_truth` channel (JSON, one message per frame),
//! read with the same memory-mapped MCAP reader the replay source uses.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// The channel the simulator writes (`sim/src/recording.rs`, `GROUND_TRUTH_TOPIC`).
pub const GROUND_TRUTH_TOPIC: &str = "/sim/ground_truth";

/// One frame's ground truth, the fields `evaluate` uses.
#[derive(Debug, Clone, Deserialize, Serialize)]
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
    /// The subject's joint angles (axis-angle per non-root joint, rad); empty in recordings whose
    /// truth lacks them.
    #[serde(default)]
    pub theta: Vec<f64>,
    pub world_from_camera: Option<WorldFromCamera>,
    /// Every subject of the scene, the primary (the fields above) first; empty in recordings made
    /// before the sim had several subjects.
    #[serde(default)]
    pub subjects: Vec<SubjectTruth>,
}

/// One subject's ground truth in one frame (scenes with several subjects).
#[derive(Debug, Clone, Deserialize, Serialize)]
pub struct SubjectTruth {
    /// The subject's place in the scene (0: the primary), constant over the recording.
    pub id: u64,
    /// In the scene (false while it has left the view).
    pub present: bool,
    /// Points of this frame's cloud on the subject.
    pub visible_points: usize,
    pub subject: String,
    pub family: String,
    pub yaw: f64,
    pub translation: [f64; 3],
}

#[derive(Debug, Clone, Copy, Deserialize, Serialize)]
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
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: ground-truth message {index} is not valid: {message}")]
    Message {
        path: PathBuf,
        index: usize,
        message: String,
    },
}

/// The ground truth of a recording (any the replay reads: MCAP, rosbag2), in playback order.
/// Empty when the recording has no ground-truth channel. A damaged record ends the reading of its
/// file, as it ends the replay; what came before it is kept.
pub fn read_truth(path: &Path) -> Result<Vec<TruthFrame>, TruthError> {
    use crate::sources::recording::{for_each_message, recording_files};
    let format = |e: crate::sources::recording::RecordingError| TruthError::Format {
        path: path.to_path_buf(),
        message: e.to_string(),
    };
    let mut frames = Vec::new();
    for file in recording_files(path).map_err(format)? {
        let mut invalid = None;
        // The same bounded reading as the replay; a damaged rest ends the file's truth.
        for_each_message(&file, &[GROUND_TRUTH_TOPIC], |message| {
            match serde_json::from_slice::<TruthFrame>(&message.data) {
                Ok(frame) => frames.push(frame),
                Err(e) => invalid = Some(e.to_string()),
            }
            invalid.is_none()
        })
        .map_err(format)?;
        if let Some(message) = invalid {
            return Err(TruthError::Message {
                path: file.path,
                index: frames.len(),
                message,
            });
        }
    }
    Ok(frames)
}
