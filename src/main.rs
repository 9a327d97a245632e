//! `gdvae-node`: the node's command line. Commands are thin wrappers over the library; errors are
//! reported once, here.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use gdvae_node::bundle::Bundle;
use gdvae_node::cloud::Unit;
use gdvae_node::prepare::{centre_and_scale, subsample, Sampling};
use gdvae_node::runtime::{loaded_library, Encoder};
use gdvae_node::sources::files::{read_cloud, FileOptions};

#[derive(Parser)]
#[command(
    name = "gdvae-node",
    version,
    about = "Point-cloud frames -> GDVAE++ rotation, pose and shape codes"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Encode one point-cloud file (PLY, PCD, OBJ, XYZ/CSV) and print the codes as JSON.
    Encode {
        file: PathBuf,
        /// Model bundle folder.
        #[arg(long)]
        bundle: PathBuf,
        /// Unit of the file's coordinates.
        #[arg(long, value_enum, default_value = "metre")]
        unit: UnitArg,
        #[arg(long, value_enum, default_value = "farthest")]
        sampling: SamplingArg,
        /// ONNX Runtime library (default: ORT_DYLIB_PATH, then the .venv onnxruntime wheel).
        #[arg(long)]
        onnxruntime: Option<PathBuf>,
        #[arg(long, default_value_t = 0)]
        seed: u64,
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
    match run(Cli::parse().command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("gdvae-node: error: {error:#}");
            ExitCode::FAILURE
        }
    }
}

fn run(command: Command) -> Result<()> {
    match command {
        Command::Encode {
            file,
            bundle,
            unit,
            sampling,
            onnxruntime,
            seed,
        } => {
            let bundle = Bundle::load(&bundle)?;
            let sizes = bundle.manifest.sizes;
            let read = read_cloud(&file, &FileOptions::default())?;
            let unit = match unit {
                UnitArg::Metre => Unit::Metre,
                UnitArg::Millimetre => Unit::Millimetre,
            };
            let sampling = match sampling {
                SamplingArg::Farthest => Sampling::Farthest,
                SamplingArg::Random => Sampling::Random,
                SamplingArg::Voxel => Sampling::Voxel,
            };
            let metres: Vec<[f32; 3]> = read
                .cloud
                .points
                .iter()
                .map(|p| p.map(|c| c * unit.to_metres()))
                .collect();
            let mut points = subsample(&metres, sizes.points, sizes.points / 4, sampling, 0.01, seed)
                .with_context(|| format!("{}", file.display()))?;
            let centre = centre_and_scale(&mut points, bundle.manifest.units.model_units_per_metre as f32);
            let mut encoder = Encoder::load(&bundle, onnxruntime.as_deref(), 2)?;
            let encoding = encoder.encode(&[&points])?.remove(0);
            let out = serde_json::json!({
                "file": file.display().to_string(),
                "points_read": read.cloud.len(),
                "dropped_non_finite": read.dropped_non_finite,
                "centre_m": centre,
                "encoding": encoding,
            });
            println!("{}", serde_json::to_string_pretty(&out)?);
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
                let encoder = Encoder::load(&bundle, onnxruntime.as_deref(), 1)?;
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
