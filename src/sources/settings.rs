//! A source's settings (`[[source]]`): what every source has, and its kind's own settings, owned
//! and validated by the kind's module. Adding a source kind: its module with its settings, a
//! `SourceKind` and an `Input` variant here, its arm in `sources::start` and `sources::check`.

use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use crate::cloud::Unit;
use crate::prepare::{check_rotation, SensorPose};

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
    Files(super::files::FilesSettings),
    Mcap(super::recording::RecordingSettings),
    Zenoh(super::zenoh::ZenohSourceSettings),
    Ros2(super::ros2_topic::Ros2TopicSettings),
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

    /// The limits its source applies to every frame.
    pub fn intake(&self) -> super::outlet::Intake {
        super::outlet::Intake {
            max_points: self.max_points,
            unit: self.unit,
        }
    }

    /// The sensor pose this source sets for its stream, for prepare.
    pub fn sensor_pose(&self) -> SensorPose {
        SensorPose {
            stream: self.stream.clone(),
            rotation: self.sensor_to_gravity_rotation,
            translation: self.sensor_to_gravity_translation,
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
    pub(crate) fn validate(&self, at: &str) -> Result<(), String> {
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
    pub(crate) fn path_mut(&mut self) -> Option<&mut PathBuf> {
        match &mut self.input {
            Input::Files(own) => Some(&mut own.path),
            Input::Mcap(own) => Some(&mut own.path),
            Input::Zenoh(_) | Input::Ros2(_) => None,
        }
    }
}
