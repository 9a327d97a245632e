//! ONNX Runtime: finding its library, and running a bundle's encoder.
//!
//! `ort` is built with `load-dynamic`: nothing is downloaded at build or run time. The library is
//! found, in order, at the configured path, at `ORT_DYLIB_PATH`, or inside the `onnxruntime` wheel
//! of a Python venv (`.venv/lib/python3.*/site-packages/onnxruntime/capi/`) in the working directory
//! or next to the executable's ancestors. `make venv` installs that wheel.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ort::session::Session;
use ort::value::Tensor;

use crate::bundle::Bundle;
pub use crate::encoding::Encoding;

#[derive(Debug, thiserror::Error)]
pub enum RuntimeError {
    #[error(
        "ONNX Runtime library not found (looked at: {looked}). Set ORT_DYLIB_PATH or `onnxruntime_library` in the \
         config to a libonnxruntime.so, or run `make venv` to install the onnxruntime wheel into .venv"
    )]
    LibraryNotFound { looked: String },
    #[error("loading ONNX Runtime from {path}: {message}")]
    Load { path: PathBuf, message: String },
    #[error("{file}: {message}")]
    Session { file: PathBuf, message: String },
    #[error("{file}: expected output '{name}' is missing (outputs: {found})")]
    MissingOutput { file: PathBuf, name: String, found: String },
    #[error("encoder run failed: {0}")]
    Run(String),
}

/// Why the one attempt to load ONNX Runtime failed (kept, so later calls report it too).
#[derive(Debug, Clone)]
enum InitFailure {
    NotFound { looked: String },
    Load { path: PathBuf, message: String },
}

static ENVIRONMENT: OnceLock<Result<(PathBuf, ort::environment::Environment), InitFailure>> = OnceLock::new();

/// Candidate locations of libonnxruntime, most specific first.
pub fn library_candidates(configured: Option<&Path>) -> Vec<PathBuf> {
    let mut candidates = Vec::new();
    if let Some(path) = configured {
        candidates.push(path.to_path_buf());
    }
    if let Some(path) = std::env::var_os("ORT_DYLIB_PATH") {
        candidates.push(PathBuf::from(path));
    }
    let mut roots = vec![std::env::current_dir().unwrap_or_default()];
    if let Ok(exe) = std::env::current_exe() {
        roots.extend(exe.ancestors().skip(1).map(Path::to_path_buf));
    }
    for root in roots {
        let lib = root.join(".venv").join("lib");
        let Ok(pythons) = std::fs::read_dir(&lib) else { continue };
        for python in pythons.flatten() {
            let capi = python.path().join("site-packages/onnxruntime/capi");
            let Ok(files) = std::fs::read_dir(&capi) else { continue };
            let mut found: Vec<PathBuf> = files
                .flatten()
                .map(|f| f.path())
                .filter(|p| {
                    p.file_name()
                        .and_then(|n| n.to_str())
                        .is_some_and(|n| n.starts_with("libonnxruntime.so"))
                })
                .collect();
            found.sort();
            candidates.extend(found.into_iter().rev());
        }
    }
    candidates
}

/// Loads ONNX Runtime once per process (later calls return the first outcome).
pub fn environment(configured: Option<&Path>) -> Result<&'static ort::environment::Environment, RuntimeError> {
    let outcome = ENVIRONMENT.get_or_init(|| {
        let candidates = library_candidates(configured);
        let Some(path) = candidates.iter().find(|p| p.is_file()).cloned() else {
            let looked = candidates
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ");
            return Err(InitFailure::NotFound {
                looked: if looked.is_empty() { "nothing".into() } else { looked },
            });
        };
        ort::init_from(&path)
            .map_err(|e| e.to_string())
            .and_then(|builder| builder.build().map_err(|e| e.to_string()))
            .map(|environment| (path.clone(), environment))
            .map_err(|message| InitFailure::Load { path, message })
    });
    match outcome {
        Ok((_, environment)) => Ok(environment),
        Err(InitFailure::NotFound { looked }) => Err(RuntimeError::LibraryNotFound { looked: looked.clone() }),
        Err(InitFailure::Load { path, message }) => Err(RuntimeError::Load {
            path: path.clone(),
            message: message.clone(),
        }),
    }
}

/// The library actually loaded, once `environment` succeeded.
pub fn loaded_library() -> Option<PathBuf> {
    ENVIRONMENT.get().and_then(|o| o.as_ref().ok()).map(|(p, _)| p.clone())
}

const OUTPUTS: [&str; 8] = [
    "q",
    "x_c",
    "z_R_mean",
    "z_R_logvar",
    "z_E_mean",
    "z_E_logvar",
    "z_I_mean",
    "z_I_logvar",
];

/// An ONNX Runtime session of one of a bundle's graphs: `threads` intra-op threads, one inter-op
/// thread; `spin` lets idle threads spin for work.
fn open_session(file: &Path, library: Option<&Path>, threads: usize, spin: bool) -> Result<Session, RuntimeError> {
    let environment = environment(library)?;
    let session_error = |e: ort::Error| RuntimeError::Session {
        file: file.to_path_buf(),
        message: e.to_string(),
    };
    Session::builder(environment)
        .map_err(session_error)?
        .with_intra_threads(threads.max(1))
        .map_err(|e| session_error(e.into()))?
        .with_inter_threads(1)
        .map_err(|e| session_error(e.into()))?
        .with_intra_op_spinning(spin)
        .map_err(|e| session_error(e.into()))?
        .commit_from_file(file)
        .map_err(session_error)
}

/// One ONNX Runtime session of a bundle's encoder (sessions are not shared between threads).
pub struct Encoder {
    session: Session,
    file: PathBuf,
    /// Test-time yaw copies per frame (`crate::yaw_copies`); 1: the frame as seen only.
    yaw_copies: usize,
}

impl Encoder {
    /// `spin`: let idle ONNX Runtime threads spin for work (lowest latency on otherwise idle cores;
    /// wasted CPU when the node's other stages share the cores).
    pub fn load(bundle: &Bundle, library: Option<&Path>, threads: usize, spin: bool) -> Result<Self, RuntimeError> {
        let file = bundle.path("encoder.onnx");
        let session = open_session(&file, library, threads, spin)?;
        let found: Vec<String> = session.outputs().iter().map(|o| o.name().to_string()).collect();
        for name in OUTPUTS {
            if !found.iter().any(|f| f == name) {
                return Err(RuntimeError::MissingOutput {
                    file: file.clone(),
                    name: name.into(),
                    found: found.join(", "),
                });
            }
        }
        Ok(Self {
            session,
            file,
            yaw_copies: 1,
        })
    }

    /// Encode every frame as `copies` turned copies fused into one answer (`crate::yaw_copies`).
    pub fn with_yaw_copies(mut self, copies: usize) -> Self {
        self.yaw_copies = copies.max(1);
        self
    }

    pub fn file(&self) -> &Path {
        &self.file
    }

    /// Encodes a batch of clouds that all have the same number of points (model units, centred),
    /// each as `yaw_copies` turned copies fused into one encoding.
    pub fn encode(&mut self, clouds: &[&[[f32; 3]]]) -> Result<Vec<Encoding>, RuntimeError> {
        if self.yaw_copies <= 1 {
            return self.encode_as_seen(clouds);
        }
        let angles = crate::yaw_copies::angles(self.yaw_copies);
        let turned: Vec<Vec<[f32; 3]>> = clouds
            .iter()
            .flat_map(|cloud| angles.iter().map(|&a| crate::yaw_copies::turned(cloud, a)))
            .collect();
        let views: Vec<&[[f32; 3]]> = turned.iter().map(Vec::as_slice).collect();
        let encodings = self.encode_as_seen(&views)?;
        Ok(encodings
            .chunks(angles.len())
            .map(|copies| crate::yaw_copies::fuse(copies, &angles).0)
            .collect())
    }

    /// One encoder run over the clouds exactly as given.
    fn encode_as_seen(&mut self, clouds: &[&[[f32; 3]]]) -> Result<Vec<Encoding>, RuntimeError> {
        let batch = clouds.len();
        if batch == 0 {
            return Ok(Vec::new());
        }
        let points = clouds[0].len();
        if clouds.iter().any(|c| c.len() != points) || points == 0 {
            return Err(RuntimeError::Run(
                "clouds of a batch must be non-empty and equally long".into(),
            ));
        }
        let mut data = Vec::with_capacity(batch * points * 3);
        for cloud in clouds {
            for point in *cloud {
                data.extend_from_slice(point);
            }
        }
        let input = Tensor::from_array(([batch, points, 3], data)).map_err(|e| RuntimeError::Run(e.to_string()))?;
        let outputs = self
            .session
            .run(ort::inputs!["points" => input])
            .map_err(|e| RuntimeError::Run(e.to_string()))?;
        let mut columns: Vec<Vec<Vec<f32>>> = Vec::with_capacity(OUTPUTS.len());
        for name in OUTPUTS {
            let (shape, values) = outputs[name]
                .try_extract_tensor::<f32>()
                .map_err(|e| RuntimeError::Run(format!("output {name}: {e}")))?;
            let width = shape.get(1).copied().unwrap_or(1).max(1) as usize;
            if values.len() != batch * width {
                return Err(RuntimeError::Run(format!(
                    "output {name} has {} values for a batch of {batch}",
                    values.len()
                )));
            }
            columns.push(values.chunks(width).map(<[f32]>::to_vec).collect());
        }
        let take = |column: usize, row: usize| columns[column][row].clone();
        Ok((0..batch)
            .map(|row| {
                let q = take(0, row);
                Encoding {
                    q: [q[0], q[1], q[2], q[3]],
                    x_c: take(1, row),
                    z_r_mean: take(2, row),
                    z_r_logvar: take(3, row),
                    z_e_mean: take(4, row),
                    z_e_logvar: take(5, row),
                    z_i_mean: take(6, row),
                    z_i_logvar: take(7, row),
                    yaw_spread: None,
                }
            })
            .collect())
    }
}

/// One ONNX Runtime session of a bundle's decoder: the canonical shape a pose code and a shape
/// code describe (the ROS 2 markers draw it). One thread; it runs off the pipeline's hot path.
pub struct ShapeDecoder {
    session: Session,
    file: PathBuf,
    z_r: usize,
}

impl ShapeDecoder {
    pub fn load(bundle: &Bundle, library: Option<&Path>) -> Result<Self, RuntimeError> {
        let file = bundle.path("decoder.onnx");
        let session = open_session(&file, library, 1, false)?;
        if !session.outputs().iter().any(|o| o.name() == "canonical_points") {
            return Err(RuntimeError::MissingOutput {
                file: file.clone(),
                name: "canonical_points".into(),
                found: session
                    .outputs()
                    .iter()
                    .map(|o| o.name().to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
        Ok(Self {
            session,
            file,
            z_r: bundle.manifest.sizes.z_r,
        })
    }

    pub fn file(&self) -> &Path {
        &self.file
    }

    /// The canonical points (model units, canonical frame) of one (z_E, z_I); z_R at its prior
    /// mean (the canonical shape does not depend on it).
    pub fn decode(&mut self, z_e: &[f32], z_i: &[f32]) -> Result<Vec<[f32; 3]>, RuntimeError> {
        let tensor = |values: Vec<f32>| {
            let n = values.len();
            Tensor::from_array(([1, n], values)).map_err(|e| RuntimeError::Run(e.to_string()))
        };
        let outputs = self
            .session
            .run(ort::inputs![
                "z_E" => tensor(z_e.to_vec())?,
                "z_I" => tensor(z_i.to_vec())?,
                "z_R" => tensor(vec![0.0; self.z_r])?,
            ])
            .map_err(|e| RuntimeError::Run(e.to_string()))?;
        let (_, values) = outputs["canonical_points"]
            .try_extract_tensor::<f32>()
            .map_err(|e| RuntimeError::Run(format!("output canonical_points: {e}")))?;
        if values.len() % 3 != 0 {
            return Err(RuntimeError::Run(format!(
                "canonical_points has {} values, not points of 3",
                values.len()
            )));
        }
        Ok(values.chunks(3).map(|p| [p[0], p[1], p[2]]).collect())
    }
}
