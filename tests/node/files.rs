//! File sources on files written by other tools (the sim's PLY writer, text written here as a user
//! would), and bad input: every error names the file and the reason, nothing panics.

use std::path::{Path, PathBuf};

use gdvae_node::sources::files::{read_cloud, FileOptions};

fn sample(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("sim/samples/meshes")
        .join(name)
}

#[test]
fn ply_meshes_from_the_sim_are_sampled_over_their_surface() {
    let options = FileOptions {
        mesh_samples: 5000,
        ..FileOptions::default()
    };
    let read = read_cloud(&sample("quadruped_rest.ply"), &options).unwrap();
    assert_eq!(read.cloud.len(), 5000);
    assert_eq!(
        read,
        read_cloud(&sample("quadruped_rest.ply"), &options).unwrap(),
        "seeded"
    );
    let top = read.cloud.points.iter().map(|p| p[2]).fold(f32::MIN, f32::max);
    assert!(
        (0.4..1.2).contains(&top),
        "a quadruped stands under a metre and a bit: {top}"
    );
}

#[test]
fn obj_xyz_and_csv_text() {
    let dir = tempfile::tempdir().unwrap();
    let obj = dir.path().join("tetra.obj");
    std::fs::write(
        &obj,
        "# tetrahedron\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n",
    )
    .unwrap();
    let read = read_cloud(&obj, &FileOptions::default()).unwrap();
    assert_eq!(read.cloud.len(), FileOptions::default().mesh_samples);
    assert!(read
        .cloud
        .points
        .iter()
        .all(|p| p.iter().all(|c| (-1e-6..=1.0 + 1e-6).contains(c))));

    let points_only = dir.path().join("points.obj");
    std::fs::write(&points_only, "v 0 0 0\nv 1 2 3\n").unwrap();
    assert_eq!(
        read_cloud(&points_only, &FileOptions::default()).unwrap().cloud.len(),
        2
    );

    let xyz = dir.path().join("cloud.xyz");
    std::fs::write(&xyz, "x y z\n0 0 0\n1 2 3\nnan 0 0\n4 5 6 extra columns\n").unwrap();
    let read = read_cloud(&xyz, &FileOptions::default()).unwrap();
    assert_eq!(
        read.cloud.points,
        vec![[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]
    );
    assert_eq!(read.dropped_non_finite, 1);

    let csv = dir.path().join("cloud.csv");
    std::fs::write(&csv, "1.5,2.5,3.5\n-1,-2,-3\n").unwrap();
    assert_eq!(read_cloud(&csv, &FileOptions::default()).unwrap().cloud.len(), 2);
}

#[test]
fn pcd_ascii_with_extra_fields_in_any_order() {
    let dir = tempfile::tempdir().unwrap();
    let pcd = dir.path().join("cloud.pcd");
    std::fs::write(
        &pcd,
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS intensity z y x\nSIZE 4 4 4 4\nTYPE F F F F\n\
         COUNT 1 1 1 1\nWIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA ascii\n\
         9 3 2 1\n9 6 5 4\n9 nan nan nan\n",
    )
    .unwrap();
    let read = read_cloud(&pcd, &FileOptions::default()).unwrap();
    assert_eq!(read.cloud.points, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
    assert_eq!(read.dropped_non_finite, 1);
}

#[test]
fn bad_files_are_clear_errors_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let cases: Vec<(&str, &[u8], &str)> = vec![
        ("empty.ply", b"", "end_header"),
        ("truncated.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nproperty float y\nproperty float z\nend_header\n\x00\x00", "PLY"),
        ("huge.ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 4000000000\nproperty float x\nproperty float y\nproperty float z\nend_header\n", "claims"),
        ("huge.pcd", b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 4000000000\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4000000000\nDATA binary\n", "claims"),
        ("noxyz.pcd", b"VERSION 0.7\nFIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 1\nDATA ascii\n1 2 3\n", "'x'"),
        ("words.xyz", b"1 2 3\nhello world again\n", "line 2"),
        ("nothing.xyz", b"# only a comment\n", "no points"),
        ("cloud.bin", b"\x00\x01", "unknown file type"),
    ];
    for (name, content, expected) in cases {
        let path = dir.path().join(name);
        std::fs::write(&path, content).unwrap();
        let error = read_cloud(&path, &FileOptions::default()).err().map(|e| e.to_string());
        let error = error.unwrap_or_else(|| panic!("{name} was accepted"));
        assert!(
            error.contains(name) && error.contains(expected),
            "{name}: '{error}' lacks '{expected}'"
        );
    }
}

#[test]
fn pcd_written_by_pypcd4_in_all_three_encodings() {
    let fixtures = crate::helpers::repo().join("tests/fixtures");
    let expected: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fixtures.join("expected_pcd.json")).unwrap()).unwrap();
    for encoding in ["ascii", "binary", "binary_compressed"] {
        let path = fixtures.join(format!("pypcd4_{encoding}.pcd"));
        let read = read_cloud(&path, &FileOptions::default()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            read.cloud.len() as u64,
            expected["points"].as_u64().unwrap(),
            "{encoding}"
        );
        assert_eq!(
            read.dropped_non_finite as u64,
            expected["dropped_non_finite"].as_u64().unwrap()
        );
        for axis in 0..3 {
            let sum: f64 = read.cloud.points.iter().map(|p| p[axis] as f64).sum();
            let want = expected["sum"][axis].as_f64().unwrap();
            assert!((sum - want).abs() < 1e-3, "{encoding} axis {axis}: {sum} vs {want}");
            assert_eq!(
                read.cloud.points[0][axis],
                expected["first"][axis].as_f64().unwrap() as f32
            );
        }
    }
}

#[test]
fn ply_and_obj_meshes_written_by_trimesh_are_sampled_over_their_surface() {
    let fixtures = crate::helpers::repo().join("tests/fixtures");
    let expected: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fixtures.join("expected_mesh.json")).unwrap()).unwrap();
    let centre: Vec<f32> = (0..3).map(|a| expected["centre"][a].as_f64().unwrap() as f32).collect();
    let radius = expected["radius"].as_f64().unwrap() as f32;
    let options = FileOptions::default();
    for name in ["trimesh_ascii.ply", "trimesh_binary.ply", "trimesh.obj"] {
        let read = read_cloud(&fixtures.join(name), &options).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(
            read.cloud.len(),
            options.mesh_samples,
            "{name}: surface samples, not the 642 vertices"
        );
        let mut mean = [0.0f32; 3];
        for p in &read.cloud.points {
            let distance = (0..3).map(|a| (p[a] - centre[a]).powi(2)).sum::<f32>().sqrt();
            // Flat faces of a subdivision-3 icosphere lie within 1.5 % inside the sphere.
            assert!(
                distance <= radius * 1.0001 && distance >= radius * 0.98,
                "{name}: {distance}"
            );
            for a in 0..3 {
                mean[a] += p[a] / read.cloud.len() as f32;
            }
        }
        for a in 0..3 {
            assert!(
                (mean[a] - centre[a]).abs() < 0.01,
                "{name}: area-weighted samples centre on the sphere"
            );
        }
    }
}
