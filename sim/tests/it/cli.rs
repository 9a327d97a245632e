//! The `sim` binary: commands succeed on good input and fail clearly on bad input.

use std::process::Command;

fn sim(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_sim"))
        .args(args)
        .output()
        .expect("sim runs")
}

#[test]
fn bad_arguments_fail_with_a_message_naming_them() {
    let out_dir = tempfile::tempdir().unwrap();
    let out = out_dir.path().to_str().unwrap();
    for (args, expected) in [
        (vec!["dataset", "--out", out, "--subjects", "0"], "subjects"),
        (vec!["dataset", "--out", out, "--split", "0.9,0.9,0.9"], "split"),
        (vec!["dataset", "--out", out, "--bent-fraction", "2"], "bent-fraction"),
        (vec!["dataset", "--out", out, "--families", "fish"], "fish"),
        (vec!["distortion", "--poses", "-3"], "-3"),
        (vec!["record", "--out", out, "--fps", "0"], "fps"),
        (vec!["record", "--out", out, "--switch-at", "9"], "switch"),
        (vec!["record", "--out", out, "--decimation", "0"], "decimation"),
        (vec!["record", "--out", out, "--camera-distance=-1"], "camera_distance"),
    ] {
        let output = sim(&args);
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{args:?} should fail");
        assert!(
            stderr.contains(expected),
            "{args:?}: stderr does not name '{expected}':\n{stderr}"
        );
        assert!(!stderr.contains("panicked"), "{args:?} panicked:\n{stderr}");
    }
}

#[test]
fn mesh_command_writes_a_readable_ply() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("biped.ply");
    let output = sim(&[
        "mesh",
        "--family",
        "biped",
        "--pose",
        "gaussian",
        "--out",
        path.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let (vertices, faces) = crate::util::read_ply(&path);
    assert!(
        vertices.len() > 1000 && faces.len() == 2 * vertices.len() - 4,
        "genus 0: F = 2V - 4"
    );
}

#[test]
fn pose_command_reproduces_dataset_meshes_from_their_ground_truth() {
    let dir = tempfile::tempdir().unwrap();
    let dataset = dir.path().join("data");
    let output = sim(&[
        "dataset",
        "--out",
        dataset.to_str().unwrap(),
        "--families",
        "biped",
        "--subjects",
        "2",
        "--poses",
        "1",
        "--split",
        "0.5,0.5,0",
    ]);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let truth: serde_json::Value = serde_json::from_str(
        std::fs::read_to_string(dataset.join("ground_truth.jsonl"))
            .unwrap()
            .lines()
            .next()
            .unwrap(),
    )
    .unwrap();
    let request = serde_json::json!({
        "name": "again", "family": truth["family"], "beta": truth["beta"], "theta": truth["theta"],
    });
    let requests = dir.path().join("requests.jsonl");
    std::fs::write(&requests, format!("{request}\n")).unwrap();
    let posed = dir.path().join("posed");
    let output = sim(&[
        "pose",
        "--requests",
        requests.to_str().unwrap(),
        "--out",
        posed.to_str().unwrap(),
    ]);
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    // Same beta and theta (and default resolution): the same mesh, vertex for vertex.
    let (original, original_faces) = crate::util::read_ply(&dataset.join(truth["file"].as_str().unwrap()));
    let (again, again_faces) = crate::util::read_ply(&posed.join("again.ply"));
    assert_eq!(original_faces, again_faces);
    assert_eq!(original, again);
}
