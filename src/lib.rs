//! gdvae-node: turns point-cloud frames into GDVAE++ rotation, pose and shape codes, tracks them
//! over time and publishes them.
//!
//! Stages (see ARCHITECTURE.md): `sources` (files, recordings, network) -> `prepare` (units,
//! gravity frame, crop, ground, outliers, centring, scaling, subsampling to N_p) -> `runtime`
//! (ONNX Runtime encoder of a checked `bundle`, optionally over turned `yaw_copies`) -> `track` (shape fusion, identity changes, pose
//! smoothing) -> `publish` (sinks: zenoh, JSON lines, ROS 2). `pipeline` joins them; `config`
//! describes a run; `ros2` holds ROS 2's wire conventions over zenoh.

pub mod benchmark;
pub mod bundle;
pub mod cloud;
pub mod config;
mod contain;
pub mod cpu;
pub mod encoding;
pub mod evaluate;
pub mod pipeline;
pub mod prepare;
pub mod publish;
pub mod ros2;
pub mod runtime;
pub mod sources;
pub mod state;
pub mod stats;
pub mod track;
pub mod yaw_copies;
pub mod zenoh_session;
