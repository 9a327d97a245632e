//! How well the node's candidate detection (`Preparer::prepare_all`, issue 34) finds the subjects
//! of multi-subject sim recordings (`sim record --others ...`): per frame, each subject the camera
//! sees (at least `--min-visible` of the cloud's points on it) is matched to at most one candidate
//! whose centre lies within `--match-m` of it on the ground plane (least total distance). Prints
//! found / missed subjects (split by whether another subject stood within 1 m: two subjects in
//! one cluster), and candidates that match no subject.
//!
//!     cargo run --release --example detection -- REC.mcap... [--crop-half-m 2.5] [--match-m 0.5]
//!         [--min-visible 100] [--cluster-m M] [--stretch-from M] [--min-points N]
//!
//! Settings: config/replay.toml's [prepare] with its crop widened to +-crop-half-m around the
//! stage and the recording's own sensor pose; candidates at most 2.5 m a side, at most 6.

use std::path::Path;

use gdvae_node::cloud::{Frame, PointCloud, Unit};
use gdvae_node::config::Config;
use gdvae_node::evaluate::truth::WorldFromCamera;
use gdvae_node::prepare::Preparer;
use gdvae_node::sources::ros2::decode_point_cloud2;
use gdvae_node::track::association::assign;

/// Distance on the ground plane between two points' x, y.
fn ground_distance(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// A candidate's centre on the ground plane.
fn ground(centre: [f32; 3]) -> [f64; 2] {
    [centre[0] as f64, centre[1] as f64]
}

fn main() -> anyhow::Result<()> {
    let mut files = Vec::new();
    let (mut crop_half, mut match_m, mut min_visible) = (2.5f32, 0.5f64, 100u64);
    let (mut cluster_m, mut stretch_from, mut min_points) = (None, None, None);
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut value = |name: &str| -> anyhow::Result<String> {
            args.next().ok_or_else(|| anyhow::anyhow!("{name} needs a value"))
        };
        match arg.as_str() {
            "--crop-half-m" => crop_half = value("--crop-half-m")?.parse()?,
            "--match-m" => match_m = value("--match-m")?.parse()?,
            "--min-visible" => min_visible = value("--min-visible")?.parse()?,
            "--cluster-m" => cluster_m = Some(value("--cluster-m")?.parse()?),
            "--stretch-from" => stretch_from = Some(value("--stretch-from")?.parse()?),
            "--min-points" => min_points = Some(value("--min-points")?.parse()?),
            _ => files.push(arg),
        }
    }
    anyhow::ensure!(
        !files.is_empty(),
        "usage: detection REC.mcap... [--crop-half-m M] [--match-m M] [--min-visible N] [--cluster-m M] [--stretch-from M] [--min-points N]"
    );
    let config = Config::load(Path::new("config/replay.toml"))?;
    let mut settings = config.prepare.clone();
    settings.cluster_m = cluster_m.unwrap_or(settings.cluster_m);
    settings.cluster_stretch_from_m = stretch_from.unwrap_or(settings.cluster_stretch_from_m);
    settings.min_points = min_points.unwrap_or(settings.min_points);
    if let Some(crop) = settings.crop.as_mut() {
        crop[0] = -crop_half;
        crop[1] = -crop_half;
        crop[3] = crop_half;
        crop[4] = crop_half;
    }
    let (mut spurious_near, mut spurious_points) = (0usize, Vec::new());
    let (mut visible, mut found, mut missed_close, mut missed_apart, mut spurious, mut candidates, mut frames) =
        (0usize, 0usize, 0usize, 0usize, 0usize, 0usize, 0usize);
    for file in &files {
        let bytes = std::fs::read(file)?;
        let (mut clouds, mut truths) = (Vec::new(), Vec::new());
        for message in mcap::MessageStream::new(&bytes)? {
            let message = message?;
            match message.channel.topic.as_str() {
                "/camera/depth/points" => clouds.push(decode_point_cloud2(&message.data, 1 << 22)?),
                "/sim/ground_truth" => truths.push(serde_json::from_slice::<serde_json::Value>(&message.data)?),
                _ => {}
            }
        }
        let pose: WorldFromCamera = serde_json::from_value(truths[0]["world_from_camera"].clone())?;
        settings.sensor_to_gravity_rotation = pose.rotation_rows();
        settings.sensor_to_gravity_translation = pose.translation.map(|v| v as f32);
        let preparer = Preparer::new(&settings, 256, 1.0);
        for (sequence, (cloud, truth)) in clouds.into_iter().zip(&truths).enumerate() {
            frames += 1;
            let frame = Frame {
                stream: "sim".into(),
                sequence: sequence as u64,
                sensor_stamp_ns: None,
                ingested: std::time::Instant::now(),
                ingest_unix_ns: 0,
                unit: Unit::Metre,
                cloud: PointCloud { points: cloud.points },
                sensor_frame: None,
            };
            let found_here = preparer.prepare_all(&frame, 2.5, 6).unwrap_or_default();
            candidates += found_here.len();
            let subjects: Vec<[f64; 2]> = truth["subjects"]
                .as_array()
                .into_iter()
                .flatten()
                .filter(|s| s["visible_points"].as_u64().unwrap_or(0) >= min_visible)
                .map(|s| {
                    [
                        s["translation"][0].as_f64().unwrap_or(0.0),
                        s["translation"][1].as_f64().unwrap_or(0.0),
                    ]
                })
                .collect();
            visible += subjects.len();
            let cost: Vec<Vec<f64>> = subjects
                .iter()
                .map(|s| {
                    found_here
                        .iter()
                        .map(|c| {
                            let d = ground_distance(ground(c.centre_m), *s);
                            if d <= match_m {
                                d
                            } else {
                                f64::INFINITY
                            }
                        })
                        .collect()
                })
                .collect();
            let pairs = assign(&cost);
            found += pairs.len();
            spurious += found_here.len() - pairs.len();
            for (c, candidate) in found_here.iter().enumerate() {
                if pairs.iter().any(|(_, k)| *k == c) {
                    continue;
                }
                let nearest = subjects
                    .iter()
                    .map(|s| ground_distance(ground(candidate.centre_m), *s))
                    .fold(f64::INFINITY, f64::min);
                if nearest < 1.0 {
                    spurious_near += 1;
                }
                spurious_points.push(candidate.points_kept);
            }
            for (i, s) in subjects.iter().enumerate() {
                if pairs.iter().any(|(r, _)| *r == i) {
                    continue;
                }
                let close = subjects
                    .iter()
                    .enumerate()
                    .any(|(j, o)| j != i && ground_distance(*o, *s) < 1.0);
                if close {
                    missed_close += 1;
                } else {
                    missed_apart += 1;
                }
            }
        }
    }
    println!(
        "{frames} frames, {visible} visible subjects: found {found} ({:.1} %), missed {missed_close} beside another \
         subject (< 1 m) and {missed_apart} apart; {candidates} candidates, {spurious} matching no subject",
        100.0 * found as f64 / visible.max(1) as f64
    );
    spurious_points.sort_unstable();
    let quantile = |q: f64| {
        spurious_points
            .get((q * spurious_points.len() as f64) as usize)
            .copied()
            .unwrap_or(0)
    };
    println!(
        "candidates matching no subject: {spurious_near} within 1 m of a subject (a part of it); points kept \
         median {} (p10 {}, p90 {})",
        quantile(0.5),
        quantile(0.1),
        quantile(0.9)
    );
    println!(
        "command: cargo run --release --example detection -- {} --crop-half-m {crop_half} --match-m {match_m} \
         --min-visible {min_visible} --cluster-m {} --stretch-from {} --min-points {}",
        files.join(" "),
        settings.cluster_m,
        settings.cluster_stretch_from_m,
        settings.min_points
    );
    Ok(())
}
