//! The non-learned `observed` baseline: every GT instance's visible depth points, cleaned,
//! boxed and hulled. Its scores are the floor a learned reconstruction has to beat.
//!
//! Per GT instance with a visible mask (BOP `mask_visib/`, YCB-Video `-label.png`):
//! 1. **Points.** The mask is eroded (5×5, once: RecGen's erosion, which trims the mixed
//!    object/background depth at silhouettes; the raw mask is used when erosion leaves
//!    fewer than `min_points`) and its valid depth pixels are back-projected
//!    ([`recon_core::geometry::pointmap::masked_points`]).
//! 2. **Outliers.** (a) Largest connected component of the k-nearest-neighbour graph whose
//!    edges are shorter than `gap_factor` × the median nearest-neighbour spacing: drops
//!    background or occluder pixels that leaked into the mask behind a depth gap, whatever
//!    their number. (b) Statistical outlier removal: a point goes when its mean distance to
//!    its k neighbours exceeds the mean of that statistic by `sor_std` standard deviations
//!    (flying pixels, isolated noise), or twice its median, whichever is larger.
//! 3. **Oriented bounding box.** Candidate "height" axes: the three PCA axes and the normal
//!    of every face of the points' 3D convex hull (a box face is flush with a hull face
//!    for boxes and most near-optimal boxes, and PCA alone is arbitrary for a cube). For
//!    each, the hull vertices are projected on the perpendicular plane and the
//!    minimum-area rectangle of that 2D hull is found exactly (it has a side on a hull
//!    edge). The smallest-volume box wins. Its axes are ordered by decreasing extent
//!    (x longest), each signed so its largest camera-frame component is positive, z = x × y.
//! 4. **Prediction.** Pose `R` = the box axes as columns, `t` = the box centre (camera
//!    frame, metres), `scale = 1`; shape = the convex hull of the cleaned points (or the box
//!    itself with [`Shape::Box`]) in that box frame, in metres. Coplanar points give a
//!    flat two-sided hull; the box stands in when no hull exists (collinear points).
//!
//! What the metrics mean for it: the mesh lives in its own frame, not the GT model's, so
//! the prediction is written with `model_frame: false` and ADD / ADD-S are not computed.
//! ADD-SB compares the posed surfaces, i.e. the hull where the points were seen against
//! the whole GT surface: it is low only when most of the object is visible and thin.
//! CD_norm ICP-aligns the hull onto the GT surface from that placement, so it measures the
//! shape error of "the visible part is the object". DRE compares the hull's diameter (the
//! visible points' diameter; the box diagonal for [`Shape::Box`]) with the GT diameter:
//! occlusion shortens it.

use crate::correction::DatasetCorrection;
use crate::report::{Prediction, PredictionsFile};
use nalgebra::{Matrix3, SymmetricEigen, Vector3};
use rayon::prelude::*;
use recon_core::dataset::bop::{Dataset, Frame, MaskSource};
use recon_core::dataset::frame::{load_depth_u16, Intrinsics};
use recon_core::dataset::masks::{erode, load_binary_mask, Erosion, InstanceMap};
use recon_core::geometry::pointmap::masked_points;
use recon_core::mesh::primitives::cuboid;
use recon_core::mesh::trimesh::TriMesh;
use recon_core::spatial::{KdTree, P3};
use recon_core::{Error, Result};
use std::path::{Path, PathBuf};

/// What the baseline outputs as the object's shape.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Shape {
    /// Convex hull of the cleaned visible points.
    Hull,
    /// The oriented bounding box as a 12-triangle mesh.
    Box,
}

#[derive(Debug, Clone, Copy)]
/// Settings of the `observed` baseline.
pub struct ObservedOptions {
    /// Output shape: convex hull or oriented box.
    pub shape: Shape,
    /// Mask erosion before back-projection (`None`: use the mask as is).
    pub erosion: Option<Erosion>,
    /// Fewer cleaned points than this: the instance gets no prediction (missed).
    pub min_points: usize,
    /// Neighbours for the component graph and the outlier statistic.
    pub knn: usize,
    /// Component-graph edge limit in units of the median nearest-neighbour spacing.
    pub gap_factor: f64,
    /// Statistical-outlier threshold in standard deviations.
    pub sor_std: f64,
}

impl Default for ObservedOptions {
    fn default() -> Self {
        ObservedOptions { shape: Shape::Hull, erosion: Some(Erosion::default()), min_points: 20, knn: 8, gap_factor: 10.0, sor_std: 3.0 }
    }
}

/// Oriented bounding box: `x_cam = axes · x_box + center`, the box being `[-half, half]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Obb {
    /// Rotation whose columns are the box axes (camera frame), det +1.
    pub axes: [[f64; 3]; 3],
    pub center: P3,
    pub half: P3,
}

impl Obb {
    pub fn volume(&self) -> f64 {
        8.0 * self.half[0] * self.half[1] * self.half[2]
    }

    fn surface(&self) -> f64 {
        let [a, b, c] = self.half;
        8.0 * (a * b + b * c + a * c)
    }

    /// Camera-frame point → box frame.
    pub fn to_local(self, p: &P3) -> P3 {
        let d = [p[0] - self.center[0], p[1] - self.center[1], p[2] - self.center[2]];
        let r = &self.axes;
        [0, 1, 2].map(|j| r[0][j] * d[0] + r[1][j] * d[1] + r[2][j] * d[2])
    }

    fn column(&self, j: usize) -> Vector3<f64> {
        Vector3::new(self.axes[0][j], self.axes[1][j], self.axes[2][j])
    }
}

fn v3(p: &P3) -> Vector3<f64> {
    Vector3::new(p[0], p[1], p[2])
}

/// Removes points outside the largest k-NN component and statistical outliers (module
/// docs, step 2). Output keeps the input order.
pub fn clean_points(pts: &[P3], o: &ObservedOptions) -> Vec<P3> {
    let k = o.knn.max(1);
    if pts.len() <= k + 1 {
        return pts.to_vec();
    }
    let nbrs = KdTree::new(pts).k_nearest_all(pts, k + 1);
    // Neighbours other than the point itself (a duplicate point may come first).
    let others = |i: usize| nbrs[i].iter().filter(move |(j, _)| *j != i).take(k);
    let mut nn1: Vec<f64> = (0..pts.len()).filter_map(|i| others(i).next().map(|x| x.1)).collect();
    nn1.sort_by(f64::total_cmp);
    let spacing = nn1[nn1.len() / 2];
    let gap = o.gap_factor * spacing;
    let mut uf: Vec<usize> = (0..pts.len()).collect();
    fn root(uf: &mut [usize], mut i: usize) -> usize {
        while uf[i] != i {
            uf[i] = uf[uf[i]];
            i = uf[i];
        }
        i
    }
    for i in 0..pts.len() {
        let nb: Vec<(usize, f64)> = others(i).copied().collect();
        for (j, d) in nb {
            if d <= gap {
                let (a, b) = (root(&mut uf, i), root(&mut uf, j));
                if a != b {
                    uf[a.max(b)] = a.min(b);
                }
            }
        }
    }
    let roots: Vec<usize> = (0..pts.len()).map(|i| root(&mut uf, i)).collect();
    let mut size = vec![0usize; pts.len()];
    for &r in &roots {
        size[r] += 1;
    }
    // Largest component; ties go to the one holding the lowest index (deterministic).
    let best = (0..pts.len()).max_by(|&a, &b| size[a].cmp(&size[b]).then(b.cmp(&a))).unwrap_or(0);
    let comp: Vec<P3> = pts.iter().zip(&roots).filter(|(_, &r)| r == best).map(|(p, _)| *p).collect();
    if comp.len() <= k + 1 {
        return comp;
    }
    let nbrs = KdTree::new(&comp).k_nearest_all(&comp, k + 1);
    let mean_d: Vec<f64> = nbrs
        .iter()
        .enumerate()
        .map(|(i, n)| {
            let d: Vec<f64> = n.iter().filter(|(j, _)| *j != i).take(k).map(|x| x.1).collect();
            d.iter().sum::<f64>() / d.len().max(1) as f64
        })
        .collect();
    let mu = mean_d.iter().sum::<f64>() / mean_d.len() as f64;
    let sd = (mean_d.iter().map(|d| (d - mu) * (d - mu)).sum::<f64>() / mean_d.len() as f64).sqrt();
    // Never below twice the typical value: on a clean surface the statistic is tight and
    // μ + kσ would shave off the (sparser-neighbourhood) boundary, shrinking the box.
    let mut sorted = mean_d.clone();
    sorted.sort_by(f64::total_cmp);
    let lim = (mu + o.sor_std * sd).max(2.0 * sorted[sorted.len() / 2]);
    comp.iter().zip(&mean_d).filter(|(_, &d)| d <= lim).map(|(p, _)| *p).collect()
}

/// Principal axes (unit columns), by decreasing variance.
fn pca_axes(pts: &[P3]) -> [Vector3<f64>; 3] {
    let n = pts.len() as f64;
    let mean = pts.iter().fold(Vector3::zeros(), |a, p| a + v3(p)) / n;
    let mut cov = Matrix3::zeros();
    for p in pts {
        let d = v3(p) - mean;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov / n);
    let mut order = [0usize, 1, 2];
    order.sort_by(|&a, &b| eig.eigenvalues[b].total_cmp(&eig.eigenvalues[a]));
    order.map(|i| eig.eigenvectors.column(i).into_owned())
}

fn cross2(o: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
}

/// 2D convex hull (Andrew's monotone chain), counter-clockwise, no collinear points.
fn hull2(mut p: Vec<[f64; 2]>) -> Vec<[f64; 2]> {
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let mut h: Vec<[f64; 2]> = Vec::with_capacity(2 * p.len());
    for pass in 0..2 {
        let start = h.len();
        let it: Box<dyn Iterator<Item = &[f64; 2]>> = if pass == 0 { Box::new(p.iter()) } else { Box::new(p.iter().rev()) };
        for &q in it {
            while h.len() >= start + 2 && cross2(h[h.len() - 2], h[h.len() - 1], q) <= 0.0 {
                h.pop();
            }
            h.push(q);
        }
        h.pop();
    }
    h
}

/// Minimum-area box whose third axis is `a` (unit): the 2D minimum-area rectangle of the
/// points projected on the plane ⊥ `a`, spanned by `u` and `a × u`.
fn box_around(pts: &[P3], a: Vector3<f64>, u: Vector3<f64>) -> Obb {
    let u = (u - a * a.dot(&u)).normalize();
    let v = a.cross(&u);
    let h = hull2(pts.iter().map(|p| [v3(p).dot(&u), v3(p).dot(&v)]).collect());
    let mut dirs: Vec<[f64; 2]> = Vec::new();
    for i in 0..h.len() {
        let (p, q) = (h[i], h[(i + 1) % h.len()]);
        let (dx, dy) = (q[0] - p[0], q[1] - p[1]);
        let l = (dx * dx + dy * dy).sqrt();
        if l > 0.0 {
            dirs.push([dx / l, dy / l]);
        }
    }
    if dirs.is_empty() {
        dirs.push([1.0, 0.0]);
    }
    // Exact for a convex polygon: the optimal rectangle has a side on a hull edge.
    let mut best = (f64::INFINITY, [1.0, 0.0]);
    for e in dirs {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for q in &h {
            let c = [q[0] * e[0] + q[1] * e[1], -q[0] * e[1] + q[1] * e[0]];
            for k in 0..2 {
                lo[k] = lo[k].min(c[k]);
                hi[k] = hi[k].max(c[k]);
            }
        }
        let area = (hi[0] - lo[0]) * (hi[1] - lo[1]);
        if area < best.0 {
            best = (area, e);
        }
    }
    let e = best.1;
    let ax = [u * e[0] + v * e[1], -u * e[1] + v * e[0], a];
    fit_to_axes(pts, ax)
}

/// The tight box with the given orthonormal axes.
fn fit_to_axes(pts: &[P3], ax: [Vector3<f64>; 3]) -> Obb {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in pts {
        for k in 0..3 {
            let c = v3(p).dot(&ax[k]);
            lo[k] = lo[k].min(c);
            hi[k] = hi[k].max(c);
        }
    }
    let mid = ax[0] * (0.5 * (lo[0] + hi[0])) + ax[1] * (0.5 * (lo[1] + hi[1])) + ax[2] * (0.5 * (lo[2] + hi[2]));
    let mut axes = [[0.0; 3]; 3];
    for (j, c) in ax.iter().enumerate() {
        for i in 0..3 {
            axes[i][j] = c[i];
        }
    }
    Obb { axes, center: [mid[0], mid[1], mid[2]], half: [0, 1, 2].map(|k| 0.5 * (hi[k] - lo[k])) }
}

/// Oriented bounding box of a point set (module docs, step 3); `None` when empty.
pub fn fit_obb(pts: &[P3]) -> Option<Obb> {
    fit_obb_with_hull(pts, convex_hull(pts).as_ref())
}

/// [`fit_obb`] given the points' convex hull (same frame), when already computed.
pub fn fit_obb_with_hull(pts: &[P3], hull: Option<&TriMesh>) -> Option<Obb> {
    if pts.is_empty() {
        return None;
    }
    // The box of a set is the box of its hull: only hull vertices need projecting.
    let ext: &[P3] = hull.map_or(pts, |h| &h.vertices);
    let pcs = pca_axes(pts);
    let mut cands = Vec::new();
    for k in 0..3 {
        cands.push(box_around(ext, pcs[k], pcs[(k + 1) % 3]));
    }
    if let Some(h) = hull {
        for f in &h.faces {
            let [a, b, c] = f.map(|i| v3(&h.vertices[i as usize]));
            let n = (b - a).cross(&(c - a));
            if n.norm() > 0.0 {
                let n = n.normalize();
                let u = if n.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
                cands.push(box_around(ext, n, u));
            }
        }
    }
    // Smallest volume; near-equal volumes (e.g. all ≈ 0 for a flat patch) by smallest surface.
    let scale = cands.iter().map(|b| b.half.iter().cloned().fold(0.0, f64::max)).fold(0.0, f64::max).max(1e-300);
    let eps = 1e-9 * scale.powi(3);
    let mut best = cands[0];
    for c in &cands[1..] {
        let dv = c.volume() - best.volume();
        if dv < -eps || (dv.abs() <= eps && c.surface() < best.surface() * (1.0 - 1e-12)) {
            best = *c;
        }
    }
    Some(canonical(ext, best))
}

/// Axis order by decreasing extent, signs by largest component, right-handed.
fn canonical(pts: &[P3], b: Obb) -> Obb {
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| b.half[j].total_cmp(&b.half[i]).then(i.cmp(&j)));
    let signed = |c: Vector3<f64>| {
        let m = (0..3).max_by(|&i, &j| c[i].abs().total_cmp(&c[j].abs()).then(j.cmp(&i))).unwrap_or(0);
        if c[m] < 0.0 {
            -c
        } else {
            c
        }
    };
    let x = signed(b.column(order[0]));
    let y = signed(b.column(order[1]));
    fit_to_axes(pts, [x, y, x.cross(&y)])
}

/// Convex hull of points (parry3d's quickhull, in f32 about the points' mean so that
/// camera-frame coordinates keep sub-micrometre precision); `None` when it fails
/// (fewer than 4 points, collinear points). Coplanar points give a flat, two-sided hull.
pub fn convex_hull(pts: &[P3]) -> Option<TriMesh> {
    if pts.len() < 4 {
        return None;
    }
    let c = pts.iter().fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]]).map(|x| x / pts.len() as f64);
    let p: Vec<parry3d::math::Vector3> =
        pts.iter().map(|q| parry3d::math::Vector3::new((q[0] - c[0]) as f32, (q[1] - c[1]) as f32, (q[2] - c[2]) as f32)).collect();
    let (v, f) = parry3d::transformation::try_convex_hull(&p).ok()?;
    if f.len() < 2 || v.len() < 3 {
        return None;
    }
    let m = TriMesh { vertices: v.iter().map(|q| [q.x as f64 + c[0], q.y as f64 + c[1], q.z as f64 + c[2]]).collect(), faces: f };
    (m.surface_area() > 0.0).then_some(m)
}

/// One object's baseline result: box, mesh in the box frame, and the points it came from.
#[derive(Debug, Clone)]
pub struct Observed {
    pub obb: Obb,
    pub mesh: TriMesh,
    /// Which shape was produced (a degenerate hull falls back to the box).
    pub shape: Shape,
    pub n_raw: usize,
    pub n_clean: usize,
}

/// Baseline for one object's back-projected points; `Err(reason)` when there are too few.
pub fn observe_points(raw: &[P3], o: &ObservedOptions) -> std::result::Result<Observed, String> {
    let pts = clean_points(raw, o);
    if pts.len() < o.min_points.max(4) {
        return Err(format!("{} points left after outlier removal (of {}), need {}", pts.len(), raw.len(), o.min_points.max(4)));
    }
    let hull = convex_hull(&pts);
    let obb = fit_obb_with_hull(&pts, hull.as_ref()).ok_or("no points")?;
    let (mesh, shape) = match (o.shape, hull) {
        (Shape::Hull, Some(h)) => (TriMesh { vertices: h.vertices.iter().map(|p| obb.to_local(p)).collect(), faces: h.faces }, Shape::Hull),
        _ => (cuboid(obb.half), Shape::Box),
    };
    Ok(Observed { obb, mesh, shape, n_raw: raw.len(), n_clean: pts.len() })
}

/// A GT instance the baseline made no prediction for, and why.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ObservedSkip {
    pub scene: String,
    pub frame: u32,
    pub gt_index: usize,
    pub obj_id: u32,
    pub reason: String,
}

#[derive(Debug, Clone)]
pub struct ObservedPrediction {
    pub prediction: Prediction,
    pub observed: Observed,
}

/// The baseline over a dataset, in dataset order.
#[derive(Debug, Clone, Default)]
pub struct ObservedRun {
    pub predictions: Vec<ObservedPrediction>,
    pub skipped: Vec<ObservedSkip>,
}

/// File name of a GT instance's predicted mesh (scene name made file-safe).
pub(crate) fn mesh_name(scene: &str, frame: u32, gi: usize, obj_id: u32) -> String {
    let s: String = scene.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect();
    format!("{s}_{frame:06}_gt{gi:02}_obj{obj_id:06}.ply")
}

/// Visible mask of GT instance `gi` of frame `f` as `(width, height, mask, file)`;
/// `label` caches the frame's label map (YCB-Video) across instances.
pub(crate) fn visible_mask(
    ds: &Dataset,
    f: &Frame,
    gi: usize,
    label: &mut Option<InstanceMap>,
) -> Result<(usize, usize, Vec<bool>, PathBuf)> {
    Ok(match ds.visible_mask_source(f, gi) {
        MaskSource::Binary(p) => {
            let m = load_binary_mask(&p)?;
            (m.width, m.height, m.to_bools(), p)
        }
        MaskSource::Label(p, id) => {
            if label.is_none() {
                *label = Some(InstanceMap::open(&p)?);
            }
            let l = label.as_ref().ok_or_else(|| Error::msg("label map"))?;
            (l.width, l.height, l.ids.iter().map(|&v| v == id).collect(), p)
        }
    })
}

/// Writes `dir/predictions.json` and each prediction's mesh (binary PLY, metres, in the
/// prediction's frame, no colours) at its relative `mesh` path; returns the predictions file's path.
pub(crate) fn write_predictions<'a>(
    dir: &Path,
    items: impl Iterator<Item = (&'a Prediction, std::borrow::Cow<'a, recon_core::mesh::Mesh>)>,
) -> Result<PathBuf> {
    use recon_core::export::ply::{save_mesh_ply, PlyOptions};
    use recon_core::export::Axes;
    let meshes = dir.join("meshes");
    std::fs::create_dir_all(&meshes).map_err(|e| Error::io(&meshes, e))?;
    let opts = PlyOptions { axes: Axes::ZUp, normals: false, vertex_colors: false };
    let mut preds = Vec::new();
    for (p, mesh) in items {
        let rel = p.mesh.as_ref().ok_or_else(|| Error::msg("prediction without mesh"))?;
        save_mesh_ply(&mesh, &dir.join(rel), &opts)?;
        preds.push(p.clone());
    }
    let path = dir.join("predictions.json");
    let text = serde_json::to_string_pretty(&PredictionsFile { predictions: preds })
        .map_err(|e| Error::msg(format!("serialising predictions: {e}")))?;
    std::fs::write(&path, text).map_err(|e| Error::io(&path, e))?;
    Ok(path)
}

/// Depth of a frame in metres (0 = no reading).
fn frame_depth(ds: &Dataset, f: &Frame) -> Result<(Vec<f32>, usize, usize)> {
    let path = ds.depth_path(f);
    let (raw, w, h) = load_depth_u16(&path)?;
    let m_per_unit = f.depth_scale_m;
    Ok((raw.iter().map(|&v| (v as f64 * m_per_unit) as f32).collect(), w, h))
}

/// Runs the baseline on every GT instance of one frame, its depth corrected by
/// `correction` first.
pub fn observe_frame(
    ds: &Dataset,
    f: &Frame,
    o: &ObservedOptions,
    correction: Option<&DatasetCorrection>,
) -> Result<(Vec<ObservedPrediction>, Vec<ObservedSkip>)> {
    let (mut depth, w, h) = frame_depth(ds, f)?;
    let k = Intrinsics::new(f.k[0][0], f.k[1][1], f.k[0][2], f.k[1][2])
        .map_err(|e| Error::input(format!("{} scene {} frame {}", ds.root.display(), f.scene, f.frame), e.to_string()))?;
    if let Some(c) = correction {
        depth = c.apply(f, &depth, w, h, &k);
    }
    let mut label: Option<InstanceMap> = None;
    let (mut preds, mut skips) = (Vec::new(), Vec::new());
    for (gi, g) in f.gt.iter().enumerate() {
        let skip = |reason: String| ObservedSkip { scene: f.scene.clone(), frame: f.frame, gt_index: gi, obj_id: g.obj_id, reason };
        let (mw, mh, mask, file) = visible_mask(ds, f, gi, &mut label)?;
        if (mw, mh) != (w, h) {
            return Err(Error::input(
                file.display().to_string(),
                format!("mask is {mw}×{mh} but the depth image {} is {w}×{h}", ds.depth_path(f).display()),
            ));
        }
        let mut raw = Vec::new();
        if let Some(e) = o.erosion {
            raw = masked_points(&depth, w, h, &k, &erode(&mask, w, h, e))?;
        }
        if raw.len() < o.min_points {
            raw = masked_points(&depth, w, h, &k, &mask)?;
        }
        if raw.len() < o.min_points {
            let n_mask = mask.iter().filter(|&&m| m).count();
            skips.push(skip(format!("{} visible pixels, {} with depth (need {})", n_mask, raw.len(), o.min_points)));
            continue;
        }
        match observe_points(&raw, o) {
            Err(r) => skips.push(skip(r)),
            Ok(obs) => {
                let prediction = Prediction {
                    scene: f.scene.clone(),
                    frame: f.frame,
                    obj_id: g.obj_id,
                    gt_index: Some(gi),
                    r: obs.obb.axes,
                    t: obs.obb.center,
                    scale: 1.0,
                    mesh: Some(PathBuf::from("meshes").join(mesh_name(&f.scene, f.frame, gi, g.obj_id))),
                    model_frame: false,
                };
                preds.push(ObservedPrediction { prediction, observed: obs });
            }
        }
    }
    Ok((preds, skips))
}

/// Runs the baseline on every frame of `ds` (in parallel over frames; the result does not
/// depend on the thread count).
pub fn observe_dataset(ds: &Dataset, o: &ObservedOptions) -> Result<ObservedRun> {
    observe_dataset_corrected(ds, o, None)
}

/// [`observe_dataset`] on depth corrected by `correction` first.
pub fn observe_dataset_corrected(ds: &Dataset, o: &ObservedOptions, correction: Option<&DatasetCorrection>) -> Result<ObservedRun> {
    let per: Vec<Result<(Vec<ObservedPrediction>, Vec<ObservedSkip>)>> =
        ds.frames.par_iter().map(|f| observe_frame(ds, f, o, correction)).collect();
    let mut run = ObservedRun::default();
    for r in per {
        let (p, s) = r?;
        run.predictions.extend(p);
        run.skipped.extend(s);
    }
    Ok(run)
}

impl ObservedRun {
    /// The predictions file (the format of [`crate::report`]).
    pub fn predictions_file(&self) -> PredictionsFile {
        PredictionsFile { predictions: self.predictions.iter().map(|p| p.prediction.clone()).collect() }
    }

    /// Writes `dir/predictions.json` and `dir/meshes/*.ply` (binary PLY, metres, box
    /// frame), so the run can be re-scored with `recon eval --predictions`. Returns the
    /// predictions file's path.
    pub fn write(&self, dir: &Path) -> Result<PathBuf> {
        let mesh = |m: &TriMesh| recon_core::mesh::Mesh {
            vertices: m.vertices.iter().map(|v| v.map(|x| x as f32)).collect(),
            faces: m.faces.clone(),
            vertex_attrs: None,
        };
        write_predictions(dir, self.predictions.iter().map(|p| (&p.prediction, std::borrow::Cow::Owned(mesh(&p.observed.mesh)))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use recon_core::math::{axis_angle, Similarity};
    use recon_core::rng::SeededRng;

    fn rotated_box_points(h: P3, rot: [[f64; 3]; 3], t: P3, n: usize, seed: u64) -> Vec<P3> {
        cuboid(h).transformed(&Similarity::rigid(rot, t)).sample_surface(n, seed)
    }

    fn col(b: &Obb, j: usize) -> [f64; 3] {
        [b.axes[0][j], b.axes[1][j], b.axes[2][j]]
    }

    #[test]
    fn obb_recovers_rotated_boxes_including_a_cube() {
        let rot = axis_angle([0.3, -0.8, 0.5], 1.1);
        let t = [0.05, -0.1, 0.9];
        for h in [[0.08, 0.04, 0.02], [0.03, 0.03, 0.03]] {
            let pts = rotated_box_points(h, rot, t, 20_000, 1);
            let b = fit_obb(&pts).unwrap();
            let vol = 8.0 * h[0] * h[1] * h[2];
            assert!((b.volume() / vol - 1.0).abs() < 0.01, "{h:?}: volume {} vs {vol}", b.volume());
            for k in 0..3 {
                assert!((b.center[k] - t[k]).abs() < 1e-3, "centre {:?}", b.center);
            }
            // Every fitted axis is parallel to one of the true axes (cube: any of them).
            for j in 0..3 {
                let a = col(&b, j);
                let best = (0..3).map(|i| (a[0] * rot[0][i] + a[1] * rot[1][i] + a[2] * rot[2][i]).abs()).fold(0.0, f64::max);
                assert!(best > 0.999, "{h:?}: axis {j} {a:?} off the box axes ({best})");
            }
            // Canonical frame: extents descending, right-handed rotation.
            assert!(b.half[0] >= b.half[1] && b.half[1] >= b.half[2]);
            let r = b.axes;
            let det = r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
                + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]);
            assert!((det - 1.0).abs() < 1e-9, "{det}");
            // Local frame round trip.
            let l = b.to_local(&pts[0]);
            let back: Vec<f64> = (0..3).map(|i| (0..3).map(|j| r[i][j] * l[j]).sum::<f64>() + b.center[i]).collect();
            assert!((0..3).all(|i| (back[i] - pts[0][i]).abs() < 1e-12));
        }
        // Visible part only (the three faces seen from the origin) still spans the box.
        let h = [0.08, 0.04, 0.02];
        let pts = rotated_box_points(h, rot, t, 20_000, 2);
        let seen: Vec<P3> = pts
            .iter()
            .copied()
            .filter(|p| {
                let l = (0..3).map(|j| (0..3).map(|i| rot[i][j] * (p[i] - t[i])).sum::<f64>()).collect::<Vec<_>>();
                // Outward normal of the face the sample lies on, camera-facing test.
                let k = (0..3).max_by(|&a, &b| (l[a] / h[a]).abs().total_cmp(&(l[b] / h[b]).abs())).unwrap();
                let n: Vec<f64> = (0..3).map(|i| rot[i][k] * l[k].signum()).collect();
                n[0] * p[0] + n[1] * p[1] + n[2] * p[2] < 0.0
            })
            .collect();
        assert!(seen.len() > 5000 && seen.len() < 15_000, "{}", seen.len());
        let b = fit_obb(&seen).unwrap();
        assert!((b.volume() / (8.0 * h[0] * h[1] * h[2]) - 1.0).abs() < 0.02, "{:?}", b.half);
    }

    #[test]
    fn obb_of_flat_patch_is_its_min_area_rectangle() {
        // Exactly coplanar points (ideal depth of a fronto-parallel face): zero thickness,
        // in-plane rectangle found although the patch is rotated in its plane.
        let r = axis_angle([0.0, 0.0, 1.0], 0.4);
        let mut pts = Vec::new();
        for i in 0..50 {
            for j in 0..20 {
                let (x, y) = (-0.05 + 0.1 * i as f64 / 49.0, -0.02 + 0.04 * j as f64 / 19.0);
                pts.push([r[0][0] * x + r[0][1] * y, r[1][0] * x + r[1][1] * y, 0.7]);
            }
        }
        let b = fit_obb(&pts).unwrap();
        // Extents come from the hull's f32 vertices (about the mean): exact to ~1e-8 m.
        assert!((b.half[0] - 0.05).abs() < 1e-7 && (b.half[1] - 0.02).abs() < 1e-7 && b.half[2] < 1e-7, "{:?}", b.half);
        // Coplanar points: a flat hull (one- or two-sided) covering the rectangle.
        let o = observe_points(&pts, &ObservedOptions::default()).unwrap();
        assert_eq!(o.shape, Shape::Hull);
        assert!(o.mesh.vertices.iter().all(|v| v[2].abs() < 1e-6));
        let a = o.mesh.surface_area() / (0.1 * 0.04);
        assert!((a - 1.0).abs() < 1e-4 || (a - 2.0).abs() < 2e-4, "area ratio {a}");
        // Collinear points have no hull: the (degenerate) box stands in.
        let line: Vec<P3> = (0..40).map(|i| [0.01 * i as f64, 0.005 * i as f64, 0.7]).collect();
        let o = observe_points(&line, &ObservedOptions::default()).unwrap();
        assert_eq!((o.shape, o.mesh.faces.len()), (Shape::Box, 12));
        assert!((o.obb.half[0] - 0.5 * 0.39 * 1.25f64.sqrt()).abs() < 1e-9 && o.obb.half[1] < 1e-12, "{:?}", o.obb.half);
    }

    #[test]
    fn cleaning_drops_leaked_background_and_flying_pixels() {
        let mut rng = SeededRng::new(5);
        // Object: a 60×60 grid, 1 mm spacing, with 0.2 mm depth noise, at 0.8 m.
        let mut pts: Vec<P3> = Vec::new();
        for i in 0..60 {
            for j in 0..60 {
                pts.push([i as f64 * 0.001, j as f64 * 0.001, 0.8 + 0.0002 * rng.normal()]);
            }
        }
        let n_obj = pts.len();
        // Background leaking into the mask 8 cm behind (a sizeable patch), and flying pixels.
        for i in 0..20 {
            for j in 0..20 {
                pts.push([0.07 + i as f64 * 0.0011, j as f64 * 0.0011, 0.88]);
            }
        }
        for _ in 0..30 {
            pts.push([rng.uniform() * 0.06, rng.uniform() * 0.06, 0.8 + 0.02 + 0.05 * rng.uniform()]);
        }
        let kept = clean_points(&pts, &ObservedOptions::default());
        assert!(kept.iter().all(|p| p[2] < 0.81), "a background or flying point survived");
        assert!(kept.len() as f64 > 0.95 * n_obj as f64, "kept {} of {n_obj}", kept.len());
        // Deterministic and order-preserving.
        assert_eq!(kept, clean_points(&pts, &ObservedOptions::default()));
        assert!(kept.windows(2).all(|w| pts.iter().position(|p| *p == w[0]) < pts.iter().position(|p| *p == w[1])));
    }

    #[test]
    fn hull_of_box_points_is_the_box() {
        let h = [0.05, 0.03, 0.01];
        let pts = rotated_box_points(h, axis_angle([1.0, 2.0, 0.5], 0.8), [0.0, 0.0, 0.6], 5000, 3);
        let o = observe_points(&pts, &ObservedOptions { erosion: None, ..Default::default() }).unwrap();
        assert_eq!(o.shape, Shape::Hull);
        // Hull vertices lie inside the OBB; its area approaches the box's from below.
        assert!(o.mesh.vertices.iter().all(|v| (0..3).all(|k| v[k].abs() <= o.obb.half[k] + 1e-6)));
        let area = 8.0 * (h[0] * h[1] + h[1] * h[2] + h[0] * h[2]);
        let a = o.mesh.surface_area();
        assert!(a < area * (1.0 + 1e-6) && a > 0.97 * area, "{a} vs {area}");
        let too_few = observe_points(&pts[..10], &ObservedOptions::default());
        assert!(too_few.unwrap_err().contains("need 20"));
    }
}
