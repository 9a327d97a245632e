//! One message as a recording's storage gives it, and the size limit every storage reader holds a
//! record to: the leaf that the readers (`mcap`, `rosbag2`) and the recording walk share.

use std::sync::Arc;

/// The largest record a reader hands over or decompresses (bytes). A chunk's header says how large
/// it is uncompressed; a hostile or corrupt header would otherwise make the reader allocate whatever
/// it claims. 512 MiB holds any frame `max_points` allows at its default (4 M points x 32 bytes)
/// four times over.
pub const MAX_RECORD_BYTES: u64 = 512 << 20;

/// One message of a recording, with its channel's topic and schema (type) name.
#[derive(Debug, Clone)]
pub struct RecordedMessage {
    pub topic: Arc<str>,
    pub schema: Arc<str>,
    /// When it was recorded (ns): MCAP's log time, rosbag2 sqlite3's timestamp.
    pub log_time: u64,
    pub data: Vec<u8>,
}
