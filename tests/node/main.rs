//! The node's integration tests: one binary, a module per area.

mod files;
mod model;
mod ros2;
mod sampling;
