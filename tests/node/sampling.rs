//! Subsampling: exact counts, determinism for a seed, coverage, padding and rejection.

use gdvae_node::prepare::{centre_and_scale, farthest_point_sampling, subsample, PrepareError, Sampling};

fn grid(n: usize) -> Vec<[f32; 3]> {
    (0..n * n)
        .map(|i| [(i % n) as f32 / n as f32, (i / n) as f32 / n as f32, 0.0])
        .collect()
}

#[test]
fn every_method_returns_exactly_n_points_deterministically() {
    let cloud = grid(60);
    for method in [Sampling::Farthest, Sampling::Random, Sampling::Voxel] {
        let a = subsample(&cloud, 256, 64, method, 0.02, 7).unwrap();
        let b = subsample(&cloud, 256, 64, method, 0.02, 7).unwrap();
        let c = subsample(&cloud, 256, 64, method, 0.02, 8).unwrap();
        assert_eq!(a.len(), 256);
        assert_eq!(a, b, "{method:?}: same seed, same points");
        assert_ne!(a, c, "{method:?}: another seed, other points");
        assert!(
            a.iter().all(|p| cloud.contains(p)),
            "{method:?}: points come from the cloud"
        );
    }
}

/// The largest distance from a cloud point to its nearest sample (the covering radius).
fn covering_radius(cloud: &[[f32; 3]], chosen: &[[f32; 3]]) -> f32 {
    cloud
        .iter()
        .map(|p| {
            chosen
                .iter()
                .map(|c| ((p[0] - c[0]).powi(2) + (p[1] - c[1]).powi(2)).sqrt())
                .fold(f32::INFINITY, f32::min)
        })
        .fold(0.0f32, f32::max)
}

#[test]
fn farthest_point_sampling_covers_the_cloud() {
    // 100 samples of the unit square: a 10 x 10 lattice would cover it within 0.071; farthest point
    // sampling is within twice the optimum, and clearly better than random choice.
    let cloud = grid(60);
    let farthest = covering_radius(&cloud, &farthest_point_sampling(&cloud, 100, 1));
    let random = covering_radius(&cloud, &gdvae_node::prepare::random_sampling(&cloud, 100, 1));
    assert!(farthest < 0.142, "farthest point sampling leaves a gap of {farthest}");
    assert!(farthest < 0.7 * random, "farthest {farthest} vs random {random}");
}

#[test]
fn small_clouds_are_padded_and_tiny_ones_rejected() {
    let cloud = grid(10); // 100 points
    let padded = subsample(&cloud, 256, 50, Sampling::Farthest, 0.01, 0).unwrap();
    assert_eq!(padded.len(), 256);
    assert_eq!(
        subsample(&cloud[..20], 256, 50, Sampling::Farthest, 0.01, 0),
        Err(PrepareError::TooFewPoints { got: 20, minimum: 50 })
    );
}

#[test]
fn centring_uses_the_bounding_box_and_scales() {
    let mut points = vec![[1.0, 2.0, 3.0], [3.0, 6.0, 3.0], [2.0, 2.0, 5.0]];
    let centre = centre_and_scale(&mut points, 0.5);
    assert_eq!(centre, [2.0, 4.0, 4.0]);
    assert_eq!(points[0], [-0.5, -1.0, -0.5]);
}

/// A deterministic pseudo-random cloud: a few dense blobs (as a cropped body) plus scattered
/// points, with every 7th point a duplicate of an earlier one (ties in the distances) and
/// coordinates on a coarse lattice every 5th point (more ties).
fn blobs(n: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut state = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 40) as f32) / (1u64 << 24) as f32
    };
    let mut cloud: Vec<[f32; 3]> = Vec::with_capacity(n);
    for i in 0..n {
        let p = if i % 7 == 6 {
            cloud[(next() * i as f32) as usize % i]
        } else if i % 5 == 4 {
            [0, 1, 2].map(|_| (next() * 8.0).floor() * 0.25)
        } else {
            let blob = (next() * 4.0) as usize as f32;
            [
                blob * 0.5 + 0.1 * next(),
                0.3 * next() - blob * 0.2,
                0.05 * next() + blob,
            ]
        };
        cloud.push(p);
    }
    cloud
}

#[test]
fn bucketed_farthest_point_sampling_chooses_exactly_the_plain_loops_points() {
    use gdvae_node::prepare::farthest_point_sampling_plain;
    for (n, count) in [
        (200, 64),
        (1000, 256),
        (2761, 256),
        (5000, 1600),
        (15000, 256),
        (3000, 2999),
    ] {
        for seed in 0..3 {
            let cloud = blobs(n, seed + n as u64);
            let fast = farthest_point_sampling(&cloud, count, seed);
            let plain = farthest_point_sampling_plain(&cloud, count, seed);
            assert_eq!(fast.len(), count);
            assert_eq!(fast, plain, "{n} points to {count}, seed {seed}");
        }
    }
    // The lattice alone: nearly every distance ties with others.
    let cloud = grid(60);
    assert_eq!(
        farthest_point_sampling(&cloud, 300, 3),
        farthest_point_sampling_plain(&cloud, 300, 3)
    );
}

#[test]
fn farthest_point_sampling_of_non_finite_clouds_matches_the_plain_loop() {
    use gdvae_node::prepare::farthest_point_sampling_plain;
    let mut cloud = blobs(1000, 9);
    cloud[10] = [f32::NAN, 0.0, 0.0];
    cloud[500] = [f32::INFINITY, 1.0, 0.0];
    // Compared bit for bit: NaN != NaN.
    let bits = |points: Vec<[f32; 3]>| points.iter().map(|p| p.map(f32::to_bits)).collect::<Vec<_>>();
    assert_eq!(
        bits(farthest_point_sampling(&cloud, 100, 1)),
        bits(farthest_point_sampling_plain(&cloud, 100, 1))
    );
}
