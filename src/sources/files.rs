//! Point clouds from files: PLY (ply-rs-bw), PCD in ascii, binary and binary_compressed with any
//! field layout (pcd-rs), OBJ (tobj), and plain XYZ/CSV text.
//!
//! Meshes (PLY or OBJ with faces) are turned into clouds by area-weighted surface sampling with a
//! fixed seed, so a mesh file gives the same cloud every time. Points with non-finite coordinates
//! are dropped and counted. A header that claims more points than the file can hold, or more than
//! `max_points`, is rejected before anything is allocated.

use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::outlet::{Intake, Outlet};
use crate::cloud::PointCloud;

#[derive(Debug, thiserror::Error)]
pub enum FileError {
    #[error("{path}: {reason}")]
    Invalid { path: String, reason: String },
    #[error("{path}: {source}")]
    Io { path: String, source: std::io::Error },
}

/// What reading a file produced, with the points it had to drop.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FileCloud {
    pub cloud: PointCloud,
    pub dropped_non_finite: usize,
}

#[derive(Debug, Clone, Copy)]
pub struct FileOptions {
    /// Refuse files claiming more points (or vertices) than this.
    pub max_points: usize,
    /// Points drawn from a mesh's surface.
    pub mesh_samples: usize,
    pub seed: u64,
}

impl Default for FileOptions {
    fn default() -> Self {
        Self {
            max_points: 5_000_000,
            mesh_samples: 20_000,
            seed: 0,
        }
    }
}

/// File extensions this module reads.
pub const EXTENSIONS: [&str; 6] = ["ply", "pcd", "obj", "xyz", "csv", "txt"];

pub fn read_cloud(path: &Path, options: &FileOptions) -> Result<FileCloud, FileError> {
    let name = path.display().to_string();
    let invalid = |reason: String| FileError::Invalid {
        path: name.clone(),
        reason,
    };
    let extension = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default();
    let (points, faces) = match extension.as_str() {
        "ply" => read_ply(path, options).map_err(invalid)?,
        "pcd" => (read_pcd(path, options).map_err(invalid)?, Vec::new()),
        "obj" => read_obj(path, options).map_err(invalid)?,
        "xyz" | "csv" | "txt" => (read_text(path, options).map_err(invalid)?, Vec::new()),
        other => {
            return Err(invalid(format!(
                "unknown file type '.{other}' (known: {})",
                EXTENSIONS.join(", ")
            )))
        }
    };
    let total = points.len();
    let finite: Vec<[f64; 3]> = points.into_iter().filter(|p| p.iter().all(|c| c.is_finite())).collect();
    let dropped_non_finite = total - finite.len();
    let cloud = if faces.is_empty() {
        finite.iter().map(|p| p.map(|c| c as f32)).collect()
    } else {
        if dropped_non_finite > 0 {
            return Err(invalid(format!(
                "{dropped_non_finite} mesh vertices have non-finite coordinates"
            )));
        }
        sample_surface(&finite, &faces, options.mesh_samples, options.seed).map_err(invalid)?
    };
    // Narrowing to f32 turns coordinates beyond f32's range into infinities, and a mesh with
    // huge vertices samples to infinities or NaN: what is left is counted with the rest.
    let mut cloud: Vec<[f32; 3]> = cloud;
    let dropped_non_finite = dropped_non_finite + drop_non_finite(&mut cloud);
    if cloud.is_empty() {
        return Err(invalid("no points".into()));
    }
    Ok(FileCloud {
        cloud: PointCloud { points: cloud },
        dropped_non_finite,
    })
}

fn drop_non_finite(points: &mut Vec<[f32; 3]>) -> usize {
    let before = points.len();
    points.retain(|p| p.iter().all(|c| c.is_finite()));
    before - points.len()
}

/// LZF expands a byte to at most this many: a larger declared ratio is a lie.
const LZF_MAX_RATIO: u64 = 100;

/// A binary_compressed PCD's two sizes (after the DATA line) against the file and the header,
/// before pcd-rs allocates the compressed size and LZF the uncompressed one.
fn check_pcd_compressed_sizes(path: &Path, length: u64, data_bytes: u64) -> Result<(), String> {
    let mut head = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(1 << 20).read_to_end(&mut head))
        .map_err(|e| e.to_string())?;
    let data_line = head
        .split_inclusive(|b| *b == b'\n')
        .scan(0usize, |offset, line| {
            let start = *offset;
            *offset += line.len();
            Some((start, line))
        })
        .find(|(_, line)| line.starts_with(b"DATA"))
        .map(|(start, line)| start + line.len())
        .ok_or("no DATA line in the first MiB")?;
    let sizes = head
        .get(data_line..data_line + 8)
        .ok_or("binary_compressed data cut short before its sizes")?;
    let compressed = u32::from_le_bytes(sizes[..4].try_into().expect("4 bytes")) as u64;
    let uncompressed = u32::from_le_bytes(sizes[4..].try_into().expect("4 bytes")) as u64;
    let remaining = length.saturating_sub(data_line as u64 + 8);
    if compressed > remaining {
        return Err(format!("compressed data claims {compressed} bytes; {remaining} follow"));
    }
    // Column-major data of exactly the header's points: pcd-rs indexes it by the header, so a
    // shorter stream would be read out of bounds (a fuzz finding) and a longer one is a lie.
    if uncompressed != data_bytes || uncompressed > compressed.saturating_mul(LZF_MAX_RATIO) + 1024 {
        return Err(format!(
            "compressed data claims {uncompressed} bytes uncompressed; the header's points are \
             {data_bytes} bytes and {compressed} compressed bytes hold at most {}",
            compressed.saturating_mul(LZF_MAX_RATIO) + 1024
        ));
    }
    Ok(())
}

type Parsed = (Vec<[f64; 3]>, Vec<[usize; 3]>);

fn read_ply(path: &Path, options: &FileOptions) -> Result<Parsed, String> {
    use ply_rs_bw::parser::Parser;
    use ply_rs_bw::ply::{DefaultElement, Property};

    // Check the header's counts against the file size before the parser allocates.
    let length = std::fs::metadata(path).map_err(|e| e.to_string())?.len();
    let mut header = String::new();
    let mut reader = BufReader::new(std::fs::File::open(path).map_err(|e| e.to_string())?);
    let mut binary = false;
    loop {
        let mut line = String::new();
        if reader
            .read_line(&mut line)
            .map_err(|e| format!("reading header: {e}"))?
            == 0
        {
            return Err("no end_header line: not a PLY file, or truncated".into());
        }
        if header.len() > 1 << 16 {
            return Err("header longer than 64 KiB".into());
        }
        binary |= line.starts_with("format binary");
        header.push_str(&line);
        if line.trim() == "end_header" {
            break;
        }
        if let Some(rest) = line.strip_prefix("element ") {
            let count: u64 = rest
                .split_whitespace()
                .nth(1)
                .and_then(|c| c.parse().ok())
                .ok_or_else(|| format!("bad element line '{}'", line.trim()))?;
            if count > options.max_points as u64 * 4 || (binary && count > length) {
                return Err(format!(
                    "header claims {count} {} elements; the file has {length} bytes",
                    rest.split_whitespace().next().unwrap_or("?")
                ));
            }
        }
    }
    drop(reader);
    let mut file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let ply = Parser::<DefaultElement>::new()
        .read_ply(&mut file)
        .map_err(|e| format!("not a valid PLY file: {e}"))?;
    let scalar = |property: Option<&Property>| -> Option<f64> {
        Some(match property? {
            Property::Char(v) => *v as f64,
            Property::UChar(v) => *v as f64,
            Property::Short(v) => *v as f64,
            Property::UShort(v) => *v as f64,
            Property::Int(v) => *v as f64,
            Property::UInt(v) => *v as f64,
            Property::Float(v) => *v as f64,
            Property::Double(v) => *v,
            _ => return None,
        })
    };
    let vertices = ply.payload.get("vertex").ok_or("no 'vertex' element")?;
    if vertices.len() > options.max_points {
        return Err(format!(
            "{} vertices (more than max_points = {})",
            vertices.len(),
            options.max_points
        ));
    }
    let mut points = Vec::with_capacity(vertices.len());
    for (index, vertex) in vertices.iter().enumerate() {
        let get = |key: &str| scalar(vertex.get(key)).ok_or_else(|| format!("vertex {index} has no numeric '{key}'"));
        points.push([get("x")?, get("y")?, get("z")?]);
    }
    let mut faces = Vec::new();
    if let Some(elements) = ply.payload.get("face") {
        for (index, face) in elements.iter().enumerate() {
            let list: Vec<i64> = match face.get("vertex_indices").or_else(|| face.get("vertex_index")) {
                Some(Property::ListInt(l)) => l.iter().map(|&v| v as i64).collect(),
                Some(Property::ListUInt(l)) => l.iter().map(|&v| v as i64).collect(),
                Some(Property::ListShort(l)) => l.iter().map(|&v| v as i64).collect(),
                Some(Property::ListUShort(l)) => l.iter().map(|&v| v as i64).collect(),
                Some(Property::ListChar(l)) => l.iter().map(|&v| v as i64).collect(),
                Some(Property::ListUChar(l)) => l.iter().map(|&v| v as i64).collect(),
                _ => return Err(format!("face {index} has no integer vertex_indices list")),
            };
            triangulate(&list, points.len(), &mut faces).map_err(|e| format!("face {index}: {e}"))?;
        }
    }
    Ok((points, faces))
}

fn triangulate(polygon: &[i64], vertex_count: usize, faces: &mut Vec<[usize; 3]>) -> Result<(), String> {
    if polygon.len() < 3 {
        return Err(format!("{} vertices (a face needs 3)", polygon.len()));
    }
    let index = |v: i64| -> Result<usize, String> {
        usize::try_from(v)
            .ok()
            .filter(|&i| i < vertex_count)
            .ok_or_else(|| format!("vertex index {v} out of range (0..{vertex_count})"))
    };
    let first = index(polygon[0])?;
    for pair in polygon[1..].windows(2) {
        faces.push([first, index(pair[0])?, index(pair[1])?]);
    }
    Ok(())
}

fn read_pcd(path: &Path, options: &FileOptions) -> Result<Vec<[f64; 3]>, String> {
    use pcd_rs::{DataKind, DynReader, Field, PcdMeta};

    let meta = PcdMeta::from_path(path).map_err(|e| format!("not a valid PCD header: {e}"))?;
    if meta.num_points > options.max_points as u64 {
        return Err(format!(
            "header claims {} points (more than max_points = {})",
            meta.num_points, options.max_points
        ));
    }
    let point_bytes: u64 = meta
        .field_defs
        .iter()
        .map(|f| f.count * f.kind.byte_size() as u64)
        .sum();
    let length = std::fs::metadata(path).map_err(|e| e.to_string())?.len();
    let data_bytes = meta.num_points.saturating_mul(point_bytes);
    if meta.data == DataKind::Binary && data_bytes > length {
        return Err(format!(
            "header claims {} points of {point_bytes} bytes; the file has {length} bytes",
            meta.num_points
        ));
    }
    if meta.data == DataKind::BinaryCompressed {
        check_pcd_compressed_sizes(path, length, data_bytes)?;
    }
    let position = |name: &str| {
        meta.field_defs.iter().position(|f| f.name == name).ok_or_else(|| {
            format!(
                "no '{name}' field (fields: {})",
                meta.field_defs
                    .iter()
                    .map(|f| f.name.as_str())
                    .collect::<Vec<_>>()
                    .join(" ")
            )
        })
    };
    let (ix, iy, iz) = (position("x")?, position("y")?, position("z")?);
    let reader = DynReader::open(path).map_err(|e| format!("cannot read PCD data: {e}"))?;
    let first = |field: &Field| -> Option<f64> {
        Some(match field {
            Field::I8(v) => *v.first()? as f64,
            Field::I16(v) => *v.first()? as f64,
            Field::I32(v) => *v.first()? as f64,
            Field::I64(v) => *v.first()? as f64,
            Field::U8(v) => *v.first()? as f64,
            Field::U16(v) => *v.first()? as f64,
            Field::U32(v) => *v.first()? as f64,
            Field::U64(v) => *v.first()? as f64,
            Field::F32(v) => *v.first()? as f64,
            Field::F64(v) => *v.first()?,
        })
    };
    let mut points = Vec::with_capacity(meta.num_points as usize);
    for (index, record) in reader.enumerate() {
        let record = record.map_err(|e| format!("point {index}: {e}"))?;
        let get = |i: usize| {
            record
                .0
                .get(i)
                .and_then(first)
                .ok_or_else(|| format!("point {index}: field {i} is empty"))
        };
        points.push([get(ix)?, get(iy)?, get(iz)?]);
    }
    Ok(points)
}

fn read_obj(path: &Path, options: &FileOptions) -> Result<Parsed, String> {
    let load = tobj::LoadOptions {
        triangulate: true,
        single_index: false,
        ignore_points: true,
        ignore_lines: true,
    };
    // Vertices and faces only: a material library the file names is never opened (it could name
    // any path, a device or a FIFO).
    let file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let (models, _) = tobj::load_obj_buf(&mut BufReader::new(file), &load, |_| {
        Err(tobj::LoadError::OpenFileFailed)
    })
    .map_err(|e| format!("not a valid OBJ file: {e}"))?;
    if models.iter().all(|m| m.mesh.indices.is_empty()) {
        // No faces: tobj keeps no vertices then, so read the `v` lines as a point cloud.
        return read_obj_vertices(path, options).map(|points| (points, Vec::new()));
    }
    let mut points = Vec::new();
    let mut faces = Vec::new();
    for model in models {
        let mesh = model.mesh;
        let offset = points.len();
        if mesh.positions.len() / 3 > options.max_points.saturating_sub(offset) {
            return Err(format!("more than max_points = {} vertices", options.max_points));
        }
        points.extend(
            mesh.positions
                .chunks_exact(3)
                .map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]),
        );
        for triangle in mesh.indices.chunks_exact(3) {
            let face = [0, 1, 2].map(|k| offset + triangle[k] as usize);
            if face.iter().any(|&i| i >= points.len()) {
                return Err("face index out of range".into());
            }
            faces.push(face);
        }
    }
    Ok((points, faces))
}

fn read_obj_vertices(path: &Path, options: &FileOptions) -> Result<Vec<[f64; 3]>, String> {
    let file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let mut points = Vec::new();
    for (number, line) in BufReader::new(file).lines().enumerate() {
        let line = line.map_err(|e| format!("line {}: {e}", number + 1))?;
        let Some(rest) = line.strip_prefix("v ") else { continue };
        let values: Option<Vec<f64>> = rest.split_whitespace().take(3).map(|v| v.parse().ok()).collect();
        match values {
            Some(v) if v.len() == 3 => points.push([v[0], v[1], v[2]]),
            _ => return Err(format!("line {}: bad vertex '{line}'", number + 1)),
        }
        if points.len() > options.max_points {
            return Err(format!("more than max_points = {} vertices", options.max_points));
        }
    }
    Ok(points)
}

fn read_text(path: &Path, options: &FileOptions) -> Result<Vec<[f64; 3]>, String> {
    let mut text = String::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(options.max_points as u64 * 200).read_to_string(&mut text))
        .map_err(|e| format!("cannot read as text: {e}"))?;
    let mut points = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') || line.starts_with("//") {
            continue;
        }
        let values: Vec<&str> = line
            .split(|c: char| c == ',' || c == ';' || c.is_whitespace())
            .filter(|s| !s.is_empty())
            .collect();
        let parsed: Option<Vec<f64>> = values.iter().take(3).map(|v| v.parse().ok()).collect();
        match parsed {
            Some(v) if v.len() == 3 => points.push([v[0], v[1], v[2]]),
            // A header line (column names) is allowed before the first point.
            _ if points.is_empty() && number < 5 => continue,
            _ => return Err(format!("line {}: expected three numbers, got '{line}'", number + 1)),
        }
        if points.len() > options.max_points {
            return Err(format!("more than max_points = {} points", options.max_points));
        }
    }
    Ok(points)
}

/// `count` points uniformly over the surface (area-weighted), seeded.
fn sample_surface(
    vertices: &[[f64; 3]],
    faces: &[[usize; 3]],
    count: usize,
    seed: u64,
) -> Result<Vec<[f32; 3]>, String> {
    let area = |f: &[usize; 3]| {
        let [a, b, c] = f.map(|i| vertices[i]);
        let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let v = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let cross = [
            u[1] * v[2] - u[2] * v[1],
            u[2] * v[0] - u[0] * v[2],
            u[0] * v[1] - u[1] * v[0],
        ];
        0.5 * (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt()
    };
    let mut cumulative = Vec::with_capacity(faces.len());
    let mut total = 0.0;
    for face in faces {
        total += area(face);
        cumulative.push(total);
    }
    if total <= 0.0 || total.is_nan() {
        return Err("mesh has zero surface area".into());
    }
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut points = Vec::with_capacity(count);
    for _ in 0..count {
        let target = rng.random::<f64>() * total;
        let face = faces[cumulative.partition_point(|&c| c < target).min(faces.len() - 1)];
        let (mut s, mut t): (f64, f64) = (rng.random(), rng.random());
        if s + t > 1.0 {
            (s, t) = (1.0 - s, 1.0 - t);
        }
        let [a, b, c] = face.map(|i| vertices[i]);
        points.push([0, 1, 2].map(|k| (a[k] + s * (b[k] - a[k]) + t * (c[k] - a[k])) as f32));
    }
    Ok(points)
}

/// The files a files source reads: the file itself, or the readable files of a folder by name.
pub fn list_files(path: &Path) -> Result<Vec<std::path::PathBuf>, FileError> {
    let files = file_or_folder(path, &EXTENSIONS).map_err(|source| FileError::Io {
        path: path.display().to_string(),
        source,
    })?;
    if files.is_empty() {
        return Err(FileError::Invalid {
            path: path.display().to_string(),
            reason: format!("folder holds no point-cloud files ({})", EXTENSIONS.join(", ")),
        });
    }
    Ok(files)
}

/// `kind = "files"`: a point-cloud file, or a folder of them.
#[derive(Debug, Clone, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct FilesSettings {
    /// The file, or a folder whose point-cloud files are read in name order.
    pub path: std::path::PathBuf,
    /// Files have no timing: frames per second (0: as fast as the pipeline takes them).
    #[serde(default)]
    pub rate_hz: f64,
    /// Start again at the end (a looping demo).
    #[serde(default)]
    pub repeat: bool,
}

impl FilesSettings {
    pub fn validate(&self) -> Result<(), String> {
        if !(self.rate_hz >= 0.0 && self.rate_hz.is_finite()) {
            return Err(format!("rate_hz = {} must be finite and >= 0", self.rate_hz));
        }
        Ok(())
    }

    /// What the source checks before anything runs: its files exist.
    pub fn check(&self) -> Result<String, String> {
        list_files(&self.path)
            .map(|files| format!("{} point-cloud file(s)", files.len()))
            .map_err(|e| e.to_string())
    }
}

/// Runs a files source: every file once (or repeatedly with `repeat`), paced at `rate_hz`
/// (0: as fast as the pipeline takes them). A file that cannot be read is a rejection.
pub fn run(intake: &Intake, settings: &FilesSettings, mut outlet: Outlet) -> Result<(), FileError> {
    let files = list_files(&settings.path)?;
    let options = FileOptions {
        max_points: intake.max_points,
        ..FileOptions::default()
    };
    let unit = intake.unit.unwrap_or(crate::cloud::Unit::Metre);
    let period = (settings.rate_hz > 0.0).then(|| std::time::Duration::from_secs_f64(1.0 / settings.rate_hz));
    let started = std::time::Instant::now();
    let mut sent = 0u32;
    loop {
        for file in &files {
            if outlet.stopping() {
                return Ok(());
            }
            if let Some(period) = period {
                if !outlet.wait_until(started + period * sent) {
                    return Ok(());
                }
            }
            sent = sent.saturating_add(1);
            let open = match read_cloud(file, &options) {
                Ok(read) => outlet.frame(read.cloud, unit, None, read.dropped_non_finite),
                Err(error) => outlet.reject(error.to_string(), None),
            };
            if !open {
                return Ok(());
            }
        }
        if !settings.repeat {
            return Ok(());
        }
    }
}

/// The path itself when it is a file (which must exist), or the files of a folder whose extension
/// (case-insensitive) is one of `extensions`, sorted by name; possibly none.
pub fn file_or_folder(path: &std::path::Path, extensions: &[&str]) -> std::io::Result<Vec<std::path::PathBuf>> {
    if !path.is_dir() {
        std::fs::metadata(path)?;
        return Ok(vec![path.to_path_buf()]);
    }
    let mut files: Vec<_> = std::fs::read_dir(path)?
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.extension()
                .and_then(|e| e.to_str())
                .is_some_and(|e| extensions.contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    files.sort();
    Ok(files)
}
