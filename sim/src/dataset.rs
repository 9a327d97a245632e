//! Training datasets: a folder of posed meshes with ground truth and subject-disjoint splits.
//!
//! Layout (documented in sim/README.md):
//! `meshes/*.ply` (binary PLY, metres, z up), `ground_truth.jsonl` (one line per mesh),
//! `splits.json` (subject ids per split), `dataset.json` (units, axes, families, the spec used).
//! Splits are by subject, never by mesh: intrinsic retrieval must be measured on individuals the
//! model never saw. Every mesh's seed derives from the dataset seed and its indices, so the output
//! is the same for any thread count.

use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use nalgebra::Vector3;
use rand::seq::SliceRandom;
use rand::Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::family::{BetaParameter, Family, PoseDraw, PoseMode, Subject, SubjectError};
use crate::motion::{gait_theta, WALK_WOBBLE};
use crate::ply::write_ply;
use crate::seeds;
use crate::skinning::place;

/// What to generate. Built from CLI arguments and checked by [`DatasetSpec::validate`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DatasetSpec {
    pub families: Vec<Family>,
    /// K: individuals per family.
    pub subjects_per_family: usize,
    /// M: poses per individual (a K x M grid per family).
    pub poses_per_subject: usize,
    /// Probability that a pose comes from the wide "bent" prior instead of the sigma-0.2 one.
    pub bent_fraction: f64,
    /// Fractions of subjects for train / validation / test.
    pub split: [f64; 3],
    /// Rotate each mesh by a uniform random yaw about z (recorded in the ground truth). Off by
    /// default: the training kit applies its own random rotations.
    pub random_yaw: bool,
    /// Paired data: pose `j` of every subject of a family is one draw ([`PoseDraw`]), so the
    /// dataset is a subjects x poses grid in which a row shares the subject and a column the pose
    /// (the ground truth's `pose_id` names the column). Off: every mesh draws its own pose.
    #[serde(default)]
    pub shared_poses: bool,
    /// Probability that a pose is a walking one, as the sim's `walk` motion poses a subject: the
    /// gait at a random phase ([`gait_theta`]) plus a drift of `WALK_WOBBLE` times a prior pose. The
    /// prior alone bends every joint independently, which no animal does; a walk moves a few joints
    /// together, and a pose code of ten numbers must learn that it is what bodies mostly do.
    #[serde(default)]
    pub gait_fraction: f64,
    pub target_vertices: usize,
    pub seed: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    #[error("invalid dataset parameter '{parameter}': {reason}")]
    InvalidParameter { parameter: &'static str, reason: String },
    #[error("cannot write {path}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("subject {subject}")]
    Subject {
        subject: String,
        #[source]
        source: SubjectError,
    },
}

fn invalid(parameter: &'static str, reason: impl Into<String>) -> DatasetError {
    DatasetError::InvalidParameter {
        parameter,
        reason: reason.into(),
    }
}

impl DatasetSpec {
    pub fn validate(&self) -> Result<(), DatasetError> {
        if self.families.is_empty() {
            return Err(invalid("families", "at least one family is needed"));
        }
        if self.subjects_per_family == 0 {
            return Err(invalid("subjects", "must be at least 1"));
        }
        if self.poses_per_subject == 0 {
            return Err(invalid("poses", "must be at least 1"));
        }
        if !(0.0..=1.0).contains(&self.bent_fraction) {
            return Err(invalid(
                "bent-fraction",
                format!("{} is not in [0, 1]", self.bent_fraction),
            ));
        }
        if !(0.0..=1.0).contains(&self.gait_fraction) {
            return Err(invalid(
                "gait-fraction",
                format!("{} is not in [0, 1]", self.gait_fraction),
            ));
        }
        if self.split.iter().any(|f| !(0.0..=1.0).contains(f)) || (self.split.iter().sum::<f64>() - 1.0).abs() > 1e-6 {
            return Err(invalid(
                "split",
                format!("{:?} must be three fractions in [0, 1] summing to 1", self.split),
            ));
        }
        if !(200..=200_000).contains(&self.target_vertices) {
            return Err(invalid(
                "vertices",
                format!("{} is not in [200, 200000]", self.target_vertices),
            ));
        }
        Ok(())
    }

    pub fn mesh_count(&self) -> usize {
        self.families.len() * self.subjects_per_family * self.poses_per_subject
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Split {
    Train,
    Validation,
    Test,
}

/// One line of `ground_truth.jsonl`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GroundTruth {
    /// Path of the mesh, relative to the dataset folder.
    pub file: String,
    pub family: Family,
    pub subject: String,
    pub split: Split,
    pub pose_index: usize,
    pub pose_mode: PoseMode,
    pub beta: Vec<f64>,
    /// Axis-angle per non-root joint (joint order in `dataset.json`), radians.
    pub theta: Vec<f64>,
    /// Rotation about +z applied after posing, radians.
    pub yaw: f64,
    /// With shared poses, the pose's name within the dataset (`<family>-pose-<index>`): meshes with
    /// the same `pose_id` are different subjects in the same pose. Absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_id: Option<String>,
    /// A walking pose's gait phase (cycles, 0..1); absent for a prior pose (`--gait-fraction`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gait_phase: Option<f64>,
    pub seed: u64,
    pub vertices: usize,
    pub triangles: usize,
}

pub fn subject_id(family: Family, index: usize) -> String {
    format!("{}-{index:04}", family.name())
}

pub fn pose_id(family: Family, index: usize) -> String {
    format!("{}-pose-{index:03}", family.name())
}

/// The pose of column `pose_index` of a family's grid, drawn once for every subject (shared poses):
/// its own seed, so it does not depend on which subjects are generated.
pub fn shared_pose(spec: &DatasetSpec, family: Family, pose_index: usize) -> GridPose {
    let mut rng = seeds::rng(seeds::derive(
        spec.seed,
        &[family as u64, u64::MAX - 1, pose_index as u64],
    ));
    GridPose::sample(spec, family, &mut rng)
}

/// One pose draw of a dataset: a prior pose, or with `gait_phase` a walking one whose drift is
/// the draw. Drawn as before `--gait-fraction` existed when it is 0, so older datasets repeat.
#[derive(Debug, Clone, PartialEq)]
pub struct GridPose {
    pub draw: PoseDraw,
    pub gait_phase: Option<f64>,
}

impl GridPose {
    pub fn sample(spec: &DatasetSpec, family: Family, rng: &mut impl Rng) -> Self {
        let mode = if rng.random_bool(spec.bent_fraction) {
            PoseMode::Bent
        } else {
            PoseMode::Gaussian
        };
        let draw = PoseDraw::sample(family, mode, rng);
        let walking = spec.gait_fraction > 0.0 && rng.random_bool(spec.gait_fraction);
        let gait_phase = walking.then(|| rng.random_range(0.0..1.0));
        // A walking pose drifts by the sigma-0.2 prior, as the `walk` motion does.
        let draw = if walking {
            PoseDraw {
                mode: PoseMode::Gaussian,
                ..draw
            }
        } else {
            draw
        };
        Self { draw, gait_phase }
    }

    /// `subject`'s joint angles in this pose.
    pub fn theta(&self, subject: &Subject) -> Vec<f64> {
        let mut theta = subject.theta_of(&self.draw);
        if let Some(phase) = self.gait_phase {
            let gait = gait_theta(&subject.skeleton, subject.family, phase);
            theta.iter_mut().zip(gait).for_each(|(t, g)| *t = WALK_WOBBLE * *t + g);
        }
        theta
    }
}

/// Assigns each subject index of a family to a split (a seeded shuffle, then the fractions).
pub fn assign_splits(spec: &DatasetSpec, family: Family) -> Vec<Split> {
    let count = spec.subjects_per_family;
    let mut order: Vec<usize> = (0..count).collect();
    order.shuffle(&mut seeds::rng(seeds::derive(spec.seed, &[family as u64, u64::MAX])));
    let mut validation = (spec.split[1] * count as f64).round() as usize;
    let mut test = (spec.split[2] * count as f64).round() as usize;
    // Keep every requested split non-empty when there are subjects enough.
    if spec.split[1] > 0.0 && validation == 0 && count >= 3 {
        validation = 1;
    }
    if spec.split[2] > 0.0 && test == 0 && count >= 3 {
        test = 1;
    }
    let train = count.saturating_sub(validation + test);
    let mut splits = vec![Split::Train; count];
    for (rank, &subject) in order.iter().enumerate() {
        splits[subject] = if rank < train {
            Split::Train
        } else if rank < train + validation {
            Split::Validation
        } else {
            Split::Test
        };
    }
    splits
}

/// What a finished run produced.
#[derive(Debug, Clone, Serialize)]
pub struct DatasetSummary {
    pub meshes: usize,
    pub subjects: usize,
    pub min_vertices: usize,
    pub max_vertices: usize,
    pub seconds: f64,
    pub meshes_per_second: f64,
    pub bytes: u64,
}

#[derive(Serialize)]
struct FamilyDescription {
    beta: &'static [BetaParameter],
    joints: Vec<&'static str>,
    theta_dimension: usize,
}

#[derive(Serialize)]
struct DatasetDescription<'a> {
    format: &'static str,
    version: u32,
    generator: String,
    units: &'static str,
    up_axis: &'static str,
    forward_axis: &'static str,
    theta_convention: &'static str,
    families: std::collections::BTreeMap<&'static str, FamilyDescription>,
    spec: &'a DatasetSpec,
    summary: &'a DatasetSummary,
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn write_json(path: &Path, value: &impl Serialize) -> Result<(), DatasetError> {
    let text = serde_json::to_string_pretty(value).expect("dataset descriptions serialise");
    fs::write(path, text + "\n").map_err(io_error(path))
}

/// Generates the dataset into `out` (created if missing). `progress` is called after each subject
/// with (meshes done, meshes total).
pub fn write_dataset(
    spec: &DatasetSpec,
    out: &Path,
    progress: impl Fn(usize, usize) + Sync,
) -> Result<DatasetSummary, DatasetError> {
    spec.validate()?;
    let mesh_dir = out.join("meshes");
    fs::create_dir_all(&mesh_dir).map_err(io_error(&mesh_dir))?;
    let started = Instant::now();
    let done = AtomicUsize::new(0);
    let total = spec.mesh_count();

    let jobs: Vec<(Family, usize, Split)> = spec
        .families
        .iter()
        .flat_map(|&family| {
            assign_splits(spec, family)
                .into_iter()
                .enumerate()
                .map(move |(i, split)| (family, i, split))
        })
        .collect();

    let shared_poses: std::collections::HashMap<Family, Vec<GridPose>> = spec
        .families
        .iter()
        .filter(|_| spec.shared_poses)
        .map(|&family| {
            let draws = (0..spec.poses_per_subject)
                .map(|j| shared_pose(spec, family, j))
                .collect();
            (family, draws)
        })
        .collect();

    let per_subject: Result<Vec<Vec<(GroundTruth, u64)>>, DatasetError> = jobs
        .par_iter()
        .map(|&(family, index, split)| {
            let subject_name = subject_id(family, index);
            let subject_seed = seeds::derive(spec.seed, &[family as u64, index as u64]);
            let subject =
                Subject::draw(family, subject_seed, spec.target_vertices).map_err(|source| DatasetError::Subject {
                    subject: subject_name.clone(),
                    source,
                })?;
            let mut records = Vec::with_capacity(spec.poses_per_subject);
            for pose_index in 0..spec.poses_per_subject {
                let seed = seeds::derive(spec.seed, &[family as u64, index as u64, pose_index as u64]);
                let mut rng = seeds::rng(seed);
                let drawn;
                let pose = if spec.shared_poses {
                    &shared_poses[&family][pose_index]
                } else {
                    drawn = GridPose::sample(spec, family, &mut rng);
                    &drawn
                };
                let (pose_mode, theta, gait_phase) = (pose.draw.mode, pose.theta(&subject), pose.gait_phase);
                let yaw = if spec.random_yaw {
                    rng.random_range(-std::f64::consts::PI..std::f64::consts::PI)
                } else {
                    0.0
                };
                let posed = subject.pose(&theta).map_err(|source| DatasetError::Subject {
                    subject: subject_name.clone(),
                    source,
                })?;
                let mesh = place(&posed, yaw, Vector3::zeros());
                let file = format!("meshes/{subject_name}-{pose_index:03}.ply");
                let path = out.join(&file);
                let mut encoded = Vec::new();
                write_ply(
                    &mesh,
                    &format!("gdvae-sim {subject_name} pose {pose_index}"),
                    &mut encoded,
                )
                .map_err(io_error(&path))?;
                fs::write(&path, &encoded).map_err(io_error(&path))?;
                let bytes = encoded.len() as u64;
                records.push((
                    GroundTruth {
                        file,
                        family,
                        subject: subject_name.clone(),
                        split,
                        pose_index,
                        pose_mode,
                        beta: subject.beta.clone(),
                        theta,
                        yaw,
                        pose_id: spec.shared_poses.then(|| pose_id(family, pose_index)),
                        gait_phase,
                        seed,
                        vertices: mesh.positions.len(),
                        triangles: mesh.triangles.len(),
                    },
                    bytes,
                ));
            }
            progress(done.fetch_add(records.len(), Ordering::Relaxed) + records.len(), total);
            Ok(records)
        })
        .collect();
    let records: Vec<(GroundTruth, u64)> = per_subject?.into_iter().flatten().collect();

    let truth_path = out.join("ground_truth.jsonl");
    let mut truth = BufWriter::new(File::create(&truth_path).map_err(io_error(&truth_path))?);
    for (record, _) in &records {
        let line = serde_json::to_string(record).expect("ground truth serialises");
        writeln!(truth, "{line}").map_err(io_error(&truth_path))?;
    }
    truth.flush().map_err(io_error(&truth_path))?;

    let mut splits: std::collections::BTreeMap<&str, Vec<String>> = Default::default();
    for &(family, index, split) in &jobs {
        let key = match split {
            Split::Train => "train",
            Split::Validation => "validation",
            Split::Test => "test",
        };
        splits.entry(key).or_default().push(subject_id(family, index));
    }
    write_json(&out.join("splits.json"), &splits)?;

    let seconds = started.elapsed().as_secs_f64();
    let summary = DatasetSummary {
        meshes: records.len(),
        subjects: jobs.len(),
        min_vertices: records.iter().map(|(r, _)| r.vertices).min().unwrap_or(0),
        max_vertices: records.iter().map(|(r, _)| r.vertices).max().unwrap_or(0),
        seconds,
        meshes_per_second: records.len() as f64 / seconds.max(1e-9),
        bytes: records.iter().map(|(_, b)| b).sum(),
    };
    let families = spec
        .families
        .iter()
        .map(|&family| {
            let skeleton = family.reference_skeleton();
            let description = FamilyDescription {
                beta: family.beta_parameters(),
                joints: skeleton.joints.iter().map(|j| j.name).collect(),
                theta_dimension: skeleton.pose_dimension(),
            };
            (family.name(), description)
        })
        .collect();
    let description = DatasetDescription {
        format: "gdvae-sim-dataset",
        version: 1,
        generator: format!("gdvae-sim {}", env!("CARGO_PKG_VERSION")),
        units: "metre",
        up_axis: "z",
        forward_axis: "x",
        theta_convention:
            "axis-angle (radians) per joint after the root, in joint order, in the world-aligned rest frame",
        families,
        spec,
        summary: &summary,
    };
    write_json(&out.join("dataset.json"), &description)?;
    Ok(summary)
}
