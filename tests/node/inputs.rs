//! How the running node treats its inputs: bad files among good ones, depth images from a
//! recording, the live drop-oldest policy, CBOR output, SIGINT on the real binary, and the exit
//! status when a source cannot start or every input fails.

use std::io::Write;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

use gdvae_node::bundle::Bundle;
use gdvae_node::cloud::{PointCloud, Unit};
use gdvae_node::config::{Config, Format, SourceSettings};
use gdvae_node::pipeline::{self, RunOptions, RunSummary};
use gdvae_node::sources::{Ingest, Outlet};
use gdvae_node::state::{Rejected, State};
use gdvae_node::stats::Stats;

use crate::helpers::*;

fn source(toml_text: &str) -> SourceSettings {
    toml::from_str(toml_text).unwrap()
}

/// Runs `config` to completion without zenoh, with JSON lines into a temporary file.
fn replay(mut config: Config) -> (RunSummary, Vec<serde_json::Value>) {
    let dir = tempfile::tempdir().unwrap();
    let jsonl = dir.path().join("out.jsonl");
    config.publish.zenoh = false;
    config.publish.jsonl = Some(jsonl.display().to_string());
    config.validate().unwrap();
    let bundle = Bundle::load(&config.model.bundle).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let summary = pipeline::run(
        &config,
        &bundle,
        None,
        stop,
        Arc::new(Stats::default()),
        RunOptions::default(),
    )
    .unwrap();
    let lines = std::fs::read_to_string(&jsonl)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    (summary, lines)
}

#[test]
fn bad_files_are_rejected_with_their_reason_and_the_good_ones_still_encode() {
    let dir = tempfile::tempdir().unwrap();
    let meshes = repo().join("sim/samples/meshes");
    std::fs::copy(meshes.join("biped_rest.ply"), dir.path().join("a_good.ply")).unwrap();
    std::fs::copy(meshes.join("quadruped_bent.ply"), dir.path().join("e_good.ply")).unwrap();
    let mut truncated = std::fs::read(meshes.join("biped_bent.ply")).unwrap();
    truncated.truncate(truncated.len() / 3);
    std::fs::write(dir.path().join("b_truncated.ply"), truncated).unwrap();
    std::fs::write(dir.path().join("c_nan.xyz"), "nan 0 0\n0 inf 0\n".repeat(100)).unwrap();
    std::fs::write(dir.path().join("d_empty.pcd"), "").unwrap();
    std::fs::write(
        dir.path().join("f_hostile.pcd"),
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 4000000000\nHEIGHT 1\nPOINTS 4000000000\nDATA binary\n",
    )
    .unwrap();

    let mut config = test_config("files", "tcp/127.0.0.1:0");
    config.sources = vec![source(&format!(
        "stream = \"f\"\nkind = \"files\"\npath = {:?}",
        dir.path().display().to_string()
    ))];
    let (summary, lines) = replay(config);
    let counters = &summary.snapshot.streams["f"];
    assert_eq!((counters.received, counters.published), (6, 2), "{counters:?}");
    assert_eq!(counters.rejected.values().sum::<u64>(), 4);
    assert_eq!(lines.len(), 6, "one message per input, in order");
    let expected = ["state", "truncated", "nan", "empty", "state", "hostile"];
    for (index, (line, what)) in lines.iter().zip(expected).enumerate() {
        assert_eq!(line["sequence"], index);
        if what == "state" {
            serde_json::from_value::<State>(line.clone()).unwrap();
        } else {
            let rejected: Rejected = serde_json::from_value(line.clone()).unwrap();
            assert!(
                rejected.reason.contains(what),
                "frame {index}: '{}' should name the {what} file",
                rejected.reason
            );
        }
    }
}

#[test]
fn depth_images_in_a_recording_are_unprojected_with_their_camera_info() {
    use gdvae_sim::family::Family;
    use gdvae_sim::motion::{MotionKind, MotionSpec};
    use gdvae_sim::recording::{write_recording, RecordingOptions, DEPTH_TOPIC};
    use gdvae_sim::scenario::{Scenario, ViewSpec};

    let spec = MotionSpec {
        families: vec![Family::Quadruped],
        kind: MotionKind::Walk,
        fps: 30.0,
        duration: 0.5,
        switch_times: vec![],
        area: [0.4, 0.7],
        seed: 5,
    };
    let view = ViewSpec {
        camera_distance: 2.6,
        ground_half_extent: 1.2,
        decimation: 2,
        ..ViewSpec::default()
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("depth.mcap");
    let scenario = Scenario::new(spec, view).unwrap();
    write_recording(
        &scenario,
        &path,
        RecordingOptions {
            depth_images: true,
            compression: true,
        },
        |_, _| {},
    )
    .unwrap();

    let mut config = test_config("depth", "tcp/127.0.0.1:0");
    config.prepare = Config::load(&repo().join("config/replay.toml")).unwrap().prepare;
    let at = |topic: &str, stream: &str| {
        source(&format!(
            "stream = \"{stream}\"\nkind = \"mcap\"\npath = {:?}\ntopic = \"{topic}\"\ndepth_step = 2\nspeed = 0.0",
            path.display().to_string()
        ))
    };
    config.sources = vec![at(DEPTH_TOPIC, "depth"), at("/camera/depth/points", "points")];
    let (summary, lines) = replay(config);
    assert_eq!(summary.snapshot.streams["depth"].published, 15);
    assert_eq!(summary.snapshot.streams["points"].published, 15);
    let states: Vec<State> = lines.into_iter().map(|l| serde_json::from_value(l).unwrap()).collect();
    for sequence in 0..15u64 {
        let of = |stream: &str| {
            states
                .iter()
                .find(|s| s.stream == stream && s.sequence == sequence)
                .unwrap()
        };
        let (depth, points) = (of("depth"), of("points"));
        // The recorded cloud is the depth image unprojected every `decimation` pixels, so the two
        // streams see the same points.
        assert_eq!(depth.points.received, points.points.received, "frame {sequence}");
        assert_eq!(depth.stamps.sensor_ns, points.stamps.sensor_ns);
        for (a, b) in depth.raw.z_i.iter().zip(&points.raw.z_i) {
            assert!((a - b).abs() < 1e-3, "frame {sequence}: {a} vs {b}");
        }
    }
}

#[test]
fn a_live_outlet_drops_its_oldest_frame_and_a_replay_outlet_waits() {
    let stats = Arc::new(Stats::default());
    let stop = Arc::new(AtomicBool::new(false));
    let (mut live, receiver) = Outlet::new("live", true, 2, stats.clone(), stop.clone());
    for _ in 0..5 {
        assert!(live.frame(PointCloud { points: vec![[0.0; 3]] }, Unit::Metre, None, 0));
    }
    let kept: Vec<u64> = receiver
        .try_iter()
        .map(|item| match item {
            Ingest::Frame(f) => f.sequence,
            Ingest::Rejected(r) => panic!("{r:?}"),
        })
        .collect();
    assert_eq!(kept, vec![3, 4], "the newest frames are kept");
    let counters = &stats.snapshot().streams["live"];
    assert_eq!((counters.received, counters.dropped), (5, 3));

    let (mut replay, receiver) = Outlet::new("replay", false, 2, stats.clone(), stop);
    let producer = std::thread::spawn(move || {
        for _ in 0..5 {
            replay.frame(PointCloud { points: vec![[0.0; 3]] }, Unit::Metre, None, 0);
        }
    });
    std::thread::sleep(Duration::from_millis(100));
    assert!(!producer.is_finished(), "a replay outlet waits for the pipeline");
    let got: Vec<_> = (0..5)
        .map(|_| receiver.recv_timeout(Duration::from_secs(5)).unwrap())
        .collect();
    producer.join().unwrap();
    assert_eq!(got.len(), 5);
    assert_eq!(stats.snapshot().streams["replay"].dropped, 0);
}

#[test]
fn states_encode_as_cbor_too() {
    let mut config = test_config("cbor", "tcp/127.0.0.1:0");
    config.publish.format = Format::Cbor;
    config.sources = vec![source(&format!(
        "stream = \"m\"\nkind = \"files\"\npath = {:?}",
        repo().join("sim/samples/meshes/biped_rest.ply").display().to_string()
    ))];
    let (_, lines) = replay(config);
    let state: State = serde_json::from_value(lines[0].clone()).unwrap();
    let bytes = gdvae_node::publish::encode(Format::Cbor, &state).unwrap();
    let decoded: State = ciborium::from_reader(bytes.as_slice()).unwrap();
    assert_eq!(decoded, state);
    assert!(bytes.len() < serde_json::to_vec(&state).unwrap().len());
}

#[test]
fn sigint_and_sigterm_drain_and_the_binary_exits_zero() {
    for signal in ["-INT", "-TERM"] {
        interrupted_run_drains(signal);
    }
}

/// A paced, repeating files run (meshes and one unreadable file) stopped by `signal` mid-run:
/// exit 0, and every frame taken in is either published or a counted rejection.
fn interrupted_run_drains(signal: &str) {
    let dir = tempfile::tempdir().unwrap();
    let inputs = dir.path().join("inputs");
    std::fs::create_dir(&inputs).unwrap();
    for entry in std::fs::read_dir(repo().join("sim/samples/meshes")).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, inputs.join(path.file_name().unwrap())).unwrap();
    }
    std::fs::write(
        inputs.join("broken.ply"),
        "ply\nformat ascii 1.0\nelement vertex 9\nend_header\n",
    )
    .unwrap();
    let jsonl = dir.path().join("states.jsonl");
    let config = dir.path().join("node.toml");
    let mut file = std::fs::File::create(&config).unwrap();
    write!(
        file,
        "[model]\nbundle = {:?}\nthreads = 1\n[pipeline]\nsummary_seconds = 0.0\n[publish]\nzenoh = false\njsonl = {:?}\n\
         [[source]]\nstream = \"m\"\nkind = \"files\"\npath = {:?}\nrepeat = true\nrate_hz = 50.0\n",
        shipped_bundle().display().to_string(),
        jsonl.display().to_string(),
        inputs.display().to_string()
    )
    .unwrap();
    let child = spawn_run(&config);
    let lines = || line_count(&jsonl);
    assert!(
        wait_until(Duration::from_secs(60), || lines() >= 5),
        "the node publishes"
    );
    send_signal(&child, signal);
    let started = std::time::Instant::now();
    let output = child.wait_with_output().unwrap();
    assert!(started.elapsed() < Duration::from_secs(30));
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "exit {:?}: {}",
        output.status,
        String::from_utf8_lossy(&output.stderr)
    );
    // The summary's counts agree with what was written: every frame taken in was published or
    // rejected.
    let row = stdout
        .lines()
        .find(|l| l.trim_start().starts_with("m "))
        .expect("a summary row");
    let numbers: Vec<u64> = row.split_whitespace().filter_map(|w| w.parse().ok()).collect();
    let (received, published, dropped, rejected) = (numbers[0], numbers[1], numbers[2], numbers[3]);
    assert_eq!(dropped, 0, "{row}");
    assert!(rejected >= 1, "the broken file came round at least once: {row}");
    assert_eq!(received, published + rejected, "{signal}: {row}");
    assert_eq!(lines() as u64, received, "one line per state or rejection");
}

/// Runs the binary with `args` and a config of `sources` (TOML), JSON lines off; its exit and output.
fn node_with_sources(command: &str, sources: &str) -> (std::process::ExitStatus, String, String) {
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("node.toml");
    std::fs::write(
        &config,
        format!(
            "[model]\nbundle = {:?}\nthreads = 1\n[pipeline]\nsummary_seconds = 0.0\n[publish]\nzenoh = false\n{sources}",
            shipped_bundle().display().to_string()
        ),
    )
    .unwrap();
    let mut node = std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"));
    node.arg(command);
    if command != "check-config" {
        node.arg("--config");
    }
    let output = node.arg(&config).output().unwrap();
    (
        output.status,
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

#[test]
fn a_source_that_cannot_start_fails_the_run_and_the_config_check_with_its_reason() {
    let meshes = repo().join("sim/samples/meshes").display().to_string();
    let sources = format!(
        "[[source]]\nstream = \"good\"\nkind = \"files\"\npath = {meshes:?}\n\
         [[source]]\nstream = \"gone\"\nkind = \"mcap\"\npath = \"/nonexistent/bag\"\n"
    );
    let (status, _, stderr) = node_with_sources("run", &sources);
    assert!(!status.success(), "{stderr}");
    assert!(
        stderr.contains("source 'gone' cannot start") && stderr.contains("/nonexistent/bag"),
        "{stderr}"
    );
    let (status, stdout, stderr) = node_with_sources("check-config", &sources);
    assert!(!status.success());
    assert!(stdout.contains("source 'good': 6 point-cloud file(s)"), "{stdout}");
    assert!(stderr.contains("gone"), "{stderr}");
    // A folder that holds nothing the node reads fails as clearly.
    let empty = tempfile::tempdir().unwrap();
    let (status, _, stderr) = node_with_sources(
        "run",
        &format!(
            "[[source]]\nstream = \"e\"\nkind = \"mcap\"\npath = {:?}\n",
            empty.path().display().to_string()
        ),
    );
    assert!(
        !status.success() && stderr.contains("folder holds no recording"),
        "{stderr}"
    );
}

#[test]
fn an_optional_source_that_cannot_start_is_left_out_and_listed() {
    let meshes = repo().join("sim/samples/meshes").display().to_string();
    let (status, stdout, stderr) = node_with_sources(
        "run",
        &format!(
            "[[source]]\nstream = \"good\"\nkind = \"files\"\npath = {meshes:?}\n\
             [[source]]\nstream = \"gone\"\nkind = \"files\"\npath = \"/nonexistent\"\noptional = true\n"
        ),
    );
    assert!(status.success(), "{stderr}");
    assert!(
        stdout.contains("gone") && stdout.contains("(optional) cannot start"),
        "{stdout}"
    );
    let row = stdout
        .lines()
        .find(|l| l.trim_start().starts_with("good "))
        .expect("a summary row");
    assert!(row.contains("6 published"), "{row}");
    // With no source left, the run fails.
    let (status, _, stderr) = node_with_sources(
        "run",
        "[[source]]\nstream = \"gone\"\nkind = \"files\"\npath = \"/nonexistent\"\noptional = true\n",
    );
    assert!(
        !status.success() && stderr.contains("no source could start"),
        "{stderr}"
    );
}

#[test]
fn a_replay_whose_every_input_failed_exits_non_zero() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.ply");
    std::fs::write(&bad, "ply\nformat ascii 1.0\nelement vertex 5\nend_header\n").unwrap();
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"))
        .args(["-q", "replay", "--no-baseline", "--bundle"])
        .arg(shipped_bundle())
        .arg(&bad)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(
        stderr.contains("every input failed") && stderr.contains("1 by source"),
        "{stderr}"
    );
}
