//! The node's integration tests: one binary, a module per area, shared helpers.

mod config;
mod files;
mod helpers;
mod model;
mod pipeline;
mod ros2;
mod sampling;
mod track;
