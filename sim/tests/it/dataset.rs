//! Datasets: determinism, ground-truth round trip through an independent PLY reader, splits.

use std::collections::{BTreeMap, BTreeSet};

use gdvae_sim::dataset::{DatasetSpec, GroundTruth, Split};
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

#[test]
fn invalid_specs_name_the_parameter() {
    let mut spec = small_spec(0);
    spec.split = [0.5, 0.5, 0.5];
    assert!(spec.validate().unwrap_err().to_string().contains("'split'"));
    let mut spec = small_spec(0);
    spec.poses_per_subject = 0;
    assert!(spec.validate().unwrap_err().to_string().contains("'poses'"));
}
