//! The published messages, schema `gdvae.state/2` (documented field by field in README.md).
//!
//! One `State` per encoded frame on `<prefix>/<node>/<stream>/state` (with `[track.objects]
//! enabled`, one per tracked object of the frame, each naming its `track`); one `Rejected` per frame that
//! was not encoded on `<prefix>/<node>/<stream>/rejected`; one `Event` per identity change on
//! `<prefix>/<node>/<stream>/event`. Adding a field is compatible; renaming or removing one bumps
//! the version in `schema`.

use serde::{Deserialize, Serialize};

pub const STATE_SCHEMA: &str = "gdvae.state/2";
pub const REJECTED_SCHEMA: &str = "gdvae.rejected/1";
pub const EVENT_SCHEMA: &str = "gdvae.event/1";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Stamps {
    /// The sensor's stamp (ns since the Unix epoch), when the input carried one.
    pub sensor_ns: Option<u64>,
    /// When the node received the frame (ns since the Unix epoch).
    pub ingest_ns: u64,
    /// When the node published this message (ns since the Unix epoch).
    pub publish_ns: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageLatency {
    pub prepare_ms: f32,
    /// Waiting for a batch and an encoder.
    pub queue_ms: f32,
    pub encode_ms: f32,
    /// Ingest to publish.
    pub total_ms: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Points {
    /// Points in the input frame (finite ones).
    pub received: usize,
    /// Points left after crop, ground and outlier removal (before subsampling to N_p).
    pub kept: usize,
}

/// What the encoder said about this frame alone.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Raw {
    /// Canonical rotation [w, x, y, z] (sign made continuous with the previous frame).
    pub q: [f32; 4],
    /// Yaw of q about the up axis, radians, unwrapped over turns.
    pub yaw: f32,
    /// 1 / (1 + mean variance of z_R): the rotation's confidence, in (0, 1].
    pub q_confidence: f32,
    /// How far the yaw copies' headings scatter about `yaw` (radians, RMS; absent with one copy):
    /// a frame whose copies disagree is one whose heading the encoder reads poorly.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub yaw_spread: Option<f32>,
    pub z_e: Vec<f32>,
    pub z_e_var: Vec<f32>,
    pub z_i: Vec<f32>,
    pub z_i_var: Vec<f32>,
}

/// Pose smoothed over time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Filtered {
    pub q: [f32; 4],
    pub yaw: f32,
    /// Standard deviation of `yaw` (radians) from the heading tracker; absent under one-euro.
    #[serde(default)]
    pub yaw_std: Option<f32>,
    pub z_e: Vec<f32>,
    /// 1 / (1 + mean variance of z_E), in (0, 1].
    pub z_e_confidence: f32,
}

/// The shape estimate: z_I fused over the frames of the current identity.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Shape {
    /// Increments at each detected identity change, from 0.
    pub identity: u64,
    pub z_i: Vec<f32>,
    pub z_i_var: Vec<f32>,
    pub frames_fused: u64,
    /// This frame was fused (false: an outlier, held out).
    pub inlier: bool,
    /// This frame's mean squared standardized distance to the estimate before it: of z_I, or of
    /// the identity projection's code when the bundle has one (`track.use_identity_projection`).
    pub distance: f32,
    /// Fraction of recent frames (up to 20, since the last change) that were fused.
    pub confidence: f32,
    /// The change detector's statistic after this frame: under `change_detector = "step"` the
    /// distance between its window and its reference (a change when it exceeds
    /// `track.step_threshold`, or `track.identity_step_threshold` on an identity projection);
    /// under `"cusum"` the CUSUM of distances (a change when it reaches `track.cusum_threshold`,
    /// or `track.identity_cusum_threshold`); under `"consecutive"` the current run of outliers.
    #[serde(default)]
    pub change_statistic: f32,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IdentityEvent {
    pub kind: String,
    pub previous: u64,
    pub identity: u64,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct State {
    pub schema: String,
    pub node: String,
    pub stream: String,
    /// The input frame's sequence number in its stream (0, 1, ...; rejections use numbers too).
    pub sequence: u64,
    /// The object's track in its stream (`[track.objects] enabled`: ids from 1, kept while the
    /// object is in view and given back when it returns); null when the node tracks the one
    /// largest object of each frame.
    pub track: Option<u64>,
    pub stamps: Stamps,
    pub latency: StageLatency,
    pub points: Points,
    /// Centre subtracted before scaling (metres, gravity frame): where the object is.
    pub centre_m: [f32; 3],
    pub raw: Raw,
    pub filtered: Filtered,
    pub shape: Shape,
    /// Set on the frame that completed an identity change.
    pub event: Option<IdentityEvent>,
    /// The N_p points the encoder saw (model units, centred on `centre_m`), for the sinks that show
    /// them (the Foxglove view); not part of the published message.
    #[serde(skip)]
    pub prepared: Option<std::sync::Arc<Vec<[f32; 3]>>>,
    /// The input cloud, decimated (metres, gravity frame), for the sinks that show it
    /// (`[publish.view] input_points`); not part of the published message.
    #[serde(skip)]
    pub input: Option<std::sync::Arc<Vec<[f32; 3]>>>,
    /// The sensor frame the input named (a ROS header's `frame_id`), for the ROS 2 sink's
    /// `/tf_static`; not part of the published message.
    #[serde(skip)]
    pub sensor_frame: Option<std::sync::Arc<str>>,
    /// With several objects: this state's place among its frame's tracked objects (index,
    /// count), for the sinks that publish a frame's objects together (ROS 2 detections); not part
    /// of the published message.
    #[serde(skip)]
    pub of_frame: Option<(usize, usize)>,
    /// The encoder's x_c (yaw copies averaged), for `evaluate --states`, on which the bundle's
    /// identity projection is fitted (`python -m gdvae fit-identity`); not part of the published
    /// message.
    #[serde(skip)]
    pub x_c: Option<std::sync::Arc<[f32]>>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Rejected {
    pub schema: String,
    pub node: String,
    pub stream: String,
    pub sequence: u64,
    /// Where it was rejected: source, prepare or encode.
    pub stage: String,
    pub reason: String,
    pub stamps: Stamps,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Event {
    pub schema: String,
    pub node: String,
    pub stream: String,
    pub sequence: u64,
    /// The state's `track` (null with one object per stream).
    #[serde(default)]
    pub track: Option<u64>,
    pub stamps: Stamps,
    pub event: IdentityEvent,
}

/// What the tracker hands the publisher.
#[derive(Debug, Clone)]
pub enum Output {
    State(Box<State>),
    Rejected(Rejected),
}

impl State {
    /// The object this state is of: its stream, or with several objects `<stream>/<track>` (the
    /// name of its frame and its drawings in the sinks).
    pub fn object_name(&self) -> std::borrow::Cow<'_, str> {
        match self.track {
            None => std::borrow::Cow::Borrowed(&self.stream),
            Some(track) => std::borrow::Cow::Owned(format!("{}/{track}", self.stream)),
        }
    }

    /// The identity event this state carries, as published on its own (`.../event`).
    pub fn event_message(&self) -> Option<Event> {
        self.event.as_ref().map(|event| Event {
            schema: EVENT_SCHEMA.into(),
            node: self.node.clone(),
            stream: self.stream.clone(),
            sequence: self.sequence,
            track: self.track,
            stamps: self.stamps.clone(),
            event: event.clone(),
        })
    }
}
