//! Prepare's geometric steps on synthetic scenes with known answers: the RANSAC ground plane, the
//! levelling rotation, ground removal, the crop and both outlier filters; and `Preparer` end to end.

use gdvae_node::cloud::{Frame, PointCloud, Unit};
use gdvae_node::config::{OutlierMethod, OutlierSettings, PrepareSettings};
use gdvae_node::prepare::{
    crop, euclidean_clusters, fit_ground, floor_noise_cut, keep_largest_cluster, levelling, remove_outliers,
    remove_plane, transform, transform_and_crop, transform_crop_and_measure_floor, voxel_grid, FloorNoise,
    PrepareError, Preparer, RangeStretch, FLOOR_BAND_M, JOIN_MIN_FRACTION,
};
use nalgebra::{Matrix3, Rotation3, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// A 2 m x 2 m floor at z = 0 (2,500 points, 5 mm noise) and a 0.4 m cube of points above it.
/// A frame of `points` on `stream`, as a source would hand it to prepare.
fn frame_of(stream: &str, sequence: u64, unit: Unit, points: Vec<[f32; 3]>) -> Frame {
    Frame {
        stream: stream.into(),
        sequence,
        sensor_stamp_ns: None,
        ingested: std::time::Instant::now(),
        ingest_unix_ns: 0,
        unit,
        cloud: PointCloud { points },
        sensor_frame: None,
    }
}

fn scene(rng: &mut ChaCha8Rng) -> (Vec<[f32; 3]>, usize) {
    let mut points = Vec::new();
    for _ in 0..2500 {
        points.push([
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-0.005..0.005),
        ]);
    }
    let floor = points.len();
    for _ in 0..1500 {
        points.push([
            rng.random_range(-0.2..0.2),
            rng.random_range(-0.2..0.2),
            rng.random_range(0.1..0.5),
        ]);
    }
    (points, floor)
}

#[test]
fn ransac_finds_a_tilted_ground_and_levelling_puts_it_at_z_zero() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    let (mut points, _) = scene(&mut rng);
    // Tilt by 20 degrees about x and lift by 1 m: what a sensor with an unknown pitch sees.
    let tilt = Rotation3::from_axis_angle(&Vector3::x_axis(), 20f32.to_radians()).into_inner();
    transform(&mut points, &tilt, &Vector3::new(0.0, 0.0, 1.0));
    let plane = fit_ground(&points, 0.02, 100, 7).expect("a ground plane");
    let expected = tilt * Vector3::z();
    assert!(
        plane.normal.dot(&expected) > 0.999,
        "normal {:?} vs {expected:?}",
        plane.normal
    );
    assert!(
        plane.inliers >= 2400 && plane.inliers <= 2600,
        "{} inliers",
        plane.inliers
    );
    let (rotation, translation) = levelling(&plane);
    transform(&mut points, &rotation, &translation);
    let floor_heights: Vec<f32> = points[..2500].iter().map(|p| p[2]).collect();
    assert!(
        floor_heights.iter().all(|z| z.abs() < 0.02),
        "the floor is at z = 0 after levelling"
    );
    let again = fit_ground(&points, 0.02, 100, 7).unwrap();
    remove_plane(&mut points, &again, 0.02);
    assert_eq!(points.len(), 1500, "only the object is left");
}

#[test]
fn no_ground_in_a_cloud_without_one() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let ball: Vec<[f32; 3]> = (0..2000)
        .map(|_| {
            let v = Vector3::new(
                rng.random_range(-1.0f32..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            );
            let v = v.normalize();
            [v.x, v.y, v.z]
        })
        .collect();
    assert!(fit_ground(&ball, 0.005, 100, 1).is_none());
    assert!(fit_ground(&[], 0.01, 10, 1).is_none());
}

#[test]
fn transform_and_crop_in_one_pass_is_transform_then_crop() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    let points: Vec<[f32; 3]> = (0..2000)
        .map(|_| std::array::from_fn(|_| rng.random_range(-3000.0..3000.0)))
        .collect();
    let rotation = Rotation3::from_euler_angles(0.3, -0.2, 1.1).into_inner();
    let translation = Vector3::new(0.5, -0.2, 1.3);
    let bounds = [-1.0, -1.5, 0.0, 1.0, 1.5, 2.0];
    let mut expected: Vec<[f32; 3]> = points.iter().map(|p| p.map(|c| c * 0.001)).collect();
    transform(&mut expected, &rotation, &translation);
    let all = transform_and_crop(&points, 0.001, &rotation, &translation, None);
    crop(&mut expected, &bounds);
    let cropped = transform_and_crop(&points, 0.001, &rotation, &translation, Some(&bounds));
    assert_eq!(all.len(), points.len());
    assert!(!cropped.is_empty() && cropped.len() < points.len() / 2);
    assert_eq!(cropped.len(), expected.len());
    for (a, b) in cropped.iter().zip(&expected) {
        assert!((0..3).all(|i| (a[i] - b[i]).abs() < 1e-5), "{a:?} != {b:?}");
    }
}

#[test]
fn a_voxel_grid_keeps_one_centroid_per_occupied_cube_in_the_order_first_met() {
    let mut points = vec![
        [0.01, 0.01, 0.01],
        [0.25, 0.05, 0.05], // its own cube
        [0.03, 0.03, 0.05],
        [-0.01, 0.02, 0.02], // the cube below zero along x
        [0.05, 0.07, 0.03],
    ];
    let removed = voxel_grid(&mut points, 0.1);
    assert_eq!(removed, 2);
    let expected = [[0.03, 0.036_666_67, 0.03], [0.25, 0.05, 0.05], [-0.01, 0.02, 0.02]];
    assert_eq!(points.len(), expected.len());
    for (a, b) in points.iter().zip(&expected) {
        assert!((0..3).all(|i| (a[i] - b[i]).abs() < 1e-6), "{a:?} != {b:?}");
    }
    // Points already further apart than the edge are kept as they are; 0 is off.
    let mut sparse: Vec<[f32; 3]> = (0..50).map(|i| [i as f32 * 0.1 + 0.05, 0.05, 0.05]).collect();
    let before = sparse.clone();
    assert_eq!(voxel_grid(&mut sparse, 0.1), 0);
    assert_eq!(sparse, before);
    assert_eq!(voxel_grid(&mut sparse, 0.0), 0);
    // Coordinates beyond what a grid can index: the cloud is left as it is.
    let mut far = vec![[0.0, 0.0, 0.0], [0.001, 0.0, 0.0], [3e38, 0.0, 0.0]];
    assert_eq!(voxel_grid(&mut far, 0.01), 0);
    assert_eq!(far.len(), 3);
}

#[test]
fn a_dense_surface_on_a_voxel_grid_keeps_its_extent_with_far_fewer_points() {
    // A 1 m x 0.5 m sheet sampled every 2.5 mm (80,000 points), reduced on a 3 cm grid.
    let mut sheet: Vec<[f32; 3]> = Vec::new();
    for i in 0..400 {
        for j in 0..200 {
            sheet.push([i as f32 * 0.0025, j as f32 * 0.0025, 0.3]);
        }
    }
    let mut reduced = sheet.clone();
    voxel_grid(&mut reduced, 0.03);
    // ceil(1 / 0.03) x ceil(0.5 / 0.03) cubes.
    assert_eq!(reduced.len(), 34 * 17);
    let extent = |c: &[[f32; 3]], a: usize| {
        let (lo, hi) = c
            .iter()
            .fold((f32::MAX, f32::MIN), |(lo, hi), p| (lo.min(p[a]), hi.max(p[a])));
        hi - lo
    };
    for axis in 0..2 {
        assert!((extent(&sheet, axis) - extent(&reduced, axis)).abs() < 0.03);
    }
}

#[test]
fn crop_keeps_the_box() {
    let mut points = vec![[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, -0.1], [0.5, 0.5, 0.5]];
    crop(&mut points, &[-1.0, -1.0, 0.0, 1.0, 1.0, 1.0]);
    assert_eq!(points, vec![[0.0, 0.0, 0.0], [0.5, 0.5, 0.5]]);
}

#[test]
fn both_outlier_filters_remove_isolated_points_and_keep_the_surface() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let mut points: Vec<[f32; 3]> = (0..40)
        .flat_map(|i| (0..40).map(move |j| [i as f32 * 0.01, j as f32 * 0.01, 0.0]))
        .collect();
    let surface = points.len();
    for _ in 0..10 {
        points.push([
            rng.random_range(1.0..2.0),
            rng.random_range(1.0..2.0),
            rng.random_range(1.0..2.0),
        ]);
    }
    for method in [OutlierMethod::Statistical, OutlierMethod::Radius] {
        let mut cleaned = points.clone();
        let settings = OutlierSettings {
            method,
            radius_m: 0.03,
            ..OutlierSettings::default()
        };
        let removed = remove_outliers(&mut cleaned, &settings);
        assert_eq!(removed, 10, "{method:?}");
        assert_eq!(cleaned.len(), surface);
        assert!(cleaned.iter().all(|p| p[2] == 0.0));
    }
    let mut untouched = points.clone();
    assert_eq!(
        remove_outliers(&mut untouched, &OutlierSettings::default()),
        0,
        "method none"
    );
}

#[test]
fn the_preparer_converts_units_levels_crops_and_rejects_too_few_points() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    let (points, _) = scene(&mut rng);
    let millimetres: Vec<[f32; 3]> = points.iter().map(|p| p.map(|c| c * 1000.0)).collect();
    let frame = |points: Vec<[f32; 3]>, unit| frame_of("s", 3, unit, points);
    let settings = PrepareSettings {
        remove_ground: true,
        crop: Some([-0.5, -0.5, -1.0, 0.5, 0.5, 1.0]),
        ..PrepareSettings::default()
    };
    let preparer = Preparer::new(&settings, 256, 2.0);
    let prepared = preparer.prepare(&frame(millimetres, Unit::Millimetre)).unwrap();
    assert_eq!(prepared.points_kept, 1500, "floor removed, object kept");
    assert_eq!(prepared.points.len(), 256);
    // The object is 0.4 x 0.4 x 0.4 m, centred at z = 0.3; in model units (2 per metre) its
    // extent is 0.8 and it is centred on the origin.
    let extent = |axis: usize| {
        let values = prepared.points.iter().map(|p| p[axis]);
        values.clone().fold(f32::MIN, f32::max) - values.fold(f32::MAX, f32::min)
    };
    for axis in 0..3 {
        assert!(
            (extent(axis) - 0.8).abs() < 0.05,
            "axis {axis}: extent {}",
            extent(axis)
        );
    }
    assert!((prepared.centre_m[2] - 0.3).abs() < 0.02);
    let again = preparer
        .prepare(&frame(
            points.iter().map(|p| p.map(|c| c * 1000.0)).collect(),
            Unit::Millimetre,
        ))
        .unwrap();
    assert_eq!(
        again.points, prepared.points,
        "deterministic for a seed and sequence number"
    );

    let sparse = frame(points[2500..2510].to_vec(), Unit::Metre);
    let plain = Preparer::new(&PrepareSettings::default(), 256, 2.0);
    assert_eq!(
        plain.prepare(&sparse).unwrap_err(),
        PrepareError::TooFewPoints { got: 10, minimum: 64 }
    );
}

/// A dense sensor's view of the floor: `n` points over a 2.4 m square at z ~ N(0, sigma), and a
/// standing 0.3 x 0.3 x 0.8 m box (2,000 points) on it at (0.3, -0.2).
fn noisy_floor_and_box(rng: &mut ChaCha8Rng, n: usize, sigma: f32) -> Vec<[f32; 3]> {
    let gaussian = |rng: &mut ChaCha8Rng| {
        // Box-Muller: the sum of uniforms would have no tails.
        let (u, v): (f32, f32) = (rng.random_range(1e-7..1.0), rng.random_range(0.0..1.0));
        (-2.0 * u.ln()).sqrt() * (std::f32::consts::TAU * v).cos()
    };
    let mut points: Vec<[f32; 3]> = (0..n)
        .map(|_| {
            [
                rng.random_range(-1.2..1.2),
                rng.random_range(-1.2..1.2),
                sigma * gaussian(rng),
            ]
        })
        .collect();
    points.extend((0..2000).map(|_| {
        [
            0.3 + rng.random_range(-0.15..0.15),
            -0.2 + rng.random_range(-0.15..0.15),
            rng.random_range(0.0..0.8),
        ]
    }));
    points
}

#[test]
fn the_floor_cut_rises_with_the_floors_noise_measured_below_the_ground() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    for sigma in [0.005f32, 0.02, 0.04] {
        let mut points = noisy_floor_and_box(&mut rng, 60_000, sigma);
        points.retain(|p| p[2] >= -FLOOR_BAND_M);
        let cut = floor_noise_cut(&mut points, 0.02, 3.0);
        assert!(
            (cut - (3.0 * sigma).max(0.02)).abs() < 0.1 * (3.0 * sigma).max(0.02),
            "sigma {sigma}: cut at {cut}"
        );
        let floor_left = points
            .iter()
            .filter(|p| !(p[0] > 0.15 && p[0] < 0.45 && p[1] > -0.35 && p[1] < -0.05))
            .count();
        // Above 3 sigma: 0.13 % of a Gaussian's points, 80 of 60,000 (a fixed 2 cm keeps 16 % at sigma 2 cm).
        assert!(
            floor_left < 150,
            "sigma {sigma}: {floor_left} floor points above the cut"
        );
        assert!(
            points.len() > 1700,
            "sigma {sigma}: the box keeps most of its points ({})",
            points.len() - floor_left
        );
    }
    // In one pass with the transform and the crop, keeping none of the points below the crop.
    let mut points = noisy_floor_and_box(&mut rng, 60_000, 0.02);
    let lift = Vector3::new(0.0, 0.0, 1.0);
    let mut sensor: Vec<[f32; 3]> = points
        .iter()
        .map(|p| [p[0] * 1000.0, p[1] * 1000.0, (p[2] - 1.0) * 1000.0])
        .collect();
    // Points the pass (written without branches on them) must neither keep nor measure: beyond
    // the floor band, outside the box's x and y, not finite.
    let deep = -1000.0 * (1.0 + 2.0 * FLOOR_BAND_M);
    for (i, odd) in [
        [0.0, 0.0, deep],
        [1500.0, 0.0, -1005.0],
        [0.0, -1500.0, -1005.0],
        [0.0, 0.0, f32::NAN],
        [f32::NAN, 0.0, -1005.0],
        [0.0, 0.0, f32::NEG_INFINITY],
        [0.0, 0.0, f32::INFINITY],
    ]
    .into_iter()
    .enumerate()
    {
        sensor.insert(i * 7919, odd);
    }
    let bounds = [-1.0, -1.0, 0.02, 1.0, 1.0, 2.0];
    let mut noise = FloorNoise::default();
    let mut one_pass =
        transform_crop_and_measure_floor(&sensor, 1e-3, &Matrix3::identity(), &lift, &bounds, &mut noise);
    let cut = noise.cut(0.02, 3.0);
    one_pass.retain(|p| p[2] >= cut);
    let mut two_steps = transform_and_crop(
        &sensor,
        1e-3,
        &Matrix3::identity(),
        &lift,
        Some(&[-1.0, -1.0, -FLOOR_BAND_M, 1.0, 1.0, 2.0]),
    );
    assert_eq!(floor_noise_cut(&mut two_steps, 0.02, 3.0), cut);
    assert_eq!(one_pass, two_steps);
    points.retain(|p| p[2] >= cut && p[0].abs() <= 1.0 && p[1].abs() <= 1.0);
    assert!(
        one_pass.len().abs_diff(points.len()) < 10,
        "{} against {}",
        one_pass.len(),
        points.len()
    );
    // Nothing below the ground (a cloud already cropped there): the crop's own floor.
    let mut above: Vec<[f32; 3]> = (0..500).map(|i| [0.0, 0.0, 0.01 + i as f32 * 1e-3]).collect();
    assert_eq!(floor_noise_cut(&mut above, 0.02, 3.0), 0.02);
    let expected = (0..500).filter(|i| 0.01 + *i as f32 * 1e-3 >= 0.02).count();
    assert_eq!(above.len(), expected);
}

/// The sim's default recording (every depth pixel, a 4 m ground patch) left thousands of noisy
/// floor points above a crop 2 cm over the ground, linked into a sheet larger than the subject:
/// prepare kept the sheet. With the floor cut (on by default) it keeps the box.
#[test]
fn on_a_dense_noisy_floor_prepare_keeps_the_object_not_the_floor() {
    let mut rng = ChaCha8Rng::seed_from_u64(13);
    let points = noisy_floor_and_box(&mut rng, 120_000, 0.03);
    let settings = |floor_noise_sigmas| PrepareSettings {
        crop: Some([-1.2, -1.2, 0.02, 1.2, 1.2, 2.5]),
        voxel_grid_m: 0.03,
        cluster_m: 0.06,
        floor_noise_sigmas,
        ..PrepareSettings::default()
    };
    let frame = frame_of("s", 0, Unit::Metre, points);
    let centre = |floor_noise_sigmas| {
        Preparer::new(&settings(floor_noise_sigmas), 256, 2.0)
            .prepare(&frame)
            .unwrap()
            .centre_m
    };
    let with_cut = centre(PrepareSettings::default().floor_noise_sigmas);
    assert!(
        (with_cut[0] - 0.3).abs() < 0.03 && (with_cut[1] + 0.2).abs() < 0.03 && (with_cut[2] - 0.45).abs() < 0.08,
        "the box's centre, got {with_cut:?}"
    );
    let without = centre(0.0);
    assert!(
        (without[0] - 0.3).abs() > 0.3 || (without[1] + 0.2).abs() > 0.3,
        "without the cut the floor's sheet wins (the test's premise), got {without:?}"
    );
}

#[test]
fn a_source_can_carry_its_own_sensor_pose() {
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let (points, _) = scene(&mut rng);
    let sources: Vec<gdvae_node::config::SourceSettings> = [
        "stream = \"a\"\nkind = \"files\"\npath = \"x\"",
        "stream = \"b\"\nkind = \"files\"\npath = \"x\"\nsensor_to_gravity_translation = [0.0, 0.0, 1.0]",
    ]
    .iter()
    .map(|t| toml::from_str(t).unwrap())
    .collect();
    let preparer =
        Preparer::new(&PrepareSettings::default(), 256, 1.0).with_sensor_poses(sources.iter().map(|s| s.sensor_pose()));
    let frame = |stream: &str| frame_of(stream, 0, Unit::Metre, points.clone());
    let a = preparer.prepare(&frame("a")).unwrap();
    let b = preparer.prepare(&frame("b")).unwrap();
    assert!(
        (b.centre_m[2] - a.centre_m[2] - 1.0).abs() < 1e-5,
        "{:?} vs {:?}",
        a.centre_m,
        b.centre_m
    );
    let largest = a
        .points
        .iter()
        .flatten()
        .zip(b.points.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    assert!(
        largest < 1e-5,
        "only the pose differs: the centred clouds agree to {largest}"
    );
}

/// The largest cluster by brute force: a breadth-first search over every pair within `radius`.
fn largest_cluster_by_brute_force(points: &[[f32; 3]], radius: f32) -> Vec<[f32; 3]> {
    let n = points.len();
    let near = |i: usize, j: usize| {
        let (p, q) = (points[i], points[j]);
        (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2) <= radius * radius
    };
    let mut label = vec![usize::MAX; n];
    let (mut best, mut best_size) = (0, 0);
    for seed in 0..n {
        if label[seed] != usize::MAX {
            continue;
        }
        label[seed] = seed;
        let (mut stack, mut size) = (vec![seed], 0);
        while let Some(i) = stack.pop() {
            size += 1;
            for j in 0..n {
                if label[j] == usize::MAX && near(i, j) {
                    label[j] = seed;
                    stack.push(j);
                }
            }
        }
        if size > best_size {
            (best, best_size) = (seed, size);
        }
    }
    (0..n).filter(|&i| label[i] == best).map(|i| points[i]).collect()
}

#[test]
fn the_largest_cluster_is_the_one_a_neighbour_search_finds() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
    for case in 0..40 {
        // Blobs of different sizes and spreads, some touching, plus sparse noise.
        let mut points = Vec::new();
        for _ in 0..rng.random_range(1..5) {
            let centre: [f32; 3] = std::array::from_fn(|_| rng.random_range(-1.0..1.0));
            let spread = rng.random_range(0.02..0.3);
            for _ in 0..rng.random_range(5..300) {
                points.push(centre.map(|c| c + rng.random_range(-spread..spread)));
            }
        }
        for _ in 0..rng.random_range(0..50) {
            points.push(std::array::from_fn(|_| rng.random_range(-1.5..1.5)));
        }
        let radius = rng.random_range(0.02..0.15);
        let expected = largest_cluster_by_brute_force(&points, radius);
        let removed = gdvae_node::prepare::keep_largest_cluster(&mut points, radius, None, 0.0, 0);
        assert_eq!(points, expected, "case {case}, radius {radius}");
        assert!(removed + points.len() > 0);
    }
}

/// Points on a 3 cm grid filling the box from `low` to `high`: one cluster at a 6 cm radius.
fn grid_box(low: [f32; 3], high: [f32; 3]) -> Vec<[f32; 3]> {
    let steps = |a: usize| ((high[a] - low[a]) / 0.03).round() as usize + 1;
    let mut points = Vec::new();
    for i in 0..steps(0) {
        for j in 0..steps(1) {
            for k in 0..steps(2) {
                points.push([
                    low[0] + 0.03 * i as f32,
                    low[1] + 0.03 * j as f32,
                    low[2] + 0.03 * k as f32,
                ]);
            }
        }
    }
    points
}

/// A body whose legs a limb hides from the torso (an 8 cm gap): the largest cluster alone is the
/// torso; `join_m` 0.1 keeps the legs with it, but not a handful of stray points just above it, an
/// arm held apart within the torso's box (its middle at the torso's height), an object beside it,
/// or a piece further than `join_m` below.
#[test]
fn a_body_broken_by_a_gap_is_joined_but_not_what_lies_beside_it() {
    // An L-shaped torso, so that the arm can lie within its box and 9 cm from it.
    let mut torso = grid_box([0.0, 0.0, 0.8], [0.3, 0.09, 1.4]);
    torso.extend(grid_box([0.0, 0.12, 0.8], [0.09, 0.3, 1.4]));
    let arm = grid_box([0.18, 0.18, 0.85], [0.3, 0.3, 1.24]);
    let legs = grid_box([0.03, 0.03, 0.0], [0.27, 0.15, 0.72]);
    let stray = grid_box([0.1, 0.05, 1.48], [0.16, 0.11, 1.51]);
    let beside = grid_box([0.6, 0.0, 0.8], [0.9, 0.09, 1.4]);
    let least = (JOIN_MIN_FRACTION * torso.len() as f32).ceil() as usize;
    assert!(stray.len() < least && arm.len() >= least && legs.len() >= least && beside.len() < torso.len());
    let scene: Vec<[f32; 3]> = [&torso, &arm, &legs, &stray, &beside]
        .into_iter()
        .flatten()
        .copied()
        .collect();
    let kept = |join_m: f32, scene: &[[f32; 3]]| {
        let mut points = scene.to_vec();
        keep_largest_cluster(&mut points, 0.06, None, join_m, 0);
        points
    };
    assert_eq!(kept(0.0, &scene), torso);
    let joined: Vec<[f32; 3]> = [&torso, &legs].into_iter().flatten().copied().collect();
    assert_eq!(kept(0.1, &scene), joined);
    // Legs 14 cm below: another object.
    let low_legs: Vec<[f32; 3]> = legs.iter().map(|p| [p[0], p[1], p[2] - 0.06]).collect();
    let far_scene: Vec<[f32; 3]> = [&torso, &low_legs].into_iter().flatten().copied().collect();
    assert_eq!(kept(0.1, &far_scene), torso);
}

/// A quadruped whose lower legs the sensor cut off (a gap of 9 cm at each knee, small pieces):
/// with `limb_min_points` they are kept, and so is nothing else: not a speck of the floor's noise
/// beside a foot (fewer points), a piece as low but further out than `join_m` (another object), a
/// piece in the body's upper half (a head held apart), or a piece below the body but outside its
/// footprint grown by `join_m`.
#[test]
fn legs_the_sensor_cut_off_are_kept_with_the_body_but_not_floor_specks_or_neighbours() {
    // Body and upper legs from 0.30 to 0.80 m, lower legs from 0 to 0.21 m.
    let mut body = grid_box([0.0, 0.0, 0.51], [0.9, 0.3, 0.81]);
    for x in [0.0, 0.81] {
        for y in [0.0, 0.24] {
            body.extend(grid_box([x, y, 0.3], [x + 0.06, y + 0.06, 0.48]));
        }
    }
    let lower_legs: Vec<Vec<[f32; 3]>> = [[0.0, 0.0], [0.81, 0.0], [0.0, 0.24], [0.81, 0.24]]
        .iter()
        .map(|&[x, y]| grid_box([x, y, 0.0], [x + 0.06, y + 0.06, 0.21]))
        .collect();
    let speck = grid_box([0.93, 0.0, 0.0], [0.96, 0.03, 0.03]);
    let neighbour = grid_box([1.2, 0.0, 0.0], [1.26, 0.06, 0.21]);
    let head = grid_box([0.3, 0.09, 0.9], [0.42, 0.21, 1.05]);
    let min_points = 10;
    assert!(speck.len() < min_points && lower_legs.iter().all(|l| l.len() >= min_points));
    assert!(neighbour.len() >= min_points && head.len() >= min_points);
    let mut scene = body.clone();
    lower_legs.iter().for_each(|l| scene.extend(l));
    for other in [&speck, &neighbour, &head] {
        scene.extend(other.iter());
    }
    let kept = |min_points: usize| {
        let mut points = scene.clone();
        keep_largest_cluster(&mut points, 0.06, None, 0.1, min_points);
        points
    };
    // Off, the legs are lost (this test can fail), and the 15 % rule keeps none of them.
    assert_eq!(kept(0), body);
    let mut with_legs = body.clone();
    lower_legs.iter().for_each(|l| with_legs.extend(l));
    assert_eq!(kept(min_points), with_legs);
}

#[test]
fn the_largest_cluster_of_a_cloud_spanning_a_huge_box_is_found_without_overflow() {
    // Found by `cargo fuzz run prepare`: the cells of the occupied box overflowed u64 when
    // multiplied, and the dense grid was sized by the wrapped product. 2^22 cells along each axis
    // (about 145 km at 6 cm) make 2^66, which wrapped to an empty grid.
    let cell = 0.06f32 / 3f32.sqrt();
    let far_corner = (4_194_304.0 - 0.5) * cell;
    let mut points = vec![[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0], [far_corner; 3]];
    let removed = gdvae_node::prepare::keep_largest_cluster(&mut points, 0.06, None, 0.0, 0);
    assert_eq!(removed, 1);
    assert_eq!(points.len(), 3);
    // Coordinates beyond what a grid of cells can index: the cloud is left as it is.
    let mut far = vec![[0.0, 0.0, 0.0], [3e38, 0.0, 0.0]];
    assert_eq!(
        gdvae_node::prepare::keep_largest_cluster(&mut far, 0.06, None, 0.0, 0),
        0
    );
    assert_eq!(far.len(), 2);
}

/// Cells are keyed in 64 bits when the cloud spans under 2^21 of them a side, else in 128: a point
/// far enough away to need the wide keys leaves the other clusters as the narrow keys found them.
#[test]
fn clusters_are_the_same_with_narrow_and_wide_cell_keys() {
    let mut rng = ChaCha8Rng::seed_from_u64(25);
    let mut points = blob(&mut rng, [0.0, 0.0, 0.4], 0.5, 600);
    points.extend(blob(&mut rng, [0.8, 0.3, 0.4], 0.3, 300));
    points.extend(blob(&mut rng, [0.45, 0.1, 0.4], 0.05, 40));
    let narrow = euclidean_clusters(&points, 0.06, None, 2, 3.0, 100);
    let far = (4_194_304.0 - 0.5) * 0.06f32 / 3f32.sqrt();
    points.push([far, far, far]);
    let wide = euclidean_clusters(&points, 0.06, None, 2, 3.0, 100);
    assert!(narrow.len() >= 2, "{} clusters", narrow.len());
    assert_eq!(narrow, wide);
}

/// A blob of `n` points in a box of side `size` centred at `centre`.
fn blob(rng: &mut ChaCha8Rng, centre: [f32; 3], size: f32, n: usize) -> Vec<[f32; 3]> {
    (0..n)
        .map(|_| std::array::from_fn(|a| centre[a] + rng.random_range(-size / 2.0..size / 2.0)))
        .collect()
}

#[test]
fn every_cluster_that_could_be_an_object_is_a_candidate_largest_first() {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut points = blob(&mut rng, [0.0, 0.0, 0.4], 0.4, 800);
    points.extend(blob(&mut rng, [1.5, 0.0, 0.4], 0.4, 1200));
    points.extend(blob(&mut rng, [-1.5, 0.0, 0.4], 0.1, 20)); // too few points
    points.extend((0..400).map(|i| [-1.0 + 0.01 * i as f32, 2.0, 0.5])); // a 4 m rail: too long
    let clusters = euclidean_clusters(&points, 0.1, None, 50, 3.0, 8);
    assert_eq!(clusters.iter().map(Vec::len).collect::<Vec<_>>(), vec![1200, 800]);
    assert!(clusters[0].iter().all(|p| p[0] > 1.0) && clusters[1].iter().all(|p| p[0].abs() < 0.5));
    assert_eq!(
        euclidean_clusters(&points, 0.1, None, 50, 3.0, 1).len(),
        1,
        "at most max_clusters"
    );
    assert_eq!(
        euclidean_clusters(&points, 0.1, None, 10, 5.0, 8).len(),
        4,
        "the small blob and the rail pass looser limits"
    );
    // The largest cluster is the one keep_largest_cluster keeps.
    let mut largest = points.clone();
    keep_largest_cluster(&mut largest, 0.1, None, 0.0, 0);
    assert_eq!(largest, clusters[0]);
}

#[test]
fn with_one_object_the_first_candidate_is_what_prepare_gives_and_with_two_each_is_centred_on_its_own() {
    let mut rng = ChaCha8Rng::seed_from_u64(22);
    let settings = PrepareSettings {
        cluster_m: 0.1,
        min_points: 50,
        ..PrepareSettings::default()
    };
    let preparer = Preparer::new(&settings, 128, 2.0);
    let frame = |points: Vec<[f32; 3]>| frame_of("s", 7, Unit::Metre, points);
    let one = frame(blob(&mut rng, [0.3, 0.2, 0.5], 0.4, 900));
    let all = preparer.prepare_all(&one, 3.0, 4).unwrap();
    let single = preparer.prepare(&one).unwrap();
    assert_eq!(all.len(), 1);
    assert_eq!(
        (&all[0].points, all[0].centre_m, all[0].points_kept),
        (&single.points, single.centre_m, single.points_kept)
    );
    let mut two = blob(&mut rng, [0.0, 0.0, 0.5], 0.4, 700);
    two.extend(blob(&mut rng, [2.0, 1.0, 0.5], 0.4, 1000));
    let all = preparer.prepare_all(&frame(two), 3.0, 4).unwrap();
    assert_eq!(all.len(), 2);
    for (prepared, centre) in all.iter().zip([[2.0, 1.0, 0.5], [0.0, 0.0, 0.5]]) {
        assert_eq!(prepared.points.len(), 128);
        assert!(
            (0..3).all(|a| (prepared.centre_m[a] - centre[a]).abs() < 0.05),
            "{:?}",
            prepared.centre_m
        );
    }
}

/// A 0.6 m x 0.6 m patch facing a sensor at the origin, `range` metres away along +x, its depth
/// quantised into layers `step` metres apart (as a stereo camera's disparity steps) and each point
/// on a random layer within one step of the surface: 2 cm apart across the ray.
fn layered_patch(rng: &mut ChaCha8Rng, range: f32, step: f32) -> Vec<[f32; 3]> {
    let mut points = Vec::new();
    for i in 0..30 {
        for j in 0..30 {
            let layer = rng.random_range(-1i32..=1) as f32;
            let (y, z) = (-0.3 + 0.02 * i as f32, -0.3 + 0.02 * j as f32);
            // Along the ray through (range, y, z).
            let along = (range + layer * step) / range;
            points.push([range * along, y * along, z * along]);
        }
    }
    points
}

#[test]
fn a_far_object_broken_by_depth_noise_stays_one_cluster_with_the_radius_grown_by_range() {
    let mut rng = ChaCha8Rng::seed_from_u64(23);
    let stretch = Some(RangeStretch {
        origin: [0.0; 3],
        from_m: 2.5,
    });
    // 4.5 m away, layers 8 cm apart (an OAK-D's disparity step there is about 7.6 cm).
    let far = layered_patch(&mut rng, 4.5, 0.08);
    let pieces = euclidean_clusters(&far, 0.06, None, 1, 3.0, 100);
    assert!(
        pieces.len() > 1 && pieces[0].len() < 700,
        "one radius breaks it: {} pieces",
        pieces.len()
    );
    let whole = euclidean_clusters(&far, 0.06, stretch, 1, 3.0, 100);
    assert_eq!(whole.len(), 1, "grown with range, one object");
    assert_eq!(whole[0].len(), far.len());
    // Two such objects 0.8 m apart along the ray stay two.
    let mut two = far.clone();
    two.extend(layered_patch(&mut rng, 5.3, 0.08));
    assert_eq!(euclidean_clusters(&two, 0.06, stretch, 100, 3.0, 100).len(), 2);
    // Nearer than `from_m` nothing changes.
    let near = layered_patch(&mut rng, 2.0, 0.08);
    assert_eq!(
        euclidean_clusters(&near, 0.06, stretch, 1, 3.0, 100),
        euclidean_clusters(&near, 0.06, None, 1, 3.0, 100)
    );
    let mut kept = far.clone();
    assert_eq!(
        keep_largest_cluster(&mut kept, 0.06, stretch, 0.0, 0),
        0,
        "keep_largest_cluster grows it too"
    );
}

#[test]
fn an_objects_position_is_not_moved_by_a_few_stray_points_as_its_box_centre_is() {
    let mut rng = ChaCha8Rng::seed_from_u64(24);
    let settings = PrepareSettings {
        cluster_m: 0.1,
        min_points: 50,
        ..PrepareSettings::default()
    };
    let preparer = Preparer::new(&settings, 128, 2.0);
    // A 0.4 m body at x = 0 and a thin trail of 20 points reaching 0.6 m behind it (joined to it).
    let mut points = blob(&mut rng, [0.0, 0.0, 0.5], 0.4, 900);
    points.extend((0..20).map(|i| [-0.2 - 0.03 * i as f32, 0.0, 0.5]));
    let all = preparer
        .prepare_all(&frame_of("s", 1, Unit::Metre, points), 3.0, 4)
        .unwrap();
    assert_eq!(all.len(), 1);
    assert!(
        all[0].centre_m[0] < -0.2,
        "the box's centre follows the trail: {:?}",
        all[0].centre_m
    );
    assert!(
        all[0].position_m[0].abs() < 0.05,
        "the position does not: {:?}",
        all[0].position_m
    );
    assert!((all[0].position_m[2] - 0.5).abs() < 0.05);
}
