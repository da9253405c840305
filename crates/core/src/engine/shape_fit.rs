//! Observation-guided structure: the stage-1 occupancy made to agree with
//! the measured depth before stage 2 generates on it.
//!
//! The depth says two things about an object, through its pose (canonical
//! grid → camera): space in front of the measured surface is empty, and the
//! object's own depth points lie on its surface. The fit works on the decoded
//! occupancy grid (the `r³` grid of `crate::geometry::voxelize`, voxel centre
//! `(i + ½)/r − ½`):
//!
//! 1. **carve**: a voxel whose centre lies in front of the measured depth
//!    (by the noise margin; nearest reading within a pixel) in any view is
//!    removed: observed free space.
//!    This also trims the silhouette, since the background behind it is
//!    measured too;
//!    The frame's support plane bounds it too: an object whose points stand
//!    in front of the plane does not reach through it;
//! 2. **fill**: every voxel holding an observed point of the object is set;
//! 3. hidden space (behind the surface, behind occluders, off the image) is
//!    left to the model;
//! 4. **clean**: a one-voxel closing seals the tunnels of a noisy volume
//!    (free space stays free), enclosed pockets are filled, the largest
//!    component is kept, and the result is reduced to its outer shell: the
//!    surface voxels the stage-2 model was trained on (`Fill::Surface`).
//!
//! Carving chose over latent guidance because stage 2's geometry follows the
//! active voxels almost exactly (README: GT shells re-encoded decode within
//! 0.014–0.022), so a correct shell is what makes a correct mesh, and the
//! grid operations cost milliseconds where guidance would repeat the SS
//! decoder at every step.

use crate::engine::pose_fit::ViewPoints;
use crate::geometry::Plane;
use crate::math::Similarity;
use crate::mesh::{marching_tetrahedra, Mesh, ScalarGrid};
use serde::Serialize;

/// Whether the stage-1 occupancy is fitted to the depth (`--shape-fit`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum ShapeFit {
    /// Carve observed free space, fill observed surface, keep the outer shell (module docs).
    #[default]
    Depth,
    /// `depth`, with the hidden concavities filled ([`ShapeFitOptions::hull`]): for convex objects.
    DepthHull,
    /// The model's occupancy as decoded.
    None,
}

/// Where an object's mesh comes from when the shape fit ran (`--mesh-from`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum MeshFrom {
    /// The closed, smoothed surface of the fitted occupancy
    /// ([`Grid::smooth_surface`]), coloured from the observed points (the
    /// Gaussians' colours where no point was observed).
    #[default]
    Fitted,
    /// The stage-2 mesh decoder's surface (FlexiCubes) as it is.
    Decoder,
}

/// Settings of the fit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ShapeFitOptions {
    /// Depth noise allowance (metres): a cell is free when its centre lies this
    /// far in front of the measured depth. Cells the surface passes through are
    /// filled back from the observed points, so the margin need only cover the
    /// noise, not the cell size.
    pub margin_m: f64,
    /// Seal tunnels up to two voxels wide before filling pockets.
    pub close: bool,
    /// Fill every axis-parallel line between its first and last occupied cell
    /// (the orthogonally convex hull), then carve again: hidden concavities the
    /// model made are filled, observed ones stay open.
    pub hull: bool,
    /// Grow the object's box until it holds the observed points (the model's
    /// shape keeps its metric size), and fit the box to the result afterwards,
    /// so the reported scale is the fitted shape's longest side.
    pub reframe: bool,
}

impl Default for ShapeFitOptions {
    fn default() -> Self {
        ShapeFitOptions { margin_m: 0.004, close: true, hull: false, reframe: true }
    }
}

/// What a fit did (voxel counts).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct ShapeFitReport {
    /// Occupied voxels as the model decoded them.
    pub model_voxels: usize,
    /// Model voxels in observed free space, removed.
    pub carved: usize,
    /// Observed-surface voxels the model left empty, set.
    pub filled: usize,
    /// Observed points outside the object grid (the pose's box is too small for them).
    pub points_outside_grid: usize,
    /// Voxels added by the closing and pocket filling.
    pub sealed: usize,
    /// Voxels of the smaller components, dropped.
    pub dropped: usize,
    /// Voxels handed to stage 2 (the outer shell).
    pub shell_voxels: usize,
}

/// A dense `r³` occupancy grid, flat index `(i·r + j)·r + k`.
#[derive(Debug, Clone, PartialEq)]
pub struct Grid {
    /// Cells per side.
    pub r: usize,
    /// Occupancy of every cell, `r³` long, by flat index.
    pub occ: Vec<bool>,
}

const N6: [[i32; 3]; 6] = [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]];

impl Grid {
    /// An `r³` grid with no cell occupied.
    pub fn empty(r: usize) -> Self {
        Grid { r, occ: vec![false; r * r * r] }
    }

    /// From occupied voxel coordinates (out-of-range ones ignored).
    pub fn from_coords(coords: &[[i32; 3]], r: usize) -> Self {
        let mut g = Self::empty(r);
        for c in coords {
            if let Some(i) = g.index(*c) {
                g.occ[i] = true;
            }
        }
        g
    }

    #[inline]
    fn index(&self, c: [i32; 3]) -> Option<usize> {
        let r = self.r as i32;
        (c.iter().all(|&v| (0..r).contains(&v))).then(|| ((c[0] * r + c[1]) * r + c[2]) as usize)
    }

    #[inline]
    fn coord(&self, i: usize) -> [i32; 3] {
        let r = self.r;
        [(i / (r * r)) as i32, ((i / r) % r) as i32, (i % r) as i32]
    }

    /// Occupied coordinates in flat-index (argwhere) order.
    pub fn coords(&self) -> Vec<[i32; 3]> {
        self.occ.iter().enumerate().filter(|(_, &o)| o).map(|(i, _)| self.coord(i)).collect()
    }

    /// Number of occupied cells.
    pub fn count(&self) -> usize {
        self.occ.iter().filter(|&&o| o).count()
    }

    /// The voxel centre in the canonical frame (`[-½, ½]³`).
    pub fn centre(&self, c: [i32; 3]) -> [f64; 3] {
        c.map(|v| (v as f64 + 0.5) / self.r as f64 - 0.5)
    }

    /// The voxel holding a canonical point, if inside the grid.
    pub fn voxel_of(&self, p: [f64; 3]) -> Option<[i32; 3]> {
        let c = p.map(|v| ((v + 0.5) * self.r as f64).floor());
        c.iter().all(|&v| v >= 0.0 && v < self.r as f64).then(|| c.map(|v| v as i32))
    }

    fn neighbours(&self, i: usize) -> impl Iterator<Item = Option<usize>> + '_ {
        let c = self.coord(i);
        N6.iter().map(move |d| self.index([c[0] + d[0], c[1] + d[1], c[2] + d[2]]))
    }

    /// One 6-neighbourhood dilation (`grow`) or erosion (cells outside the grid count as empty).
    fn morph(&self, grow: bool) -> Grid {
        let occ = (0..self.occ.len())
            .map(|i| {
                if grow {
                    self.occ[i] || self.neighbours(i).any(|n| n.is_some_and(|n| self.occ[n]))
                } else {
                    self.occ[i] && self.neighbours(i).all(|n| n.is_some_and(|n| self.occ[n]))
                }
            })
            .collect();
        Grid { r: self.r, occ }
    }

    /// Empty cells not reachable from outside the grid through empty cells
    /// (6-connected) become occupied.
    pub fn fill_pockets(&mut self) -> usize {
        let mut outside = vec![false; self.occ.len()];
        let mut stack: Vec<usize> = Vec::new();
        let r = self.r as i32;
        for i in 0..self.occ.len() {
            let c = self.coord(i);
            if !self.occ[i] && c.iter().any(|&v| v == 0 || v == r - 1) {
                outside[i] = true;
                stack.push(i);
            }
        }
        while let Some(i) = stack.pop() {
            for n in self.neighbours(i).flatten().collect::<Vec<_>>() {
                if !self.occ[n] && !outside[n] {
                    outside[n] = true;
                    stack.push(n);
                }
            }
        }
        let mut added = 0;
        for (o, out) in self.occ.iter_mut().zip(outside) {
            if !*o && !out {
                *o = true;
                added += 1;
            }
        }
        added
    }

    /// 26-connected components of the occupied cells, largest first (ties: lowest first cell).
    pub fn components(&self) -> Vec<Vec<usize>> {
        let mut label = vec![usize::MAX; self.occ.len()];
        let mut comps: Vec<Vec<usize>> = Vec::new();
        for start in 0..self.occ.len() {
            if !self.occ[start] || label[start] != usize::MAX {
                continue;
            }
            let id = comps.len();
            let (mut comp, mut stack) = (Vec::new(), vec![start]);
            label[start] = id;
            while let Some(i) = stack.pop() {
                comp.push(i);
                let c = self.coord(i);
                for dx in -1..=1 {
                    for dy in -1..=1 {
                        for dz in -1..=1 {
                            if let Some(n) = self.index([c[0] + dx, c[1] + dy, c[2] + dz]) {
                                if self.occ[n] && label[n] == usize::MAX {
                                    label[n] = id;
                                    stack.push(n);
                                }
                            }
                        }
                    }
                }
            }
            comps.push(comp);
        }
        comps.sort_by_key(|c| std::cmp::Reverse(c.len()));
        comps
    }

    /// Keep only the largest component; returns the voxels dropped.
    pub fn keep_largest(&mut self) -> usize {
        let comps = self.components();
        let mut dropped = 0;
        for c in comps.iter().skip(1) {
            for &i in c {
                self.occ[i] = false;
            }
            dropped += c.len();
        }
        dropped
    }

    /// Fill each axis-parallel line of cells between its first and last occupied one.
    pub fn fill_lines(&mut self) {
        let r = self.r as i32;
        for axis in 0..3 {
            let (a, b) = ((axis + 1) % 3, (axis + 2) % 3);
            for u in 0..r {
                for v in 0..r {
                    let at = |t: i32| {
                        let mut c = [0; 3];
                        (c[axis], c[a], c[b]) = (t, u, v);
                        c
                    };
                    let occ: Vec<i32> = (0..r).filter(|&t| self.index(at(t)).is_some_and(|i| self.occ[i])).collect();
                    if let (Some(&lo), Some(&hi)) = (occ.first(), occ.last()) {
                        for t in lo..=hi {
                            if let Some(i) = self.index(at(t)) {
                                self.occ[i] = true;
                            }
                        }
                    }
                }
            }
        }
    }

    /// The grid seen through `to_old` (new canonical point → old canonical
    /// point): each cell takes the value of the old cell its centre falls in.
    pub fn resample(&self, to_old: impl Fn([f64; 3]) -> [f64; 3]) -> Grid {
        let occ = (0..self.occ.len())
            .map(|i| self.voxel_of(to_old(self.centre(self.coord(i)))).and_then(|c| self.index(c)).is_some_and(|j| self.occ[j]))
            .collect();
        Grid { r: self.r, occ }
    }

    /// Bounding box of the occupied cells (canonical units, cell faces).
    pub fn bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let cs = self.coords();
        let first = *cs.first()?;
        let (mut lo, mut hi) = (first, first);
        for c in &cs {
            for a in 0..3 {
                lo[a] = lo[a].min(c[a]);
                hi[a] = hi[a].max(c[a]);
            }
        }
        let r = self.r as f64;
        Some((lo.map(|v| v as f64 / r - 0.5), hi.map(|v| (v + 1) as f64 / r - 0.5)))
    }

    /// Occupied cells with an empty (or out-of-grid) 6-neighbour.
    pub fn shell(&self) -> Grid {
        let occ = (0..self.occ.len()).map(|i| self.occ[i] && self.neighbours(i).any(|n| n.is_none_or(|n| !self.occ[n]))).collect();
        Grid { r: self.r, occ }
    }

    /// Occupied cells that touch only along an edge or at a corner are joined
    /// through a face-adjacent cell (x first, then y), so the 26-connected solid
    /// is 6-connected and its surface one piece. Returns the cells added.
    pub fn bridge_diagonals(&mut self) -> usize {
        let mut added = 0;
        for i in 0..self.occ.len() {
            if !self.occ[i] {
                continue;
            }
            let c = self.coord(i);
            for d in (0..27).map(|k| [k / 9 - 1, k / 3 % 3 - 1, k % 3 - 1]).filter(|d| d.iter().filter(|&&v| v != 0).count() >= 2) {
                let n = [c[0] + d[0], c[1] + d[1], c[2] + d[2]];
                if !self.index(n).is_some_and(|j| self.occ[j]) {
                    continue;
                }
                // Every monotone face path from c to n, axes taken in each order.
                let axes: Vec<usize> = (0..3).filter(|&a| d[a] != 0).collect();
                let orders: Vec<Vec<usize>> = if axes.len() == 2 {
                    vec![vec![axes[0], axes[1]], vec![axes[1], axes[0]]]
                } else {
                    vec![vec![0, 1, 2], vec![0, 2, 1], vec![1, 0, 2], vec![1, 2, 0], vec![2, 0, 1], vec![2, 1, 0]]
                };
                let path = |order: &[usize]| -> Vec<[i32; 3]> {
                    let mut p = c;
                    order[..order.len() - 1]
                        .iter()
                        .map(|&a| {
                            p[a] += d[a];
                            p
                        })
                        .collect()
                };
                let open = |q: &[i32; 3]| self.index(*q).is_some_and(|j| self.occ[j]);
                if orders.iter().any(|o| path(o).iter().all(open)) {
                    continue;
                }
                for q in path(&orders[0]) {
                    if let Some(j) = self.index(q) {
                        added += usize::from(!self.occ[j]);
                        self.occ[j] = true;
                    }
                }
            }
        }
        added
    }

    /// A closed, smooth surface of the solid these voxels enclose (pockets
    /// filled), in the canonical frame: the occupancy sampled `upsample` times
    /// finer, blurred ([1 2 1]/4 per axis), and its 0.5
    /// level taken with marching tetrahedra, so flat faces stay at the voxel faces.
    pub fn smooth_surface(&self, upsample: usize) -> Mesh {
        let mut solid = self.clone();
        solid.fill_pockets();
        solid.bridge_diagonals();
        let up = upsample.max(1);
        let pad = 3;
        let n = self.r * up + 2 * pad;
        let fine = 1.0 / (self.r * up) as f64;
        let coarse = |p: usize| (p as i64 - pad as i64).div_euclid(up as i64) as i32;
        let mut f: Vec<f32> = (0..n * n * n)
            .map(|i| {
                let c = [coarse(i / (n * n)), coarse(i / n % n), coarse(i % n)];
                if solid.index(c).is_some_and(|k| solid.occ[k]) {
                    1.0
                } else {
                    0.0
                }
            })
            .collect();
        // One [1 2 1]/4 pass per axis (σ ≈ 0.35 voxel): a one-voxel line of cells still
        // peaks at 0.71 and stays; wider blurs (two 5-tap passes, σ ≈ 0.7 voxel) broke
        // such lines into separate pieces and opened holes where the volume is thin.
        const K: [f32; 3] = [0.25, 0.5, 0.25];
        let stride = [n * n, n, 1];
        let mut tmp = vec![0f32; f.len()];
        for s in stride {
            for (i, out) in tmp.iter_mut().enumerate() {
                let pos = (i / s) % n;
                *out = (0..3).filter_map(|k| (pos + k).checked_sub(1).filter(|&q| q < n).map(|q| K[k] * f[i - pos * s + q * s])).sum();
            }
            std::mem::swap(&mut f, &mut tmp);
        }
        let origin = ((0.5 - pad as f64) * fine - 0.5) as f32;
        marching_tetrahedra(&ScalarGrid { values: &f, dims: [n; 3], origin: [origin; 3], spacing: fine as f32 }, 0.5)
    }

    /// Centres of the outer shell of the solid these voxels enclose (pockets
    /// filled), as canonical points: the surface a pose is refined against.
    pub fn outer_surface_points(&self) -> Vec<[f32; 3]> {
        let mut solid = self.clone();
        solid.fill_pockets();
        solid.shell().coords().iter().map(|&c| self.centre(c).map(|v| v as f32)).collect()
    }
}

/// Where the views put each cell: observed free space, and the cells holding
/// an observed point.
pub struct Observation {
    /// Per cell: observed free space in some view (in front of the measured depth, or beyond a support plane).
    pub free: Vec<bool>,
    /// Per cell: holds an observed point of the object.
    pub surface: Vec<bool>,
    /// Observed points that fall outside the grid.
    pub points_outside_grid: usize,
}

/// Classify the cells of an `r³` grid placed by `pose` (canonical → anchor
/// camera, after the per-axis `stretch` of the canonical frame) in every view.
/// `supports[k]` is view `k`'s support plane (camera frame, normal towards the
/// camera), when one was found: an object standing on it cannot reach through
/// it, so the cells beyond it count as free.
pub fn observe(
    r: usize,
    pose: &Similarity,
    stretch: [f64; 3],
    views: &[ViewPoints],
    supports: &[Option<Plane>],
    margin_m: f64,
) -> Observation {
    let grid = Grid::empty(r);
    let n = r * r * r;
    let mut free = vec![false; n];
    let mut surface = vec![false; n];
    let mut points_outside_grid = 0;
    for (k, v) in views.iter().enumerate() {
        let to_view = v.to_anchor.inverse().compose(pose);
        let support = standing_on(supports.get(k).copied().flatten(), v, margin_m);
        let depth = v.depth.as_deref();
        if support.is_some() || depth.is_some() {
            for (i, f) in free.iter_mut().enumerate().filter(|(_, f)| !**f) {
                let c = grid.centre(grid.coord(i));
                let q = to_view.apply(&[c[0] * stretch[0], c[1] * stretch[1], c[2] * stretch[2]]);
                *f = support.is_some_and(|p| p.signed_distance(&q) < -margin_m)
                    || depth.and_then(|d| d.depth_at(&q)).is_some_and(|d| q[2] + margin_m < d);
            }
        }
        let from_view = to_view.inverse();
        // Points on the support plane are the table's, whatever the mask says.
        for p in v.points.iter().filter(|p| support.is_none_or(|s| s.signed_distance(p) > margin_m)) {
            let c = from_view.apply(p);
            match grid.voxel_of([c[0] / stretch[0], c[1] / stretch[1], c[2] / stretch[2]]) {
                Some(c) => surface[grid.index(c).unwrap_or_default()] = true,
                None => points_outside_grid += 1,
            }
        }
    }
    Observation { free, surface, points_outside_grid }
}

/// `plane` when the object stands on it: most of its observed points lie in
/// front of it (by more than `margin_m`); a plane behind the object is not a support.
fn standing_on(plane: Option<Plane>, v: &ViewPoints, margin_m: f64) -> Option<Plane> {
    plane.filter(|p| {
        let mut d: Vec<f64> = v.points.iter().map(|q| p.signed_distance(q)).collect();
        d.sort_by(f64::total_cmp);
        d.get(d.len() / 2).is_some_and(|&m| m > margin_m)
    })
}

/// Move the vertices of a canonical mesh, placed by `pose` (canonical → anchor
/// camera, after `stretch`), that lie beyond a support plane the object stands
/// on ([`observe`]'s rule) onto that plane: the carved occupancy ends within a
/// voxel of the table, and the decoder's surface may reach past it, which a
/// physics engine would resolve by pushing the object up. Returns how many moved.
pub fn rest_on_supports(
    mesh: &mut Mesh,
    pose: &Similarity,
    stretch: [f64; 3],
    views: &[ViewPoints],
    supports: &[Option<Plane>],
    margin_m: f64,
) -> usize {
    let mut moved = 0;
    for (k, v) in views.iter().enumerate() {
        let Some(plane) = standing_on(supports.get(k).copied().flatten(), v, margin_m) else { continue };
        let to_view = v.to_anchor.inverse().compose(pose);
        let from_view = to_view.inverse();
        for p in mesh.vertices.iter_mut() {
            let q = to_view.apply(&std::array::from_fn(|a| p[a] as f64 * stretch[a]));
            let d = plane.signed_distance(&q);
            if d < 0.0 {
                let c = from_view.apply(&std::array::from_fn(|a| q[a] - d * plane.normal[a]));
                *p = std::array::from_fn(|a| (c[a] / stretch[a]) as f32);
                moved += 1;
            }
        }
    }
    moved
}

impl Observation {
    /// The observation wins over the grid: observed surface set, observed free space cleared.
    pub fn impose(&self, g: &mut Grid) {
        for (i, o) in g.occ.iter_mut().enumerate() {
            *o = (*o && !self.free[i]) || self.surface[i];
        }
    }
}

/// Fit the model's occupancy to the observation (module docs): the shell
/// handed to stage 2, and what changed.
pub fn fit_occupancy(model: &Grid, obs: &Observation, opts: &ShapeFitOptions) -> (Grid, ShapeFitReport) {
    let (solid, mut report) = fit_solid(model, obs, opts);
    let shell = solid.shell();
    report.shell_voxels = shell.count();
    (shell, report)
}

/// [`fit_occupancy`] before the shell: the cleaned solid.
pub fn fit_solid(model: &Grid, obs: &Observation, opts: &ShapeFitOptions) -> (Grid, ShapeFitReport) {
    let mut report = ShapeFitReport { model_voxels: model.count(), points_outside_grid: obs.points_outside_grid, ..Default::default() };
    let mut g = model.clone();
    for i in 0..g.occ.len() {
        if obs.surface[i] {
            report.filled += usize::from(!g.occ[i]);
            g.occ[i] = true;
        } else if obs.free[i] && g.occ[i] {
            g.occ[i] = false;
            report.carved += 1;
        }
    }
    let before = g.count();
    if opts.close {
        g = g.morph(true).morph(false);
        // The closing must not put back what the depth removed.
        obs.impose(&mut g);
    }
    if opts.hull {
        g.fill_lines();
        obs.impose(&mut g);
    }
    g.fill_pockets();
    report.sealed = g.count().saturating_sub(before);
    report.dropped = g.keep_largest();
    (g, report)
}

/// Fit the model's grid in the pose it was chosen in (canonical → anchor camera, after
/// `stretch`): with [`ShapeFitOptions::reframe`] the box first grows to hold the observed
/// points and is fitted to the result afterwards, the constraints held again in that
/// final frame. Returns the final pose, the shell for stage 2 and what changed.
pub fn fit_in_pose(
    mut model: Grid,
    mut anchor: Similarity,
    stretch: [f64; 3],
    views: &[ViewPoints],
    supports: &[Option<Plane>],
    fo: &ShapeFitOptions,
) -> (Similarity, Grid, ShapeFitReport) {
    let r = model.r;
    // Re-express the grid in a new canonical frame x_old = k·x_new + c (the pose absorbs it).
    let reframe = |anchor: &Similarity, k: f64, c: [f64; 3]| {
        anchor.compose(&Similarity { rotation: IDENTITY, translation: std::array::from_fn(|a| stretch[a] * c[a]), scale: k })
    };
    if fo.reframe {
        // Grow the box to hold the observed points (1–99 % per axis, against stray points).
        let inv = anchor.inverse();
        let pts: Vec<[f64; 3]> = views
            .iter()
            .flat_map(|v| v.points.iter().map(|p| inv.apply(&v.to_anchor.apply(p))))
            .map(|q| std::array::from_fn(|a| q[a] / stretch[a]))
            .collect();
        if pts.len() >= 10 {
            let (mut lo, mut hi) = ([-0.5f64; 3], [0.5f64; 3]);
            for a in 0..3 {
                let mut v: Vec<f64> = pts.iter().map(|p| p[a]).collect();
                v.sort_by(f64::total_cmp);
                lo[a] = lo[a].min(v[v.len() / 100]);
                hi[a] = hi[a].max(v[v.len() - 1 - v.len() / 100]);
            }
            let k = (0..3).map(|a| hi[a] - lo[a]).fold(1.0, f64::max);
            let c: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
            if k > 1.0 || c.iter().any(|&x| x != 0.0) {
                model = model.resample(|x| std::array::from_fn(|a| k * x[a] + c[a]));
                anchor = reframe(&anchor, k, c);
            }
        }
    }
    let obs = observe(r, &anchor, stretch, views, supports, fo.margin_m);
    let (mut solid, mut report) = fit_solid(&model, &obs, fo);
    if fo.reframe {
        // Fit the box to the shape (longest side = the grid), then hold the constraints
        // again in that frame: the shell handed on obeys them in the final pose.
        if let Some((lo, hi)) = solid.bounds() {
            let k = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
            let c: [f64; 3] = std::array::from_fn(|a| 0.5 * (lo[a] + hi[a]));
            if k > 0.0 {
                solid = solid.resample(|x| std::array::from_fn(|a| k * x[a] + c[a]));
                anchor = reframe(&anchor, k, c);
                let obs = observe(r, &anchor, stretch, views, supports, fo.margin_m);
                obs.impose(&mut solid);
                solid.fill_pockets();
                solid.keep_largest();
                report.points_outside_grid = obs.points_outside_grid;
            }
        }
    }
    let shell = solid.shell();
    report.shell_voxels = shell.count();
    (anchor, shell, report)
}

const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::frame::Intrinsics;
    use crate::engine::pose_fit::DepthView;
    use crate::mesh::primitives::cuboid;
    use crate::render::{render, Camera, Instance, RenderMesh, RenderOptions};

    const K: Intrinsics = Intrinsics { fx: 500.0, fy: 500.0, cx: 160.0, cy: 120.0 };
    const W: usize = 320;
    const H: usize = 240;
    /// The GT box in the canonical frame: 1.0 × 0.4 × 0.6 (longest side 1).
    const HALF: [f64; 3] = [0.5, 0.2, 0.3];

    /// A box at 0.8 m (0.2 m long, thin axis across the image, 0.6 deep along the rays)
    /// in front of a wall at 1.2 m: its pose, the measured view, and the raw depth.
    fn scene() -> (Similarity, ViewPoints, Vec<f32>) {
        let pose = Similarity { rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], translation: [0.0, 0.0, 0.8], scale: 0.2 };
        let obj = RenderMesh::from_trimesh(&cuboid(HALF), "box").unwrap();
        let wall = RenderMesh::from_trimesh(&cuboid([2.0, 2.0, 0.01]), "wall").unwrap();
        let wall_pose = Similarity { translation: [0.0, 0.0, 1.2], ..Similarity::identity() };
        let cam = Camera::new(W, H, K);
        let out = render(&[Instance::new(&obj, pose, 1), Instance::new(&wall, wall_pose, 2)], &cam, &RenderOptions::default()).unwrap();
        let mut points = Vec::new();
        for v in 0..H {
            for u in 0..W {
                let i = v * W + u;
                if out.index[i] == 0 && out.depth[i] > 0.0 {
                    let z = out.depth[i] as f64;
                    points.push([(u as f64 - K.cx) / K.fx * z, (v as f64 - K.cy) / K.fy * z, z]);
                }
            }
        }
        let depth = DepthView::new(&out.depth, W, H, K);
        (pose, ViewPoints { points, to_anchor: Similarity::identity(), depth }, out.depth)
    }

    fn extent(g: &Grid, axis: usize) -> (f64, f64) {
        let v: Vec<f64> = g.coords().iter().map(|&c| g.centre(c)[axis]).collect();
        (v.iter().cloned().fold(f64::INFINITY, f64::min), v.iter().cloned().fold(f64::NEG_INFINITY, f64::max))
    }

    #[test]
    fn a_planted_wrong_shape_is_corrected_and_free_space_stays_empty() {
        let (pose, view, raw_depth) = scene();
        let r = 32;
        // The model's guess: a ball, too full across the image and in front of the box.
        let model = ball(r, 0.45, [0.0; 3]);
        let opts = ShapeFitOptions::default();
        let obs = observe(r, &pose, [1.0; 3], std::slice::from_ref(&view), &[], opts.margin_m);
        assert_eq!(obs.points_outside_grid, 0);
        let (shell, report) = fit_occupancy(&model, &obs, &opts);
        let cell = 1.0 / r as f64;
        assert!(report.carved > 0 && report.filled > 0, "{report:?}");

        // No occupied voxel in observed free space: every cell's centre lies behind the
        // nearest depth reading within a pixel of its projection, less the margin.
        for c in shell.coords() {
            let p = pose.apply(&shell.centre(c));
            let (u, v) = ((K.fx * p[0] / p[2] + K.cx).round() as i64, (K.fy * p[1] / p[2] + K.cy).round() as i64);
            let mut d = f64::INFINITY;
            for (uu, vv) in (u - 1..=u + 1).flat_map(|uu| (v - 1..=v + 1).map(move |vv| (uu, vv))) {
                if (0..W as i64).contains(&uu) && (0..H as i64).contains(&vv) {
                    d = d.min(raw_depth[vv as usize * W + uu as usize] as f64);
                }
            }
            assert!(
                p[2] >= d - opts.margin_m - 1e-9 || !d.is_finite(),
                "voxel {c:?} lies in free space: {:.4} m in front of {d:.4} m",
                p[2]
            );
        }

        // Across the image (y) and in front (−z) the shape now follows the box; along x
        // the observed face extends it where the ball fell short; behind, the model stays.
        let tol = 1.5 * cell;
        let (y0, y1) = extent(&shell, 1);
        assert!(y0 >= -HALF[1] - tol && y1 <= HALF[1] + tol, "y extent {y0:.3}..{y1:.3}, box ±{}", HALF[1]);
        let (m0, m1) = extent(&model, 1);
        assert!(m0 < -0.4 && m1 > 0.4, "the planted shape was wrong to begin with");
        let (z0, z1) = extent(&shell, 2);
        assert!(z0 >= -HALF[2] - tol, "front at {z0:.3}, box front at {}", -HALF[2]);
        assert!(z1 > 0.4, "hidden space is the model's: back at {z1:.3}");
        let (x0, x1) = extent(&shell, 0);
        assert!(x0 <= -HALF[0] + tol && x1 >= HALF[0] - tol, "x extent {x0:.3}..{x1:.3}");

        // One component, no internal pockets: filling the shell's inside and taking the
        // shell again gives the same voxels.
        assert_eq!(shell.components().len(), 1);
        let mut solid = shell.clone();
        solid.fill_pockets();
        assert_eq!(solid.shell(), shell);
        assert_eq!(report.shell_voxels, shell.count());
    }

    #[test]
    fn the_support_plane_bounds_the_hidden_side() {
        let (pose, mut view, _) = scene();
        view.depth = None;
        let r = 32;
        let model = ball(r, 0.45, [0.0; 3]);
        let opts = ShapeFitOptions::default();
        // The plane the box stands on: y = 0.04 m (its bottom face; camera y is down).
        let table = Plane { normal: [0.0, -1.0, 0.0], offset: 0.04 };
        let obs = observe(r, &pose, [1.0; 3], std::slice::from_ref(&view), &[Some(table)], opts.margin_m);
        let (shell, _) = fit_occupancy(&model, &obs, &opts);
        let (_, y1) = extent(&shell, 1);
        assert!(y1 <= HALF[1] + opts.margin_m / pose.scale + 1.0 / r as f64, "reaches y = {y1:.3} through the table");
        // A plane the object is not standing on (its points behind it) is ignored.
        let behind = Plane { normal: [0.0, 1.0, 0.0], offset: -0.04 };
        let obs = observe(r, &pose, [1.0; 3], std::slice::from_ref(&view), &[Some(behind)], opts.margin_m);
        assert!(obs.free.iter().all(|f| !f));
    }

    #[test]
    fn nothing_is_carved_without_depth_and_the_fit_is_deterministic() {
        let (pose, mut view, _) = scene();
        let model = ball(24, 0.45, [0.0; 3]);
        let opts = ShapeFitOptions::default();
        let a = fit_occupancy(&model, &observe(24, &pose, [1.0; 3], std::slice::from_ref(&view), &[], opts.margin_m), &opts);
        let b = fit_occupancy(&model, &observe(24, &pose, [1.0; 3], std::slice::from_ref(&view), &[], opts.margin_m), &opts);
        assert_eq!(a, b);
        view.depth = None;
        let (_, report) = fit_occupancy(&model, &observe(24, &pose, [1.0; 3], std::slice::from_ref(&view), &[], opts.margin_m), &opts);
        assert_eq!(report.carved, 0);
    }

    fn ball(r: usize, radius: f64, centre: [f64; 3]) -> Grid {
        let mut g = Grid::empty(r);
        for i in 0..g.occ.len() {
            let c = g.centre(g.coord(i));
            g.occ[i] = (0..3).map(|a| (c[a] - centre[a]).powi(2)).sum::<f64>().sqrt() <= radius;
        }
        g
    }

    #[test]
    fn pockets_fill_and_shell_is_the_outside() {
        let mut g = ball(16, 0.4, [0.0; 3]);
        let solid = g.count();
        let hollow = g.shell();
        let mut h = hollow.clone();
        let added = h.fill_pockets();
        assert_eq!(h.count(), solid, "filling the hollow ball's pocket gives the solid back");
        assert_eq!(added, solid - hollow.count());
        assert!(hollow.count() < solid / 2);
        // A second, smaller blob is dropped.
        g.occ[0] = true;
        assert_eq!(g.keep_largest(), 1);
        assert_eq!(g.count(), solid);
    }

    #[test]
    fn closing_seals_a_tunnel() {
        // A solid cube with a one-voxel tunnel drilled to its centre.
        let r = 16;
        let mut g = Grid::empty(r);
        for i in 0..g.occ.len() {
            let c = g.coord(i);
            g.occ[i] = c.iter().all(|&v| (3..13).contains(&v));
        }
        for x in 3..8 {
            let i = g.index([x, 8, 8]).unwrap();
            g.occ[i] = false;
        }
        let open = g.clone();
        let mut o2 = open.clone();
        assert_eq!(o2.fill_pockets(), 0, "the tunnel connects the hole to the outside");
        let mut closed = g.morph(true).morph(false);
        closed.fill_pockets();
        // Sealed behind its mouth (a one-voxel dent at the face stays, as for any closing).
        assert!((4..8).all(|x| closed.occ[closed.index([x, 8, 8]).unwrap()]));
        assert_eq!(closed.count(), open.count() + 4);
    }

    /// A mesh reaching through the table the box stands on ends on it; a plane
    /// the object does not stand on moves nothing.
    #[test]
    fn a_mesh_through_the_support_plane_is_brought_onto_it() {
        let (pose, view, _) = scene();
        // The box's bottom face is y = +0.04 m (camera y down); the mesh is 10 % too tall.
        let tall = crate::mesh::primitives::cuboid([HALF[0], HALF[1] * 1.1, HALF[2]]);
        let mut mesh = Mesh::from(&tall);
        let before = mesh.clone();
        let table = Plane { normal: [0.0, -1.0, 0.0], offset: 0.04 };
        let views = std::slice::from_ref(&view);
        let moved = rest_on_supports(&mut mesh, &pose, [1.0; 3], views, &[Some(table)], 0.002);
        assert!(moved > 0);
        for (a, b) in mesh.vertices.iter().zip(&before.vertices) {
            let q = pose.apply(&a.map(|x| x as f64));
            assert!(table.signed_distance(&q) > -1e-6, "vertex {a:?} beyond the table");
            if table.signed_distance(&pose.apply(&b.map(|x| x as f64))) >= 0.0 {
                assert_eq!(a, b, "a vertex in front of the table moved");
            }
        }
        let behind = Plane { normal: [0.0, 1.0, 0.0], offset: -0.04 };
        let mut m2 = before.clone();
        assert_eq!(rest_on_supports(&mut m2, &pose, [1.0; 3], views, &[Some(behind)], 0.002), 0);
        assert_eq!(m2, before);
    }

    /// Cells touching at an edge or a corner only become one 6-connected piece,
    /// and the fitted surface of a solid is one closed piece.
    #[test]
    fn diagonal_contacts_are_bridged_and_the_surface_is_one_piece() {
        let mut g = Grid::empty(8);
        for c in [[2, 2, 2], [3, 3, 2], [4, 4, 3]] {
            let i = g.index(c).unwrap();
            g.occ[i] = true;
        }
        let added = g.bridge_diagonals();
        assert!(added >= 3, "{added}");
        let six_connected = |g: &Grid| {
            let start = g.occ.iter().position(|&o| o).unwrap();
            let (mut seen, mut stack) = (vec![false; g.occ.len()], vec![start]);
            seen[start] = true;
            while let Some(i) = stack.pop() {
                for n in g.neighbours(i).flatten() {
                    if g.occ[n] && !seen[n] {
                        seen[n] = true;
                        stack.push(n);
                    }
                }
            }
            seen.iter().filter(|&&s| s).count() == g.count()
        };
        assert!(six_connected(&g));
        assert_eq!(g.bridge_diagonals(), 0);
        // A one-voxel line stays one piece through the blur.
        let mut line = Grid::empty(12);
        for x in 2..10 {
            let i = line.index([x, 5, 5]).unwrap();
            line.occ[i] = true;
        }
        let q = crate::mesh::mesh_quality(&line.smooth_surface(2)).unwrap();
        assert_eq!((q.components, q.boundary_edges), (1, 0), "{q:?}");
        let m = ball(16, 0.35, [0.0; 3]).smooth_surface(2);
        let q = crate::mesh::mesh_quality(&m).unwrap();
        assert_eq!((q.components, q.boundary_edges, q.non_manifold_edges), (1, 0, 0), "{q:?}");
    }
}
