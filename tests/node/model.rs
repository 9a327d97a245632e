//! The shipped bundle through the real ONNX Runtime (the onnxruntime wheel in .venv, installed by
//! `make venv`), and bundle checks that must refuse altered or unsupported bundles.

use std::path::{Path, PathBuf};

use gdvae_node::bundle::Bundle;
use gdvae_node::prepare::{centre_and_scale, subsample, Sampling};
use gdvae_node::runtime::Encoder;
use gdvae_node::sources::files::{read_cloud, FileOptions};

fn shipped() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/bundles/cpu-fo")
}

fn prepared(bundle: &Bundle, mesh: &str, seed: u64) -> Vec<[f32; 3]> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("sim/samples/meshes")
        .join(mesh);
    let cloud = read_cloud(&path, &FileOptions::default()).unwrap().cloud;
    let n = bundle.manifest.sizes.points;
    let mut points = subsample(&cloud.points, n, n / 4, Sampling::Farthest, 0.01, seed).unwrap();
    centre_and_scale(&mut points, bundle.manifest.units.model_units_per_metre as f32);
    points
}

#[test]
fn the_shipped_bundle_encodes_in_onnx_runtime() {
    let bundle = Bundle::load(shipped()).unwrap();
    let sizes = bundle.manifest.sizes;
    let mut encoder = Encoder::load(&bundle, None, 1, false).unwrap();
    let a = prepared(&bundle, "biped_rest.ply", 0);
    let b = prepared(&bundle, "quadruped_rest.ply", 0);
    let batch = encoder.encode(&[&a, &b]).unwrap();
    assert_eq!(batch.len(), 2);
    for encoding in &batch {
        assert_eq!(encoding.x_c.len(), sizes.x_c);
        assert_eq!(encoding.z_e_mean.len(), sizes.z_e);
        assert_eq!(encoding.z_i_mean.len(), sizes.z_i);
        assert_eq!(encoding.z_i_logvar.len(), sizes.z_i);
        let norm: f32 = encoding.q.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!((norm - 1.0).abs() < 1e-4, "q is a unit quaternion: |q| = {norm}");
        assert!(encoding.z_i_mean.iter().chain(&encoding.x_c).all(|v| v.is_finite()));
    }
    // Batching does not change a frame's result, and running twice gives the same numbers.
    let alone = encoder.encode(&[&a]).unwrap().remove(0);
    for (x, y) in alone.x_c.iter().zip(&batch[0].x_c) {
        assert!((x - y).abs() < 1e-4, "batched {y} vs alone {x}");
    }
    assert_eq!(alone, encoder.encode(&[&a]).unwrap().remove(0));
    assert_ne!(
        batch[0].z_i_mean, batch[1].z_i_mean,
        "a biped and a quadruped differ in shape"
    );
}

/// With 4 yaw copies, a frame turned by a quarter turn gives the same four copies in another
/// order: the fused yaw turns with it and the codes stay (a sign or order slip in turning the
/// copies' answers back breaks both).
#[test]
fn yaw_copies_turn_back_each_answer_so_a_quarter_turn_turns_only_the_heading() {
    use gdvae_node::track::pose::yaw_of;
    let bundle = Bundle::load(shipped()).unwrap();
    let mut encoder = Encoder::load(&bundle, None, 1, false).unwrap().with_yaw_copies(4);
    let cloud = prepared(&bundle, "quadruped_rest.ply", 0);
    let quarter: Vec<[f32; 3]> = cloud.iter().map(|&[x, y, z]| [-y, x, z]).collect();
    let encodings = encoder.encode(&[&cloud, &quarter]).unwrap();
    let turn = (yaw_of(&encodings[1].q) - yaw_of(&encodings[0].q)).to_degrees();
    let turn = (turn + 540.0).rem_euclid(360.0) - 180.0;
    assert!(
        (turn - 90.0).abs() < 1.0,
        "the fused yaw turned by {turn:.2} deg, not 90"
    );
    for (a, b) in encodings[0].z_i_mean.iter().zip(&encodings[1].z_i_mean) {
        assert!((a - b).abs() < 1e-3 * (1.0 + a.abs()), "z_I {a} vs {b}");
    }
    assert_eq!(encodings.len(), 2, "one fused encoding per frame");
}

#[test]
fn altered_or_unsupported_bundles_are_refused_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    for file in ["manifest.json", "encoder.onnx", "decoder.onnx", "flow.onnx"] {
        std::fs::copy(shipped().join(file), dir.path().join(file)).unwrap();
    }
    assert!(Bundle::load(dir.path()).is_ok());

    let mut flow = std::fs::read(dir.path().join("flow.onnx")).unwrap();
    let last = flow.len() - 1;
    flow[last] ^= 1;
    std::fs::write(dir.path().join("flow.onnx"), &flow).unwrap();
    let error = Bundle::load(dir.path()).unwrap_err().to_string();
    assert!(error.contains("flow.onnx") && error.contains("sha256"), "{error}");
    std::fs::copy(shipped().join("flow.onnx"), dir.path().join("flow.onnx")).unwrap();

    let manifest = std::fs::read_to_string(shipped().join("manifest.json")).unwrap();
    for (from, to, expected) in [
        ("\"schema_version\": 1", "\"schema_version\": 9", "schema version 9"),
        ("\"up_axis\": \"+z\"", "\"up_axis\": \"+y\"", "up axis"),
        ("\"input_unit\": \"metre\"", "\"input_unit\": \"inch\"", "input unit"),
    ] {
        assert!(manifest.contains(from), "the shipped manifest has {from}");
        std::fs::write(dir.path().join("manifest.json"), manifest.replace(from, to)).unwrap();
        let error = Bundle::load(dir.path()).unwrap_err().to_string();
        assert!(error.contains(expected), "{error} lacks '{expected}'");
    }
    let mut calibrated: serde_json::Value = serde_json::from_str(&manifest).unwrap();
    for bad in [serde_json::json!(0.0), serde_json::json!(-1.0)] {
        calibrated["calibration"] = serde_json::json!({ "z_I_variance_scale": bad });
        std::fs::write(dir.path().join("manifest.json"), calibrated.to_string()).unwrap();
        let error = Bundle::load(dir.path()).unwrap_err().to_string();
        assert!(error.contains("z_I_variance_scale"), "{error}");
        calibrated["calibration"] = serde_json::json!({ "z_I_variance_scale": 1.0, "z_I_spread": bad });
        std::fs::write(dir.path().join("manifest.json"), calibrated.to_string()).unwrap();
        let error = Bundle::load(dir.path()).unwrap_err().to_string();
        assert!(error.contains("z_I_spread"), "{error}");
    }
    calibrated["calibration"] = serde_json::json!({ "z_I_variance_scale": 1.0, "z_I_spread": 1.5 });
    std::fs::write(dir.path().join("manifest.json"), calibrated.to_string()).unwrap();
    assert_eq!(Bundle::load(dir.path()).unwrap().manifest.calibration.z_i_unit(), 1.5);
    let width = calibrated["sizes"]["x_c"].as_u64().unwrap() as usize;
    let encoder = calibrated["files"]["encoder.onnx"]["sha256"].clone();
    for (projection, expected) in [
        (
            serde_json::json!({ "input": "z_I", "matrix": [vec![0.0; width]], "encoder_sha256": encoder }),
            "reads 'z_I'",
        ),
        (
            serde_json::json!({ "input": "x_c", "matrix": [vec![0.0; width], vec![0.0; width - 1]], "encoder_sha256": encoder }),
            "row 1 has",
        ),
        (
            serde_json::json!({ "input": "x_c", "matrix": [], "encoder_sha256": encoder }),
            "has 0 rows",
        ),
    ] {
        calibrated["calibration"] = serde_json::json!({ "z_I_variance_scale": 1.0, "identity_projection": projection });
        std::fs::write(dir.path().join("manifest.json"), calibrated.to_string()).unwrap();
        let error = Bundle::load(dir.path()).unwrap_err().to_string();
        assert!(
            error.contains("identity_projection") && error.contains(expected),
            "{error} lacks '{expected}'"
        );
    }
    // Fitted on another encoder: the bundle still loads, without it (identity changes on z_I).
    calibrated["calibration"] = serde_json::json!({ "z_I_variance_scale": 1.0, "identity_projection":
        { "input": "x_c", "matrix": [vec![0.0; width]], "encoder_sha256": "00ff" } });
    std::fs::write(dir.path().join("manifest.json"), calibrated.to_string()).unwrap();
    let loaded = Bundle::load(dir.path()).expect("a stale projection does not stop the bundle");
    assert!(loaded.manifest.calibration.identity_projection.is_none());
    calibrated["calibration"]["identity_projection"]["encoder_sha256"] = encoder.clone();
    std::fs::write(dir.path().join("manifest.json"), calibrated.to_string()).unwrap();
    assert!(Bundle::load(dir.path())
        .unwrap()
        .manifest
        .calibration
        .identity_projection
        .is_some());
    std::fs::write(dir.path().join("manifest.json"), "{ not json").unwrap();
    assert!(Bundle::load(dir.path())
        .unwrap_err()
        .to_string()
        .contains("not a valid manifest"));
}

/// Replays the sample with `bundle` and `settings`; its identity changes reported.
fn changes_reported(bundle: &std::path::Path, settings: &[&str]) -> u64 {
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"));
    command
        .current_dir(crate::helpers::repo())
        .args([
            "-q",
            "evaluate",
            "--config",
            "config/replay.toml",
            "--out",
            "-",
            "--bundle",
        ])
        .arg(bundle)
        .arg(crate::helpers::sample_recording());
    for setting in settings {
        command.args(["--set", setting]);
    }
    let output = command.output().unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    report["recordings"][0]["changes_reported"].as_u64().unwrap()
}

#[test]
fn the_bundles_calibration_scales_the_z_i_variances_before_the_configs_multiplier() {
    let dir = tempfile::tempdir().unwrap();
    for file in ["manifest.json", "encoder.onnx", "decoder.onnx", "flow.onnx"] {
        std::fs::copy(shipped().join(file), dir.path().join(file)).unwrap();
    }
    let shipped_changes = changes_reported(dir.path(), &[]);
    assert_eq!(shipped_changes, 1, "the sample's one swap");
    let mut manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(shipped().join("manifest.json")).unwrap()).unwrap();
    let measured = Bundle::load(shipped()).unwrap().manifest.calibration.z_i_variance_scale as f64;
    // Variances a million times wider: no frame stands out.
    manifest["calibration"] = serde_json::json!({ "z_I_variance_scale": measured * 1e6 });
    std::fs::write(dir.path().join("manifest.json"), manifest.to_string()).unwrap();
    assert_eq!(changes_reported(dir.path(), &[]), 0);
    // The same product from the config's multiplier: the shipped behaviour again.
    let default = gdvae_node::config::Config::default().track.shape_variance_scale as f64;
    let setting = format!("shape_variance_scale={:e}", default * 1e-6);
    assert_eq!(changes_reported(dir.path(), &[&setting]), shipped_changes);
}

#[test]
fn inspect_model_shows_the_bundles_calibration() {
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"))
        .args(["inspect-model"])
        .arg(shipped())
        .output()
        .unwrap();
    assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
    let stdout = String::from_utf8_lossy(&output.stdout);
    let scale = Bundle::load(shipped()).unwrap().manifest.calibration.z_i_variance_scale;
    assert!(
        stdout.contains(&format!("calibration: z_I variances x {scale} ")),
        "{stdout}"
    );
    assert!(
        stdout.contains("calibration: identity changes on z_I (no identity projection)"),
        "{stdout}"
    );
    // The default bundle detects identity changes on its identity projection.
    let default = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/bundles/h200-fo-nodeid");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"))
        .args(["inspect-model"])
        .arg(&default)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    let projection = Bundle::load(&default)
        .unwrap()
        .manifest
        .calibration
        .identity_projection
        .expect("the default bundle has an identity projection");
    let subjects: u64 = projection.fitted_on["subjects"]
        .as_object()
        .unwrap()
        .values()
        .map(|n| n.as_u64().unwrap())
        .sum();
    let expected = format!(
        "calibration: identity changes on {} directions of x_c (fitted on {subjects} subjects",
        projection.matrix.len()
    );
    assert!(subjects > 0 && stdout.contains(&expected), "{stdout}");
    // Its z_I spread is measured, and the tracker's z_I distances are in it.
    let spread = Bundle::load(&default).unwrap().manifest.calibration.z_i_spread;
    let spread = spread.expect("the default bundle's calibration has its z_I spread");
    assert!(
        stdout.contains(&format!("calibration: z_I spread {spread}")),
        "{stdout}"
    );
}
