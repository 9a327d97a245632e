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
// So does each sink, and each source its kind's settings.
pub use crate::publish::Ros2Settings;
pub use crate::sources::zenoh::WireFormat;

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

/// One `[[source]]`: what every source has (its stream, its frames' unit and size limit, its
/// sensor's pose), and its kind's own settings, owned and validated by its module in `sources/`.
/// A key that does not belong to the kind is refused.
#[derive(Debug, Clone, Serialize)]
pub struct SourceSettings {
    /// Stream id: the third part of the state's key expression.
    pub stream: String,
    #[serde(flatten)]
    pub input: Input,
    /// The node runs on without this source when it cannot start or fails (logged, listed in the
    /// report). Off by default: a source that cannot do its job fails the run, with a non-zero exit.
    pub optional: bool,
    /// Unit of the coordinates (files and CDR are metres by convention; DepthAI is millimetres).
    pub unit: Option<Unit>,
    /// Largest frame accepted (points); bigger frames are rejected before they are decoded.
    pub max_points: usize,
    /// This sensor's pose, when it differs from `[prepare]`'s: sensor frame -> gravity frame.
    pub sensor_to_gravity_rotation: Option<[[f32; 3]; 3]>,
    pub sensor_to_gravity_translation: Option<[f32; 3]>,
}

/// A source's kind and the settings of that kind.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Input {
    Files(crate::sources::files::FilesSettings),
    Mcap(crate::sources::recording::RecordingSettings),
    Zenoh(crate::sources::zenoh::ZenohSourceSettings),
    Ros2(crate::sources::ros2_topic::Ros2TopicSettings),
}

/// The keys every source has; the rest belong to its kind.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct CommonSettings {
    stream: String,
    kind: SourceKind,
    #[serde(default)]
    optional: bool,
    #[serde(default)]
    unit: Option<Unit>,
    #[serde(default = "default_max_points")]
    max_points: usize,
    #[serde(default)]
    sensor_to_gravity_rotation: Option<[[f32; 3]; 3]>,
    #[serde(default)]
    sensor_to_gravity_translation: Option<[f32; 3]>,
}

const COMMON_KEYS: [&str; 7] = [
    "stream",
    "kind",
    "optional",
    "unit",
    "max_points",
    "sensor_to_gravity_rotation",
    "sensor_to_gravity_translation",
];

fn default_max_points() -> usize {
    4_000_000
}

impl<'de> Deserialize<'de> for SourceSettings {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        use serde::de::Error;
        let table = toml::Table::deserialize(deserializer)?;
        let (common, own): (toml::Table, toml::Table) = table
            .into_iter()
            .partition(|(key, _)| COMMON_KEYS.contains(&key.as_str()));
        let common = CommonSettings::deserialize(toml::Value::Table(common)).map_err(D::Error::custom)?;
        let own = toml::Value::Table(own);
        let kind_error = |e: toml::de::Error| {
            D::Error::custom(format!(
                "source '{}' ({}): {}",
                common.stream,
                serde_json::to_string(&common.kind)
                    .unwrap_or_default()
                    .trim_matches('"'),
                e.message()
            ))
        };
        let input = match common.kind {
            SourceKind::Files => Input::Files(Deserialize::deserialize(own).map_err(kind_error)?),
            SourceKind::Mcap => Input::Mcap(Deserialize::deserialize(own).map_err(kind_error)?),
            SourceKind::Zenoh => Input::Zenoh(Deserialize::deserialize(own).map_err(kind_error)?),
            SourceKind::Ros2 => Input::Ros2(Deserialize::deserialize(own).map_err(kind_error)?),
        };
        Ok(Self {
            stream: common.stream,
            input,
            optional: common.optional,
            unit: common.unit,
            max_points: common.max_points,
            sensor_to_gravity_rotation: common.sensor_to_gravity_rotation,
            sensor_to_gravity_translation: common.sensor_to_gravity_translation,
        })
    }
}

impl SourceSettings {
    /// A source of `input` with every common setting at its default.
    pub fn new(stream: String, input: Input) -> Self {
        Self {
            stream,
            input,
            optional: false,
            unit: None,
            max_points: default_max_points(),
            sensor_to_gravity_rotation: None,
            sensor_to_gravity_translation: None,
        }
    }

    pub fn kind(&self) -> SourceKind {
        match self.input {
            Input::Files(_) => SourceKind::Files,
            Input::Mcap(_) => SourceKind::Mcap,
            Input::Zenoh(_) => SourceKind::Zenoh,
            Input::Ros2(_) => SourceKind::Ros2,
        }
    }

    /// Live sources never block their sensor: when the pipeline is behind they drop the oldest frame.
    pub fn is_live(&self) -> bool {
        self.is_subscription()
    }

    /// Whether it subscribes on the zenoh session (rather than running a thread of its own).
    pub fn is_subscription(&self) -> bool {
        matches!(self.input, Input::Zenoh(_) | Input::Ros2(_))
    }

    /// Checks every value once; the message names the source and the key.
    fn validate(&self, at: &str) -> Result<(), String> {
        if let Some(rotation) = &self.sensor_to_gravity_rotation {
            check_rotation(&format!("{at} sensor_to_gravity_rotation"), rotation)?;
        }
        if self.max_points == 0 {
            return Err(format!("{at}: max_points must be at least 1"));
        }
        match &self.input {
            Input::Files(own) => own.validate(),
            Input::Mcap(own) => own.validate(),
            Input::Zenoh(own) => own.validate(),
            Input::Ros2(own) => own.validate(),
        }
        .map_err(|message| format!("{at}: {message}"))
    }

    /// The file or folder it reads, if it reads one.
    fn path_mut(&mut self) -> Option<&mut PathBuf> {
        match &mut self.input {
            Input::Files(own) => Some(&mut own.path),
            Input::Mcap(own) => Some(&mut own.path),
            Input::Zenoh(_) | Input::Ros2(_) => None,
        }
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
        let config = Self::read(path)?;
        config.validate().map_err(|message| ConfigError::Invalid {
            path: path.to_path_buf(),
            message,
        })?;
        Ok(config)
    }

    /// Reads and parses a config file, relative paths resolved, not yet validated: for a command
    /// that adjusts it (replay's sources, evaluate's outputs) before its one validation.
    pub fn read(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let mut config = Self::parse(&text).map_err(|message| ConfigError::Parse {
            path: path.to_path_buf(),
            message,
        })?;
        config.resolve_paths(path.parent().unwrap_or(Path::new(".")));
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
            if let Some(p) = source.path_mut() {
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
            s.validate(&at)?;
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
