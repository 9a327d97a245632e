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
use gdvae_node::config::{Config, Format, SourceKind, SourceSettings};
use gdvae_node::pipeline::{self, RunOptions, RunSummary};
use gdvae_node::prepare::{Preparer, Sampling};
use gdvae_node::publish::open_session;
use gdvae_node::runtime::{loaded_library, Encoder};
use gdvae_node::sources::files::{read_cloud, FileOptions};
use gdvae_node::stats::{peak_memory_mib, Stats, STAGES};

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
    Run {
        #[arg(long, default_value = "config/default.toml")]
        config: PathBuf,
        /// Print one line per published state (stream, sequence, identity, yaw, latency).
        #[arg(long)]
        live_summary: bool,
    },
    /// Offline replay benchmark: every frame of the recordings or point-cloud files, as fast as
    /// possible, losslessly; prints throughput and latency percentiles per stage, peak memory,
    /// and ONNX Runtime alone on the same bundle, batch and threads for comparison.
    Replay {
        /// MCAP files, rosbag2 folders, point-cloud files or folders; one stream each.
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
    },
    /// Encode one point-cloud file (PLY, PCD, OBJ, XYZ/CSV) and print the codes as JSON.
    Encode {
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
    },
    /// Parse and validate a config; check its bundle, ONNX Runtime and source paths.
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
        Command::Run { config, live_summary } => {
            let mut config = Config::load(&config)?;
            if config.sources.is_empty() {
                bail!("the config has no [[source]]; nothing to run");
            }
            if live_summary && config.publish.jsonl.is_none() {
                config.pipeline.summary_seconds = 0.0;
            }
            let summary = run_pipeline(&config, RunOptions::default(), live_summary)?;
            print_report(&summary, None, false)?;
            Ok(())
        }
        Command::Replay {
            inputs,
            config,
            bundle,
            speed,
            zenoh,
            jsonl,
            json,
            no_baseline,
        } => {
            let mut config = starting_config(config, bundle)?;
            config.sources = replay_sources(&inputs, speed)?;
            config.publish.zenoh = zenoh;
            config.publish.jsonl = jsonl;
            config.validate().map_err(anyhow::Error::msg)?;
            let summary = run_pipeline(&config, RunOptions { lossless_publish: true }, false)?;
            let baseline = if no_baseline {
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
            print_report(&summary, baseline.as_ref().map(|b| (b, &config)), json)?;
            Ok(())
        }
        Command::Encode {
            file,
            config,
            bundle,
            unit,
            sampling,
            onnxruntime,
            seed,
        } => {
            let mut config = starting_config(config, bundle)?;
            if let Some(sampling) = sampling {
                config.prepare.sampling = match sampling {
                    SamplingArg::Farthest => Sampling::Farthest,
                    SamplingArg::Random => Sampling::Random,
                    SamplingArg::Voxel => Sampling::Voxel,
                };
            }
            if let Some(seed) = seed {
                config.prepare.seed = seed;
            }
            let bundle = Bundle::load(&config.model.bundle)?;
            let read = read_cloud(&file, &FileOptions::default())?;
            let points_read = read.cloud.len();
            let frame = Frame {
                stream: "file".into(),
                sequence: 0,
                sensor_stamp_ns: None,
                ingested: std::time::Instant::now(),
                ingest_unix_ns: 0,
                unit: match unit {
                    UnitArg::Metre => Unit::Metre,
                    UnitArg::Millimetre => Unit::Millimetre,
                },
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
            let library = onnxruntime.or(config.model.onnxruntime.clone());
            let mut encoder = Encoder::load(&bundle, library.as_deref(), config.model.threads, config.model.spin)?;
            let encoding = encoder.encode(&[&prepared.points])?.remove(0);
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
        Command::CheckConfig { config: path } => {
            let config = Config::load(&path)?;
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
            for source in &config.sources {
                match source.kind {
                    SourceKind::Files => {
                        let files =
                            gdvae_node::sources::files::list_files(source.path.as_deref().unwrap_or(Path::new("")))?;
                        println!("source '{}': {} file(s)", source.stream, files.len());
                    }
                    SourceKind::Mcap => {
                        let files = gdvae_node::sources::mcap::recording_files(
                            source.path.as_deref().unwrap_or(Path::new("")),
                        )?;
                        println!("source '{}': {} recording file(s)", source.stream, files.len());
                    }
                    SourceKind::Zenoh => {
                        println!(
                            "source '{}': zenoh key {}",
                            source.stream,
                            source.key.as_deref().unwrap_or("")
                        )
                    }
                }
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
            Ok(())
        }
        Command::InspectModel {
            bundle,
            load,
            onnxruntime,
        } => {
            let bundle = Bundle::load(&bundle)?;
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
            for key in ["S", "C_X", "d_C", "heading_error_median_deg"] {
                if let Some(value) = m.metrics.get(key).and_then(|v| v.as_f64()) {
                    println!("metric {key}: {value:.4}");
                }
            }
            if load {
                let encoder = Encoder::load(&bundle, onnxruntime.as_deref(), 1, false)?;
                println!(
                    "encoder {} loaded with ONNX Runtime from {}",
                    encoder.file().display(),
                    loaded_library().map(|p| p.display().to_string()).unwrap_or_default()
                );
            }
            Ok(())
        }
    }
}

/// The config a one-off command starts from: the given file or the defaults, with `--bundle` applied.
fn starting_config(path: Option<PathBuf>, bundle: Option<PathBuf>) -> Result<Config> {
    let mut config = match path {
        Some(path) => Config::load(&path)?,
        None => Config::default(),
    };
    if let Some(bundle) = bundle {
        config.model.bundle = bundle;
    }
    Ok(config)
}

/// One replay source per input: MCAP files and rosbag2 folders replay their point clouds, other
/// files and folders are point-cloud files.
fn replay_sources(inputs: &[PathBuf], speed: f64) -> Result<Vec<SourceSettings>> {
    let mut sources: Vec<SourceSettings> = Vec::new();
    for input in inputs {
        let is_recording = input.extension().is_some_and(|e| e == "mcap")
            || (input.is_dir() && gdvae_node::sources::mcap::recording_files(input).is_ok());
        let stem = input
            .file_stem()
            .and_then(|s| s.to_str())
            .unwrap_or("input")
            .replace(|c: char| !(c.is_ascii_alphanumeric() || c == '-' || c == '_'), "_");
        let mut stream = stem.clone();
        let mut n = 1;
        while sources.iter().any(|s| s.stream == stream) {
            n += 1;
            stream = format!("{stem}_{n}");
        }
        let mut source: SourceSettings = toml::from_str(&format!(
            "stream = {stream:?}\nkind = {:?}\npath = {:?}",
            if is_recording { "mcap" } else { "files" },
            input.display().to_string()
        ))
        .context("building a replay source")?;
        source.speed = speed;
        sources.push(source);
    }
    Ok(sources)
}

fn run_pipeline(config: &Config, options: RunOptions, live_summary: bool) -> Result<RunSummary> {
    let bundle = Bundle::load(&config.model.bundle)?;
    let session = if config.publish.zenoh || config.sources.iter().any(|s| s.kind == SourceKind::Zenoh) {
        let session = open_session(config)?;
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
        let mut config = config.clone();
        config.publish.jsonl = None;
        return run_with_live_summary(&config, &bundle, session, stop, stats, options);
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
    json: bool,
) -> Result<()> {
    let s = &summary.snapshot;
    let published: u64 = s.streams.values().map(|c| c.published).sum();
    let rejected: u64 = s.streams.values().map(|c| c.rejected.values().sum::<u64>()).sum();
    let wall = summary.busy.as_secs_f64().max(1e-9);
    let throughput = published as f64 / wall;
    let memory = peak_memory_mib();
    if json {
        let report = serde_json::json!({
            "wall_s": summary.wall.as_secs_f64(),
            "busy_s": wall,
            "states": published,
            "rejected": rejected,
            "throughput_fps": throughput,
            "peak_memory_mib": memory,
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
            }
        );
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
            "ONNX Runtime alone (batch {}, {} worker(s) x {} thread(s)): {:.1} frames/s -> pipeline at {:.0} % of it",
            config.model.max_batch,
            config.model.workers,
            config.model.threads,
            b.frames_per_second,
            100.0 * throughput / b.frames_per_second
        );
    }
    if let Some(mib) = memory {
        println!("peak memory (VmHWM): {mib:.1} MiB");
    }
    Ok(())
}
