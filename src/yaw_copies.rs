//! Test-time yaw copies: the encoder sees each frame K times, turned about the vertical (+z of the
//! gravity frame) by 360°/K steps, and the K answers are turned back and fused.
//!
//! Why: the shipped encoders are invariant to yaw only as far as training made them. Each turned
//! copy gives an estimate of the same rotation and the same codes with partly independent errors,
//! and a copy that took the back for the front (a near-symmetric body) is outvoted instead of
//! published. The cost is K encoder runs per frame (the batch grows K-fold).
//!
//! Fusion: each copy's rotation q_k, turned back by its copy's angle, is one vote; the vote nearest
//! to all others (the medoid in rotation angle) picks the answer, and the copies within
//! `INLIER_DEG` of it are averaged (sign-aligned quaternion mean; arithmetic mean of x_c, z_E and
//! z_I; mean of the variances, since the copies share one observation and are not independent
//! measurements). `z_R`, which describes the rotation as seen, is the unturned copy's.

use crate::encoding::Encoding;
use crate::track::pose::{normalized as unit, turn_rotation, unwrap, yaw_of};

/// Copies further than this from the medoid's rotation are outvoted.
pub const INLIER_DEG: f32 = 45.0;

/// The angles (radians) of K copies: 0, 2π/K, 4π/K, ...
pub fn angles(copies: usize) -> Vec<f32> {
    (0..copies)
        .map(|k| k as f32 * std::f32::consts::TAU / copies as f32)
        .collect()
}

/// `cloud` turned about +z by `angle` radians.
pub fn turned(cloud: &[[f32; 3]], angle: f32) -> Vec<[f32; 3]> {
    let (s, c) = angle.sin_cos();
    cloud
        .iter()
        .map(|&[x, y, z]| [c * x - s * y, s * x + c * y, z])
        .collect()
}

/// The rotation angle (radians) between two unit quaternions (q and -q are the same rotation).
fn angle_between(a: &[f32; 4], b: &[f32; 4]) -> f32 {
    let dot: f32 = a.iter().zip(b).map(|(x, y)| x * y).sum();
    2.0 * dot.abs().min(1.0).acos()
}

/// The RMS of the copies' yaws (turned back) about the fused rotation's yaw (radians; each
/// difference wrapped to (-pi, pi], so a copy that took the back for the front counts as half a
/// turn).
fn yaw_spread(votes: &[[f32; 4]], fused: &[f32; 4]) -> f32 {
    let centre = yaw_of(fused);
    let sum: f32 = votes
        .iter()
        .map(|v| (unwrap(Some(centre), yaw_of(v)) - centre).powi(2))
        .sum();
    (sum / votes.len() as f32).sqrt()
}

/// One frame's encoding from its copies' encodings; `copies[k]` saw the frame turned by `angles[k]`
/// (`angles[0]` must be 0: the frame as seen). Returns the fused encoding and the number of copies
/// that agreed with it.
pub fn fuse(copies: &[Encoding], angles: &[f32]) -> (Encoding, usize) {
    assert!(!copies.is_empty() && copies.len() == angles.len(), "one angle per copy");
    if copies.len() == 1 {
        return (copies[0].clone(), 1);
    }
    // A non-finite copy makes the frame non-finite: the encode stage rejects it (and counts it)
    // rather than fusing around it.
    if let Some(broken) = copies.iter().find(|e| !e.is_finite()) {
        return (broken.clone(), 0);
    }
    // Copy k saw R_z(a_k) * P, so its rotation estimates R_z(a_k) * R: turn it back by -a_k.
    let votes: Vec<[f32; 4]> = copies
        .iter()
        .zip(angles)
        .map(|(e, &a)| unit(turn_rotation(unit(e.q), -a)))
        .collect();
    let spreads: Vec<f32> = votes
        .iter()
        .map(|a| votes.iter().map(|b| angle_between(a, b)).sum())
        .collect();
    let medoid = (0..votes.len())
        .min_by(|&i, &j| spreads[i].total_cmp(&spreads[j]))
        .unwrap_or(0);
    let limit = INLIER_DEG.to_radians();
    let inliers: Vec<usize> = (0..votes.len())
        .filter(|&k| angle_between(&votes[medoid], &votes[k]) <= limit)
        .collect();
    let mut q = [0.0f32; 4];
    for &k in &inliers {
        let dot: f32 = votes[k].iter().zip(&votes[medoid]).map(|(x, y)| x * y).sum();
        let sign = if dot < 0.0 { -1.0 } else { 1.0 };
        for (sum, c) in q.iter_mut().zip(votes[k]) {
            *sum += sign * c;
        }
    }
    // The inliers' mean of one output, element by element, taken in the space `into` maps to.
    let mean_in = |field: fn(&Encoding) -> &Vec<f32>, into: fn(f32) -> f32, back: fn(f32) -> f32| -> Vec<f32> {
        let mut sum = vec![0.0f32; field(&copies[0]).len()];
        for &k in &inliers {
            for (s, v) in sum.iter_mut().zip(field(&copies[k])) {
                *s += into(*v);
            }
        }
        sum.iter().map(|s| back(s / inliers.len() as f32)).collect()
    };
    let mean = |field: fn(&Encoding) -> &Vec<f32>| mean_in(field, |v| v, |v| v);
    let mean_variance = |field: fn(&Encoding) -> &Vec<f32>| mean_in(field, f32::exp, f32::ln);
    let fused = Encoding {
        q: unit(q),
        x_c: mean(|e| &e.x_c),
        z_r_mean: copies[0].z_r_mean.clone(),
        z_r_logvar: copies[0].z_r_logvar.clone(),
        z_e_mean: mean(|e| &e.z_e_mean),
        z_e_logvar: mean_variance(|e| &e.z_e_logvar),
        z_i_mean: mean(|e| &e.z_i_mean),
        z_i_logvar: mean_variance(|e| &e.z_i_logvar),
        yaw_spread: Some(yaw_spread(&votes, &unit(q))),
    };
    (fused, inliers.len())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::pose::yaw_of;

    fn encoding(q: [f32; 4], z_i: f32) -> Encoding {
        Encoding {
            q,
            x_c: vec![z_i],
            z_r_mean: vec![0.0],
            z_r_logvar: vec![0.0],
            z_e_mean: vec![0.0],
            z_e_logvar: vec![0.0],
            z_i_mean: vec![z_i],
            z_i_logvar: vec![(0.5f32).ln()],
            yaw_spread: None,
        }
    }

    fn yaw_q(yaw: f32) -> [f32; 4] {
        turn_rotation([1.0, 0.0, 0.0, 0.0], yaw)
    }

    #[test]
    fn a_turned_cloud_and_a_turned_rotation_agree() {
        let turned_point = turned(&[[1.0, 0.0, 0.5]], std::f32::consts::FRAC_PI_2)[0];
        assert!((turned_point[0]).abs() < 1e-6 && (turned_point[1] - 1.0).abs() < 1e-6 && turned_point[2] == 0.5);
        assert!((yaw_of(&turn_rotation(yaw_q(0.3), 0.5)) - 0.8).abs() < 1e-5);
    }

    #[test]
    fn copies_are_turned_back_and_a_flipped_copy_is_outvoted() {
        let true_yaw = 0.4f32;
        let steps = angles(4);
        // Copies 0..2 see the truth (plus the turn), with small errors; copy 3 took the back for
        // the front and is 180° off.
        let errors = [0.05f32, -0.03, 0.01, std::f32::consts::PI];
        let copies: Vec<Encoding> = steps
            .iter()
            .zip(errors)
            .enumerate()
            .map(|(k, (&a, e))| encoding(yaw_q(true_yaw + a + e), if k == 3 { 9.0 } else { k as f32 }))
            .collect();
        let (fused, agreed) = fuse(&copies, &steps);
        assert_eq!(agreed, 3);
        assert!(
            (yaw_of(&fused.q) - (true_yaw + 0.01)).abs() < 0.01,
            "yaw {}",
            yaw_of(&fused.q)
        );
        // The outvoted copy's code is left out; variances are averaged, not shrunk.
        assert!((fused.z_i_mean[0] - 1.0).abs() < 1e-6);
        assert!((fused.z_i_logvar[0] - (0.5f32).ln()).abs() < 1e-6);
        // The scatter counts the outvoted copy as half a turn away: RMS about pi / 2.
        let spread = fused.yaw_spread.expect("copies give a spread");
        assert!((spread - std::f32::consts::FRAC_PI_2).abs() < 0.05, "spread {spread}");
    }

    #[test]
    fn copies_that_agree_scatter_little_about_the_fused_yaw() {
        let steps = angles(4);
        let errors = [0.05f32, -0.03, 0.01, -0.02];
        let copies: Vec<Encoding> = steps
            .iter()
            .zip(errors)
            .map(|(&a, e)| encoding(yaw_q(2.9 + a + e), 0.0))
            .collect();
        let spread = fuse(&copies, &steps).0.yaw_spread.expect("copies give a spread");
        let rms = (errors.iter().map(|e| (e - 0.0025).powi(2)).sum::<f32>() / 4.0).sqrt();
        assert!((spread - rms).abs() < 0.005, "spread {spread}, the errors' RMS {rms}");
    }

    #[test]
    fn a_non_finite_copy_makes_the_frame_non_finite() {
        let steps = angles(2);
        let mut broken = encoding(yaw_q(0.0), 1.0);
        broken.q[0] = f32::NAN;
        let (fused, agreed) = fuse(&[encoding(yaw_q(0.0), 1.0), broken], &steps);
        assert!(!fused.is_finite() && agreed == 0);
    }

    #[test]
    fn one_copy_is_the_encoding_itself() {
        let only = encoding(yaw_q(1.0), 2.0);
        assert_eq!(fuse(std::slice::from_ref(&only), &[0.0]), (only, 1));
    }
}
