//! Prepare: from a sensor's points to the model's input (N_p points in model units, centred).
//!
//! In order: unit conversion to metres, the sensor-to-gravity transform (or levelling on a
//! RANSAC ground plane), region-of-interest crop, ground removal, then a voxel grid that reduces
//! the cloud to one point per small cube before the steps whose cost grows with the points and
//! their neighbours (outlier removal, the largest cluster, farthest point sampling), then
//! subsampling to N_p, centring on the bounding-box centre and scaling by the bundle's model units
//! per metre. Every step is deterministic for the configured seed and the frame's
//! sequence number. A frame that ends with too few points is rejected with the reason.

mod filters;
mod occupancy;
mod sampling;
mod settings;

pub use filters::{
    crop, euclidean_clusters, fit_ground, floor_noise_cut, keep_largest_cluster, levelling, remove_outliers,
    remove_plane, transform, transform_and_crop, transform_crop_and_measure_floor, voxel_grid, FloorNoise, Plane,
    RangeStretch, FLOOR_BAND_M, JOIN_MIN_FRACTION,
};
pub use sampling::{
    centre_and_scale, farthest_point_sampling, farthest_point_sampling_plain, random_sampling, subsample,
    voxel_sampling, PrepareError, Sampling,
};
pub use settings::{check_rotation, OutlierMethod, OutlierSettings, PrepareSettings};

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};

use crate::cloud::Frame;
use crate::cpu::ThreadLap;

/// Prepare's steps in order, as the CPU table names them: `transform` is the
/// unit conversion, the sensor pose and the crop (one pass over the sensor's points); `ground` the
/// RANSAC plane, levelling and ground removal (the crop moves here when the ground is estimated);
/// `reduce` the voxel grid; `sample` farthest point (or other) sampling, centring and scaling.
pub const STEPS: [&str; 6] = [
    "prepare.transform",
    "prepare.ground",
    "prepare.reduce",
    "prepare.outliers",
    "prepare.cluster",
    "prepare.sample",
];

#[derive(Clone, Copy)]
enum Step {
    Transform,
    Ground,
    Reduce,
    Outliers,
    Cluster,
    Sample,
}

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
    /// Where the object is, for telling objects apart frame to frame (metres, gravity frame):
    /// with several objects ([`Preparer::prepare_all`]) the centre of its points' box with the
    /// outer 5 % on each axis left out, which a few stray points hardly move (the whole box's
    /// centre, which `centre_m` is, can jump by a quarter metre); else `centre_m`.
    pub position_m: [f32; 3],
    /// Points after filtering (before subsampling or padding).
    pub points_kept: usize,
    /// The input cloud decimated to at most [`Preparer::showing_input`]'s points (metres, gravity
    /// frame by the sensor pose, before any levelling), for the sinks that show it.
    pub input: Option<Vec<[f32; 3]>>,
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
    /// Keep a decimated copy of the input of at most this many points (0: none).
    input_points: usize,
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
            input_points: 0,
        }
    }

    /// The sensor pose of `stream` (rotation, translation: sensor -> gravity frame), when it is a
    /// constant of the configuration; None when the ground plane levels each frame.
    pub fn sensor_pose(&self, stream: &str) -> Option<([[f32; 3]; 3], [f32; 3])> {
        if self.settings.auto_ground {
            return None;
        }
        let (rotation, translation) = self.per_stream.get(stream).unwrap_or(&self.sensor_to_gravity);
        Some((
            std::array::from_fn(|i| std::array::from_fn(|j| rotation[(i, j)])),
            (*translation).into(),
        ))
    }

    /// Keeps a copy of each frame's input decimated to at most `points` points (every k-th), for
    /// the sinks that show it (0: none).
    pub fn showing_input(mut self, points: usize) -> Self {
        self.input_points = points;
        self
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

    /// The fewest points an object may have (`[prepare] min_points`).
    pub fn min_points(&self) -> usize {
        self.settings.min_points
    }

    pub fn prepare(&self, frame: &Frame) -> Result<Prepared, PrepareError> {
        self.prepare_measured(frame, &mut [0; STEPS.len()])
    }

    /// [`Preparer::prepare`], adding each step's CPU time (this thread's clock, nanoseconds) to
    /// `cpu`, in the order of [`STEPS`].
    pub fn prepare_measured(&self, frame: &Frame, cpu: &mut [u64; STEPS.len()]) -> Result<Prepared, PrepareError> {
        let s = &self.settings;
        let mut clock = ThreadLap::start();
        let (mut points, input, seed, stretch) = self.reduce(frame, cpu, &mut clock)?;
        if s.cluster_m > 0.0 {
            keep_largest_cluster(
                &mut points,
                s.cluster_m,
                stretch,
                s.cluster_join_m,
                s.cluster_join_min_points,
            );
        }
        cpu[Step::Cluster as usize] += clock.lap();
        let prepared = self.sample(&points, input, seed);
        cpu[Step::Sample as usize] += clock.lap();
        prepared
    }

    /// Every candidate object of a frame (several objects in view, issue 34): the same steps as
    /// [`Preparer::prepare`], then each Euclidean cluster of at least `min_points` points and at
    /// most `max_extent_m` on every side (largest first, at most `max_objects`) sampled, centred
    /// and scaled on its own. With one object in view the first is what `prepare` gives. Without
    /// clustering (`cluster_m = 0`), the one cloud; none when nothing passes.
    pub fn prepare_all(
        &self,
        frame: &Frame,
        max_extent_m: f32,
        max_objects: usize,
    ) -> Result<Vec<Prepared>, PrepareError> {
        self.prepare_all_measured(frame, max_extent_m, max_objects, &mut [0; STEPS.len()])
    }

    /// [`Preparer::prepare_all`], adding each step's CPU time to `cpu` as
    /// [`Preparer::prepare_measured`] does. The decimated input cloud goes with the first.
    pub fn prepare_all_measured(
        &self,
        frame: &Frame,
        max_extent_m: f32,
        max_objects: usize,
        cpu: &mut [u64; STEPS.len()],
    ) -> Result<Vec<Prepared>, PrepareError> {
        let s = &self.settings;
        let mut clock = ThreadLap::start();
        let (points, mut input, seed, stretch) = self.reduce(frame, cpu, &mut clock)?;
        if !(s.cluster_m > 0.0) {
            let prepared = self.sample(&points, input, seed);
            cpu[Step::Sample as usize] += clock.lap();
            return Ok(vec![prepared?]);
        }
        let clusters = euclidean_clusters(&points, s.cluster_m, stretch, s.min_points, max_extent_m, max_objects);
        cpu[Step::Cluster as usize] += clock.lap();
        let prepared = clusters
            .into_iter()
            .map(|mut cluster| {
                let mut prepared = self.sample(&cluster, input.take(), seed)?;
                prepared.position_m = trimmed_centre(&mut cluster);
                Ok(prepared)
            })
            .collect();
        cpu[Step::Sample as usize] += clock.lap();
        prepared
    }

    /// The steps before clustering: the points left, the decimated input copy, the frame's seed
    /// and the cluster radius's growth with range (from the sensor's origin in the points' frame).
    fn reduce(
        &self,
        frame: &Frame,
        cpu: &mut [u64; STEPS.len()],
        clock: &mut ThreadLap,
    ) -> Result<(Vec<[f32; 3]>, Option<Vec<[f32; 3]>>, u64, Option<RangeStretch>), PrepareError> {
        let s = &self.settings;
        let seed = s.seed ^ frame.sequence.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let to_metres = frame.unit.to_metres();
        let (rotation, translation) = self.per_stream.get(&frame.stream).unwrap_or(&self.sensor_to_gravity);
        let estimate_ground = s.auto_ground || s.remove_ground;
        // One pass from the sensor's points to the cropped cloud in metres, unless the ground plane
        // must be found first (it levels the cloud before the crop, and lies partly outside it).
        let mut points = match (&s.crop, estimate_ground) {
            (Some(bounds), false) if floor_cut_on(s) => {
                let mut noise = FloorNoise::default();
                let mut points = transform_crop_and_measure_floor(
                    &frame.cloud.points,
                    to_metres,
                    rotation,
                    translation,
                    bounds,
                    &mut noise,
                );
                let cut = noise.cut(bounds[2], s.floor_noise_sigmas);
                if cut > bounds[2] {
                    points.retain(|p| p[2] >= cut);
                }
                points
            }
            (bounds, _) => transform_and_crop(
                &frame.cloud.points,
                to_metres,
                rotation,
                translation,
                bounds.as_ref().filter(|_| !estimate_ground),
            ),
        };
        let input = (self.input_points > 0).then(|| {
            let every = frame.cloud.points.len().div_ceil(self.input_points).max(1);
            let decimated: Vec<[f32; 3]> = frame.cloud.points.iter().step_by(every).copied().collect();
            transform_and_crop(&decimated, to_metres, rotation, translation, None)
        });
        cpu[Step::Transform as usize] += clock.lap();
        let mut origin = *translation;
        if estimate_ground {
            self.ground(&mut points, &mut origin, seed)?;
        }
        cpu[Step::Ground as usize] += clock.lap();
        if s.voxel_grid_m > 0.0 {
            voxel_grid(&mut points, s.voxel_grid_m);
        }
        cpu[Step::Reduce as usize] += clock.lap();
        remove_outliers(&mut points, &s.outliers);
        cpu[Step::Outliers as usize] += clock.lap();
        let stretch = (s.cluster_stretch_from_m > 0.0).then(|| RangeStretch {
            origin: origin.into(),
            from_m: s.cluster_stretch_from_m,
        });
        Ok((points, input, seed, stretch))
    }

    /// The crop's floor raised above the floor's depth noise (`floor_noise_sigmas`), on a cloud
    /// cropped with [`crop_with_floor_band`].
    fn cut_floor(&self, points: &mut Vec<[f32; 3]>) {
        let s = &self.settings;
        if let (true, Some(bounds)) = (floor_cut_on(s), &s.crop) {
            floor_noise_cut(points, bounds[2], s.floor_noise_sigmas);
        }
    }

    /// N_p points of `points`, centred and scaled.
    fn sample(&self, points: &[[f32; 3]], input: Option<Vec<[f32; 3]>>, seed: u64) -> Result<Prepared, PrepareError> {
        let s = &self.settings;
        let points_kept = points.len();
        let mut chosen = subsample(points, self.points, s.min_points, s.sampling, s.voxel_m, seed)?;
        let centre_m = centre_and_scale(&mut chosen, self.model_units_per_metre);
        Ok(Prepared {
            points: chosen,
            centre_m,
            position_m: centre_m,
            points_kept,
            input,
        })
    }

    /// The ground plane by RANSAC: levels the cloud (and the sensor's `origin`) on it
    /// (`auto_ground`), crops (after levelling) and removes the points on it (`remove_ground`).
    fn ground(&self, points: &mut Vec<[f32; 3]>, origin: &mut Vector3<f32>, seed: u64) -> Result<(), PrepareError> {
        let s = &self.settings;
        let plane = fit_ground(points, s.ground_tolerance_m, s.ransac_iterations, seed);
        if plane.is_none() && s.auto_ground {
            return Err(PrepareError::NoGround);
        }
        let plane = match (plane, s.auto_ground) {
            (Some(plane), true) => {
                let (rotation, translation) = levelling(&plane);
                transform(points, &rotation, &translation);
                *origin = rotation * *origin + translation;
                Some(Plane {
                    normal: Vector3::z(),
                    offset: 0.0,
                    inliers: plane.inliers,
                })
            }
            (plane, _) => plane,
        };
        if let Some(bounds) = &crop_with_floor_band(s) {
            crop(points, bounds);
            self.cut_floor(points);
        }
        if let (true, Some(plane)) = (s.remove_ground, plane) {
            remove_plane(points, &plane, s.ground_tolerance_m);
        }
        Ok(())
    }
}

/// Whether the floor cut applies: on, with a crop whose floor is at or above the ground.
fn floor_cut_on(s: &PrepareSettings) -> bool {
    s.floor_noise_sigmas > 0.0 && s.crop.is_some_and(|c| c[2] >= 0.0)
}

/// The crop to apply before [`floor_noise_cut`]: the configured one, reaching `FLOOR_BAND_M` below
/// the ground when the floor cut is on, so that the points it measures the noise on pass; `None`
/// without a crop.
fn crop_with_floor_band(s: &PrepareSettings) -> Option<[f32; 6]> {
    s.crop.map(|mut bounds| {
        if floor_cut_on(s) {
            bounds[2] = -FLOOR_BAND_M;
        }
        bounds
    })
}

/// The centre of `points`' box with the lowest and highest `TRIM` of them left out on each axis
/// (reorders them); the origin for none.
fn trimmed_centre(points: &mut [[f32; 3]]) -> [f32; 3] {
    const TRIM: f32 = 0.05;
    if points.is_empty() {
        return [0.0; 3];
    }
    let low = ((points.len() as f32 * TRIM) as usize).min(points.len() - 1);
    let high = points.len() - 1 - low;
    [0, 1, 2].map(|axis| {
        let by_axis = |a: &[f32; 3], b: &[f32; 3]| a[axis].total_cmp(&b[axis]);
        let lowest = points.select_nth_unstable_by(low, by_axis).1[axis];
        let highest = points.select_nth_unstable_by(high, by_axis).1[axis];
        0.5 * (lowest + highest)
    })
}
