//! Track: per stream, what the encoder says frame by frame turned into estimates over time.
//!
//! - `shape`: z_I fused over the frames of one identity; identity changes found by a sequential
//!   test on how far each frame's z_I lies from the fused estimate.
//! - `heading`: the yaw tracked by a Kalman filter on angle and turn rate, fed by the encoder's yaw
//!   and the direction of motion, with the front/back sense decided by accumulated evidence.
//! - `pose`: one-euro smoothing of z_E and the rotation (and of the yaw, when `heading = "one-euro"`).
//!
//! - `association`: several objects in one stream, matched to tracks frame by frame;
//!   `objects`: those tracks, each with its own three filters (`[track.objects] enabled`).
//!
//! `StreamTracker` holds the three for one object; the pipeline's track stage owns one per stream,
//! or an `ObjectTracks` per stream when it tracks several objects.

pub mod association;
pub mod heading;
pub mod objects;
pub mod pose;
mod settings;
pub mod shape;
mod state;
mod stream;

pub use heading::{Heading, HeadingFilter};
pub use objects::{ObjectTracks, TrackedCandidate};
pub use pose::{confidence_from_log_variance, unwrap, yaw_of, OneEuro, Pose, PoseFilter};
pub use settings::{ChangeDetector, HeadingMode, IdentityDirections, Smoothing, TrackSettings};
pub use shape::{IdentityChange, ShapeFilter, ShapeUpdate};
pub use state::Observed;
pub use stream::{step_dt, with_yaw, StreamTracker, Tracked};
