//! CDR decoding: the sim's recorded PointCloud2 (an independent writer: the sim's own CDR code,
//! read back through the mcap crate), other field layouts, and hostile payloads.

use gdvae_node::sources::ros2::{decode_point_cloud2, CdrError};

/// A PointCloud2 with fields (name, offset, datatype) written field by field, little-endian.
fn cloud2(fields: &[(&str, u32, u8)], point_step: u32, points: &[Vec<u8>], width: u32) -> Vec<u8> {
    let mut out = vec![0, 1, 0, 0];
    let align = |out: &mut Vec<u8>, n: usize| {
        while !(out.len() - 4).is_multiple_of(n) {
            out.push(0)
        }
    };
    let u32le = |out: &mut Vec<u8>, v: u32| {
        align(out, 4);
        out.extend_from_slice(&v.to_le_bytes())
    };
    let string = |out: &mut Vec<u8>, s: &str| {
        u32le(out, s.len() as u32 + 1);
        out.extend_from_slice(s.as_bytes());
        out.push(0)
    };
    u32le(&mut out, 7); // sec
    u32le(&mut out, 9); // nanosec
    string(&mut out, "frame");
    u32le(&mut out, 1);
    u32le(&mut out, width);
    u32le(&mut out, fields.len() as u32);
    for (name, offset, datatype) in fields {
        string(&mut out, name);
        u32le(&mut out, *offset);
        out.push(*datatype);
        u32le(&mut out, 1);
    }
    out.push(0);
    u32le(&mut out, point_step);
    u32le(&mut out, point_step * width);
    let data: Vec<u8> = points.concat();
    u32le(&mut out, data.len() as u32);
    out.extend_from_slice(&data);
    out.push(1);
    out
}

#[test]
fn any_field_layout_and_datatype() {
    // rgb first, then z (float64), padding, x and y (float32): point step 32.
    let point = |x: f32, y: f32, z: f64| {
        let mut p = vec![0u8; 32];
        p[0..4].copy_from_slice(&0xffu32.to_le_bytes());
        p[8..16].copy_from_slice(&z.to_le_bytes());
        p[20..24].copy_from_slice(&x.to_le_bytes());
        p[24..28].copy_from_slice(&y.to_le_bytes());
        p
    };
    let payload = cloud2(
        &[("rgb", 0, 6), ("z", 8, 8), ("x", 20, 7), ("y", 24, 7)],
        32,
        &[point(1.0, 2.0, 3.0), point(f32::NAN, 0.0, 0.0), point(-1.0, -2.0, -3.5)],
        3,
    );
    let cloud = decode_point_cloud2(&payload, 1000).unwrap();
    assert_eq!(cloud.header.stamp_ns, 7_000_000_009);
    assert_eq!(cloud.header.frame_id, "frame");
    assert_eq!(cloud.points, vec![[1.0, 2.0, 3.0], [-1.0, -2.0, -3.5]]);
    assert_eq!(cloud.dropped_non_finite, 1);
}

#[test]
fn truncated_and_hostile_payloads_are_errors() {
    let good = cloud2(&[("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12, &[vec![0; 12]], 1);
    for cut in [0, 3, 10, 30, good.len() - 5] {
        assert!(decode_point_cloud2(&good[..cut], 1000).is_err(), "cut at {cut}");
    }
    let billions = cloud2(
        &[("x", 0, 7), ("y", 4, 7), ("z", 8, 7)],
        12,
        &[vec![0; 12]],
        2_000_000_000,
    );
    let error = decode_point_cloud2(&billions, 1_000_000).unwrap_err();
    assert!(
        matches!(error, CdrError::Invalid(ref m) if m.contains("2000000000")),
        "{error}"
    );
    let no_z = cloud2(&[("x", 0, 7), ("y", 4, 7)], 8, &[vec![0; 8]], 1);
    assert!(decode_point_cloud2(&no_z, 1000).is_err());
    let overrun = cloud2(&[("x", 0, 7), ("y", 4, 7), ("z", 10, 7)], 12, &[vec![0; 12]], 1);
    assert!(decode_point_cloud2(&overrun, 1000).is_err());
    assert_eq!(
        decode_point_cloud2(&[7, 7, 0, 0, 1], 10).unwrap_err(),
        CdrError::Representation(0x0707)
    );
}

#[test]
fn the_sample_recording_decodes_to_its_ground_truth_point_counts() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("sim/samples/walk_switch.mcap");
    let bytes = std::fs::read(path).unwrap();
    let mut clouds = Vec::new();
    let mut counts = Vec::new();
    for message in mcap::MessageStream::new(&bytes).unwrap() {
        let message = message.unwrap();
        match message.channel.topic.as_str() {
            "/camera/depth/points" => clouds.push(decode_point_cloud2(&message.data, 1 << 22).unwrap()),
            "/sim/ground_truth" => {
                let truth: serde_json::Value = serde_json::from_slice(&message.data).unwrap();
                counts.push((
                    truth["stamp_nanos"].as_u64().unwrap(),
                    truth["points"].as_u64().unwrap() as usize,
                ));
            }
            _ => {}
        }
    }
    assert_eq!(clouds.len(), 150);
    for (cloud, (stamp, count)) in clouds.iter().zip(counts) {
        assert_eq!(cloud.header.stamp_ns, stamp);
        assert_eq!(cloud.points.len(), count);
        assert!(
            cloud.points.iter().all(|p| p[2] > 0.3),
            "optical-frame depths are positive"
        );
    }
}
