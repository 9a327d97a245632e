//! The simulator's integration tests: one binary, a module per area.

mod anatomy;
mod cli;
mod dataset;
mod meshes;
mod sensor;
mod util;
