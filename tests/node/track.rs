//! The temporal filters on synthetic code sequences: shape fusion converges and grows certain, an
//! identity switch is found within a bounded number of frames (and a lone outlier is not one),
//! pose smoothing lags a moving pose by a bounded amount, quaternions keep their sign, yaw unwraps.

use gdvae_node::config::{Smoothing, TrackSettings};
use gdvae_node::track::{unwrap, yaw_of, PoseFilter, ShapeFilter};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};

const DIMENSIONS: usize = 22;

/// Frames of one object: its true z_I plus noise of standard deviation `sigma`, reported with
/// the log-variance of that noise.
fn frames(truth: &[f32], sigma: f32, count: usize, rng: &mut ChaCha8Rng) -> Vec<(Vec<f32>, Vec<f32>)> {
    let noise = Normal::new(0.0, sigma).unwrap();
    (0..count)
        .map(|_| {
            let mean = truth.iter().map(|t| t + noise.sample(rng)).collect();
            (mean, vec![2.0 * sigma.ln(); truth.len()])
        })
        .collect()
}

/// The synthetic frames report their true noise variance, so an inlier's mean squared standardized
/// distance averages about 1 (a chi-square per dimension). These tests use a gate for such calibrated
/// variances; the default gate is set lower, for the shipped bundle, whose variances are wider than
/// its errors (README, "Tracking").
fn calibrated() -> TrackSettings {
    TrackSettings {
        shape_gate: 2.5,
        ..TrackSettings::default()
    }
}

fn object(offset: f32) -> Vec<f32> {
    (0..DIMENSIONS).map(|k| offset + 0.1 * k as f32).collect()
}

#[test]
fn fused_shape_converges_and_its_variance_shrinks() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let truth = object(0.0);
    let settings = TrackSettings {
        min_shape_variance: 1e-6,
        ..calibrated()
    };
    let mut filter = ShapeFilter::new(&settings);
    let mut floored = ShapeFilter::new(&calibrated());
    let mut errors = Vec::new();
    let mut variances = Vec::new();
    for (mean, log_variance) in frames(&truth, 0.05, 100, &mut rng) {
        let update = filter.update(&mean, &log_variance);
        assert!(update.inlier && update.change.is_none());
        floored.update(&mean, &log_variance);
        let rms = (filter
            .mean()
            .iter()
            .zip(&truth)
            .map(|(m, t)| (m - t).powi(2))
            .sum::<f32>()
            / DIMENSIONS as f32)
            .sqrt();
        errors.push(rms);
        variances.push(filter.variance()[0]);
    }
    assert!(errors[0] > 0.03, "one frame carries the frame noise ({})", errors[0]);
    assert!(
        errors[99] < 0.012,
        "100 frames average it out: rms {} (sigma / sqrt(100) = 0.005)",
        errors[99]
    );
    // The product of 100 Gaussians of variance 0.0025 has variance 0.0025 / 100.
    assert!(
        (variances[99] / 2.5e-5 - 1.0).abs() < 0.01,
        "variance {} -> {}",
        variances[0],
        variances[99]
    );
    assert!(
        variances.windows(2).all(|w| w[1] < w[0]),
        "the variance shrinks with every frame"
    );
    let floor = TrackSettings::default().min_shape_variance;
    assert!(
        (floored.variance()[0] - floor).abs() < 1e-9,
        "never below min_shape_variance"
    );
    assert_eq!(filter.frames_fused(), 100);
    assert!((filter.confidence() - 1.0).abs() < 1e-6);
}

#[test]
fn an_identity_switch_is_detected_within_switch_frames() {
    let settings = calibrated();
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let mut filter = ShapeFilter::new(&settings);
    for (mean, lv) in frames(&object(0.0), 0.05, 40, &mut rng) {
        filter.update(&mean, &lv);
    }
    let second = object(0.3);
    let mut detected_at = None;
    for (index, (mean, lv)) in frames(&second, 0.05, 40, &mut rng).into_iter().enumerate() {
        let update = filter.update(&mean, &lv);
        if let Some(change) = update.change {
            assert_eq!((change.previous, change.identity), (0, 1));
            detected_at.get_or_insert(index);
        }
    }
    let detected_at = detected_at.expect("the switch must be detected");
    assert_eq!(
        detected_at + 1,
        settings.switch_frames,
        "detected on the switch_frames-th frame of the new object"
    );
    assert_eq!(filter.identity(), 1, "exactly one change");
    let error = filter
        .mean()
        .iter()
        .zip(&second)
        .map(|(m, t)| (m - t).abs())
        .fold(0.0, f32::max);
    assert!(
        error < 0.05,
        "after the switch the filter tracks the new object (max error {error})"
    );
}

#[test]
fn a_lone_outlier_frame_is_held_out_not_a_switch() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut filter = ShapeFilter::new(&calibrated());
    let truth = object(0.0);
    for (mean, lv) in frames(&truth, 0.05, 20, &mut rng) {
        filter.update(&mean, &lv);
    }
    let before = filter.mean().to_vec();
    let glitch: Vec<f32> = truth.iter().map(|t| t + 1.0).collect();
    let update = filter.update(&glitch, &vec![2.0 * 0.05f32.ln(); DIMENSIONS]);
    assert!(!update.inlier && update.change.is_none());
    assert!(update.distance > calibrated().shape_gate);
    assert_eq!(filter.mean(), &before[..], "an outlier is not fused");
    for (mean, lv) in frames(&truth, 0.05, 20, &mut rng) {
        assert!(filter.update(&mean, &lv).change.is_none());
    }
    assert_eq!(filter.identity(), 0);
}

#[test]
fn pose_smoothing_lags_a_moving_pose_by_a_bounded_amount_and_calms_a_still_one() {
    let settings = TrackSettings::default();
    let mut filter = PoseFilter::new(&settings);
    let dt = 1.0 / 30.0;
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let noise = Normal::new(0.0f32, 0.02).unwrap();
    // Still, noisy: the filtered value jitters less than the raw one.
    let (mut raw_jitter, mut filtered_jitter) = (0.0, 0.0);
    let (mut last_raw, mut last_filtered) = (0.0, 0.0);
    for step in 0..60 {
        let x = noise.sample(&mut rng);
        let pose = filter.update([1.0, 0.0, 0.0, 0.0], &[x], dt);
        if step > 0 {
            raw_jitter += (x - last_raw).abs();
            filtered_jitter += (pose.z_e[0] - last_filtered).abs();
        }
        (last_raw, last_filtered) = (x, pose.z_e[0]);
    }
    assert!(
        filtered_jitter < 0.5 * raw_jitter,
        "jitter {filtered_jitter} vs raw {raw_jitter}"
    );
    // Moving at 1 unit/s: after settling the filter lags by a bounded amount.
    let mut lag = 0.0;
    for step in 0..90 {
        let x = step as f32 * dt;
        let pose = filter.update([1.0, 0.0, 0.0, 0.0], &[x], dt);
        lag = x - pose.z_e[0];
    }
    assert!(
        lag > 0.0 && lag < 0.25,
        "lag {lag} units = {:.0} ms at 1 unit/s",
        lag * 1000.0
    );
    // Without smoothing the filtered value is the raw value.
    let mut none = PoseFilter::new(&TrackSettings {
        smoothing: Smoothing::None,
        ..settings
    });
    assert_eq!(none.update([1.0, 0.0, 0.0, 0.0], &[0.7], dt).z_e, vec![0.7]);
}

#[test]
fn quaternion_sign_is_continuous_and_yaw_unwraps_over_turns() {
    let mut filter = PoseFilter::new(&TrackSettings {
        smoothing: Smoothing::None,
        ..TrackSettings::default()
    });
    let dt = 1.0 / 30.0;
    let mut last_yaw = None;
    let mut last_q: Option<[f32; 4]> = None;
    // Three full turns about z in 10-degree steps; every other frame reports -q (same rotation).
    for step in 0..=108 {
        let angle = (step as f32 * 10.0).to_radians();
        let q = [(angle / 2.0).cos(), 0.0, 0.0, (angle / 2.0).sin()];
        let reported = if step % 2 == 1 { q.map(|c| -c) } else { q };
        let pose = filter.update(reported, &[], dt);
        if let Some(previous) = last_q {
            let dot: f32 = previous.iter().zip(&pose.q_raw).map(|(a, b)| a * b).sum();
            assert!(dot > 0.0, "step {step}: sign flipped");
        }
        last_q = Some(pose.q_raw);
        assert!(
            (pose.yaw_raw - angle).abs() < 1e-3,
            "step {step}: yaw {} vs {angle}",
            pose.yaw_raw
        );
        last_yaw = Some(pose.yaw_raw);
    }
    assert!((last_yaw.unwrap() - 6.0 * std::f32::consts::PI).abs() < 1e-3);
    assert!((yaw_of(&[0.0, 0.0, 0.0, 1.0]).abs() - std::f32::consts::PI).abs() < 1e-6);
    assert!((unwrap(Some(3.1), -3.1) - (2.0 * std::f32::consts::PI - 3.1)).abs() < 1e-5);
}
