//! The prepare stage's settings (`[prepare]`): the sensor's pose, ground, crop, outliers,
//! clustering, sampling; their defaults and their validation.

use serde::{Deserialize, Serialize};

use super::sampling::Sampling;

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct PrepareSettings {
    /// Row-major 3x3 rotation from the sensor frame into a gravity-aligned frame (z up).
    pub sensor_to_gravity_rotation: [[f32; 3]; 3],
    /// Translation (metres) applied after the rotation.
    pub sensor_to_gravity_translation: [f32; 3],
    /// Estimate the ground plane by RANSAC on every frame and level the cloud with it (replaces the
    /// configured rotation's tilt, keeps its heading).
    pub auto_ground: bool,
    /// Remove points within `ground_tolerance_m` of the ground plane (estimated by RANSAC).
    pub remove_ground: bool,
    pub ground_tolerance_m: f32,
    pub ransac_iterations: usize,
    /// Region of interest in the gravity frame (metres): [min_x, min_y, min_z, max_x, max_y, max_z].
    pub crop: Option<[f32; 6]>,
    /// Raise the crop's floor (its min_z, when that is at or above the ground, z = 0) above the
    /// floor's depth noise: to this many times the noise's spread, measured on every frame from
    /// the points just below the ground, where nothing real lies (`prepare::floor_noise_cut`).
    /// A dense sensor leaves thousands of noisy floor points above a fixed min_z, which join into
    /// a sheet larger than the object. 0: the crop's min_z alone.
    pub floor_noise_sigmas: f32,
    /// Reduce the cropped cloud to the centroid of each occupied cube of this edge (metres) before
    /// outliers, clusters and sampling, whose cost grows with the points. 0 keeps every point.
    pub voxel_grid_m: f32,
    pub outliers: OutlierSettings,
    /// Keep only the largest cluster of points joined by neighbours closer than this (metres):
    /// drops what the crop leaves of the floor's noise and stray clutter. 0 keeps every point.
    pub cluster_m: f32,
    /// Beyond this range from the sensor (metres) the cluster radius grows with the range, as a
    /// stereo camera's depth noise does (see `prepare::RangeStretch`), so that a far object stays
    /// one cluster. 0: the same radius at every range.
    pub cluster_stretch_from_m: f32,
    /// Keep with the largest cluster those of at least `prepare::JOIN_MIN_FRACTION` of its points
    /// that lie above or below it (boxes overlapping in x and y, the middle of their height
    /// outside its own) within this distance (metres): a body whose limbs hide what joins them,
    /// seen from close by or from above, falls into pieces (see `prepare::keep_largest_cluster`).
    /// 0: the largest cluster alone. Single-object streams only (`[objects]` makes every cluster a
    /// candidate).
    pub cluster_join_m: f32,
    /// With `cluster_join_m` > 0, keep with the largest cluster the pieces of at least this many
    /// points within its footprint grown by `cluster_join_m` and wholly in the lower half of its
    /// height: legs and feet a stereo camera cut off at depth edges and in its shadows (see
    /// `prepare::keep_largest_cluster`). 0: off.
    pub cluster_join_min_points: usize,
    pub sampling: Sampling,
    /// Voxel edge (metres) for `sampling = "voxel"`.
    pub voxel_m: f32,
    /// Frames with fewer points than this after filtering are rejected (fewer than N_p are padded).
    pub min_points: usize,
    /// Seed of the random choices (sampling, RANSAC); frames are deterministic for a seed.
    pub seed: u64,
}

impl Default for PrepareSettings {
    fn default() -> Self {
        Self {
            sensor_to_gravity_rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            sensor_to_gravity_translation: [0.0; 3],
            auto_ground: false,
            remove_ground: false,
            ground_tolerance_m: 0.02,
            ransac_iterations: 100,
            crop: None,
            floor_noise_sigmas: 3.0,
            voxel_grid_m: 0.0,
            outliers: OutlierSettings::default(),
            cluster_m: 0.0,
            cluster_stretch_from_m: 3.5,
            cluster_join_m: 0.1,
            cluster_join_min_points: 10,
            sampling: Sampling::Farthest,
            voxel_m: 0.01,
            min_points: 64,
            seed: 0,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum OutlierMethod {
    None,
    Statistical,
    Radius,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct OutlierSettings {
    pub method: OutlierMethod,
    /// Statistical: neighbours per point, and the number of standard deviations of the mean
    /// neighbour distance beyond which a point is removed.
    pub neighbours: usize,
    pub std_ratio: f32,
    /// Radius: a point needs `min_neighbours` others within `radius_m`.
    pub radius_m: f32,
    pub min_neighbours: usize,
}

impl Default for OutlierSettings {
    fn default() -> Self {
        Self {
            method: OutlierMethod::None,
            neighbours: 8,
            std_ratio: 2.0,
            radius_m: 0.05,
            min_neighbours: 3,
        }
    }
}

impl PrepareSettings {
    /// Checks every value once; the message names the key.
    pub fn validate(&self) -> Result<(), String> {
        let p = self;
        check_rotation("prepare.sensor_to_gravity_rotation", &p.sensor_to_gravity_rotation)?;
        if let Some(c) = p.crop {
            if !(c[0] < c[3] && c[1] < c[4] && c[2] < c[5]) {
                return Err(format!(
                    "prepare.crop {c:?} must be [min_x, min_y, min_z, max_x, max_y, max_z] with min < max"
                ));
            }
        }
        if !(p.floor_noise_sigmas >= 0.0 && p.floor_noise_sigmas.is_finite()) {
            return Err(format!(
                "prepare.floor_noise_sigmas = {} must be >= 0 (0: off)",
                p.floor_noise_sigmas
            ));
        }
        if !(p.ground_tolerance_m > 0.0) || !(p.voxel_m > 0.0) || p.min_points == 0 {
            return Err("prepare.ground_tolerance_m, prepare.voxel_m and prepare.min_points must be positive".into());
        }
        if (p.auto_ground || p.remove_ground) && p.ransac_iterations == 0 {
            return Err("prepare.ransac_iterations must be at least 1 when the ground is estimated".into());
        }
        if !(p.voxel_grid_m >= 0.0 && p.voxel_grid_m.is_finite()) {
            return Err(format!(
                "prepare.voxel_grid_m = {} must be >= 0 (0: off)",
                p.voxel_grid_m
            ));
        }
        if !(p.cluster_m >= 0.0 && p.cluster_m.is_finite()) {
            return Err(format!("prepare.cluster_m = {} must be >= 0 (0: off)", p.cluster_m));
        }
        if !(p.cluster_stretch_from_m >= 0.0 && p.cluster_stretch_from_m.is_finite()) {
            return Err(format!(
                "prepare.cluster_stretch_from_m = {} must be >= 0 (0: off)",
                p.cluster_stretch_from_m
            ));
        }
        if !(p.cluster_join_m >= 0.0 && p.cluster_join_m.is_finite()) {
            return Err(format!(
                "prepare.cluster_join_m = {} must be >= 0 (0: off)",
                p.cluster_join_m
            ));
        }
        let o = &p.outliers;
        if o.method != OutlierMethod::None && (o.neighbours == 0 || !(o.std_ratio > 0.0) || !(o.radius_m > 0.0)) {
            return Err("prepare.outliers: neighbours, std_ratio and radius_m must be positive".into());
        }
        Ok(())
    }
}

/// A sensor-to-gravity rotation must be one (orthonormal, determinant 1); `key` names it.
pub fn check_rotation(key: &str, rows: &[[f32; 3]; 3]) -> Result<(), String> {
    let r = nalgebra::Matrix3::from_fn(|i, j| rows[i][j]);
    let orthogonality = (r.transpose() * r - nalgebra::Matrix3::identity()).abs().max();
    if orthogonality < 1e-3 && (r.determinant() - 1.0).abs() < 1e-3 {
        Ok(())
    } else {
        Err(format!("{key} must be a rotation matrix (orthonormal, determinant 1)"))
    }
}
