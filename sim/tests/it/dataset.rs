//! Datasets: determinism, ground-truth round trip through an independent PLY reader, splits.

use std::collections::{BTreeMap, BTreeSet};

use gdvae_sim::dataset::{shared_pose, DatasetSpec, GroundTruth, Split};
use gdvae_sim::family::Subject;
use gdvae_sim::skinning::place;
use nalgebra::Vector3;

use crate::util::{read_ply, small_spec, write_small};

fn read_truth(dir: &std::path::Path) -> Vec<GroundTruth> {
    std::fs::read_to_string(dir.join("ground_truth.jsonl"))
        .expect("ground truth present")
        .lines()
        .map(|line| serde_json::from_str(line).expect("ground truth line parses"))
        .collect()
}

#[test]
fn same_seed_gives_identical_files_and_another_seed_does_not() {
    let (a, b, c) = (
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
        tempfile::tempdir().unwrap(),
    );
    let mut spec = small_spec(5);
    spec.subjects_per_family = 2;
    write_small(&spec, a.path());
    write_small(&spec, b.path());
    spec.seed = 6;
    write_small(&spec, c.path());
    for name in ["ground_truth.jsonl", "splits.json"] {
        assert_eq!(
            std::fs::read(a.path().join(name)).unwrap(),
            std::fs::read(b.path().join(name)).unwrap(),
            "{name}"
        );
    }
    let truth = read_truth(a.path());
    for record in &truth {
        let bytes_a = std::fs::read(a.path().join(&record.file)).unwrap();
        assert_eq!(
            bytes_a,
            std::fs::read(b.path().join(&record.file)).unwrap(),
            "{}",
            record.file
        );
    }
    assert_ne!(truth, read_truth(c.path()), "a different seed gives different data");
}

#[test]
fn ground_truth_regenerates_every_mesh_and_splits_are_subject_disjoint() {
    let dir = tempfile::tempdir().unwrap();
    let spec: DatasetSpec = small_spec(21);
    let summary = write_small(&spec, dir.path());
    let truth = read_truth(dir.path());
    assert_eq!(truth.len(), spec.mesh_count());
    assert_eq!(summary.meshes, spec.mesh_count());

    let mut subjects: BTreeMap<String, Subject> = BTreeMap::new();
    for record in &truth {
        let (vertices, faces) = read_ply(&dir.path().join(&record.file));
        assert_eq!(vertices.len(), record.vertices);
        assert_eq!(faces.len(), record.triangles);
        assert!(faces
            .iter()
            .all(|f| f.len() == 3 && f.iter().all(|&i| (i as usize) < vertices.len())));
        // Rebuild the mesh from the recorded beta, theta and yaw alone.
        let subject = subjects.entry(record.subject.clone()).or_insert_with(|| {
            Subject::with_vertex_count(record.family, record.beta.clone(), spec.target_vertices).unwrap()
        });
        let rebuilt = place(&subject.pose(&record.theta).unwrap(), record.yaw, Vector3::zeros());
        let worst = rebuilt
            .positions
            .iter()
            .zip(&vertices)
            .map(|(p, v)| (p - nalgebra::Point3::new(v[0] as f64, v[1] as f64, v[2] as f64)).norm())
            .fold(0.0, f64::max);
        assert!(worst < 1e-5, "{}: rebuilt mesh differs by {worst} m", record.file);
    }

    let splits: BTreeMap<String, Vec<String>> =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("splits.json")).unwrap()).unwrap();
    let sets: Vec<BTreeSet<&String>> = ["train", "validation", "test"]
        .iter()
        .map(|k| splits[*k].iter().collect())
        .collect();
    for i in 0..3 {
        assert!(!sets[i].is_empty(), "split {i} is empty");
        for j in i + 1..3 {
            assert!(sets[i].is_disjoint(&sets[j]), "splits {i} and {j} share a subject");
        }
    }
    for record in &truth {
        let listed = match record.split {
            Split::Train => &sets[0],
            Split::Validation => &sets[1],
            Split::Test => &sets[2],
        };
        assert!(
            listed.contains(&record.subject),
            "{} is not in its split's list",
            record.subject
        );
    }

    let description: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("dataset.json")).unwrap()).unwrap();
    assert_eq!(description["units"], "metre");
    assert_eq!(description["up_axis"], "z");
    assert_eq!(description["families"]["quadruped"]["theta_dimension"], 57);
}

/// Largest difference between two thetas, radians per component.
fn theta_gap(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}

#[test]
fn gait_poses_are_the_walk_at_a_shared_phase_plus_a_small_drift() {
    use gdvae_sim::motion::{gait_theta, WALK_WOBBLE};
    let dir = tempfile::tempdir().unwrap();
    let mut spec = small_spec(32);
    spec.subjects_per_family = 2;
    spec.poses_per_subject = 8;
    spec.shared_poses = true;
    spec.gait_fraction = 0.5;
    write_small(&spec, dir.path());
    let truth = read_truth(dir.path());
    let walking = truth.iter().filter(|r| r.gait_phase.is_some()).count();
    assert!(
        walking > 0 && walking < truth.len(),
        "{walking} of {} walking",
        truth.len()
    );
    for record in &truth {
        let subject = Subject::with_vertex_count(record.family, record.beta.clone(), spec.target_vertices).unwrap();
        let pose = shared_pose(&spec, record.family, record.pose_index);
        assert_eq!(record.gait_phase, pose.gait_phase, "one phase per column");
        let Some(phase) = record.gait_phase else {
            assert_eq!(record.theta, subject.theta_of(&pose.draw));
            continue;
        };
        // theta = the gait at the column's phase + WALK_WOBBLE x this subject's reading of the draw.
        let gait = gait_theta(&subject.skeleton, record.family, phase);
        let drift = subject.theta_of(&pose.draw);
        for ((t, g), d) in record.theta.iter().zip(&gait).zip(&drift) {
            assert!((t - (g + WALK_WOBBLE * d)).abs() < 1e-9, "{}", record.file);
        }
        assert!(gait.iter().any(|g| g.abs() > 0.1), "a gait moves joints");
    }
    spec.gait_fraction = 1.5;
    assert!(spec.validate().is_err());
}

#[test]
fn shared_poses_make_a_grid_of_subjects_by_poses() {
    let (dir, unpaired) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    let mut spec = small_spec(31);
    spec.subjects_per_family = 3;
    spec.poses_per_subject = 3;
    spec.random_yaw = false;
    spec.shared_poses = true;
    write_small(&spec, dir.path());
    let truth = read_truth(dir.path());
    assert_eq!(truth.len(), spec.mesh_count());

    let mut subjects: BTreeMap<String, Subject> = BTreeMap::new();
    let mut columns: BTreeMap<String, Vec<&GroundTruth>> = BTreeMap::new();
    for record in &truth {
        let pose_id = record.pose_id.clone().expect("shared poses name their pose");
        assert_eq!(
            pose_id,
            format!("{}-pose-{:03}", record.family.name(), record.pose_index)
        );
        // The recorded theta is this subject's reading of the family's one draw for the column.
        let subject = subjects.entry(record.subject.clone()).or_insert_with(|| {
            Subject::with_vertex_count(record.family, record.beta.clone(), spec.target_vertices).unwrap()
        });
        let draw = shared_pose(&spec, record.family, record.pose_index);
        assert_eq!(record.pose_mode, draw.draw.mode);
        assert_eq!(record.theta, draw.theta(subject), "{}", record.file);
        assert_eq!(
            (record.gait_phase, draw.gait_phase),
            (None, None),
            "no walking poses unless asked"
        );
        columns.entry(pose_id).or_default().push(record);
    }
    assert_eq!(columns.len(), 2 * spec.poses_per_subject);
    for (pose_id, column) in &columns {
        // Every subject of the family in this pose, each once, each with its own beta.
        let names: BTreeSet<&String> = column.iter().map(|r| &r.subject).collect();
        assert_eq!(names.len(), spec.subjects_per_family, "{pose_id}");
        assert!(
            column.windows(2).all(|w| w[0].beta != w[1].beta),
            "{pose_id}: subjects share a beta"
        );
        // Same pose: the subjects' thetas differ only by their own bone axes, far less than the
        // thetas of two different poses of one subject do.
        let within = column
            .windows(2)
            .map(|w| theta_gap(&w[0].theta, &w[1].theta))
            .fold(0.0, f64::max);
        let across = truth
            .iter()
            .filter(|r| r.subject == column[0].subject && r.pose_id.as_ref() != Some(pose_id))
            .map(|r| theta_gap(&r.theta, &column[0].theta))
            .fold(f64::INFINITY, f64::min);
        assert!(
            within < 0.1 && within < 0.25 * across,
            "{pose_id}: within {within} rad, across {across} rad"
        );
    }
    for record in &truth {
        let rows: Vec<&GroundTruth> = truth.iter().filter(|r| r.subject == record.subject).collect();
        assert!(
            rows.iter().all(|r| r.beta == record.beta),
            "{}: a subject's beta varies",
            record.subject
        );
        assert_eq!(rows.len(), spec.poses_per_subject);
    }

    // Without shared poses nothing names a pose, and the subjects' poses are their own.
    spec.shared_poses = false;
    write_small(&spec, unpaired.path());
    let unpaired = read_truth(unpaired.path());
    assert!(unpaired.iter().all(|r| r.pose_id.is_none()));
    let first: Vec<&GroundTruth> = unpaired
        .iter()
        .filter(|r| r.pose_index == 0 && r.family == truth[0].family)
        .collect();
    assert!(
        theta_gap(&first[0].theta, &first[1].theta) > 0.1,
        "unshared poses differ"
    );
}

#[test]
fn invalid_specs_name_the_parameter() {
    let mut spec = small_spec(0);
    spec.split = [0.5, 0.5, 0.5];
    assert!(spec.validate().unwrap_err().to_string().contains("'split'"));
    let mut spec = small_spec(0);
    spec.poses_per_subject = 0;
    assert!(spec.validate().unwrap_err().to_string().contains("'poses'"));
}
