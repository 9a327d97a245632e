//! Geometric clean-up of a frame before subsampling: the sensor-to-gravity transform, a
//! region-of-interest crop, the ground plane (RANSAC: to level the cloud and/or remove the ground)
//! and outlier removal (statistical or radius, on a kiddo KD-tree).

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, Rotation3, Unit as UnitVector, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::config::{OutlierMethod, OutlierSettings};

/// x' = R x + t for every point.
pub fn transform(points: &mut [[f32; 3]], rotation: &Matrix3<f32>, translation: &Vector3<f32>) {
    for p in points.iter_mut() {
        let v = rotation * Vector3::from(*p) + translation;
        *p = [v.x, v.y, v.z];
    }
}

/// Keeps the points inside [min_x, min_y, min_z, max_x, max_y, max_z].
pub fn crop(points: &mut Vec<[f32; 3]>, bounds: &[f32; 6]) {
    points.retain(|p| (0..3).all(|a| p[a] >= bounds[a] && p[a] <= bounds[a + 3]));
}

/// A plane n . x = d with |n| = 1 and n pointing up (n.z >= 0).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plane {
    pub normal: Vector3<f32>,
    pub offset: f32,
    pub inliers: usize,
}

/// RANSAC fit of the dominant near-horizontal plane (normal within 45 degrees of +z): the ground
/// in a roughly gravity-aligned frame. None when no plane holds at least 10 % of the points.
pub fn fit_ground(points: &[[f32; 3]], tolerance: f32, iterations: usize, seed: u64) -> Option<Plane> {
    if points.len() < 3 {
        return None;
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // Count inliers on at most 2000 points per hypothesis; refit on all of them at the end.
    let stride = (points.len() / 2000).max(1);
    let mut best: Option<Plane> = None;
    for _ in 0..iterations {
        let [a, b, c] = [0; 3].map(|_| Vector3::from(points[rng.random_range(0..points.len())]));
        let Some(normal) = UnitVector::try_new((b - a).cross(&(c - a)), 1e-9) else {
            continue;
        };
        let normal = if normal.z < 0.0 {
            -normal.into_inner()
        } else {
            normal.into_inner()
        };
        if normal.z < std::f32::consts::FRAC_1_SQRT_2 {
            continue;
        }
        let offset = normal.dot(&a);
        let inliers = points
            .iter()
            .step_by(stride)
            .filter(|p| (normal.dot(&Vector3::from(**p)) - offset).abs() <= tolerance)
            .count();
        if best.is_none_or(|b| inliers > b.inliers) {
            best = Some(Plane {
                normal,
                offset,
                inliers,
            });
        }
    }
    let best = best?;
    let inliers: Vec<Vector3<f32>> = points
        .iter()
        .map(|p| Vector3::from(*p))
        .filter(|p| (best.normal.dot(p) - best.offset).abs() <= tolerance)
        .collect();
    if inliers.len() * 10 < points.len() || inliers.len() < 3 {
        return None;
    }
    // Least-squares refit: the normal is the smallest principal axis of the inliers.
    let mean = inliers.iter().sum::<Vector3<f32>>() / inliers.len() as f32;
    let covariance = inliers.iter().fold(Matrix3::zeros(), |acc, p| {
        let d = p - mean;
        acc + d * d.transpose()
    });
    let eigen = covariance.symmetric_eigen();
    let smallest = eigen.eigenvalues.imin();
    let mut normal: Vector3<f32> = eigen.eigenvectors.column(smallest).into_owned().normalize();
    if normal.z < 0.0 {
        normal = -normal;
    }
    Some(Plane {
        normal,
        offset: normal.dot(&mean),
        inliers: inliers.len(),
    })
}

/// The rotation that turns the plane's normal onto +z (the smallest such rotation: heading kept),
/// and moves the plane to z = 0.
pub fn levelling(plane: &Plane) -> (Matrix3<f32>, Vector3<f32>) {
    let rotation = Rotation3::rotation_between(&plane.normal, &Vector3::z())
        .unwrap_or_else(Rotation3::identity)
        .into_inner();
    (rotation, Vector3::new(0.0, 0.0, -plane.offset))
}

/// Removes the points within `tolerance` of the plane or below it.
pub fn remove_plane(points: &mut Vec<[f32; 3]>, plane: &Plane, tolerance: f32) {
    points.retain(|p| plane.normal.dot(&Vector3::from(*p)) - plane.offset > tolerance);
}

/// Statistical or radius outlier removal. Returns how many points were removed.
pub fn remove_outliers(points: &mut Vec<[f32; 3]>, settings: &OutlierSettings) -> usize {
    if settings.method == OutlierMethod::None || points.len() < 2 {
        return 0;
    }
    let Ok(tree) = ImmutableKdTree::<f32, 3>::new_from_slice(points) else {
        return 0;
    };
    let keep: Vec<bool> = match settings.method {
        OutlierMethod::None => unreachable!(),
        OutlierMethod::Statistical => {
            // Mean distance to the k nearest neighbours (the point itself excluded); points whose
            // mean is beyond mean + std_ratio * std of all points are outliers.
            let k = NonZeroUsize::new(settings.neighbours.min(points.len() - 1) + 1).expect("k >= 1");
            let means: Vec<f32> = points
                .iter()
                .map(|p| {
                    let found = tree.query(p).nearest_n::<SquaredEuclidean<f32>>(k).execute();
                    let others = found.len().saturating_sub(1).max(1) as f32;
                    found.iter().map(|r| r.distance.sqrt()).sum::<f32>() / others
                })
                .collect();
            let n = means.len() as f32;
            let mean = means.iter().sum::<f32>() / n;
            let std = (means.iter().map(|m| (m - mean).powi(2)).sum::<f32>() / n).sqrt();
            let limit = mean + settings.std_ratio * std;
            means.iter().map(|m| *m <= limit).collect()
        }
        OutlierMethod::Radius => {
            let wanted = NonZeroUsize::new(settings.min_neighbours + 1).expect("min_neighbours + 1 >= 1");
            let radius_squared = settings.radius_m * settings.radius_m;
            points
                .iter()
                .map(|p| {
                    tree.query(p)
                        .nearest_n::<SquaredEuclidean<f32>>(wanted)
                        .execute()
                        .iter()
                        .filter(|r| r.distance <= radius_squared)
                        .count()
                        >= wanted.get()
                })
                .collect()
        }
    };
    let before = points.len();
    let mut flags = keep.into_iter();
    points.retain(|_| flags.next().unwrap_or(true));
    before - points.len()
}

/// Keeps the largest Euclidean cluster: points joined by chains of neighbours closer than
/// `radius` (PCL's EuclideanClusterExtraction, one cluster). What a crop leaves of the floor's
/// depth noise and of stray clutter is sparse and falls apart from the object. Returns how many
/// points were removed.
pub fn keep_largest_cluster(points: &mut Vec<[f32; 3]>, radius: f32) -> usize {
    if points.len() < 2 {
        return 0;
    }
    let Ok(tree) = ImmutableKdTree::<f32, 3>::new_from_slice(points) else {
        return 0;
    };
    let radius_squared = radius * radius;
    let mut label = vec![usize::MAX; points.len()];
    let (mut best, mut best_size) = (0usize, 0usize);
    let mut stack = Vec::new();
    for seed in 0..points.len() {
        if label[seed] != usize::MAX {
            continue;
        }
        label[seed] = seed;
        stack.push(seed);
        let mut size = 0;
        while let Some(i) = stack.pop() {
            size += 1;
            let found = tree
                .query(&points[i])
                .within::<SquaredEuclidean<f32>>(radius_squared)
                .unsorted()
                .execute();
            for neighbour in found {
                let j = neighbour.item as usize;
                if label[j] == usize::MAX {
                    label[j] = seed;
                    stack.push(j);
                }
            }
        }
        if size > best_size {
            (best, best_size) = (seed, size);
        }
    }
    let before = points.len();
    let mut labels = label.into_iter();
    points.retain(|_| labels.next() == Some(best));
    before - points.len()
}
