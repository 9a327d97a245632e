//! The rest-pose body of a subject as an implicit surface.
//!
//! A subject is a smooth union of round cones (capsules whose radius varies along the bone), each
//! carried by one joint. Meshing the zero level set gives a closed surface without self-intersections
//! by construction, and the per-part distances give smooth skinning weights for free.

use nalgebra::{Point3, Vector3};

/// A round cone from `start` to `end`, radius varying linearly; `lateral_scale` > 1 widens the
/// cross-section along the world y axis (torsos are wider than they are deep).
#[derive(Debug, Clone)]
pub struct RoundCone {
    pub start: Point3<f64>,
    pub end: Point3<f64>,
    pub start_radius: f64,
    pub end_radius: f64,
    pub lateral_scale: f64,
}

impl RoundCone {
    pub fn new(start: Point3<f64>, end: Point3<f64>, start_radius: f64, end_radius: f64) -> Self {
        Self {
            start,
            end,
            start_radius,
            end_radius,
            lateral_scale: 1.0,
        }
    }

    pub fn widened(mut self, lateral_scale: f64) -> Self {
        self.lateral_scale = lateral_scale;
        self
    }

    /// Approximate signed distance (exact for `lateral_scale` = 1 and equal radii).
    pub fn distance(&self, point: &Point3<f64>) -> f64 {
        let squash = |p: Vector3<f64>| Vector3::new(p.x, p.y / self.lateral_scale, p.z);
        let axis = squash(self.end - self.start);
        let relative = squash(point - self.start);
        let length_squared = axis.norm_squared();
        let t = if length_squared > 0.0 {
            (relative.dot(&axis) / length_squared).clamp(0.0, 1.0)
        } else {
            0.0
        };
        let radius = self.start_radius + t * (self.end_radius - self.start_radius);
        (relative - t * axis).norm() - radius
    }

    /// Axis-aligned bounds: the radius along x and z, the radius times `lateral_scale` along y.
    fn bounds(&self) -> (Point3<f64>, Point3<f64>) {
        let radius = self.start_radius.max(self.end_radius);
        let reach = Vector3::new(radius, radius * self.lateral_scale, radius);
        let lower = self.start.coords.inf(&self.end.coords) - reach;
        let upper = self.start.coords.sup(&self.end.coords) + reach;
        (lower.into(), upper.into())
    }
}

/// One primitive and the joint that carries it.
#[derive(Debug, Clone)]
pub struct Part {
    pub shape: RoundCone,
    pub joint: usize,
}

/// The implicit body: a smooth union of parts with blend radius `blend`.
#[derive(Debug, Clone)]
pub struct Body {
    pub parts: Vec<Part>,
    pub blend: f64,
}

/// Polynomial smooth minimum (Quilez): equal to `min` when the arguments differ by more than `k`.
fn smooth_min(a: f64, b: f64, k: f64) -> f64 {
    let h = (k - (a - b).abs()).max(0.0) / k;
    a.min(b) - h * h * k * 0.25
}

impl Body {
    /// The blended field: the smooth minimum of the part distances, in part order.
    pub fn distance(&self, point: &Point3<f64>) -> f64 {
        let mut distances = self.parts.iter().map(|part| part.shape.distance(point));
        let Some(first) = distances.next() else {
            return f64::INFINITY;
        };
        distances.fold(first, |acc, d| smooth_min(acc, d, self.blend))
    }

    /// Central-difference gradient of the distance.
    pub fn gradient(&self, point: &Point3<f64>, step: f64) -> Vector3<f64> {
        let mut gradient = Vector3::zeros();
        for axis in 0..3 {
            let mut offset = Vector3::zeros();
            offset[axis] = step;
            gradient[axis] = (self.distance(&(point + offset)) - self.distance(&(point - offset))) / (2.0 * step);
        }
        gradient
    }

    /// Axis-aligned bounds of the surface, padded by `margin`.
    pub fn bounds(&self, margin: f64) -> (Point3<f64>, Point3<f64>) {
        let mut lower = Vector3::repeat(f64::INFINITY);
        let mut upper = Vector3::repeat(f64::NEG_INFINITY);
        for part in &self.parts {
            let (l, u) = part.shape.bounds();
            lower = lower.inf(&l.coords);
            upper = upper.sup(&u.coords);
        }
        (lower.add_scalar(-margin).into(), upper.add_scalar(margin).into())
    }
}
