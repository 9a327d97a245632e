//! One stream's three filters together (`StreamTracker`): a frame's codes in, what the filters
//! say out (`Tracked`); `state.rs` turns that into the published state.

use super::heading::{Heading, HeadingFilter};
use super::pose::{self, yaw_of, Pose, PoseFilter};
use super::settings::{HeadingMode, TrackSettings};
use super::shape::{ShapeFilter, ShapeUpdate};

/// The three filters of one stream.
#[derive(Debug, Clone)]
pub struct StreamTracker {
    pub shape: ShapeFilter,
    pub pose: PoseFilter,
    pub heading: HeadingFilter,
    mode: HeadingMode,
}

/// What the filters say after one frame.
#[derive(Debug, Clone)]
pub struct Tracked {
    pub shape: ShapeUpdate,
    /// z_E and the rotation smoothed; with the tracker, `q` and `yaw` carry the tracked heading.
    pub pose: Pose,
    /// The tracker's output (None under `heading = "one-euro"`).
    pub heading: Option<Heading>,
}

impl StreamTracker {
    pub fn new(settings: &TrackSettings) -> Self {
        Self {
            shape: ShapeFilter::new(settings),
            pose: PoseFilter::new(settings),
            heading: HeadingFilter::new(settings),
            mode: settings.heading,
        }
    }

    /// One encoded frame: z_I (mean, log-variance), the rotation q [w, x, y, z] with the scatter of
    /// the encoder's yaw copies (`Encoding::yaw_spread`), z_E, the object's centre (m, gravity
    /// frame) and the time since the stream's previous frame (s). Without x_c: for filters on z_I
    /// (an identity projection reads x_c; the pipeline calls [`StreamTracker::update_coded`]).
    pub fn update(
        &mut self,
        z_i: (&[f32], &[f32]),
        (q, yaw_spread): ([f32; 4], Option<f32>),
        z_e: &[f32],
        centre_m: [f32; 3],
        dt: f32,
    ) -> Tracked {
        self.update_coded(z_i, &[], (q, yaw_spread), z_e, centre_m, dt)
    }

    /// [`StreamTracker::update`] with the encoder's x_c, which the shape filter's identity
    /// projection reads when the bundle has one.
    pub fn update_coded(
        &mut self,
        z_i: (&[f32], &[f32]),
        x_c: &[f32],
        (q, yaw_spread): ([f32; 4], Option<f32>),
        z_e: &[f32],
        centre_m: [f32; 3],
        dt: f32,
    ) -> Tracked {
        let shape = self.shape.update_coded(z_i.0, z_i.1, x_c);
        if shape.change.is_some() {
            self.heading.reset();
        }
        let mut pose = self.pose.update(q, z_e, dt);
        let heading = match self.mode {
            HeadingMode::OneEuro => None,
            HeadingMode::Tracker => {
                let centre = [centre_m[0] as f64, centre_m[1] as f64];
                let heading =
                    self.heading
                        .update_read(pose.yaw_raw as f64, yaw_spread.map(f64::from), centre, dt as f64);
                // Keep the smoothed rotation's tilt, give it the tracked yaw.
                pose.q = with_yaw(pose.q, heading.yaw as f32);
                pose.yaw = heading.yaw as f32;
                Some(heading)
            }
        };
        Tracked { shape, pose, heading }
    }
}

/// The time step the filters take for a frame `gap_s` seconds after the object's previous one: the
/// gap itself, or the nominal period (`nominal_dt`) when it is not a usable step (none, backwards,
/// or a second or more: the object was away, and its filters do not extrapolate across that).
pub fn step_dt(gap_s: Option<f32>, nominal_dt: f32) -> f32 {
    match gap_s {
        Some(gap) if gap > 0.0 && gap < 1.0 => gap,
        _ => nominal_dt,
    }
}

/// `q` [w, x, y, z] turned about +z so that its yaw becomes `yaw`.
pub fn with_yaw(q: [f32; 4], yaw: f32) -> [f32; 4] {
    pose::turn_rotation(q, yaw - yaw_of(&q))
}
