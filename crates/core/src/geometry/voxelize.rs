//! Occupancy grids of triangle meshes: the training target of the
//! sparse-structure VAE and flow.
//!
//! **Frame and grid** (TRELLIS `dataset_toolkits`): a mesh is first put in
//! its canonical frame, centred on its bounding-box centre and scaled so the
//! longest box side is 1 ([`CanonicalFrame`]), i.e. inside `[-0.5, 0.5]³`,
//! the frame the decoders emit. Voxel `(i, j, k)` of an `r³` grid covers
//! `[-0.5 + i/r, -0.5 + (i+1)/r]` along x (j along y, k along z), and the
//! flat index is `(i·r + j)·r + k`, the layout of the SS decoder's
//! `[B, 1, X, Y, Z]` logits.
//!
//! **What is occupied.** [`Fill::Surface`] marks every voxel a triangle
//! passes through (TRELLIS voxelises surfaces with Open3D); here triangles
//! are sampled on a barycentric lattice finer than half a voxel, so a voxel
//! the triangle only grazes at a corner may be missed. [`Fill::Solid`] adds
//! the interior: for each (x, y) voxel column a ray along z at the column's
//! centre collects its crossings with the surface, and voxels whose centres
//! lie between the 1st and 2nd, 3rd and 4th, … crossing are inside (parity
//! rule; a column with an odd count, from an open mesh, drops its last
//! crossing). The ray is offset by an irrational fraction of a voxel so it
//! does not run exactly through mesh edges of axis-aligned primitives.

use crate::{Error, Result};

/// Which voxels count as occupied (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Fill {
    /// Voxels the surface passes through.
    Surface,
    /// Surface voxels and the interior (parity rule along z).
    Solid,
}

/// The canonical frame of a mesh: `x_canonical = (x − centre) / extent`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CanonicalFrame {
    /// Bounding-box centre, in the mesh's units.
    pub centre: [f64; 3],
    /// Longest bounding-box side, in the mesh's units.
    pub extent: f64,
}

impl CanonicalFrame {
    /// The frame of the vertices used by `faces` (all vertices when there are no faces).
    pub fn of(vertices: &[[f64; 3]], faces: &[[u32; 3]]) -> Result<Self> {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        let mut add = |p: &[f64; 3]| {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        };
        if faces.is_empty() {
            vertices.iter().for_each(&mut add);
        } else {
            for f in faces {
                for &i in f {
                    add(vertices
                        .get(i as usize)
                        .ok_or_else(|| Error::msg(format!("mesh: face {f:?} indexes past {} vertices", vertices.len())))?);
                }
            }
        }
        let extent = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
        if !(extent.is_finite() && extent > 0.0) {
            return Err(Error::msg("mesh: empty or degenerate (zero-size bounding box); cannot build its canonical frame"));
        }
        Ok(Self { centre: std::array::from_fn(|a| 0.5 * (lo[a] + hi[a])), extent })
    }

    /// Mesh point → canonical frame.
    pub fn to_canonical(self, p: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|a| (p[a] - self.centre[a]) / self.extent)
    }
}

/// Occupancy (flat, `(i·r + j)·r + k`) of a mesh already in canonical
/// coordinates. Parts outside `[-0.5, 0.5]³` are ignored.
pub fn voxelize(vertices: &[[f64; 3]], faces: &[[u32; 3]], r: usize, fill: Fill) -> Result<Vec<bool>> {
    if r == 0 {
        return Err(Error::msg("voxelize: resolution must be positive"));
    }
    if let Some(f) = faces.iter().find(|f| f.iter().any(|&i| i as usize >= vertices.len())) {
        return Err(Error::msg(format!("voxelize: face {f:?} indexes past {} vertices", vertices.len())));
    }
    let mut occ = vec![false; r * r * r];
    let rf = r as f64;
    let cell = |x: f64| -> Option<usize> {
        let i = ((x + 0.5) * rf).floor();
        (i >= 0.0 && i < rf).then_some(i as usize)
    };
    // Surface: barycentric lattice with spacing below half a voxel.
    for f in faces {
        let [a, b, c] = f.map(|i| vertices[i as usize]);
        let edge = |p: [f64; 3], q: [f64; 3]| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt();
        let longest = edge(a, b).max(edge(b, c)).max(edge(c, a));
        let n = ((longest * rf * 2.0).ceil() as usize).clamp(1, 4 * r);
        for u in 0..=n {
            for v in 0..=(n - u) {
                let (wu, wv) = (u as f64 / n as f64, v as f64 / n as f64);
                let ww = 1.0 - wu - wv;
                let p: [f64; 3] = std::array::from_fn(|k| wu * a[k] + wv * b[k] + ww * c[k]);
                if let (Some(i), Some(j), Some(k)) = (cell(p[0]), cell(p[1]), cell(p[2])) {
                    occ[(i * r + j) * r + k] = true;
                }
            }
        }
    }
    if fill == Fill::Solid {
        solid_fill(vertices, faces, r, &mut occ);
    }
    Ok(occ)
}

/// Parity fill along z columns (module docs).
fn solid_fill(vertices: &[[f64; 3]], faces: &[[u32; 3]], r: usize, occ: &mut [bool]) {
    let rf = r as f64;
    // Irrational sub-voxel offsets keep rays off mesh edges and vertices.
    let (ox, oy) = (0.5 + 1e-4 * std::f64::consts::SQRT_2, 0.5 + 1e-4 * std::f64::consts::PI);
    let mut hits: Vec<Vec<f64>> = vec![Vec::new(); r * r];
    for f in faces {
        let [a, b, c] = f.map(|i| vertices[i as usize]);
        let to_grid = |p: f64| (p + 0.5) * rf;
        let (ax, ay, bx, by, cx, cy) = (to_grid(a[0]), to_grid(a[1]), to_grid(b[0]), to_grid(b[1]), to_grid(c[0]), to_grid(c[1]));
        let area = (bx - ax) * (cy - ay) - (cx - ax) * (by - ay);
        if area.abs() < 1e-12 {
            continue; // edge-on to the ray direction
        }
        let lo_i = (ax.min(bx).min(cx) - ox).ceil().max(0.0) as usize;
        let hi_i = (ax.max(bx).max(cx) - ox).floor().min(rf - 1.0);
        let lo_j = (ay.min(by).min(cy) - oy).ceil().max(0.0) as usize;
        let hi_j = (ay.max(by).max(cy) - oy).floor().min(rf - 1.0);
        if hi_i < 0.0 || hi_j < 0.0 {
            continue;
        }
        for i in lo_i..=hi_i as usize {
            for j in lo_j..=hi_j as usize {
                let (px, py) = (i as f64 + ox, j as f64 + oy);
                // Barycentric coordinates of the ray's (x, y) in the projected triangle.
                let wb = ((px - ax) * (cy - ay) - (cx - ax) * (py - ay)) / area;
                let wc = ((bx - ax) * (py - ay) - (px - ax) * (by - ay)) / area;
                let wa = 1.0 - wb - wc;
                if wa >= 0.0 && wb >= 0.0 && wc >= 0.0 {
                    hits[i * r + j].push(wa * a[2] + wb * b[2] + wc * c[2]);
                }
            }
        }
    }
    for (col, zs) in hits.iter_mut().enumerate() {
        zs.sort_by(|p, q| p.total_cmp(q));
        for pair in zs.chunks_exact(2) {
            for k in 0..r {
                let zc = (k as f64 + 0.5) / rf - 0.5;
                if zc >= pair[0] && zc <= pair[1] {
                    occ[col * r + k] = true;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Axis-aligned box `[lo, hi]` as 12 outward-facing triangles.
    pub(crate) fn box_mesh(lo: [f64; 3], hi: [f64; 3]) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        (crate::mesh::primitives::box_corners(lo, hi), crate::mesh::primitives::BOX_FACES.to_vec())
    }

    fn count(o: &[bool]) -> usize {
        o.iter().filter(|&&b| b).count()
    }

    #[test]
    fn solid_box_fills_exactly_its_voxels() -> Result<()> {
        // Box from voxel 2 to voxel 6 (exclusive) on every axis of an 8³ grid,
        // faces slightly inside the voxel boundaries.
        let r = 8;
        let (lo, hi) = (-0.5 + 2.0 / 8.0 + 1e-3, -0.5 + 6.0 / 8.0 - 1e-3);
        let (v, f) = box_mesh([lo; 3], [hi; 3]);
        let solid = voxelize(&v, &f, r, Fill::Solid)?;
        assert_eq!(count(&solid), 4 * 4 * 4);
        for i in 0..r {
            for j in 0..r {
                for k in 0..r {
                    let inside = [i, j, k].iter().all(|&x| (2..6).contains(&x));
                    assert_eq!(solid[(i * r + j) * r + k], inside, "({i},{j},{k})");
                }
            }
        }
        // The surface shell of a 4³ block: 4³ − 2³ interior voxels.
        let surf = voxelize(&v, &f, r, Fill::Surface)?;
        assert_eq!(count(&surf), 64 - 8);
        Ok(())
    }

    #[test]
    fn solid_sphere_is_filled_and_axes_follow_the_grid_layout() -> Result<()> {
        // UV sphere of radius 0.4 at 32³.
        let (n_lat, n_lon) = (24, 48);
        let mut v = vec![[0.0, 0.0, 0.4], [0.0, 0.0, -0.4]];
        for i in 1..n_lat {
            let th = std::f64::consts::PI * i as f64 / n_lat as f64;
            for j in 0..n_lon {
                let ph = std::f64::consts::TAU * j as f64 / n_lon as f64;
                v.push([0.4 * th.sin() * ph.cos(), 0.4 * th.sin() * ph.sin(), 0.4 * th.cos()]);
            }
        }
        let idx = |i: usize, j: usize| (2 + (i - 1) * n_lon + j % n_lon) as u32;
        let mut f = Vec::new();
        for j in 0..n_lon {
            f.push([0, idx(1, j), idx(1, j + 1)]);
            f.push([1, idx(n_lat - 1, j + 1), idx(n_lat - 1, j)]);
            for i in 1..n_lat - 1 {
                f.push([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)]);
                f.push([idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]);
            }
        }
        let r = 32;
        let occ = voxelize(&v, &f, r, Fill::Solid)?;
        // Solid fill: every voxel whose centre is inside the (inscribed)
        // polyhedron by more than half a voxel diagonal is occupied, none
        // further than that outside the sphere is.
        let half_diag = 0.5 * 3f64.sqrt() / r as f64;
        let inner = 0.4 * (std::f64::consts::PI / n_lat as f64).cos() * (std::f64::consts::PI / n_lon as f64).cos();
        let (mut must, mut wrong) = (0, 0);
        for i in 0..r {
            for j in 0..r {
                for k in 0..r {
                    let c = [i, j, k].map(|x| (x as f64 + 0.5) / r as f64 - 0.5);
                    let d = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
                    let o = occ[(i * r + j) * r + k];
                    if d < inner - half_diag {
                        must += 1;
                        assert!(o, "inside voxel ({i},{j},{k}) empty");
                    }
                    if d > 0.4 + half_diag && o {
                        wrong += 1;
                    }
                }
            }
        }
        assert!(must > 3000 && wrong == 0, "{must} inside, {wrong} occupied outside");
        // Without the fill only a shell is occupied: the centre is empty.
        let shell = voxelize(&v, &f, r, Fill::Surface)?;
        assert!(!shell[(16 * r + 16) * r + 16] && occ[(16 * r + 16) * r + 16]);
        assert!(count(&shell) < count(&occ) / 2);
        // A box elongated along x occupies more i than k: (i, j, k) = (x, y, z).
        let (bv, bf) = box_mesh([-0.45, -0.1, -0.1], [0.45, 0.1, 0.1]);
        let o = voxelize(&bv, &bf, r, Fill::Solid)?;
        assert!(o[(2 * r + 16) * r + 16] && !o[(16 * r + 16) * r + 2]);
        Ok(())
    }

    #[test]
    fn canonical_frame_fits_unit_cube() -> Result<()> {
        let (v, f) = box_mesh([0.1, 0.2, 0.3], [0.3, 0.3, 0.9]);
        let c = CanonicalFrame::of(&v, &f)?;
        assert!((c.extent - 0.6).abs() < 1e-12);
        let p = c.to_canonical([0.3, 0.3, 0.9]);
        assert!((p[2] - 0.5).abs() < 1e-12 && (p[0] - 0.2 / 1.2).abs() < 1e-12);
        assert!(CanonicalFrame::of(&[[1.0; 3]], &[]).is_err());
        assert!(voxelize(&v, &[[0, 1, 99]], 4, Fill::Solid).is_err());
        Ok(())
    }
}
