//! Track: per stream, what the encoder says frame by frame turned into estimates over time.
//!
//! - Shape (`ShapeFilter`): z_I is a constant of the object, so the frames' Gaussians
//!   N(mu_t, sigma_t^2) are fused as their precision-weighted product. A frame whose z_I lies far
//!   outside the fused estimate (mean squared standardized distance above `shape_gate`) is an
//!   outlier and is not fused; `switch_frames` consecutive outliers mean the object changed: the
//!   filter restarts on those frames under a new identity and reports the change.
//! - Pose (`PoseFilter`): z_E and the rotation are smoothed with one-euro filters (little lag when
//!   they move, little jitter when they rest); the quaternion is kept in one hemisphere (q and -q
//!   are the same rotation) and the yaw about the up axis is unwrapped.

use std::collections::VecDeque;

use crate::config::{Smoothing, TrackSettings};

/// What one frame did to the shape estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct ShapeUpdate {
    /// The frame agreed with the fused estimate (or started it) and was fused.
    pub inlier: bool,
    /// Mean squared standardized distance of the frame's z_I to the estimate before this frame.
    pub distance: f32,
    /// Set on the frame that completed an identity change.
    pub change: Option<IdentityChange>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct IdentityChange {
    pub previous: u64,
    pub identity: u64,
}

/// Causal precision-weighted fusion of per-frame z_I Gaussians, with outlier gating and identity
/// change detection.
#[derive(Debug, Clone)]
pub struct ShapeFilter {
    gate: f32,
    switch_frames: usize,
    max_precision: f32,
    mean: Vec<f32>,
    precision: Vec<f32>,
    frames: u64,
    identity: u64,
    /// The current run of consecutive outliers (mean, variance).
    outliers: Vec<(Vec<f32>, Vec<f32>)>,
    recent: VecDeque<bool>,
}

const CONFIDENCE_WINDOW: usize = 20;

impl ShapeFilter {
    pub fn new(settings: &TrackSettings) -> Self {
        Self {
            gate: settings.shape_gate,
            switch_frames: settings.switch_frames,
            max_precision: 1.0 / settings.min_shape_variance,
            mean: Vec::new(),
            precision: Vec::new(),
            frames: 0,
            identity: 0,
            outliers: Vec::new(),
            recent: VecDeque::new(),
        }
    }

    pub fn update(&mut self, mean: &[f32], log_variance: &[f32]) -> ShapeUpdate {
        let variance: Vec<f32> = log_variance.iter().map(|lv| lv.clamp(-20.0, 20.0).exp()).collect();
        if self.frames == 0 || self.mean.len() != mean.len() {
            self.restart(&[(mean.to_vec(), variance)]);
            return self.record(true, 0.0, None);
        }
        let distance = self.distance(mean, &variance);
        if distance <= self.gate {
            self.fuse(mean, &variance);
            self.outliers.clear();
            return self.record(true, distance, None);
        }
        self.outliers.push((mean.to_vec(), variance));
        if self.outliers.len() < self.switch_frames {
            return self.record(false, distance, None);
        }
        let previous = self.identity;
        let run = std::mem::take(&mut self.outliers);
        self.restart(&run);
        self.identity = previous + 1;
        self.recent.clear();
        let change = IdentityChange {
            previous,
            identity: self.identity,
        };
        self.record(true, distance, Some(change))
    }

    /// Mean over dimensions of (mu - m)^2 / (sigma^2 + fused variance).
    pub fn distance(&self, mean: &[f32], variance: &[f32]) -> f32 {
        let sum: f32 = mean
            .iter()
            .zip(variance)
            .zip(self.mean.iter().zip(&self.precision))
            .map(|((mu, var), (m, p))| (mu - m).powi(2) / (var + 1.0 / p))
            .sum();
        sum / mean.len().max(1) as f32
    }

    fn restart(&mut self, frames: &[(Vec<f32>, Vec<f32>)]) {
        let width = frames[0].0.len();
        self.mean = vec![0.0; width];
        self.precision = vec![0.0; width];
        self.frames = 0;
        for (mean, variance) in frames {
            self.fuse(mean, variance);
        }
    }

    fn fuse(&mut self, mean: &[f32], variance: &[f32]) {
        for k in 0..self.mean.len() {
            let p = 1.0 / variance[k].max(1e-12);
            let total = self.precision[k] + p;
            self.mean[k] = (self.mean[k] * self.precision[k] + mean[k] * p) / total;
            self.precision[k] = total.min(self.max_precision);
        }
        self.frames += 1;
    }

    fn record(&mut self, inlier: bool, distance: f32, change: Option<IdentityChange>) -> ShapeUpdate {
        self.recent.push_back(inlier);
        if self.recent.len() > CONFIDENCE_WINDOW {
            self.recent.pop_front();
        }
        ShapeUpdate {
            inlier,
            distance,
            change,
        }
    }

    pub fn mean(&self) -> &[f32] {
        &self.mean
    }

    pub fn variance(&self) -> Vec<f32> {
        self.precision.iter().map(|p| 1.0 / p).collect()
    }

    pub fn identity(&self) -> u64 {
        self.identity
    }

    pub fn frames_fused(&self) -> u64 {
        self.frames
    }

    /// Fraction of the last 20 frames (since the last identity change) that were fused.
    pub fn confidence(&self) -> f32 {
        if self.recent.is_empty() {
            return 0.0;
        }
        self.recent.iter().filter(|i| **i).count() as f32 / self.recent.len() as f32
    }
}

/// One-euro filter of one scalar (Casiez et al. 2012).
#[derive(Debug, Clone)]
pub struct OneEuro {
    min_cutoff: f32,
    beta: f32,
    value: Option<f32>,
    derivative: f32,
}

const DERIVATIVE_CUTOFF_HZ: f32 = 1.0;

fn smoothing_factor(cutoff_hz: f32, dt: f32) -> f32 {
    let tau = 1.0 / (2.0 * std::f32::consts::PI * cutoff_hz);
    1.0 / (1.0 + tau / dt)
}

impl OneEuro {
    pub fn new(min_cutoff: f32, beta: f32) -> Self {
        Self {
            min_cutoff,
            beta,
            value: None,
            derivative: 0.0,
        }
    }

    pub fn filter(&mut self, x: f32, dt: f32) -> f32 {
        let Some(previous) = self.value else {
            self.value = Some(x);
            return x;
        };
        let a_d = smoothing_factor(DERIVATIVE_CUTOFF_HZ, dt);
        self.derivative += a_d * ((x - previous) / dt - self.derivative);
        let cutoff = self.min_cutoff + self.beta * self.derivative.abs();
        let value = previous + smoothing_factor(cutoff, dt) * (x - previous);
        self.value = Some(value);
        value
    }
}

/// Yaw (radians) about +z of the rotation q = [w, x, y, z].
pub fn yaw_of(q: &[f32; 4]) -> f32 {
    let [w, x, y, z] = *q;
    (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z))
}

fn normalized(q: [f32; 4]) -> [f32; 4] {
    let n = q.iter().map(|c| c * c).sum::<f32>().sqrt();
    if n > 0.0 && n.is_finite() {
        q.map(|c| c / n)
    } else {
        [1.0, 0.0, 0.0, 0.0]
    }
}

/// Filtered pose of one stream.
#[derive(Debug, Clone, PartialEq)]
pub struct Pose {
    /// Raw rotation in the hemisphere of the previous one.
    pub q_raw: [f32; 4],
    pub q: [f32; 4],
    /// Unwrapped yaw of the raw and filtered rotations (radians; continuous over turns).
    pub yaw_raw: f32,
    pub yaw: f32,
    pub z_e: Vec<f32>,
}

#[derive(Debug, Clone)]
pub struct PoseFilter {
    smoothing: Smoothing,
    min_cutoff: f32,
    beta: f32,
    q: [OneEuro; 4],
    z_e: Vec<OneEuro>,
    last_q: Option<[f32; 4]>,
    yaw_raw: Option<f32>,
    yaw: Option<f32>,
}

impl PoseFilter {
    pub fn new(settings: &TrackSettings) -> Self {
        let euro = || OneEuro::new(settings.min_cutoff_hz, settings.beta);
        Self {
            smoothing: settings.smoothing,
            min_cutoff: settings.min_cutoff_hz,
            beta: settings.beta,
            q: [euro(), euro(), euro(), euro()],
            z_e: Vec::new(),
            last_q: None,
            yaw_raw: None,
            yaw: None,
        }
    }

    pub fn update(&mut self, q: [f32; 4], z_e: &[f32], dt: f32) -> Pose {
        let mut q = normalized(q);
        if let Some(last) = self.last_q {
            if q.iter().zip(&last).map(|(a, b)| a * b).sum::<f32>() < 0.0 {
                q = q.map(|c| -c);
            }
        }
        self.last_q = Some(q);
        if self.z_e.len() != z_e.len() {
            self.z_e = vec![OneEuro::new(self.min_cutoff, self.beta); z_e.len()];
        }
        let (q_filtered, z_e_filtered) = match self.smoothing {
            Smoothing::None => (q, z_e.to_vec()),
            Smoothing::OneEuro => {
                let mut filtered = [0.0; 4];
                for (k, f) in self.q.iter_mut().enumerate() {
                    filtered[k] = f.filter(q[k], dt);
                }
                let z: Vec<f32> = z_e.iter().zip(&mut self.z_e).map(|(x, f)| f.filter(*x, dt)).collect();
                (normalized(filtered), z)
            }
        };
        let yaw_raw = unwrap(self.yaw_raw, yaw_of(&q));
        let yaw = unwrap(self.yaw, yaw_of(&q_filtered));
        self.yaw_raw = Some(yaw_raw);
        self.yaw = Some(yaw);
        Pose {
            q_raw: q,
            q: q_filtered,
            yaw_raw,
            yaw,
            z_e: z_e_filtered,
        }
    }
}

/// The angle equal to `angle` modulo 2 pi that is nearest to `previous`.
pub fn unwrap(previous: Option<f32>, angle: f32) -> f32 {
    use std::f32::consts::{PI, TAU};
    match previous {
        None => angle,
        Some(p) => {
            let delta = (angle - p + PI).rem_euclid(TAU) - PI;
            p + delta
        }
    }
}

/// A confidence in (0, 1] from log-variances: 1 / (1 + mean variance).
pub fn confidence_from_log_variance(log_variance: &[f32]) -> f32 {
    if log_variance.is_empty() {
        return 0.0;
    }
    let mean = log_variance.iter().map(|lv| lv.clamp(-20.0, 20.0).exp()).sum::<f32>() / log_variance.len() as f32;
    1.0 / (1.0 + mean)
}
