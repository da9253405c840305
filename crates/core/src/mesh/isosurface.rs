//! Closed surfaces of scalar grids (marching tetrahedra): every grid cell is
//! split into the six tetrahedra around its main diagonal (the same split in
//! every cell, so neighbouring cells share faces), and each tetrahedron the
//! iso-surface crosses gives one or two triangles. Unlike surface nets or
//! marching cubes there are no ambiguous cases, so the surface is a closed
//! 2-manifold wherever the field's border samples are all outside.

use super::indexed::Mesh;
use std::collections::HashMap;

/// A scalar field sampled on a regular grid, flat index `(x·ny + y)·nz + z`.
pub struct ScalarGrid<'a> {
    /// Samples, flat index `(x·ny + y)·nz + z`.
    pub values: &'a [f32],
    /// Samples along x, y, z.
    pub dims: [usize; 3],
    /// Position of sample (0, 0, 0).
    pub origin: [f32; 3],
    /// Distance between neighbouring samples.
    pub spacing: f32,
}

/// Cell corners by bit (x = 1, y = 2, z = 4), and the six tetrahedra around the 0–7 diagonal.
const TETS: [[usize; 4]; 6] = [[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]];

/// The surface `value = iso` of `grid`, inside where `value > iso`, faces
/// counter-clockwise seen from outside (normals point out).
pub fn marching_tetrahedra(grid: &ScalarGrid, iso: f32) -> Mesh {
    let [nx, ny, nz] = grid.dims;
    if nx < 2 || ny < 2 || nz < 2 || grid.values.len() != nx * ny * nz {
        return Mesh::default();
    }
    let index = |p: [usize; 3]| (p[0] * ny + p[1]) * nz + p[2];
    let position = |i: usize| -> [f32; 3] {
        let p = [i / (ny * nz), i / nz % ny, i % nz];
        std::array::from_fn(|d| grid.origin[d] + p[d] as f32 * grid.spacing)
    };
    let mut vertex_of: HashMap<(u32, u32), u32> = HashMap::new();
    let mut vertices: Vec<[f32; 3]> = Vec::new();
    let mut faces = Vec::new();
    let mut crossing = |a: usize, b: usize, vertices: &mut Vec<[f32; 3]>| -> u32 {
        let key = (a.min(b) as u32, a.max(b) as u32);
        *vertex_of.entry(key).or_insert_with(|| {
            let (va, vb) = (grid.values[a], grid.values[b]);
            let t = ((iso - va) / (vb - va)).clamp(0.0, 1.0);
            let (pa, pb) = (position(a), position(b));
            vertices.push(std::array::from_fn(|d| pa[d] + t * (pb[d] - pa[d])));
            (vertices.len() - 1) as u32
        })
    };
    for x in 0..nx - 1 {
        for y in 0..ny - 1 {
            for z in 0..nz - 1 {
                let corner: [usize; 8] = std::array::from_fn(|k| index([x + (k & 1), y + (k >> 1 & 1), z + (k >> 2 & 1)]));
                let inside: [bool; 8] = corner.map(|i| grid.values[i] > iso);
                if inside.iter().all(|&b| b) || inside.iter().all(|&b| !b) {
                    continue;
                }
                for tet in TETS {
                    let ids = tet.map(|k| corner[k]);
                    let (ins, outs): (Vec<usize>, Vec<usize>) = ids.iter().partition(|&&i| grid.values[i] > iso);
                    let tris: Vec<[u32; 3]> = match (ins.len(), outs.len()) {
                        (1, 3) | (3, 1) => {
                            let (one, many) = if ins.len() == 1 { (ins[0], &outs) } else { (outs[0], &ins) };
                            vec![[0, 1, 2].map(|k| crossing(one, many[k], &mut vertices))]
                        }
                        (2, 2) => {
                            let q = [(ins[0], outs[0]), (ins[0], outs[1]), (ins[1], outs[1]), (ins[1], outs[0])]
                                .map(|(a, b)| crossing(a, b, &mut vertices));
                            vec![[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
                        }
                        _ => continue,
                    };
                    // Outwards: from the inside corners' centroid towards the outside ones'.
                    let centroid = |s: &[usize]| -> [f32; 3] {
                        let mut c = [0f32; 3];
                        for &i in s {
                            let p = position(i);
                            c = std::array::from_fn(|d| c[d] + p[d] / s.len() as f32);
                        }
                        c
                    };
                    let (ci, co) = (centroid(&ins), centroid(&outs));
                    let out_dir: [f32; 3] = std::array::from_fn(|d| co[d] - ci[d]);
                    for mut t in tris {
                        let [a, b, c] = t.map(|i| vertices[i as usize]);
                        let n = crate::math::cross(crate::math::sub(b, a), crate::math::sub(c, a));
                        if n[0] * out_dir[0] + n[1] * out_dir[1] + n[2] * out_dir[2] < 0.0 {
                            t.swap(1, 2);
                        }
                        if t[0] != t[1] && t[1] != t[2] && t[0] != t[2] {
                            faces.push(t);
                        }
                    }
                }
            }
        }
    }
    Mesh { vertices, faces, vertex_attrs: None }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::post::mesh_quality;

    fn signed_volume(m: &Mesh) -> f64 {
        m.faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| m.vertices[i as usize].map(|x| x as f64));
                (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0])) / 6.0
            })
            .sum()
    }

    /// A ball's field gives one closed, outward-facing surface of about its volume.
    #[test]
    fn a_ball_gives_one_closed_outward_surface() {
        let n = 24;
        let h = 1.0 / (n - 1) as f32;
        let values: Vec<f32> = (0..n * n * n)
            .map(|i| {
                let p = [i / (n * n), i / n % n, i % n].map(|v| v as f32 * h - 0.5);
                0.35 - (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt()
            })
            .collect();
        let m = marching_tetrahedra(&ScalarGrid { values: &values, dims: [n; 3], origin: [-0.5; 3], spacing: h }, 0.0);
        let q = mesh_quality(&m).unwrap();
        assert_eq!((q.components, q.boundary_edges, q.non_manifold_edges), (1, 0, 0), "{q:?}");
        let v = signed_volume(&m);
        let exact = 4.0 / 3.0 * std::f64::consts::PI * 0.35f64.powi(3);
        assert!(v > 0.0 && (v - exact).abs() < 0.05 * exact, "volume {v} vs {exact}");
        for p in &m.vertices {
            let r = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
            assert!((r - 0.35).abs() < h, "vertex at radius {r}");
        }
    }

    /// Two blocks touching along an edge and a third at a corner only (the
    /// ambiguous cases of marching cubes) give manifold, closed surfaces.
    #[test]
    fn blocks_touching_at_an_edge_or_corner_stay_manifold() {
        let n = 10;
        let solid = |p: [usize; 3]| {
            let box_at = |lo: [usize; 3]| (0..3).all(|d| (lo[d]..lo[d] + 3).contains(&p[d]));
            box_at([1, 1, 1]) || box_at([4, 4, 1]) || box_at([4, 4, 4]) && p != [4, 4, 4] || box_at([1, 1, 4]) && p == [3, 3, 4]
        };
        let values: Vec<f32> = (0..n * n * n).map(|i| if solid([i / (n * n), i / n % n, i % n]) { 1.0 } else { 0.0 }).collect();
        let m = marching_tetrahedra(&ScalarGrid { values: &values, dims: [n; 3], origin: [0.0; 3], spacing: 1.0 }, 0.5);
        let q = mesh_quality(&m).unwrap();
        assert_eq!((q.boundary_edges, q.non_manifold_edges), (0, 0), "{q:?}");
        assert!(signed_volume(&m) > 0.0);
    }

    #[test]
    fn an_empty_or_full_field_has_no_surface() {
        let values = vec![1.0f32; 27];
        let g = ScalarGrid { values: &values, dims: [3; 3], origin: [0.0; 3], spacing: 1.0 };
        assert!(marching_tetrahedra(&g, 0.5).faces.is_empty());
        assert!(marching_tetrahedra(&g, 2.0).faces.is_empty());
    }
}
