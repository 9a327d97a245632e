//! Model bundles: the kit's `manifest.json` and ONNX files, checked before the first frame.
//!
//! The node refuses a bundle it cannot honour (unknown schema, missing or altered files, units or
//! conventions it does not implement) with a message that says which and why. The format is
//! documented in models/README.md.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use sha2::{Digest, Sha256};

pub const SCHEMA_VERSION: u32 = 1;
pub const FILES: [&str; 3] = ["encoder.onnx", "decoder.onnx", "flow.onnx"];

#[derive(Debug, Clone, Deserialize)]
pub struct Manifest {
    pub schema_version: u32,
    pub format: String,
    pub model: ModelInfo,
    pub sizes: Sizes,
    pub units: Units,
    pub files: BTreeMap<String, FileEntry>,
    #[serde(default)]
    pub calibration: Calibration,
    #[serde(default)]
    pub metrics: serde_json::Value,
}

/// What the kit measured of the encoder's own uncertainty at export (absent: as reported), and
/// what was fitted on the node's own clouds after it.
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
pub struct Calibration {
    /// How far one subject's z_I spreads over its poses and camera views, against the variance the
    /// encoder reports (median over dimensions of their ratio). The tracker multiplies the
    /// encoder's z_I variances by it, then by `[track] shape_variance_scale`.
    #[serde(rename = "z_I_variance_scale")]
    pub z_i_variance_scale: f32,
    /// Directions of x_c that tell subjects of one family apart, fitted on the node's clouds of
    /// sim subjects (`python -m gdvae fit-identity`); the tracker detects identity changes on
    /// them (absent: on z_I).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identity_projection: Option<IdentityProjection>,
    /// How far one subject's z_I lies from its mean over its poses and camera views (root mean
    /// square, median over subjects; model units): the unit of the tracker's z_I distances and
    /// variance floor (`[track]` min_shape_variance, `[track.objects]` shape_scale and
    /// reid_distance). Absent (bundles calibrated before it was measured):
    /// [`UNCALIBRATED_Z_I_SPREAD`].
    #[serde(rename = "z_I_spread", default, skip_serializing_if = "Option::is_none")]
    pub z_i_spread: Option<f32>,
}

/// The z_I spread assumed for a bundle whose calibration does not give one: h200-fo-theta's
/// (`python -m gdvae export --calibrate /work/data/sim-grid150` measures 0.3413), the bundle with
/// which the tracker's z_I settings were chosen, so that they keep their meaning for the bundles
/// shipped before the spread was measured.
pub const UNCALIBRATED_Z_I_SPREAD: f32 = 0.3413;

impl Calibration {
    /// The identity projection's rows as the tracker takes them (`[track]` identity_projection).
    /// The unit of the tracker's z_I distances: the measured spread, else the assumed one.
    pub fn z_i_unit(&self) -> f32 {
        self.z_i_spread.unwrap_or(UNCALIBRATED_Z_I_SPREAD)
    }

    pub fn identity_directions(&self) -> Option<std::sync::Arc<Vec<Vec<f32>>>> {
        self.identity_projection
            .as_ref()
            .map(|p| std::sync::Arc::new(p.matrix.clone()))
    }
}

impl Default for Calibration {
    fn default() -> Self {
        Self {
            z_i_variance_scale: 1.0,
            identity_projection: None,
            z_i_spread: None,
        }
    }
}

/// `calibration.identity_projection`: rows of weights on one encoder output, each a direction
/// scaled to unit spread within one subject (models/README, "Identity projection").
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
pub struct IdentityProjection {
    /// The encoder output it reads; this node reads "x_c".
    pub input: String,
    pub matrix: Vec<Vec<f32>>,
    /// The sha256 of the `encoder.onnx` whose x_c it was fitted on: beside another encoder, whose
    /// x_c means something else, the node drops it with a warning (`Bundle::load`).
    pub encoder_sha256: String,
    /// How it was fitted (subjects, frames, the files), for the model card; not read.
    #[serde(default)]
    pub fitted_on: serde_json::Value,
}

#[derive(Debug, Clone, Deserialize)]
pub struct ModelInfo {
    pub ae_type: String,
    pub supervision: String,
    pub regime: String,
    pub recipe: String,
    /// Whether z_E's encoder reads a pose encoder's code (the kit's pose stage); absent in bundles
    /// exported before it existed.
    #[serde(default)]
    pub pose_encoder: bool,
    /// Whether z_I's encoder reads a body encoder's code (the kit's body stage); absent in bundles
    /// exported before it existed.
    #[serde(default)]
    pub body_encoder: bool,
}

#[derive(Debug, Clone, Copy, Deserialize, serde::Serialize)]
pub struct Sizes {
    pub points: usize,
    pub spectrum: usize,
    pub x_c: usize,
    #[serde(rename = "z_R")]
    pub z_r: usize,
    #[serde(rename = "z_E")]
    pub z_e: usize,
    #[serde(rename = "z_I")]
    pub z_i: usize,
}

#[derive(Debug, Clone, Deserialize)]
pub struct Units {
    pub input_unit: String,
    pub model_units_per_metre: f64,
    pub centering: String,
    pub up_axis: String,
    pub rotation_mode: String,
}

#[derive(Debug, Clone, Deserialize)]
pub struct FileEntry {
    pub sha256: String,
}

#[derive(Debug, thiserror::Error)]
pub enum BundleError {
    #[error("bundle {path}: cannot read manifest.json: {source}")]
    Read { path: PathBuf, source: std::io::Error },
    #[error("bundle {path}: manifest.json is not a valid manifest: {source}")]
    Parse { path: PathBuf, source: serde_json::Error },
    #[error("bundle {path}: {reason}")]
    Unsupported { path: PathBuf, reason: String },
}

/// A checked bundle: its folder and manifest.
#[derive(Debug, Clone)]
pub struct Bundle {
    pub folder: PathBuf,
    pub manifest: Manifest,
}

impl Bundle {
    pub fn load(folder: impl AsRef<Path>) -> Result<Self, BundleError> {
        let folder = folder.as_ref().to_path_buf();
        let manifest_path = folder.join("manifest.json");
        let text = std::fs::read_to_string(&manifest_path).map_err(|source| BundleError::Read {
            path: folder.clone(),
            source,
        })?;
        let manifest: Manifest = serde_json::from_str(&text).map_err(|source| BundleError::Parse {
            path: folder.clone(),
            source,
        })?;
        let mut bundle = Self { folder, manifest };
        bundle.check()?;
        bundle.drop_stale_identity_projection();
        Ok(bundle)
    }

    /// An identity projection fitted on another encoder than the bundle's reads an x_c that means
    /// something else: it is dropped with a warning (identity changes are then found on z_I), so
    /// that the node still runs and the states to fit it again can be written.
    fn drop_stale_identity_projection(&mut self) {
        let m = &mut self.manifest;
        let encoder = m
            .files
            .get("encoder.onnx")
            .map(|e| e.sha256.clone())
            .unwrap_or_default();
        if let Some(p) = &m.calibration.identity_projection {
            if !p.encoder_sha256.eq_ignore_ascii_case(&encoder) {
                log::warn!(
                    "bundle {}: its identity projection was fitted on another encoder (sha256 {}), so identity \
                     changes are found on z_I; fit it again (python -m gdvae fit-identity, `make fit-identity`)",
                    self.folder.display(),
                    p.encoder_sha256
                );
                m.calibration.identity_projection = None;
            }
        }
    }

    pub fn path(&self, file: &str) -> PathBuf {
        self.folder.join(file)
    }

    fn unsupported(&self, reason: String) -> BundleError {
        BundleError::Unsupported {
            path: self.folder.clone(),
            reason,
        }
    }

    fn check(&self) -> Result<(), BundleError> {
        let m = &self.manifest;
        if m.format != "gdvae-bundle" {
            return Err(self.unsupported(format!("format is '{}', expected 'gdvae-bundle'", m.format)));
        }
        if m.schema_version != SCHEMA_VERSION {
            return Err(self.unsupported(format!(
                "schema version {} is not supported (this node reads version {SCHEMA_VERSION})",
                m.schema_version
            )));
        }
        let s = m.sizes;
        for (name, value) in [
            ("points", s.points),
            ("spectrum", s.spectrum),
            ("x_c", s.x_c),
            ("z_R", s.z_r),
            ("z_E", s.z_e),
            ("z_I", s.z_i),
        ] {
            if value == 0 || value > 1 << 20 {
                return Err(self.unsupported(format!("size {name} = {value} is out of range")));
            }
        }
        let scale = m.calibration.z_i_variance_scale;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(self.unsupported(format!("calibration z_I_variance_scale = {scale} must be positive")));
        }
        if let Some(spread) = m.calibration.z_i_spread {
            if !(spread.is_finite() && spread > 0.0) {
                return Err(self.unsupported(format!("calibration z_I_spread = {spread} must be positive")));
            }
        }
        if let Some(projection) = &m.calibration.identity_projection {
            let wrong = if projection.input != "x_c" {
                Some(format!("reads '{}' (this node projects x_c)", projection.input))
            } else if projection.matrix.is_empty() || projection.matrix.len() > s.x_c {
                Some(format!("has {} rows (1 to x_c's {})", projection.matrix.len(), s.x_c))
            } else if let Some(row) = projection.matrix.iter().position(|row| row.len() != s.x_c) {
                Some(format!(
                    "row {row} has {} weights, not x_c's {}",
                    projection.matrix[row].len(),
                    s.x_c
                ))
            } else if projection.matrix.iter().flatten().any(|w| !w.is_finite()) {
                Some("has a weight that is not finite".into())
            } else {
                None
            };
            if let Some(wrong) = wrong {
                return Err(self.unsupported(format!("calibration identity_projection {wrong}")));
            }
        }
        let u = &m.units;
        if u.input_unit != "metre" {
            return Err(self.unsupported(format!("input unit '{}' (this node feeds metres)", u.input_unit)));
        }
        if !(u.model_units_per_metre.is_finite() && u.model_units_per_metre > 0.0) {
            return Err(self.unsupported(format!(
                "model_units_per_metre = {} must be positive",
                u.model_units_per_metre
            )));
        }
        if u.centering != "bounding-box centre" {
            return Err(self.unsupported(format!("centering '{}' is not implemented", u.centering)));
        }
        if u.up_axis != "+z" {
            return Err(self.unsupported(format!("up axis '{}' (this node's gravity frame is +z up)", u.up_axis)));
        }
        if u.rotation_mode != "yaw" && u.rotation_mode != "so3" {
            return Err(self.unsupported(format!("rotation mode '{}' is unknown", u.rotation_mode)));
        }
        for file in FILES {
            let entry = m
                .files
                .get(file)
                .ok_or_else(|| self.unsupported(format!("manifest lists no {file}")))?;
            let actual =
                sha256_file(&self.path(file)).map_err(|e| self.unsupported(format!("cannot read {file}: {e}")))?;
            if !actual.eq_ignore_ascii_case(&entry.sha256) {
                return Err(self.unsupported(format!(
                    "{file} has sha256 {actual}, but the manifest says {} (altered or mismatched file)",
                    entry.sha256
                )));
            }
        }
        Ok(())
    }
}

fn sha256_file(path: &Path) -> std::io::Result<String> {
    let mut file = std::fs::File::open(path)?;
    let mut hasher = Sha256::new();
    let mut buffer = vec![0u8; 1 << 16];
    loop {
        let read = file.read(&mut buffer)?;
        if read == 0 {
            break;
        }
        hasher.update(&buffer[..read]);
    }
    Ok(hasher.finalize().iter().map(|b| format!("{b:02x}")).collect())
}
