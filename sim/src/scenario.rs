//! A scenario: a motion script seen by a depth camera. It yields sensor frames (depth image, point
//! cloud in the camera's optical frame, and the frame's ground truth), shared by MCAP recordings
//! (`recording`) and the live zenoh feed (`sim feed`).
//!
//! Besides the script's subject (the primary, whose switches model identity changes), a scenario
//! may hold other subjects, each on its own path on a stage shifted sideways (so that paths cross
//! in the image and one subject hides another), and any subject may leave the view for given
//! intervals. Each frame's ground truth then lists every subject: its pose and shape, whether it
//! is in the scene, and how many of the cloud's points it gave (0 when hidden).

use nalgebra::{Point3, Vector3};
use rand::Rng;
use serde::{Deserialize, Serialize};

use crate::camera::{ground_box, CameraError, DepthCamera, DepthImage, Intrinsics, Scene, StereoModel};
use crate::mesh::Mesh;
use crate::motion::{FrameTruth, Motion, MotionBuildError, MotionSpec};
use crate::seeds;

/// Where the camera stands and what else is in view.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ViewSpec {
    /// Horizontal distance from the camera to the centre of the stage (m).
    pub camera_distance: f64,
    pub camera_height: f64,
    /// Height of the point the camera looks at, above the stage centre (m).
    pub target_height: f64,
    /// Azimuth of the camera around the stage, from +x (rad).
    pub camera_azimuth: f64,
    /// Half side of the ground patch (m); 0 leaves the ground out.
    pub ground_half_extent: f64,
    /// Boxes placed on the ground around the stage.
    pub clutter: usize,
    /// Point-cloud decimation: keep every n-th pixel in each direction.
    pub decimation: usize,
}

impl Default for ViewSpec {
    fn default() -> Self {
        Self {
            camera_distance: 3.2,
            camera_height: 1.3,
            target_height: 0.8,
            camera_azimuth: 0.0,
            ground_half_extent: 4.0,
            clutter: 0,
            decimation: 1,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    #[error(transparent)]
    Motion(#[from] MotionBuildError),
    #[error(transparent)]
    Camera(#[from] CameraError),
    #[error("view parameter '{0}' must be positive and finite, got {1}")]
    NotPositive(&'static str, f64),
    #[error("posing frame {0}: {1}")]
    Pose(usize, crate::family::SubjectError),
    #[error("away interval {0:?}: the subject must be one of the {1} (0: the primary) and from < to")]
    BadAway(Away, usize),
    #[error(
        "subjects {} and {} would stand {distance:.2} m apart at {time:.2} s (less than {separation} m: their \
         bodies would pass through each other); place the others' stages farther (--others-offset)",
        subjects.0, subjects.1
    )]
    TooClose {
        subjects: (usize, usize),
        distance: f64,
        time: f64,
        separation: f64,
    },
}

/// The camera's pose in the world, as a ROS transform (translation m, rotation quaternion x y z w).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct WorldFromCamera {
    pub translation: [f64; 3],
    pub rotation_xyzw: [f64; 4],
}

/// Ground truth of one sensor frame as recordings and feeds publish it (JSON): the primary
/// subject's truth flattened (as single-subject recordings always had it), and every subject's.
#[derive(Debug, Clone, Serialize)]
pub struct GroundTruthMessage<'a> {
    /// Sensor stamp of the frame's point cloud and image (ns since the Unix epoch).
    pub stamp_nanos: u64,
    #[serde(flatten)]
    pub truth: &'a FrameTruth,
    pub world_from_camera: WorldFromCamera,
    /// Points in this frame's cloud.
    pub points: usize,
    /// Every subject of the scenario, the primary first (`id` 0).
    pub subjects: &'a [SubjectTruth],
}

/// One subject's ground truth in one frame.
#[derive(Debug, Clone, Serialize)]
pub struct SubjectTruth {
    /// The subject's place in the scenario: 0 the primary, then the others in order. A track's
    /// identity for multi-object evaluation (the primary's `subject` changes at its switches).
    pub id: usize,
    /// In the scene (false while it has left the view).
    pub present: bool,
    /// Points of this frame's cloud on the subject (0 when absent, hidden or out of the image).
    pub visible_points: usize,
    #[serde(flatten)]
    pub truth: FrameTruth,
}

/// Another subject in a scenario: its own motion, its stage shifted by `offset` (m, world x, y).
pub struct Companion {
    pub motion: Motion,
    pub offset: [f64; 2],
}

/// An interval (s) in which subject `subject` (0: the primary) is out of the scene.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Away {
    pub subject: usize,
    pub from: f64,
    pub to: f64,
}

/// One simulated sensor frame.
pub struct SensorFrame {
    pub truth: FrameTruth,
    pub depth: DepthImage,
    /// Valid, decimated depth pixels unprojected to the optical frame (m).
    pub points: Vec<[f32; 3]>,
    /// Nanoseconds since the start of the sequence.
    pub offset_nanos: u64,
    /// Every subject's truth, the primary first.
    pub subjects: Vec<SubjectTruth>,
}

pub struct Scenario {
    pub motion: Motion,
    pub view: ViewSpec,
    pub camera: DepthCamera,
    /// The other subjects in view, if any.
    pub others: Vec<Companion>,
    pub away: Vec<Away>,
    clutter: Vec<Mesh>,
}

impl Scenario {
    pub fn new(motion: MotionSpec, view: ViewSpec) -> Result<Self, ScenarioError> {
        for (name, value) in [
            ("camera_distance", view.camera_distance),
            ("camera_height", view.camera_height),
            ("decimation", view.decimation as f64),
        ] {
            if !(value > 0.0 && value.is_finite()) {
                return Err(ScenarioError::NotPositive(name, value));
            }
        }
        if !(view.ground_half_extent >= 0.0 && view.target_height.is_finite() && view.camera_azimuth.is_finite()) {
            return Err(ScenarioError::NotPositive(
                "ground_half_extent",
                view.ground_half_extent,
            ));
        }
        let direction = Vector3::new(view.camera_azimuth.cos(), view.camera_azimuth.sin(), 0.0);
        let position = Point3::from(direction * view.camera_distance + Vector3::z() * view.camera_height);
        let camera = DepthCamera::looking_at(
            Intrinsics::oak_d_400p(),
            StereoModel::oak_d(),
            position,
            Point3::new(0.0, 0.0, view.target_height),
        )?;
        let clutter = place_clutter(&motion, &view);
        let motion = Motion::new(motion)?;
        Ok(Self {
            motion,
            view,
            camera,
            others: Vec::new(),
            away: Vec::new(),
            clutter,
        })
    }

    /// Adds other subjects (each its own motion script, lasting as long as the primary's, on a
    /// stage shifted by its offset) and intervals in which subjects leave the view. Refused when
    /// two subjects would stand closer than `separation` (m) at any frame while both are in the
    /// scene: bodies would pass through each other (0: no check).
    pub fn with_others(
        mut self,
        others: Vec<(MotionSpec, [f64; 2])>,
        away: Vec<Away>,
        separation: f64,
    ) -> Result<Self, ScenarioError> {
        for (spec, offset) in others {
            if !offset.iter().all(|v| v.is_finite()) {
                return Err(ScenarioError::NotPositive("offset", offset[0]));
            }
            self.others.push(Companion {
                motion: Motion::new(spec)?,
                offset,
            });
        }
        for a in &away {
            if a.subject > self.others.len() || !(a.from < a.to && a.from.is_finite() && a.to.is_finite()) {
                return Err(ScenarioError::BadAway(*a, self.others.len() + 1));
            }
        }
        self.away = away;
        if separation > 0.0 {
            self.check_separation(separation)?;
        }
        Ok(self)
    }

    /// Where subject `id` (0: the primary) stands at frame `index` (m, world x, y).
    fn position(&self, id: usize, index: usize) -> [f64; 2] {
        match id {
            0 => self.motion.position_at(index),
            _ => {
                let other = &self.others[id - 1];
                let p = other.motion.position_at(index);
                [p[0] + other.offset[0], p[1] + other.offset[1]]
            }
        }
    }

    fn check_separation(&self, separation: f64) -> Result<(), ScenarioError> {
        let fps = self.motion.spec.fps;
        let subjects = 1 + self.others.len();
        for index in 0..self.frame_count() {
            let time = index as f64 / fps;
            for a in 0..subjects {
                for b in a + 1..subjects {
                    if !(self.present(a, time) && self.present(b, time)) {
                        continue;
                    }
                    let (p, q) = (self.position(a, index), self.position(b, index));
                    let distance = (p[0] - q[0]).hypot(p[1] - q[1]);
                    if distance < separation {
                        return Err(ScenarioError::TooClose {
                            subjects: (a, b),
                            distance,
                            time,
                            separation,
                        });
                    }
                }
            }
        }
        Ok(())
    }

    fn present(&self, subject: usize, time: f64) -> bool {
        !self
            .away
            .iter()
            .any(|a| a.subject == subject && (a.from..a.to).contains(&time))
    }

    pub fn frame_count(&self) -> usize {
        self.motion.frame_count()
    }

    /// The camera's pose in the world (what a node needs as its sensor-to-gravity transform).
    pub fn world_from_camera(&self) -> WorldFromCamera {
        let pose = self.camera.world_from_camera;
        let q = pose.rotation;
        WorldFromCamera {
            translation: pose.translation.vector.into(),
            rotation_xyzw: [q.i, q.j, q.k, q.w],
        }
    }

    /// Frame `index`: deterministic given the specs (its noise has its own seed).
    pub fn frame(&self, index: usize) -> Result<SensorFrame, ScenarioError> {
        let (truth, mesh) = self.motion.frame(index).map_err(|e| ScenarioError::Pose(index, e))?;
        // Every subject's truth and mesh; the scene holds those present, then the clutter.
        let mut posed = vec![(truth.clone(), mesh)];
        for other in &self.others {
            let (mut truth, mut mesh) = other.motion.frame(index).map_err(|e| ScenarioError::Pose(index, e))?;
            let shift = Vector3::new(other.offset[0], other.offset[1], 0.0);
            mesh.positions.iter_mut().for_each(|p| *p += shift);
            truth.translation[0] += other.offset[0];
            truth.translation[1] += other.offset[1];
            posed.push((truth, mesh));
        }
        let mut subjects = Vec::with_capacity(posed.len());
        let mut meshes = Vec::with_capacity(posed.len() + self.clutter.len());
        let mut owner = Vec::new();
        for (id, (truth, mesh)) in posed.into_iter().enumerate() {
            let present = self.present(id, truth.time);
            if present {
                owner.push(id);
                meshes.push(mesh);
            }
            subjects.push(SubjectTruth {
                id,
                present,
                visible_points: 0,
                truth,
            });
        }
        meshes.extend(self.clutter.iter().cloned());
        let scene = Scene {
            meshes,
            ground_half_extent: (self.view.ground_half_extent > 0.0).then_some(self.view.ground_half_extent),
        };
        let mut rng = seeds::rng(seeds::derive(self.motion.spec.seed, &[4, index as u64]));
        let (depth, labels) = self.camera.capture_labelled(&scene, &mut rng);
        let points = depth.unproject(&self.camera.intrinsics, self.view.decimation);
        // The cloud's points on each subject, on the pixels `unproject` keeps.
        let (width, step) = (depth.width as usize, self.view.decimation.max(1));
        for v in (0..depth.height as usize).step_by(step) {
            for u in (0..width).step_by(step) {
                if let Some(&id) = owner.get(labels[v * width + u] as usize) {
                    subjects[id].visible_points += 1;
                }
            }
        }
        let offset_nanos = (truth.time * 1e9).round() as u64;
        Ok(SensorFrame {
            truth,
            depth,
            points,
            offset_nanos,
            subjects,
        })
    }
}

/// Boxes of 0.2-0.6 m outside the subject's wander area, not between it and the camera.
fn place_clutter(motion: &MotionSpec, view: &ViewSpec) -> Vec<Mesh> {
    let mut rng = seeds::rng(seeds::derive(motion.seed, &[5]));
    let clear = motion.area[0].hypot(motion.area[1]) + 0.6;
    let mut boxes = Vec::with_capacity(view.clutter);
    let mut attempts = 0;
    while boxes.len() < view.clutter && attempts < 1000 {
        attempts += 1;
        let radius = rng.random_range(clear..clear + 1.5);
        let angle: f64 = rng.random_range(-std::f64::consts::PI..std::f64::consts::PI);
        // Keep the camera's line of sight to the stage free.
        let from_camera = (angle - view.camera_azimuth).rem_euclid(std::f64::consts::TAU);
        if !(0.8..=std::f64::consts::TAU - 0.8).contains(&from_camera) {
            continue;
        }
        let size = Vector3::new(
            rng.random_range(0.2..0.6),
            rng.random_range(0.2..0.6),
            rng.random_range(0.2..0.6),
        );
        let yaw = rng.random_range(0.0..std::f64::consts::PI);
        boxes.push(ground_box(radius * angle.cos(), radius * angle.sin(), size, yaw));
    }
    boxes
}
