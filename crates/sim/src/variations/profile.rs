//! What an object offers to others, from vertical ray casts over its
//! footprint in its resting frame (z up, origin at the centre of mass): the
//! flat top a load can stand on, the cavity of an open container, and the
//! flat base it stands on itself.

use parry3d::math::Vector;
use parry3d::query::{Ray, RayCast};
use parry3d::shape::TriMesh as ParryTriMesh;
use recon_core::mesh::Mesh;

/// Grid cells per side.
const N: usize = 32;

#[derive(Debug, Clone)]
pub struct Profile {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
    /// First hit from above per cell (row-major, y rows), if any.
    pub top_hit: Vec<Option<f64>>,
    /// Cells of the flat top (within `tol` of the highest point).
    pub plateau: Vec<bool>,
    /// Cells over an enclosed, deep floor (an open container's inside).
    pub cavity: Vec<bool>,
    /// Cells of the flat base (within `tol` of the lowest point).
    pub base: Vec<bool>,
}

impl Profile {
    /// Cast 2·N² vertical rays at `mesh` (resting frame).
    pub fn new(mesh: &Mesh) -> Option<Profile> {
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for v in &mesh.vertices {
            for k in 0..3 {
                lo[k] = lo[k].min(v[k] as f64);
                hi[k] = hi[k].max(v[k] as f64);
            }
        }
        let verts: Vec<Vector> = mesh.vertices.iter().map(|v| Vector::new(v[0], v[1], v[2])).collect();
        let tm = ParryTriMesh::new(verts, mesh.faces.clone()).ok()?;
        let height = hi[2] - lo[2];
        if !(height > 0.0 && hi[0] > lo[0] && hi[1] > lo[1]) {
            return None;
        }
        // Flat within 1.5 mm (or 1.5 % of the height): a ball offers almost no top.
        let tol = (0.015 * height).max(0.0015);
        let mut top_hit = vec![None; N * N];
        let mut bottom_hit = vec![None; N * N];
        for j in 0..N {
            for i in 0..N {
                let (x, y) = cell_centre(&lo, &hi, i, j);
                let down = Ray::new(Vector::new(x as f32, y as f32, (hi[2] + 0.01) as f32), Vector::new(0.0, 0.0, -1.0));
                top_hit[j * N + i] = tm.cast_local_ray(&down, (height + 0.02) as f32, false).map(|t| hi[2] + 0.01 - t as f64);
                let up = Ray::new(Vector::new(x as f32, y as f32, (lo[2] - 0.01) as f32), Vector::new(0.0, 0.0, 1.0));
                bottom_hit[j * N + i] = tm.cast_local_ray(&up, (height + 0.02) as f32, false).map(|t| lo[2] - 0.01 + t as f64);
            }
        }
        let plateau: Vec<bool> = top_hit.iter().map(|h| h.is_some_and(|z| z >= hi[2] - tol)).collect();
        let base: Vec<bool> = bottom_hit.iter().map(|h| h.is_some_and(|z| z <= lo[2] + tol)).collect();
        // A cavity cell lies deep below the rim and meets rim before empty
        // space in all four grid directions (a bottle's shoulder or a torus'
        // hole does not).
        let deep = (0.25 * height).max(0.01);
        let rim = |c: usize| top_hit[c].is_some_and(|z| z >= hi[2] - deep / 2.0);
        let mut cavity = vec![false; N * N];
        for j in 0..N {
            for i in 0..N {
                let Some(z) = top_hit[j * N + i] else { continue };
                if z > hi[2] - deep {
                    continue;
                }
                let dirs: [(i64, i64); 4] = [(1, 0), (-1, 0), (0, 1), (0, -1)];
                cavity[j * N + i] = dirs.iter().all(|&(di, dj)| {
                    let (mut ci, mut cj) = (i as i64, j as i64);
                    loop {
                        ci += di;
                        cj += dj;
                        if ci < 0 || cj < 0 || ci >= N as i64 || cj >= N as i64 {
                            return false;
                        }
                        let c = cj as usize * N + ci as usize;
                        if top_hit[c].is_none() {
                            return false;
                        }
                        if rim(c) {
                            return true;
                        }
                    }
                });
            }
        }
        Some(Profile { lo, hi, top_hit, plateau, cavity, base })
    }

    fn cell(&self, x: f64, y: f64) -> Option<usize> {
        let fi = (x - self.lo[0]) / (self.hi[0] - self.lo[0]) * N as f64;
        let fj = (y - self.lo[1]) / (self.hi[1] - self.lo[1]) * N as f64;
        (fi >= 0.0 && fj >= 0.0 && fi < N as f64 && fj < N as f64).then(|| fj as usize * N + fi as usize)
    }

    pub fn in_cavity(&self, x: f64, y: f64) -> bool {
        self.cell(x, y).is_some_and(|c| self.cavity[c])
    }
    pub fn has_cavity(&self) -> bool {
        self.cavity.iter().any(|c| *c)
    }

    /// A flat base under the centre of mass covering at least 15 % of the footprint.
    pub fn flat_base(&self) -> bool {
        let hit = self.top_hit.iter().filter(|h| h.is_some()).count().max(1);
        let base = self.base.iter().filter(|b| **b).count();
        base >= 4 && base as f64 >= 0.15 * hit as f64 && self.cell(0.0, 0.0).is_some_and(|c| self.base[c])
    }

    /// Every test point of the rectangle `centre ± half·0.95` (corners, edge
    /// midpoints, centre) lies in the cells `set` selects.
    pub fn rect_in(&self, set: &[bool], centre: [f64; 2], half: [f64; 2]) -> bool {
        let s = [-0.95, 0.0, 0.95];
        s.iter().all(|u| s.iter().all(|v| self.cell(centre[0] + u * half[0], centre[1] + v * half[1]).is_some_and(|c| set[c])))
    }

    /// Highest floor under the rectangle (for dropping a load into a cavity).
    pub fn floor_under(&self, centre: [f64; 2], half: [f64; 2]) -> f64 {
        let s = [-1.0, -0.5, 0.0, 0.5, 1.0];
        let mut z = self.lo[2];
        for u in s {
            for v in s {
                if let Some(h) = self.cell(centre[0] + u * half[0], centre[1] + v * half[1]).and_then(|c| self.top_hit[c]) {
                    z = z.max(h);
                }
            }
        }
        z
    }

    /// Centres of the cells in `set`, in grid order.
    pub fn centres(&self, set: &[bool]) -> Vec<[f64; 2]> {
        (0..N * N)
            .filter(|c| set[*c])
            .map(|c| {
                let (x, y) = cell_centre(&self.lo, &self.hi, c % N, c / N);
                [x, y]
            })
            .collect()
    }
}

fn cell_centre(lo: &[f64; 3], hi: &[f64; 3], i: usize, j: usize) -> (f64, f64) {
    (lo[0] + (i as f64 + 0.5) / N as f64 * (hi[0] - lo[0]), lo[1] + (j as f64 + 0.5) / N as f64 * (hi[1] - lo[1]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use recon_core::mesh::primitives::{bowl_mesh, box_mesh, cylinder_mesh, sphere_mesh, torus_mesh};

    #[test]
    fn boxes_have_tops_bowls_have_cavities() {
        let b = Profile::new(&box_mesh(0.1, 0.08, 0.05)).unwrap();
        assert!(b.plateau.iter().all(|p| *p) && !b.has_cavity() && b.flat_base());
        let bowl = Profile::new(&bowl_mesh(0.08, 0.06, 0.04, 0.005)).unwrap();
        assert!(bowl.has_cavity() && bowl.in_cavity(0.0, 0.0), "bowl without cavity");
        assert!(!bowl.rect_in(&bowl.plateau, [0.0, 0.0], [0.0, 0.0]));
        let s = Profile::new(&sphere_mesh(0.04)).unwrap();
        assert!(
            !s.has_cavity() && !s.flat_base() && s.plateau.iter().filter(|p| **p).count() < 100,
            "{:?}",
            s.plateau.iter().filter(|p| **p).count()
        );
        let t = Profile::new(&torus_mesh(0.05, 0.015)).unwrap();
        assert!(!t.has_cavity(), "a torus' hole is no container");
        let c = Profile::new(&cylinder_mesh(0.03, 0.1, 0.002)).unwrap();
        assert!(
            !c.has_cavity()
                && c.flat_base()
                && c.rect_in(&c.plateau, [0.0, 0.0], [0.0; 2])
                && !c.rect_in(&c.plateau, [0.029, 0.029], [0.0; 2])
        );
    }
}
