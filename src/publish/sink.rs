//! What a sink is (`Sink`: one way out of the node) and how publishing fails (`PublishError`): the
//! leaf every sink implements, and the publisher over them reads.

use crate::state::Output;

#[derive(Debug, thiserror::Error)]
pub enum PublishError {
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("JSON lines sink {path}: {source}")]
    Sink { path: String, source: std::io::Error },
    #[error("encoding a message: {0}")]
    Encode(String),
    #[error("ROS 2: {0}")]
    Ros2(String),
    #[error("Foxglove live view: {0}")]
    Foxglove(String),
    #[error("decoded shape: {0}")]
    Shape(String),
    #[error("every output has failed; the message is lost")]
    Closed,
}

/// One way out of the node.
pub trait Sink: Send {
    /// Sends one message (a state with its identity event, or a rejection).
    fn publish(&mut self, output: &Output) -> Result<(), PublishError>;
    /// Whether it still takes messages: a sink that failed for good closes itself.
    fn is_open(&self) -> bool {
        true
    }
    /// Flushes what it buffers; an error if it failed at any time during the run.
    fn flush(&mut self) -> Result<(), PublishError> {
        Ok(())
    }
}
