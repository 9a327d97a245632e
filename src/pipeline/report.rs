//! What a run shows a person: the report `run` and `replay` print at the end (or as JSON), and
//! the live line per state of `run --live-summary`, read back from the node's own publications.

use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use zenoh::Wait;

use super::{RunOptions, RunSummary};
use crate::benchmark::EncoderAlone;
use crate::bundle::Bundle;
use crate::config::Config;
use crate::state::State;
use crate::stats::{peak_memory_mib, Stats, STAGES};

/// `run --live-summary`: a readable line per state on stdout, read back from the node's own
/// zenoh publications (so it shows exactly what subscribers get).
pub fn run_with_live_summary(
    config: &Config,
    bundle: &Bundle,
    session: Option<zenoh::Session>,
    stop: Arc<AtomicBool>,
    stats: Arc<Stats>,
    options: RunOptions,
) -> anyhow::Result<RunSummary> {
    let Some(session) = session.filter(|_| config.publish.zenoh) else {
        anyhow::bail!("--live-summary reads the node's zenoh states; enable publish.zenoh");
    };
    let subscriber = session
        .declare_subscriber(config.state_key("*"))
        .callback(|sample| {
            let Ok(state) = serde_json::from_slice::<State>(&sample.payload().to_bytes()) else {
                return;
            };
            let event = state
                .event
                .as_ref()
                .map(|e| format!("  << identity {} -> {}", e.previous, e.identity))
                .unwrap_or_default();
            println!(
                "{:<12} #{:<5} identity {} ({}{} fused, conf {:.2})  yaw {:>7.1} deg  z_E[0..3] {:>6.2} {:>6.2} {:>6.2}  {:>5.1} ms{event}",
                state.stream,
                state.sequence,
                state.shape.identity,
                if state.shape.inlier { "" } else { "outlier, " },
                state.shape.frames_fused,
                state.shape.confidence,
                state.filtered.yaw.to_degrees(),
                state.filtered.z_e.first().copied().unwrap_or(0.0),
                state.filtered.z_e.get(1).copied().unwrap_or(0.0),
                state.filtered.z_e.get(2).copied().unwrap_or(0.0),
                state.latency.total_ms,
            );
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("zenoh: {e}"))?;
    let summary = super::run(config, bundle, Some(session), stop, stats, options)?;
    std::thread::sleep(std::time::Duration::from_millis(200));
    drop(subscriber);
    Ok(summary)
}

/// Where a frame's CPU time went: each measured stage and prepare step (`encode` is the encode
/// threads' own clocks around the encoder's runs: all of ONNX Runtime's work where a session runs
/// on one thread, as `config/replay.toml` sets), the rest of the process (ONNX Runtime's own
/// threads, batching, the channels), and what everything around the encoder costs: against the
/// encode threads of the same run, and against ONNX Runtime alone on the same bundle.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CpuPerFrame {
    /// Frames received (states and rejections): what every figure is divided by.
    pub frames: u64,
    /// Milliseconds of CPU per frame by stage, in pipeline order.
    pub stages_ms: Vec<(String, f64)>,
    /// The process's CPU per frame from the first ingest to the last publish, all threads.
    pub process_ms: f64,
    /// The process less the measured stages: ONNX Runtime's own threads, batching, channels.
    pub rest_ms: f64,
    /// The process less the encode threads, and that as a multiple of theirs: what the node spends
    /// around its encoder in the same run (with one thread a session, the encode threads hold all
    /// of ONNX Runtime's work).
    pub around_encode_ms: Option<f64>,
    pub around_encode_ratio: Option<f64>,
    /// ONNX Runtime alone's CPU per frame (same bundle, batch, yaw copies and threads).
    pub encoder_alone_ms: Option<f64>,
    /// The process less ONNX Runtime alone: what the node spends around its model, and that as a
    /// multiple of the encoder's own CPU.
    pub around_encoder_ms: Option<f64>,
    pub around_encoder_ratio: Option<f64>,
}

/// The CPU table of a run (and of ONNX Runtime alone, when measured).
pub fn cpu_per_frame(summary: &RunSummary, baseline: Option<&EncoderAlone>) -> CpuPerFrame {
    let s = &summary.snapshot;
    let frames = s.streams.values().map(|c| c.received).sum::<u64>();
    let per_frame = |ns: f64| ns * 1e-6 / frames.max(1) as f64;
    let order = ["decode"]
        .into_iter()
        .chain(crate::prepare::STEPS)
        .chain(["encode", "track", "publish"]);
    let stages_ms: Vec<(String, f64)> = order
        .filter_map(|stage| s.cpu.get(stage).map(|a| (stage.to_string(), per_frame(a.ns as f64))))
        .collect();
    let process_ms = per_frame(summary.busy_cpu.as_nanos() as f64);
    let measured: f64 = stages_ms.iter().map(|(_, ms)| ms).sum();
    let encoder_alone_ms = baseline
        .filter(|b| b.frames > 0)
        .map(|b| b.cpu_seconds * 1e3 / b.frames as f64);
    let around_encoder_ms = encoder_alone_ms.map(|e| process_ms - e);
    let encode_ms = stages_ms
        .iter()
        .find(|(stage, _)| stage == "encode")
        .map(|(_, ms)| *ms)
        .filter(|ms| *ms > 0.0);
    CpuPerFrame {
        frames,
        process_ms,
        rest_ms: process_ms - measured,
        around_encode_ms: encode_ms.map(|e| process_ms - e),
        around_encode_ratio: encode_ms.map(|e| (process_ms - e) / e),
        stages_ms,
        encoder_alone_ms,
        around_encoder_ms,
        around_encoder_ratio: encoder_alone_ms
            .zip(around_encoder_ms)
            .filter(|(e, _)| *e > 0.0)
            .map(|(e, a)| a / e),
    }
}

/// A run's report as `run` and `replay` print it: per stream counts, per stage latency, throughput,
/// against ONNX Runtime alone when `baseline` is given, peak memory and the host's CPU steal; or
/// the same as one JSON document (`json`).
pub fn print_report(
    summary: &RunSummary,
    baseline: Option<(&EncoderAlone, &Config)>,
    steal_s: Option<f64>,
    json: bool,
) -> serde_json::Result<()> {
    let s = &summary.snapshot;
    let published: u64 = s.streams.values().map(|c| c.published).sum();
    let rejected: u64 = s.streams.values().map(|c| c.rejected.values().sum::<u64>()).sum();
    let wall = summary.busy.as_secs_f64().max(1e-9);
    let throughput = published as f64 / wall;
    let memory = peak_memory_mib();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get()) as f64;
    // The share of the run's CPU time (all cores) that the host took: its latency tail's context.
    let steal_share = steal_s.map(|steal| steal / (summary.wall.as_secs_f64().max(1e-9) * cores));
    let cpu = cpu_per_frame(summary, baseline.map(|(b, _)| b));
    if json {
        let report = serde_json::json!({
            "wall_s": summary.wall.as_secs_f64(),
            "busy_s": wall,
            "states": published,
            "rejected": rejected,
            "throughput_fps": throughput,
            "peak_memory_mib": memory,
            "host_cpu_steal_s": steal_s,
            "host_cpu_steal_share": steal_share,
            "counters": s,
            "encoder_alone": baseline.map(|(b, _)| b),
            "throughput_vs_encoder_alone": baseline.map(|(b, _)| throughput / b.frames_per_second),
            "cpu_per_frame": cpu,
        });
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!("streams:");
    for (name, c) in &s.streams {
        println!(
            "  {name:<16} {:>6} received {:>6} published {:>4} dropped {:>4} rejected {:?}{}",
            c.received,
            c.published,
            c.dropped,
            c.rejected.values().sum::<u64>(),
            c.rejected,
            if c.publish_errors > 0 {
                format!(" {} publish errors", c.publish_errors)
            } else {
                String::new()
            } + &if c.feed_gaps > 0 {
                format!(" {} feed gap(s), {:.1} s silent", c.feed_gaps, c.feed_gap_s)
            } else {
                String::new()
            }
        );
        if c.tracks_born + c.frames_untracked > 0 {
            println!(
                "  {:<16} tracks: {} born, {} re-identified, {} ended; {} frame(s) with no confirmed track",
                "", c.tracks_born, c.tracks_reidentified, c.tracks_ended, c.frames_untracked
            );
        }
    }
    for (stream, reason) in &summary.failed_sources {
        println!("  {stream:<16} (optional) {reason}");
    }
    println!("latency (ms)      count     mean      p50      p90      p99      max");
    for stage in STAGES {
        if let Some(l) = s.stages.get(stage) {
            println!(
                "  {stage:<12} {:>8} {:>8.2} {:>8.2} {:>8.2} {:>8.2} {:>8.2}",
                l.count, l.mean_ms, l.p50_ms, l.p90_ms, l.p99_ms, l.max_ms
            );
        }
    }
    println!(
        "throughput: {published} states in {wall:.2} s from first ingest to last publish = {throughput:.1} frames/s \
         (mean batch {:.2}, {rejected} rejected; {:.2} s with start-up)",
        s.mean_batch,
        summary.wall.as_secs_f64()
    );
    if let Some((b, config)) = baseline {
        println!(
            "ONNX Runtime alone (batch {}, {} yaw copies, {} worker(s) x {} thread(s)): {:.1} frames/s -> pipeline at {:.0} % of it",
            config.model.max_batch,
            config.model.yaw_copies,
            config.model.workers,
            config.model.threads,
            b.frames_per_second,
            100.0 * throughput / b.frames_per_second
        );
    }
    print_cpu(&cpu);
    if let Some(mib) = memory {
        println!("peak memory (VmHWM): {mib:.1} MiB");
    }
    if let (Some(steal), Some(share)) = (steal_s, steal_share) {
        println!(
            "host CPU steal during the run: {steal:.2} s ({:.1} % of {cores} cores' time){}",
            100.0 * share,
            if share > 0.002 {
                ": the hypervisor ran other work on these cores; latency tails are not the node's alone"
            } else {
                ""
            }
        );
    }
    Ok(())
}

fn print_cpu(cpu: &CpuPerFrame) {
    if cpu.frames == 0 {
        return;
    }
    println!("CPU per frame (ms, each thread's own clock; {} frames)", cpu.frames);
    for (stage, ms) in &cpu.stages_ms {
        println!("  {stage:<18} {ms:>7.3}");
    }
    println!(
        "  {:<18} {:>7.3}   the process less the above: ONNX Runtime's own threads, batching, channels",
        "rest", cpu.rest_ms
    );
    println!(
        "  {:<18} {:>7.3}   all threads, first ingest to last publish",
        "process", cpu.process_ms
    );
    if let (Some(around), Some(ratio)) = (cpu.around_encode_ms, cpu.around_encode_ratio) {
        println!(
            "  around the encode threads: {around:.3} ms a frame, {ratio:.2}x their CPU (this run; all of ONNX Runtime's work with threads = 1)"
        );
    }
    if let (Some(encoder), Some(around), Some(ratio)) =
        (cpu.encoder_alone_ms, cpu.around_encoder_ms, cpu.around_encoder_ratio)
    {
        println!(
            "  ONNX Runtime alone {encoder:>7.3}   -> around the encoder: {around:.3} ms a frame, {ratio:.2}x the encoder's CPU"
        );
    }
}
