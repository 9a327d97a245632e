//! `sim`: the simulator's command line. Each subcommand is a thin wrapper over the library; argument
//! checking happens here once, and library errors are reported once, by `main`.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use gdvae_sim::dataset::{write_dataset, DatasetSpec};
use gdvae_sim::distortion::measure_distortion;
use gdvae_sim::family::{Family, PoseMode, Subject, DEFAULT_VERTEX_COUNT};
use gdvae_sim::feed::{run_feed, zenoh_config, FeedOptions, DEFAULT_PREFIX};
use gdvae_sim::motion::{planned_positions, MotionKind, MotionSpec};
use gdvae_sim::ply::write_ply;
use gdvae_sim::recording::{write_recording, RecordingOptions};
use gdvae_sim::scenario::{Away, Scenario, ViewSpec};
use gdvae_sim::seeds;
use zenoh::Wait;

#[derive(Parser)]
#[command(
    name = "sim",
    version,
    about = "Synthetic articulated subjects, datasets and sensor feeds for GDVAE++"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, ValueEnum)]
enum FamilyArg {
    Quadruped,
    Biped,
}

impl From<FamilyArg> for Family {
    fn from(arg: FamilyArg) -> Self {
        match arg {
            FamilyArg::Quadruped => Family::Quadruped,
            FamilyArg::Biped => Family::Biped,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum PoseArg {
    Rest,
    Gaussian,
    Bent,
}

impl From<PoseArg> for PoseMode {
    fn from(arg: PoseArg) -> Self {
        match arg {
            PoseArg::Rest => PoseMode::Rest,
            PoseArg::Gaussian => PoseMode::Gaussian,
            PoseArg::Bent => PoseMode::Bent,
        }
    }
}

#[derive(Clone, Copy, ValueEnum)]
enum MotionArg {
    Walk,
    Idle,
    /// Back and forth along a straight line across the view (others only by intent, though any
    /// subject may).
    Cross,
    /// Standing and turning in place as `idle` does, the pose drifting only as much as a walking
    /// subject's does around its gait (idle shifts through the whole pose prior).
    Stand,
}

impl From<MotionArg> for MotionKind {
    fn from(arg: MotionArg) -> Self {
        match arg {
            MotionArg::Walk => MotionKind::Walk,
            MotionArg::Idle => MotionKind::Idle,
            MotionArg::Cross => MotionKind::Cross,
            MotionArg::Stand => MotionKind::Stand,
        }
    }
}

/// A subject moving in front of the simulated depth camera (shared by `record` and `feed`).
#[derive(clap::Args)]
struct ScenarioArgs {
    /// Family of each successive subject, cycled at every identity switch.
    #[arg(long, value_delimiter = ',', default_value = "quadruped")]
    families: Vec<FamilyArg>,
    #[arg(long, value_enum, default_value = "walk")]
    motion: MotionArg,
    /// Frames per second.
    #[arg(long, default_value_t = 30.0)]
    fps: f64,
    /// Length of the sequence in seconds.
    #[arg(long, default_value_t = 4.0)]
    duration: f64,
    /// Times (s) at which another subject replaces the current one, e.g. `--switch-at 2,4`.
    #[arg(long, value_delimiter = ',')]
    switch_at: Vec<f64>,
    /// Horizontal distance from the camera to the stage centre (m).
    #[arg(long, default_value_t = 3.2)]
    camera_distance: f64,
    /// Camera height above the ground (m).
    #[arg(long, default_value_t = 1.3)]
    camera_height: f64,
    /// Height of the point above the stage centre that the camera looks at (m).
    #[arg(long, default_value_t = 0.8)]
    target_height: f64,
    /// Half side of the square ground patch centred on the stage (m); 0 leaves the ground out.
    #[arg(long, default_value_t = 4.0)]
    ground_extent: f64,
    /// Boxes of clutter on the ground around the stage.
    #[arg(long, default_value_t = 0)]
    clutter: usize,
    /// Point-cloud decimation: keep every n-th depth pixel in each direction (1 keeps all).
    #[arg(long, default_value_t = 1)]
    decimation: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Other subjects in view, one per family given (e.g. `--others biped,quadruped`), each on its
    /// own path on a stage shifted by its `--others-offset`, so that they pass behind each other
    /// in the image.
    #[arg(long, value_delimiter = ',')]
    others: Vec<FamilyArg>,
    /// Where each other subject's stage lies, `X:Y` (m, world; the camera looks along -x from
    /// +x), one per other subject in order: by default the first 0.9 m to the primary's left, the
    /// second 0.9 m to its right, so that the paths cross and the subjects pass behind each other.
    #[arg(long, value_delimiter = ',', value_parser = parse_offset, default_value = "0:0.9,0:-0.9", allow_hyphen_values = true)]
    others_offset: Vec<[f64; 2]>,
    /// How the other subjects move (default: as the primary, `--motion`). `cross`: back and forth
    /// along a 4 m line across the view through its stage's centre, slanted up to 26 degrees; with
    /// `--others-offset 0.7:0` it passes in front of the primary twice in 12 s, with `-0.9:0`
    /// behind it, so that their paths cross in the image and one hides the other.
    #[arg(long, value_enum)]
    others_motion: Option<MotionArg>,
    /// Least distance (m) between where two subjects stand, so that bodies never pass through
    /// each other: each other subject's path (its phase) is drawn again until it keeps this
    /// distance from the subjects before it at every frame (0: no check).
    #[arg(long, default_value_t = 0.8)]
    others_separation: f64,
    /// A subject out of the scene for an interval: `SUBJECT:FROM-TO` in seconds, SUBJECT 0 the
    /// primary and 1.. the others (e.g. `--away 1:3-6,1:9-10`).
    #[arg(long, value_delimiter = ',', value_parser = parse_away)]
    away: Vec<Away>,
}

/// How many seeds an other subject's path is drawn from before the scene is refused.
const MAX_DRAWS: u64 = 200;

fn parse_offset(text: &str) -> Result<[f64; 2], String> {
    let bad = || format!("'{text}': expected X:Y in metres, e.g. -1.8:0");
    let (x, y) = text.split_once(':').ok_or_else(bad)?;
    Ok([
        x.trim().parse().map_err(|_| bad())?,
        y.trim().parse().map_err(|_| bad())?,
    ])
}

fn parse_away(text: &str) -> Result<Away, String> {
    let bad = || format!("'{text}': expected SUBJECT:FROM-TO, e.g. 1:3-6");
    let (subject, interval) = text.split_once(':').ok_or_else(bad)?;
    let (from, to) = interval.split_once('-').ok_or_else(bad)?;
    Ok(Away {
        subject: subject.trim().parse().map_err(|_| bad())?,
        from: from.trim().parse().map_err(|_| bad())?,
        to: to.trim().parse().map_err(|_| bad())?,
    })
}

impl ScenarioArgs {
    fn build(&self) -> Result<Scenario> {
        let motion = MotionSpec {
            families: self.families.iter().copied().map(Family::from).collect(),
            kind: self.motion.into(),
            fps: self.fps,
            duration: self.duration,
            switch_times: self.switch_at.clone(),
            area: [0.4, 0.7],
            seed: self.seed,
        };
        let view = ViewSpec {
            camera_distance: self.camera_distance,
            camera_height: self.camera_height,
            target_height: self.target_height,
            ground_half_extent: self.ground_extent,
            clutter: self.clutter,
            decimation: self.decimation,
            ..ViewSpec::default()
        };
        if self.others.len() > self.others_offset.len() {
            anyhow::bail!(
                "--others names {} subjects but --others-offset places {}: give one X:Y per other subject",
                self.others.len(),
                self.others_offset.len()
            );
        }
        // Each other subject's seed (its shape and its path's phase) drawn until its path keeps
        // its distance from the subjects before it (while both are in the scene).
        let fps = motion.fps;
        let present = |id: usize, index: usize| {
            let time = index as f64 / fps;
            !self
                .away
                .iter()
                .any(|a| a.subject == id && (a.from..a.to).contains(&time))
        };
        let mut placed: Vec<Vec<[f64; 2]>> = vec![planned_positions(&motion)];
        let mut others = Vec::new();
        for (k, (family, offset)) in self.others.iter().zip(&self.others_offset).enumerate() {
            let id = k + 1;
            let spec = (0..MAX_DRAWS)
                .map(|draw| MotionSpec {
                    families: vec![Family::from(*family)],
                    kind: self.others_motion.unwrap_or(self.motion).into(),
                    switch_times: Vec::new(),
                    seed: seeds::derive(self.seed, &[6, k as u64, draw]),
                    ..motion.clone()
                })
                .find(|spec| {
                    let own = planned_positions(spec);
                    own.iter().enumerate().all(|(index, p)| {
                        let p = [p[0] + offset[0], p[1] + offset[1]];
                        placed.iter().enumerate().all(|(other, positions)| {
                            let q = positions[index];
                            !(present(id, index) && present(other, index))
                                || (p[0] - q[0]).hypot(p[1] - q[1]) >= self.others_separation
                        })
                    })
                });
            let Some(spec) = spec else {
                anyhow::bail!(
                    "subject {id}: no path in {MAX_DRAWS} draws keeps {} m from the subjects before \
                     it on a stage offset {offset:?}: move its stage (--others-offset) or lower --others-separation",
                    self.others_separation
                );
            };
            placed.push(
                planned_positions(&spec)
                    .iter()
                    .map(|p| [p[0] + offset[0], p[1] + offset[1]])
                    .collect(),
            );
            others.push((spec, *offset));
        }
        Ok(Scenario::new(motion, view)?.with_others(others, self.away.clone(), self.others_separation)?)
    }
}

#[derive(Subcommand)]
enum Command {
    /// List the families, their shape parameters (beta) with ranges, and their joints.
    Families,
    /// Write a training dataset: K subjects x M poses per family, binary PLY + ground truth + splits.
    Dataset {
        /// Output folder (created if missing).
        #[arg(long)]
        out: PathBuf,
        /// Families to include.
        #[arg(long, value_delimiter = ',', default_value = "quadruped,biped")]
        families: Vec<FamilyArg>,
        /// Subjects (individuals, distinct beta) per family.
        #[arg(long, default_value_t = 20)]
        subjects: usize,
        /// Poses per subject.
        #[arg(long, default_value_t = 10)]
        poses: usize,
        /// Fraction of poses drawn from the wide "bent" prior (sigma 0.5 rad) instead of sigma 0.2.
        #[arg(long, default_value_t = 0.15)]
        bent_fraction: f64,
        /// Train, validation and test fractions of the subjects (splits never share a subject).
        #[arg(long, value_delimiter = ',', default_value = "0.8,0.1,0.1")]
        split: Vec<f64>,
        /// Rotate each mesh by a random yaw about the up axis (recorded in the ground truth).
        #[arg(long)]
        random_yaw: bool,
        /// Paired data: pose j is one draw shared by every subject of a family (a subjects x poses
        /// grid; the ground truth's `pose_id` names the pose), for supervised training.
        #[arg(long)]
        shared_poses: bool,
        /// Fraction of poses that are walking ones, as the sim's walk poses a subject (the gait at a
        /// random phase plus a small prior drift; `gait_phase` in the ground truth)
        #[arg(long, default_value_t = 0.0)]
        gait_fraction: f64,
        /// Vertices per mesh (the decimation target).
        #[arg(long, default_value_t = DEFAULT_VERTEX_COUNT)]
        vertices: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Report how far posing departs from isometry: percentiles of per-edge length change.
    Distortion {
        #[arg(long, value_delimiter = ',', default_value = "quadruped,biped")]
        families: Vec<FamilyArg>,
        #[arg(long, default_value_t = 4)]
        subjects: usize,
        #[arg(long, default_value_t = 25)]
        poses: usize,
        #[arg(long, value_enum, default_value = "gaussian")]
        mode: PoseArg,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Print one JSON object per family instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// Record a subject moving in front of the simulated depth camera to an MCAP file (ROS 2 CDR).
    Record {
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        scenario: ScenarioArgs,
        /// Also record the 16UC1 depth images and their CameraInfo.
        #[arg(long)]
        depth_images: bool,
        /// Write uncompressed chunks (default: zstd).
        #[arg(long)]
        no_compression: bool,
    },
    /// Publish a subject moving in front of the simulated depth camera over zenoh, in real time.
    Feed {
        #[command(flatten)]
        scenario: ScenarioArgs,
        /// Key expression prefix: clouds on <prefix>/points, ground truth on <prefix>/ground_truth.
        #[arg(long, default_value = DEFAULT_PREFIX)]
        key_prefix: String,
        /// Zenoh endpoints to listen on (e.g. tcp/127.0.0.1:7447); default: zenoh's own.
        #[arg(long, value_delimiter = ',')]
        listen: Vec<String>,
        /// Zenoh endpoints (routers or peers) to connect to.
        #[arg(long, value_delimiter = ',')]
        connect: Vec<String>,
        /// Do not discover peers by UDP multicast (use explicit endpoints only).
        #[arg(long)]
        no_multicast: bool,
        /// Also publish 16UC1 depth images on <prefix>/depth and calibration on <prefix>/camera_info.
        #[arg(long)]
        depth_images: bool,
        /// Publish as fast as frames are made instead of at --fps.
        #[arg(long)]
        unpaced: bool,
        /// Wait up to this many seconds for a subscriber to <prefix>/points (or /depth) before the first frame.
        #[arg(long)]
        wait_for_subscriber: Option<f64>,
    },
    /// Pose given subjects in given poses: one JSON request per line, {"name", "family", "beta",
    /// "theta"}, each written as <out>/<name>.ply (the kit's pose-transfer ground truth).
    Pose {
        /// JSON-lines file of requests.
        #[arg(long)]
        requests: PathBuf,
        /// Output folder (created if missing).
        #[arg(long)]
        out: PathBuf,
    },
    /// Write one posed subject as a binary PLY.
    Mesh {
        #[arg(long, value_enum)]
        family: FamilyArg,
        /// Seed of the subject's shape (beta); `--mean-shape` uses mid-range values instead.
        #[arg(long, default_value_t = 0)]
        subject_seed: u64,
        #[arg(long)]
        mean_shape: bool,
        #[arg(long, value_enum, default_value = "rest")]
        pose: PoseArg,
        #[arg(long, default_value_t = 0)]
        pose_seed: u64,
        #[arg(long)]
        out: PathBuf,
    },
}

#[derive(serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct PoseRequest {
    name: String,
    family: Family,
    beta: Vec<f64>,
    theta: Vec<f64>,
}

/// `sim pose`: builds each distinct subject once (in parallel) and writes every requested pose.
fn pose_requests(requests: &std::path::Path, out: &std::path::Path) -> Result<()> {
    use rayon::prelude::*;

    let text = std::fs::read_to_string(requests).with_context(|| format!("reading {}", requests.display()))?;
    let mut parsed = Vec::new();
    for (number, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let request: PoseRequest = serde_json::from_str(line)
            .with_context(|| format!("{}:{}: not a pose request", requests.display(), number + 1))?;
        let valid_name = !request.name.is_empty()
            && request
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
            && !request.name.starts_with('.');
        if !valid_name {
            bail!(
                "{}:{}: name '{}' must be letters, digits, '-', '_' or '.'",
                requests.display(),
                number + 1,
                request.name
            );
        }
        parsed.push(request);
    }
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    // Group by subject: meshing a subject costs far more than posing it.
    let mut subjects: Vec<(Family, Vec<f64>, Vec<&PoseRequest>)> = Vec::new();
    for request in &parsed {
        match subjects
            .iter_mut()
            .find(|(f, b, _)| *f == request.family && *b == request.beta)
        {
            Some((_, _, group)) => group.push(request),
            None => subjects.push((request.family, request.beta.clone(), vec![request])),
        }
    }
    subjects
        .par_iter()
        .try_for_each(|(family, beta, group)| -> Result<()> {
            let subject = Subject::new(*family, beta.clone())?;
            for request in group {
                let mesh = subject
                    .pose(&request.theta)
                    .with_context(|| format!("request '{}'", request.name))?;
                let path = out.join(format!("{}.ply", request.name));
                let mut file = std::io::BufWriter::new(
                    std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?,
                );
                write_ply(
                    &mesh,
                    &format!("gdvae-sim {} pose request {}", family.name(), request.name),
                    &mut file,
                )
                .with_context(|| format!("writing {}", path.display()))?;
            }
            Ok(())
        })?;
    println!(
        "wrote {} meshes of {} subjects to {}",
        parsed.len(),
        subjects.len(),
        out.display()
    );
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("sim: error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Families => {
            for family in Family::ALL {
                let skeleton = family.reference_skeleton();
                println!(
                    "{} ({} joints, theta dimension {})",
                    family.name(),
                    skeleton.len(),
                    skeleton.pose_dimension()
                );
                for b in family.beta_parameters() {
                    println!("  beta {:<22} [{:.3}, {:.3}]  {}", b.name, b.min, b.max, b.description);
                }
                let names: Vec<&str> = skeleton.joints.iter().map(|j| j.name).collect();
                println!("  joints: {}", names.join(", "));
            }
            Ok(())
        }
        Command::Dataset {
            out,
            families,
            subjects,
            poses,
            bent_fraction,
            split,
            random_yaw,
            shared_poses,
            gait_fraction,
            vertices,
            seed,
        } => {
            let [train, validation, test] = split[..] else {
                bail!("--split needs three fractions")
            };
            let spec = DatasetSpec {
                families: families.into_iter().map(Family::from).collect(),
                subjects_per_family: subjects,
                poses_per_subject: poses,
                bent_fraction,
                split: [train, validation, test],
                random_yaw,
                shared_poses,
                gait_fraction,
                target_vertices: vertices,
                seed,
            };
            spec.validate()?;
            eprintln!("sim: writing {} meshes to {}", spec.mesh_count(), out.display());
            let started = Instant::now();
            let last_report = Mutex::new(Instant::now());
            let summary = write_dataset(&spec, &out, |done, total| {
                let mut last = last_report.lock().unwrap_or_else(|e| e.into_inner());
                if last.elapsed().as_secs_f64() >= 2.0 || done == total {
                    *last = Instant::now();
                    let rate = done as f64 / started.elapsed().as_secs_f64().max(1e-9);
                    let eta = (total - done) as f64 / rate.max(1e-9);
                    eprintln!("sim: {done}/{total} meshes, {rate:.1} meshes/s, ETA {eta:.0} s");
                }
            })
            .with_context(|| format!("writing dataset to {}", out.display()))?;
            println!(
                "wrote {} meshes of {} subjects in {:.1} s ({:.1} meshes/s), {}-{} vertices, {:.1} MB",
                summary.meshes,
                summary.subjects,
                summary.seconds,
                summary.meshes_per_second,
                summary.min_vertices,
                summary.max_vertices,
                summary.bytes as f64 / 1e6
            );
            Ok(())
        }
        Command::Distortion {
            families,
            subjects,
            poses,
            mode,
            seed,
            json,
        } => {
            if subjects == 0 || poses == 0 {
                bail!("--subjects and --poses must be at least 1");
            }
            if !json {
                println!(
                    "edge-length distortion |l - l_rest| / l_rest, {subjects} subjects x {poses} poses per family"
                );
                println!(
                    "{:<10} {:>9} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
                    "family", "edges", "mean", "p50", "p90", "p95", "p99", "max"
                );
            }
            for family in families {
                let report = measure_distortion(family.into(), mode.into(), subjects, poses, seed)?;
                if json {
                    println!("{}", serde_json::to_string(&report)?);
                } else {
                    let pct = |v: f64| format!("{:.2}%", 100.0 * v);
                    println!(
                        "{:<10} {:>9} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8}",
                        report.family.name(),
                        report.edges_measured,
                        pct(report.mean),
                        pct(report.p50),
                        pct(report.p90),
                        pct(report.p95),
                        pct(report.p99),
                        pct(report.max)
                    );
                }
            }
            Ok(())
        }
        Command::Record {
            out,
            scenario,
            depth_images,
            no_compression,
        } => {
            let scenario = scenario.build()?;
            let total = scenario.frame_count();
            eprintln!("sim: recording {total} frames to {}", out.display());
            let options = RecordingOptions {
                depth_images,
                compression: !no_compression,
            };
            let last_report = Mutex::new(Instant::now());
            let summary = write_recording(&scenario, &out, options, |done, total| {
                let mut last = last_report.lock().unwrap_or_else(|e| e.into_inner());
                if last.elapsed().as_secs_f64() >= 2.0 || done == total {
                    *last = Instant::now();
                    eprintln!("sim: {done}/{total} frames");
                }
            })
            .with_context(|| format!("writing recording {}", out.display()))?;
            println!(
                "wrote {} frames in {:.1} s ({:.1} frames/s), {:.0} points per frame (min {}), {:.2} MB",
                summary.frames,
                summary.seconds,
                summary.frames as f64 / summary.seconds.max(1e-9),
                summary.points_per_frame_mean,
                summary.points_per_frame_min,
                summary.bytes as f64 / 1e6
            );
            Ok(())
        }
        Command::Feed {
            scenario,
            key_prefix,
            listen,
            connect,
            no_multicast,
            depth_images,
            unpaced,
            wait_for_subscriber,
        } => {
            let wait_for_subscriber = match wait_for_subscriber {
                Some(seconds) if !(seconds >= 0.0 && seconds.is_finite()) => {
                    bail!("--wait-for-subscriber must be a non-negative number of seconds, got {seconds}")
                }
                Some(seconds) => Some(Duration::from_secs_f64(seconds)),
                None => None,
            };
            if key_prefix.trim_matches('/').is_empty() {
                bail!("--key-prefix must not be empty");
            }
            let scenario = scenario.build()?;
            let config = zenoh_config(&listen, &connect, !no_multicast)?;
            let session = zenoh::open(config)
                .wait()
                .map_err(|e| anyhow::anyhow!("opening a zenoh session: {e}"))?;
            let stop = Arc::new(AtomicBool::new(false));
            let handler_stop = stop.clone();
            ctrlc::set_handler(move || handler_stop.store(true, Ordering::Relaxed))
                .context("installing the Ctrl-C handler")?;
            let options = FeedOptions {
                key_prefix: key_prefix.clone(),
                depth_images,
                unpaced,
                wait_for_subscriber,
            };
            eprintln!(
                "sim: publishing {} frames at {} Hz on {}/points (zenoh id {})",
                scenario.frame_count(),
                scenario.motion.spec.fps,
                key_prefix.trim_end_matches('/'),
                session.zid()
            );
            let last_report = Mutex::new(Instant::now());
            let summary = run_feed(&scenario, &session, &options, &stop, |done, total| {
                let mut last = last_report.lock().unwrap_or_else(|e| e.into_inner());
                if last.elapsed().as_secs_f64() >= 2.0 || done == total {
                    *last = Instant::now();
                    eprintln!("sim: {done}/{total} frames published");
                }
            });
            session
                .close()
                .wait()
                .map_err(|e| anyhow::anyhow!("closing the zenoh session: {e}"))?;
            let summary = summary?;
            println!(
                "published {} frames in {:.1} s, {} late (max {:.1} ms late)",
                summary.published, summary.seconds, summary.late, summary.max_lateness_ms
            );
            Ok(())
        }
        Command::Pose { requests, out } => pose_requests(&requests, &out),
        Command::Mesh {
            family,
            subject_seed,
            mean_shape,
            pose,
            pose_seed,
            out,
        } => {
            let family = Family::from(family);
            let subject = if mean_shape {
                Subject::new(family, family.mean_beta())?
            } else {
                Subject::draw(family, subject_seed, DEFAULT_VERTEX_COUNT)?
            };
            let theta = subject.sample_theta(pose.into(), &mut seeds::rng(pose_seed));
            let mesh = subject.pose(&theta)?;
            let mut file = std::io::BufWriter::new(
                std::fs::File::create(&out).with_context(|| format!("creating {}", out.display()))?,
            );
            write_ply(&mesh, &format!("gdvae-sim {} mesh", family.name()), &mut file)
                .with_context(|| format!("writing {}", out.display()))?;
            println!(
                "wrote {} ({} vertices, {} triangles)",
                out.display(),
                mesh.positions.len(),
                mesh.triangles.len()
            );
            Ok(())
        }
    }
}
