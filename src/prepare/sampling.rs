//! Subsampling to the model's N_p and scaling into model units.
//!
//! Subsampling is deterministic for a seed: farthest point sampling (the default: even coverage,
//! which the encoder was trained on), uniform random, or voxel-grid thinning followed by random
//! choice. A cloud with fewer points than N_p but at least the configured minimum is padded by
//! repeating points, which leaves PointNet's max-pooled features unchanged.

use rand::seq::index::sample;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Sampling {
    Farthest,
    Random,
    Voxel,
}

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PrepareError {
    #[error("{got} points after filtering; at least {minimum} are needed")]
    TooFewPoints { got: usize, minimum: usize },
    #[error("no ground plane found (prepare.auto_ground is on)")]
    NoGround,
}

/// Farthest point sampling: start at a seeded random point, then repeatedly take the point
/// farthest from those chosen. O(N * count).
pub fn farthest_point_sampling(points: &[[f32; 3]], count: usize, seed: u64) -> Vec<[f32; 3]> {
    if points.len() <= count {
        return points.to_vec();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    // Coordinates in separate arrays, and the distance update apart from the arg-max, so that
    // both loops vectorize.
    let xs: Vec<f32> = points.iter().map(|p| p[0]).collect();
    let ys: Vec<f32> = points.iter().map(|p| p[1]).collect();
    let zs: Vec<f32> = points.iter().map(|p| p[2]).collect();
    let mut nearest = vec![f32::INFINITY; points.len()];
    let mut chosen = Vec::with_capacity(count);
    let mut current = rng.random_range(0..points.len());
    for _ in 0..count {
        let c = points[current];
        chosen.push(c);
        for (((n, x), y), z) in nearest.iter_mut().zip(&xs).zip(&ys).zip(&zs) {
            let d = (x - c[0]) * (x - c[0]) + (y - c[1]) * (y - c[1]) + (z - c[2]) * (z - c[2]);
            *n = n.min(d);
        }
        let largest = nearest.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        current = nearest.iter().position(|n| *n == largest).unwrap_or(0);
    }
    chosen
}

pub fn random_sampling(points: &[[f32; 3]], count: usize, seed: u64) -> Vec<[f32; 3]> {
    if points.len() <= count {
        return points.to_vec();
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut indices = sample(&mut rng, points.len(), count).into_vec();
    indices.sort_unstable();
    indices.into_iter().map(|i| points[i]).collect()
}

/// One point (the first) per occupied voxel of side `voxel`, then random sampling to `count`.
pub fn voxel_sampling(points: &[[f32; 3]], count: usize, voxel: f32, seed: u64) -> Vec<[f32; 3]> {
    let mut seen = std::collections::HashSet::new();
    let thinned: Vec<[f32; 3]> = points
        .iter()
        .copied()
        .filter(|p| {
            let key = (
                (p[0] / voxel).floor() as i64,
                (p[1] / voxel).floor() as i64,
                (p[2] / voxel).floor() as i64,
            );
            seen.insert(key)
        })
        .collect();
    random_sampling(&thinned, count, seed)
}

/// Exactly `count` points: subsampled, or padded by cycling through the cloud.
pub fn subsample(
    points: &[[f32; 3]],
    count: usize,
    minimum: usize,
    method: Sampling,
    voxel: f32,
    seed: u64,
) -> Result<Vec<[f32; 3]>, PrepareError> {
    if points.len() < minimum.max(1) {
        return Err(PrepareError::TooFewPoints {
            got: points.len(),
            minimum: minimum.max(1),
        });
    }
    let mut chosen = match method {
        Sampling::Farthest => farthest_point_sampling(points, count, seed),
        Sampling::Random => random_sampling(points, count, seed),
        Sampling::Voxel => voxel_sampling(points, count, voxel, seed),
    };
    let distinct = chosen.len();
    let mut index = 0;
    while chosen.len() < count {
        chosen.push(chosen[index % distinct]);
        index += 1;
    }
    Ok(chosen)
}

/// Centres on the bounding-box centre (as the kit does) and scales into model units.
pub fn centre_and_scale(points: &mut [[f32; 3]], model_units_per_metre: f32) -> [f32; 3] {
    let mut low = [f32::INFINITY; 3];
    let mut high = [f32::NEG_INFINITY; 3];
    for p in points.iter() {
        for axis in 0..3 {
            low[axis] = low[axis].min(p[axis]);
            high[axis] = high[axis].max(p[axis]);
        }
    }
    let centre = [0, 1, 2].map(|a| 0.5 * (low[a] + high[a]));
    for p in points.iter_mut() {
        for axis in 0..3 {
            p[axis] = (p[axis] - centre[axis]) * model_units_per_metre;
        }
    }
    centre
}
