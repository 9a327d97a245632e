//! MCAP, read within bounds: a walk over the top-level records that checks every length against
//! the bytes that exist before anything is decompressed (`scan`), and a message reader built on the
//! mcap crate's sans-io reader that holds every record, inside chunks too, to a limit (`messages`).
//! The replay source (`recording`) reads MCAP files through these two.

use std::sync::Arc;

use super::message::{RecordedMessage, MAX_RECORD_BYTES};

/// Largest chunk the reader will decompress (bytes): the readers' one record limit.
pub const MAX_CHUNK_BYTES: u64 = MAX_RECORD_BYTES;

pub const MAGIC: &[u8] = b"\x89MCAP0\r\n";
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
            if opcode == OP_CHUNK && length <= MAX_CHUNK_BYTES {
                match check_cut_chunk(&rest[9..]) {
                    Ok(()) => scan.sound_bytes = bytes.len(),
                    Err(reason) => scan.damage = Some(format!("the chunk at byte {offset}: {reason}")),
                }
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
pub fn check_chunk_header(content: &[u8]) -> Result<(u64, String, u64, usize), String> {
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
        check_inner_records(&content[at..at + records as usize], records)?;
    }
    Ok(())
}

/// A chunk cut short by the end of the file: a sound header, and for an uncompressed one, every
/// inner record that starts in the bytes there are must end within the records length the header
/// claims (the reader stops at the end of the bytes, not at a record that overruns its chunk).
fn check_cut_chunk(content: &[u8]) -> Result<(), String> {
    let (uncompressed, compression, records, at) = check_chunk_header(content)?;
    if compression.is_empty() {
        if uncompressed != records {
            return Err(format!(
                "uncompressed, its records are {records} bytes but it claims {uncompressed}"
            ));
        }
        let available = content.len().saturating_sub(at).min(records as usize);
        check_inner_records(&content[at..at + available], records)?;
    }
    Ok(())
}

/// Walks the records of an uncompressed chunk: `inner` is what there is of them, `claimed` the
/// records length of the chunk's header. Each record's header and content must end within
/// `claimed`; a record cut by the end of `inner` (and so of the file) is left to the reader.
fn check_inner_records(inner: &[u8], claimed: u64) -> Result<(), String> {
    let mut offset = 0u64;
    while offset < inner.len() as u64 {
        let left = claimed - offset;
        if left < 9 {
            return Err(format!(
                "a record header inside it runs {} bytes past its end",
                9 - left
            ));
        }
        let Some(header) = inner.get(offset as usize..offset as usize + 9) else {
            break; // cut by the end of the file
        };
        let length = u64::from_le_bytes(header[1..9].try_into().expect("8 bytes"));
        if length > left - 9 {
            return Err(format!(
                "a record inside it claims {length} bytes; {} remain in the chunk",
                left - 9
            ));
        }
        offset += 9 + length;
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

/// The messages of a recording's sound prefix (see [`scan`]), in file order, decompressing
/// each chunk once as it comes, with every record length (inside chunks too) held to
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

impl BoundedMessages<'_> {
    /// Hands each message, its bytes lent from the decompressed chunk, to `each` until it returns
    /// false; a damaged record is handed over as `Err` and ends the walk. The walk resumes where it
    /// stopped when called again.
    pub fn walk(&mut self, mut each: impl FnMut(Result<RecordedMessage<'_>, String>) -> bool) {
        use mcap::sans_io::LinearReadEvent;
        while !self.done {
            let event = match self.reader.next_event() {
                None => return,
                Some(Ok(event)) => event,
                Some(Err(e)) => {
                    self.done = true;
                    each(Err(e.to_string()));
                    return;
                }
            };
            match event {
                LinearReadEvent::ReadRequest(wanted) => {
                    // Never more than what is left: a corrupt length cannot make this allocate.
                    let n = wanted.min(self.bytes.len() - self.at);
                    if n == 0 {
                        // The end of the sound prefix: whatever lies beyond is the scan's to report.
                        self.done = true;
                        return;
                    }
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
                        let message = read_message(&self.channels, data);
                        if message.is_err() {
                            self.done = true;
                        }
                        if !each(message) || self.done {
                            return;
                        }
                    }
                    OP_DATA_END => self.done = true,
                    _ => {}
                },
            }
        }
    }
}

/// A message record: its channel's topic and schema, its log time and its payload (lent).
fn read_message<'a>(
    channels: &std::collections::HashMap<u16, (Arc<str>, Arc<str>)>,
    data: &'a [u8],
) -> Result<RecordedMessage<'a>, String> {
    let mut at = 0;
    let (Some(channel_id), Some(_sequence)) = (read_u16(data, &mut at), read_u32(data, &mut at)) else {
        return Err("a message record cut short".into());
    };
    let (Some(log_time), Some(_publish_time)) = (read_u64(data, &mut at), read_u64(data, &mut at)) else {
        return Err("a message record cut short".into());
    };
    let Some((topic, schema)) = channels.get(&channel_id).cloned() else {
        return Err(format!("a message on unknown channel {channel_id}"));
    };
    Ok(RecordedMessage {
        topic,
        schema,
        log_time,
        data: std::borrow::Cow::Borrowed(&data[at..]),
    })
}

/// The messages one by one, each with its own copy of its bytes (for a caller that keeps them;
/// a replay uses [`BoundedMessages::walk`]).
impl Iterator for BoundedMessages<'_> {
    type Item = Result<RecordedMessage<'static>, String>;

    fn next(&mut self) -> Option<Self::Item> {
        let mut next = None;
        self.walk(|message| {
            next = Some(message.map(RecordedMessage::into_owned));
            false
        });
        next
    }
}

/// The records of `bytes` no larger than the file itself or [`MAX_CHUNK_BYTES`].
pub fn messages(bytes: &[u8]) -> BoundedMessages<'_> {
    BoundedMessages::new(bytes, bytes.len().min(MAX_CHUNK_BYTES as usize))
}

/// What a recording holds for the node: its topics and their schema names. From the summary's
/// channel records when there are some; otherwise (a file cut short has no summary) from the
/// channels of the messages in its sound prefix.
pub fn topics(bytes: &[u8]) -> Result<Vec<(String, String)>, String> {
    let scanned = scan(bytes)?;
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
