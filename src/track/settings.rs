//! `[track]`: the settings of the three filters (shape fusion and identity changes, heading, pose
//! smoothing), their defaults and their one validation. A leaf the filters read.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Smoothing {
    None,
    OneEuro,
}

/// How the published (filtered) heading is made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum HeadingMode {
    /// The heading tracker (`track::heading`).
    Tracker,
    /// The yaw of the one-euro-smoothed rotation.
    OneEuro,
}

/// How identity changes are found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ChangeDetector {
    /// CUSUM of the per-frame distances (`track::shape`).
    Cusum,
    /// `switch_frames` frames beyond the gate in a row.
    Consecutive,
    /// A step between the last `step_window` frames and up to `step_reference` frames before them
    /// (`track::shape`): slow wander within one subject moves both sides together.
    Step,
}

/// The bundle's identity projection as the shape filter uses it: its rows, each a direction of x_c
/// (`bundle::IdentityProjection::matrix`).
pub type IdentityDirections = std::sync::Arc<Vec<Vec<f32>>>;

/// `[track]`: every setting of the track stage. `config/default.toml` documents each key;
/// docs/tracking.md says how to tune them for a new bundle or sensor.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackSettings {
    /// A frame's z_I is an outlier (not fused) when its mean squared standardized distance to the
    /// fused estimate (per dimension) exceeds this.
    pub shape_gate: f32,
    /// A change needs at least this many frames of evidence.
    pub switch_frames: usize,
    /// Floor on each fused z_I variance, so the filter never becomes certain beyond what
    /// correlated frames justify (and follows slow drift). In squared z_I spreads (the bundle's
    /// `calibration.z_I_spread`, [`TrackSettings::in_model_units`]).
    pub min_shape_variance: f32,
    /// Multiplier on the encoder's z_I variances after the bundle's own calibration (manifest
    /// `calibration`): the sensor's share (frame-to-frame jitter the kit's views do not have).
    pub shape_variance_scale: f32,
    pub change_detector: ChangeDetector,
    /// CUSUM drift allowance k: distances below it count as agreement.
    pub cusum_drift: f32,
    /// CUSUM threshold h: a change is reported when the statistic reaches it.
    pub cusum_threshold: f32,
    /// Step detector: the last `step_window` frames are compared with up to `step_reference`
    /// frames before them (since the last change), each side the precision-weighted mean of its
    /// frames; a change when their mean squared standardized distance exceeds `step_threshold`
    /// (`identity_step_threshold` on the identity projection's code).
    pub step_window: usize,
    pub step_reference: usize,
    pub step_threshold: f32,
    pub identity_step_threshold: f32,
    /// Floor on one frame's z_I variance in the step detector, in squared z_I spreads: a frame
    /// the encoder is sure of weighs no more than this allows, since frames of one subject wander
    /// together more than the encoder's variances say.
    pub step_min_variance: f32,
    /// A frame enters the step detector clipped to within this many standard deviations (its own
    /// and the reference mean's) of the reference's mean, per dimension: one wild frame then
    /// moves the window's mean a bounded amount (`inf`: no clip).
    pub step_clip: f32,
    /// Detect identity changes on the bundle's identity projection of x_c when it has one
    /// (`calibration.identity_projection`), else on z_I.
    pub use_identity_projection: bool,
    /// The CUSUM's drift and threshold on the identity projection's code (unit within-subject
    /// spread per direction), in place of `cusum_drift` and `cusum_threshold`.
    pub identity_cusum_drift: f32,
    pub identity_cusum_threshold: f32,
    /// Floor on each fused variance of the identity projection's code (its units: unit
    /// within-subject spread per direction), as `min_shape_variance` is z_I's.
    pub min_identity_variance: f32,
    /// The bundle's identity projection (rows of weights on x_c), set from the bundle at start;
    /// not a config key.
    #[serde(skip)]
    pub identity_projection: Option<IdentityDirections>,
    /// Smoothing of z_E and the rotation.
    pub smoothing: Smoothing,
    /// One-euro filter: cutoff at rest (Hz) and its increase per unit of speed.
    pub min_cutoff_hz: f32,
    pub beta: f32,
    /// Frame rate assumed when frames carry no usable stamps.
    pub nominal_rate_hz: f32,
    /// The published heading: the tracker, or the one-euro-smoothed yaw.
    pub heading: HeadingMode,
    /// Standard deviation of the encoder's yaw as a measurement (degrees).
    pub heading_std_deg: f32,
    /// Standard deviation of the heading's angular acceleration (rad/s^2): how fast turns may change.
    pub heading_accel_std: f32,
    /// The turn rate fades with this time constant (s) unless the readings renew it (0: kept).
    pub heading_rate_time_s: f32,
    /// Use the direction of motion of the object's centre as a heading measurement.
    pub heading_from_motion: bool,
    /// The centre's velocity is its least-squares slope over this window (s).
    pub motion_window_s: f32,
    /// Below this speed (m/s) the direction of motion is not used.
    pub motion_min_speed_mps: f32,
    /// A walk goes somewhere: the motion is used only once the centre travelled this far (m) over
    /// twice `motion_window_s` (0: no such test).
    pub motion_min_travel_m: f32,
    /// A motion whose centre travelled this far (m) over twice `motion_window_s` is a walk, and
    /// votes `heading_walk_vote` on front and back instead of 1 (0: no walks told apart).
    pub motion_walk_travel_m: f32,
    /// Standard deviation of the motion direction as a measurement (degrees), at twice the
    /// minimum speed and above; it widens towards the minimum speed.
    pub motion_heading_std_deg: f32,
    /// Most front/back evidence the track keeps (log-odds): how much contrary evidence it takes to
    /// turn the track round by 180 degrees.
    pub heading_flip_evidence: f32,
    /// Front/back evidence one encoder frame adds (log-odds; a frame of motion adds 1, of a walk
    /// `heading_walk_vote`), before it is scaled down for an encoder that jitters more than
    /// `heading_std_deg`.
    pub heading_encoder_vote: f32,
    /// A frame's encoder reading counts as noisier by this many times the scatter of its yaw
    /// copies (their RMS about the reading, added to the noise in quadrature; 0: copies ignored).
    pub heading_copy_spread_scale: f32,
    /// Front/back evidence one frame of a walk adds (log-odds; other motion adds 1).
    pub heading_walk_vote: f32,
    /// Share of encoder yaws taken to be wild (any angle): a reading that fits neither the track's
    /// front nor its back moves it little.
    pub heading_wild_share: f32,
    /// Share of the other encoder yaws taken to read the back for the front.
    pub heading_back_share: f32,
    /// Several objects per stream (`[track.objects]`).
    pub objects: super::association::AssociationSettings,
}

impl Default for TrackSettings {
    fn default() -> Self {
        Self {
            shape_gate: 2.0,
            switch_frames: 5,
            min_shape_variance: 3.434e-3,
            shape_variance_scale: 2.2,
            change_detector: ChangeDetector::Step,
            cusum_drift: 3.0,
            cusum_threshold: 10.0,
            step_window: 5,
            step_reference: 15,
            step_threshold: 7.0,
            identity_step_threshold: 25.0,
            step_min_variance: 0.1,
            step_clip: 4.0,
            use_identity_projection: false,
            identity_cusum_drift: 9.0,
            identity_cusum_threshold: 20.0,
            min_identity_variance: 4e-4,
            identity_projection: None,
            smoothing: Smoothing::OneEuro,
            min_cutoff_hz: 1.0,
            beta: 0.5,
            nominal_rate_hz: 30.0,
            heading: HeadingMode::Tracker,
            heading_std_deg: 12.0,
            heading_accel_std: 12.0,
            heading_rate_time_s: 0.5,
            heading_from_motion: true,
            motion_window_s: 1.0,
            motion_min_speed_mps: 0.3,
            motion_min_travel_m: 0.0,
            motion_walk_travel_m: 0.5,
            motion_heading_std_deg: 20.0,
            heading_flip_evidence: 12.0,
            heading_encoder_vote: 1.0,
            heading_copy_spread_scale: 1.0,
            heading_walk_vote: 3.0,
            heading_wild_share: 0.1,
            heading_back_share: 0.05,
            objects: Default::default(),
        }
    }
}

impl TrackSettings {
    /// The settings with their z_I distances, given in z_I spreads (how far one subject's z_I
    /// wanders over its poses and views), turned into model units for a bundle whose spread is
    /// `spread`: a bundle whose z_I is twice as wide gets twice the distances, and the same
    /// behaviour. `min_shape_variance` and `step_min_variance` (squared), `objects.shape_scale`,
    /// `objects.reid_distance`.
    pub fn in_model_units(mut self, spread: f32) -> Self {
        self.min_shape_variance *= spread * spread;
        self.step_min_variance *= spread * spread;
        self.objects.shape_scale *= spread;
        self.objects.reid_distance *= spread;
        self
    }

    /// The identity directions the shape filter works on: the bundle's, unless
    /// `use_identity_projection` is off (None: on z_I).
    pub fn identity_directions(&self) -> Option<&IdentityDirections> {
        self.identity_projection
            .as_ref()
            .filter(|_| self.use_identity_projection)
    }

    /// The CUSUM's drift and threshold in the space the shape filter works in.
    pub fn cusum(&self) -> (f32, f32) {
        match self.identity_directions() {
            Some(_) => (self.identity_cusum_drift, self.identity_cusum_threshold),
            None => (self.cusum_drift, self.cusum_threshold),
        }
    }

    /// The step detector's threshold in the space the shape filter works in.
    pub fn step_threshold(&self) -> f32 {
        match self.identity_directions() {
            Some(_) => self.identity_step_threshold,
            None => self.step_threshold,
        }
    }

    /// The change detector's threshold on the published `change_statistic` in the space the
    /// shape filter works in (the consecutive rule's: `switch_frames` outliers).
    pub fn change_threshold(&self) -> f32 {
        match self.change_detector {
            ChangeDetector::Cusum => self.cusum().1,
            ChangeDetector::Consecutive => self.switch_frames as f32,
            ChangeDetector::Step => self.step_threshold(),
        }
    }

    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("shape_gate", self.shape_gate),
            ("min_shape_variance", self.min_shape_variance),
            ("shape_variance_scale", self.shape_variance_scale),
            ("cusum_drift", self.cusum_drift),
            ("cusum_threshold", self.cusum_threshold),
            ("identity_cusum_drift", self.identity_cusum_drift),
            ("identity_cusum_threshold", self.identity_cusum_threshold),
            ("step_threshold", self.step_threshold),
            ("identity_step_threshold", self.identity_step_threshold),
            ("step_min_variance", self.step_min_variance),
            ("min_identity_variance", self.min_identity_variance),
            ("min_cutoff_hz", self.min_cutoff_hz),
            ("nominal_rate_hz", self.nominal_rate_hz),
            ("heading_std_deg", self.heading_std_deg),
            ("heading_accel_std", self.heading_accel_std),
            ("motion_window_s", self.motion_window_s),
            ("motion_min_speed_mps", self.motion_min_speed_mps),
            ("motion_heading_std_deg", self.motion_heading_std_deg),
            ("heading_flip_evidence", self.heading_flip_evidence),
            ("heading_encoder_vote", self.heading_encoder_vote),
            ("heading_walk_vote", self.heading_walk_vote),
        ];
        for (name, value) in positive {
            if !(value > 0.0 && value.is_finite()) {
                return Err(format!("track.{name} = {value} must be positive and finite"));
            }
        }
        let shares = [
            ("heading_wild_share", self.heading_wild_share, 1.0),
            ("heading_back_share", self.heading_back_share, 0.5),
        ];
        for (name, value, below) in shares {
            if !(value >= 0.0 && value < below) {
                return Err(format!("track.{name} = {value} must be at least 0 and below {below}"));
            }
        }
        for (name, value) in [
            ("heading_copy_spread_scale", self.heading_copy_spread_scale),
            ("heading_rate_time_s", self.heading_rate_time_s),
            ("motion_min_travel_m", self.motion_min_travel_m),
            ("motion_walk_travel_m", self.motion_walk_travel_m),
        ] {
            if !(value >= 0.0 && value.is_finite()) {
                return Err(format!("track.{name} = {value} must be at least 0 and finite"));
            }
        }
        if self.switch_frames == 0 {
            return Err("track.switch_frames must be at least 1".into());
        }
        if !(self.step_clip > 0.0) {
            return Err(format!(
                "track.step_clip = {} must be positive (inf: no clip)",
                self.step_clip
            ));
        }
        if self.step_window == 0 {
            return Err("track.step_window must be at least 1".into());
        }
        if self.step_reference < self.switch_frames {
            return Err(format!(
                "track.step_reference = {} must be at least switch_frames ({}): the step detector compares its \
                 window with at least that many frames before it",
                self.step_reference, self.switch_frames
            ));
        }
        if !(self.beta >= 0.0 && self.beta.is_finite()) {
            return Err(format!("track.beta = {} must be >= 0", self.beta));
        }
        self.objects.validate()
    }
}
