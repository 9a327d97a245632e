//! Triangle meshes: the sim's output and the checks that make it trustworthy training data.
//!
//! The training kit computes Laplace-Beltrami spectra on these meshes; a hole, a non-manifold edge
//! or a flipped face silently corrupts a spectrum. So every mesh can be checked here, and the
//! articulation's departure from isometry (the kit's learning signal) can be measured.

use std::collections::HashMap;

use nalgebra::{Point3, Vector3};

#[derive(Debug, Clone, Default)]
pub struct Mesh {
    pub positions: Vec<Point3<f64>>,
    /// Counter-clockwise seen from outside.
    pub triangles: Vec<[u32; 3]>,
}

/// Why a mesh is not a closed, oriented 2-manifold of genus 0.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MeshDefect {
    #[error("mesh is empty")]
    Empty,
    #[error("triangle {0} references a missing vertex or repeats one")]
    BadTriangle(usize),
    #[error("triangle {0} has zero area")]
    DegenerateTriangle(usize),
    #[error("edge ({0}, {1}) is used by {2} triangles (watertight manifold edges are used by exactly 2)")]
    EdgeNotManifold(u32, u32, usize),
    #[error("edge ({0}, {1}) appears twice with the same direction: inconsistent winding")]
    InconsistentWinding(u32, u32),
    #[error("vertex {0} is not a single fan of triangles (non-manifold vertex or unused vertex)")]
    VertexNotManifold(u32),
    #[error("Euler characteristic is {0}, not 2: the surface has handles or several components")]
    NotGenusZero(i64),
    #[error("enclosed volume is {0}: faces point inward")]
    InsideOut(f64),
}

/// Summary of a valid mesh.
#[derive(Debug, Clone, Copy)]
pub struct MeshReport {
    pub vertices: usize,
    pub triangles: usize,
    pub area: f64,
    pub volume: f64,
    pub min_angle_degrees: f64,
}

impl Mesh {
    pub fn vertex_neighbours(&self) -> Vec<Vec<u32>> {
        let mut neighbours: Vec<Vec<u32>> = vec![Vec::new(); self.positions.len()];
        for triangle in &self.triangles {
            for k in 0..3 {
                let (a, b) = (triangle[k], triangle[(k + 1) % 3]);
                if !neighbours[a as usize].contains(&b) {
                    neighbours[a as usize].push(b);
                }
                if !neighbours[b as usize].contains(&a) {
                    neighbours[b as usize].push(a);
                }
            }
        }
        neighbours
    }

    /// Undirected edges, each once, smaller index first.
    pub fn edges(&self) -> Vec<(u32, u32)> {
        let mut edges: Vec<(u32, u32)> = self
            .triangles
            .iter()
            .flat_map(|t| (0..3).map(move |k| (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3]))))
            .collect();
        edges.sort_unstable();
        edges.dedup();
        edges
    }

    fn corner(&self, triangle: &[u32; 3], k: usize) -> Point3<f64> {
        self.positions[triangle[k] as usize]
    }

    pub fn area(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                0.5 * (self.corner(t, 1) - self.corner(t, 0))
                    .cross(&(self.corner(t, 2) - self.corner(t, 0)))
                    .norm()
            })
            .sum()
    }

    /// Signed enclosed volume (positive for outward-facing triangles).
    pub fn volume(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                self.corner(t, 0)
                    .coords
                    .dot(&self.corner(t, 1).coords.cross(&self.corner(t, 2).coords))
                    / 6.0
            })
            .sum()
    }

    pub fn bounds(&self) -> (Point3<f64>, Point3<f64>) {
        let mut lower = Vector3::repeat(f64::INFINITY);
        let mut upper = Vector3::repeat(f64::NEG_INFINITY);
        for p in &self.positions {
            lower = lower.inf(&p.coords);
            upper = upper.sup(&p.coords);
        }
        (lower.into(), upper.into())
    }

    /// Smallest interior angle over all triangles, in degrees.
    pub fn min_angle_degrees(&self) -> f64 {
        let mut smallest = 180.0f64;
        for t in &self.triangles {
            for k in 0..3 {
                let (a, b, c) = (
                    self.corner(t, k),
                    self.corner(t, (k + 1) % 3),
                    self.corner(t, (k + 2) % 3),
                );
                smallest = smallest.min((b - a).angle(&(c - a)).to_degrees());
            }
        }
        smallest
    }

    /// Checks that the mesh is a closed, consistently wound, outward-facing 2-manifold of genus 0
    /// with no degenerate triangles.
    pub fn validate(&self) -> Result<MeshReport, MeshDefect> {
        if self.positions.is_empty() || self.triangles.is_empty() {
            return Err(MeshDefect::Empty);
        }
        let vertex_count = self.positions.len() as u32;
        let mut directed: HashMap<(u32, u32), usize> = HashMap::with_capacity(3 * self.triangles.len());
        for (index, t) in self.triangles.iter().enumerate() {
            if t.iter().any(|&v| v >= vertex_count) || t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
                return Err(MeshDefect::BadTriangle(index));
            }
            let doubled_area = (self.corner(t, 1) - self.corner(t, 0))
                .cross(&(self.corner(t, 2) - self.corner(t, 0)))
                .norm();
            if doubled_area <= 1e-14 {
                return Err(MeshDefect::DegenerateTriangle(index));
            }
            for k in 0..3 {
                let edge = (t[k], t[(k + 1) % 3]);
                if directed.insert(edge, index).is_some() {
                    return Err(MeshDefect::InconsistentWinding(edge.0, edge.1));
                }
            }
        }
        // Every directed edge must have its twin: each undirected edge used exactly twice, oppositely.
        for &(a, b) in directed.keys() {
            if !directed.contains_key(&(b, a)) {
                return Err(MeshDefect::EdgeNotManifold(a.min(b), a.max(b), 1));
            }
        }
        // Each vertex: its outgoing edges, chained through the triangles, must form one cycle.
        let mut outgoing: Vec<Vec<u32>> = vec![Vec::new(); self.positions.len()];
        for &(a, b) in directed.keys() {
            outgoing[a as usize].push(b);
        }
        let next_around = |vertex: u32, from: u32| -> Option<u32> {
            // Triangle containing directed edge (vertex, from): its third corner is the next neighbour.
            let triangle = &self.triangles[*directed.get(&(vertex, from))?];
            triangle.iter().copied().find(|&v| v != vertex && v != from)
        };
        for (vertex, neighbours) in outgoing.iter().enumerate() {
            let vertex = vertex as u32;
            let Some(&first) = neighbours.first() else {
                return Err(MeshDefect::VertexNotManifold(vertex));
            };
            let mut current = first;
            let mut steps = 0;
            loop {
                let next = next_around(vertex, current).ok_or(MeshDefect::VertexNotManifold(vertex))?;
                steps += 1;
                if next == first {
                    break;
                }
                if steps > neighbours.len() {
                    return Err(MeshDefect::VertexNotManifold(vertex));
                }
                current = next;
            }
            if steps != neighbours.len() {
                return Err(MeshDefect::VertexNotManifold(vertex));
            }
        }
        let edges = directed.len() / 2;
        let euler = self.positions.len() as i64 - edges as i64 + self.triangles.len() as i64;
        if euler != 2 {
            return Err(MeshDefect::NotGenusZero(euler));
        }
        let volume = self.volume();
        if volume <= 0.0 {
            return Err(MeshDefect::InsideOut(volume));
        }
        Ok(MeshReport {
            vertices: self.positions.len(),
            triangles: self.triangles.len(),
            area: self.area(),
            volume,
            min_angle_degrees: self.min_angle_degrees(),
        })
    }
}

/// Relative change of every edge length between two embeddings of the same connectivity,
/// `|l - l_rest| / l_rest`. Isometric articulation gives all zeros.
pub fn edge_length_distortion(rest: &Mesh, posed: &Mesh) -> Vec<f64> {
    rest.edges()
        .into_iter()
        .map(|(a, b)| {
            let rest_length = (rest.positions[a as usize] - rest.positions[b as usize]).norm();
            let posed_length = (posed.positions[a as usize] - posed.positions[b as usize]).norm();
            (posed_length - rest_length).abs() / rest_length.max(1e-12)
        })
        .collect()
}

/// Linear-interpolated percentile of unsorted values (`q` in 0..=100).
pub fn percentile(values: &mut [f64], q: f64) -> f64 {
    if values.is_empty() {
        return f64::NAN;
    }
    values.sort_unstable_by(|a, b| a.total_cmp(b));
    let rank = (q / 100.0).clamp(0.0, 1.0) * (values.len() - 1) as f64;
    let (low, high) = (rank.floor() as usize, rank.ceil() as usize);
    values[low] + (values[high] - values[low]) * (rank - low as f64)
}
