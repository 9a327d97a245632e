//! How far articulation departs from isometry, measured.
//!
//! GDVAE++ separates shape from pose because the Laplace-Beltrami spectrum barely moves under
//! near-isometric deformation. This reports, per family, the percentiles of per-edge relative
//! length change between each subject's rest mesh and its sampled poses.

use rayon::prelude::*;
use serde::Serialize;

use crate::family::{Family, PoseMode, Subject, SubjectError, DEFAULT_VERTEX_COUNT};
use crate::mesh::{edge_length_distortion, percentile};
use crate::seeds;

#[derive(Debug, Clone, Serialize)]
pub struct DistortionReport {
    pub family: Family,
    pub pose_mode: PoseMode,
    pub subjects: usize,
    pub poses_per_subject: usize,
    pub edges_measured: usize,
    pub mean: f64,
    pub p50: f64,
    pub p90: f64,
    pub p95: f64,
    pub p99: f64,
    pub max: f64,
}

pub fn measure_distortion(
    family: Family,
    pose_mode: PoseMode,
    subjects: usize,
    poses_per_subject: usize,
    seed: u64,
) -> Result<DistortionReport, SubjectError> {
    let per_subject: Result<Vec<Vec<f64>>, SubjectError> = (0..subjects)
        .into_par_iter()
        .map(|index| {
            let subject_seed = seeds::derive(seed, &[family as u64, index as u64]);
            let subject = Subject::draw(family, subject_seed, DEFAULT_VERTEX_COUNT)?;
            let mut distortions = Vec::new();
            for pose in 0..poses_per_subject {
                let mut rng = seeds::rng(seeds::derive(seed, &[family as u64, index as u64, pose as u64]));
                let posed = subject.pose(&subject.sample_theta(pose_mode, &mut rng))?;
                distortions.extend(edge_length_distortion(&subject.rest_mesh, &posed));
            }
            Ok(distortions)
        })
        .collect();
    let mut all: Vec<f64> = per_subject?.into_iter().flatten().collect();
    let mean = all.iter().sum::<f64>() / all.len().max(1) as f64;
    Ok(DistortionReport {
        family,
        pose_mode,
        subjects,
        poses_per_subject,
        edges_measured: all.len(),
        mean,
        p50: percentile(&mut all, 50.0),
        p90: percentile(&mut all, 90.0),
        p95: percentile(&mut all, 95.0),
        p99: percentile(&mut all, 99.0),
        max: percentile(&mut all, 100.0),
    })
}
