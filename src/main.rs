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
use gdvae_node::stats::{cpu_steal_seconds, Stats};
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
    /// Record every published message to this MCAP file (as `[publish] mcap`).
    #[arg(long)]
    record: Option<String>,
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
    /// Record every published message to this MCAP file.
    #[arg(long)]
    record: Option<String>,
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
    /// Override a track setting, e.g. `--set cusum_threshold=6` or `--set objects.enabled=true`
    /// (repeatable; for tuning).
    #[arg(long = "set", value_name = "KEY=VALUE")]
    set: Vec<String>,
    /// A true identity change counts as found when reported within this many frames.
    #[arg(long, default_value_t = 10)]
    tolerance_frames: usize,
    /// Several objects: a track matches a subject within this horizontal distance (m).
    #[arg(long, default_value_t = 0.5)]
    mot_distance: f64,
    /// Several objects: a subject with fewer points on it in a frame is ignored there.
    #[arg(long, default_value_t = 200)]
    mot_min_visible: usize,
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
    /// Write the N_p points the encoder saw for every published state, in `--states`' order, as
    /// a NumPy `.npy` array [states, N_p, 3] (float32, model units, centred), for training on
    /// the node's own clouds.
    #[arg(long)]
    clouds: Option<PathBuf>,
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
    if args.record.is_some() {
        config.publish.mcap = args.record.clone();
    }
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
    Ok(pipeline::report::print_report(&summary, None, None, false)?)
}

/// `replay`: the inputs as fast as possible (or at `--speed`), every frame kept; the report.
fn replay(args: ReplayArgs) -> Result<()> {
    let (mut config, origin) = starting_config(args.config, args.bundle)?;
    config.sources = gdvae_node::sources::replay_sources(&args.inputs, args.speed);
    config.publish.zenoh = args.zenoh;
    config.publish.jsonl = args.jsonl;
    if args.record.is_some() {
        config.publish.mcap = args.record;
    }
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
    pipeline::report::print_report(&summary, baseline.as_ref().map(|b| (b, &config)), steal, args.json)?;
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
        sensor_frame: None,
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
    let zenoh = gdvae_node::zenoh_session::session_config(&config.zenoh)?;
    let plan = gdvae_node::zenoh_session::plan(&zenoh);
    if let Some(file) = config.zenoh.file() {
        println!("zenoh configuration file: {}", file.display());
    }
    for endpoint in gdvae_node::zenoh_session::open_to_the_network(&plan) {
        println!(
            "warning: zenoh listens on {endpoint} without TLS: anyone who can reach it can publish into \
             the node's inputs, query its status and subscribe to its states (README \"Who can reach the node\")"
        );
    }
    if config.publish.zenoh {
        println!(
            "publishing on {} (zenoh {}, {})",
            config.state_key("<stream>"),
            plan.mode,
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
        "model: {} regime, {} autoencoder, {}, recipe {}{}{}",
        m.model.regime,
        m.model.ae_type,
        m.model.supervision,
        m.model.recipe,
        if m.model.pose_encoder {
            ", z_E from a pose encoder"
        } else {
            ""
        },
        if m.model.body_encoder {
            ", z_I from a body encoder"
        } else {
            ""
        }
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
    match m.calibration.z_i_spread {
        Some(spread) => println!("calibration: z_I spread {spread} (the unit of the tracker's z_I distances)"),
        None => println!(
            "calibration: no z_I spread measured; the tracker assumes {}",
            gdvae_node::bundle::UNCALIBRATED_Z_I_SPREAD
        ),
    }
    match &m.calibration.identity_projection {
        Some(p) => println!(
            "calibration: identity changes on {} directions of {} (fitted on {} subjects, {} frames)",
            p.matrix.len(),
            p.input,
            p.fitted_on["subjects"]
                .as_object()
                .map_or(0, |families| families.values().filter_map(|n| n.as_u64()).sum::<u64>()),
            p.fitted_on["frames"]
        ),
        None => println!("calibration: identity changes on z_I (no identity projection)"),
    }
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
        objects: gdvae_node::evaluate::objects::ObjectsOptions {
            max_distance_m: args.mot_distance,
            min_visible_points: args.mot_min_visible,
        },
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
    if args.states.is_some() || args.clouds.is_some() {
        let matched = gdvae_node::evaluate::matched_states(&recordings, &outputs);
        if let Some(path) = &args.states {
            gdvae_node::evaluate::print::write_matched_states(path, &matched)?;
        }
        if let Some(path) = &args.clouds {
            gdvae_node::evaluate::print::write_clouds(path, &matched)?;
        }
    }
    if let Some(folder) = plots {
        // The threshold of the space the pipeline's shape filters worked in (the bundle decides).
        let mut track = config.track.clone();
        track.identity_projection = Bundle::load(&config.model.bundle)?
            .manifest
            .calibration
            .identity_directions();
        let threshold = match track.change_detector {
            gdvae_node::config::ChangeDetector::Consecutive => None,
            _ => Some(track.change_threshold() as f64),
        };
        let written = gdvae_node::evaluate::write_plots(&report, folder, config.track.shape_gate as f64, threshold)?;
        eprintln!("evaluate: {} plot(s) in {}", written.len(), folder.display());
    }
    match out {
        Some("-") => println!("{}", serde_json::to_string_pretty(&report)?),
        Some(path) => {
            std::fs::write(path, serde_json::to_string_pretty(&report)?).with_context(|| format!("writing {path}"))?;
            gdvae_node::evaluate::print::print(&report, &summary);
            eprintln!("evaluate: report in {path}");
        }
        None => gdvae_node::evaluate::print::print(&report, &summary),
    }
    if report.overall.matched == 0 && report.overall.with_truth > 0 {
        bail!("no state matched any ground-truth frame by sensor stamp");
    }
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
        // `objects.gate_m=0.5`: a key of a table within [track].
        let (within, key) = match key.split_once('.') {
            Some((section, key)) => match table.get_mut(section) {
                Some(toml::Value::Table(inner)) => (inner, key),
                _ => bail!("--set {item}: [track] has no table '{section}'"),
            },
            None => (&mut table, key),
        };
        if !within.contains_key(key) {
            bail!("--set {item}: [track] has no key '{key}'");
        }
        within.insert(key.to_string(), value);
    }
    let settings: gdvae_node::config::TrackSettings =
        table.try_into().context("--set: the track settings do not parse")?;
    settings.validate().map_err(anyhow::Error::msg)?;
    Ok(settings)
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
            if let Some(file) = config.zenoh.file() {
                log::info!("zenoh configuration from {}", file.display());
            }
            log::info!(
                "zenoh {} session {} up; publishing on {}",
                gdvae_node::zenoh_session::session_config(&config.zenoh)
                    .map(|zc| gdvae_node::zenoh_session::plan(&zc).mode)
                    .unwrap_or_default(),
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
        return pipeline::report::run_with_live_summary(config, &bundle, session, stop, stats, options);
    }
    Ok(pipeline::run(config, &bundle, session, stop, stats, options)?)
}
