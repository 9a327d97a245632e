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
/// farthest from those chosen (of equal ones, the first in the cloud).
///
/// Exactly what [`farthest_point_sampling_plain`] returns, at a fraction of its O(N * count)
/// cost: the points are grouped into buckets of nearby points (a k-d split), each with its
/// bounding box and its largest distance to the chosen set. A new sample can lower no distance in
/// a bucket whose box is at least that far from it, so the bucket is skipped. The bound is exact
/// in floating point (rounded subtraction, squaring and addition are monotone, and the box gap is
/// summed in the same order as the distances), so the choice is the same point for point.
pub fn farthest_point_sampling(points: &[[f32; 3]], count: usize, seed: u64) -> Vec<[f32; 3]> {
    if points.len() <= count {
        return points.to_vec();
    }
    if points.len() < 4 * BUCKET || points.iter().flatten().any(|c| !c.is_finite()) {
        return farthest_point_sampling_plain(points, count, seed);
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut current = rng.random_range(0..points.len());
    let mut buckets = Buckets::new(points);
    let mut chosen = Vec::with_capacity(count);
    for _ in 0..count {
        let c = points[current];
        chosen.push(c);
        current = buckets.add_sample(c);
    }
    chosen
}

/// The textbook loop, O(N * count): the reference [`farthest_point_sampling`] is tested against,
/// and its path for small or non-finite clouds.
pub fn farthest_point_sampling_plain(points: &[[f32; 3]], count: usize, seed: u64) -> Vec<[f32; 3]> {
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

/// Points per bucket of [`farthest_point_sampling`], at most (a leaf of the k-d split).
const BUCKET: usize = 48;

/// The cloud reordered bucket by bucket (structure of arrays), with each point's squared distance
/// to the chosen set and its index in the cloud.
struct Buckets {
    xs: Vec<f32>,
    ys: Vec<f32>,
    zs: Vec<f32>,
    index: Vec<u32>,
    nearest: Vec<f32>,
    /// Per bucket: its range in the arrays, its box (lowest and highest corner, an array per
    /// axis), and its farthest point (distance, index), so that the loops over buckets vectorize.
    ranges: Vec<(usize, usize)>,
    low: [Vec<f32>; 3],
    high: [Vec<f32>; 3],
    farthest: Vec<f32>,
    farthest_index: Vec<u32>,
    /// Per bucket, the squared gap from the latest sample to its box.
    gap: Vec<f32>,
}

impl Buckets {
    fn new(points: &[[f32; 3]]) -> Self {
        let mut order: Vec<u32> = (0..points.len() as u32).collect();
        let mut ranges = Vec::with_capacity(2 * points.len() / BUCKET + 1);
        split(points, &mut order, 0, &mut ranges);
        let boxes: Vec<([f32; 3], [f32; 3])> = ranges
            .iter()
            .map(|&(start, end)| bounds(points, &order[start..end]))
            .collect();
        Self {
            xs: order.iter().map(|&i| points[i as usize][0]).collect(),
            ys: order.iter().map(|&i| points[i as usize][1]).collect(),
            zs: order.iter().map(|&i| points[i as usize][2]).collect(),
            nearest: vec![f32::INFINITY; points.len()],
            low: [0, 1, 2].map(|a| boxes.iter().map(|(low, _)| low[a]).collect()),
            high: [0, 1, 2].map(|a| boxes.iter().map(|(_, high)| high[a]).collect()),
            farthest: vec![f32::INFINITY; ranges.len()],
            farthest_index: vec![0; ranges.len()],
            gap: vec![0.0; ranges.len()],
            index: order,
            ranges,
        }
    }

    /// Takes `c` into the chosen set and returns the cloud index of the next farthest point.
    fn add_sample(&mut self, c: [f32; 3]) -> usize {
        // The squared gap from c to every bucket's box, in one pass that vectorizes.
        let [lx, ly, lz] = &self.low;
        let [hx, hy, hz] = &self.high;
        let boxes = lx.iter().zip(hx).zip(ly.iter().zip(hy)).zip(lz.iter().zip(hz));
        for (gap, (((lx, hx), (ly, hy)), (lz, hz))) in self.gap.iter_mut().zip(boxes) {
            let gx = (lx - c[0]).max(c[0] - hx).max(0.0);
            let gy = (ly - c[1]).max(c[1] - hy).max(0.0);
            let gz = (lz - c[2]).max(c[2] - hz).max(0.0);
            *gap = gx * gx + gy * gy + gz * gz;
        }
        for b in 0..self.ranges.len() {
            if self.gap[b] >= self.farthest[b] {
                continue;
            }
            let (start, end) = self.ranges[b];
            let nearest = &mut self.nearest[start..end];
            for (((n, x), y), z) in nearest
                .iter_mut()
                .zip(&self.xs[start..end])
                .zip(&self.ys[start..end])
                .zip(&self.zs[start..end])
            {
                let d = (x - c[0]) * (x - c[0]) + (y - c[1]) * (y - c[1]) + (z - c[2]) * (z - c[2]);
                *n = n.min(d);
            }
            (self.farthest[b], self.farthest_index[b]) = farthest_in_bucket(nearest, &self.index[start..end]);
        }
        farthest_in_bucket(&self.farthest, &self.farthest_index).1 as usize
    }
}

/// The largest of (distance, cloud index) pairs and, of equal ones, the lowest index (the plain
/// loop's first): of one bucket's points, or of the buckets' farthest. In two passes that
/// vectorize: the largest distance (distances are >= 0, so their bits order as they do), then the
/// lowest cloud index holding it.
fn farthest_in_bucket(nearest: &[f32], index: &[u32]) -> (f32, u32) {
    let largest = f32::from_bits(nearest.iter().map(|n| n.to_bits()).max().unwrap_or(0));
    let at = nearest
        .iter()
        .zip(index)
        .filter(|(n, _)| **n == largest)
        .map(|(_, i)| *i)
        .min()
        .unwrap_or(u32::MAX);
    (largest, at)
}

/// The bounding box of the points `order` names.
fn bounds(points: &[[f32; 3]], order: &[u32]) -> ([f32; 3], [f32; 3]) {
    order
        .iter()
        .fold(([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]), |(low, high), &i| {
            let p = points[i as usize];
            (
                [0, 1, 2].map(|a| low[a].min(p[a])),
                [0, 1, 2].map(|a| high[a].max(p[a])),
            )
        })
}

/// Splits `order[offset..]` at the median of its widest axis until at most [`BUCKET`] points
/// remain, and appends each leaf's range.
fn split(points: &[[f32; 3]], order: &mut [u32], offset: usize, ranges: &mut Vec<(usize, usize)>) {
    if order.len() <= BUCKET {
        ranges.push((offset, offset + order.len()));
        return;
    }
    let (low, high) = bounds(points, order);
    let axis = (0..3)
        .max_by(|&a, &b| (high[a] - low[a]).total_cmp(&(high[b] - low[b])))
        .unwrap_or(0);
    let middle = order.len() / 2;
    order.select_nth_unstable_by(middle, |&i, &j| {
        points[i as usize][axis].total_cmp(&points[j as usize][axis])
    });
    let (left, right) = order.split_at_mut(middle);
    split(points, left, offset, ranges);
    split(points, right, offset + middle, ranges);
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
