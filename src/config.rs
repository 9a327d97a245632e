//! The node's one settings type: everything the pipeline does, read from one TOML file.
//!
//! Every section has defaults (so an empty file is a valid config), unknown keys are refused
//! (`deny_unknown_fields`: a typo must not silently fall back to a default), and `validate` checks
//! the values once, so the stages can trust them. `config/default.toml` documents every key.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

// Each stage owns its settings (type, defaults, validation); they are re-exported here, where the
// one settings type gathers them.
pub use crate::prepare::{OutlierMethod, OutlierSettings, PrepareSettings};
pub use crate::publish::{Format, PublishSettings, Ros2Settings};
pub use crate::sources::zenoh::WireFormat;
pub use crate::sources::{Input, SourceKind, SourceSettings};
pub use crate::track::{ChangeDetector, HeadingMode, Smoothing, TrackSettings};
pub use crate::zenoh_session::{NodeSettings, ZenohSettings};

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
    /// Test-time yaw copies per frame (each turned by 360°/K about +z, answers fused); 1: off.
    pub yaw_copies: usize,
}

impl Default for ModelSettings {
    fn default() -> Self {
        Self {
            bundle: PathBuf::from("models/bundles/h200-fo-nodeid"),
            onnxruntime: None,
            workers: 1,
            threads: 2,
            spin: false,
            max_batch: 8,
            max_wait_ms: 2.0,
            yaw_copies: 4,
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
    /// A live feed silent for longer than this (seconds) that then resumes counts as a gap
    /// (`feed_gaps` in the counters, a warning in the log). 0: not watched.
    pub feed_gap_s: f64,
}

impl Default for PipelineSettings {
    fn default() -> Self {
        Self {
            queue: 16,
            prepare_workers: 2,
            summary_seconds: 5.0,
            feed_gap_s: 1.0,
        }
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
        if let Some(p) = self.zenoh.config.as_mut() {
            resolve(p);
        }
        if let Some(p) = self.model.onnxruntime.as_mut() {
            resolve(p);
        }
        if let Some(jsonl) = self.publish.jsonl.as_mut().filter(|j| *j != "-") {
            let mut path = PathBuf::from(&*jsonl);
            resolve(&mut path);
            *jsonl = path.display().to_string();
        }
        if let Some(mcap) = self.publish.mcap.as_mut() {
            let mut path = PathBuf::from(&*mcap);
            resolve(&mut path);
            *mcap = path.display().to_string();
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
        if !(1..=16).contains(&m.yaw_copies) {
            return Err(format!("model.yaw_copies = {} must be within 1..=16", m.yaw_copies));
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
        if !(self.pipeline.feed_gap_s >= 0.0 && self.pipeline.feed_gap_s.is_finite()) {
            return Err("pipeline.feed_gap_s must be finite and >= 0 (0: off)".into());
        }
        self.prepare.validate()?;
        self.track.validate()?;
        self.publish.validate()?;
        self.zenoh.validate()?;
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
