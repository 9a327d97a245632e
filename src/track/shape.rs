//! Shape: z_I is a constant of the object, so the frames' Gaussians N(mu_t, s * sigma_t^2) are
//! fused as their precision-weighted product (`s` is the bundle's variance calibration,
//! `shape_variance_scale`). Each frame's mean squared standardized distance to the fused estimate
//! says how well it agrees; a frame beyond `shape_gate` is not fused.
//!
//! Identity changes are found by a sequential test on those distances (`change_detector`):
//! - `cusum` (default): S_t = max(0, S_{t-1} + min(d_t, clip) - k) with drift allowance
//!   k = `cusum_drift` and clip = k + h / `switch_frames`; a change is reported when S_t reaches
//!   h = `cusum_threshold`, so never on fewer than `switch_frames` frames. A small persistent shift
//!   accumulates where "k outliers in a row" would miss it; one wild frame adds at most h /
//!   `switch_frames`. While S_t > 0 the frames are held, not fused (once the estimate rests on 30
//!   frames): if the suspicion clears they are fused late, if a change is reported the new
//!   identity starts from them.
//! - `consecutive`: `switch_frames` frames beyond the gate in a row.
//!
//! The fused variance has a floor (`min_shape_variance`), which makes the estimate a slowly
//! forgetting average: it follows the slow drift of z_I as the subject turns and changes pose.

use std::collections::VecDeque;

use super::settings::{ChangeDetector, TrackSettings};

/// What one frame did to the shape estimate.
#[derive(Debug, Clone, PartialEq)]
pub struct ShapeUpdate {
    /// The frame agreed with the fused estimate (distance within the gate), or started it.
    pub inlier: bool,
    /// Mean squared standardized distance of the frame's z_I to the estimate before this frame.
    pub distance: f32,
    /// The change detector's statistic after this frame.
    pub statistic: f32,
    /// Set on the frame that completed an identity change.
    pub change: Option<IdentityChange>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct IdentityChange {
    pub previous: u64,
    pub identity: u64,
}

/// Frames held while a change is suspected, at most (about 10 s at 30 Hz); older ones are fused.
const MAX_HELD: usize = 300;
const CONFIDENCE_WINDOW: usize = 20;

#[derive(Debug, Clone)]
struct Held {
    mean: Vec<f32>,
    variance: Vec<f32>,
    inlier: bool,
    /// Already in the estimate (a young estimate takes its inliers at once).
    fused: bool,
}

/// An estimate of fewer frames than this takes its inliers at once, even under suspicion: holding
/// them would leave it resting on a handful of frames whose common error every later frame would
/// seem to confirm.
const MATURE_FRAMES: u64 = 30;

/// Causal precision-weighted fusion of per-frame z_I Gaussians, with outlier gating and identity
/// change detection.
#[derive(Debug, Clone)]
pub struct ShapeFilter {
    gate: f32,
    switch_frames: usize,
    max_precision: f32,
    variance_scale: f32,
    detector: ChangeDetector,
    drift: f32,
    threshold: f32,
    mean: Vec<f32>,
    precision: Vec<f32>,
    frames: u64,
    identity: u64,
    statistic: f32,
    /// Frames since the suspicion began (cusum) or the current run of outliers (consecutive).
    held: Vec<Held>,
    recent: VecDeque<bool>,
}

impl ShapeFilter {
    pub fn new(settings: &TrackSettings) -> Self {
        Self {
            gate: settings.shape_gate,
            switch_frames: settings.switch_frames,
            max_precision: 1.0 / settings.min_shape_variance,
            variance_scale: settings.shape_variance_scale,
            detector: settings.change_detector,
            drift: settings.cusum_drift,
            threshold: settings.cusum_threshold,
            mean: Vec::new(),
            precision: Vec::new(),
            frames: 0,
            identity: 0,
            statistic: 0.0,
            held: Vec::new(),
            recent: VecDeque::new(),
        }
    }

    /// The change detector's threshold on `ShapeUpdate::statistic`.
    pub fn threshold(&self) -> f32 {
        match self.detector {
            ChangeDetector::Cusum => self.threshold,
            ChangeDetector::Consecutive => self.switch_frames as f32,
        }
    }

    pub fn update(&mut self, mean: &[f32], log_variance: &[f32]) -> ShapeUpdate {
        let variance: Vec<f32> = log_variance
            .iter()
            .map(|lv| lv.clamp(-20.0, 20.0).exp() * self.variance_scale)
            .collect();
        if self.frames == 0 || self.mean.len() != mean.len() {
            self.restart(vec![Held {
                mean: mean.to_vec(),
                variance,
                inlier: true,
                fused: true,
            }]);
            return self.record(true, 0.0, None);
        }
        let distance = self.distance_scaled(mean, &variance);
        let frame = Held {
            mean: mean.to_vec(),
            variance,
            inlier: distance <= self.gate,
            fused: false,
        };
        match self.detector {
            ChangeDetector::Consecutive => self.consecutive(frame, distance),
            ChangeDetector::Cusum => self.cusum(frame, distance),
        }
    }

    fn consecutive(&mut self, frame: Held, distance: f32) -> ShapeUpdate {
        if frame.inlier {
            self.fuse(&frame.mean, &frame.variance);
            self.held.clear();
            self.statistic = 0.0;
            return self.record(true, distance, None);
        }
        self.held.push(frame);
        self.statistic = self.held.len() as f32;
        if self.held.len() < self.switch_frames {
            return self.record(false, distance, None);
        }
        let change = self.change();
        self.record(true, distance, Some(change))
    }

    fn cusum(&mut self, mut frame: Held, distance: f32) -> ShapeUpdate {
        let clip = self.drift + self.threshold / self.switch_frames as f32;
        let evidence = if distance.is_finite() { distance.min(clip) } else { clip };
        self.statistic = (self.statistic + evidence - self.drift).max(0.0);
        let inlier = frame.inlier;
        if self.statistic <= 0.0 {
            // No suspicion (any more): what was held joins the estimate, then this frame.
            for held in std::mem::take(&mut self.held) {
                if held.inlier && !held.fused {
                    self.fuse(&held.mean, &held.variance);
                }
            }
            if inlier {
                self.fuse(&frame.mean, &frame.variance);
            }
            return self.record(inlier, distance, None);
        }
        if inlier && self.frames < MATURE_FRAMES {
            self.fuse(&frame.mean, &frame.variance);
            frame.fused = true;
        }
        self.held.push(frame);
        if self.held.len() > MAX_HELD {
            let oldest = self.held.remove(0);
            if oldest.inlier && !oldest.fused {
                self.fuse(&oldest.mean, &oldest.variance);
            }
        }
        if self.statistic >= self.threshold && self.held.len() >= self.switch_frames {
            let change = self.change();
            return self.record(true, distance, Some(change));
        }
        self.record(inlier, distance, None)
    }

    /// A new identity, started from the held frames.
    fn change(&mut self) -> IdentityChange {
        let previous = self.identity;
        let held = std::mem::take(&mut self.held);
        self.restart(held);
        self.identity = previous + 1;
        self.statistic = 0.0;
        self.recent.clear();
        IdentityChange {
            previous,
            identity: self.identity,
        }
    }

    /// Mean over dimensions of (mu - m)^2 / (s sigma^2 + fused variance), with the frame's
    /// variances as the encoder reports them (log-variances are not taken here).
    pub fn distance(&self, mean: &[f32], variance: &[f32]) -> f32 {
        let scaled: Vec<f32> = variance.iter().map(|v| v * self.variance_scale).collect();
        self.distance_scaled(mean, &scaled)
    }

    fn distance_scaled(&self, mean: &[f32], variance: &[f32]) -> f32 {
        let sum: f32 = mean
            .iter()
            .zip(variance)
            .zip(self.mean.iter().zip(&self.precision))
            .map(|((mu, var), (m, p))| (mu - m).powi(2) / (var + 1.0 / p))
            .sum();
        sum / mean.len().max(1) as f32
    }

    fn restart(&mut self, frames: Vec<Held>) {
        let width = frames[0].mean.len();
        self.mean = vec![0.0; width];
        self.precision = vec![0.0; width];
        self.frames = 0;
        for frame in &frames {
            self.fuse(&frame.mean, &frame.variance);
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
            statistic: self.statistic,
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

    /// Fraction of the last 20 frames (since the last identity change) that agreed with the estimate.
    pub fn confidence(&self) -> f32 {
        if self.recent.is_empty() {
            return 0.0;
        }
        self.recent.iter().filter(|i| **i).count() as f32 / self.recent.len() as f32
    }
}
