//! Articulated families and their subjects.
//!
//! A family maps intrinsic parameters `beta` (proportions: they change the surface metric and so
//! the Laplace-Beltrami spectrum) to a rest-pose skeleton and implicit body. A [`Subject`] is one
//! beta, meshed once; its poses `theta` are produced by skinning that one rest mesh, so every pose of
//! a subject shares its connectivity and articulation stays measurably close to isometric.

mod biped;
mod quadruped;

use nalgebra::Vector3;
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::Serialize;

use crate::implicit::Body;
use crate::mesh::{Mesh, MeshDefect};
use crate::meshing::{mesh_body, spacing_for, MeshingSettings};
use crate::skeleton::Skeleton;
use crate::skinning::{skin, skin_weights, SkinWeights};

/// One intrinsic parameter: its name, plausible range (the uniform sampling prior) and meaning.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct BetaParameter {
    pub name: &'static str,
    pub min: f64,
    pub max: f64,
    pub description: &'static str,
}

impl BetaParameter {
    pub const fn new(name: &'static str, min: f64, max: f64, description: &'static str) -> Self {
        Self {
            name,
            min,
            max,
            description,
        }
    }
}

/// A skeleton, the implicit body around it, and how freely each joint moves (a multiplier on the
/// pose prior's standard deviation; 0 for the root).
pub struct Anatomy {
    pub skeleton: Skeleton,
    pub body: Body,
    pub mobility: Vec<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Family {
    Quadruped,
    Biped,
}

#[derive(Debug, thiserror::Error)]
pub enum SubjectError {
    #[error("{family:?} expects {expected} beta values, got {actual}")]
    BetaLength {
        family: Family,
        expected: usize,
        actual: usize,
    },
    #[error("beta parameter '{name}' = {value} is outside its range [{min}, {max}]")]
    BetaOutOfRange {
        name: &'static str,
        value: f64,
        min: f64,
        max: f64,
    },
    #[error("theta has {actual} values; this family's skeleton expects {expected}")]
    ThetaLength { expected: usize, actual: usize },
    #[error("meshing produced an invalid surface")]
    InvalidMesh(#[from] MeshDefect),
}

impl Family {
    pub const ALL: [Family; 2] = [Family::Quadruped, Family::Biped];

    pub fn name(self) -> &'static str {
        match self {
            Family::Quadruped => "quadruped",
            Family::Biped => "biped",
        }
    }

    pub fn beta_parameters(self) -> &'static [BetaParameter] {
        match self {
            Family::Quadruped => quadruped::BETA,
            Family::Biped => biped::BETA,
        }
    }

    /// The skeleton at the family's mid-range proportions (joint names and count do not depend on beta).
    pub fn reference_skeleton(self) -> Skeleton {
        self.anatomy(&self.mean_beta()).skeleton
    }

    pub fn mean_beta(self) -> Vec<f64> {
        self.beta_parameters().iter().map(|b| 0.5 * (b.min + b.max)).collect()
    }

    /// Uniform over each parameter's range.
    pub fn sample_beta(self, rng: &mut impl Rng) -> Vec<f64> {
        self.beta_parameters()
            .iter()
            .map(|b| rng.random_range(b.min..=b.max))
            .collect()
    }

    pub fn check_beta(self, beta: &[f64]) -> Result<(), SubjectError> {
        let parameters = self.beta_parameters();
        if beta.len() != parameters.len() {
            return Err(SubjectError::BetaLength {
                family: self,
                expected: parameters.len(),
                actual: beta.len(),
            });
        }
        for (parameter, &value) in parameters.iter().zip(beta) {
            // `!(a <= v && v <= b)` also rejects NaN.
            if !(parameter.min <= value && value <= parameter.max) {
                return Err(SubjectError::BetaOutOfRange {
                    name: parameter.name,
                    value,
                    min: parameter.min,
                    max: parameter.max,
                });
            }
        }
        Ok(())
    }

    fn anatomy(self, beta: &[f64]) -> Anatomy {
        match self {
            Family::Quadruped => quadruped::build(beta),
            Family::Biped => biped::build(beta),
        }
    }
}

impl std::str::FromStr for Family {
    type Err = String;
    fn from_str(text: &str) -> Result<Self, String> {
        Family::ALL
            .into_iter()
            .find(|f| f.name() == text)
            .ok_or_else(|| format!("unknown family '{text}' (known: quadruped, biped)"))
    }
}

/// How poses are drawn from the prior.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PoseMode {
    /// The rest pose (theta = 0).
    Rest,
    /// Gaussian about the rest pose, sigma 0.2 rad per bending axis (as the paper's SMAL/SMPL data).
    Gaussian,
    /// The wider "bent" mode: sigma 0.5 rad per bending axis.
    Bent,
}

impl PoseMode {
    pub fn bend_sigma(self) -> f64 {
        match self {
            PoseMode::Rest => 0.0,
            PoseMode::Gaussian => 0.2,
            PoseMode::Bent => 0.5,
        }
    }
}

/// Twist about a bone is much stiffer than bending it (and is what breaks isometry when overdone).
const TWIST_TO_BEND: f64 = 0.3;

/// How far a joint may turn: anatomical limits that every sampled pose and the walking gait keep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum JointLimit {
    /// Bends about `Skeleton::limb_axis` only, one way: `sign` (+1: the distal end goes backwards,
    /// as a knee; -1: forwards, as an elbow), at most `max` radians.
    Hinge { sign: f64, max: f64 },
    /// Turns any way, at most `max` radians in all (hips, shoulders, spine, neck, head, tail).
    Ball { max: f64 },
}

impl JointLimit {
    /// Whether `rotation` (axis-angle) keeps this limit, about `limb_axis` for a hinge.
    pub fn holds(self, rotation: &Vector3<f64>, limb_axis: &Vector3<f64>) -> bool {
        let angle = rotation.norm();
        match self {
            JointLimit::Ball { max } => angle <= max + 1e-9,
            JointLimit::Hinge { sign, max } => {
                let along = rotation.dot(limb_axis);
                (rotation - along * limb_axis).norm() <= 1e-9 * (1.0 + angle)
                    && sign * along >= -1e-12
                    && angle <= max + 1e-9
            }
        }
    }
}

impl Family {
    /// A joint's anatomical limit, by its name. Quadrupeds: elbows and knees bend backwards,
    /// wrists and ankles forwards (a dog's carpus and hock); bipeds: knees backwards, elbows
    /// forwards; wrists and ankles of bipeds, and every other joint, turn within a cone.
    pub fn joint_limit(self, name: &str) -> JointLimit {
        let hinge = |sign: f64, max: f64| JointLimit::Hinge { sign, max };
        match self {
            Family::Quadruped if name.ends_with("elbow") || name.ends_with("knee") => hinge(1.0, 2.2),
            Family::Quadruped if name.ends_with("wrist") || name.ends_with("ankle") => hinge(-1.0, 1.6),
            Family::Biped if name.ends_with("knee") => hinge(1.0, 2.4),
            Family::Biped if name.ends_with("elbow") => hinge(-1.0, 2.4),
            _ if name.starts_with("tail") => JointLimit::Ball { max: 1.6 },
            _ if name.contains("spine") || name == "chest" => JointLimit::Ball { max: 0.6 },
            _ if name.contains("neck") || name == "head" => JointLimit::Ball { max: 1.0 },
            _ if name.contains("wrist") || name.contains("ankle") => JointLimit::Ball { max: 0.9 },
            _ => JointLimit::Ball { max: 1.6 },
        }
    }
}

/// Vertices per subject mesh (the paper's SMAL meshes have 3,889).
pub const DEFAULT_VERTEX_COUNT: usize = 4000;

/// Meshing grid resolutions tried in turn (cells across the thinnest part's radius).
const CELLS_PER_MIN_RADIUS: [f64; 3] = [1.4, 2.0, 3.0];

/// Skinning-weight falloff as a multiple of each part's radius, and rounds of diffusion over the
/// mesh: wider blending spreads a joint's bend over more surface and so stretches each edge less.
const SKIN_FALLOFF_PER_RADIUS: f64 = 0.4;
const SKIN_DIFFUSION_ROUNDS: usize = 4;

/// Shapes drawn for one seed at most: a drawn beta whose body does not mesh to one closed surface
/// (a limb grown into the torso makes a handle) is drawn again from the same generator.
const MAX_SHAPE_DRAWS: usize = 8;

/// One individual: a beta, its rest mesh and skinning weights. Built once, posed many times.
pub struct Subject {
    pub family: Family,
    pub beta: Vec<f64>,
    pub skeleton: Skeleton,
    pub body: Body,
    pub rest_mesh: Mesh,
    pub weights: SkinWeights,
    mobility: Vec<f64>,
}

impl Subject {
    pub fn new(family: Family, beta: Vec<f64>) -> Result<Self, SubjectError> {
        Self::with_vertex_count(family, beta, DEFAULT_VERTEX_COUNT)
    }

    /// A random subject of `family` from the generator seeded with `seed`: its first drawn shape,
    /// or, where that does not mesh to one closed surface (rare: 1 of 331 subjects in
    /// `bench/tracking.sh fit-1..16`), the next one drawn, so that every seed gives a subject and
    /// a seed's subject never changes.
    pub fn draw(family: Family, seed: u64, target_vertices: usize) -> Result<Self, SubjectError> {
        let mut rng = crate::seeds::rng(seed);
        let mut last = None;
        for _ in 0..MAX_SHAPE_DRAWS {
            match Self::with_vertex_count(family, family.sample_beta(&mut rng), target_vertices) {
                Err(SubjectError::InvalidMesh(defect)) => last = Some(defect),
                outcome => return outcome,
            }
        }
        Err(SubjectError::InvalidMesh(last.expect("at least one draw")))
    }

    pub fn with_vertex_count(family: Family, beta: Vec<f64>, target_vertices: usize) -> Result<Self, SubjectError> {
        family.check_beta(&beta)?;
        let Anatomy {
            skeleton,
            body,
            mobility,
        } = family.anatomy(&beta);
        // Coarse grids are fast but may miss a thin limb; validation decides, finer grids retry.
        let mut outcome = Err(MeshDefect::Empty);
        for cells in CELLS_PER_MIN_RADIUS {
            let settings = MeshingSettings {
                spacing: spacing_for(&body, cells),
                target_vertices,
                relaxation_rounds: 3,
            };
            let mesh = mesh_body(&body, settings);
            outcome = mesh.validate().map(|_| mesh);
            if outcome.is_ok() {
                break;
            }
        }
        let rest_mesh = outcome?;
        let weights = skin_weights(
            &rest_mesh,
            &body,
            &skeleton,
            SKIN_FALLOFF_PER_RADIUS,
            SKIN_DIFFUSION_ROUNDS,
        );
        Ok(Self {
            family,
            beta,
            skeleton,
            body,
            rest_mesh,
            weights,
            mobility,
        })
    }

    pub fn pose_dimension(&self) -> usize {
        self.skeleton.pose_dimension()
    }

    /// The subject's mesh in pose `theta` (axis-angle per non-root joint, world-aligned rest frame).
    pub fn pose(&self, theta: &[f64]) -> Result<Mesh, SubjectError> {
        if theta.len() != self.pose_dimension() {
            return Err(SubjectError::ThetaLength {
                expected: self.pose_dimension(),
                actual: theta.len(),
            });
        }
        let transforms = self
            .skeleton
            .posed_from_rest(&self.skeleton.rotations_from_theta(theta));
        Ok(skin(&self.rest_mesh, &self.weights, &transforms))
    }

    /// A pose from the prior: per joint, Gaussian bending about two axes orthogonal to the bone and
    /// a smaller twist about it, scaled by the joint's mobility, within the joint's anatomical
    /// limit (a hinge bends about its limb axis only, one way; any joint turns at most its range).
    pub fn sample_theta(&self, mode: PoseMode, rng: &mut impl Rng) -> Vec<f64> {
        self.theta_of(&PoseDraw::sample(self.family, mode, rng))
    }

    /// This subject's theta for a pose drawn once for its family ([`PoseDraw`]): the same bends,
    /// about this subject's own bone and limb axes, within the same limits, so that one draw gives
    /// every subject of a family the same pose.
    pub fn theta_of(&self, draw: &PoseDraw) -> Vec<f64> {
        assert_eq!(draw.family, self.family, "a pose drawn for another family");
        let sigma = draw.mode.bend_sigma();
        let mut theta = Vec::with_capacity(self.pose_dimension());
        for (joint, normals) in (1..self.skeleton.len()).zip(&draw.joints) {
            let limit = self.family.joint_limit(self.skeleton.joints[joint].name);
            if let JointLimit::Hinge { sign, max } = limit {
                let angle = (sigma * self.mobility[joint] * normals[0].abs()).min(max);
                theta.extend_from_slice((sign * angle * self.skeleton.limb_axis(joint)).as_slice());
                continue;
            }
            let parent = self.skeleton.joints[joint].parent.unwrap_or(0);
            let incoming = (self.skeleton.joints[joint].rest_position - self.skeleton.joints[parent].rest_position)
                .try_normalize(1e-12)
                .unwrap_or_else(Vector3::z);
            let along = self.skeleton.bone_direction(joint, incoming);
            let across = along
                .cross(&Vector3::z())
                .try_normalize(1e-9)
                .unwrap_or_else(Vector3::x);
            let across_too = along.cross(&across);
            let scale = sigma * self.mobility[joint];
            let mut rotation =
                scale * (normals[0] * across + normals[1] * across_too) + TWIST_TO_BEND * scale * normals[2] * along;
            if let JointLimit::Ball { max } = limit {
                if rotation.norm() > max {
                    rotation *= max / rotation.norm();
                }
            }
            theta.extend_from_slice(rotation.as_slice());
        }
        theta
    }
}

/// One pose of a family's prior, independent of any subject: the mode and, per non-root joint, the
/// standard normals that [`Subject::theta_of`] scales by the joint's mobility and turns about the
/// subject's axes (a hinge uses the first; a ball joint all three: across, across again, twist).
/// Drawn in the order `sample_theta` always drew them, so a subject's poses are unchanged.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseDraw {
    pub family: Family,
    pub mode: PoseMode,
    pub joints: Vec<[f64; 3]>,
}

impl PoseDraw {
    pub fn sample(family: Family, mode: PoseMode, rng: &mut impl Rng) -> Self {
        let skeleton = family.reference_skeleton();
        let mut normal = || -> f64 { StandardNormal.sample(rng) };
        let joints = skeleton.joints[1..]
            .iter()
            .map(|joint| match family.joint_limit(joint.name) {
                JointLimit::Hinge { .. } => [normal(), 0.0, 0.0],
                JointLimit::Ball { .. } => [normal(), normal(), normal()],
            })
            .collect();
        Self { family, mode, joints }
    }
}
