//! One message as a recording's storage gives it, and the size limit every storage reader holds a
//! record to: the leaf that the readers (`mcap`, `rosbag2`) and the recording walk share.

use std::borrow::Cow;
use std::sync::Arc;

/// The largest record a reader hands over or decompresses (bytes). A chunk's header says how large
/// it is uncompressed; a hostile or corrupt header would otherwise make the reader allocate whatever
/// it claims. 512 MiB holds any frame `max_points` allows at its default (4 M points x 32 bytes)
/// four times over.
pub const MAX_RECORD_BYTES: u64 = 512 << 20;

/// One message of a recording, with its channel's topic and schema (type) name. The walk over a
/// recording lends each message's bytes where they lie (a decompressed chunk, a database row):
/// a frame is decoded from there, never copied first.
#[derive(Debug, Clone)]
pub struct RecordedMessage<'a> {
    pub topic: Arc<str>,
    pub schema: Arc<str>,
    /// When it was recorded (ns): MCAP's log time, rosbag2 sqlite3's timestamp.
    pub log_time: u64,
    pub data: Cow<'a, [u8]>,
}

impl RecordedMessage<'_> {
    /// The message with its own copy of the bytes.
    pub fn into_owned(self) -> RecordedMessage<'static> {
        RecordedMessage {
            topic: self.topic,
            schema: self.schema,
            log_time: self.log_time,
            data: Cow::Owned(self.data.into_owned()),
        }
    }
}
