//! Motion: 30 Hz sequences of one subject moving smoothly, with scripted identity switches.
//!
//! The node's temporal filter needs sequences where shape (beta) is constant while pose (theta),
//! heading (yaw) and position change smoothly, and where occasionally another individual replaces
//! the first, so that fusing `z_I` and detecting the change can be tested against ground truth.
//!
//! Four kinds of motion: `walk` (a gait cycle driven by the distance travelled along a smooth
//! figure-of-eight path, heading along the path), `cross` (the same gait, back and forth along a
//! straight line 4 m long across the view, turning at its ends: a subject that passes in front of or
//! behind another, so that their paths cross in the image), `idle` (standing, turning slowly in
//! place, shifting through poses of the sigma 0.2 prior) and `stand` (idle's place and turn with
//! only a walking subject's pose drift: a walk without the gait and the path, so that what a pose
//! code does during a walk can be told from what it does while the pose holds still). All add a
//! slow random "wobble" so no two cycles repeat exactly. Every frame is a pure function of the spec
//! and its index.

use std::f64::consts::TAU;

use nalgebra::Vector3;
use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::family::{Family, PoseMode, Subject, SubjectError, DEFAULT_VERTEX_COUNT};
use crate::mesh::Mesh;
use crate::seeds;
use crate::skeleton::Skeleton;
use crate::skinning::place;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MotionKind {
    Walk,
    Idle,
    Cross,
    Stand,
}

impl MotionKind {
    /// Whether the subject walks (a gait cycle along its path) rather than stands.
    pub fn walks(self) -> bool {
        matches!(self, Self::Walk | Self::Cross)
    }
}

/// What to simulate. Checked by [`MotionSpec::validate`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct MotionSpec {
    /// The family of each successive subject, cycled (one family: every subject is of it).
    pub families: Vec<Family>,
    pub kind: MotionKind,
    /// Frames per second.
    pub fps: f64,
    /// Length of the sequence (s).
    pub duration: f64,
    /// Times (s) at which the next subject replaces the current one, increasing.
    pub switch_times: Vec<f64>,
    /// Half-size of the area the subject wanders in (m): `[along x, along y]`.
    pub area: [f64; 2],
    pub seed: u64,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MotionError {
    #[error("motion parameter '{0}' must be positive and finite, got {1}")]
    NotPositive(&'static str, f64),
    #[error("at least one family is needed")]
    NoFamily,
    #[error("switch times must increase and lie inside (0, duration = {duration}); got {times:?}")]
    BadSwitchTimes { times: Vec<f64>, duration: f64 },
    #[error("{frames} frames requested; at most {max} per sequence")]
    TooManyFrames { frames: usize, max: usize },
}

/// One day at 30 Hz: far beyond any test or recording, small enough to index safely.
const MAX_FRAMES: usize = 30 * 86_400;

impl MotionSpec {
    pub fn validate(&self) -> Result<(), MotionError> {
        for (name, value) in [
            ("fps", self.fps),
            ("duration", self.duration),
            ("area[0]", self.area[0]),
            ("area[1]", self.area[1]),
        ] {
            if !(value > 0.0 && value.is_finite()) {
                return Err(MotionError::NotPositive(name, value));
            }
        }
        if self.families.is_empty() {
            return Err(MotionError::NoFamily);
        }
        let frames = (self.fps * self.duration).round();
        if frames > MAX_FRAMES as f64 {
            return Err(MotionError::TooManyFrames {
                frames: frames as usize,
                max: MAX_FRAMES,
            });
        }
        let increasing = self.switch_times.windows(2).all(|w| w[0] < w[1]);
        let inside = self.switch_times.iter().all(|&t| t > 0.0 && t < self.duration);
        if !increasing || !inside {
            return Err(MotionError::BadSwitchTimes {
                times: self.switch_times.clone(),
                duration: self.duration,
            });
        }
        Ok(())
    }

    pub fn frame_count(&self) -> usize {
        ((self.fps * self.duration).round() as usize).max(1)
    }

    pub fn subject_count(&self) -> usize {
        self.switch_times.len() + 1
    }
}

/// Ground truth of one frame, in the world frame (metres, z up, ground at z = 0).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FrameTruth {
    pub frame: usize,
    /// Seconds since the start of the sequence.
    pub time: f64,
    pub subject: String,
    pub family: Family,
    pub beta: Vec<f64>,
    /// Axis-angle per non-root joint (the family's joint order), radians.
    pub theta: Vec<f64>,
    /// Heading: rotation about +z of the subject's forward (+x at rest), radians, unwrapped.
    pub yaw: f64,
    pub translation: [f64; 3],
    /// Gait cycles completed (walk) or 0 (idle).
    pub gait_phase: f64,
}

/// A built sequence: its subjects (meshed once each) and its smooth trajectories.
pub struct Motion {
    pub spec: MotionSpec,
    subjects: Vec<(String, Subject)>,
    path: Path,
    wobbles: Vec<Wobble>,
}

impl Motion {
    /// Builds every subject of the script (in parallel; each takes about half a second).
    pub fn new(spec: MotionSpec) -> Result<Self, MotionBuildError> {
        spec.validate()?;
        let subjects = (0..spec.subject_count())
            .into_par_iter()
            .map(|index| {
                let family = spec.families[index % spec.families.len()];
                let seed = seeds::derive(spec.seed, &[1, index as u64]);
                let subject = Subject::draw(family, seed, DEFAULT_VERTEX_COUNT)?;
                Ok((format!("{}-{:08x}", family.name(), seed as u32), subject))
            })
            .collect::<Result<Vec<_>, SubjectError>>()?;
        let path = Path::new(&spec, &subjects.iter().map(|(_, s)| s).collect::<Vec<_>>());
        let wobbles = subjects
            .iter()
            .enumerate()
            .map(|(index, (_, subject))| {
                let mut rng = seeds::rng(seeds::derive(spec.seed, &[2, index as u64]));
                Wobble::sample(subject, spec.kind, &mut rng)
            })
            .collect();
        Ok(Self {
            spec,
            subjects,
            path,
            wobbles,
        })
    }

    pub fn frame_count(&self) -> usize {
        self.spec.frame_count()
    }

    /// The subject's yaw at frame `index` (radians, unwrapped): the path alone, without posing a
    /// mesh.
    pub fn yaw_at(&self, index: usize) -> f64 {
        self.path.at(index).yaw
    }

    /// Which subject is on stage at `time`.
    fn subject_index(&self, time: f64) -> usize {
        self.spec.switch_times.iter().filter(|&&t| t <= time).count()
    }

    /// Where the subject stands at frame `index` (m, world x, y; before any stage offset).
    pub fn position_at(&self, index: usize) -> [f64; 2] {
        self.path.at(index).position
    }

    /// Ground truth and the posed, placed mesh of frame `index`.
    pub fn frame(&self, index: usize) -> Result<(FrameTruth, Mesh), SubjectError> {
        let time = index as f64 / self.spec.fps;
        let subject_index = self.subject_index(time);
        let (id, subject) = &self.subjects[subject_index];
        let sample = self.path.at(index);
        let mut theta = self.wobbles[subject_index].theta(time);
        if self.spec.kind.walks() {
            let gait = gait_theta(&subject.skeleton, subject.family, sample.gait_phase);
            theta.iter_mut().zip(gait).for_each(|(t, g)| *t += g);
        }
        let posed = subject.pose(&theta)?;
        let translation = Vector3::new(sample.position[0], sample.position[1], 0.0);
        let mesh = place(&posed, sample.yaw, translation);
        let truth = FrameTruth {
            frame: index,
            time,
            subject: id.clone(),
            family: subject.family,
            beta: subject.beta.clone(),
            theta,
            yaw: sample.yaw,
            translation: translation.into(),
            gait_phase: sample.gait_phase,
        };
        Ok((truth, mesh))
    }
}

#[derive(Debug, thiserror::Error)]
pub enum MotionBuildError {
    #[error(transparent)]
    Spec(#[from] MotionError),
    #[error("building a subject: {0}")]
    Subject(#[from] SubjectError),
}

/// Per-frame rigid placement and gait phase, integrated once along the whole sequence.
struct Path {
    samples: Vec<PathSample>,
}

#[derive(Debug, Clone, Copy)]
struct PathSample {
    position: [f64; 2],
    yaw: f64,
    gait_phase: f64,
}

/// Period of the figure-of-eight and of a crossing's there and back (s), and turning rate when
/// idle (rad/s).
const PATH_PERIOD: f64 = 12.0;
/// Half the length of a crossing's line (m): at most 1.05 m/s mid-line, for the period above.
const CROSS_HALF_LENGTH: f64 = 2.0;
/// Largest angle between a crossing's line and the view's across direction (world y), rad.
const CROSS_SLANT: f64 = 0.45;
const IDLE_TURN_RATE: f64 = 0.35;
/// Fastest a walking subject turns (rad/s): a brisk turn on the spot. With some start phases the
/// path nearly stops and reverses, and its direction swings by up to 180 degrees within a few
/// frames (over 1,000 degrees/s); a body turns no faster than this, so there it lags the path for a
/// moment while it hardly moves.
pub const MAX_TURN_RATE: f64 = std::f64::consts::PI;

/// A path's random draws, from the spec's seed.
#[derive(Debug, Clone, Copy)]
struct PathPhases {
    x: f64,
    y: f64,
    start_yaw: f64,
    /// A crossing's line: its angle from world y (rad).
    slant: f64,
}

impl PathPhases {
    fn of(spec: &MotionSpec) -> Self {
        let mut rng = seeds::rng(seeds::derive(spec.seed, &[3]));
        let x: f64 = rng.random_range(0.0..TAU);
        let y: f64 = rng.random_range(0.0..TAU);
        let start_yaw: f64 = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        // Drawn last so that the other kinds' draws stay what they were.
        let slant = rng.random_range(-CROSS_SLANT..CROSS_SLANT);
        Self { x, y, start_yaw, slant }
    }

    /// Where a subject of `spec` stands at `t` (s) and its velocity (m/s): on a figure of eight
    /// whose lobes lie across the view (y), so its tightest turns (radius ay^2 / (8 ax), about
    /// 0.15 m for the default area) stay gentle enough to walk; crossing, back and forth along its
    /// line through the stage centre, slowing to turn at the ends; idle, at one place.
    fn at(&self, spec: &MotionSpec, t: f64) -> ([f64; 2], [f64; 2]) {
        let omega = TAU / PATH_PERIOD;
        let [ax, ay] = spec.area;
        match spec.kind {
            MotionKind::Walk => (
                [ax * (2.0 * omega * t + self.x).sin(), ay * (omega * t + self.y).sin()],
                [
                    2.0 * ax * omega * (2.0 * omega * t + self.x).cos(),
                    ay * omega * (omega * t + self.y).cos(),
                ],
            ),
            MotionKind::Cross => {
                let (along, speed) = (
                    CROSS_HALF_LENGTH * (omega * t + self.x).sin(),
                    CROSS_HALF_LENGTH * omega * (omega * t + self.x).cos(),
                );
                let direction = [self.slant.sin(), self.slant.cos()];
                (
                    [along * direction[0], along * direction[1]],
                    [speed * direction[0], speed * direction[1]],
                )
            }
            MotionKind::Idle | MotionKind::Stand => ([0.3 * ax * self.x.cos(), 0.3 * ay * self.y.cos()], [0.0, 0.0]),
        }
    }
}

/// Where a subject of `spec` stands at each frame (m, world x, y), without building it: to place
/// several subjects apart before their meshes are made.
pub fn planned_positions(spec: &MotionSpec) -> Vec<[f64; 2]> {
    let phases = PathPhases::of(spec);
    (0..spec.frame_count())
        .map(|index| phases.at(spec, index as f64 / spec.fps).0)
        .collect()
}

impl Path {
    fn new(spec: &MotionSpec, subjects: &[&Subject]) -> Self {
        let phases = PathPhases::of(spec);
        let dt = 1.0 / spec.fps;
        let mut samples = Vec::with_capacity(spec.frame_count());
        let (mut yaw, mut gait_phase) = (0.0, 0.0);
        for index in 0..spec.frame_count() {
            let t = index as f64 * dt;
            let subject = subjects[spec.switch_times.iter().filter(|&&s| s <= t).count()];
            let (position, [vx, vy]) = phases.at(spec, t);
            match spec.kind {
                MotionKind::Walk | MotionKind::Cross => {
                    let heading = vy.atan2(vx);
                    let max_turn = MAX_TURN_RATE * dt;
                    yaw = if index == 0 {
                        heading
                    } else {
                        yaw + wrap(heading - yaw).clamp(-max_turn, max_turn)
                    };
                    if index > 0 {
                        gait_phase += vx.hypot(vy) * dt / stride_length(subject);
                    }
                    samples.push(PathSample {
                        position,
                        yaw,
                        gait_phase,
                    });
                }
                MotionKind::Idle | MotionKind::Stand => samples.push(PathSample {
                    position,
                    yaw: phases.start_yaw + IDLE_TURN_RATE * t,
                    gait_phase: 0.0,
                }),
            }
        }
        Self { samples }
    }

    fn at(&self, index: usize) -> PathSample {
        self.samples[index.min(self.samples.len() - 1)]
    }
}

/// Angle wrapped to (-pi, pi].
fn wrap(angle: f64) -> f64 {
    let wrapped = angle.rem_euclid(TAU);
    if wrapped > std::f64::consts::PI {
        wrapped - TAU
    } else {
        wrapped
    }
}

/// Distance covered per gait cycle: about one and a half leg lengths.
fn stride_length(subject: &Subject) -> f64 {
    let skeleton = &subject.skeleton;
    let hip_height = skeleton
        .joints
        .iter()
        .filter(|j| j.name.contains("hip"))
        .map(|j| j.rest_position.z)
        .fold(0.0, f64::max);
    (1.5 * hip_height).max(0.2)
}

/// A walking subject's pose drift, as a share of the pose prior's: the gait carries most of the
/// pose, the drift keeps no two cycles alike (`sim dataset --gait-fraction` draws poses the same way).
pub const WALK_WOBBLE: f64 = 0.35;

/// Slow random pose drift: a few prior poses blended by sinusoids of random frequency and phase.
struct Wobble {
    poses: Vec<Vec<f64>>,
    frequencies: Vec<f64>,
    phases: Vec<f64>,
}

impl Wobble {
    const COMPONENTS: usize = 3;

    fn sample(subject: &Subject, kind: MotionKind, rng: &mut impl Rng) -> Self {
        // Walking adds a small drift on top of the gait, and standing the same drift alone; idling
        // is all drift, at the prior's scale.
        let scale = match kind {
            MotionKind::Walk | MotionKind::Cross | MotionKind::Stand => WALK_WOBBLE,
            MotionKind::Idle => 1.0,
        };
        let poses = (0..Self::COMPONENTS)
            .map(|_| {
                let theta = subject.sample_theta(PoseMode::Gaussian, rng);
                theta.into_iter().map(|t| scale * t).collect()
            })
            .collect();
        let frequencies = (0..Self::COMPONENTS).map(|_| rng.random_range(0.08..0.3)).collect();
        let phases = (0..Self::COMPONENTS).map(|_| rng.random_range(0.0..TAU)).collect();
        Self {
            poses,
            frequencies,
            phases,
        }
    }

    fn theta(&self, time: f64) -> Vec<f64> {
        let mut theta = vec![0.0; self.poses[0].len()];
        // Sum of K unit sinusoids has variance K/2: normalise back to the prior's.
        let norm = (2.0 / Self::COMPONENTS as f64).sqrt();
        for ((pose, frequency), phase) in self.poses.iter().zip(&self.frequencies).zip(&self.phases) {
            let weight = norm * (TAU * frequency * time + phase).sin();
            theta.iter_mut().zip(pose).for_each(|(t, p)| *t += weight * p);
        }
        theta
    }
}

/// Joint angles of a walking gait at `phase` (cycles). Limbs swing about the horizontal axis
/// across their bone (positive angle moves the distal end backwards); knees flex during the swing;
/// a quadruped walks in lateral sequence (hind left, fore left, hind right, fore right), a biped
/// swings its arms against its legs.
pub fn gait_theta(skeleton: &Skeleton, family: Family, phase: f64) -> Vec<f64> {
    let mut theta = vec![0.0; skeleton.pose_dimension()];
    for (joint, spec) in skeleton.joints.iter().enumerate().skip(1) {
        let name = spec.name;
        let side_offset = if name.contains("right") { 0.5 } else { 0.0 };
        let (swing, flex, axis) = match family {
            Family::Quadruped => {
                let offset = side_offset + if name.starts_with("front") { 0.25 } else { 0.0 };
                let angle = TAU * (phase + offset);
                let (swing_wave, flex_wave) = (angle.sin(), 0.5 - 0.5 * angle.cos());
                if name.ends_with("shoulder") || name.ends_with("hip") {
                    (0.3 * swing_wave, 0.0, skeleton.limb_axis(joint))
                } else if name.ends_with("elbow") || name.ends_with("knee") {
                    (0.0, 0.45 * flex_wave, skeleton.limb_axis(joint))
                } else if name.ends_with("wrist") || name.ends_with("ankle") {
                    (0.0, -0.3 * flex_wave, skeleton.limb_axis(joint))
                } else if name.starts_with("tail") {
                    (0.25 * (TAU * phase).sin(), 0.0, Vector3::z())
                } else if name == "head" {
                    (0.06 * (2.0 * TAU * phase).sin(), 0.0, Vector3::y())
                } else {
                    continue;
                }
            }
            Family::Biped => {
                let is_arm = name.contains("shoulder") || name.contains("elbow") || name.contains("wrist");
                // Arms swing against the leg on the same side.
                let offset = side_offset + if is_arm { 0.5 } else { 0.0 };
                let angle = TAU * (phase + offset);
                if name.ends_with("hip") {
                    (0.35 * angle.sin(), 0.0, skeleton.limb_axis(joint))
                } else if name.ends_with("knee") {
                    (0.0, 0.6 * (0.5 - 0.5 * angle.cos()), skeleton.limb_axis(joint))
                } else if name.ends_with("shoulder") {
                    (0.25 * angle.sin(), 0.0, skeleton.limb_axis(joint))
                } else if name.ends_with("elbow") {
                    (0.0, -0.15 - 0.15 * (0.5 - 0.5 * angle.cos()), skeleton.limb_axis(joint))
                } else if name == "head" {
                    (0.04 * (2.0 * TAU * phase).sin(), 0.0, Vector3::y())
                } else {
                    continue;
                }
            }
        };
        let rotation = (swing + flex) * axis;
        theta[3 * (joint - 1)..3 * joint].copy_from_slice(rotation.as_slice());
    }
    theta
}
