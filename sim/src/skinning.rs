//! Skinning: how a rest mesh follows its skeleton.
//!
//! Weights come from the implicit parts (a vertex belongs to the part whose surface it lies on,
//! blended where parts meet) and are diffused over the mesh so joints bend smoothly. Blending uses
//! dual quaternions rather than linear blend skinning: LBS collapses volume at bent joints and
//! "candy-wraps" under twist, which would break the near-isometry the training signal relies on.

use nalgebra::{Isometry3, Point3, Quaternion, UnitQuaternion, Vector3};

use crate::implicit::Body;
use crate::mesh::Mesh;
use crate::skeleton::Skeleton;

/// At most this many joints influence a vertex.
const INFLUENCES: usize = 4;

/// Per-vertex joint influences, weights summing to one.
#[derive(Debug, Clone)]
pub struct SkinWeights {
    pub influences: Vec<Vec<(usize, f64)>>,
}

/// Weights from part distances: `exp(-(d_part - d_nearest) / (falloff_per_radius * r_part))`, summed
/// per joint, then `diffusion_rounds` of neighbour averaging over the mesh. Scaling the falloff by the
/// part's radius spreads a bend over a zone as wide as the lever arm that moves it, so a hip joint in
/// a thick torso blends over centimetres, not millimetres.
pub fn skin_weights(
    mesh: &Mesh,
    body: &Body,
    skeleton: &Skeleton,
    falloff_per_radius: f64,
    diffusion_rounds: usize,
) -> SkinWeights {
    let joint_count = skeleton.len();
    let mut dense: Vec<Vec<f64>> = mesh
        .positions
        .iter()
        .map(|p| {
            let distances: Vec<f64> = body.parts.iter().map(|part| part.shape.distance(p)).collect();
            let nearest = distances.iter().copied().fold(f64::INFINITY, f64::min);
            let mut weights = vec![0.0; joint_count];
            for (part, d) in body.parts.iter().zip(&distances) {
                let falloff = falloff_per_radius * 0.5 * (part.shape.start_radius + part.shape.end_radius);
                weights[part.joint] += (-(d - nearest) / falloff).exp();
            }
            weights
        })
        .collect();

    let neighbours = mesh.vertex_neighbours();
    for _ in 0..diffusion_rounds {
        dense = dense
            .iter()
            .zip(&neighbours)
            .map(|(own, adjacent)| {
                let mut mixed: Vec<f64> = own.iter().map(|w| 0.5 * w).collect();
                let share = 0.5 / adjacent.len().max(1) as f64;
                for &n in adjacent {
                    for (m, w) in mixed.iter_mut().zip(&dense[n as usize]) {
                        *m += share * w;
                    }
                }
                mixed
            })
            .collect();
    }

    let influences = dense
        .into_iter()
        .map(|weights| {
            let mut ranked: Vec<(usize, f64)> = weights.into_iter().enumerate().filter(|(_, w)| *w > 1e-6).collect();
            ranked.sort_unstable_by(|a, b| b.1.total_cmp(&a.1));
            ranked.truncate(INFLUENCES);
            let total: f64 = ranked.iter().map(|(_, w)| w).sum();
            ranked.iter_mut().for_each(|(_, w)| *w /= total);
            ranked
        })
        .collect();
    SkinWeights { influences }
}

/// A rigid motion as a unit dual quaternion `real + eps * dual`.
#[derive(Debug, Clone, Copy)]
struct DualQuaternion {
    real: Quaternion<f64>,
    dual: Quaternion<f64>,
}

impl DualQuaternion {
    fn from_isometry(isometry: &Isometry3<f64>) -> Self {
        let real = *isometry.rotation.quaternion();
        let t = isometry.translation.vector;
        let dual = Quaternion::new(0.0, t.x, t.y, t.z) * real * 0.5;
        Self { real, dual }
    }
}

/// Poses the rest mesh: each vertex moved by the normalised blend of its joints' dual quaternions.
pub fn skin(rest: &Mesh, weights: &SkinWeights, posed_from_rest: &[Isometry3<f64>]) -> Mesh {
    let dual: Vec<DualQuaternion> = posed_from_rest.iter().map(DualQuaternion::from_isometry).collect();
    let positions = rest
        .positions
        .iter()
        .zip(&weights.influences)
        .map(|(p, influences)| {
            let Some(&(pivot_joint, _)) = influences.first() else {
                return *p;
            };
            let pivot = dual[pivot_joint].real;
            let mut real = Quaternion::new(0.0, 0.0, 0.0, 0.0);
            let mut dual_part = Quaternion::new(0.0, 0.0, 0.0, 0.0);
            for &(joint, weight) in influences {
                // Antipodal quaternions describe the same rotation; blend on one hemisphere.
                let sign = if dual[joint].real.dot(&pivot) < 0.0 {
                    -weight
                } else {
                    weight
                };
                real += dual[joint].real * sign;
                dual_part += dual[joint].dual * sign;
            }
            let norm = real.norm();
            let (real, dual_part) = (real / norm, dual_part / norm);
            let rotation = UnitQuaternion::new_unchecked(real);
            let translation = (dual_part * real.conjugate() * 2.0).imag();
            Point3::from(rotation * p.coords + translation)
        })
        .collect();
    Mesh {
        positions,
        triangles: rest.triangles.clone(),
    }
}

/// Rotation about the up (z) axis followed by a translation: the rigid ground truth of a frame.
pub fn place(mesh: &Mesh, yaw: f64, translation: Vector3<f64>) -> Mesh {
    let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
    Mesh {
        positions: mesh
            .positions
            .iter()
            .map(|p| Point3::from(rotation * p.coords + translation))
            .collect(),
        triangles: mesh.triangles.clone(),
    }
}
