//! Triangle mesh as produced by the mesh decoder (FlexiCubes) and consumed by
//! post-processing and the exporters.

use crate::{Error, Result};

/// Indexed triangle mesh. Coordinates are in the decoder's object frame
/// ([-0.5, 0.5]³, z up) unless a transform was applied.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<[f32; 3]>,
    pub faces: Vec<[u32; 3]>,
    /// Per-vertex attributes in [0, 1]: TRELLIS's 6 colour channels
    /// (RGB then a normal-map triple).
    pub vertex_attrs: Option<Vec<[f32; 6]>>,
}

impl Mesh {
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

pub(crate) fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

pub(crate) fn face_area(v: &[[f32; 3]], f: &[u32; 3]) -> f64 {
    let [a, b, c] = f.map(|i| v[i as usize].map(|x| x as f64));
    let u = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
    let w = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
    let n = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]];
    0.5 * (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt()
}
