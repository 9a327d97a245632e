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
//! - `step`: the last `step_window` frames against up to `step_reference` frames before them
//!   (since the last change), each side the precision-weighted mean of its frames (a frame's z_I
//!   variance floored at `step_min_variance`); a change when their mean squared standardized
//!   distance exceeds `step_threshold`, tested once at least `switch_frames` frames precede the
//!   window. Each frame enters clipped to within `step_clip` standard deviations of the
//!   reference's mean, per dimension, so that one wild frame moves either side a bounded amount.
//!   The new identity starts from the window's frames. A subject's z_I wanders slowly with its
//!   pose and view, which moves both sides together and so never adds up as it does in the CUSUM
//!   against a fixed estimate; a change of subject is a step. Frames are fused (for the published
//!   z_I) as they come, by the gate alone.
//!
//! The fused variance has a floor (`min_shape_variance`; `min_identity_variance` for the identity
//! projection's code below), which makes the estimate a slowly forgetting average: it follows the
//! slow drift of z_I as the subject turns and changes pose.
//!
//! With an **identity projection** (the bundle's `calibration.identity_projection`, fitted on the
//! node's own clouds of many sim subjects; `[track] use_identity_projection`) the distances, the
//! gate and the change detector work on the projected code of the encoder's x_c instead, whose
//! directions are those that tell subjects of one family apart, scaled to unit within-subject
//! spread (each frame's variance 1), with `identity_cusum_drift` / `identity_cusum_threshold`. The
//! published z_I is still fused as above, on the same frames.

use std::collections::VecDeque;

use super::settings::{ChangeDetector, IdentityDirections, TrackSettings};

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

/// One frame's Gaussian in one space: z_I, or the identity projection's code.
#[derive(Debug, Clone)]
struct Gaussian {
    mean: Vec<f32>,
    variance: Vec<f32>,
}

#[derive(Debug, Clone)]
struct Held {
    shape: Gaussian,
    /// The identity projection's code, when there is one.
    code: Option<Gaussian>,
    inlier: bool,
    /// Already in the estimate (a young estimate takes its inliers at once).
    fused: bool,
}

/// A frame as the step detector keeps it: the frame itself (a change restarts the estimate from
/// it) and its code in the detector's space, clipped on entry (`step_clip`), with its precisions.
#[derive(Debug, Clone)]
struct StepFrame {
    held: Held,
    raw: Vec<f64>,
    value: Vec<f64>,
    precision: Vec<f64>,
}

/// The precision-weighted mean of some step frames and its precision, per dimension.
fn step_side<'a>(frames: impl Iterator<Item = &'a StepFrame>, width: usize) -> (Vec<f64>, Vec<f64>) {
    let (mut precision, mut weighted) = (vec![0.0f64; width], vec![0.0f64; width]);
    for frame in frames {
        for k in 0..width {
            precision[k] += frame.precision[k];
            weighted[k] += frame.precision[k] * frame.value[k];
        }
    }
    let mean = weighted.iter().zip(&precision).map(|(w, p)| w / p).collect();
    (mean, precision)
}

/// A precision-weighted running product of Gaussians, with a floor on its variance.
#[derive(Debug, Clone, Default)]
struct Fusion {
    mean: Vec<f32>,
    precision: Vec<f32>,
}

impl Fusion {
    fn starting(width: usize) -> Self {
        Self {
            mean: vec![0.0; width],
            precision: vec![0.0; width],
        }
    }

    fn fuse(&mut self, frame: &Gaussian, max_precision: f32) {
        for k in 0..self.mean.len() {
            let p = 1.0 / frame.variance[k].max(1e-12);
            let total = self.precision[k] + p;
            self.mean[k] = (self.mean[k] * self.precision[k] + frame.mean[k] * p) / total;
            self.precision[k] = total.min(max_precision);
        }
    }

    /// Mean over dimensions of (mu - m)^2 / (frame variance + fused variance).
    fn distance(&self, frame: &Gaussian) -> f32 {
        let sum: f32 = frame
            .mean
            .iter()
            .zip(&frame.variance)
            .zip(self.mean.iter().zip(&self.precision))
            .map(|((mu, var), (m, p))| (mu - m).powi(2) / (var + 1.0 / p))
            .sum();
        sum / frame.mean.len().max(1) as f32
    }
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
    /// The same for the identity projection's code.
    code_max_precision: f32,
    variance_scale: f32,
    detector: ChangeDetector,
    drift: f32,
    threshold: f32,
    step_window: usize,
    step_reference: usize,
    step_threshold: f32,
    /// Floor on a frame's z_I variance in the step detector (model units); none on the
    /// projection's code, whose frames have unit variance.
    step_floor: f32,
    step_clip: f32,
    /// The detector's threshold on its statistic (`TrackSettings::change_threshold`).
    change_threshold: f32,
    /// The step detector's frames since the last change, at most `step_window + step_reference`.
    steps: VecDeque<StepFrame>,
    projection: Option<IdentityDirections>,
    /// The published z_I estimate.
    shape: Fusion,
    /// The identity projection's estimate, on which distances are taken when there is one.
    code: Option<Fusion>,
    frames: u64,
    identity: u64,
    statistic: f32,
    /// Frames since the suspicion began (cusum) or the current run of outliers (consecutive).
    held: Vec<Held>,
    recent: VecDeque<bool>,
}

impl ShapeFilter {
    pub fn new(settings: &TrackSettings) -> Self {
        let (drift, threshold) = settings.cusum();
        Self {
            gate: settings.shape_gate,
            switch_frames: settings.switch_frames,
            max_precision: 1.0 / settings.min_shape_variance,
            code_max_precision: 1.0 / settings.min_identity_variance,
            variance_scale: settings.shape_variance_scale,
            detector: settings.change_detector,
            drift,
            threshold,
            step_window: settings.step_window,
            step_reference: settings.step_reference,
            step_threshold: settings.step_threshold(),
            step_floor: settings.step_min_variance,
            step_clip: settings.step_clip,
            change_threshold: settings.change_threshold(),
            steps: VecDeque::new(),
            projection: settings.identity_directions().cloned(),
            shape: Fusion::default(),
            code: None,
            frames: 0,
            identity: 0,
            statistic: 0.0,
            held: Vec::new(),
            recent: VecDeque::new(),
        }
    }

    /// The change detector's threshold on `ShapeUpdate::statistic`.
    pub fn threshold(&self) -> f32 {
        self.change_threshold
    }

    /// Whether distances are taken on the identity projection's code (else on z_I).
    pub fn projected(&self) -> bool {
        self.projection.is_some()
    }

    /// One frame's z_I (mean, log-variance), without an identity projection's code: under a
    /// projection, use [`ShapeFilter::update_coded`].
    pub fn update(&mut self, mean: &[f32], log_variance: &[f32]) -> ShapeUpdate {
        self.update_coded(mean, log_variance, &[])
    }

    /// One frame's z_I (mean, log-variance) and the encoder's x_c, which the identity projection
    /// (when there is one) reads. An x_c of another width than the projection's rows is a bundle
    /// the node refused at start, so it cannot reach here; it is read as zeros.
    pub fn update_coded(&mut self, mean: &[f32], log_variance: &[f32], x_c: &[f32]) -> ShapeUpdate {
        let variance: Vec<f32> = log_variance
            .iter()
            .map(|lv| lv.clamp(-20.0, 20.0).exp() * self.variance_scale)
            .collect();
        let shape = Gaussian {
            mean: mean.to_vec(),
            variance,
        };
        let code = self.projection.as_ref().map(|rows| Gaussian {
            mean: rows
                .iter()
                .map(|row| row.iter().zip(x_c).map(|(w, x)| w * x).sum())
                .collect(),
            variance: vec![1.0; rows.len()],
        });
        if self.frames == 0 || self.shape.mean.len() != mean.len() {
            let first = Held {
                shape,
                code,
                inlier: true,
                fused: true,
            };
            self.steps = VecDeque::from([self.step_frame(first.clone())]);
            self.restart(vec![first]);
            return self.record(true, 0.0, None);
        }
        let distance = match (&self.code, &code) {
            (Some(fused), Some(frame)) => fused.distance(frame),
            _ => self.shape.distance(&shape),
        };
        let frame = Held {
            shape,
            code,
            inlier: distance <= self.gate,
            fused: false,
        };
        match self.detector {
            ChangeDetector::Consecutive => self.consecutive(frame, distance),
            ChangeDetector::Cusum => self.cusum(frame, distance),
            ChangeDetector::Step => self.step(frame, distance),
        }
    }

    fn step(&mut self, frame: Held, distance: f32) -> ShapeUpdate {
        let inlier = frame.inlier;
        self.steps.push_back(self.step_frame(frame.clone()));
        if self.steps.len() > self.step_window + self.step_reference {
            self.steps.pop_front();
        }
        let before = self.steps.len().saturating_sub(self.step_window);
        self.statistic = if before >= self.switch_frames {
            self.clip_newest_and_measure(before)
        } else {
            0.0
        };
        if self.statistic > self.step_threshold {
            // The window's frames are the new subject's: they start its estimate and its reference,
            // unclipped.
            let mut window: Vec<StepFrame> = self.steps.drain(before..).collect();
            for frame in &mut window {
                frame.value.clone_from(&frame.raw);
            }
            let previous = self.identity;
            self.restart(window.iter().map(|f| f.held.clone()).collect());
            self.steps = window.into();
            self.identity = previous + 1;
            self.recent.clear();
            let change = IdentityChange {
                previous,
                identity: self.identity,
            };
            return self.record(true, distance, Some(change));
        }
        if inlier {
            self.fuse(&frame);
        }
        self.record(inlier, distance, None)
    }

    /// A frame in the step detector's space: the projection's code when there is one (unit
    /// variances), else z_I with its variances floored at `step_min_variance`.
    fn step_frame(&self, held: Held) -> StepFrame {
        let (space, floor) = match &held.code {
            Some(code) if self.projection.is_some() => (code, 0.0),
            _ => (&held.shape, self.step_floor as f64),
        };
        let raw: Vec<f64> = space.mean.iter().map(|m| *m as f64).collect();
        let precision = space
            .variance
            .iter()
            .map(|v| 1.0 / (*v as f64).max(floor).max(1e-12))
            .collect();
        StepFrame {
            value: raw.clone(),
            raw,
            precision,
            held,
        }
    }

    /// Clips the newest frame to within `step_clip` standard deviations (its own and m_r's) of
    /// m_r, then returns the step detector's statistic: the mean over dimensions of
    /// (m_w - m_r)^2 / (1/P_w + 1/P_r) between the precision-weighted means of the last
    /// `step_window` frames (w) and the frames before them (r, up to index `before`).
    fn clip_newest_and_measure(&mut self, before: usize) -> f32 {
        let width = self.steps[0].raw.len();
        let (reference, reference_precision) = step_side(self.steps.range(..before), width);
        let clip = self.step_clip as f64;
        if clip.is_finite() {
            let newest = self.steps.back_mut().expect("the frame just pushed");
            for k in 0..width {
                let limit = clip * (1.0 / newest.precision[k] + 1.0 / reference_precision[k]).sqrt();
                newest.value[k] = reference[k] + (newest.raw[k] - reference[k]).clamp(-limit, limit);
            }
        }
        let (window, window_precision) = step_side(self.steps.range(before..), width);
        let sum: f64 = (0..width)
            .map(|k| (window[k] - reference[k]).powi(2) / (1.0 / window_precision[k] + 1.0 / reference_precision[k]))
            .sum();
        (sum / width.max(1) as f64) as f32
    }

    fn consecutive(&mut self, frame: Held, distance: f32) -> ShapeUpdate {
        if frame.inlier {
            self.fuse(&frame);
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
                    self.fuse(&held);
                }
            }
            if inlier {
                self.fuse(&frame);
            }
            return self.record(inlier, distance, None);
        }
        if inlier && self.frames < MATURE_FRAMES {
            self.fuse(&frame);
            frame.fused = true;
        }
        self.held.push(frame);
        if self.held.len() > MAX_HELD {
            let oldest = self.held.remove(0);
            if oldest.inlier && !oldest.fused {
                self.fuse(&oldest);
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

    /// Mean over dimensions of (mu - m)^2 / (s sigma^2 + fused variance) of a z_I, with the
    /// frame's variances as the encoder reports them (log-variances are not taken here).
    pub fn distance(&self, mean: &[f32], variance: &[f32]) -> f32 {
        self.shape.distance(&Gaussian {
            mean: mean.to_vec(),
            variance: variance.iter().map(|v| v * self.variance_scale).collect(),
        })
    }

    fn restart(&mut self, frames: Vec<Held>) {
        self.shape = Fusion::starting(frames[0].shape.mean.len());
        self.code = frames[0].code.as_ref().map(|code| Fusion::starting(code.mean.len()));
        self.frames = 0;
        for frame in &frames {
            self.fuse(frame);
        }
    }

    fn fuse(&mut self, frame: &Held) {
        self.shape.fuse(&frame.shape, self.max_precision);
        if let (Some(fused), Some(code)) = (&mut self.code, &frame.code) {
            fused.fuse(code, self.code_max_precision);
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

    /// The fused z_I.
    pub fn mean(&self) -> &[f32] {
        &self.shape.mean
    }

    /// The fused z_I's variance.
    pub fn variance(&self) -> Vec<f32> {
        self.shape.precision.iter().map(|p| 1.0 / p).collect()
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
