//! Primitive meshes that tests, synthetic scenes and baselines share: boxes,
//! surfaces of revolution (cylinders, spheres, cups, bowls, tori), extrusions
//! and swept tubes, closed and outward-oriented.

use crate::math::{cross, normalize};
use crate::mesh::indexed::Mesh;
use crate::mesh::trimesh::TriMesh;
use crate::spatial::P3;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

/// The unit square in z = 0 as an `n`×`n` grid of cells, two triangles each
/// (an open mesh with a boundary, all faces coplanar).
pub fn flat_grid(n: u32) -> Mesh {
    let mut mesh = Mesh::default();
    for y in 0..=n {
        for x in 0..=n {
            mesh.vertices.push([x as f32 / n as f32, y as f32 / n as f32, 0.0]);
        }
    }
    let id = |x: u32, y: u32| y * (n + 1) + x;
    for y in 0..n {
        for x in 0..n {
            mesh.faces.push([id(x, y), id(x + 1, y), id(x + 1, y + 1)]);
            mesh.faces.push([id(x, y), id(x + 1, y + 1), id(x, y + 1)]);
        }
    }
    mesh
}

/// A closed, outward-oriented tetrahedron.
pub fn tetrahedron() -> Mesh {
    Mesh {
        vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        faces: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        vertex_attrs: None,
    }
}

/// The 12 outward-facing triangles of a box over its corners as [`box_corners`]
/// numbers them (corner `i` is on the high side of axis `k` where bit `k` of `i` is
/// set): two per side, in the order z−, z+, y−, y+, x−, x+.
pub const BOX_FACES: [[u32; 3]; 12] =
    [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]];

/// The 8 corners of the axis-aligned box `[lo, hi]`, numbered for [`BOX_FACES`].
pub fn box_corners<T: Copy>(lo: [T; 3], hi: [T; 3]) -> Vec<[T; 3]> {
    (0..8)
        .map(|i| [if i & 1 == 1 { hi[0] } else { lo[0] }, if i & 2 == 2 { hi[1] } else { lo[1] }, if i & 4 == 4 { hi[2] } else { lo[2] }])
        .collect()
}

/// A closed box mesh `[-h, h]`, outward-facing triangles.
pub fn cuboid(h: P3) -> TriMesh {
    TriMesh { vertices: box_corners(h.map(|x| -x), h), faces: BOX_FACES.to_vec() }
}

/// The closed box `[lo, hi]` as an f32 [`Mesh`], outward-facing triangles.
pub fn box_between(lo: [f32; 3], hi: [f32; 3]) -> Mesh {
    Mesh { vertices: box_corners(lo, hi), faces: BOX_FACES.to_vec(), vertex_attrs: None }
}

/// Ring resolution of revolved surfaces (a multiple of 4 keeps the bounding box, and
/// so the canonical origin, on the axis of revolution).
pub const SEGMENTS: usize = 32;

/// Shift a mesh so its bounding-box centre is the origin.
pub fn centred(mut m: Mesh) -> Mesh {
    let (lo, hi) = bounds(&m);
    let c = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, (lo[2] + hi[2]) / 2.0];
    for v in &mut m.vertices {
        for k in 0..3 {
            v[k] = (v[k] as f64 - c[k]) as f32;
        }
    }
    m
}

/// Bounding-box centre of a mesh (f64).
pub fn centre_of(m: &Mesh) -> [f64; 3] {
    let (lo, hi) = bounds(m);
    [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, (lo[2] + hi[2]) / 2.0]
}

/// Axis-aligned bounding box `(lo, hi)` of the vertices (f64).
pub fn bounds(m: &Mesh) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for v in &m.vertices {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k] as f64);
            hi[k] = hi[k].max(v[k] as f64);
        }
    }
    (lo, hi)
}

fn mesh_from(vertices: Vec<[f64; 3]>, faces: Vec<[u32; 3]>) -> Mesh {
    Mesh { vertices: vertices.into_iter().map(|v| v.map(|x| x as f32)).collect(), faces, vertex_attrs: None }
}

/// Surface of revolution about z of a profile in the (r, z) half-plane.
///
/// `closed = false`: the profile starts and ends on the axis (r = 0; those become single
/// pole vertices) and runs counter-clockwise (material on its left, r to the right and z
/// up), which gives outward normals. `closed = true`: a counter-clockwise loop off the
/// axis (a torus).
pub fn revolve(profile: &[[f64; 2]], closed: bool, n: usize) -> Mesh {
    let on_axis = |p: &[f64; 2]| p[0] == 0.0;
    let mut verts = Vec::new();
    let mut first = Vec::with_capacity(profile.len());
    for p in profile {
        first.push(verts.len() as u32);
        if on_axis(p) {
            verts.push([0.0, 0.0, p[1]]);
        } else {
            for k in 0..n {
                let a = TAU * k as f64 / n as f64;
                verts.push([p[0] * a.cos(), p[0] * a.sin(), p[1]]);
            }
        }
    }
    let idx = |i: usize, k: usize| if on_axis(&profile[i]) { first[i] } else { first[i] + (k % n) as u32 };
    let mut faces = Vec::new();
    let segs = if closed { profile.len() } else { profile.len() - 1 };
    for i in 0..segs {
        let j = (i + 1) % profile.len();
        for k in 0..n {
            let (a, b, c, d) = (idx(i, k), idx(j, k), idx(j, k + 1), idx(i, k + 1));
            if on_axis(&profile[i]) {
                faces.push([a, c, b]);
            } else if on_axis(&profile[j]) {
                faces.push([a, d, b]);
            } else {
                faces.push([a, c, b]);
                faces.push([a, d, c]);
            }
        }
    }
    mesh_from(verts, faces)
}

/// Prism: a counter-clockwise simple polygon in the xy-plane (with its triangulation)
/// extruded from z = 0 to z = h.
pub fn extrude(poly: &[[f64; 2]], tris: &[[u32; 3]], h: f64) -> Mesh {
    let n = poly.len() as u32;
    let mut verts: Vec<[f64; 3]> = poly.iter().map(|p| [p[0], p[1], 0.0]).collect();
    verts.extend(poly.iter().map(|p| [p[0], p[1], h]));
    let mut faces = Vec::new();
    for t in tris {
        faces.push([t[0], t[2], t[1]]);
        faces.push([t[0] + n, t[1] + n, t[2] + n]);
    }
    for i in 0..n {
        let j = (i + 1) % n;
        faces.push([i, j, j + n]);
        faces.push([i, j + n, i + n]);
    }
    mesh_from(verts, faces)
}

/// A closed box of sides `x`, `y`, `z`, centred on the origin.
pub fn box_mesh(x: f64, y: f64, z: f64) -> Mesh {
    let poly = [[-x / 2.0, -y / 2.0], [x / 2.0, -y / 2.0], [x / 2.0, y / 2.0], [-x / 2.0, y / 2.0]];
    centred(extrude(&poly, &[[0, 1, 2], [0, 2, 3]], z))
}

/// L-shaped prism: legs of length `a` (along x, width `tb`) and `b` (along y, width `ta`).
pub fn l_shape_mesh(a: f64, b: f64, ta: f64, tb: f64, h: f64) -> Mesh {
    let poly = [[0.0, 0.0], [a, 0.0], [a, tb], [ta, tb], [ta, b], [0.0, b]];
    // Fan from the outer corner (0, 0), which sees every vertex of the L.
    centred(extrude(&poly, &[[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]], h))
}

/// Closed can with bevelled rims.
pub fn cylinder_mesh(r: f64, h: f64, bevel: f64) -> Mesh {
    let p = [[0.0, 0.0], [r - bevel, 0.0], [r, bevel], [r, h - bevel], [r - bevel, h], [0.0, h]];
    centred(revolve(&p, false, SEGMENTS))
}

/// A closed sphere of radius `r`, centred on the origin.
pub fn sphere_mesh(r: f64) -> Mesh {
    let m = SEGMENTS / 2;
    let p: Vec<[f64; 2]> = (0..=m)
        .map(|i| {
            let phi = -FRAC_PI_2 + PI * i as f64 / m as f64;
            // Exact zeros at the poles so they become single vertices.
            let rr = if i == 0 || i == m { 0.0 } else { r * phi.cos() };
            [rr, r * phi.sin()]
        })
        .collect();
    centred(revolve(&p, false, SEGMENTS))
}

/// A closed torus about z: ring radius `big`, tube radius `small`, centred.
pub fn torus_mesh(big: f64, small: f64) -> Mesh {
    let m = 16;
    let p: Vec<[f64; 2]> = (0..m)
        .map(|i| {
            let b = TAU * i as f64 / m as f64;
            [big + small * b.cos(), small * b.sin()]
        })
        .collect();
    centred(revolve(&p, true, SEGMENTS))
}

/// Open bowl with walls of thickness `t`: an elliptic-quadrant wall from the foot
/// (radius `foot`) to the rim (radius `r`, height `h`).
pub fn bowl_mesh(r: f64, h: f64, foot: f64, t: f64) -> Mesh {
    let m = 10;
    let mut p = vec![[0.0, 0.0]];
    for i in 0..=m {
        let phi = FRAC_PI_2 * i as f64 / m as f64;
        p.push([foot + (r - foot) * phi.sin(), h * (1.0 - phi.cos())]);
    }
    for i in (0..=m).rev() {
        let phi = FRAC_PI_2 * i as f64 / m as f64;
        p.push([foot - t + (r - foot) * phi.sin(), t + (h - t) * (1.0 - phi.cos())]);
    }
    p.push([0.0, t]);
    centred(revolve(&p, false, SEGMENTS))
}

/// Cup body: flat bottom and vertical walls of thickness `t`.
pub fn cup_mesh(r: f64, h: f64, t: f64) -> Mesh {
    let p = [[0.0, 0.0], [r, 0.0], [r, h], [r - t, h], [r - t, t], [0.0, t]];
    revolve(&p, false, SEGMENTS)
}

/// A tube of radius `rho` swept along a polyline (path in the xz-plane), with flat caps.
pub fn tube_mesh(path: &[[f64; 3]], rho: f64, n: usize) -> Mesh {
    let mut verts = Vec::new();
    let m = path.len();
    for i in 0..m {
        let a = path[i.saturating_sub(1)];
        let b = path[(i + 1).min(m - 1)];
        let t = normalize([b[0] - a[0], b[1] - a[1], b[2] - a[2]]);
        // Path lies in the xz-plane: y is a constant normal, the binormal completes the frame.
        let nrm = [0.0, 1.0, 0.0];
        let bin = cross(t, nrm);
        for k in 0..n {
            let be = TAU * k as f64 / n as f64;
            let (c, s) = (be.cos(), be.sin());
            verts.push([0, 1, 2].map(|j| path[i][j] + rho * (c * nrm[j] + s * bin[j])));
        }
    }
    let c0 = verts.len() as u32;
    verts.push(path[0]);
    verts.push(path[m - 1]);
    let idx = |i: usize, k: usize| (i * n + k % n) as u32;
    let mut faces = Vec::new();
    for i in 0..m - 1 {
        for k in 0..n {
            let (a, b, c, d) = (idx(i, k), idx(i + 1, k), idx(i + 1, k + 1), idx(i, k + 1));
            faces.push([a, b, c]);
            faces.push([a, c, d]);
        }
    }
    for k in 0..n {
        faces.push([c0, idx(0, k), idx(0, k + 1)]);
        faces.push([c0 + 1, idx(m - 1, k + 1), idx(m - 1, k)]);
    }
    let mesh = mesh_from(verts, faces);
    // Orientation depends on the sweep direction; make it outward.
    if signed_volume(&mesh) < 0.0 {
        flip(mesh)
    } else {
        mesh
    }
}

/// Signed enclosed volume (positive for outward-oriented closed meshes).
pub fn signed_volume(m: &Mesh) -> f64 {
    m.faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| m.vertices[i as usize].map(|x| x as f64));
            a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0])
        })
        .sum::<f64>()
        / 6.0
}

/// The mesh with every face's orientation reversed.
pub fn flip(mut m: Mesh) -> Mesh {
    for f in &mut m.faces {
        f.swap(1, 2);
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tetrahedron_is_closed() {
        assert!(tetrahedron().topology().is_closed_oriented_manifold());
    }
}
