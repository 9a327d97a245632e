//! Arbitrary clouds, finite or not, through what every frame goes through: the outlet's
//! plausibility filter, then the prepare stage (transform, crop, ground, voxel grid, outliers,
//! largest cluster, sampling to N_p) with the filters switched on by the first byte (the voxel grid
//! by the length: on when 6 or more bytes are left over after the points; the cluster radius grown
//! with range, and every candidate object prepared too, when an odd number is). Farthest point
//! sampling is also checked against its plain loop: the bucketed one must choose the same points.
#![no_main]

use gdvae_node::cloud::{drop_implausible, Frame, PointCloud, Unit};
use gdvae_node::config::{OutlierMethod, PrepareSettings};
use gdvae_node::prepare::{farthest_point_sampling, farthest_point_sampling_plain, Preparer, Sampling};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&switches, body)) = data.split_first() else { return };
    let mut points: Vec<[f32; 3]> = body
        .chunks_exact(12)
        .take(20_000)
        .map(|c| {
            let f = |i: usize| f32::from_le_bytes(c[i..i + 4].try_into().unwrap());
            [f(0), f(4), f(8)]
        })
        .collect();
    drop_implausible(&mut points, Unit::Metre);
    if (switches >> 5) & 3 == 0 {
        let bits = |p: Vec<[f32; 3]>| p.iter().map(|q| q.map(f32::to_bits)).collect::<Vec<_>>();
        let seed = switches as u64;
        assert_eq!(
            bits(farthest_point_sampling(&points, 64, seed)),
            bits(farthest_point_sampling_plain(&points, 64, seed)),
            "bucketed and plain farthest point sampling differ"
        );
    }
    let mut settings = PrepareSettings::default();
    settings.remove_ground = switches & 1 != 0;
    settings.auto_ground = switches & 2 != 0;
    settings.outliers.method = match (switches >> 2) & 3 {
        0 => OutlierMethod::None,
        1 => OutlierMethod::Statistical,
        _ => OutlierMethod::Radius,
    };
    settings.cluster_m = if switches & 16 != 0 { 0.05 } else { 0.0 };
    settings.voxel_grid_m = if body.len() % 12 >= 6 { 0.02 } else { 0.0 };
    let several = body.len() % 2 == 1;
    settings.cluster_stretch_from_m = if several { 0.5 } else { 0.0 };
    settings.sampling = match (switches >> 5) & 3 {
        0 => Sampling::Farthest,
        1 => Sampling::Random,
        _ => Sampling::Voxel,
    };
    settings.ransac_iterations = 10;
    if switches & 128 != 0 {
        settings.crop = Some([-1.0, -1.0, 0.0, 1.0, 1.0, 2.0]);
    }
    let preparer = Preparer::new(&settings, 64, 2.0);
    let frame = Frame {
        stream: "fuzz".into(),
        sequence: 0,
        sensor_stamp_ns: None,
        ingested: std::time::Instant::now(),
        ingest_unix_ns: 0,
        unit: Unit::Metre,
        cloud: PointCloud { points },
        sensor_frame: None,
    };
    if let Ok(prepared) = preparer.prepare(&frame) {
        assert_eq!(prepared.points.len(), 64);
        assert!(prepared.points.iter().flatten().all(|c| c.is_finite()), "prepared points are finite");
    }
    if several {
        for prepared in preparer.prepare_all(&frame, 2.5, 4).unwrap_or_default() {
            assert_eq!(prepared.points.len(), 64);
            assert!(prepared.position_m.iter().all(|c| c.is_finite()), "positions are finite");
        }
    }
});
