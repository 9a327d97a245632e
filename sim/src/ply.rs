//! Binary PLY output: the mesh format at the sim -> training-kit seam.
//!
//! Little-endian float32 vertices and `uchar`-counted int32 triangle lists: the layout every mesh
//! tool (trimesh, Open3D, MeshLab, Blender, ply-rs) reads.

use std::io::{self, Write};

use crate::mesh::Mesh;

pub fn write_ply(mesh: &Mesh, comment: &str, out: &mut impl Write) -> io::Result<()> {
    let comment = comment.replace(['\n', '\r'], " ");
    write!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment {comment}\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        mesh.positions.len(),
        mesh.triangles.len()
    )?;
    let mut body = Vec::with_capacity(12 * mesh.positions.len() + 13 * mesh.triangles.len());
    for p in &mesh.positions {
        for c in [p.x, p.y, p.z] {
            body.extend_from_slice(&(c as f32).to_le_bytes());
        }
    }
    for t in &mesh.triangles {
        body.push(3u8);
        for &v in t {
            body.extend_from_slice(&(v as i32).to_le_bytes());
        }
    }
    out.write_all(&body)
}
