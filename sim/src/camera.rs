//! A virtual stereo depth camera in the style of an OAK-D: what the node sees on a robot.
//!
//! The scene (posed subject meshes, a ground patch, optional clutter boxes) is z-buffered from the
//! left (reference) camera and from the right camera one baseline away. A pixel is valid only where
//! both see the same surface (stereo occlusion), away from depth discontinuities (where block
//! matching fails), and inside the disparity range. Depth noise is added in disparity, so its
//! standard deviation in depth grows with depth squared, then quantised to subpixel steps and
//! written as uint16 millimetres (0 = invalid), as the device does.
//!
//! Frames: the camera frame is the ROS optical frame (x right, y down, z forward); the world is
//! metres with z up and the ground at z = 0.

use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

use crate::mesh::Mesh;

/// Pinhole intrinsics; pixel (u, v) has its centre at integer coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// The OAK-D's stereo pair at 640x400 (fx = fy = 441.25 px), principal point at the centre.
    pub fn oak_d_400p() -> Self {
        Self {
            width: 640,
            height: 400,
            fx: 441.25,
            fy: 441.25,
            cx: 319.5,
            cy: 199.5,
        }
    }

    /// Row-major 3x3 camera matrix (CameraInfo `k`).
    pub fn matrix(&self) -> [f64; 9] {
        [self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0]
    }

    /// Ray through a pixel, scaled so its z component is 1 (so `ray * depth` is the point).
    fn ray(&self, u: f64, v: f64) -> Vector3<f64> {
        Vector3::new((u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0)
    }
}

/// How the stereo matcher degrades depth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StereoModel {
    /// Distance between the two cameras (m); the right camera sits at +x in the optical frame.
    pub baseline: f64,
    /// Standard deviation of the disparity error (px); depth sigma = z^2 * this / (fx * baseline).
    pub disparity_sigma: f64,
    /// Disparity quantum (px): OAK-D subpixel mode has 3 fractional bits.
    pub disparity_step: f64,
    /// Largest disparity the matcher searches (px); sets the minimum depth fx * baseline / this.
    pub max_disparity: f64,
    /// Depths beyond this are reported invalid (m).
    pub max_depth: f64,
    /// A pixel whose 8-neighbour differs in depth by more than this fraction of its own is invalid.
    pub edge_threshold: f64,
}

impl StereoModel {
    pub fn oak_d() -> Self {
        Self {
            baseline: 0.075,
            disparity_sigma: 0.1,
            disparity_step: 0.125,
            max_disparity: 95.0,
            max_depth: 10.0,
            edge_threshold: 0.04,
        }
    }

    /// Standard deviation of depth at `z` metres.
    pub fn depth_sigma(&self, fx: f64, z: f64) -> f64 {
        z * z * self.disparity_sigma / (fx * self.baseline)
    }
}

/// A camera in the world: intrinsics, stereo model, and where it stands.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DepthCamera {
    pub intrinsics: Intrinsics,
    pub stereo: StereoModel,
    /// Maps optical-frame points to world points.
    pub world_from_camera: Isometry3<f64>,
}

/// Everything the camera can see.
#[derive(Debug, Clone, Default)]
pub struct Scene {
    pub meshes: Vec<Mesh>,
    /// Half the side of the square ground patch centred at the origin (m); `None`: no ground.
    pub ground_half_extent: Option<f64>,
}

/// A depth frame: uint16 millimetres, row-major, 0 where invalid.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub millimetres: Vec<u16>,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("camera parameter '{0}' must be positive and finite, got {1}")]
    NotPositive(&'static str, f64),
    #[error("camera position {0:?} and target {1:?} coincide or are vertically aligned")]
    DegenerateLookAt([f64; 3], [f64; 3]),
}

impl DepthCamera {
    /// A camera at `position` looking at `target`, with the image's "down" towards the world's -z.
    pub fn looking_at(
        intrinsics: Intrinsics,
        stereo: StereoModel,
        position: Point3<f64>,
        target: Point3<f64>,
    ) -> Result<Self, CameraError> {
        let degenerate = || CameraError::DegenerateLookAt(position.coords.into(), target.coords.into());
        let forward = (target - position).try_normalize(1e-9).ok_or_else(degenerate)?;
        let right = forward
            .cross(&Vector3::z())
            .try_normalize(1e-6)
            .ok_or_else(degenerate)?;
        let down = forward.cross(&right);
        let rotation = Rotation3::from_basis_unchecked(&[right, down, forward]);
        let camera = Self {
            intrinsics,
            stereo,
            world_from_camera: Isometry3::from_parts(
                Translation3::from(position.coords),
                UnitQuaternion::from_rotation_matrix(&rotation),
            ),
        };
        camera.validate()?;
        Ok(camera)
    }

    pub fn validate(&self) -> Result<(), CameraError> {
        let i = &self.intrinsics;
        let s = &self.stereo;
        for (name, value) in [
            ("width", i.width as f64),
            ("height", i.height as f64),
            ("fx", i.fx),
            ("fy", i.fy),
            ("baseline", s.baseline),
            ("disparity_step", s.disparity_step),
            ("max_disparity", s.max_disparity),
            ("max_depth", s.max_depth),
            ("edge_threshold", s.edge_threshold),
        ] {
            if !(value > 0.0 && value.is_finite()) {
                return Err(CameraError::NotPositive(name, value));
            }
        }
        if !(s.disparity_sigma >= 0.0 && s.disparity_sigma.is_finite()) {
            return Err(CameraError::NotPositive("disparity_sigma", s.disparity_sigma));
        }
        Ok(())
    }

    /// Nearest depth the matcher can measure (m).
    pub fn min_depth(&self) -> f64 {
        self.intrinsics.fx * self.stereo.baseline / self.stereo.max_disparity
    }

    /// Renders one noisy depth frame.
    pub fn capture(&self, scene: &Scene, rng: &mut impl Rng) -> DepthImage {
        self.capture_labelled(scene, rng).0
    }

    /// [`DepthCamera::capture`], with the index of the mesh (in `scene.meshes`) each valid pixel
    /// measured ([`NO_MESH`] where the pixel is invalid or saw the ground).
    pub fn capture_labelled(&self, scene: &Scene, rng: &mut impl Rng) -> (DepthImage, Vec<u16>) {
        let intrinsics = &self.intrinsics;
        let mut labels = vec![NO_MESH; intrinsics.width as usize * intrinsics.height as usize];
        let left = render_depth(intrinsics, &self.world_from_camera, scene, Some(&mut labels));
        let world_from_right = self.world_from_camera * Translation3::new(self.stereo.baseline, 0.0, 0.0);
        let right = render_depth(intrinsics, &world_from_right, scene, None);

        let (width, height) = (intrinsics.width as usize, intrinsics.height as usize);
        let min_depth = self.min_depth();
        let focal_baseline = intrinsics.fx * self.stereo.baseline;
        let mut millimetres = vec![0u16; width * height];
        for v in 0..height {
            for u in 0..width {
                let z = left[v * width + u];
                if !(z.is_finite() && z >= min_depth && z <= self.stereo.max_depth) {
                    continue;
                }
                if at_depth_edge(&left, width, height, u, v, self.stereo.edge_threshold)
                    || occluded_in_right(intrinsics, &right, u, v, z, self.stereo.baseline)
                {
                    continue;
                }
                let noise: f64 = StandardNormal.sample(rng);
                let disparity = focal_baseline / z + self.stereo.disparity_sigma * noise;
                let disparity = (disparity / self.stereo.disparity_step).round() * self.stereo.disparity_step;
                if disparity <= 0.0 || disparity > self.stereo.max_disparity {
                    continue;
                }
                let measured = focal_baseline / disparity;
                if measured <= self.stereo.max_depth {
                    millimetres[v * width + u] = (measured * 1000.0).round().min(65535.0) as u16;
                }
            }
        }
        for (label, depth) in labels.iter_mut().zip(&millimetres) {
            if *depth == 0 {
                *label = NO_MESH;
            }
        }
        let image = DepthImage {
            width: intrinsics.width,
            height: intrinsics.height,
            millimetres,
        };
        (image, labels)
    }
}

impl DepthImage {
    pub fn valid_pixels(&self) -> usize {
        self.millimetres.iter().filter(|&&d| d > 0).count()
    }

    /// Valid pixels as points in the optical frame (metres), taking every `step`-th pixel in each
    /// direction (the device's pixel-skipping decimation filter; 1 keeps every pixel).
    pub fn unproject(&self, intrinsics: &Intrinsics, step: usize) -> Vec<[f32; 3]> {
        let step = step.max(1);
        let mut points = Vec::new();
        for v in (0..self.height as usize).step_by(step) {
            for u in (0..self.width as usize).step_by(step) {
                let depth = self.millimetres[v * self.width as usize + u];
                if depth == 0 {
                    continue;
                }
                let point = intrinsics.ray(u as f64, v as f64) * (depth as f64 / 1000.0);
                points.push([point.x as f32, point.y as f32, point.z as f32]);
            }
        }
        points
    }
}

/// Noise-free optical depth per pixel (infinity where nothing is hit).
/// A pixel that measured no mesh (invalid, or the ground).
pub const NO_MESH: u16 = u16::MAX;

/// Noise-free optical depth per pixel (infinity where nothing is hit); with `labels`, the index of
/// the mesh nearest at each pixel.
fn render_depth(
    intrinsics: &Intrinsics,
    world_from_camera: &Isometry3<f64>,
    scene: &Scene,
    mut labels: Option<&mut [u16]>,
) -> Vec<f64> {
    let (width, height) = (intrinsics.width as usize, intrinsics.height as usize);
    let mut depth = vec![f64::INFINITY; width * height];
    if let Some(half_extent) = scene.ground_half_extent {
        render_ground(intrinsics, world_from_camera, half_extent, &mut depth);
    }
    let camera_from_world = world_from_camera.inverse();
    for (index, mesh) in scene.meshes.iter().enumerate() {
        let label = index.min(NO_MESH as usize - 1) as u16;
        let points: Vec<Point3<f64>> = mesh.positions.iter().map(|p| camera_from_world * p).collect();
        for triangle in &mesh.triangles {
            let corners = triangle.map(|i| points[i as usize]);
            rasterize(
                intrinsics,
                corners,
                &mut depth,
                labels.as_deref_mut().map(|l| (l, label)),
            );
        }
    }
    depth
}

/// The plane z = 0 inside a square patch.
fn render_ground(intrinsics: &Intrinsics, world_from_camera: &Isometry3<f64>, half_extent: f64, depth: &mut [f64]) {
    let origin = world_from_camera.translation.vector;
    let rotation = world_from_camera.rotation;
    let width = intrinsics.width as usize;
    for (index, pixel) in depth.iter_mut().enumerate() {
        let (u, v) = ((index % width) as f64, (index / width) as f64);
        let direction = rotation * intrinsics.ray(u, v);
        if direction.z >= -1e-12 {
            continue;
        }
        // The ray's z component in the optical frame is 1, so the parameter is the optical depth.
        let t = -origin.z / direction.z;
        let hit = origin + t * direction;
        if t > 0.0 && hit.x.abs() <= half_extent && hit.y.abs() <= half_extent {
            *pixel = pixel.min(t);
        }
    }
}

/// Z-buffers one triangle given in the optical frame; triangles reaching behind the near plane
/// are skipped (the scene is always well in front of the camera).
fn rasterize(
    intrinsics: &Intrinsics,
    corners: [Point3<f64>; 3],
    depth: &mut [f64],
    mut labels: Option<(&mut [u16], u16)>,
) {
    const NEAR: f64 = 0.05;
    if corners.iter().any(|p| p.z < NEAR) {
        return;
    }
    let projected = corners.map(|p| {
        (
            intrinsics.fx * p.x / p.z + intrinsics.cx,
            intrinsics.fy * p.y / p.z + intrinsics.cy,
            1.0 / p.z,
        )
    });
    let [(x0, y0, w0), (x1, y1, w1), (x2, y2, w2)] = projected;
    let area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0);
    if area.abs() < 1e-12 {
        return;
    }
    let (width, height) = (intrinsics.width as i64, intrinsics.height as i64);
    let min_u = (x0.min(x1).min(x2).ceil() as i64).max(0);
    let max_u = (x0.max(x1).max(x2).floor() as i64).min(width - 1);
    let min_v = (y0.min(y1).min(y2).ceil() as i64).max(0);
    let max_v = (y0.max(y1).max(y2).floor() as i64).min(height - 1);
    for v in min_v..=max_v {
        let y = v as f64;
        for u in min_u..=max_u {
            let x = u as f64;
            // Barycentric weights from edge functions; sign-agnostic so either winding renders.
            let b0 = ((x1 - x) * (y2 - y) - (x2 - x) * (y1 - y)) / area;
            let b1 = ((x2 - x) * (y0 - y) - (x0 - x) * (y2 - y)) / area;
            let b2 = 1.0 - b0 - b1;
            if b0 < 0.0 || b1 < 0.0 || b2 < 0.0 {
                continue;
            }
            // 1/z is affine in screen space: interpolate it, not z.
            let z = 1.0 / (b0 * w0 + b1 * w1 + b2 * w2);
            let index = (v * width + u) as usize;
            if z < depth[index] {
                depth[index] = z;
                if let Some((labels, label)) = labels.as_mut() {
                    labels[index] = *label;
                }
            }
        }
    }
}

fn at_depth_edge(depth: &[f64], width: usize, height: usize, u: usize, v: usize, threshold: f64) -> bool {
    let z = depth[v * width + u];
    for dv in -1i64..=1 {
        for du in -1i64..=1 {
            let (nu, nv) = (u as i64 + du, v as i64 + dv);
            if nu < 0 || nv < 0 || nu >= width as i64 || nv >= height as i64 {
                continue;
            }
            let neighbour = depth[nv as usize * width + nu as usize];
            if !neighbour.is_finite() || (neighbour - z).abs() > threshold * z {
                return true;
            }
        }
    }
    false
}

/// True when the right camera sees something nearer in front of this left-camera point: the
/// stereo matcher finds no correspondence there (the occlusion shadow beside foreground objects).
fn occluded_in_right(intrinsics: &Intrinsics, right: &[f64], u: usize, v: usize, z: f64, baseline: f64) -> bool {
    let disparity = intrinsics.fx * baseline / z;
    let right_u = (u as f64 - disparity).round();
    if right_u < 0.0 {
        return true;
    }
    let seen = right[v * intrinsics.width as usize + right_u as usize];
    seen < z * (1.0 - 0.02)
}

/// An axis-aligned box standing on the ground, as a closed mesh (clutter).
pub fn ground_box(centre_x: f64, centre_y: f64, size: Vector3<f64>, yaw: f64) -> Mesh {
    let half = size / 2.0;
    let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw);
    let mut positions = Vec::with_capacity(8);
    for corner in 0..8 {
        let local = Vector3::new(
            if corner & 1 == 0 { -half.x } else { half.x },
            if corner & 2 == 0 { -half.y } else { half.y },
            if corner & 4 == 0 { 0.0 } else { size.z },
        );
        positions.push(Point3::from(rotation * local + Vector3::new(centre_x, centre_y, 0.0)));
    }
    let triangles = vec![
        [0, 2, 3],
        [0, 3, 1],
        [4, 5, 7],
        [4, 7, 6],
        [0, 1, 5],
        [0, 5, 4],
        [2, 6, 7],
        [2, 7, 3],
        [0, 4, 6],
        [0, 6, 2],
        [1, 3, 7],
        [1, 7, 5],
    ];
    Mesh { positions, triangles }
}
