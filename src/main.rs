//! `gdvae-node`: the node's command line. Commands are thin wrappers over the library; errors are
//! reported once, here.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use gdvae_node::bundle::Bundle;
use gdvae_node::cloud::{Frame, PointCloud, Unit};
use gdvae_node::config::{Config, Format};
use gdvae_node::evaluate::EvaluateOptions;
use gdvae_node::pipeline::{self, RunOptions, RunSummary};
use gdvae_node::prepare::{Preparer, Sampling};
use gdvae_node::runtime::{loaded_library, Encoder};
use gdvae_node::sources::files::{read_cloud, FileOptions};
use gdvae_node::stats::{cpu_steal_seconds, peak_memory_mib, Stats, STAGES};
use gdvae_node::zenoh_session::open_session;

#[derive(Parser)]
#[command(
    name = "gdvae-node",
    version,
    about = "Point-cloud frames -> GDVAE++ rotation, pose and shape codes, tracked over time, published over zenoh"
)]
struct Cli {
    /// More log output (-v: debug). RUST_LOG overrides.
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    verbose: u8,
    /// Only warnings and errors.
    #[arg(short, long, global = true)]
    quiet: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the node as configured until SIGINT/SIGTERM (or until every replayed source has ended).
    Run(RunArgs),
    /// Offline replay benchmark: every frame of the recordings or point-cloud files, as fast as
    /// possible, losslessly; prints throughput and latency percentiles per stage, peak memory,
    /// and ONNX Runtime alone on the same bundle, batch and threads for comparison.
    Replay(ReplayArgs),
    /// Tracking measured against ground truth: replays sim recordings (their `/sim/ground_truth`
    /// channel) through the pipeline and reports heading and position errors, identity changes
    /// found (recall, false changes, delay) and identity retrieval, per recording and overall.
    Evaluate(EvaluateArgs),
    /// Encode one point-cloud file (PLY, PCD, OBJ, XYZ/CSV) and print the codes as JSON.
    Encode(EncodeArgs),
    /// Parse and validate a config; check its bundle, ONNX Runtime and sources.
    CheckConfig {
        #[arg(default_value = "config/default.toml")]
        config: PathBuf,
    },
    /// Check a bundle (manifest, sizes, units, file hashes) and print what it contains.
    InspectModel {
        bundle: PathBuf,
        /// Also load the encoder in ONNX Runtime.
        #[arg(long)]
        load: bool,
        #[arg(long)]
        onnxruntime: Option<PathBuf>,
    },
}

#[derive(clap::Args)]
struct RunArgs {
    #[arg(long, default_value = "config/default.toml")]
    config: PathBuf,
    /// Print one line per published state (stream, sequence, identity, yaw, latency); JSON lines
    /// and the periodic summary are then off.
    #[arg(long)]
    live_summary: bool,
}

#[derive(clap::Args)]
struct ReplayArgs {
    /// MCAP files, rosbag2 bags (folders or .db3 files), point-cloud files or folders; one stream each.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Settings to start from (sources in it are ignored).
    #[arg(long)]
    config: Option<PathBuf>,
    #[arg(long)]
    bundle: Option<PathBuf>,
    /// Replay speed: 0 = as fast as possible, 1 = original timing (e.g. a 30 Hz feed).
    #[arg(long, default_value_t = 0.0)]
    speed: f64,
    /// Also publish on zenoh (default: no network, JSON lines only if --jsonl).
    #[arg(long)]
    zenoh: bool,
    /// Write every state as a JSON line to this file ("-": stdout).
    #[arg(long)]
    jsonl: Option<String>,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
    /// Skip the ONNX-Runtime-alone comparison.
    #[arg(long)]
    no_baseline: bool,
}

#[derive(clap::Args)]
struct EvaluateArgs {
    /// Sim recordings (MCAP files or rosbag2 bags); one stream each.
    #[arg(required = true)]
    recordings: Vec<PathBuf>,
    /// Settings to start from (its sources and publishing are replaced; the crop, model and
    /// track settings are used).
    #[arg(long, default_value = "config/replay.toml")]
    config: PathBuf,
    #[arg(long)]
    bundle: Option<PathBuf>,
    /// Override a track setting, e.g. `--set cusum_threshold=6` (repeatable; for tuning).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// A true identity change counts as found when reported within this many frames.
    #[arg(long, default_value_t = 10)]
    tolerance_frames: usize,
    /// Keep the config's sensor pose instead of the recording's `world_from_camera`.
    #[arg(long)]
    keep_sensor_pose: bool,
    /// Write the report as JSON to this file ("-": stdout, instead of the table).
    #[arg(long)]
    out: Option<String>,
    /// Write one PNG per recording into this folder.
    #[arg(long)]
    plots: Option<PathBuf>,
    /// Write every published state as a JSON line with the ground truth it was matched to
    /// (`{"state": ..., "truth": ...}`; truth null when unmatched), for studying the raw streams.
    #[arg(long)]
    states: Option<PathBuf>,
}

#[derive(clap::Args)]
struct EncodeArgs {
    file: PathBuf,
    /// Settings (prepare, model); default: config/default.toml's defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Model bundle folder (overrides the config's).
    #[arg(long)]
    bundle: Option<PathBuf>,
    /// Unit of the file's coordinates.
    #[arg(long, value_enum, default_value = "metre")]
    unit: UnitArg,
    #[arg(long, value_enum)]
    sampling: Option<SamplingArg>,
    /// ONNX Runtime library (default: ORT_DYLIB_PATH, then the .venv onnxruntime wheel).
    #[arg(long)]
    onnxruntime: Option<PathBuf>,
    #[arg(long)]
    seed: Option<u64>,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum UnitArg {
    Metre,
    Millimetre,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum SamplingArg {
    Farthest,
    Random,
    Voxel,
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let level = match (cli.quiet, cli.verbose) {
        (true, _) => "warn",
        (false, 0) => "info",
        (false, _) => "debug",
    };
    env_logger::Builder::from_env(
        env_logger::Env::default().default_filter_or(format!("warn,gdvae_node={level},gdvae_node::pipeline={level}")),
    )
    .format_target(false)
    .init();
    match run(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("gdvae-node: error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Run(args) => run_node(args),
        Command::Replay(args) => replay(args),
        Command::Evaluate(args) => evaluate(args),
        Command::Encode(args) => encode(args),
        Command::CheckConfig { config } => check_config(&config),
        Command::InspectModel {
            bundle,
            load,
            onnxruntime,
        } => inspect_model(&bundle, load, onnxruntime.as_deref()),
    }
}

/// `run`: the daemon, as its config says.
fn run_node(args: RunArgs) -> Result<()> {
    let mut config = Config::read(&args.config)?;
    if args.live_summary {
        // The live summary owns stdout: no JSON lines there, no periodic summary in between.
        if config.publish.jsonl.take().is_some() {
            log::warn!("--live-summary: [publish] jsonl is off for this run");
        }
        config.pipeline.summary_seconds = 0.0;
    }
    let config = validated(config, &args.config)?;
    if config.sources.is_empty() {
        bail!("the config has no [[source]]; nothing to run");
    }
    let summary = run_pipeline(&config, RunOptions::default(), args.live_summary)?;
    print_report(&summary, None, None, false)
}

/// `replay`: the inputs as fast as possible (or at `--speed`), every frame kept; the report.
fn replay(args: ReplayArgs) -> Result<()> {
    let (mut config, origin) = starting_config(args.config, args.bundle)?;
    config.sources = gdvae_node::sources::replay_sources(&args.inputs, args.speed);
    config.publish.zenoh = args.zenoh;
    config.publish.jsonl = args.jsonl;
    let config = validated(config, &origin)?;
    let options = RunOptions {
        lossless_publish: true,
        ..RunOptions::default()
    };
    let steal_before = cpu_steal_seconds();
    let summary = run_pipeline(&config, options, false)?;
    let steal = steal_before
        .zip(cpu_steal_seconds())
        .map(|(before, after)| after - before);
    let baseline = if args.no_baseline {
        None
    } else {
        let bundle = Bundle::load(&config.model.bundle)?;
        let frames = summary
            .snapshot
            .streams
            .values()
            .map(|s| s.published)
            .sum::<u64>()
            .max(64) as usize;
        Some(gdvae_node::benchmark::encoder_alone(&bundle, &config.model, frames)?)
    };
    print_report(&summary, baseline.as_ref().map(|b| (b, &config)), steal, args.json)?;
    require_states(&summary)
}

/// `encode`: one file through prepare and the encoder; the codes as JSON.
fn encode(args: EncodeArgs) -> Result<()> {
    let (mut config, origin) = starting_config(args.config, args.bundle)?;
    if let Some(sampling) = args.sampling {
        config.prepare.sampling = match sampling {
            SamplingArg::Farthest => Sampling::Farthest,
            SamplingArg::Random => Sampling::Random,
            SamplingArg::Voxel => Sampling::Voxel,
        };
    }
    if let Some(seed) = args.seed {
        config.prepare.seed = seed;
    }
    if let Some(library) = args.onnxruntime {
        config.model.onnxruntime = Some(library);
    }
    let config = validated(config, &origin)?;
    let file = args.file;
    let bundle = Bundle::load(&config.model.bundle)?;
    let mut read = read_cloud(&file, &FileOptions::default())?;
    let unit = match args.unit {
        UnitArg::Metre => Unit::Metre,
        UnitArg::Millimetre => Unit::Millimetre,
    };
    read.dropped_non_finite += gdvae_node::cloud::drop_implausible(&mut read.cloud.points, unit);
    let points_read = read.cloud.len();
    let frame = Frame {
        stream: "file".into(),
        sequence: 0,
        sensor_stamp_ns: None,
        ingested: std::time::Instant::now(),
        ingest_unix_ns: 0,
        unit,
        cloud: PointCloud {
            points: read.cloud.points,
        },
    };
    let preparer = Preparer::new(
        &config.prepare,
        bundle.manifest.sizes.points,
        bundle.manifest.units.model_units_per_metre as f32,
    );
    let prepared = preparer
        .prepare(&frame)
        .with_context(|| format!("{}", file.display()))?;
    let mut encoder = Encoder::load(
        &bundle,
        config.model.onnxruntime.as_deref(),
        config.model.threads,
        config.model.spin,
    )?
    .with_yaw_copies(config.model.yaw_copies);
    let encoding = encoder.encode(&[&prepared.points])?.remove(0);
    if !encoding.is_finite() {
        bail!("{}: the encoder's output is not finite", file.display());
    }
    let out = serde_json::json!({
        "file": file.display().to_string(),
        "points_read": points_read,
        "points_kept": prepared.points_kept,
        "dropped_non_finite": read.dropped_non_finite,
        "centre_m": prepared.centre_m,
        "yaw": gdvae_node::track::yaw_of(&encoding.q),
        "encoding": encoding,
    });
    println!("{}", serde_json::to_string_pretty(&out)?);
    Ok(())
}

/// `check-config`: everything a run checks before it starts, without running.
fn check_config(path: &Path) -> Result<()> {
    let config = Config::load(path)?;
    println!("{}: parsed and valid", path.display());
    let bundle = Bundle::load(&config.model.bundle)?;
    println!(
        "bundle {}: {} regime, N_p {}, hashes match",
        bundle.folder.display(),
        bundle.manifest.model.regime,
        bundle.manifest.sizes.points
    );
    Encoder::load(&bundle, config.model.onnxruntime.as_deref(), 1, false)?;
    println!(
        "ONNX Runtime: {}",
        loaded_library().map(|p| p.display().to_string()).unwrap_or_default()
    );
    let mut unusable = Vec::new();
    for source in &config.sources {
        match gdvae_node::sources::check(source) {
            Ok(found) => println!("source '{}': {found}", source.stream),
            Err(message) if source.optional => {
                println!("source '{}' (optional) cannot start: {message}", source.stream)
            }
            Err(message) => {
                println!("source '{}' cannot start: {message}", source.stream);
                unusable.push(source.stream.clone());
            }
        }
    }
    if !unusable.is_empty() {
        bail!("source(s) {} cannot start; `run` would fail", unusable.join(", "));
    }
    if config.publish.zenoh {
        println!(
            "publishing on {} (zenoh {}, {})",
            config.state_key("<stream>"),
            config.zenoh.mode,
            match config.publish.format {
                Format::Json => "JSON",
                Format::Cbor => "CBOR",
            }
        );
    }
    let ros2 = &config.publish.ros2;
    if ros2.enabled {
        println!(
            "publishing to ROS 2: node {}/{} in domain {}, topics {}",
            ros2.namespace.trim_end_matches('/'),
            ros2.node_name,
            ros2.domain_id,
            ros2.topic("<stream>", "{pose,markers,z_e,z_i,state,events,rejected}")
        );
    }
    Ok(())
}

/// `inspect-model`: a bundle's manifest, checked, and optionally its encoder loaded.
fn inspect_model(bundle: &Path, load: bool, onnxruntime: Option<&Path>) -> Result<()> {
    let bundle = Bundle::load(bundle)?;
    let m = &bundle.manifest;
    println!("bundle {} (schema {})", bundle.folder.display(), m.schema_version);
    println!(
        "model: {} regime, {} autoencoder, {}, recipe {}",
        m.model.regime, m.model.ae_type, m.model.supervision, m.model.recipe
    );
    let s = m.sizes;
    println!(
        "sizes: N_p {}, N_lambda {}, x_c {}, z_R {}, z_E {}, z_I {}",
        s.points, s.spectrum, s.x_c, s.z_r, s.z_e, s.z_i
    );
    println!(
        "units: {} model units per metre, {} centring, up {}, rotations {}",
        m.units.model_units_per_metre, m.units.centering, m.units.up_axis, m.units.rotation_mode
    );
    println!(
        "calibration: z_I variances x {} (1: none measured; see models/README, bundle format)",
        m.calibration.z_i_variance_scale
    );
    for key in ["S", "C_X", "d_C", "heading_error_median_deg"] {
        if let Some(value) = m.metrics.get(key).and_then(|v| v.as_f64()) {
            println!("metric {key}: {value:.4}");
        }
    }
    if load {
        let encoder = Encoder::load(&bundle, onnxruntime, 1, false)?;
        println!(
            "encoder {} loaded with ONNX Runtime from {}",
            encoder.file().display(),
            loaded_library().map(|p| p.display().to_string()).unwrap_or_default()
        );
    }
    Ok(())
}

/// `evaluate`: the recordings replayed through the pipeline, every state collected in process and
/// measured against the ground truth.
fn evaluate(args: EvaluateArgs) -> Result<()> {
    let (mut config, origin) = starting_config(Some(args.config), args.bundle)?;
    let options = EvaluateOptions {
        tolerance_frames: args.tolerance_frames,
        pose_from_truth: !args.keep_sensor_pose,
        ..EvaluateOptions::default()
    };
    config.track = track_overrides(&config.track, &args.set)?;
    let recordings = gdvae_node::evaluate::recordings(&args.recordings)?;
    for r in recordings.iter().filter(|r| r.truth.is_empty()) {
        log::warn!(
            "{}: no {} channel; reporting what needs no ground truth (identity changes, heading smoothness)",
            r.path.display(),
            gdvae_node::evaluate::truth::GROUND_TRUTH_TOPIC
        );
    }
    config.sources = gdvae_node::evaluate::sources(&recordings, &options);
    config.publish.zenoh = false;
    config.publish.jsonl = None;
    config.publish.ros2.enabled = false;
    let config = validated(config, &origin)?;
    let (out, plots) = (args.out.as_deref(), args.plots.as_deref());
    let (tx, rx) = crossbeam_channel::unbounded();
    let options_run = RunOptions {
        lossless_publish: true,
        collect: Some(tx),
    };
    let summary = run_pipeline(&config, options_run, false)?;
    require_states(&summary)?;
    let outputs: Vec<_> = rx.try_iter().collect();
    let report = gdvae_node::evaluate::report(&recordings, &outputs, &options);
    if let Some(path) = &args.states {
        write_matched_states(path, &gdvae_node::evaluate::matched_states(&recordings, &outputs))?;
    }
    if let Some(folder) = plots {
        let threshold = match config.track.change_detector {
            gdvae_node::config::ChangeDetector::Cusum => Some(config.track.cusum_threshold as f64),
            gdvae_node::config::ChangeDetector::Consecutive => None,
        };
        let written = gdvae_node::evaluate::write_plots(&report, folder, config.track.shape_gate as f64, threshold)?;
        eprintln!("evaluate: {} plot(s) in {}", written.len(), folder.display());
    }
    match out {
        Some("-") => println!("{}", serde_json::to_string_pretty(&report)?),
        Some(path) => {
            std::fs::write(path, serde_json::to_string_pretty(&report)?).with_context(|| format!("writing {path}"))?;
            print_evaluation(&report, &summary);
            eprintln!("evaluate: report in {path}");
        }
        None => print_evaluation(&report, &summary),
    }
    if report.overall.matched == 0 && report.overall.with_truth > 0 {
        bail!("no state matched any ground-truth frame by sensor stamp");
    }
    Ok(())
}

fn write_matched_states(path: &Path, states: &[gdvae_node::evaluate::MatchedState]) -> Result<()> {
    use std::io::Write;
    let file = std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    let mut out = std::io::BufWriter::new(file);
    for state in states {
        serde_json::to_writer(&mut out, state)?;
        out.write_all(b"\n")?;
    }
    out.flush().with_context(|| format!("writing {}", path.display()))?;
    eprintln!("evaluate: {} state(s) in {}", states.len(), path.display());
    Ok(())
}

/// `--set KEY=VALUE` over `[track]`, typed by the setting it replaces (unknown keys refused).
fn track_overrides(
    settings: &gdvae_node::config::TrackSettings,
    set: &[String],
) -> Result<gdvae_node::config::TrackSettings> {
    let mut table = toml::Table::try_from(settings).context("track settings")?;
    for item in set {
        let (key, value) = item
            .split_once('=')
            .with_context(|| format!("--set {item}: expected KEY=VALUE"))?;
        let key = key.trim().trim_start_matches("track.");
        let value: toml::Value = toml::from_str::<toml::Table>(&format!("v = {value}"))
            .or_else(|_| toml::from_str::<toml::Table>(&format!("v = {value:?}")))
            .with_context(|| format!("--set {item}: not a value"))?
            .remove("v")
            .unwrap_or(toml::Value::Boolean(false));
        if !table.contains_key(key) {
            bail!("--set {item}: [track] has no key '{key}'");
        }
        table.insert(key.to_string(), value);
    }
    let settings: gdvae_node::config::TrackSettings =
        table.try_into().context("--set: the track settings do not parse")?;
    settings.validate().map_err(anyhow::Error::msg)?;
    Ok(settings)
}

fn fmt_opt(value: Option<f64>, scale: f64, decimals: usize) -> String {
    value
        .map(|v| format!("{:.*}", decimals, v * scale))
        .unwrap_or_else(|| "-".into())
}

fn print_evaluation(report: &gdvae_node::evaluate::Report, summary: &RunSummary) {
    println!("convention: {}", report.convention);
    println!(
        "{:<22} {:>6} {:>5} | {:>23} | {:>23} | {:>10} | {:>14} {:>5} {:>6}",
        "recording",
        "frames",
        "rej",
        "yaw raw med/p90/>30%",
        "yaw filt med/p90/>30%",
        "pos med m",
        "changes found",
        "false",
        "delay"
    );
    let angles = |a: &Option<gdvae_node::evaluate::metrics::AngleErrors>| match a {
        Some(a) => format!(
            "{:>6}/{:>6}/{:>5}%",
            fmt_opt(a.median_deg, 1.0, 1),
            fmt_opt(a.p90_deg, 1.0, 1),
            fmt_opt(a.over_30_deg, 100.0, 0)
        ),
        None => "no ground truth".into(),
    };
    for r in &report.recordings {
        let changes = r
            .changes
            .as_ref()
            .map(|c| {
                (
                    format!("{}/{}", c.found, c.true_changes),
                    c.false_changes.to_string(),
                    fmt_opt(c.median_delay_frames, 1.0, 0),
                )
            })
            .unwrap_or((format!("{} reported", r.changes_reported), "-".into(), "-".into()));
        println!(
            "{:<22} {:>6} {:>5} | {:>23} | {:>23} | {:>10} | {:>14} {:>5} {:>6}",
            r.stream,
            r.states,
            r.rejected,
            angles(&r.heading_raw),
            angles(&r.heading_filtered),
            fmt_opt(r.position.as_ref().and_then(|p| p.median_m), 1.0, 3),
            changes.0,
            changes.1,
            changes.2
        );
        if !r.has_truth {
            println!(
                "{:<22} filtered yaw steps: median {} deg, p90 {} deg per frame",
                "",
                fmt_opt(r.filtered_yaw_steps.median_deg, 1.0, 2),
                fmt_opt(r.filtered_yaw_steps.p90_deg, 1.0, 2)
            );
        }
        if r.truth_without_state > 0 || r.states_without_truth > 0 {
            println!(
                "{:<22} unmatched: {} truth frames without a state, {} states without truth",
                "", r.truth_without_state, r.states_without_truth
            );
        }
    }
    let o = &report.overall;
    println!(
        "overall ({} recordings, {} matched frames): heading raw {}, filtered {} (median/p90/>30%)",
        o.recordings,
        o.matched,
        angles(&Some(o.heading_raw.clone())),
        angles(&Some(o.heading_filtered.clone()))
    );
    for (family, a) in &o.heading_filtered_by_family {
        let raw = o.heading_raw_by_family.get(family).cloned();
        println!(
            "  {family:<10} heading raw {} (>150: {}%), filtered {} (>150: {}%)",
            angles(&raw),
            fmt_opt(raw.as_ref().and_then(|r| r.over_150_deg), 100.0, 0),
            angles(&Some(a.clone())),
            fmt_opt(a.over_150_deg, 100.0, 0)
        );
    }
    let c = &o.changes;
    println!(
        "  identity changes: {}/{} found within {} frames (recall {}), {} false = {} per 1000 frames, median delay {} frames",
        c.found,
        c.true_changes,
        report.tolerance_frames,
        fmt_opt(c.recall, 1.0, 3),
        c.false_changes,
        fmt_opt(c.false_per_1000_frames, 1.0, 2),
        fmt_opt(c.median_delay_frames, 1.0, 0)
    );
    println!(
        "  position (centre_m vs truth, horizontal): median {} m, p90 {} m",
        fmt_opt(o.position.median_m, 1.0, 3),
        fmt_opt(o.position.p90_m, 1.0, 3)
    );
    for r in &o.retrieval {
        println!(
            "  identity retrieval after {:>2} frames: top-1 {} (same family {}) over {} subjects",
            r.frames,
            fmt_opt(r.top1, 1.0, 3),
            fmt_opt(r.top1_same_family, 1.0, 3),
            r.queries
        );
    }
    for s in &o.separability {
        println!(
            "  z_I separability over {:>2} frames: AUC {} (same family {}), {} of {} changes above the within-subject p99.9 (same family {} of {})",
            s.frames,
            fmt_opt(s.auc, 1.0, 3),
            fmt_opt(s.auc_same_family, 1.0, 3),
            fmt_opt(s.found_at_p999, 1.0, 2),
            s.changes,
            fmt_opt(s.found_at_p999_same_family, 1.0, 2),
            s.same_family_changes
        );
    }
    for (label, p) in [("raw", &o.pose_code), ("published", &o.pose_code_published)] {
        println!(
            "  pose code z_E ({label}): frame-to-frame step walking {} / standing {}, ratio {} ({} / {} steps); \
             spread over 1 s walking {} / standing {}, ratio {} ({} / {} windows)",
            fmt_opt(p.walking_step_median, 1.0, 4),
            fmt_opt(p.standing_step_median, 1.0, 4),
            fmt_opt(p.ratio, 1.0, 2),
            p.walking_steps,
            p.standing_steps,
            fmt_opt(p.walking_spread_median, 1.0, 4),
            fmt_opt(p.standing_spread_median, 1.0, 4),
            fmt_opt(p.spread_ratio, 1.0, 2),
            p.walking_windows,
            p.standing_windows,
        );
    }
    let states: u64 = summary.snapshot.streams.values().map(|c| c.published).sum();
    println!(
        "  replay: {states} states in {:.1} s ({:.1} frames/s)",
        summary.busy.as_secs_f64(),
        states as f64 / summary.busy.as_secs_f64().max(1e-9)
    );
}

/// A replay that published nothing did not do its job: every input failed. The error says how
/// many frames came in and at which stages they were rejected (the log has each reason).
fn require_states(summary: &RunSummary) -> Result<()> {
    let streams = &summary.snapshot.streams;
    if streams.values().any(|c| c.published > 0) {
        return Ok(());
    }
    let received: u64 = streams.values().map(|c| c.received).sum();
    let mut reasons: Vec<(u64, String)> = streams
        .values()
        .flat_map(|c| c.rejected.iter().map(|(reason, n)| (*n, reason.clone())))
        .collect();
    reasons.sort_by(|a, b| b.0.cmp(&a.0));
    let reasons: Vec<String> = reasons.iter().map(|(n, stage)| format!("{n} by {stage}")).collect();
    bail!(
        "every input failed: no state published ({received} frame(s) received{}{})",
        if reasons.is_empty() { "" } else { "; rejected " },
        reasons.join(", ")
    )
}

/// The config a one-off command starts from: the given file (read, not yet validated) or the
/// defaults, with `--bundle` applied; and where it came from, for the error of its validation.
fn starting_config(path: Option<PathBuf>, bundle: Option<PathBuf>) -> Result<(Config, PathBuf)> {
    let (mut config, origin) = match path {
        Some(path) => (Config::read(&path)?, path),
        None => (Config::default(), PathBuf::from("(defaults)")),
    };
    if let Some(bundle) = bundle {
        config.model.bundle = bundle;
    }
    Ok((config, origin))
}

/// The one validation of a config a command has finished adjusting.
fn validated(config: Config, origin: &Path) -> Result<Config> {
    config
        .validate()
        .map_err(|message| anyhow::anyhow!("{}: {message}", origin.display()))?;
    Ok(config)
}

fn run_pipeline(config: &Config, options: RunOptions, live_summary: bool) -> Result<RunSummary> {
    let bundle = Bundle::load(&config.model.bundle)?;
    let session =
        if config.publish.zenoh || config.publish.ros2.enabled || config.sources.iter().any(|s| s.is_subscription()) {
            let session = open_session(&config.zenoh)?;
            log::info!(
                "zenoh {} session {} up; publishing on {}",
                config.zenoh.mode,
                session.zid(),
                config.state_key("*")
            );
            Some(session)
        } else {
            None
        };
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        let presses = std::sync::atomic::AtomicUsize::new(0);
        ctrlc::set_handler(move || {
            if presses.fetch_add(1, Ordering::SeqCst) > 0 {
                eprintln!("gdvae-node: second interrupt, exiting without draining");
                std::process::exit(130);
            }
            eprintln!("gdvae-node: stopping: draining the frames in flight (interrupt again to exit now)");
            stop.store(true, Ordering::SeqCst);
        })
        .context("installing the SIGINT/SIGTERM handler")?;
    }
    let stats = Arc::new(Stats::default());
    if live_summary {
        return run_with_live_summary(config, &bundle, session, stop, stats, options);
    }
    Ok(pipeline::run(config, &bundle, session, stop, stats, options)?)
}

/// `run --live-summary`: a readable line per state on stdout, read back from the node's own
/// zenoh publications (so it shows exactly what subscribers get).
fn run_with_live_summary(
    config: &Config,
    bundle: &Bundle,
    session: Option<zenoh::Session>,
    stop: Arc<AtomicBool>,
    stats: Arc<Stats>,
    options: RunOptions,
) -> Result<RunSummary> {
    use zenoh::Wait;
    let Some(session) = session.filter(|_| config.publish.zenoh) else {
        bail!("--live-summary reads the node's zenoh states; enable publish.zenoh");
    };
    let subscriber = session
        .declare_subscriber(config.state_key("*"))
        .callback(|sample| {
            let Ok(state) = serde_json::from_slice::<gdvae_node::state::State>(&sample.payload().to_bytes()) else {
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
    let summary = pipeline::run(config, bundle, Some(session), stop, stats, options)?;
    std::thread::sleep(std::time::Duration::from_millis(200));
    drop(subscriber);
    Ok(summary)
}

fn print_report(
    summary: &RunSummary,
    baseline: Option<(&gdvae_node::benchmark::EncoderAlone, &Config)>,
    steal_s: Option<f64>,
    json: bool,
) -> Result<()> {
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
