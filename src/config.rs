//! The node's one settings type: everything the pipeline does, read from one TOML file.
//!
//! Every section has defaults (so an empty file is a valid config), unknown keys are refused
//! (`deny_unknown_fields`: a typo must not silently fall back to a default), and `validate` checks
//! the values once, so the stages can trust them. `config/default.toml` documents every key.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::cloud::Unit;
use crate::prepare::Sampling;
// The track stage owns its settings; they are re-exported here with the rest of the config.
pub use crate::track::{ChangeDetector, HeadingMode, Smoothing, TrackSettings};
// So does each sink.
pub use crate::publish::Ros2Settings;

#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{path}: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("{path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Invalid { path: PathBuf, message: String },
}

#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    pub node: NodeSettings,
    pub model: ModelSettings,
    pub pipeline: PipelineSettings,
    pub prepare: PrepareSettings,
    pub track: TrackSettings,
    pub publish: PublishSettings,
    pub zenoh: ZenohSettings,
    #[serde(rename = "source")]
    pub sources: Vec<SourceSettings>,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct NodeSettings {
    /// This node's name: the second part of every key expression.
    pub name: String,
    /// First part of every key expression.
    pub prefix: String,
}

impl Default for NodeSettings {
    fn default() -> Self {
        Self {
            name: "node".into(),
            prefix: "gdvae".into(),
        }
    }
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelSettings {
    /// Bundle folder (relative paths are resolved against the config file's folder).
    pub bundle: PathBuf,
    /// libonnxruntime.so; empty: ORT_DYLIB_PATH, then a .venv's onnxruntime wheel.
    pub onnxruntime: Option<PathBuf>,
    /// Encoder workers, each with its own ONNX Runtime session.
    pub workers: usize,
    /// Intra-op threads per session.
    pub threads: usize,
    /// Let idle ONNX Runtime threads spin (only worth it on cores nothing else uses).
    pub spin: bool,
    /// Most frames encoded in one call (frames of all streams are batched together).
    pub max_batch: usize,
    /// How long the batcher waits for a batch to fill before running a smaller one.
    pub max_wait_ms: f64,
}

impl Default for ModelSettings {
    fn default() -> Self {
        Self {
            bundle: PathBuf::from("models/bundles/cpu-gdvaepp"),
            onnxruntime: None,
            workers: 1,
            threads: 2,
            spin: false,
            max_batch: 8,
            max_wait_ms: 2.0,
        }
    }
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct PipelineSettings {
    /// Capacity of each channel between stages (frames).
    pub queue: usize,
    /// Threads that prepare frames (crop, filter, subsample).
    pub prepare_workers: usize,
    /// Seconds between summary lines in the log (0: none).
    pub summary_seconds: f64,
}

impl Default for PipelineSettings {
    fn default() -> Self {
        Self {
            queue: 16,
            prepare_workers: 2,
            summary_seconds: 5.0,
        }
    }
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct PrepareSettings {
    /// Row-major 3x3 rotation from the sensor frame into a gravity-aligned frame (z up).
    pub sensor_to_gravity_rotation: [[f32; 3]; 3],
    /// Translation (metres) applied after the rotation.
    pub sensor_to_gravity_translation: [f32; 3],
    /// Estimate the ground plane by RANSAC on every frame and level the cloud with it (replaces the
    /// configured rotation's tilt, keeps its heading).
    pub auto_ground: bool,
    /// Remove points within `ground_tolerance_m` of the ground plane (estimated by RANSAC).
    pub remove_ground: bool,
    pub ground_tolerance_m: f32,
    pub ransac_iterations: usize,
    /// Region of interest in the gravity frame (metres): [min_x, min_y, min_z, max_x, max_y, max_z].
    pub crop: Option<[f32; 6]>,
    pub outliers: OutlierSettings,
    /// Keep only the largest cluster of points joined by neighbours closer than this (metres):
    /// drops what the crop leaves of the floor's noise and stray clutter. 0 keeps every point.
    pub cluster_m: f32,
    pub sampling: Sampling,
    /// Voxel edge (metres) for `sampling = "voxel"`.
    pub voxel_m: f32,
    /// Frames with fewer points than this after filtering are rejected (fewer than N_p are padded).
    pub min_points: usize,
    /// Seed of the random choices (sampling, RANSAC); frames are deterministic for a seed.
    pub seed: u64,
}

impl Default for PrepareSettings {
    fn default() -> Self {
        Self {
            sensor_to_gravity_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            sensor_to_gravity_translation: [0.0; 3],
            auto_ground: false,
            remove_ground: false,
            ground_tolerance_m: 0.02,
            ransac_iterations: 100,
            crop: None,
            outliers: OutlierSettings::default(),
            cluster_m: 0.0,
            sampling: Sampling::Farthest,
            voxel_m: 0.01,
            min_points: 64,
            seed: 0,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum OutlierMethod {
    None,
    Statistical,
    Radius,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutlierSettings {
    pub method: OutlierMethod,
    /// Statistical: neighbours per point, and the number of standard deviations of the mean
    /// neighbour distance beyond which a point is removed.
    pub neighbours: usize,
    pub std_ratio: f32,
    /// Radius: a point needs `min_neighbours` others within `radius_m`.
    pub radius_m: f32,
    pub min_neighbours: usize,
}

impl Default for OutlierSettings {
    fn default() -> Self {
        Self {
            method: OutlierMethod::None,
            neighbours: 8,
            std_ratio: 2.0,
            radius_m: 0.05,
            min_neighbours: 3,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Json,
    Cbor,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct PublishSettings {
    /// Publish states on zenoh (`<prefix>/<node>/<stream>/state`).
    pub zenoh: bool,
    pub format: Format,
    /// Also write one JSON line per state: a file path, or "-" for stdout.
    pub jsonl: Option<String>,
    /// The node as a ROS 2 node over rmw_zenoh (`[publish.ros2]`).
    pub ros2: Ros2Settings,
}

impl Default for PublishSettings {
    fn default() -> Self {
        Self {
            zenoh: true,
            format: Format::Json,
            jsonl: None,
            ros2: Ros2Settings::default(),
        }
    }
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct ZenohSettings {
    /// "peer" (an embedded peer, no router needed) or "client" (needs a router in `connect`).
    pub mode: String,
    /// Endpoints to listen on, e.g. "tcp/0.0.0.0:7447".
    pub listen: Vec<String>,
    /// Routers or peers to connect to, e.g. "tcp/192.168.1.10:7447".
    pub connect: Vec<String>,
    /// Find peers on the LAN by UDP multicast.
    pub multicast_scouting: bool,
}

impl Default for ZenohSettings {
    fn default() -> Self {
        Self {
            mode: "peer".into(),
            listen: Vec::new(),
            connect: Vec::new(),
            multicast_scouting: true,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SourceKind {
    /// Point-cloud files (PLY, PCD, OBJ, XYZ/CSV): one file, or every such file of a folder.
    Files,
    /// A recording: an MCAP file, a rosbag2 sqlite3 file (.db3), or a rosbag2 folder (either storage).
    #[serde(alias = "rosbag2", alias = "recording")]
    Mcap,
    /// A zenoh subscription.
    Zenoh,
    /// A ROS 2 topic by name, over rmw_zenoh.
    Ros2,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum WireFormat {
    /// Decide per sample from its zenoh encoding.
    Auto,
    /// ROS 2 sensor_msgs/msg/PointCloud2 in CDR.
    Cdr,
    /// The DepthAI harness: float32 x, y, z in millimetres.
    Depthai,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct SourceSettings {
    /// Stream id: the third part of the state's key expression.
    pub stream: String,
    pub kind: SourceKind,
    /// Files and MCAP: the file or folder.
    #[serde(default)]
    pub path: Option<PathBuf>,
    /// MCAP: the PointCloud2 topic (default: the first PointCloud2 topic), or a depth Image topic
    /// (its CameraInfo is `camera_info_topic`). ROS 2: the topic to subscribe to (required).
    #[serde(default)]
    pub topic: Option<String>,
    #[serde(default)]
    pub camera_info_topic: Option<String>,
    /// Depth images: keep every `depth_step`-th pixel in each direction.
    #[serde(default = "default_depth_step")]
    pub depth_step: usize,
    /// Replay speed: 1 = original timing, 2 = twice as fast, 0 = as fast as possible.
    /// Files have no timing: `rate_hz` paces them (0 = as fast as possible).
    #[serde(default = "default_speed")]
    pub speed: f64,
    #[serde(default)]
    pub rate_hz: f64,
    /// Start again at the end (a looping demo); a replay benchmark leaves it off.
    #[serde(default)]
    pub repeat: bool,
    /// ROS 2: the domain (default: `[publish.ros2] domain_id`).
    #[serde(default)]
    pub domain_id: Option<u32>,
    /// Zenoh: key expression to subscribe to.
    #[serde(default)]
    pub key: Option<String>,
    #[serde(default = "default_wire")]
    pub format: WireFormat,
    /// Unit of the coordinates (files and CDR are metres by convention; DepthAI is millimetres).
    #[serde(default)]
    pub unit: Option<Unit>,
    /// Largest frame accepted (points); bigger frames are rejected before they are decoded.
    #[serde(default = "default_max_points")]
    pub max_points: usize,
    /// This sensor's pose, when it differs from `[prepare]`'s: sensor frame -> gravity frame.
    #[serde(default)]
    pub sensor_to_gravity_rotation: Option<[[f32; 3]; 3]>,
    #[serde(default)]
    pub sensor_to_gravity_translation: Option<[f32; 3]>,
    /// The node runs on without this source when it cannot start or fails (logged, listed in the
    /// report). Off by default: a source that cannot do its job fails the run, with a non-zero exit.
    #[serde(default)]
    pub optional: bool,
}

fn default_depth_step() -> usize {
    2
}
fn default_speed() -> f64 {
    1.0
}
fn default_wire() -> WireFormat {
    WireFormat::Auto
}
fn default_max_points() -> usize {
    4_000_000
}

impl SourceSettings {
    /// Live sources never block their sensor: when the pipeline is behind they drop the oldest frame.
    pub fn is_live(&self) -> bool {
        matches!(self.kind, SourceKind::Zenoh | SourceKind::Ros2)
    }

    /// Whether it subscribes on the zenoh session (rather than running a thread of its own).
    pub fn is_subscription(&self) -> bool {
        self.is_live()
    }
}

fn check_rotation(key: &str, rows: &[[f32; 3]; 3]) -> Result<(), String> {
    let r = nalgebra::Matrix3::from_fn(|i, j| rows[i][j]);
    let orthogonality = (r.transpose() * r - nalgebra::Matrix3::identity()).abs().max();
    if orthogonality < 1e-3 && (r.determinant() - 1.0).abs() < 1e-3 {
        Ok(())
    } else {
        Err(format!("{key} must be a rotation matrix (orthonormal, determinant 1)"))
    }
}

impl Config {
    /// Reads, parses and validates a config file; relative paths become relative to its folder.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let mut config = Self::parse(&text).map_err(|message| ConfigError::Parse {
            path: path.to_path_buf(),
            message,
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        config.resolve_paths(base);
        config.validate().map_err(|message| ConfigError::Invalid {
            path: path.to_path_buf(),
            message,
        })?;
        Ok(config)
    }

    pub fn parse(text: &str) -> Result<Self, String> {
        toml::from_str(text).map_err(|e| e.to_string())
    }

    fn resolve_paths(&mut self, base: &Path) {
        let resolve = |p: &mut PathBuf| {
            if p.is_relative() && !p.as_os_str().is_empty() {
                *p = base.join(&*p);
            }
        };
        resolve(&mut self.model.bundle);
        if let Some(p) = self.model.onnxruntime.as_mut() {
            resolve(p);
        }
        if let Some(jsonl) = self.publish.jsonl.as_mut().filter(|j| *j != "-") {
            let mut path = PathBuf::from(&*jsonl);
            resolve(&mut path);
            *jsonl = path.display().to_string();
        }
        for source in &mut self.sources {
            if let Some(p) = source.path.as_mut() {
                resolve(p);
            }
        }
    }

    /// Checks every value once; the message names the key.
    pub fn validate(&self) -> Result<(), String> {
        let key_part = |what: &str, value: &str| {
            if value.is_empty()
                || value.contains(['*', '$', '#', '?'])
                || value.starts_with('/')
                || value.ends_with('/')
            {
                Err(format!(
                    "{what} '{value}' must be a non-empty key expression part without wildcards"
                ))
            } else {
                Ok(())
            }
        };
        key_part("node.name", &self.node.name)?;
        key_part("node.prefix", &self.node.prefix)?;
        let m = &self.model;
        if m.workers == 0 || m.threads == 0 || m.max_batch == 0 {
            return Err("model.workers, model.threads and model.max_batch must be at least 1".into());
        }
        if !(m.max_wait_ms >= 0.0 && m.max_wait_ms <= 1000.0) {
            return Err(format!("model.max_wait_ms = {} must be within 0..=1000", m.max_wait_ms));
        }
        if self.pipeline.queue == 0 || self.pipeline.prepare_workers == 0 {
            return Err("pipeline.queue and pipeline.prepare_workers must be at least 1".into());
        }
        if !(self.pipeline.summary_seconds >= 0.0) {
            return Err("pipeline.summary_seconds must be >= 0".into());
        }
        let p = &self.prepare;
        check_rotation("prepare.sensor_to_gravity_rotation", &p.sensor_to_gravity_rotation)?;
        if let Some(c) = p.crop {
            if !(c[0] < c[3] && c[1] < c[4] && c[2] < c[5]) {
                return Err(format!(
                    "prepare.crop {c:?} must be [min_x, min_y, min_z, max_x, max_y, max_z] with min < max"
                ));
            }
        }
        if !(p.ground_tolerance_m > 0.0) || !(p.voxel_m > 0.0) || p.min_points == 0 {
            return Err("prepare.ground_tolerance_m, prepare.voxel_m and prepare.min_points must be positive".into());
        }
        if (p.auto_ground || p.remove_ground) && p.ransac_iterations == 0 {
            return Err("prepare.ransac_iterations must be at least 1 when the ground is estimated".into());
        }
        if !(p.cluster_m >= 0.0 && p.cluster_m.is_finite()) {
            return Err(format!("prepare.cluster_m = {} must be >= 0 (0: off)", p.cluster_m));
        }
        let o = &p.outliers;
        if o.method != OutlierMethod::None && (o.neighbours == 0 || !(o.std_ratio > 0.0) || !(o.radius_m > 0.0)) {
            return Err("prepare.outliers: neighbours, std_ratio and radius_m must be positive".into());
        }
        self.track.validate()?;
        self.publish.ros2.validate()?;
        if !matches!(self.zenoh.mode.as_str(), "peer" | "client") {
            return Err(format!(
                "zenoh.mode '{}' must be \"peer\" or \"client\"",
                self.zenoh.mode
            ));
        }
        if self.zenoh.mode == "client" && self.zenoh.connect.is_empty() {
            return Err("zenoh.mode = \"client\" needs a router in zenoh.connect".into());
        }
        let mut streams = std::collections::HashSet::new();
        for (index, s) in self.sources.iter().enumerate() {
            let at = format!("source[{index}] ('{}')", s.stream);
            key_part(&format!("{at} stream"), &s.stream)?;
            if !streams.insert(s.stream.as_str()) {
                return Err(format!("{at}: stream '{}' is used by two sources", s.stream));
            }
            match s.kind {
                SourceKind::Files | SourceKind::Mcap if s.path.is_none() => {
                    return Err(format!("{at}: a {:?} source needs `path`", s.kind).to_lowercase())
                }
                SourceKind::Zenoh if s.key.as_deref().is_none_or(str::is_empty) => {
                    return Err(format!("{at}: a zenoh source needs `key`"))
                }
                SourceKind::Ros2 => {
                    let topic = s.topic.as_deref().unwrap_or("");
                    let names = |t: &str| {
                        !t.is_empty()
                            && t.trim_start_matches('/').split('/').all(|part| {
                                part.chars().next().is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
                                    && part.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
                            })
                    };
                    if !names(topic) || !s.camera_info_topic.as_deref().is_none_or(names) {
                        return Err(format!(
                            "{at}: a ros2 source needs `topic`, a ROS 2 topic name like \"/camera/points\" \
                             (letters, digits, underscores); got '{topic}'"
                        ));
                    }
                    if s.domain_id.is_some_and(|d| d > 232) {
                        return Err(format!("{at}: domain_id must be within 0..=232"));
                    }
                }
                _ => {}
            }
            if !(s.speed >= 0.0 && s.speed.is_finite()) || !(s.rate_hz >= 0.0 && s.rate_hz.is_finite()) {
                return Err(format!("{at}: speed and rate_hz must be finite and >= 0"));
            }
            if let Some(rotation) = &s.sensor_to_gravity_rotation {
                check_rotation(&format!("{at} sensor_to_gravity_rotation"), rotation)?;
            }
            if s.depth_step == 0 || s.max_points == 0 {
                return Err(format!("{at}: depth_step and max_points must be at least 1"));
            }
        }
        Ok(())
    }

    /// The key expression of one stream's states.
    pub fn state_key(&self, stream: &str) -> String {
        format!("{}/{}/{stream}/state", self.node.prefix, self.node.name)
    }

    pub fn status_key(&self) -> String {
        format!("{}/{}/status", self.node.prefix, self.node.name)
    }

    pub fn liveliness_key(&self) -> String {
        format!("{}/{}/alive", self.node.prefix, self.node.name)
    }
}
