//! gdvae-sim: synthetic articulated subjects with known intrinsic shape (beta) and pose (theta),
//! the training datasets the kit learns from, and a simulated depth-camera feed that tests the node.
//!
//! Layout: `family` (beta -> skeleton + implicit body), `meshing` (implicit -> closed mesh),
//! `skinning` (rest mesh -> posed mesh), `mesh` (validity and distortion checks), `ply` (output),
//! `dataset` (folders of meshes + ground truth + splits), `distortion` (isometry measurements).

pub mod dataset;
pub mod decimate;
pub mod distortion;
pub mod family;
pub mod implicit;
pub mod mesh;
pub mod meshing;
pub mod ply;
pub mod seeds;
pub mod skeleton;
pub mod skinning;
