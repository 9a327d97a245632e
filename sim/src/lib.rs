//! gdvae-sim: synthetic articulated subjects with known intrinsic shape (beta) and pose (theta),
//! the training datasets the kit learns from, and a simulated depth-camera feed that tests the node.
//!
//! Layout: `family` (beta -> skeleton + implicit body), `meshing` (implicit -> closed mesh),
//! `skinning` (rest mesh -> posed mesh), `mesh` (validity and distortion checks), `ply` (output),
//! `dataset` (folders of meshes + ground truth + splits), `distortion` (isometry measurements),
//! `motion` (30 Hz sequences with identity switches), `camera` (an OAK-D-like stereo depth camera),
//! `scenario` (motion seen by the camera), `ros2` (CDR messages), `recording` (MCAP files),
//! `feed` (the live zenoh feed).

pub mod camera;
pub mod dataset;
pub mod decimate;
pub mod distortion;
pub mod family;
pub mod feed;
pub mod implicit;
pub mod mesh;
pub mod meshing;
pub mod motion;
pub mod ply;
pub mod recording;
pub mod ros2;
pub mod scenario;
pub mod seeds;
pub mod skeleton;
pub mod skinning;
