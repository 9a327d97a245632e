//! MCAP replay: ROS 2 recordings (an `.mcap` file, or a rosbag2 folder of them) played into the
//! pipeline at their original timing times a speed factor, or as fast as the pipeline takes them.
//!
//! The stream is one topic: `sensor_msgs/msg/PointCloud2` (any field layout), or a depth
//! `sensor_msgs/msg/Image` unprojected with the latest `CameraInfo` of its camera. Without a
//! configured topic the first PointCloud2 topic is used. Files are memory-mapped, so a recording
//! of any size costs no more memory than the frames in flight.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::cloud::{PointCloud, Unit};
use crate::config::SourceSettings;
use crate::sources::ros2::{decode_camera_info, decode_depth_image, decode_point_cloud2, CameraIntrinsics};
use crate::sources::Outlet;

const POINT_CLOUD2: &str = "sensor_msgs/msg/PointCloud2";
const IMAGE: &str = "sensor_msgs/msg/Image";
const CAMERA_INFO: &str = "sensor_msgs/msg/CameraInfo";

#[derive(Debug, thiserror::Error)]
pub enum McapSourceError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{path}: not a readable MCAP file: {message}")]
    Format { path: PathBuf, message: String },
    #[error("{path}: {message}")]
    Topic { path: PathBuf, message: String },
}

/// The MCAP files of a path: the file itself, or a rosbag2 folder's `.mcap` files by name.
pub fn recording_files(path: &Path) -> Result<Vec<PathBuf>, McapSourceError> {
    let files = super::file_or_folder(path, &["mcap"]).map_err(|source| McapSourceError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if files.is_empty() {
        return Err(McapSourceError::Topic {
            path: path.to_path_buf(),
            message: "folder holds no .mcap files (rosbag2 must be recorded with the mcap storage plugin)".into(),
        });
    }
    Ok(files)
}

/// Largest chunk the reader will decompress (bytes). A chunk's header says how large it is
/// uncompressed; a hostile or corrupt header would otherwise make the reader allocate whatever it
/// claims. 512 MiB holds any frame `max_points` allows at its default (4 M points x 32 bytes)
/// four times over.
pub const MAX_CHUNK_BYTES: u64 = 512 << 20;

const MAGIC: &[u8] = b"\x89MCAP0\r\n";
const OP_SCHEMA: u8 = 0x03;
const OP_CHANNEL: u8 = 0x04;
const OP_MESSAGE: u8 = 0x05;
const OP_CHUNK: u8 = 0x06;
const OP_DATA_END: u8 = 0x0F;

/// What a walk over a recording's top-level records found, before anything is decompressed.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Scan {
    /// Bytes from the start that are whole, sound records: what the replay reads.
    pub sound_bytes: usize,
    /// Why the rest is not read (a truncated record, a chunk that claims more than the limits);
    /// None when the file is whole up to its data end.
    pub damage: Option<String>,
    /// Topics and schema names from the top-level (summary) channel records.
    pub topics: Vec<(String, String)>,
}

/// Walks the top-level records of an MCAP file (opcode, u64 length, content) checking every
/// length against the bytes that exist and every chunk's declared sizes against
/// [`MAX_CHUNK_BYTES`], without decompressing anything. The mcap crate's streaming reader is then
/// given only the sound prefix, so no header it reads can claim more than is there.
pub fn scan(bytes: &[u8]) -> Result<Scan, String> {
    if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
        return Err("not an MCAP file (no MCAP magic at the start)".into());
    }
    let mut scan = Scan::default();
    let mut schemas: std::collections::HashMap<u16, String> = Default::default();
    let mut channels: Vec<(u16, String)> = Vec::new();
    let mut offset = MAGIC.len();
    loop {
        scan.sound_bytes = offset;
        let rest = &bytes[offset..];
        if rest.is_empty() {
            scan.damage = Some(format!(
                "the file ends at byte {offset} without a data end record (cut short?)"
            ));
            break;
        }
        if rest.len() < 9 {
            scan.damage = Some(format!("a record header at byte {offset} is cut short"));
            break;
        }
        let opcode = rest[0];
        let length = u64::from_le_bytes(rest[1..9].try_into().expect("8 bytes"));
        if length > (rest.len() - 9) as u64 {
            scan.damage = Some(format!(
                "the record at byte {offset} claims {length} bytes; {} remain (cut short or corrupt)",
                rest.len() - 9
            ));
            // A chunk cut short (a plausible length, a sound header) still holds whole messages:
            // the streaming reader decompresses what is there and stops at the end of the bytes.
            // A length beyond any chunk's is corruption, not a cut.
            if opcode == OP_CHUNK && length <= MAX_CHUNK_BYTES && check_chunk_header(&rest[9..]).is_ok() {
                scan.sound_bytes = bytes.len();
            }
            break;
        }
        let content = &rest[9..9 + length as usize];
        match opcode {
            OP_CHUNK => {
                if let Err(reason) = check_chunk(content) {
                    scan.damage = Some(format!("the chunk at byte {offset}: {reason}"));
                    break;
                }
            }
            OP_DATA_END => {
                scan.sound_bytes = offset + 9 + length as usize;
                // The summary follows: read on for its channel records, which name the topics.
                let mut at = scan.sound_bytes;
                while bytes.len() - at >= 9 {
                    let op = bytes[at];
                    let len = u64::from_le_bytes(bytes[at + 1..at + 9].try_into().expect("8 bytes"));
                    if len > (bytes.len() - at - 9) as u64 {
                        break;
                    }
                    note_channel(op, &bytes[at + 9..at + 9 + len as usize], &mut schemas, &mut channels);
                    at += 9 + len as usize;
                }
                break;
            }
            op => note_channel(op, content, &mut schemas, &mut channels),
        }
        offset += 9 + length as usize;
    }
    let mut seen = std::collections::HashSet::new();
    for (schema_id, topic) in channels {
        if seen.insert(topic.clone()) {
            scan.topics
                .push((topic, schemas.get(&schema_id).cloned().unwrap_or_default()));
        }
    }
    Ok(scan)
}

/// Notes a top-level schema or channel record (the others are ignored here).
fn note_channel(
    opcode: u8,
    content: &[u8],
    schemas: &mut std::collections::HashMap<u16, String>,
    channels: &mut Vec<(u16, String)>,
) {
    match opcode {
        OP_SCHEMA => {
            if let Some((id, name)) = read_schema(content) {
                schemas.insert(id, name);
            }
        }
        OP_CHANNEL => {
            if let Some((_, schema_id, topic)) = read_channel(content) {
                channels.push((schema_id, topic));
            }
        }
        _ => {}
    }
}

/// A chunk's header (start and end time, uncompressed size and CRC, compression, records
/// length): its sizes within the limits and a compression the reader knows. Returns the
/// uncompressed size, the compression, the records length and where the records start.
fn check_chunk_header(content: &[u8]) -> Result<(u64, String, u64, usize), String> {
    let mut at = 16; // message start and end times
    let uncompressed = read_u64(content, &mut at).ok_or("header cut short")?;
    at += 4; // uncompressed CRC
    let compression = read_string(content, &mut at).ok_or("compression name cut short")?;
    let records = read_u64(content, &mut at).ok_or("header cut short")?;
    if uncompressed > MAX_CHUNK_BYTES {
        return Err(format!(
            "it claims {uncompressed} bytes uncompressed; at most {MAX_CHUNK_BYTES} are read"
        ));
    }
    match compression.as_str() {
        "" | "zstd" | "lz4" => Ok((uncompressed, compression, records, at)),
        other => Err(format!("unknown compression '{other}'")),
    }
}

/// A whole chunk: a sound header whose records length fits in the chunk.
fn check_chunk(content: &[u8]) -> Result<(), String> {
    let (uncompressed, compression, records, at) = check_chunk_header(content)?;
    if records > (content.len().saturating_sub(at)) as u64 {
        return Err(format!(
            "its records claim {records} bytes; the chunk holds {}",
            content.len() - at
        ));
    }
    if compression.is_empty() {
        if uncompressed != records {
            return Err(format!(
                "uncompressed, its records are {records} bytes but it claims {uncompressed}"
            ));
        }
        // Uncompressed records can be checked here: each must end within the chunk.
        let inner = &content[at..at + records as usize];
        let mut offset = 0usize;
        while offset < inner.len() {
            let header = inner
                .get(offset..offset + 9)
                .ok_or("a record header inside it is cut short")?;
            let length = u64::from_le_bytes(header[1..9].try_into().expect("8 bytes"));
            if length > (inner.len() - offset - 9) as u64 {
                return Err(format!(
                    "a record inside it claims {length} bytes; {} remain in the chunk",
                    inner.len() - offset - 9
                ));
            }
            offset += 9 + length as usize;
        }
    }
    Ok(())
}

fn read_u16(bytes: &[u8], at: &mut usize) -> Option<u16> {
    let value = u16::from_le_bytes(bytes.get(*at..*at + 2)?.try_into().ok()?);
    *at += 2;
    Some(value)
}

fn read_u32(bytes: &[u8], at: &mut usize) -> Option<u32> {
    let value = u32::from_le_bytes(bytes.get(*at..*at + 4)?.try_into().ok()?);
    *at += 4;
    Some(value)
}

fn read_u64(bytes: &[u8], at: &mut usize) -> Option<u64> {
    let value = u64::from_le_bytes(bytes.get(*at..*at + 8)?.try_into().ok()?);
    *at += 8;
    Some(value)
}

fn read_string(bytes: &[u8], at: &mut usize) -> Option<String> {
    let length = read_u32(bytes, at)? as usize;
    let text = bytes.get(*at..at.checked_add(length)?)?;
    *at += length;
    Some(String::from_utf8_lossy(text).into_owned())
}

fn read_schema(content: &[u8]) -> Option<(u16, String)> {
    let mut at = 0;
    let id = read_u16(content, &mut at)?;
    Some((id, read_string(content, &mut at)?))
}

/// A channel record's id, schema id and topic.
fn read_channel(content: &[u8]) -> Option<(u16, u16, String)> {
    let mut at = 0;
    let id = read_u16(content, &mut at)?;
    let schema_id = read_u16(content, &mut at)?;
    Some((id, schema_id, read_string(content, &mut at)?))
}

/// One message of a recording, with its channel's topic and schema name.
#[derive(Debug, Clone)]
pub struct RecordedMessage {
    pub topic: Arc<str>,
    pub schema: Arc<str>,
    pub log_time: u64,
    pub data: Vec<u8>,
}

/// The messages of a recording's sound prefix (see [`scan`]), in file order, decompressing
/// chunks as they come, with every record length (inside chunks too) held to
/// `record_length_limit` and no read larger than the bytes that remain. Replaces the mcap crate's
/// `MessageStream`, whose chunk reader reserves whatever an inner record's length claims. A
/// damaged record ends the stream with its error.
pub struct BoundedMessages<'a> {
    bytes: &'a [u8],
    at: usize,
    reader: mcap::sans_io::LinearReader,
    schemas: std::collections::HashMap<u16, Arc<str>>,
    channels: std::collections::HashMap<u16, (Arc<str>, Arc<str>)>,
    done: bool,
}

impl<'a> BoundedMessages<'a> {
    /// `bytes`: the whole file (magic included), as far as it is sound; `record_length_limit`:
    /// the largest record accepted, inside chunks too.
    pub fn new(bytes: &'a [u8], record_length_limit: usize) -> Self {
        let options = mcap::sans_io::LinearReaderOptions::default()
            .with_record_length_limit(record_length_limit)
            .with_skip_end_magic(true);
        Self {
            bytes,
            at: 0,
            reader: mcap::sans_io::LinearReader::new_with_options(options),
            schemas: Default::default(),
            channels: Default::default(),
            done: false,
        }
    }
}

impl Iterator for BoundedMessages<'_> {
    type Item = Result<RecordedMessage, String>;

    fn next(&mut self) -> Option<Self::Item> {
        use mcap::sans_io::LinearReadEvent;
        while !self.done {
            let event = match self.reader.next_event()? {
                Ok(event) => event,
                Err(e) => {
                    self.done = true;
                    return Some(Err(e.to_string()));
                }
            };
            match event {
                LinearReadEvent::ReadRequest(wanted) => {
                    // Never more than what is left: a corrupt length cannot make this allocate.
                    let n = wanted.min(self.bytes.len() - self.at);
                    self.reader.insert(n).copy_from_slice(&self.bytes[self.at..self.at + n]);
                    self.reader.notify_read(n);
                    self.at += n;
                }
                // Records are parsed here, every length checked against the record's bytes (the
                // mcap crate's parser reserves whatever a string length claims).
                LinearReadEvent::Record { data, opcode } => match opcode {
                    OP_SCHEMA => {
                        if let Some((id, name)) = read_schema(data) {
                            self.schemas.insert(id, name.into());
                        }
                    }
                    OP_CHANNEL => {
                        if let Some((id, schema_id, topic)) = read_channel(data) {
                            let schema = self.schemas.get(&schema_id).cloned().unwrap_or_else(|| "".into());
                            self.channels.insert(id, (topic.into(), schema));
                        }
                    }
                    OP_MESSAGE => {
                        let mut at = 0;
                        let (Some(channel_id), Some(_sequence)) = (read_u16(data, &mut at), read_u32(data, &mut at))
                        else {
                            self.done = true;
                            return Some(Err("a message record cut short".into()));
                        };
                        let (Some(log_time), Some(_publish_time)) = (read_u64(data, &mut at), read_u64(data, &mut at))
                        else {
                            self.done = true;
                            return Some(Err("a message record cut short".into()));
                        };
                        let Some((topic, schema)) = self.channels.get(&channel_id).cloned() else {
                            self.done = true;
                            return Some(Err(format!("a message on unknown channel {channel_id}")));
                        };
                        return Some(Ok(RecordedMessage {
                            topic,
                            schema,
                            log_time,
                            data: data[at..].to_vec(),
                        }));
                    }
                    OP_DATA_END => self.done = true,
                    _ => {}
                },
            }
        }
        None
    }
}

/// The records of `bytes` no larger than the file itself or [`MAX_CHUNK_BYTES`].
pub fn messages(bytes: &[u8]) -> BoundedMessages<'_> {
    BoundedMessages::new(bytes, bytes.len().min(MAX_CHUNK_BYTES as usize))
}

/// What a recording holds for the node: its topics and their schema names. From the summary's
/// channel records when there are some; otherwise (a file cut short has no summary) from the
/// channels of the messages in its sound prefix.
pub fn topics(bytes: &[u8], path: &Path) -> Result<Vec<(String, String)>, McapSourceError> {
    let format = |message: String| McapSourceError::Format {
        path: path.to_path_buf(),
        message,
    };
    let scanned = scan(bytes).map_err(format)?;
    if !scanned.topics.is_empty() {
        return Ok(scanned.topics);
    }
    let mut found: Vec<(String, String)> = Vec::new();
    for message in messages(&bytes[..scanned.sound_bytes]) {
        let Ok(message) = message else { break };
        if !found.iter().any(|(t, _)| **t == *message.topic) {
            found.push((message.topic.to_string(), message.schema.to_string()));
        }
    }
    Ok(found)
}

enum Wanted {
    Clouds(String),
    Depth { image: String, info: String },
}

fn choose_topic(
    settings: &SourceSettings,
    topics: &[(String, String)],
    path: &Path,
) -> Result<Wanted, McapSourceError> {
    let listing = || {
        topics
            .iter()
            .map(|(t, s)| format!("{t} ({s})"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    let error = |message: String| McapSourceError::Topic {
        path: path.to_path_buf(),
        message,
    };
    let schema_of = |topic: &str| topics.iter().find(|(t, _)| t == topic).map(|(_, s)| s.as_str());
    let topic = match &settings.topic {
        Some(topic) => topic.clone(),
        None => topics
            .iter()
            .find(|(_, s)| s == POINT_CLOUD2)
            .map(|(t, _)| t.clone())
            .ok_or_else(|| error(format!("no {POINT_CLOUD2} topic; set `topic` (topics: {})", listing())))?,
    };
    match schema_of(&topic) {
        Some(POINT_CLOUD2) => Ok(Wanted::Clouds(topic)),
        Some(IMAGE) => {
            let info = settings.camera_info_topic.clone().unwrap_or_else(|| {
                let parent = topic.rsplit_once('/').map(|(p, _)| p).unwrap_or("");
                format!("{parent}/camera_info")
            });
            if schema_of(&info) != Some(CAMERA_INFO) {
                return Err(error(format!(
                    "depth topic {topic} needs a {CAMERA_INFO} topic; '{info}' is not one; set `camera_info_topic` (topics: {})",
                    listing()
                )));
            }
            Ok(Wanted::Depth { image: topic, info })
        }
        Some(other) => Err(error(format!(
            "topic {topic} carries {other}; the node reads {POINT_CLOUD2} or {IMAGE}"
        ))),
        None => Err(error(format!("no topic {topic} (topics: {})", listing()))),
    }
}

/// Replays the recording into `outlet`. Errors opening the recording end the source; a message
/// that does not decode is a rejection and the replay goes on.
pub fn run(settings: &SourceSettings, mut outlet: Outlet) -> Result<(), McapSourceError> {
    let path = settings.path.clone().unwrap_or_default();
    let files = recording_files(&path)?;
    let unit = settings.unit.unwrap_or(Unit::Metre);
    loop {
        // Original timing: message i is due at start + (log_time_i - log_time_0) / speed.
        let mut clock: Option<(Instant, u64)> = None;
        for file in &files {
            let handle = std::fs::File::open(file).map_err(|source| McapSourceError::Io {
                path: file.clone(),
                source,
            })?;
            // SAFETY: the map is read-only; a recording changed by another process while it is
            // replayed yields undecodable messages (rejections), not undefined behaviour in safe code
            // that only reads bytes.
            let mapped = unsafe { memmap2::Mmap::map(&handle) }.map_err(|source| McapSourceError::Io {
                path: file.clone(),
                source,
            })?;
            let bytes: &[u8] = &mapped;
            let wanted = choose_topic(settings, &topics(bytes, file)?, file)?;
            // Only the sound prefix goes to the mcap crate; what lies beyond is one rejection.
            let scanned = scan(bytes).map_err(|message| McapSourceError::Format {
                path: file.clone(),
                message,
            })?;
            let stream = messages(&bytes[..scanned.sound_bytes]);
            let mut unreadable = false;
            let mut intrinsics: Option<Arc<CameraIntrinsics>> = None;
            let mut waiting: Option<Vec<u8>> = None;
            for message in stream {
                if outlet.stopping() {
                    return Ok(());
                }
                let message = match message {
                    Ok(m) => m,
                    Err(e) => {
                        // A damaged chunk ends this file; what was read so far has been replayed.
                        outlet.reject(
                            format!("{}: unreadable record, rest of file skipped: {e}", file.display()),
                            None,
                        );
                        unreadable = true;
                        break;
                    }
                };
                let topic: &str = &message.topic;
                let decoded = match &wanted {
                    Wanted::Clouds(t) if topic == t => Some(
                        decode_point_cloud2(&message.data, settings.max_points)
                            .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite)),
                    ),
                    Wanted::Depth { info, .. } if topic == info => {
                        match decode_camera_info(&message.data) {
                            Ok((_, k)) => intrinsics = Some(Arc::new(k)),
                            Err(e) => log::warn!("{}: {topic}: CameraInfo ignored: {e}", file.display()),
                        }
                        // An image that came just before its camera's first CameraInfo goes now.
                        match (&intrinsics, waiting.take()) {
                            (Some(k), Some(image)) => Some(
                                decode_depth_image(&image, k, settings.depth_step, settings.max_points)
                                    .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite)),
                            ),
                            (_, image) => {
                                waiting = image;
                                None
                            }
                        }
                    }
                    Wanted::Depth { image, .. } if topic == image => match &intrinsics {
                        Some(k) => Some(
                            decode_depth_image(&message.data, k, settings.depth_step, settings.max_points)
                                .map(|c| (c.header.stamp_ns, c.points, c.dropped_non_finite)),
                        ),
                        None => {
                            // Wait for the first CameraInfo; an image it replaces is rejected.
                            let replaced = waiting.replace(message.data.to_vec());
                            replaced.map(|_| {
                                Err(crate::sources::ros2::CdrError::Invalid(
                                    "depth image with no CameraInfo before the next image".into(),
                                ))
                            })
                        }
                    },
                    _ => None,
                };
                let Some(decoded) = decoded else { continue };
                if settings.speed > 0.0 {
                    let (start, first) = *clock.get_or_insert((Instant::now(), message.log_time));
                    let offset = message.log_time.saturating_sub(first) as f64 / settings.speed;
                    let due = start + Duration::from_nanos(offset as u64);
                    if !outlet.wait_until(due) {
                        return Ok(());
                    }
                }
                let open = match decoded {
                    Ok((stamp, points, dropped)) => outlet.frame(PointCloud { points }, unit, Some(stamp), dropped),
                    Err(e) => outlet.reject(
                        format!("{} {topic} at log time {}: {e}", file.display(), message.log_time),
                        Some(message.log_time),
                    ),
                };
                if !open {
                    return Ok(());
                }
            }
            if let (false, Some(damage)) = (unreadable, &scanned.damage) {
                // The messages before the damage were replayed; the rest is one rejection.
                if !outlet.reject(format!("{}: rest of file skipped: {damage}", file.display()), None) {
                    return Ok(());
                }
            }
            if waiting.take().is_some()
                && !outlet.reject(
                    format!("{}: depth image with no CameraInfo after it", file.display()),
                    None,
                )
            {
                return Ok(());
            }
        }
        if !settings.repeat {
            return Ok(());
        }
    }
}
