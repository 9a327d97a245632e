//! Pose smoothing: z_E and the rotation through one-euro filters (little lag when they move,
//! little jitter when they rest); the quaternion is kept in one hemisphere (q and -q are the same
//! rotation) and the yaw about the up axis is unwrapped. The heading tracker (`heading.rs`) may
//! replace the yaw of the smoothed rotation.

use super::settings::{Smoothing, TrackSettings};

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

/// q [w, x, y, z] with the turn about +z by `angle` (radians) applied on the left: R_z(angle) * q.
pub fn turn_rotation(q: [f32; 4], angle: f32) -> [f32; 4] {
    let (s, c) = (angle / 2.0).sin_cos();
    let [w, x, y, z] = q;
    [c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w]
}

/// `q` scaled to unit length; the identity rotation if it has none (zero or not finite).
pub(crate) fn normalized(q: [f32; 4]) -> [f32; 4] {
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
