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
