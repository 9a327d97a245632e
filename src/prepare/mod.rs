//! Prepare: from a sensor's points to the model's input (N_p points in model units, centred).
//!
//! In order: unit conversion to metres, the sensor-to-gravity transform (or levelling on a
//! RANSAC ground plane), region-of-interest crop, ground removal, outlier removal, then
//! centring on the bounding-box centre, scaling by the bundle's model units per metre and
//! subsampling to N_p. Every step is deterministic for the configured seed and the frame's
//! sequence number. A frame that ends with too few points is rejected with the reason.

mod filters;
mod sampling;
mod settings;

pub use filters::{crop, fit_ground, keep_largest_cluster, levelling, remove_outliers, remove_plane, transform, Plane};
pub use sampling::{
    centre_and_scale, farthest_point_sampling, farthest_point_sampling_plain, random_sampling, subsample,
    voxel_sampling, PrepareError, Sampling,
};
pub use settings::{check_rotation, OutlierMethod, OutlierSettings, PrepareSettings};

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};

use crate::cloud::Frame;

/// One stream's sensor pose as its source sets it: either part may be left to `[prepare]`'s.
#[derive(Debug, Clone, PartialEq)]
pub struct SensorPose {
    pub stream: String,
    pub rotation: Option<[[f32; 3]; 3]>,
    pub translation: Option<[f32; 3]>,
}

/// A frame ready for the encoder.
#[derive(Debug, Clone)]
pub struct Prepared {
    /// Exactly N_p points, centred, in model units.
    pub points: Vec<[f32; 3]>,
    /// The centre that was subtracted (metres, gravity frame).
    pub centre_m: [f32; 3],
    /// Points after filtering (before subsampling or padding).
    pub points_kept: usize,
}

type Pose = (Matrix3<f32>, Vector3<f32>);

fn pose(rotation: &[[f32; 3]; 3], translation: &[f32; 3]) -> Pose {
    (Matrix3::from_fn(|i, j| rotation[i][j]), Vector3::from(*translation))
}

/// Prepares frames for one bundle; immutable and shared by the prepare workers.
#[derive(Debug, Clone)]
pub struct Preparer {
    settings: PrepareSettings,
    /// Sensor -> gravity frame: `[prepare]`'s, and per stream where a source sets its own.
    sensor_to_gravity: Pose,
    per_stream: HashMap<String, Pose>,
    points: usize,
    model_units_per_metre: f32,
}

impl Preparer {
    pub fn new(settings: &PrepareSettings, points: usize, model_units_per_metre: f32) -> Self {
        Self {
            settings: settings.clone(),
            sensor_to_gravity: pose(
                &settings.sensor_to_gravity_rotation,
                &settings.sensor_to_gravity_translation,
            ),
            per_stream: HashMap::new(),
            points,
            model_units_per_metre,
        }
    }

    /// The streams' own sensor poses, where their sources set one (each part falls back to
    /// `[prepare]`'s).
    pub fn with_sensor_poses(mut self, poses: impl IntoIterator<Item = SensorPose>) -> Self {
        for source in poses {
            if source.rotation.is_some() || source.translation.is_some() {
                let rotation = source.rotation.unwrap_or(self.settings.sensor_to_gravity_rotation);
                let translation = source
                    .translation
                    .unwrap_or(self.settings.sensor_to_gravity_translation);
                self.per_stream.insert(source.stream, pose(&rotation, &translation));
            }
        }
        self
    }

    pub fn prepare(&self, frame: &Frame) -> Result<Prepared, PrepareError> {
        let s = &self.settings;
        let seed = s.seed ^ frame.sequence.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let to_metres = frame.unit.to_metres();
        let mut points: Vec<[f32; 3]> = frame.cloud.points.iter().map(|p| p.map(|c| c * to_metres)).collect();
        let (rotation, translation) = self.per_stream.get(&frame.stream).unwrap_or(&self.sensor_to_gravity);
        transform(&mut points, rotation, translation);
        let ground = if s.auto_ground || s.remove_ground {
            let plane = fit_ground(&points, s.ground_tolerance_m, s.ransac_iterations, seed);
            if plane.is_none() && s.auto_ground {
                return Err(PrepareError::NoGround);
            }
            plane
        } else {
            None
        };
        let ground = match (ground, s.auto_ground) {
            (Some(plane), true) => {
                let (rotation, translation) = levelling(&plane);
                transform(&mut points, &rotation, &translation);
                Some(Plane {
                    normal: Vector3::z(),
                    offset: 0.0,
                    inliers: plane.inliers,
                })
            }
            (plane, _) => plane,
        };
        if let Some(bounds) = &s.crop {
            crop(&mut points, bounds);
        }
        if let (true, Some(plane)) = (s.remove_ground, ground) {
            remove_plane(&mut points, &plane, s.ground_tolerance_m);
        }
        remove_outliers(&mut points, &s.outliers);
        if s.cluster_m > 0.0 {
            keep_largest_cluster(&mut points, s.cluster_m);
        }
        let points_kept = points.len();
        let mut chosen = subsample(&points, self.points, s.min_points, s.sampling, s.voxel_m, seed)?;
        let centre_m = centre_and_scale(&mut chosen, self.model_units_per_metre);
        Ok(Prepared {
            points: chosen,
            centre_m,
            points_kept,
        })
    }
}
