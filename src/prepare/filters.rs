//! Geometric clean-up of a frame before subsampling: the sensor-to-gravity transform, a
//! region-of-interest crop, the ground plane (RANSAC: to level the cloud and/or remove the ground),
//! the voxel grid, outlier removal (statistical or radius, on a kiddo KD-tree) and the largest
//! Euclidean cluster (on a grid of cells, union-find). The voxel grid and the clusters look cells
//! up in an occupancy bitmap (`occupancy.rs`) where the cloud's box is small enough, as a frame's
//! after the crop is; a hash map and sorted cell keys beyond.

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, Rotation3, Unit as UnitVector, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::occupancy::Occupancy;
use super::settings::{OutlierMethod, OutlierSettings};

/// x' = R x + t for every point.
pub fn transform(points: &mut [[f32; 3]], rotation: &Matrix3<f32>, translation: &Vector3<f32>) {
    for p in points.iter_mut() {
        let v = rotation * Vector3::from(*p) + translation;
        *p = [v.x, v.y, v.z];
    }
}

/// Keeps the points inside [min_x, min_y, min_z, max_x, max_y, max_z].
pub fn crop(points: &mut Vec<[f32; 3]>, bounds: &[f32; 6]) {
    points.retain(|p| inside(p, bounds));
}

fn inside(p: &[f32; 3], bounds: &[f32; 6]) -> bool {
    (0..3).all(|a| p[a] >= bounds[a] && p[a] <= bounds[a + 3])
}

/// How far below the ground (z = 0 of the gravity frame) [`floor_noise_cut`] looks for the
/// floor's noise: deeper points are not the floor's (a wrong sensor pose, a pit) and are dropped.
pub const FLOOR_BAND_M: f32 = 0.25;

/// Fewer floor points below the ground than this and the crop's own floor is kept.
const MIN_FLOOR_POINTS: usize = 32;

/// The floor's depth noise, measured on the points below the ground (z < 0, down to
/// `FLOOR_BAND_M`): they can only be the floor seen through the sensor's noise, and as a stereo
/// camera's noise is about symmetric, their root-mean-square height is its spread.
#[derive(Debug, Clone, Copy, Default)]
pub struct FloorNoise {
    squares: f64,
    count: usize,
}

impl FloorNoise {
    /// Counts a point's height when it lies in the band below the ground.
    #[inline]
    pub fn add(&mut self, z: f32) {
        if z < 0.0 && z >= -FLOOR_BAND_M {
            self.squares += (z as f64) * (z as f64);
            self.count += 1;
        }
    }

    /// max(`min_z`, `sigmas` x the noise's spread); `min_z` with fewer than `MIN_FLOOR_POINTS`
    /// measured.
    pub fn cut(&self, min_z: f32, sigmas: f32) -> f32 {
        if self.count < MIN_FLOOR_POINTS {
            return min_z;
        }
        min_z.max(sigmas * (self.squares / self.count as f64).sqrt() as f32)
    }
}

/// Drops the floor's depth noise from `points` (which reach below the ground, as a crop lowered to
/// `FLOOR_BAND_M` leaves them): keeps the points at or above [`FloorNoise::cut`] and returns that
/// height.
pub fn floor_noise_cut(points: &mut Vec<[f32; 3]>, min_z: f32, sigmas: f32) -> f32 {
    let mut noise = FloorNoise::default();
    points.iter().for_each(|p| noise.add(p[2]));
    let cut = noise.cut(min_z, sigmas);
    points.retain(|p| p[2] >= cut);
    cut
}

/// x' = R (scale x) + t for every point of the sensor's cloud, keeping only those inside `crop`
/// (when given): [`transform`] then [`crop`] in one pass, without a copy of the whole frame.
pub fn transform_and_crop(
    points: &[[f32; 3]],
    scale: f32,
    rotation: &Matrix3<f32>,
    translation: &Vector3<f32>,
    bounds: Option<&[f32; 6]>,
) -> Vec<[f32; 3]> {
    match bounds {
        Some(bounds) => transform_crop_pass::<false>(points, scale, rotation, translation, bounds, None),
        None => {
            let rotation = rotation * scale;
            points
                .iter()
                .map(|p| {
                    let v = rotation * Vector3::from(*p) + translation;
                    [v.x, v.y, v.z]
                })
                .collect()
        }
    }
}

/// [`transform_and_crop`] that also measures the floor's noise on the points within the crop's
/// x and y below its box, down to `FLOOR_BAND_M` under the ground, without keeping them.
pub fn transform_crop_and_measure_floor(
    points: &[[f32; 3]],
    scale: f32,
    rotation: &Matrix3<f32>,
    translation: &Vector3<f32>,
    bounds: &[f32; 6],
    noise: &mut FloorNoise,
) -> Vec<[f32; 3]> {
    transform_crop_pass::<true>(points, scale, rotation, translation, bounds, Some(noise))
}

/// The one pass behind both: every point moved; written to the output and kept when inside
/// `bounds` (the cursor advances only then); with `MEASURE_FLOOR`, added to `noise` when within
/// the box's x and y, below its floor, in the floor band. No branch depends on a point: a noisy
/// floor lies on both sides of the crop's floor at random, and branches on it mispredicted every
/// other floor point (the pass with the floor cut cost 0.155 ms a frame on the sample, 0.078 now:
/// docs/benchmarks.md "The floor cut's cost").
fn transform_crop_pass<const MEASURE_FLOOR: bool>(
    points: &[[f32; 3]],
    scale: f32,
    rotation: &Matrix3<f32>,
    translation: &Vector3<f32>,
    b: &[f32; 6],
    noise: Option<&mut FloorNoise>,
) -> Vec<[f32; 3]> {
    let rotation = rotation * scale;
    let mut kept = vec![[0.0f32; 3]; points.len()];
    let mut count = 0;
    let (mut squares, mut floor) = (0.0f64, 0usize);
    for p in points {
        let v = rotation * Vector3::from(*p) + translation;
        let (x, y, z) = (v.x, v.y, v.z);
        let within_xy = (x >= b[0]) & (x <= b[3]) & (y >= b[1]) & (y <= b[4]);
        kept[count] = [x, y, z];
        count += (within_xy & (z >= b[2]) & (z <= b[5])) as usize;
        if MEASURE_FLOOR {
            let below = within_xy & (z < b[2]) & (z < 0.0) & (z >= -FLOOR_BAND_M);
            // The height of a point below the ground, else 0, by arithmetic: clamped into the
            // band (min and max are single instructions) and multiplied by 1 or 0. Any form of
            // `if below { z } else { 0 }` (a select, a bit mask) was compiled into a branch, as
            // it feeds the running sum, and mispredicted as above.
            let height = (below as u32 as f32) * z.min(0.0).max(-FLOOR_BAND_M);
            squares += (height as f64) * (height as f64);
            floor += below as usize;
        }
    }
    kept.truncate(count);
    if let Some(noise) = noise {
        noise.squares += squares;
        noise.count += floor;
    }
    kept
}

/// `x.floor() as i64` for the finite |x| < 2^40 the grids allow, without a call into libm (which
/// `floor` is on x86-64 without SSE4.1).
fn floor(x: f32) -> i64 {
    let t = x as i64;
    t - ((t as f32) > x) as i64
}

/// A voxel grid (PCL's VoxelGrid): the points of each occupied cube of edge `edge` (metres) are
/// replaced by their centroid, in the order the cubes are first met in the cloud. Surfaces sampled
/// more densely than the edge keep their shape at a fraction of the points, so the steps after it,
/// whose cost grows with the points, run on what the model's N_p points can resolve. Returns how
/// many points were removed. Clouds whose cube coordinates would not fit in i64 are left as they
/// are (the node drops points beyond 1e5 m before prepare).
pub fn voxel_grid(points: &mut Vec<[f32; 3]>, edge: f32) -> usize {
    if points.len() < 2 || !(edge > 0.0) {
        return 0;
    }
    const LIMIT: f32 = (1u64 << 40) as f32;
    if points.iter().flatten().any(|c| !((c / edge).abs() < LIMIT)) {
        return 0;
    }
    let cells: Vec<[i64; 3]> = points.iter().map(|p| p.map(|c| floor(c / edge))).collect();
    // Per cube: the sum of its points (relative to the first, to keep the rounding small) and how
    // many there are, in the order the cubes are first met.
    let mut sums: Vec<([f32; 3], [f32; 3], u32)> = Vec::with_capacity(points.len());
    let mut add = |at: usize, p: &[f32; 3]| {
        if at == sums.len() {
            sums.push((*p, [0.0; 3], 1));
        } else {
            let (first, sum, n) = &mut sums[at];
            for a in 0..3 {
                sum[a] += p[a] - first[a];
            }
            *n += 1;
        }
    };
    match Occupancy::of(&cells) {
        // Each occupied cube's place among the cubes in grid order (its rank), then its slot.
        Some(grid) => {
            let mut slot = vec![u32::MAX; grid.occupied()];
            let mut next = 0;
            // Neighbouring points of a scan often share a cube: its rank is looked up once.
            let mut last = (usize::MAX, 0);
            for (p, k) in points.iter().zip(&cells) {
                let at = grid.position(*k);
                if at != last.0 {
                    last = (at, grid.rank(at) as usize);
                }
                let rank = last.1;
                if slot[rank] == u32::MAX {
                    slot[rank] = next;
                    next += 1;
                }
                add(slot[rank] as usize, p);
            }
        }
        // A cloud spread over too large a box for a bitmap: the cubes in a hash map.
        None => {
            let mut slot: CellMap = CellMap::default();
            slot.reserve(points.len());
            for (p, k) in points.iter().zip(&cells) {
                let next = slot.len();
                add(*slot.entry(*k).or_insert(next), p);
            }
        }
    }
    let before = points.len();
    points.clear();
    points.extend(
        sums.iter()
            .map(|(first, sum, n)| [0, 1, 2].map(|a| first[a] + sum[a] / *n as f32)),
    );
    before - points.len()
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

/// Grid cells by their integer coordinates, hashed cheaply (a multiply-xor; the keys are not
/// chosen by an adversary that could exploit collisions beyond slowing one frame).
type CellMap = std::collections::HashMap<[i64; 3], usize, std::hash::BuildHasherDefault<CellHasher>>;

#[derive(Default)]
struct CellHasher(u64);

impl std::hash::Hasher for CellHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        // Eight bytes a round: `[i64; 3]` arrives as one 24-byte write (after its length).
        for chunk in bytes.chunks(8) {
            let mut word = [0u8; 8];
            word[..chunk.len()].copy_from_slice(chunk);
            self.write_u64(u64::from_le_bytes(word));
        }
    }
    fn write_usize(&mut self, value: usize) {
        self.write_u64(value as u64);
    }
    fn write_i64(&mut self, value: i64) {
        self.write_u64(value as u64);
    }
    fn write_u64(&mut self, value: u64) {
        self.0 = (self.0.rotate_left(5) ^ value).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}

/// A cluster near the largest joins it only when it has at least this share of its points: a
/// body's legs or torso, not what the crop leaves of the floor's noise. Chosen with
/// `cluster_join_m` (docs/tracking.md "A body in pieces"; 0.1 did the same on the choice sets).
pub const JOIN_MIN_FRACTION: f32 = 0.15;

/// Keeps the largest Euclidean cluster: points joined by chains of neighbours closer than
/// `radius` (PCL's EuclideanClusterExtraction, one cluster; `stretch`: see [`RangeStretch`]).
/// What a crop leaves of the floor's depth noise and of stray clutter is sparse and falls apart
/// from the object. With `join_m` > 0, the clusters of at least [`JOIN_MIN_FRACTION`] of its
/// points that lie above or below it (their boxes overlap in x and y, the middle of their height
/// is outside its own, and the vertical gap is at most `join_m`) are kept with it: a body seen from
/// close by or from above shows gaps wider than `radius` where a limb hides what joins its legs to
/// its torso, and the largest piece alone is a different shape (a false identity change). A piece
/// at the torso's height (an arm held apart) stays out: joined, it cost walking bipeds heading.
/// With `limb_min_points` > 0 as well, the clusters of at least that many points that lie within
/// the largest's footprint grown by `join_m` on each side and wholly in the lower half of its
/// height are kept too: the legs and feet a stereo camera cuts off where it drops the pixels at a
/// depth edge or in the other eye's shadow. Without them the pose code cannot see a quadruped's
/// legs (docs/tracking.md "Legs cut off by the sensor"); a smaller piece there is the floor's noise.
/// Returns how many points were removed.
pub fn keep_largest_cluster(
    points: &mut Vec<[f32; 3]>,
    radius: f32,
    stretch: Option<RangeStretch>,
    join_m: f32,
    limb_min_points: usize,
) -> usize {
    if points.len() < 2 {
        return 0;
    }
    let Some((labels, count)) = cluster_labels(points, radius, stretch) else {
        return 0;
    };
    // The largest cluster; of equal ones, the one holding the lowest point index.
    let mut size = vec![0usize; count];
    let mut first = vec![usize::MAX; count];
    for (i, &l) in labels.iter().enumerate() {
        size[l as usize] += 1;
        first[l as usize] = first[l as usize].min(i);
    }
    let best = (0..count)
        .max_by(|&a, &b| size[a].cmp(&size[b]).then(first[b].cmp(&first[a])))
        .expect("at least one cluster");
    let mut kept = vec![false; count];
    kept[best] = true;
    if join_m > 0.0 && count > 1 {
        let mut boxes = vec![([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]); count];
        for (p, &l) in points.iter().zip(&labels) {
            let (low, high) = &mut boxes[l as usize];
            for a in 0..3 {
                low[a] = low[a].min(p[a]);
                high[a] = high[a].max(p[a]);
            }
        }
        let (best_low, best_high) = boxes[best];
        let least = (JOIN_MIN_FRACTION * size[best] as f32).ceil() as usize;
        for (l, (low, high)) in boxes.iter().enumerate() {
            let gap = |a: usize| (low[a] - best_high[a]).max(best_low[a] - high[a]);
            // Above or below: the middle of its height outside the largest's.
            let middle = 0.5 * (low[2] + high[2]);
            let above_or_below = middle < best_low[2] || middle > best_high[2];
            kept[l] |= size[l] >= least && gap(0) <= 0.0 && gap(1) <= 0.0 && gap(2) <= join_m && above_or_below;
            // A limb: within the grown footprint, wholly in the lower half, not a speck of floor.
            let within = (0..2).all(|a| low[a] >= best_low[a] - join_m && high[a] <= best_high[a] + join_m);
            let lower_half = high[2] <= 0.5 * (best_low[2] + best_high[2]);
            kept[l] |= limb_min_points > 0 && size[l] >= limb_min_points && within && lower_half;
        }
    }
    let before = points.len();
    let mut flags = labels.iter().map(|&l| kept[l as usize]);
    points.retain(|_| flags.next().unwrap_or(false));
    before - points.len()
}

/// Every Euclidean cluster (as [`keep_largest_cluster`] finds them) of at least `min_points`
/// points whose bounding box is at most `max_extent_m` on every side, largest first (of equal
/// ones, the one holding the lowest point index first), at most `max_clusters` of them: the
/// candidate objects of a frame.
pub fn euclidean_clusters(
    points: &[[f32; 3]],
    radius: f32,
    stretch: Option<RangeStretch>,
    min_points: usize,
    max_extent_m: f32,
    max_clusters: usize,
) -> Vec<Vec<[f32; 3]>> {
    if points.is_empty() {
        return Vec::new();
    }
    let Some((labels, count)) = cluster_labels(points, radius, stretch) else {
        return Vec::new();
    };
    let mut clusters: Vec<Vec<[f32; 3]>> = vec![Vec::new(); count];
    for (p, &l) in points.iter().zip(&labels) {
        clusters[l as usize].push(*p);
    }
    // Components are numbered in the order of their lowest point, so a stable sort by size keeps
    // that order among equals.
    clusters.sort_by_key(|c| std::cmp::Reverse(c.len()));
    clusters
        .into_iter()
        .filter(|c| c.len() >= min_points.max(1))
        .filter(|c| {
            (0..3).all(|a| {
                let (low, high) = c.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), p| {
                    (l.min(p[a]), h.max(p[a]))
                });
                high - low <= max_extent_m
            })
        })
        .take(max_clusters)
        .collect()
}

/// A cluster radius that grows with range, as a stereo camera's depth noise does: clusters are
/// found on the points with each one's range `r` from the sensor, beyond `from_m` (`r0`), taken
/// down to `2 r0 - r0^2 / r` along its ray. That is affine in the disparity (1 / r), whose noise
/// is the same at every range, and continuous with the range at `r0`; a chain of neighbours may
/// then stretch `(r / r0)^2` times the radius along the ray (the noise grows as r^2: 2.7 times at
/// 4.1 m beyond 2.5 m) and about `r / r0` across it (as the pixels' footprint does). Far objects
/// whose depth noise breaks them into pieces at one radius stay whole; near ones are clustered as
/// before.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RangeStretch {
    /// The sensor's origin in the cloud's frame (m).
    pub origin: [f32; 3],
    /// Range (m) up to which the radius is the same everywhere.
    pub from_m: f32,
}

impl RangeStretch {
    /// Where `p` lies in the space clusters are found in.
    fn warp(&self, p: [f32; 3]) -> [f32; 3] {
        let v = [0, 1, 2].map(|a| p[a] - self.origin[a]);
        let range = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        if !(range > self.from_m) {
            return p;
        }
        let scale = (2.0 * self.from_m - self.from_m * self.from_m / range) / range;
        [0, 1, 2].map(|a| self.origin[a] + scale * v[a])
    }
}

/// Each point's cluster at `radius` (see [`components`]) and the number of clusters; none when
/// the radius is not positive or the cloud reaches too far for the grid.
fn cluster_labels(points: &[[f32; 3]], radius: f32, stretch: Option<RangeStretch>) -> Option<(Vec<u32>, usize)> {
    if !(radius > 0.0) {
        return None;
    }
    let warped: Vec<[f32; 3]>;
    let points = match stretch {
        Some(stretch) if stretch.from_m > 0.0 => {
            warped = points.iter().map(|&p| stretch.warp(p)).collect();
            &warped[..]
        }
        _ => points,
    };
    // A grid of cells whose diagonal is `radius`: the points of one cell are all within `radius`
    // of each other, so each cell lies in one cluster, and clusters are found by joining cells
    // (union-find) that hold a pair of points within `radius` of each other. The same clusters as
    // a neighbour search from every point, at a fraction of its cost on dense surfaces.
    let cell = radius / 3f32.sqrt();
    // Cell coordinates must stay far inside i64 (so that neighbours and box sizes cannot overflow):
    // a cloud reaching beyond 2^40 cells (10^10 m at a 1 cm radius) is left as it is. The node
    // drops points beyond 1e5 m before prepare; this guards the function itself (found by
    // `cargo fuzz run prepare`).
    const LIMIT: f32 = (1u64 << 40) as f32;
    if points.iter().flatten().any(|c| !((c / cell).abs() < LIMIT)) {
        return None;
    }
    let cells: Vec<[i64; 3]> = points.iter().map(|p| p.map(|c| floor(c / cell))).collect();
    Some(components(points, &cells, radius * radius))
}

/// A cell's coordinates (each from the cloud's lowest cell, plus 2) packed into one number, x
/// first, `FIELD` bits an axis: sorted keys are in grid order, and a neighbour's key is the
/// cell's key plus the offset's. `u64` (21 bits an axis: the clouds prepare sees, up to two
/// million cells a side) sorts and compares faster than `u128` (42 bits: any cloud the grid
/// takes).
trait CellKey: Copy + Ord {
    const FIELD: u32;
    fn pack(relative: [i64; 3]) -> Self;
    /// The key `d` cells away (every axis stays inside its field).
    fn shifted(self, d: [i64; 3]) -> Self;
    fn z(self) -> i64;
}

impl CellKey for u64 {
    const FIELD: u32 = 21;
    fn pack(k: [i64; 3]) -> Self {
        (k[0] as u64) << (2 * Self::FIELD) | (k[1] as u64) << Self::FIELD | k[2] as u64
    }
    fn shifted(self, d: [i64; 3]) -> Self {
        (self as i64 + (d[0] << (2 * Self::FIELD)) + (d[1] << Self::FIELD) + d[2]) as u64
    }
    fn z(self) -> i64 {
        (self & ((1 << Self::FIELD) - 1)) as i64
    }
}

impl CellKey for u128 {
    const FIELD: u32 = 42;
    fn pack(k: [i64; 3]) -> Self {
        (k[0] as u128) << (2 * Self::FIELD) | (k[1] as u128) << Self::FIELD | k[2] as u128
    }
    fn shifted(self, d: [i64; 3]) -> Self {
        let offset = ((d[0] as i128) << (2 * Self::FIELD)) + ((d[1] as i128) << Self::FIELD) + d[2] as i128;
        (self as i128 + offset) as u128
    }
    fn z(self) -> i64 {
        (self & ((1 << Self::FIELD) - 1)) as i64
    }
}

/// Each point's cluster (numbered 0.. in the order of each cluster's lowest point index) and the
/// number of clusters, given each point's cell.
fn components(points: &[[f32; 3]], cells: &[[i64; 3]], radius_squared: f32) -> (Vec<u32>, usize) {
    if let Some(grid) = Occupancy::of(cells) {
        return components_on_grid(points, cells, &grid, radius_squared);
    }
    // Every cell's coordinates from the lowest corner (plus 2, so that a neighbour two cells lower
    // is >= 0), with room for a neighbour two cells higher.
    let low = cells
        .iter()
        .fold([i64::MAX; 3], |m, k| [0, 1, 2].map(|a| m[a].min(k[a] - 2)));
    let span = cells
        .iter()
        .fold(0, |m, k| [0, 1, 2].iter().fold(m, |m, &a| m.max(k[a] - low[a] + 2)));
    if span < 1 << <u64 as CellKey>::FIELD {
        components_keyed::<u64>(points, cells, low, radius_squared)
    } else {
        components_keyed::<u128>(points, cells, low, radius_squared)
    }
}

/// The cells of a cloud in grid order, each with its points, joined into clusters (union-find)
/// where two hold a pair of points within the radius.
struct Joined<'a> {
    points: &'a [[f32; 3]],
    /// Cell a holds the points `members[start[a]..start[a + 1]]`, in cloud order.
    members: Vec<u32>,
    start: Vec<u32>,
    parent: Vec<u32>,
    radius_squared: f32,
}

impl Joined<'_> {
    fn root(&mut self, mut a: u32) -> u32 {
        while self.parent[a as usize] != a {
            self.parent[a as usize] = self.parent[self.parent[a as usize] as usize];
            a = self.parent[a as usize];
        }
        a
    }

    fn members(&self, a: u32) -> &[u32] {
        &self.members[self.start[a as usize] as usize..self.start[a as usize + 1] as usize]
    }

    /// Whether cells a and c hold a pair of points within the radius.
    fn near(&self, a: u32, c: u32) -> bool {
        self.members(a).iter().any(|&i| {
            let p = self.points[i as usize];
            self.members(c).iter().any(|&j| {
                let q = self.points[j as usize];
                (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2) <= self.radius_squared
            })
        })
    }

    /// Joins cell c to a, whose root is `ra` (u32::MAX: not looked up yet), when they are apart and
    /// near; returns a's root.
    fn join(&mut self, a: u32, ra: u32, c: u32) -> u32 {
        let ra = if ra == u32::MAX { self.root(a) } else { ra };
        let rc = self.root(c);
        if ra != rc && self.near(a, c) {
            self.parent[ra.max(rc) as usize] = ra.min(rc);
            return ra.min(rc);
        }
        ra
    }

    /// Each point's cluster, numbered by first appearance in cloud order, and the count.
    fn labels(mut self) -> (Vec<u32>, usize) {
        let cells = self.parent.len() as u32;
        let mut cell_of = vec![0u32; self.points.len()];
        for a in 0..cells {
            let r = self.root(a);
            for &i in self.members(a) {
                cell_of[i as usize] = r;
            }
        }
        let mut number = vec![u32::MAX; cells as usize];
        let mut count = 0u32;
        let labels = cell_of
            .iter()
            .map(|&r| {
                if number[r as usize] == u32::MAX {
                    number[r as usize] = count;
                    count += 1;
                }
                number[r as usize]
            })
            .collect();
        (labels, count as usize)
    }
}

/// [`components`] with the cells looked up in an occupancy bitmap. Cells up to two apart along
/// each axis can hold points within the radius (the 5 x 5 x 5 around a cell). First those one
/// apart, which join most cells: for each cell the 13 of its 3 x 3 x 3 after it in grid order, as
/// rows (dx, dy) of cells dz apart (a few bits of the bitmap each). Then those two apart, only
/// where they can still join two clusters: one of the pair outside the largest cluster found so
/// far (two cells in it are joined already), so from the cells outside it, in both directions
/// (on a frame, the few hundred stray points around the object).
fn components_on_grid(
    points: &[[f32; 3]],
    cells: &[[i64; 3]],
    grid: &Occupancy,
    radius_squared: f32,
) -> (Vec<u32>, usize) {
    // Each point's cell (its rank in grid order), then the points by cell (a counting sort, which
    // keeps cloud order within a cell), and each cell's place in the bitmap.
    let at: Vec<usize> = cells.iter().map(|k| grid.position(*k)).collect();
    let cell_of: Vec<u32> = at.iter().map(|&p| grid.rank(p)).collect();
    let count = grid.occupied();
    let mut start = vec![0u32; count + 1];
    cell_of.iter().for_each(|&c| start[c as usize + 1] += 1);
    for c in 0..count {
        start[c + 1] += start[c];
    }
    let mut fill = start.clone();
    let mut members = vec![0u32; points.len()];
    let mut place = vec![0usize; count];
    for (i, &c) in cell_of.iter().enumerate() {
        members[fill[c as usize] as usize] = i as u32;
        fill[c as usize] += 1;
        place[c as usize] = at[i];
    }
    let mut joined = Joined {
        points,
        members,
        start,
        parent: (0..count as u32).collect(),
        radius_squared,
    };
    let [sx, sy, _] = grid.strides();
    // Joins cell a with the occupied cells among `mask` of the cells from `from` on along z.
    let join_window = |joined: &mut Joined, a: usize, from: usize, mask: u64| {
        let occupied = grid.window(from, 5);
        if occupied & mask == 0 {
            return;
        }
        // The occupied cells of the window are consecutive in grid order: the k-th has the rank
        // of the window's start plus k.
        let (first, mut ra) = (grid.rank(from), u32::MAX);
        let (mut bits, mut k) = (occupied, 0);
        while bits != 0 {
            if (mask >> bits.trailing_zeros()) & 1 == 1 {
                ra = joined.join(a as u32, ra, first + k);
            }
            bits &= bits - 1;
            k += 1;
        }
    };
    // Rows (dx, dy) with the cells dz = -2..=2 along them as bits 0 to 4.
    let row = |a: usize, dx: isize, dy: isize| (place[a] as isize + dx * sx + dy * sy - 2) as usize;
    const ABOVE_ONE: u64 = 0b01000;
    const WITHIN_ONE: u64 = 0b01110;
    const TWO_APART: u64 = 0b10001;
    const WITHIN_TWO: u64 = 0b11111;
    for a in 0..count {
        join_window(&mut joined, a, row(a, 0, 0), ABOVE_ONE);
        for [dx, dy] in [[0, 1], [1, -1], [1, 0], [1, 1]] {
            join_window(&mut joined, a, row(a, dx, dy), WITHIN_ONE);
        }
    }
    let roots: Vec<u32> = (0..count as u32).map(|a| joined.root(a)).collect();
    let mut size = vec![0u32; count];
    roots.iter().for_each(|&r| size[r as usize] += 1);
    let largest = (0..count).max_by_key(|&r| size[r]).unwrap_or(0) as u32;
    for a in (0..count).filter(|&a| roots[a] != largest) {
        for dx in -2..=2isize {
            for dy in -2..=2isize {
                let mask = if dx.abs() == 2 || dy.abs() == 2 {
                    WITHIN_TWO
                } else {
                    TWO_APART
                };
                join_window(&mut joined, a, row(a, dx, dy), mask);
            }
        }
    }
    joined.labels()
}

fn components_keyed<K: CellKey>(
    points: &[[f32; 3]],
    cells: &[[i64; 3]],
    low: [i64; 3],
    radius_squared: f32,
) -> (Vec<u32>, usize) {
    let pack = |k: &[i64; 3]| K::pack([0, 1, 2].map(|a| k[a] - low[a]));
    // The points sorted by cell: cell a holds order[start[a]..start[a + 1]], in cloud order.
    let mut order: Vec<(K, u32)> = cells.iter().enumerate().map(|(i, k)| (pack(k), i as u32)).collect();
    order.sort_unstable();
    let mut keys: Vec<K> = Vec::new();
    let mut start: Vec<u32> = Vec::new();
    for (at, (key, _)) in order.iter().enumerate() {
        if keys.last() != Some(key) {
            keys.push(*key);
            start.push(at as u32);
        }
    }
    start.push(order.len() as u32);
    let mut joined = Joined {
        points,
        members: order.iter().map(|(_, i)| *i).collect(),
        start,
        parent: (0..keys.len() as u32).collect(),
        radius_squared,
    };
    // Of the 5 x 5 x 5 around a cell, the half after it in grid order, walked as rows (dx, dy) of
    // cells dz apart, the nearest (up to one apart) first. For one row, the cells' neighbours come
    // in the same order as the cells, so one walk along the sorted keys finds them all.
    let mut rows: Vec<([i64; 2], i64)> = Vec::new();
    for reach in [1i64, 2] {
        for dx in 0..=reach {
            for dy in -reach..=reach {
                if dx > 0 || dy >= 0 {
                    rows.push(([dx, dy], reach));
                }
            }
        }
    }
    for ([dx, dy], reach) in rows {
        // The row (0, 0) is the cell's own column: only the cells above it. Rows the first pass
        // walked need only the cells two apart in the second.
        let (below, above) = if (dx, dy) == (0, 0) {
            (1, reach)
        } else {
            (-reach, reach)
        };
        let walked = reach == 2 && dx.abs() <= 1 && dy.abs() <= 1;
        let mut b = 0;
        for a in 0..keys.len() {
            let (first, last) = (keys[a].shifted([dx, dy, below]), keys[a].shifted([dx, dy, above]));
            let mut ra = u32::MAX;
            while b < keys.len() && keys[b] < first {
                b += 1;
            }
            let mut c = b;
            while c < keys.len() && keys[c] <= last {
                if !walked || (keys[c].z() - keys[a].z()).abs() == 2 {
                    ra = joined.join(a as u32, ra, c as u32);
                }
                c += 1;
            }
        }
    }
    joined.labels()
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The occupancy bitmap (clouds in a small box) and the sorted cell keys (any box) find the
    /// same clusters: blobs of every size and spread, some touching, and sparse noise.
    #[test]
    fn clusters_on_the_bitmap_are_those_of_the_sorted_keys() {
        let mut rng = ChaCha8Rng::seed_from_u64(9);
        for case in 0..60 {
            let mut points: Vec<[f32; 3]> = Vec::new();
            for _ in 0..rng.random_range(1..6) {
                let centre: [f32; 3] = std::array::from_fn(|_| rng.random_range(-0.4..0.4));
                let spread = rng.random_range(0.02..0.2);
                for _ in 0..rng.random_range(5..400) {
                    points.push(centre.map(|c| c + rng.random_range(-spread..spread)));
                }
            }
            for _ in 0..rng.random_range(0..200) {
                points.push(std::array::from_fn(|_| rng.random_range(-0.6..0.6)));
            }
            let radius = rng.random_range(0.04..0.12);
            let cell = radius / 3f32.sqrt();
            let cells: Vec<[i64; 3]> = points.iter().map(|p| p.map(|c| floor(c / cell))).collect();
            let grid = Occupancy::of(&cells).expect("a small box");
            let on_grid = components_on_grid(&points, &cells, &grid, radius * radius);
            let low = cells
                .iter()
                .fold([i64::MAX; 3], |m, k| [0, 1, 2].map(|a| m[a].min(k[a] - 2)));
            let keyed = components_keyed::<u64>(&points, &cells, low, radius * radius);
            assert_eq!(on_grid, keyed, "case {case}, radius {radius}");
            assert!(on_grid.1 >= 1);
        }
    }

    /// The voxel grid on the bitmap and in a hash map (a cloud spread too far for a bitmap) give
    /// the same centroids in the same order.
    #[test]
    fn the_voxel_grid_is_the_same_on_the_bitmap_and_in_a_hash_map() {
        let mut rng = ChaCha8Rng::seed_from_u64(10);
        let mut near: Vec<[f32; 3]> = (0..3000)
            .map(|_| std::array::from_fn(|_| rng.random_range(-0.5..0.5)))
            .collect();
        let far_point = [900.0, 900.0, 900.0];
        let mut with_far = near.clone();
        with_far.push(far_point);
        let cells: Vec<[i64; 3]> = with_far.iter().map(|p| p.map(|c| floor(c / 0.05))).collect();
        assert!(
            Occupancy::of(&cells).is_none(),
            "the far point puts the box beyond a bitmap"
        );
        voxel_grid(&mut near, 0.05);
        voxel_grid(&mut with_far, 0.05);
        assert_eq!(with_far.pop(), Some(far_point));
        assert_eq!(near, with_far);
    }
}
