//! Where decode and prepare spend a frame's CPU, with nothing else running: the replay
//! benchmark's CPU table (`gdvae-node replay`) measures the same steps inside the running node,
//! where ONNX Runtime's threads share the cores and move the figures by a fifth from run to run;
//! this harness runs them alone on one thread, so that a change to one step shows.
//!
//!     cargo run --release --example prepare_steps -- REC.mcap... [--passes 5] [--config config/replay.toml]
//!
//! Decode: the recording's `/camera/depth/points` (the sim's topic) walked as a replay walks it
//! (the MCAP reader with zstd, PointCloud2 decoding), every pass. Prepare:
//! `Preparer::prepare_measured` on every decoded frame, every pass, with `[prepare]` from the
//! config and N_p from its bundle. Decompress: the MCAP files' zstd chunks alone, each in one call
//! into a buffer kept from chunk to chunk (the floor of decode for a compressed recording, and what
//! a one-shot decompression would cost against the reader's streaming one). Prints CPU ms a frame (this
//! thread's clock), the median pass of each, and a digest of the prepared points (two builds that
//! prepare every frame alike print the same).

use std::path::PathBuf;

use gdvae_node::bundle::Bundle;
use gdvae_node::cloud::{Frame, PointCloud, Unit};
use gdvae_node::config::Config;
use gdvae_node::cpu::ThreadLap;
use gdvae_node::prepare::{Preparer, STEPS};
use gdvae_node::sources::recording::mcap::check_chunk_header;
use gdvae_node::sources::recording::{for_each_message, recording_files};
use gdvae_node::sources::ros2::decode_point_cloud2;

const TOPIC: &str = "/camera/depth/points";

fn main() -> anyhow::Result<()> {
    let (mut files, mut passes, mut config) = (Vec::new(), 5usize, PathBuf::from("config/replay.toml"));
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--passes" => {
                passes = args
                    .next()
                    .ok_or_else(|| anyhow::anyhow!("--passes needs a value"))?
                    .parse()?
            }
            "--config" => {
                config = args
                    .next()
                    .ok_or_else(|| anyhow::anyhow!("--config needs a value"))?
                    .into()
            }
            _ => files.push(PathBuf::from(arg)),
        }
    }
    anyhow::ensure!(
        !files.is_empty() && passes > 0,
        "usage: prepare_steps REC.mcap... [--passes N] [--config FILE]"
    );
    let config = Config::load(&config)?;
    let bundle = Bundle::load(&config.model.bundle)?;
    let preparer = Preparer::new(
        &config.prepare,
        bundle.manifest.sizes.points,
        bundle.manifest.units.model_units_per_metre as f32,
    );

    let mut frames: Vec<Frame> = Vec::new();
    let mut decode_ms = Vec::new();
    for pass in 0..passes {
        let mut clock = ThreadLap::start();
        let mut decoded = 0usize;
        for path in &files {
            for file in recording_files(path)? {
                for_each_message(&file, &[TOPIC], |message| {
                    let cloud = decode_point_cloud2(&message.data, 1 << 22).expect("a PointCloud2");
                    decoded += 1;
                    if pass == 0 {
                        frames.push(Frame {
                            stream: "bench".into(),
                            sequence: frames.len() as u64,
                            sensor_stamp_ns: Some(cloud.header.stamp_ns),
                            ingested: std::time::Instant::now(),
                            ingest_unix_ns: 0,
                            unit: Unit::Metre,
                            cloud: PointCloud { points: cloud.points },
                            sensor_frame: None,
                        });
                    }
                    true
                })?;
            }
        }
        anyhow::ensure!(decoded > 0, "no {TOPIC} messages in {files:?}");
        decode_ms.push(clock.lap() as f64 * 1e-6 / decoded as f64);
    }
    let mcaps = files
        .iter()
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .map(std::fs::read)
        .collect::<Result<Vec<_>, _>>()?;
    let mut decompress_ms = Vec::new();
    for _ in 0..passes {
        let mut clock = ThreadLap::start();
        let mut chunks = 0usize;
        for bytes in &mcaps {
            chunks += decompress_chunks(bytes)?;
        }
        let ns = clock.lap();
        if chunks > 0 {
            decompress_ms.push(ns as f64 * 1e-6 / frames.len() as f64);
        }
    }
    let mut steps_ms: Vec<Vec<f64>> = vec![Vec::new(); STEPS.len()];
    let (mut kept, mut digest) = (0usize, 0u64);
    for _ in 0..passes {
        let mut cpu = [0u64; STEPS.len()];
        (kept, digest) = (0, 0xcbf2_9ce4_8422_2325);
        for frame in &frames {
            if let Ok(prepared) = preparer.prepare_measured(frame, &mut cpu) {
                kept += prepared.points_kept;
                // FNV-1a over the bits of every point the encoder would see: two builds prepare
                // the same frames alike exactly when their digests agree.
                for c in prepared.points.iter().flatten() {
                    digest = (digest ^ c.to_bits() as u64).wrapping_mul(0x100_0000_01b3);
                }
            }
        }
        for (step, ns) in steps_ms.iter_mut().zip(cpu) {
            step.push(ns as f64 * 1e-6 / frames.len() as f64);
        }
    }
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let points = frames.iter().map(|f| f.cloud.points.len()).sum::<usize>() / frames.len();
    println!(
        "{} frames ({} points a frame, {} kept before sampling; prepared points' digest {digest:016x}), {passes} passes; CPU ms a frame, median pass",
        frames.len(),
        points,
        kept / frames.len()
    );
    println!("  {:<20} {:.3}", "decode", median(&mut decode_ms));
    if !decompress_ms.is_empty() {
        println!(
            "  {:<20} {:.3}   of decode: the zstd chunks alone, one call a chunk",
            "decode.decompress",
            median(&mut decompress_ms)
        );
    }
    let mut prepare = 0.0;
    for (name, ms) in STEPS.iter().zip(steps_ms.iter_mut()) {
        let ms = median(ms);
        prepare += ms;
        println!("  {name:<20} {ms:.3}");
    }
    println!("  {:<20} {prepare:.3}", "prepare (sum)");
    Ok(())
}

/// Decompresses every zstd chunk of an MCAP file in one call each, into one buffer kept from chunk
/// to chunk; returns how many chunks it decompressed (uncompressed chunks are skipped).
fn decompress_chunks(bytes: &[u8]) -> anyhow::Result<usize> {
    use mcap::sans_io::{LinearReadEvent, LinearReader, LinearReaderOptions};
    const OP_CHUNK: u8 = 0x06;
    let mut reader = LinearReader::new_with_options(LinearReaderOptions::default().with_emit_chunks(true));
    let mut zstd = zstd::bulk::Decompressor::new()?;
    let (mut out, mut at, mut chunks) = (Vec::new(), 0usize, 0usize);
    while let Some(event) = reader.next_event() {
        match event? {
            LinearReadEvent::ReadRequest(wanted) => {
                let n = wanted.min(bytes.len() - at);
                if n == 0 {
                    break;
                }
                reader.insert(n).copy_from_slice(&bytes[at..at + n]);
                reader.notify_read(n);
                at += n;
            }
            LinearReadEvent::Record { data, opcode } if opcode == OP_CHUNK => {
                let (size, compression, records_len, at) =
                    check_chunk_header(data).map_err(|e| anyhow::anyhow!("a chunk: {e}"))?;
                let records = data
                    .get(at..at + records_len as usize)
                    .ok_or_else(|| anyhow::anyhow!("a chunk cut short"))?;
                if compression == "zstd" {
                    out.clear();
                    out.reserve(size as usize);
                    zstd.decompress_to_buffer(records, &mut out)?;
                    chunks += 1;
                }
            }
            LinearReadEvent::Record { .. } => {}
        }
    }
    Ok(chunks)
}
