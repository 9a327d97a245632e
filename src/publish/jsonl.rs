//! The JSON-lines sink: one line per published message (states, identity events, rejections) to a
//! file or stdout, line by line, so that whoever tails it sees each state when it is published.
//! A write error closes it with one log line; the other sinks go on and the run fails at its end.

use std::io::Write;

use super::sink::{PublishError, Sink};
use crate::state::Output;

pub struct JsonLines {
    out: Option<Box<dyn Write + Send>>,
    path: String,
    /// Why it closed, reported once more by `flush`.
    failed: Option<std::io::Error>,
}

impl JsonLines {
    /// A file path, or "-" for stdout.
    pub fn create(path: &str) -> Result<Self, PublishError> {
        let out: Box<dyn Write + Send> = if path == "-" {
            Box::new(std::io::LineWriter::new(std::io::stdout()))
        } else {
            let file = std::fs::File::create(path).map_err(|source| PublishError::Sink {
                path: path.to_string(),
                source,
            })?;
            Box::new(std::io::LineWriter::new(file))
        };
        Ok(Self {
            out: Some(out),
            path: path.to_string(),
            failed: None,
        })
    }

    fn write<T: serde::Serialize>(&mut self, message: &T) -> Result<(), PublishError> {
        let line = serde_json::to_string(message).map_err(|e| PublishError::Encode(e.to_string()))?;
        if let Some(out) = self.out.as_mut() {
            if let Err(source) = writeln!(out, "{line}") {
                self.close(source);
            }
        }
        Ok(())
    }

    fn close(&mut self, source: std::io::Error) {
        log::error!(
            "JSON lines sink {}: {source}; closed (any other output goes on; the run will fail at its end)",
            self.path
        );
        self.out = None;
        self.failed = Some(source);
    }
}

impl Sink for JsonLines {
    fn publish(&mut self, output: &Output) -> Result<(), PublishError> {
        match output {
            Output::State(state) => {
                self.write(state.as_ref())?;
                if let Some(event) = state.event_message() {
                    self.write(&event)?;
                }
                Ok(())
            }
            Output::Rejected(rejected) => self.write(rejected),
        }
    }

    fn is_open(&self) -> bool {
        self.out.is_some()
    }

    fn flush(&mut self) -> Result<(), PublishError> {
        if let Some(out) = self.out.as_mut() {
            if let Err(source) = out.flush() {
                self.close(source);
            }
        }
        match self.failed.take() {
            Some(source) => Err(PublishError::Sink {
                path: self.path.clone(),
                source,
            }),
            None => Ok(()),
        }
    }
}
