//! Shared helpers: an independent PLY reader (ply-rs-bw) and small datasets.

use std::path::Path;

use gdvae_sim::dataset::{write_dataset, DatasetSpec, DatasetSummary};
use gdvae_sim::family::Family;
use ply_rs_bw::parser::Parser;
use ply_rs_bw::ply::{DefaultElement, Property};

/// Vertices and faces of a PLY file, read by ply-rs-bw rather than by our own code.
pub fn read_ply(path: &Path) -> (Vec<[f32; 3]>, Vec<Vec<i64>>) {
    let mut file = std::fs::File::open(path).unwrap_or_else(|e| panic!("open {}: {e}", path.display()));
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut file)
        .unwrap_or_else(|e| panic!("parse {}: {e}", path.display()));
    let scalar = |element: &DefaultElement, key: &str| match element.get(key) {
        Some(Property::Float(v)) => *v,
        other => panic!("{}: vertex property {key} is {other:?}", path.display()),
    };
    let vertices = ply.payload["vertex"]
        .iter()
        .map(|v| [scalar(v, "x"), scalar(v, "y"), scalar(v, "z")])
        .collect();
    let faces = ply.payload["face"]
        .iter()
        .map(|f| match f.get("vertex_indices") {
            Some(Property::ListInt(list)) => list.iter().map(|&i| i as i64).collect(),
            other => panic!("{}: face list is {other:?}", path.display()),
        })
        .collect();
    (vertices, faces)
}

/// A small two-family dataset with light meshes, for speed.
pub fn small_spec(seed: u64) -> DatasetSpec {
    DatasetSpec {
        families: Family::ALL.to_vec(),
        subjects_per_family: 4,
        poses_per_subject: 2,
        bent_fraction: 0.5,
        split: [0.5, 0.25, 0.25],
        random_yaw: true,
        shared_poses: false,
        gait_fraction: 0.0,
        target_vertices: 2000,
        seed,
    }
}

pub fn write_small(spec: &DatasetSpec, out: &Path) -> DatasetSummary {
    write_dataset(spec, out, |_, _| {}).expect("dataset is written")
}
