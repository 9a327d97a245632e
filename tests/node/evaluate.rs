//! `evaluate`: its measures on cases computed by hand, and the command on a short generated
//! recording (with and without its ground-truth channel), where the counts are known exactly.

use std::path::Path;

use gdvae_node::evaluate::metrics::{
    angle_errors, code_step, match_changes, pose_code_motion, pose_retrieval, retrieval, separability, window_spreads,
    PoseFrame, Segment,
};

use crate::helpers::repo;

#[test]
fn changes_are_matched_within_the_tolerance_and_the_rest_are_false() {
    // True changes at 10 and 50; reports at 3 (before any change), 12 (finds 10 after 2 frames),
    // 13 (a second report for the same change), 56 (one frame too late for 50 with tolerance 5),
    // 70.
    let c = match_changes(&[10, 50], &[3, 12, 13, 56, 70], 5, 100);
    assert_eq!((c.true_changes, c.reported, c.found, c.false_changes), (2, 5, 1, 4));
    assert_eq!(c.delays_frames, vec![2]);
    assert_eq!(c.recall, Some(0.5));
    assert_eq!(c.false_per_1000_frames, Some(40.0));
    // The last frame of the tolerance counts; a report belongs to the change before it.
    let c = match_changes(&[10, 12], &[15, 17], 5, 40);
    assert_eq!(
        (c.found, c.false_changes),
        (1, 1),
        "15 is after the second change: it finds 12, not 10"
    );
    assert_eq!(c.delays_frames, vec![3]);
    let c = match_changes(&[10], &[15], 5, 40);
    assert_eq!((c.found, c.false_changes), (1, 0));
    let none = match_changes(&[], &[], 10, 0);
    assert_eq!((none.recall, none.false_per_1000_frames), (None, None));
}

#[test]
fn angle_errors_wrap_and_summarise() {
    let errors: Vec<f64> = [0.0f64, 10.0, -20.0, 40.0, 190.0]
        .iter()
        .map(|d| d.to_radians())
        .collect();
    let a = angle_errors(&errors);
    assert_eq!(a.count, 5);
    let close = |x: Option<f64>, y: f64| (x.unwrap() - y).abs() < 1e-9;
    // |errors| sorted: 0, 10, 20, 40, 170 (190 wraps to -170).
    assert!(close(a.median_deg, 20.0), "{a:?}");
    assert!(close(a.p90_deg, 118.0), "{a:?}");
    assert!(close(a.over_30_deg, 0.4) && close(a.over_150_deg, 0.2), "{a:?}");
}

#[test]
fn retrieval_counts_a_query_right_when_its_own_reference_is_nearest() {
    let segment = |subject: &str, family: &str, first: [f32; 2], second: [f32; 2]| Segment {
        recording: "r".into(),
        subject: subject.into(),
        family: family.into(),
        frames: vec![
            (first.to_vec(), vec![0.1, 0.1]),
            (first.to_vec(), vec![0.1, 0.1]),
            (second.to_vec(), vec![0.1, 0.1]),
            (second.to_vec(), vec![0.1, 0.1]),
        ],
    };
    let segments = vec![
        segment("a", "quadruped", [0.0, 0.0], [0.05, 0.0]),
        segment("b", "quadruped", [1.0, 0.0], [1.0, 0.05]),
        // c's later frames look like b: wrong among all, right among bipeds (it is the only one).
        segment("c", "biped", [0.0, 1.0], [0.95, 0.0]),
    ];
    let r = retrieval(&segments, 1);
    assert_eq!(r.queries, 3);
    assert!((r.top1.unwrap() - 2.0 / 3.0).abs() < 1e-12, "{r:?}");
    assert_eq!(r.top1_same_family, Some(1.0));
    // Two frames after the half would need 4 frames each: none of these segments takes part.
    assert_eq!(retrieval(&segments, 3).queries, 0);
    assert_eq!(retrieval(&segments, 3).top1, None);
}

#[test]
fn separability_compares_distances_across_changes_with_distances_within_a_subject() {
    let segment = |recording: &str, subject: &str, family: &str, values: &[f32]| Segment {
        recording: recording.into(),
        subject: subject.into(),
        family: family.into(),
        frames: values.iter().map(|v| (vec![*v], vec![0.1])).collect(),
    };
    let segments = vec![
        segment("r", "a", "quadruped", &[0.0, 0.0, 0.2, 0.2]),
        segment("r", "b", "quadruped", &[1.0, 1.0, 1.0]),
        // A new recording: b -> c is not a change. c -> d is one that z_I cannot see.
        segment("s", "c", "biped", &[3.0, 3.0]),
        segment("s", "d", "biped", &[3.0, 3.0]),
    ];
    // z_I is f32: figures agree to its precision.
    let close = |x: Option<f64>, y: f64| (x.unwrap() - y).abs() < 1e-6;
    // One frame: within-subject steps 0, 0.2, 0 (a), 0, 0 (b), 0 (c), 0 (d); across a -> b 0.8,
    // across c -> d 0.
    let s = separability(&segments, 1);
    assert_eq!((s.changes, s.same_family_changes, s.within_windows), (2, 2, 7));
    // 0.8 beats all 7; 0 ties 6 and loses to 1: (7 + 3) / 14.
    assert!(close(s.auc, 10.0 / 14.0), "{s:?}");
    assert!(close(s.within_p999, 0.2 * 0.994), "{s:?}");
    assert!(
        close(s.found_at_p999, 0.5) && close(s.found_at_p999_same_family, 0.5),
        "{s:?}"
    );
    assert!(close(s.between_median, 0.4), "{s:?}");
    // Two frames: only a is long enough for a within-subject window (its halves differ by 0.2);
    // both changes have two frames on each side (0.8 and 0).
    let s = separability(&segments, 2);
    assert_eq!((s.changes, s.within_windows), (2, 1));
    assert!(close(s.within_p999, 0.2) && close(s.auc, 0.5), "{s:?}");
    assert!(close(s.found_at_p999, 0.5), "{s:?}");
    // Too long a window: nothing to measure, no figure invented.
    let s = separability(&segments, 5);
    assert_eq!(
        (s.changes, s.within_windows, s.auc, s.found_at_p999),
        (0, 0, None, None)
    );
}

/// A 2 s recording, one quadruped replaced by another at 1 s: 60 frames, one true change.
fn short_recording(path: &Path) {
    use gdvae_sim::family::Family;
    use gdvae_sim::motion::{MotionKind, MotionSpec};
    use gdvae_sim::recording::{write_recording, RecordingOptions};
    use gdvae_sim::scenario::{Scenario, ViewSpec};
    let spec = MotionSpec {
        families: vec![Family::Quadruped],
        kind: MotionKind::Walk,
        fps: 30.0,
        duration: 2.0,
        switch_times: vec![1.0],
        area: [0.4, 0.7],
        seed: 31,
    };
    let view = ViewSpec {
        camera_distance: 2.8,
        ground_half_extent: 1.2,
        decimation: 2,
        ..ViewSpec::default()
    };
    let scenario = Scenario::new(spec, view).unwrap();
    write_recording(
        &scenario,
        path,
        RecordingOptions {
            depth_images: false,
            compression: true,
        },
        |_, _| {},
    )
    .unwrap();
}

/// The same recording without its ground-truth channel, rewritten by the mcap crate.
fn without_truth(from: &Path, to: &Path) {
    let bytes = std::fs::read(from).unwrap();
    let mut writer = mcap::Writer::new(std::io::BufWriter::new(std::fs::File::create(to).unwrap())).unwrap();
    for message in mcap::MessageStream::new(&bytes).unwrap() {
        let message = message.unwrap();
        if message.channel.topic != "/sim/ground_truth" {
            writer.write(&message).unwrap();
        }
    }
    writer.finish().unwrap();
}

#[test]
fn one_yaw_copy_with_the_four_copy_heading_noise_is_warned_about() {
    let dir = tempfile::tempdir().unwrap();
    let recording = dir.path().join("switch.mcap");
    short_recording(&recording);
    // config/replay.toml with one yaw copy, its relative paths made absolute.
    let text = std::fs::read_to_string(repo().join("config/replay.toml"))
        .unwrap()
        .replace("[model]", "[model]\nyaw_copies = 1")
        .replace("\"../", &format!("\"{}/", repo().display()));
    let config = dir.path().join("one-copy.toml");
    std::fs::write(&config, text).unwrap();
    let run = |extra: &[&str]| {
        let output = std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"))
            .current_dir(repo())
            .arg("evaluate")
            .arg("--config")
            .arg(&config)
            .args(extra)
            .arg(&recording)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&output.stderr).to_string();
        assert!(output.status.success(), "evaluate failed: {stderr}");
        stderr.contains("with yaw_copies = 1 set it to about 25")
    };
    assert!(run(&[]), "heading_std_deg 12 with one copy is warned about");
    assert!(!run(&["--set", "heading_std_deg=25"]), "25 is not");
}

#[test]
fn evaluate_on_a_short_recording_counts_exactly_what_it_holds() {
    let dir = tempfile::tempdir().unwrap();
    let with = dir.path().join("switch.mcap");
    let without = dir.path().join("bare.mcap");
    short_recording(&with);
    without_truth(&with, &without);
    let plots = dir.path().join("plots");
    let states_file = dir.path().join("states.jsonl");
    let clouds_file = dir.path().join("clouds.npy");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"))
        .current_dir(repo())
        .args(["evaluate", "--config", "config/replay.toml", "--out", "-", "--plots"])
        .arg(&plots)
        .arg("--states")
        .arg(&states_file)
        .arg("--clouds")
        .arg(&clouds_file)
        .arg(&with)
        .arg(&without)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(output.status.success(), "evaluate failed: {stderr}");
    assert!(
        stderr.contains("bare.mcap: no /sim/ground_truth channel"),
        "the recording without truth is named: {stderr}"
    );
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    let recordings = report["recordings"].as_array().unwrap();
    assert_eq!(recordings.len(), 2);
    let r = &recordings[0];
    assert_eq!(r["truth_frames"], 60);
    let (states, rejected) = (r["states"].as_u64().unwrap(), r["rejected"].as_u64().unwrap());
    assert_eq!(states + rejected, 60, "every frame is a state or a counted rejection");
    assert_eq!(r["matched"], states, "every state has its truth frame");
    assert_eq!(r["truth_without_state"], rejected);
    assert_eq!(r["subjects"].as_array().unwrap().len(), 2);
    assert_eq!(r["changes"]["true_changes"], 1);
    assert_eq!(r["changes"]["frames"], 60);
    assert_eq!(r["heading_filtered"]["count"], states);
    let found = r["changes"]["found"].as_u64().unwrap();
    let false_changes = r["changes"]["false_changes"].as_u64().unwrap();
    assert_eq!(found + false_changes, r["changes"]["reported"].as_u64().unwrap());
    // z_E steps: one per pair of consecutive frames of one subject (58 of a 60-frame walk with one
    // switch, fewer when a frame was rejected), each walking, standing or neither by the true speed.
    let pose = &r["pose_code"];
    let counted = pose["walking_steps"].as_u64().unwrap() + pose["standing_steps"].as_u64().unwrap();
    assert!(counted > 0 && counted <= 58, "{pose}");
    assert!(
        pose["walking_step_median"].as_f64().is_some(),
        "a walk has walking steps: {pose}"
    );
    // Without truth: what can be said without it, and no change counts against truth.
    let bare = &recordings[1];
    let published = &r["pose_code_published"];
    assert_eq!(
        published["walking_steps"], pose["walking_steps"],
        "the same pairs of frames"
    );
    // One-second windows of a subject's consecutive frames: a 60-frame recording with a switch at
    // its middle has at most two.
    let windows = pose["walking_windows"].as_u64().unwrap() + pose["standing_windows"].as_u64().unwrap();
    assert!(windows <= 2, "{pose}");
    // The true pose over the same pairs of frames; the truth alone has it.
    assert_eq!(
        r["true_pose"]["walking_steps"], pose["walking_steps"],
        "{}",
        r["true_pose"]
    );
    assert!(bare["true_pose"].is_null());
    assert!(bare["pose_code"].is_null(), "speed needs truth");
    assert!(bare["pose_code_published"].is_null(), "speed needs truth");
    assert_eq!(bare["has_truth"], false);
    assert!(bare["changes"].is_null() && bare["heading_filtered"].is_null());
    assert_eq!(bare["states"], states, "the same frames replay");
    assert_eq!(
        bare["changes_reported"], r["changes"]["reported"],
        "the same tracker, the same reports"
    );
    assert!(bare["filtered_yaw_steps"]["count"].as_u64().unwrap() + 1 == states);
    // Overall: only the recording with truth; retrieval needs 2 n frames per subject (30 each).
    let o = &report["overall"];
    assert_eq!((o["recordings"].as_u64(), o["with_truth"].as_u64()), (Some(2), Some(1)));
    let queries: Vec<u64> = o["retrieval"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["queries"].as_u64().unwrap())
        .collect();
    // Pose retrieval: two quadrupeds, each frame searches the other's; the bare recording has no truth.
    assert_eq!(o["pose_retrieval"]["frames"].as_u64(), Some(states));
    let floor = o["pose_retrieval"]["truth_floor"].as_f64().unwrap();
    let ratio = o["pose_retrieval"]["code_ratio"].as_f64().unwrap();
    assert!(
        (0.0..=1.0).contains(&floor) && floor <= ratio,
        "{}",
        o["pose_retrieval"]
    );
    let segment_lengths_ok = states == 60; // with a rejection a segment may fall under 2 n frames
    if segment_lengths_ok {
        assert_eq!(
            queries,
            vec![2, 2, 0],
            "n = 1, 5: both subjects; n = 30 needs 60 frames each"
        );
    }
    assert!(
        plots.join("switch.png").is_file(),
        "a plot for the recording with truth"
    );
    assert!(!plots.join("bare.png").exists(), "none without truth");
    // --states: every published state once, with its truth where its recording has one.
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(&states_file)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len() as u64, 2 * states);
    let stream_of = |l: &serde_json::Value| l["state"]["stream"].as_str().unwrap().to_string();
    let with_stream = r["stream"].as_str().unwrap();
    for line in &lines {
        assert_eq!(line["truth"].is_null(), stream_of(line) != with_stream, "{line}");
        assert_eq!(line["state"]["raw"]["z_i"].as_array().unwrap().len(), 22);
        // config/replay.toml runs 4 yaw copies: every state says how far they scatter.
        let spread = line["state"]["raw"]["yaw_spread"].as_f64().expect("raw.yaw_spread");
        assert!((0.0..=std::f64::consts::PI).contains(&spread), "{spread}");
    }
    let subjects: std::collections::BTreeSet<&str> =
        lines.iter().filter_map(|l| l["truth"]["subject"].as_str()).collect();
    assert_eq!(subjects.len(), 2, "both subjects' frames carry their subject");
    // --clouds: the encoder's N_p points of every state, in --states' order, as one .npy array.
    let (shape, values) = read_npy_f32(&clouds_file);
    assert_eq!(shape, vec![lines.len(), 256, 3], "states x N_p x 3");
    assert_eq!(values.len(), lines.len() * 256 * 3);
    assert!(
        values.iter().all(|v| v.is_finite() && v.abs() < 2.0),
        "centred, in model units"
    );
    for (cloud, line) in values.chunks(256 * 3).zip(&lines) {
        let spread = cloud.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
        assert!(
            spread > 0.05,
            "a real cloud, not padding: {}",
            line["state"]["sequence"]
        );
    }
}

/// A NumPy .npy file of little-endian float32 (version 1.0 header): its shape and its values.
fn read_npy_f32(path: &std::path::Path) -> (Vec<usize>, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00", "a version 1.0 .npy file");
    let length = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    assert_eq!((10 + length) % 64, 0, "the data starts at a multiple of 64 bytes");
    let header = std::str::from_utf8(&bytes[10..10 + length]).unwrap();
    assert!(
        header.contains("'descr': '<f4'") && header.contains("'fortran_order': False"),
        "{header}"
    );
    let inner = header.split("'shape': (").nth(1).unwrap().split(')').next().unwrap();
    let shape = inner
        .split(',')
        .filter(|d| !d.trim().is_empty())
        .map(|d| d.trim().parse().unwrap())
        .collect();
    let values = bytes[10 + length..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    (shape, values)
}

#[test]
fn pose_code_motion_compares_steps_while_walking_with_steps_while_standing() {
    // (step, speed m/s): walking above 0.15 m/s, standing below 0.03, the rest neither.
    let steps = [(0.5, 1.0), (0.7, 0.8), (0.9, 0.2), (0.1, 0.0), (0.3, 0.01), (5.0, 0.1)];
    let p = pose_code_motion(&steps, &[]);
    assert_eq!((p.walking_steps, p.standing_steps), (3, 2));
    assert_eq!(p.walking_step_median, Some(0.7));
    assert!((p.standing_step_median.unwrap() - 0.2).abs() < 1e-12);
    assert!((p.ratio.unwrap() - 3.5).abs() < 1e-9, "{p:?}");
    assert_eq!((p.walking_windows, p.spread_ratio), (0, None));
    // A dead code steps by nothing: no ratio. One that ignores the gait: about 1.
    let dead = pose_code_motion(&[(0.0, 1.0), (0.0, 0.0)], &[]);
    assert_eq!((dead.walking_step_median, dead.ratio), (Some(0.0), None));
    assert_eq!(pose_code_motion(&[(0.2, 1.0), (0.2, 0.0)], &[]).ratio, Some(1.0));
    assert_eq!(pose_code_motion(&[], &[]).ratio, None);
    assert!((code_step(&[0.0, 3.0], &[4.0, 0.0]) - 5.0).abs() < 1e-12);
    // Spreads are sorted into walking and standing windows as steps are.
    let p = pose_code_motion(&[], &[(2.0, 0.5), (0.4, 0.0), (0.6, 0.02), (9.0, 0.1)]);
    assert_eq!((p.walking_windows, p.standing_windows), (1, 2));
    assert!((p.spread_ratio.unwrap() - 4.0).abs() < 1e-9, "{p:?}");
}

/// Four subjects of one family, 60 frames each, poses drawn on a circle of joint angles; `code`
/// makes each frame's z_E from (subject, pose angle, frame number).
fn pose_frames(code: impl Fn(usize, f32, usize) -> Vec<f32>) -> Vec<PoseFrame> {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut frames = Vec::new();
    for subject in 0..4 {
        for n in 0..60 {
            let angle: f32 = rng.random_range(0.0..std::f32::consts::TAU);
            frames.push(PoseFrame {
                family: "quadruped".into(),
                subject: format!("s{subject}"),
                code: code(subject, angle, n),
                theta: vec![0.3 * angle.sin(), 0.3 * angle.cos(), 0.1],
            });
        }
    }
    frames
}

#[test]
fn pose_retrieval_finds_the_pose_on_other_subjects_only_with_a_code_that_carries_it() {
    // A code that is the pose (scaled, in other units): its nearest is the nearest true pose.
    let exact = pose_retrieval(&pose_frames(|_, angle, _| vec![angle.sin(), angle.cos()]));
    assert_eq!(exact.frames, 240);
    assert_eq!(exact.code_ratio, exact.truth_floor);
    assert!(exact.truth_floor.unwrap() < 0.1, "{exact:?}");
    // A code that names the subject, or the pose only within one subject (same-subject frames are
    // never searched), or counts frames (a drift with time): about 1.
    for dead in [
        pose_retrieval(&pose_frames(|subject, _, _| vec![subject as f32])),
        pose_retrieval(&pose_frames(|subject, angle, _| vec![100.0 * subject as f32 + angle])),
        pose_retrieval(&pose_frames(|_, _, n| vec![n as f32, 0.0])),
    ] {
        let ratio = dead.code_ratio.unwrap();
        assert!((0.6..1.4).contains(&ratio), "{dead:?}");
    }
    // A pose code with noise on it lies between.
    let noisy = pose_retrieval(&pose_frames(|subject, angle, n| {
        vec![angle.sin() + 0.3 * ((subject * 7 + n * 13) % 5) as f32, angle.cos()]
    }));
    let ratio = noisy.code_ratio.unwrap();
    assert!(ratio > exact.code_ratio.unwrap() && ratio < 0.6, "{noisy:?}");
    // One subject per family, or no joint angles: nothing to search.
    let alone: Vec<PoseFrame> = pose_frames(|_, a, _| vec![a])
        .into_iter()
        .filter(|f| f.subject == "s0")
        .collect();
    assert_eq!(pose_retrieval(&alone).frames, 0);
    // Per family: a family whose code is the pose beside one whose code names the subject; each
    // is scored on its own, and the whole is the median over both families' frames.
    let mut mixed = pose_frames(|_, angle, _| vec![angle.sin(), angle.cos()]);
    mixed.extend(
        pose_frames(|subject, _, _| vec![subject as f32])
            .into_iter()
            .map(|f| PoseFrame {
                family: "biped".into(),
                ..f
            }),
    );
    let both = pose_retrieval(&mixed);
    assert_eq!(both.families.len(), 2);
    assert_eq!(both.families["quadruped"].code_ratio, exact.code_ratio);
    assert!(both.families["biped"].code_ratio.unwrap() > 0.6, "{both:?}");
    assert_eq!((both.families["quadruped"].frames, both.frames), (240, 480));
    let blind: Vec<PoseFrame> = pose_frames(|_, a, _| vec![a])
        .into_iter()
        .map(|f| PoseFrame { theta: Vec::new(), ..f })
        .collect();
    assert_eq!(
        (pose_retrieval(&blind).frames, pose_retrieval(&blind).code_ratio),
        (0, None)
    );
}

#[test]
fn window_spreads_are_the_rms_distance_from_each_window_mean() {
    // Two windows of two frames and a tail left out. Window 1: codes (0,0) and (2,0), mean (1,0),
    // each 1 away: spread 1, speed (0.2 + 0.4) / 2. Window 2: one code twice: spread 0.
    let run = vec![
        (vec![0.0, 0.0], 0.2),
        (vec![2.0, 0.0], 0.4),
        (vec![1.0, 5.0], 0.0),
        (vec![1.0, 5.0], 0.0),
        (vec![7.0, 7.0], 9.0),
    ];
    let spreads = window_spreads(&run, 2);
    assert_eq!(spreads.len(), 2);
    assert!(
        (spreads[0].0 - 1.0).abs() < 1e-12 && (spreads[0].1 - 0.3).abs() < 1e-12,
        "{spreads:?}"
    );
    assert_eq!(spreads[1], (0.0, 0.0));
    // A diagonal: (0,0), (3,4), mean (1.5,2): each 2.5 away.
    assert!((window_spreads(&[(vec![0.0, 0.0], 1.0), (vec![3.0, 4.0], 1.0)], 2)[0].0 - 2.5).abs() < 1e-12);
    assert!(window_spreads(&run, 0).is_empty() && window_spreads(&run[..1], 2).is_empty());
}

/// CLEAR MOT and IDF1 on five frames counted by hand: two objects A and B; B missed in frame 1
/// and found again in frame 2 (a fragmentation); A's track replaced by another id in frame 3 (an
/// identity switch) while a stray hypothesis appears (a false positive); B leaves in frame 4.
#[test]
fn multi_object_counts_match_a_sequence_counted_by_hand() {
    use gdvae_node::evaluate::mot::{mot_counts, Located, MotFrame};
    let at = |id, x: f32, y: f32| Located {
        id,
        centre: [x, y, 0.0],
    };
    let (a, b) = (100, 200);
    let frames = vec![
        MotFrame {
            truth: vec![at(a, 0.0, 0.0), at(b, 5.0, 0.0)],
            hypotheses: vec![at(1, 0.1, 0.0), at(2, 5.0, 0.1)],
        },
        MotFrame {
            truth: vec![at(a, 0.2, 0.0), at(b, 5.0, 0.0)],
            hypotheses: vec![at(1, 0.3, 0.0)],
        },
        MotFrame {
            truth: vec![at(a, 0.4, 0.0), at(b, 5.0, 0.0)],
            hypotheses: vec![at(1, 0.5, 0.0), at(2, 5.0, 0.0)],
        },
        MotFrame {
            truth: vec![at(a, 0.6, 0.0), at(b, 5.0, 0.0)],
            hypotheses: vec![at(3, 0.6, 0.0), at(2, 5.0, 0.0), at(4, 9.0, 9.0)],
        },
        MotFrame {
            truth: vec![at(a, 0.8, 0.0)],
            hypotheses: vec![at(3, 0.8, 0.0)],
        },
    ];
    let c = mot_counts(&frames, 0.5);
    assert_eq!((c.frames, c.objects, c.hypotheses, c.matches), (5, 9, 9, 8));
    assert_eq!(
        (c.misses, c.false_positives, c.id_switches, c.fragmentations),
        (1, 1, 1, 1)
    );
    assert!((c.mota - (1.0 - 3.0 / 9.0)).abs() < 1e-12, "{}", c.mota);
    // IDF1: A with 1 (3 frames), B with 2 (3 frames); 3's two frames with A are identity errors.
    assert_eq!((c.idtp, c.idfp, c.idfn), (6, 3, 3));
    assert!((c.idf1 - 12.0 / 18.0).abs() < 1e-12, "{}", c.idf1);
    // A perfect tracker: MOTA and IDF1 of 1.
    let perfect: Vec<MotFrame> = frames
        .iter()
        .map(|f| MotFrame {
            truth: f.truth.clone(),
            hypotheses: f.truth.iter().map(|t| at(t.id + 1, t.centre[0], t.centre[1])).collect(),
        })
        .collect();
    let c = mot_counts(&perfect, 0.5);
    assert_eq!((c.mota, c.idf1, c.id_switches, c.fragmentations), (1.0, 1.0, 0, 0));
}

/// The committed two-subject sample (a quadruped and a biped; the biped leaves for 1.5 s) through
/// `evaluate` with several objects: every state names a track, at most one per subject a frame,
/// the two subjects keep their ids and the biped gets its own back; without `[track.objects]`
/// the same recording gives one state per frame, naming none.
#[test]
fn evaluate_tracks_both_subjects_of_the_two_subject_sample() {
    let dir = tempfile::tempdir().unwrap();
    let sample = repo().join("sim/samples/two_subjects.mcap");
    let evaluate = |set: &str, states: &Path| {
        let output = std::process::Command::new(env!("CARGO_BIN_EXE_gdvae-node"))
            .current_dir(repo())
            .args([
                "evaluate",
                "--config",
                "config/objects.toml",
                "--out",
                "-",
                "--set",
                set,
                "--states",
            ])
            .arg(states)
            .arg(&sample)
            .output()
            .unwrap();
        assert!(output.status.success(), "{}", String::from_utf8_lossy(&output.stderr));
        let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
        let lines: Vec<serde_json::Value> = std::fs::read_to_string(states)
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .collect();
        (report, lines)
    };
    let (report, lines) = evaluate("objects.enabled=true", &dir.path().join("several.jsonl"));
    let objects = &report["recordings"][0]["objects"];
    assert_eq!(objects["mot"]["frames"], 60, "{objects}");
    assert_eq!(objects["tracks"], 2, "one track per subject: {objects}");
    assert_eq!(objects["mot"]["id_switches"], 0, "{objects}");
    assert_eq!(objects["mot"]["false_positives"], 0, "{objects}");
    assert!(objects["mot"]["idf1"].as_f64().unwrap() > 0.9, "{objects}");
    assert_eq!(
        (
            objects["returns"]["other_family"].as_u64(),
            objects["returns"]["other_family_same_id"].as_u64()
        ),
        (Some(1), Some(1)),
        "the biped came back and got its id back: {objects}"
    );
    assert!(report["overall"]["objects"]["mot"]["idf1"].as_f64().is_some());
    let mut per_frame: std::collections::BTreeMap<u64, Vec<u64>> = Default::default();
    for line in &lines {
        let state = &line["state"];
        assert_eq!(state["schema"], "gdvae.state/2");
        let track = state["track"].as_u64().expect("every state names its track");
        per_frame
            .entry(state["sequence"].as_u64().unwrap())
            .or_default()
            .push(track);
    }
    assert!(
        per_frame
            .values()
            .all(|t| t.len() <= 2 && (t.len() < 2 || t[0] != t[1])),
        "{per_frame:?}"
    );
    assert!(
        per_frame.values().filter(|t| t.len() == 2).count() >= 30,
        "both tracked most of the time"
    );
    let (single, lines) = evaluate("objects.enabled=false", &dir.path().join("one.jsonl"));
    assert!(single["recordings"][0]["objects"].is_null());
    assert!(lines.len() <= 60 && lines.iter().all(|l| l["state"]["track"].is_null()));
}
