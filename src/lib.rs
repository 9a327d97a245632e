//! gdvae-node: turns point-cloud frames into GDVAE++ rotation, pose and shape codes.
//!
//! Stages (see ARCHITECTURE.md): `sources` (files, recordings, network) -> `prepare` (units,
//! centring, scaling, subsampling to the model's N_p) -> `runtime` (ONNX Runtime encoder of a
//! checked `bundle`) -> tracking and publishing (to come).

pub mod bundle;
pub mod cloud;
pub mod prepare;
pub mod runtime;
pub mod sources;
