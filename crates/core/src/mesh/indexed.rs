//! The indexed triangle mesh the mesh decoder produces and the exporters write.

use crate::math::{cross, sub, Similarity32};
use crate::{Error, Result};

/// Indexed triangle mesh. Coordinates are in the decoder's object frame
/// ([-0.5, 0.5]³, z up) unless a transform was applied.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions.
    pub vertices: Vec<[f32; 3]>,
    /// Triangles as vertex indices (counter-clockwise seen from outside).
    pub faces: Vec<[u32; 3]>,
    /// Per-vertex attributes in [0, 1]: TRELLIS's 6 colour channels
    /// (RGB then a normal-map triple).
    pub vertex_attrs: Option<Vec<[f32; 6]>>,
}

impl Mesh {
    /// Whether the mesh has no faces.
    pub fn is_empty(&self) -> bool {
        self.faces.is_empty()
    }

    /// Every face index in range and the attribute count matching.
    pub fn validate(&self) -> Result<()> {
        let n = self.vertices.len();
        if let Some(f) = self.faces.iter().find(|f| f.iter().any(|&i| i as usize >= n)) {
            return Err(Error::msg(format!("mesh: face {f:?} indexes past {n} vertices")));
        }
        if let Some(a) = &self.vertex_attrs {
            if a.len() != n {
                return Err(Error::msg(format!("mesh: {} vertex attrs for {n} vertices", a.len())));
            }
        }
        Ok(())
    }

    /// Unit face normals `normalize(cross(v1 - v0, v2 - v0))` (upstream
    /// `MeshExtractResult.face_normal`; a degenerate face gives zeros).
    pub fn face_normals(&self) -> Vec<[f32; 3]> {
        self.faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| self.vertices[i as usize]);
                let n = cross(sub(b, a), sub(c, a));
                let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt().max(1e-12);
                [n[0] / len, n[1] / len, n[2] / len]
            })
            .collect()
    }

    /// Area-weighted unit vertex normals (zero for unreferenced vertices).
    pub fn vertex_normals(&self) -> Vec<[f32; 3]> {
        let mut acc = vec![[0f32; 3]; self.vertices.len()];
        for f in &self.faces {
            let [a, b, c] = f.map(|i| self.vertices[i as usize]);
            let n = cross(sub(b, a), sub(c, a));
            for &i in f {
                for k in 0..3 {
                    acc[i as usize][k] += n[k];
                }
            }
        }
        for n in &mut acc {
            let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            if len > 0.0 {
                *n = [n[0] / len, n[1] / len, n[2] / len];
            }
        }
        acc
    }

    /// RGB vertex colours (the first three attribute channels), if present.
    pub fn vertex_colors(&self) -> Option<Vec<[f32; 3]>> {
        self.vertex_attrs.as_ref().map(|a| a.iter().map(|c| [c[0], c[1], c[2]]).collect())
    }

    /// Total surface area.
    pub fn area(&self) -> f64 {
        self.faces.iter().map(|f| face_area(&self.vertices, f)).sum()
    }
}

/// Area of triangle `f` over vertices `v`.
pub fn face_area(v: &[[f32; 3]], f: &[u32; 3]) -> f64 {
    let [a, b, c] = f.map(|i| v[i as usize].map(|x| x as f64));
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let w = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let n = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]];
    0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
}

/// Edge/orientation statistics of a triangle mesh (over referenced vertices).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Topology {
    /// Vertices referenced by a face.
    pub vertices: usize,
    /// Distinct undirected edges.
    pub edges: usize,
    /// Faces.
    pub faces: usize,
    /// Edges used by one face.
    pub boundary_edges: usize,
    /// Edges used by more than two faces.
    pub nonmanifold_edges: usize,
    /// Manifold edges whose two faces traverse it in the same direction.
    pub misoriented_edges: usize,
    /// Faces with a repeated vertex index.
    pub degenerate_faces: usize,
    /// Connected components (by shared vertices).
    pub components: usize,
}

impl Topology {
    /// V − E + F.
    pub fn euler(&self) -> i64 {
        self.vertices as i64 - self.edges as i64 + self.faces as i64
    }

    /// Every edge shared by exactly two consistently oriented faces.
    pub fn is_closed_oriented_manifold(&self) -> bool {
        self.boundary_edges == 0 && self.nonmanifold_edges == 0 && self.misoriented_edges == 0 && self.degenerate_faces == 0
    }
}

impl Mesh {
    /// Edge, orientation and component statistics of the mesh.
    pub fn topology(&self) -> Topology {
        use std::collections::HashMap;
        // Directed edge counts per undirected edge: (a→b uses, b→a uses) with a < b.
        let mut edges: HashMap<(u32, u32), (u32, u32)> = HashMap::new();
        let mut degenerate = 0;
        let mut used = vec![false; self.vertices.len()];
        let mut uf = UnionFind::new(self.vertices.len());
        for f in &self.faces {
            if f[0] == f[1] || f[1] == f[2] || f[0] == f[2] {
                degenerate += 1;
            }
            for k in 0..3 {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                used[a as usize] = true;
                uf.union(a as usize, b as usize);
                let e = edges.entry((a.min(b), a.max(b))).or_insert((0, 0));
                if a < b {
                    e.0 += 1
                } else {
                    e.1 += 1
                }
            }
        }
        let mut t = Topology {
            vertices: used.iter().filter(|&&u| u).count(),
            edges: edges.len(),
            faces: self.faces.len(),
            boundary_edges: 0,
            nonmanifold_edges: 0,
            misoriented_edges: 0,
            degenerate_faces: degenerate,
            components: 0,
        };
        for &(f, b) in edges.values() {
            match f + b {
                1 => t.boundary_edges += 1,
                2 if f != 1 => t.misoriented_edges += 1,
                2 => {}
                _ => t.nonmanifold_edges += 1,
            }
        }
        let mut roots = std::collections::HashSet::new();
        for (v, &u) in used.iter().enumerate() {
            if u {
                roots.insert(uf.find(v));
            }
        }
        t.components = roots.len();
        t
    }
}

/// Disjoint sets with path halving.
pub(crate) struct UnionFind {
    parent: Vec<usize>,
}

impl UnionFind {
    pub(crate) fn new(n: usize) -> Self {
        UnionFind { parent: (0..n).collect() }
    }
    pub(crate) fn find(&mut self, mut x: usize) -> usize {
        while self.parent[x] != x {
            self.parent[x] = self.parent[self.parent[x]];
            x = self.parent[x];
        }
        x
    }
    pub(crate) fn union(&mut self, a: usize, b: usize) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra != rb {
            self.parent[ra.max(rb)] = ra.min(rb);
        }
    }
}

impl Similarity32 {
    /// The mesh with every vertex transformed (attributes kept).
    pub fn apply_mesh(&self, mesh: &Mesh) -> Mesh {
        Mesh {
            vertices: mesh.vertices.iter().map(|&v| self.apply(&v)).collect(),
            faces: mesh.faces.clone(),
            vertex_attrs: mesh.vertex_attrs.clone(),
        }
    }
}

/// A mesh stretched along the axes of its own frame, `x ↦ diag(k)·x`.
pub fn stretch_mesh(mesh: &Mesh, k: [f64; 3]) -> Mesh {
    let k = k.map(|x| x as f32);
    Mesh {
        vertices: mesh.vertices.iter().map(|v| [v[0] * k[0], v[1] * k[1], v[2] * k[2]]).collect(),
        faces: mesh.faces.clone(),
        vertex_attrs: mesh.vertex_attrs.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mesh_transform_rotates_normals_and_composes() {
        let t = Similarity32::from_quaternion([0.5, 0.5, 0.5, 0.5], [1.0, 2.0, 3.0], 2.0).unwrap();
        let mesh = crate::mesh::primitives::tetrahedron();
        let m2 = t.apply_mesh(&mesh);
        for (n0, n1) in mesh.face_normals().iter().zip(m2.face_normals()) {
            let rn = [0, 1, 2].map(|i| (0..3).map(|k| t.rotation[i][k] * n0[k]).sum::<f32>());
            assert!((0..3).all(|k| (rn[k] - n1[k]).abs() < 1e-5));
        }
        let u = Similarity32::from_quaternion([0.9, -0.2, 0.1, 0.3], [0.0, -1.0, 0.5], 0.5).unwrap();
        let p = [0.3, -0.2, 0.9];
        let a = t.compose(&u).apply(&p);
        let b = t.apply(&u.apply(&p));
        assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-5));
    }
}
