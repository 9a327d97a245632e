//! Geometric clean-up of a frame before subsampling: the sensor-to-gravity transform, a
//! region-of-interest crop, the ground plane (RANSAC: to level the cloud and/or remove the ground)
//! outlier removal (statistical or radius, on a kiddo KD-tree) and the largest Euclidean cluster
//! (on a grid of cells, union-find).

use std::num::NonZeroUsize;

use kiddo::{ImmutableKdTree, SquaredEuclidean};
use nalgebra::{Matrix3, Rotation3, Unit as UnitVector, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

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

/// Keeps the largest Euclidean cluster: points joined by chains of neighbours closer than
/// `radius` (PCL's EuclideanClusterExtraction, one cluster). What a crop leaves of the floor's
/// depth noise and of stray clutter is sparse and falls apart from the object. Returns how many
/// points were removed.
pub fn keep_largest_cluster(points: &mut Vec<[f32; 3]>, radius: f32) -> usize {
    if points.len() < 2 || !(radius > 0.0) {
        return 0;
    }
    // A grid of cells whose diagonal is `radius`: the points of one cell are all within `radius`
    // of each other, so each cell lies in one cluster, and clusters are found by joining cells
    // (union-find) that hold a pair of points within `radius` of each other. The same clusters as
    // a neighbour search from every point, at a fraction of its cost on dense surfaces.
    let cell = radius / 3f32.sqrt();
    let radius_squared = radius * radius;
    // Cell coordinates must stay far inside i64 (so that neighbours and box sizes cannot overflow):
    // a cloud reaching beyond 2^40 cells (10^10 m at a 1 cm radius) is left as it is. The node
    // drops points beyond 1e5 m before prepare; this guards the function itself (found by
    // `cargo fuzz run prepare`).
    const LIMIT: f32 = (1u64 << 40) as f32;
    if points.iter().flatten().any(|c| !((c / cell).abs() < LIMIT)) {
        return 0;
    }
    let key = |p: &[f32; 3]| p.map(|c| (c / cell).floor() as i64);
    let mut id: CellMap = CellMap::default();
    let mut keys: Vec<[i64; 3]> = Vec::new();
    let cell_of: Vec<usize> = points
        .iter()
        .map(|p| {
            let k = key(p);
            *id.entry(k).or_insert_with(|| {
                keys.push(k);
                keys.len() - 1
            })
        })
        .collect();
    // Cells numbered in grid order, so that the neighbour loops below walk the grid (and the
    // points) in order rather than in the sensor's scan order.
    let mut by_key: Vec<usize> = (0..keys.len()).collect();
    by_key.sort_unstable_by_key(|&c| keys[c]);
    let mut rank = vec![0usize; keys.len()];
    for (r, &c) in by_key.iter().enumerate() {
        rank[c] = r;
    }
    let keys: Vec<[i64; 3]> = by_key.iter().map(|&c| keys[c]).collect();
    id.values_mut().for_each(|c| *c = rank[*c]);
    // Each cell's points, in cloud order, as one array (cell a: member[start[a]..start[a + 1]]).
    let mut start = vec![0usize; keys.len() + 1];
    for &c in &cell_of {
        start[rank[c] + 1] += 1;
    }
    for a in 0..keys.len() {
        start[a + 1] += start[a];
    }
    let mut member = vec![0usize; points.len()];
    let mut cursor = start.clone();
    for (index, &c) in cell_of.iter().enumerate() {
        member[cursor[rank[c]]] = index;
        cursor[rank[c]] += 1;
    }
    let members = |a: usize| &member[start[a]..start[a + 1]];
    // Neighbour lookups in a dense grid over the occupied box when it is small enough (a cropped
    // frame), else in the hash map.
    let low = keys
        .iter()
        .fold([i64::MAX; 3], |m, k| [0, 1, 2].map(|a| m[a].min(k[a])));
    let high = keys
        .iter()
        .fold([i64::MIN; 3], |m, k| [0, 1, 2].map(|a| m[a].max(k[a])));
    let dims = [0, 1, 2].map(|a| (high[a] - low[a] + 1) as u64);
    let cells = dims.iter().try_fold(1u64, |total, d| total.checked_mul(*d));
    let dense: Option<Vec<u32>> = cells.filter(|n| *n <= 1 << 22).map(|n| {
        let mut grid = vec![u32::MAX; n as usize];
        for (i, k) in keys.iter().enumerate() {
            grid[(((k[0] - low[0]) as u64 * dims[1] + (k[1] - low[1]) as u64) * dims[2] + (k[2] - low[2]) as u64)
                as usize] = i as u32;
        }
        grid
    });
    let lookup = |k: [i64; 3]| -> Option<usize> {
        match &dense {
            Some(grid) => {
                if (0..3).any(|a| k[a] < low[a] || k[a] > high[a]) {
                    return None;
                }
                let at = (((k[0] - low[0]) as u64 * dims[1] + (k[1] - low[1]) as u64) * dims[2]
                    + (k[2] - low[2]) as u64) as usize;
                (grid[at] != u32::MAX).then_some(grid[at] as usize)
            }
            None => id.get(&k).copied(),
        }
    };
    let mut parent: Vec<usize> = (0..keys.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    // Cells up to two apart along an axis can hold points within `radius` (gap (|d| - 1) * cell);
    // the nearest first, which join most cells before the farther ones need a pair search.
    let mut offsets = Vec::new();
    for dx in -2i64..=2 {
        for dy in -2i64..=2 {
            for dz in -2i64..=2 {
                let gap: i64 = [dx, dy, dz].iter().map(|d| (d.abs() - 1).max(0).pow(2)).sum();
                if (dx, dy, dz) > (0, 0, 0) && gap <= 3 {
                    offsets.push((gap, [dx, dy, dz]));
                }
            }
        }
    }
    offsets.sort();
    for (_, d) in &offsets {
        for a in 0..keys.len() {
            let k = keys[a];
            let Some(b) = lookup([k[0] + d[0], k[1] + d[1], k[2] + d[2]]) else {
                continue;
            };
            let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
            if ra == rb {
                continue;
            }
            let joined = members(a).iter().any(|&i| {
                let p = points[i];
                members(b).iter().any(|&j| {
                    let q = points[j];
                    (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2) <= radius_squared
                })
            });
            if joined {
                parent[ra.max(rb)] = ra.min(rb);
            }
        }
    }
    // The largest cluster; of equal ones, the one holding the lowest point index.
    let mut size = vec![0usize; keys.len()];
    let mut first = vec![usize::MAX; keys.len()];
    for a in 0..keys.len() {
        let r = root(&mut parent, a);
        size[r] += members(a).len();
        first[r] = first[r].min(members(a)[0]);
    }
    let best = (0..keys.len())
        .max_by(|&a, &b| size[a].cmp(&size[b]).then(first[b].cmp(&first[a])))
        .expect("at least one cell");
    let mut keep = vec![false; points.len()];
    for a in 0..keys.len() {
        if root(&mut parent, a) == best {
            members(a).iter().for_each(|&i| keep[i] = true);
        }
    }
    let before = points.len();
    let mut flags = keep.into_iter();
    points.retain(|_| flags.next().unwrap_or(false));
    before - points.len()
}
