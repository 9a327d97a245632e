//! One file's bytes through the file source's readers: the first byte picks PLY, PCD, OBJ or XYZ,
//! the rest is the file (written to a private temporary file, as the readers take paths).
#![no_main]

use gdvae_node::sources::files::{read_cloud, FileOptions};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Some((&kind, body)) = data.split_first() else { return };
    let extension = ["ply", "pcd", "obj", "xyz"][kind as usize % 4];
    let path = std::env::temp_dir().join(format!("gdvae-fuzz-{}.{extension}", std::process::id()));
    if std::fs::write(&path, body).is_err() {
        return;
    }
    let options = FileOptions {
        max_points: 100_000,
        mesh_samples: 256,
        ..FileOptions::default()
    };
    let _ = read_cloud(&path, &options);
});
