//! rosbag2 folders and their sqlite3 storage (Humble's default; `.db3`).
//!
//! A folder is a bag when it holds `metadata.yaml`: its `storage_identifier` says how the files it
//! lists in `relative_file_paths` are stored (`sqlite3` or `mcap`), whatever their extension. A
//! sqlite3 file is read through SQLite itself (compiled in), opened read-only, with every message
//! held to the size limit SQLite enforces before it hands a row over.

use std::path::{Path, PathBuf};

use rusqlite::{Connection, OpenFlags};

use super::message::{RecordedMessage, MAX_RECORD_BYTES};

/// How a recording file stores its messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Storage {
    Mcap,
    Sqlite3,
}

/// The largest message accepted from a sqlite3 bag (bytes): the same bound as an MCAP chunk.
pub const MAX_MESSAGE_BYTES: usize = MAX_RECORD_BYTES as usize;

/// What a bag's `metadata.yaml` says about its files.
#[derive(Debug, Clone, PartialEq)]
pub struct Metadata {
    pub storage: Storage,
    /// The bag's files, in the order the metadata lists them (their playback order).
    pub files: Vec<PathBuf>,
}

/// Reads `<folder>/metadata.yaml`. An unknown storage plugin, compression, or a listed file that
/// is missing is an error naming the file and the reason.
pub fn read_metadata(folder: &Path) -> Result<Metadata, String> {
    let path = folder.join("metadata.yaml");
    let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e}", path.display()))?;
    parse_metadata(&text, folder)
}

/// Most structure one line of `metadata.yaml` may open before its content (indentation and block
/// indicators: each nesting level of a block collection takes at least one column), and most
/// nested flow brackets. rosbag2 writes a few levels; the limits keep yaml-rust2, which recurses
/// once per level, far from the end of a source thread's stack.
const MAX_STRUCTURE_COLUMNS: usize = 256;
const MAX_FLOW_DEPTH: usize = 64;

/// Refuses YAML nested deeper than a metadata file can be (found by fuzzing: 28 KB of `- - - ...`
/// overflowed the stack inside yaml-rust2's scanner, which aborts the whole process).
fn check_nesting(text: &str) -> Result<(), String> {
    let mut flow_depth = 0usize;
    for (number, line) in text.lines().enumerate() {
        let structure = line
            .chars()
            .take_while(|c| matches!(c, ' ' | '\t' | '-' | '?' | ':'))
            .count();
        if structure > MAX_STRUCTURE_COLUMNS {
            return Err(format!(
                "line {}: nested deeper than a metadata file can be ({structure} columns of indentation and indicators, at most {MAX_STRUCTURE_COLUMNS})",
                number + 1
            ));
        }
        for c in line.chars() {
            match c {
                '[' | '{' => flow_depth += 1,
                ']' | '}' => flow_depth = flow_depth.saturating_sub(1),
                _ => {}
            }
            if flow_depth > MAX_FLOW_DEPTH {
                return Err(format!(
                    "line {}: more than {MAX_FLOW_DEPTH} nested brackets",
                    number + 1
                ));
            }
        }
    }
    Ok(())
}

/// `metadata.yaml`'s text, for the bag in `folder` (listed files are checked to exist there).
pub fn parse_metadata(text: &str, folder: &Path) -> Result<Metadata, String> {
    let path = folder.join("metadata.yaml");
    let fail = |message: String| format!("{}: {message}", path.display());
    check_nesting(text).map_err(fail)?;
    let documents = yaml_rust2::YamlLoader::load_from_str(text).map_err(|e| fail(format!("not YAML: {e}")))?;
    let info = documents
        .first()
        .map(|d| &d["rosbag2_bagfile_information"])
        .filter(|i| !i.is_badvalue())
        .ok_or_else(|| fail("no rosbag2_bagfile_information: not a rosbag2 metadata file".into()))?;
    let storage = match info["storage_identifier"].as_str() {
        Some("sqlite3") => Storage::Sqlite3,
        Some("mcap") => Storage::Mcap,
        Some(other) => {
            return Err(fail(format!(
                "storage plugin '{other}' is not supported (the node reads sqlite3 and mcap)"
            )))
        }
        None => return Err(fail("no storage_identifier".into())),
    };
    let compression = info["compression_format"].as_str().unwrap_or("");
    if !compression.is_empty() {
        return Err(fail(format!(
            "compressed bag ({compression}, mode {}): decompress it first (`ros2 bag decompress`)",
            info["compression_mode"].as_str().unwrap_or("?")
        )));
    }
    let files: Vec<PathBuf> = info["relative_file_paths"]
        .as_vec()
        .ok_or_else(|| fail("no relative_file_paths".into()))?
        .iter()
        .map(|p| p.as_str().map(|p| folder.join(p)))
        .collect::<Option<_>>()
        .ok_or_else(|| fail("relative_file_paths holds something that is not a path".into()))?;
    if files.is_empty() {
        return Err(fail("the bag lists no files".into()));
    }
    if let Some(missing) = files.iter().find(|f| !f.is_file()) {
        return Err(fail(format!("lists {}, which does not exist", missing.display())));
    }
    Ok(Metadata { storage, files })
}

/// Whether `bytes` begin like a SQLite database.
pub fn is_sqlite(bytes: &[u8]) -> bool {
    bytes.starts_with(b"SQLite format 3\0")
}

/// One sqlite3 bag file, open for reading.
pub struct Sqlite3Bag {
    path: PathBuf,
    connection: Connection,
}

impl Sqlite3Bag {
    /// Opens the file read-only; a file that is not a rosbag2 database is an error naming it.
    pub fn open(path: &Path) -> Result<Self, String> {
        let fail = |e: rusqlite::Error| format!("{}: not a readable rosbag2 sqlite3 file: {e}", path.display());
        let connection =
            Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX)
                .map_err(fail)?;
        // Rows larger than the limit are refused by SQLite before they are loaded.
        connection
            .set_limit(rusqlite::limits::Limit::SQLITE_LIMIT_LENGTH, MAX_MESSAGE_BYTES as i32)
            .map_err(fail)?;
        let bag = Self {
            path: path.to_path_buf(),
            connection,
        };
        bag.topics()?;
        Ok(bag)
    }

    /// The bag's topics and their types, in the order of their ids.
    pub fn topics(&self) -> Result<Vec<(String, String)>, String> {
        let fail = |e: rusqlite::Error| format!("{}: reading its topics: {e}", self.path.display());
        let mut statement = self
            .connection
            .prepare("SELECT name, type FROM topics ORDER BY id")
            .map_err(fail)?;
        let rows = statement
            .query_map([], |row| Ok((row.get::<_, String>(0)?, row.get::<_, String>(1)?)))
            .map_err(fail)?;
        rows.collect::<Result<Vec<_>, _>>().map_err(fail)
    }

    /// Hands the messages of `topics` to `each` in the order they were recorded, until it returns
    /// false. An error reading a row (a damaged database) ends the walk: `Err` with the reason,
    /// after every message before it was handed over.
    pub fn for_each(&self, topics: &[&str], mut each: impl FnMut(RecordedMessage<'_>) -> bool) -> Result<(), String> {
        let fail = |e: rusqlite::Error| format!("{}: {e}", self.path.display());
        let wanted = vec!["?"; topics.len()].join(", ");
        let mut statement = self
            .connection
            .prepare(&format!(
                "SELECT t.name, t.type, m.timestamp, m.data FROM messages m JOIN topics t ON m.topic_id = t.id \
                 WHERE t.name IN ({wanted}) ORDER BY m.timestamp, m.id"
            ))
            .map_err(fail)?;
        let mut rows = statement.query(rusqlite::params_from_iter(topics)).map_err(fail)?;
        let mut names: std::collections::HashMap<(String, String), (std::sync::Arc<str>, std::sync::Arc<str>)> =
            Default::default();
        while let Some(row) = rows.next().map_err(fail)? {
            let topic: String = row.get(0).map_err(fail)?;
            let schema: String = row.get(1).map_err(fail)?;
            let timestamp: i64 = row.get(2).map_err(fail)?;
            let data = row.get_ref(3).map_err(fail)?.as_blob().map_err(|e| fail(e.into()))?;
            let (topic, schema) = names
                .entry((topic, schema))
                .or_insert_with_key(|(t, s)| (t.as_str().into(), s.as_str().into()))
                .clone();
            let message = RecordedMessage {
                topic,
                schema,
                log_time: u64::try_from(timestamp).unwrap_or(0),
                data: std::borrow::Cow::Borrowed(data),
            };
            if !each(message) {
                break;
            }
        }
        Ok(())
    }
}
