//! The node's integration tests: one binary, a module per area, shared helpers.

mod association;
mod config;
mod evaluate;
mod files;
mod helpers;
mod hostile;
mod inputs;
mod model;
mod pipeline;
mod prepare;
mod ros2;
mod sampling;
mod track;
mod zenoh_security;
