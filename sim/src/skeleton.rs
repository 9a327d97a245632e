//! Kinematic trees: joints at rest and forward kinematics.
//!
//! Every family poses its subjects through the same machinery, so a pose `theta` means the same
//! thing everywhere: one axis-angle rotation per non-root joint, expressed in the world-aligned rest
//! frame (as SMPL and SMAL do). The root carries no rotation here; the rigid yaw is separate ground
//! truth, applied after skinning.

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

/// One joint of a kinematic tree.
#[derive(Debug, Clone)]
pub struct Joint {
    pub name: &'static str,
    /// Index of the parent joint; `None` only for the root. Parents always precede children.
    pub parent: Option<usize>,
    pub rest_position: Point3<f64>,
}

/// A kinematic tree in topological order (joint 0 is the root).
#[derive(Debug, Clone, Default)]
pub struct Skeleton {
    pub joints: Vec<Joint>,
}

impl Skeleton {
    /// Adds a joint and returns its index.
    pub fn add(&mut self, name: &'static str, parent: Option<usize>, rest_position: Point3<f64>) -> usize {
        debug_assert!(parent.is_none_or(|p| p < self.joints.len()));
        self.joints.push(Joint {
            name,
            parent,
            rest_position,
        });
        self.joints.len() - 1
    }

    pub fn len(&self) -> usize {
        self.joints.len()
    }

    pub fn is_empty(&self) -> bool {
        self.joints.is_empty()
    }

    /// Number of pose parameters: three per non-root joint.
    pub fn pose_dimension(&self) -> usize {
        3 * self.joints.len().saturating_sub(1)
    }

    /// Local joint rotations from a pose vector (axis-angle triples for joints 1..n).
    pub fn rotations_from_theta(&self, theta: &[f64]) -> Vec<UnitQuaternion<f64>> {
        let mut rotations = vec![UnitQuaternion::identity(); self.joints.len()];
        for (joint, rotation) in rotations.iter_mut().enumerate().skip(1) {
            let offset = 3 * (joint - 1);
            if let Some(axis_angle) = theta.get(offset..offset + 3) {
                *rotation = UnitQuaternion::from_scaled_axis(Vector3::new(axis_angle[0], axis_angle[1], axis_angle[2]));
            }
        }
        rotations
    }

    /// Forward kinematics: for each joint, the rigid map `posed_from_rest` that carries a rest-pose
    /// point attached to that joint to its posed position.
    pub fn posed_from_rest(&self, local_rotations: &[UnitQuaternion<f64>]) -> Vec<Isometry3<f64>> {
        let mut global_rotation: Vec<UnitQuaternion<f64>> = Vec::with_capacity(self.joints.len());
        let mut global_position: Vec<Point3<f64>> = Vec::with_capacity(self.joints.len());
        for (index, joint) in self.joints.iter().enumerate() {
            let local = local_rotations
                .get(index)
                .copied()
                .unwrap_or_else(UnitQuaternion::identity);
            match joint.parent {
                None => {
                    global_rotation.push(local);
                    global_position.push(joint.rest_position);
                }
                Some(parent) => {
                    let parent_rotation = global_rotation[parent];
                    let offset = joint.rest_position - self.joints[parent].rest_position;
                    global_position.push(global_position[parent] + parent_rotation * offset);
                    global_rotation.push(parent_rotation * local);
                }
            }
        }
        self.joints
            .iter()
            .enumerate()
            .map(|(index, joint)| {
                let rotation = global_rotation[index];
                let translation = global_position[index].coords - rotation * joint.rest_position.coords;
                Isometry3::from_parts(Translation3::from(translation), rotation)
            })
            .collect()
    }

    /// The horizontal axis across a limb's bone at rest: rotating a joint about it by a positive
    /// angle moves the limb's distal end backwards (-x). Knees, elbows, wrists and ankles bend
    /// about it only (see `family::JointLimit`), and the walking gait swings limbs about it.
    pub fn limb_axis(&self, joint: usize) -> Vector3<f64> {
        let bone = self.bone_direction(joint, -Vector3::z());
        Vector3::x().cross(&bone).try_normalize(1e-9).unwrap_or_else(Vector3::y)
    }

    /// Direction from a joint to its first child at rest (or `fallback` for end joints); used to
    /// separate bending from twisting when sampling poses.
    pub fn bone_direction(&self, joint: usize, fallback: Vector3<f64>) -> Vector3<f64> {
        self.joints
            .iter()
            .find(|child| child.parent == Some(joint))
            .map(|child| child.rest_position - self.joints[joint].rest_position)
            .and_then(|d| d.try_normalize(1e-12))
            .unwrap_or(fallback)
    }
}
