//! The simulated depth camera, motion scripts and MCAP recordings.

use gdvae_sim::camera::{ground_box, DepthCamera, Intrinsics, Scene, StereoModel};
use gdvae_sim::family::Family;
use gdvae_sim::mesh::Mesh;
use gdvae_sim::motion::{Motion, MotionKind, MotionSpec, MAX_TURN_RATE, WALK_WOBBLE};
use gdvae_sim::recording::{write_recording, RecordingOptions, GROUND_TRUTH_TOPIC, POINTS_TOPIC};
use gdvae_sim::scenario::{Away, Scenario, ViewSpec};
use gdvae_sim::seeds;
use nalgebra::{Point3, Vector3};

/// A camera 1 m above the ground looking along +x.
fn level_camera() -> DepthCamera {
    DepthCamera::looking_at(
        Intrinsics::oak_d_400p(),
        StereoModel::oak_d(),
        Point3::new(0.0, 0.0, 1.0),
        Point3::new(1.0, 0.0, 1.0),
    )
    .unwrap()
}

/// A wall filling the view at `distance` along +x.
fn wall(distance: f64) -> Mesh {
    let corners = [(-20.0, -20.0), (20.0, -20.0), (20.0, 20.0), (-20.0, 20.0)];
    Mesh {
        positions: corners
            .iter()
            .map(|&(y, z)| Point3::new(distance, y, 1.0 + z))
            .collect(),
        triangles: vec![[0, 1, 2], [0, 2, 3]],
    }
}

fn depth_statistics(millimetres: &[u16]) -> (f64, f64, usize) {
    let valid: Vec<f64> = millimetres
        .iter()
        .filter(|&&d| d > 0)
        .map(|&d| d as f64 / 1000.0)
        .collect();
    let mean = valid.iter().sum::<f64>() / valid.len().max(1) as f64;
    let variance = valid.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / valid.len().max(1) as f64;
    (mean, variance.sqrt(), valid.len())
}

#[test]
fn depth_of_a_wall_is_unbiased_and_its_noise_grows_with_depth_squared() {
    let camera = level_camera();
    let mut sigmas = Vec::new();
    for distance in [1.5, 3.0] {
        let scene = Scene {
            meshes: vec![wall(distance)],
            ground_half_extent: None,
        };
        let image = camera.capture(&scene, &mut seeds::rng(7));
        let (mean, sigma, valid) = depth_statistics(&image.millimetres);
        // Only the left border strip, outside the right camera's view (one disparity wide, 22 px at
        // 1.5 m), has no stereo match.
        assert!(valid > 240_000, "{valid} valid pixels at {distance} m");
        assert!(
            (mean - distance).abs() < 0.002 * distance,
            "mean {mean} at {distance} m"
        );
        let predicted = camera.stereo.depth_sigma(camera.intrinsics.fx, distance);
        assert!(
            (sigma / predicted - 1.0).abs() < 0.25,
            "sigma {sigma} vs predicted {predicted} at {distance} m"
        );
        sigmas.push(sigma);
    }
    let ratio = sigmas[1] / sigmas[0];
    assert!(
        (3.0..5.0).contains(&ratio),
        "doubling depth scaled noise by {ratio}, expected ~4"
    );
}

#[test]
fn out_of_range_depth_edges_and_stereo_shadows_are_invalid() {
    let camera = level_camera();
    let too_near = Scene {
        meshes: vec![wall(0.9 * camera.min_depth())],
        ground_half_extent: None,
    };
    assert_eq!(camera.capture(&too_near, &mut seeds::rng(1)).valid_pixels(), 0);
    let too_far = Scene {
        meshes: vec![wall(1.2 * camera.stereo.max_depth)],
        ground_half_extent: None,
    };
    assert_eq!(camera.capture(&too_far, &mut seeds::rng(1)).valid_pixels(), 0);

    // A box in front of a wall: the pixels just left of the box (the right camera's shadow) and on
    // its silhouette are invalid; the wall far from it is valid.
    let obstacle = ground_box(2.0, 0.0, Vector3::new(0.3, 0.3, 1.5), 0.0);
    let scene = Scene {
        meshes: vec![wall(4.0), obstacle],
        ground_half_extent: None,
    };
    let image = camera.capture(&scene, &mut seeds::rng(1));
    let row = (image.height / 2) as usize;
    let width = image.width as usize;
    let line: Vec<u16> = image.millimetres[row * width..(row + 1) * width].to_vec();
    let near: Vec<usize> = (0..width).filter(|&u| line[u] > 0 && line[u] < 2500).collect();
    assert!(!near.is_empty(), "the box is visible");
    let (left, right) = (near[0], *near.last().unwrap());
    assert_eq!(line[left - 1], 0, "silhouette pixel left of the box is invalid");
    assert_eq!(line[right + 1], 0, "silhouette pixel right of the box is invalid");
    // Shadow width at the wall: fx * b * (1/z_near - 1/z_far) = 441.25 * 0.075 * (1/1.85 - 1/4) ~ 9 px.
    let shadow = (0..left).rev().take_while(|&u| line[u] == 0).count();
    assert!(
        (6..=14).contains(&shadow),
        "stereo shadow of {shadow} px left of the box"
    );
    assert!(
        line[10] > 3900 && line[width - 10] > 3900,
        "the wall away from the box is valid"
    );
}

#[test]
fn unprojected_points_lie_on_the_rendered_surface() {
    let camera = level_camera();
    let scene = Scene {
        meshes: vec![wall(2.0)],
        ground_half_extent: None,
    };
    let image = camera.capture(&scene, &mut seeds::rng(3));
    let points = image.unproject(&camera.intrinsics, 4);
    let expected = image.valid_pixels() as f64 / 16.0;
    assert!(
        (points.len() as f64 / expected - 1.0).abs() < 0.05,
        "decimation keeps 1 in 16 pixels"
    );
    for point in &points {
        // Optical frame: z is the depth; back in the world every point is on the wall x = 2.
        let world = camera.world_from_camera * Point3::new(point[0] as f64, point[1] as f64, point[2] as f64);
        assert!((world.x - 2.0).abs() < 0.08, "point {world:?} off the wall (6 sigma)");
    }
}

fn walk_spec(switch_times: Vec<f64>) -> MotionSpec {
    MotionSpec {
        families: vec![Family::Quadruped, Family::Biped],
        kind: MotionKind::Walk,
        fps: 30.0,
        duration: 2.0,
        switch_times,
        area: [0.4, 0.7],
        seed: 11,
    }
}

#[test]
fn motion_is_smooth_and_identity_changes_only_at_switches() {
    let motion = Motion::new(walk_spec(vec![1.0])).unwrap();
    let frames: Vec<_> = (0..motion.frame_count()).map(|i| motion.frame(i).unwrap().0).collect();
    assert_eq!(frames.len(), 60);
    for pair in frames.windows(2) {
        let (a, b) = (&pair[0], &pair[1]);
        let moved = Vector3::from(b.translation) - Vector3::from(a.translation);
        assert!(moved.norm() < 0.05, "frame {}: jumped {} m", b.frame, moved.norm());
        assert!(
            (b.yaw - a.yaw).abs() < 0.15,
            "frame {}: turned {} rad",
            b.frame,
            b.yaw - a.yaw
        );
        assert!(b.gait_phase > a.gait_phase, "gait advances while walking");
        if a.subject == b.subject {
            assert_eq!(a.beta, b.beta, "beta is constant for one subject");
            let step = a
                .theta
                .iter()
                .zip(&b.theta)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            assert!(step < 0.1, "frame {}: a joint moved {step} rad in one frame", b.frame);
        } else {
            assert_eq!(b.frame, 30, "the switch happens at the scripted time, 1.0 s");
            assert_ne!(a.family, b.family, "families cycle at a switch");
        }
    }
    let identities: std::collections::BTreeSet<_> = frames.iter().map(|f| f.subject.clone()).collect();
    assert_eq!(identities.len(), 2);
}

#[test]
fn a_walking_subject_never_turns_faster_than_a_body_can() {
    // Over a whole path period and many start phases, some paths nearly stop and reverse; there the
    // path's direction swings by up to 180 degrees within a few frames, and the body must not.
    let fps = 30.0;
    let (mut fastest, mut capped) = (0.0f64, 0);
    for seed in 0..12 {
        let spec = MotionSpec {
            duration: 12.0,
            seed,
            ..walk_spec(vec![])
        };
        let motion = Motion::new(spec).unwrap();
        let yaws: Vec<f64> = (0..motion.frame_count()).map(|i| motion.yaw_at(i)).collect();
        for pair in yaws.windows(2) {
            let rate = (pair[1] - pair[0]).abs() * fps;
            assert!(rate <= MAX_TURN_RATE + 1e-9, "seed {seed}: turned at {rate} rad/s");
            fastest = fastest.max(rate);
            capped += usize::from(rate > MAX_TURN_RATE - 1e-9);
        }
    }
    // The bound is reached (some path turns faster than a body), so this test can fail.
    assert!(
        capped > 0,
        "no path turned fast enough to meet the bound (fastest {fastest} rad/s)"
    );
}

/// `cross`: there and back along a 4 m line across the view (world y, slanted at most 26 degrees)
/// through the stage's centre, heading along the line, walking (the gait advances), turning at
/// the ends no faster than a body can.
#[test]
fn a_crossing_subject_walks_there_and_back_along_a_line_across_the_view() {
    for seed in 0..6 {
        let spec = MotionSpec {
            kind: MotionKind::Cross,
            duration: 12.0,
            seed,
            ..walk_spec(vec![])
        };
        let motion = Motion::new(spec).unwrap();
        let frames: Vec<_> = (0..motion.frame_count())
            .step_by(3)
            .map(|i| motion.frame(i).unwrap().0)
            .collect();
        let ys: Vec<f64> = frames.iter().map(|f| f.translation[1]).collect();
        let span = ys.iter().cloned().fold(f64::MIN, f64::max) - ys.iter().cloned().fold(f64::MAX, f64::min);
        assert!(span > 3.4, "seed {seed}: crosses {span} m of the view");
        for f in &frames {
            let [x, y, _] = f.translation;
            assert!(
                x.abs() <= y.abs() * 0.46f64.tan() + 1e-9,
                "seed {seed}: ({x}, {y}) off a line through the centre within 26 degrees of y"
            );
        }
        // Mid-line (fast), the heading is along the line, one way or the other.
        let middle = frames
            .iter()
            .min_by(|a, b| a.translation[1].abs().total_cmp(&b.translation[1].abs()))
            .unwrap();
        let across = middle.yaw.sin().abs();
        assert!(
            across > 0.85,
            "seed {seed}: heading {} rad is not across the view",
            middle.yaw
        );
        assert!(
            frames.windows(2).all(|w| w[1].gait_phase >= w[0].gait_phase) && frames.last().unwrap().gait_phase > 3.0
        );
        let yaws: Vec<f64> = (0..motion.frame_count()).map(|i| motion.yaw_at(i)).collect();
        assert!(yaws
            .windows(2)
            .all(|w| (w[1] - w[0]).abs() * 30.0 <= MAX_TURN_RATE + 1e-9));
    }
}

#[test]
fn bad_motion_and_view_parameters_are_rejected_by_name() {
    let mut spec = walk_spec(vec![3.0]);
    let error = Motion::new(spec.clone()).err().unwrap().to_string();
    assert!(error.contains("switch"), "{error}");
    spec.switch_times = vec![];
    spec.fps = 0.0;
    let error = Motion::new(spec.clone()).err().unwrap().to_string();
    assert!(error.contains("fps"), "{error}");
    spec.fps = 30.0;
    let view = ViewSpec {
        decimation: 0,
        ..ViewSpec::default()
    };
    let error = Scenario::new(spec, view).err().unwrap().to_string();
    assert!(error.contains("decimation"), "{error}");
}

#[test]
fn recordings_are_deterministic_and_complete() {
    let mut spec = walk_spec(vec![0.5]);
    spec.duration = 1.0;
    let view = ViewSpec {
        decimation: 4,
        clutter: 2,
        ..ViewSpec::default()
    };
    let scenario = Scenario::new(spec, view).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let options = RecordingOptions {
        depth_images: true,
        compression: true,
    };
    let paths = [dir.path().join("a.mcap"), dir.path().join("b.mcap")];
    for path in &paths {
        let summary = write_recording(&scenario, path, options, |_, _| {}).unwrap();
        assert_eq!(summary.frames, 30);
        assert!(summary.points_per_frame_min > 1000);
    }
    let bytes = std::fs::read(&paths[0]).unwrap();
    assert_eq!(bytes, std::fs::read(&paths[1]).unwrap(), "same specs, same bytes");

    let mut per_topic = std::collections::BTreeMap::<String, usize>::new();
    for message in mcap::MessageStream::new(&bytes).unwrap() {
        *per_topic.entry(message.unwrap().channel.topic.clone()).or_default() += 1;
    }
    assert_eq!(per_topic.len(), 4, "{per_topic:?}");
    assert!(per_topic.values().all(|&count| count == 30), "{per_topic:?}");
    assert!(per_topic.contains_key(POINTS_TOPIC) && per_topic.contains_key(GROUND_TRUTH_TOPIC));
}

#[test]
fn every_subject_of_a_crowded_scene_has_its_truth_its_visible_points_and_its_absences() {
    let view = ViewSpec {
        decimation: 4,
        ..ViewSpec::default()
    };
    let mut spec = walk_spec(vec![]);
    spec.duration = 2.0;
    let other = MotionSpec {
        families: vec![Family::Biped],
        seed: 99,
        ..spec.clone()
    };
    let away = Away {
        subject: 1,
        from: 0.5,
        to: 1.0,
    };
    let scenario = Scenario::new(spec.clone(), view.clone())
        .unwrap()
        .with_others(vec![(other, [-1.8, 0.0])], vec![away], 1.0)
        .unwrap();
    let alone = Scenario::new(spec, view).unwrap();
    for index in [0, 20, 40] {
        let frame = scenario.frame(index).unwrap();
        let [primary, biped] = &frame.subjects[..] else {
            panic!("two subjects: {:?}", frame.subjects.len())
        };
        assert_eq!((primary.id, biped.id), (0, 1));
        assert_eq!(primary.truth, frame.truth, "the primary's truth is the flattened one");
        assert_eq!(biped.truth.family, Family::Biped);
        assert!((biped.truth.translation[0] + 1.8).abs() < 0.5, "on its shifted stage");
        let gone = (0.5..1.0).contains(&frame.truth.time);
        assert_eq!(biped.present, !gone, "frame {index}");
        if gone {
            assert_eq!(biped.visible_points, 0);
        } else {
            assert!(biped.visible_points > 100, "frame {index}: {}", biped.visible_points);
        }
        // The primary's points: as many as it gives alone, less what the biped hides.
        let solo = alone.frame(index).unwrap();
        assert!(primary.visible_points > 100 && primary.visible_points <= solo.subjects[0].visible_points + 5);
        assert!(primary.visible_points + biped.visible_points < frame.points.len());
        if gone {
            // Without the biped the scene is the primary's alone: the same cloud and count.
            assert_eq!(frame.points.len(), solo.points.len(), "frame {index}");
            assert_eq!(primary.visible_points, solo.subjects[0].visible_points);
        }
    }
    let bad = Away {
        subject: 2,
        from: 0.0,
        to: 1.0,
    };
    let one = Scenario::new(walk_spec(vec![]), ViewSpec::default()).unwrap();
    assert!(one.with_others(vec![], vec![bad], 1.0).is_err(), "no subject 2");
}

/// Two walkers on overlapping stages would walk through each other: refused, with the subjects
/// and the distance named; on stages far enough apart they are accepted.
#[test]
fn subjects_that_would_pass_through_each_other_are_refused() {
    let mut spec = walk_spec(vec![]);
    spec.duration = 12.0;
    spec.fps = 5.0;
    let other = MotionSpec {
        families: vec![Family::Quadruped],
        seed: 7,
        ..spec.clone()
    };
    let scene = |offset: [f64; 2], separation: f64| {
        Scenario::new(spec.clone(), ViewSpec::default()).unwrap().with_others(
            vec![(other.clone(), offset)],
            vec![],
            separation,
        )
    };
    let Err(error) = scene([0.0, 0.9], 1.0) else {
        panic!("overlapping stages accepted")
    };
    let message = error.to_string();
    assert!(
        message.contains("subjects 0 and 1") && message.contains("--others-offset"),
        "{message}"
    );
    assert!(scene([0.0, 0.9], 0.0).is_ok(), "no check asked for");
    assert!(scene([-1.8, 0.0], 1.0).is_ok(), "1.8 m behind: never closer than 1 m");
}

/// `stand`: idle's place and turn, with the pose drifting only as a walking subject's drift does
/// (`WALK_WOBBLE` of idle's, which shifts through the whole prior), and no gait: the same seed's
/// idle subject, frame for frame, with every joint angle scaled by `WALK_WOBBLE`.
#[test]
fn a_standing_subject_is_the_idle_one_with_a_walkers_small_pose_drift() {
    let spec = |kind| MotionSpec {
        kind,
        duration: 4.0,
        ..walk_spec(vec![2.0])
    };
    let (idle, stand) = (
        Motion::new(spec(MotionKind::Idle)).unwrap(),
        Motion::new(spec(MotionKind::Stand)).unwrap(),
    );
    let mut largest = 0.0f64;
    for index in (0..stand.frame_count()).step_by(7) {
        let (a, b) = (idle.frame(index).unwrap().0, stand.frame(index).unwrap().0);
        assert_eq!((a.translation, a.yaw, &a.subject), (b.translation, b.yaw, &b.subject));
        assert_eq!(b.gait_phase, 0.0, "no gait while standing");
        for (i, s) in a.theta.iter().zip(&b.theta) {
            assert!(
                (s - WALK_WOBBLE * i).abs() < 1e-12,
                "frame {index}: {s} against {i} x {WALK_WOBBLE}"
            );
            largest = largest.max(i.abs());
        }
    }
    // The idle subject's pose does move, so the scaling is seen (and this test can fail).
    assert!(largest > 0.1, "idle's largest joint angle only {largest} rad");
    assert!(!MotionKind::Stand.walks());
}
