//! Collision geometry for one object (in its body frame): approximate convex
//! decomposition (parry3d's VHACD), a single convex hull, or a primitive
//! (box, cylinder, sphere) when one matches the mesh well; with a report of
//! the part count and the volume and surface error against the mesh.
//!
//! Primitive acceptance (closed meshes only; an open shell keeps its
//! cavity, which a primitive would fill): each candidate encloses the mesh's
//! convex hull, and is accepted when its volume is at most
//! `(1 + volume_tolerance)` × the mesh volume AND no mesh surface sample lies
//! further than `surface_tolerance` × the mesh's bounding-box diagonal from
//! the primitive's surface. Of the accepted ones the tightest (smallest
//! volume) wins; with none accepted the decomposition is used instead.

use crate::physics::{bbox, bbox_diagonal};
use parry3d::math::Vector;
use parry3d::query::PointQuery;
use parry3d::shape::{ConvexPolyhedron, TriMesh as ParryTriMesh, TriMeshFlags};
use recon_core::math::{cross, dot, norm, sub};
use recon_core::mesh::trimesh::TriMesh;
use recon_core::mesh::Mesh;
use recon_core::rng::SeededRng;
use recon_core::{Error, Result};
use serde::{Deserialize, Serialize};

/// Requested collision representation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum CollisionMethod {
    /// Approximate convex decomposition (VHACD).
    Convex,
    /// One convex hull of the whole mesh.
    Hull,
    /// A box, cylinder or sphere when one fits (else the decomposition).
    Primitive,
}

impl CollisionMethod {
    /// The method named `s` (`convex` or `vhacd`, `hull`, `primitive`).
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "convex" | "vhacd" => Some(Self::Convex),
            "hull" => Some(Self::Hull),
            "primitive" => Some(Self::Primitive),
            _ => None,
        }
    }
}

/// VHACD parameters (parry3d's `VHACDParameters`; see its docs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct VhacdOptions {
    /// Voxels along the longest axis.
    pub resolution: u32,
    /// Maximum concavity of a part (relative to the mesh size).
    pub concavity: f32,
    /// Most convex parts.
    pub max_convex_hulls: u32,
    /// Plane downsampling of the split search (VHACD).
    pub plane_downsampling: u32,
    /// Downsampling of the hull computation during the search (VHACD).
    pub convex_hull_downsampling: u32,
    /// Bias toward clipping along symmetry planes.
    pub alpha: f32,
    /// Bias toward clipping along revolution axes.
    pub beta: f32,
}

impl Default for VhacdOptions {
    fn default() -> Self {
        Self {
            resolution: 64,
            concavity: 0.01,
            max_convex_hulls: 16,
            plane_downsampling: 4,
            convex_hull_downsampling: 4,
            alpha: 0.05,
            beta: 0.05,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PrimitiveTolerances {
    /// Accepted excess volume fraction over the mesh volume.
    pub volume_tolerance: f64,
    /// Accepted surface deviation as a fraction of the bounding-box diagonal.
    pub surface_tolerance: f64,
}

impl Default for PrimitiveTolerances {
    fn default() -> Self {
        Self { volume_tolerance: 0.05, surface_tolerance: 0.02 }
    }
}

#[derive(Debug, Clone, Default)]
pub struct CollisionOptions {
    pub vhacd: VhacdOptions,
    pub primitive: PrimitiveTolerances,
    /// Surface samples per direction for the error report.
    pub error_samples: usize,
    /// Voxel grid cells along the longest axis for the volume report.
    pub volume_grid: usize,
    pub seed: u64,
}

impl CollisionOptions {
    pub fn new() -> Self {
        Self { error_samples: 2000, volume_grid: 40, ..Default::default() }
    }
}

/// A primitive in the body frame; `rotation` maps primitive axes to body
/// axes (the cylinder's axis is its local z).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Primitive {
    Box { center: [f32; 3], rotation: [[f32; 3]; 3], half_extents: [f32; 3] },
    Cylinder { center: [f32; 3], rotation: [[f32; 3]; 3], radius: f32, half_height: f32 },
    Sphere { center: [f32; 3], radius: f32 },
}

impl Primitive {
    pub fn name(&self) -> &'static str {
        match self {
            Primitive::Box { .. } => "box",
            Primitive::Cylinder { .. } => "cylinder",
            Primitive::Sphere { .. } => "sphere",
        }
    }

    pub fn volume(&self) -> f64 {
        match *self {
            Primitive::Box { half_extents: h, .. } => 8.0 * h.iter().map(|&x| x as f64).product::<f64>(),
            Primitive::Cylinder { radius, half_height, .. } => std::f64::consts::PI * (radius as f64).powi(2) * 2.0 * half_height as f64,
            Primitive::Sphere { radius, .. } => 4.0 / 3.0 * std::f64::consts::PI * (radius as f64).powi(3),
        }
    }

    /// Signed distance to the surface (negative inside).
    pub fn sdf(&self, p: [f64; 3]) -> f64 {
        match *self {
            Primitive::Box { center, rotation, half_extents } => {
                let q = to_local(p, center, rotation);
                let d = [0, 1, 2].map(|k| q[k].abs() - half_extents[k] as f64);
                let outside = d.iter().map(|x| x.max(0.0).powi(2)).sum::<f64>().sqrt();
                outside + d[0].max(d[1]).max(d[2]).min(0.0)
            }
            Primitive::Cylinder { center, rotation, radius, half_height } => {
                let q = to_local(p, center, rotation);
                let dr = (q[0] * q[0] + q[1] * q[1]).sqrt() - radius as f64;
                let dz = q[2].abs() - half_height as f64;
                (dr.max(0.0).powi(2) + dz.max(0.0).powi(2)).sqrt() + dr.max(dz).min(0.0)
            }
            Primitive::Sphere { center, radius } => {
                let d = [0, 1, 2].map(|k| p[k] - center[k] as f64);
                (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() - radius as f64
            }
        }
    }

    /// A triangulation of the surface (for sampling and the GLB preview).
    pub fn to_mesh(self) -> Mesh {
        let place = |m: Mesh, c: [f32; 3], r: [[f32; 3]; 3]| Mesh {
            vertices: m.vertices.iter().map(|v| [0, 1, 2].map(|i| c[i] + r[i][0] * v[0] + r[i][1] * v[1] + r[i][2] * v[2])).collect(),
            faces: m.faces,
            vertex_attrs: None,
        };
        match self {
            Primitive::Box { center, rotation, half_extents: h } => {
                let (v, f) = parry3d::shape::Cuboid::new(Vector::new(h[0], h[1], h[2])).to_trimesh();
                place(from_parry(&v, &f), center, rotation)
            }
            Primitive::Cylinder { center, rotation, radius, half_height } => {
                // parry's cylinder axis is y; ours is z.
                let (v, f) = parry3d::shape::Cylinder::new(half_height, radius).to_trimesh(64);
                let m = from_parry(&v, &f);
                let yz = Mesh { vertices: m.vertices.iter().map(|p| [p[0], -p[2], p[1]]).collect(), faces: m.faces, vertex_attrs: None };
                place(yz, center, rotation)
            }
            Primitive::Sphere { center, radius } => {
                let (v, f) = parry3d::shape::Ball::new(radius).to_trimesh(24, 48);
                place(from_parry(&v, &f), center, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
            }
        }
    }
}

fn to_local(p: [f64; 3], c: [f32; 3], r: [[f32; 3]; 3]) -> [f64; 3] {
    let d = [0, 1, 2].map(|k| p[k] - c[k] as f64);
    [0, 1, 2].map(|j| (0..3).map(|i| r[i][j] as f64 * d[i]).sum())
}

fn from_parry(v: &[Vector], f: &[[u32; 3]]) -> Mesh {
    Mesh { vertices: v.iter().map(|p| [p.x, p.y, p.z]).collect(), faces: f.to_vec(), vertex_attrs: None }
}

/// One collision part in the body frame.
#[derive(Debug, Clone)]
pub enum Part {
    /// A convex hull: outward-oriented triangles.
    Hull(Mesh),
    Primitive(Primitive),
}

impl Part {
    pub fn surface_mesh(&self) -> Mesh {
        match self {
            Part::Hull(m) => m.clone(),
            Part::Primitive(p) => p.to_mesh(),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct PrimitiveCandidate {
    pub kind: &'static str,
    /// Primitive volume / mesh volume.
    pub volume_ratio: f64,
    /// Largest distance from a mesh surface sample to the primitive surface.
    pub max_surface_deviation_m: f64,
    pub accepted: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct PrimitiveFitReport {
    pub criterion: String,
    pub candidates: Vec<PrimitiveCandidate>,
    pub chosen: Option<&'static str>,
}

#[derive(Debug, Clone, Serialize)]
pub struct VolumeReport {
    /// Enclosed mesh volume (closed meshes).
    pub mesh_m3: Option<f64>,
    /// Sum of the parts' exact volumes (overlaps counted twice).
    pub parts_sum_m3: f64,
    /// Union of the parts, estimated on the voxel grid.
    pub collision_union_m3: f64,
    /// (union − mesh) / mesh on the same grid (closed meshes).
    pub relative_error: Option<f64>,
    /// Volume in exactly one of mesh and collision / mesh volume (closed meshes).
    pub symmetric_difference_ratio: Option<f64>,
    pub grid_cells: [usize; 3],
}

#[derive(Debug, Clone, Serialize)]
pub struct SurfaceReport {
    pub samples: usize,
    /// Mesh surface samples outside the collision geometry: how far.
    pub mesh_to_collision_mean_m: f64,
    pub mesh_to_collision_max_m: f64,
    /// Collision surface samples (outer surface only): distance to the mesh surface.
    pub collision_to_mesh_mean_m: f64,
    pub collision_to_mesh_max_m: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct CollisionReport {
    pub requested: CollisionMethod,
    /// "vhacd", "convex_hull", "box", "cylinder" or "sphere".
    pub used: String,
    pub parts: usize,
    pub hull_count: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vhacd: Option<VhacdOptions>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub primitive_fit: Option<PrimitiveFitReport>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    pub volume: VolumeReport,
    pub surface: SurfaceReport,
}

#[derive(Debug, Clone)]
pub struct Collision {
    pub parts: Vec<Part>,
    pub report: CollisionReport,
}

/// Build the collision geometry of `mesh` (body frame, checked by
/// `physics::check_mesh`); `closed_volume` is its enclosed volume when closed.
pub fn build_collision(
    mesh: &Mesh,
    closed_volume: Option<f64>,
    method: CollisionMethod,
    opts: &CollisionOptions,
    file: &str,
) -> Result<Collision> {
    let samples = surface_samples(mesh, opts.error_samples.max(100), opts.seed);
    let mut notes = Vec::new();
    let mut fit_report = None;
    let mut vhacd_used = None;
    let (parts, used) = match method {
        CollisionMethod::Hull => {
            if closed_volume.is_none() {
                notes.push("open mesh: the single hull closes its cavity".into());
            }
            (vec![Part::Hull(convex_hull(&mesh.vertices, file)?)], "convex_hull".to_string())
        }
        CollisionMethod::Convex => {
            vhacd_used = Some(opts.vhacd);
            (vhacd(mesh, &opts.vhacd, file)?, "vhacd".to_string())
        }
        CollisionMethod::Primitive => {
            let chosen = match closed_volume {
                Some(v) => {
                    let hull = convex_hull(&mesh.vertices, file)?;
                    let (rep, best) = fit_primitive(mesh, &hull, v, &samples, &opts.primitive, opts.seed);
                    fit_report = Some(rep);
                    best
                }
                None => {
                    notes.push("open mesh: primitives would fill its cavity; no primitive tried".into());
                    None
                }
            };
            match chosen {
                Some(p) => (vec![Part::Primitive(p)], p.name().to_string()),
                None => {
                    notes.push("no primitive matched; used the convex decomposition".into());
                    vhacd_used = Some(opts.vhacd);
                    (vhacd(mesh, &opts.vhacd, file)?, "vhacd".to_string())
                }
            }
        }
    };
    let volume = volume_report(mesh, closed_volume, &parts, opts.volume_grid.max(8));
    let surface = surface_report(mesh, &parts, &samples, opts.error_samples.max(100), opts.seed);
    let hull_count = parts.iter().filter(|p| matches!(p, Part::Hull(_))).count();
    Ok(Collision {
        report: CollisionReport {
            requested: method,
            used,
            parts: parts.len(),
            hull_count,
            vhacd: vhacd_used,
            primitive_fit: fit_report,
            notes,
            volume,
            surface,
        },
        parts,
    })
}

fn to_parry(v: &[[f32; 3]]) -> Vec<Vector> {
    v.iter().map(|p| Vector::new(p[0], p[1], p[2])).collect()
}

/// Convex hull with outward-oriented triangles.
pub fn convex_hull(points: &[[f32; 3]], file: &str) -> Result<Mesh> {
    let (v, f) = parry3d::transformation::try_convex_hull(&to_parry(points))
        .map_err(|e| Error::input(file, format!("convex hull failed: {e:?}")))?;
    let m = orient_outward(from_parry(&v, &f));
    if m.faces.len() < 4 {
        return Err(Error::input(file, "convex hull is flat (the mesh has no volume)"));
    }
    Ok(m)
}

fn orient_outward(mut m: Mesh) -> Mesh {
    let n = m.vertices.len().max(1) as f32;
    let c = [0, 1, 2].map(|k| m.vertices.iter().map(|v| v[k]).sum::<f32>() / n);
    for f in &mut m.faces {
        let [a, b, d] = f.map(|i| m.vertices[i as usize]);
        let nrm = cross(sub(b, a), sub(d, a));
        let fc = [0, 1, 2].map(|k| (a[k] + b[k] + d[k]) / 3.0 - c[k]);
        if nrm[0] * fc[0] + nrm[1] * fc[1] + nrm[2] * fc[2] < 0.0 {
            f.swap(1, 2);
        }
    }
    m
}

fn vhacd(mesh: &Mesh, o: &VhacdOptions, file: &str) -> Result<Vec<Part>> {
    use parry3d::transformation::vhacd::{VHACDParameters, VHACD};
    use parry3d::transformation::voxelization::FillMode;
    if o.resolution < 8 || o.resolution > 512 || o.max_convex_hulls == 0 || !(o.concavity > 0.0) {
        return Err(Error::input(file, format!("bad VHACD parameters {o:?}: resolution in 8..=512, max hulls ≥ 1, concavity > 0")));
    }
    let params = VHACDParameters {
        concavity: o.concavity,
        alpha: o.alpha,
        beta: o.beta,
        resolution: o.resolution,
        plane_downsampling: o.plane_downsampling.max(1),
        convex_hull_downsampling: o.convex_hull_downsampling.max(1),
        fill_mode: FillMode::FloodFill { detect_cavities: false },
        convex_hull_approximation: true,
        max_convex_hulls: o.max_convex_hulls,
    };
    let pts = to_parry(&mesh.vertices);
    // parry asserts on some degenerate inputs; never let that take the process down.
    let (exact, voxel) = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let d = VHACD::decompose(&params, &pts, &mesh.faces, true);
        (d.compute_exact_convex_hulls(&pts, &mesh.faces), d.compute_convex_hulls(params.convex_hull_downsampling))
    }))
    .map_err(|_| Error::input(file, "VHACD failed on this mesh (internal panic); try --collision hull"))?;
    let hull_mesh = |v: &[Vector], f: &[[u32; 3]]| -> Option<Mesh> {
        if v.len() < 4 || f.len() < 4 {
            return None;
        }
        let m = orient_outward(from_parry(v, f));
        (crate::physics::signed_volume(&m) > 0.0).then_some(m)
    };
    // Exact hulls (clipped mesh triangles) follow the surface; where a part
    // is a piece of a zero-thickness wall its exact hull is flat, so the
    // voxel hull of the same part (one voxel thick) stands in.
    let parts: Vec<Part> = exact
        .iter()
        .zip(&voxel)
        .filter_map(|((ev, ef), (vv, vf))| {
            let e = hull_mesh(ev, ef);
            let v = hull_mesh(vv, vf);
            match (e, v) {
                (Some(e), Some(v)) if crate::physics::signed_volume(&e) >= 0.1 * crate::physics::signed_volume(&v) => Some(e),
                (_, Some(v)) => Some(v),
                (e, None) => e,
            }
        })
        .map(Part::Hull)
        .collect();
    if parts.is_empty() {
        return Err(Error::input(file, "VHACD produced no convex part; try a higher --vhacd-resolution or --collision hull"));
    }
    Ok(parts)
}

fn surface_samples(mesh: &Mesh, n: usize, seed: u64) -> Vec<[f64; 3]> {
    TriMesh::from(mesh).sample_surface(n, seed)
}

/// Half-space form of a hull (outward normals, `n·x ≤ d` inside).
fn hull_planes(m: &Mesh) -> Vec<([f64; 3], f64)> {
    m.faces
        .iter()
        .filter_map(|f| {
            let [a, b, c] = f.map(|i| m.vertices[i as usize].map(|x| x as f64));
            let n = cross(sub(b, a), sub(c, a));
            let l = norm(n);
            (l > 0.0).then(|| {
                let n = n.map(|x| x / l);
                (n, dot(n, a))
            })
        })
        .collect()
}

/// Point queries against the union of the parts.
struct PartQuery {
    planes: Vec<Option<Vec<([f64; 3], f64)>>>,
    polys: Vec<Option<ConvexPolyhedron>>,
    prims: Vec<Option<Primitive>>,
}

impl PartQuery {
    fn new(parts: &[Part]) -> Self {
        let mut q = PartQuery { planes: vec![], polys: vec![], prims: vec![] };
        for p in parts {
            match p {
                Part::Hull(m) => {
                    q.planes.push(Some(hull_planes(m)));
                    q.polys.push(ConvexPolyhedron::from_convex_hull(&to_parry(&m.vertices)));
                    q.prims.push(None);
                }
                Part::Primitive(pr) => {
                    q.planes.push(None);
                    q.polys.push(None);
                    q.prims.push(Some(*pr));
                }
            }
        }
        q
    }

    /// Inside part `i` by at least `-tol` (tol > 0 widens the part).
    fn inside(&self, i: usize, p: [f64; 3], tol: f64) -> bool {
        if let Some(pl) = &self.planes[i] {
            return pl.iter().all(|(n, d)| dot(*n, p) <= d + tol);
        }
        self.prims[i].is_some_and(|pr| pr.sdf(p) <= tol)
    }

    fn inside_any(&self, p: [f64; 3]) -> bool {
        (0..self.planes.len()).any(|i| self.inside(i, p, 0.0))
    }

    /// Distance to the union (0 inside).
    fn distance(&self, p: [f64; 3]) -> f64 {
        let mut best = f64::INFINITY;
        for i in 0..self.planes.len() {
            let d = match (&self.polys[i], &self.prims[i]) {
                (Some(poly), _) => poly.distance_to_local_point(Vector::new(p[0] as f32, p[1] as f32, p[2] as f32), true) as f64,
                (None, Some(pr)) => pr.sdf(p).max(0.0),
                (None, None) => f64::INFINITY,
            };
            best = best.min(d);
        }
        best
    }
}

fn volume_report(mesh: &Mesh, closed_volume: Option<f64>, parts: &[Part], cells: usize) -> VolumeReport {
    let parts_sum: f64 = parts
        .iter()
        .map(|p| match p {
            Part::Hull(m) => crate::physics::signed_volume(m),
            Part::Primitive(pr) => pr.volume(),
        })
        .sum();
    let q = PartQuery::new(parts);
    let mut lo = bbox(&mesh.vertices).0.map(|x| x as f64);
    let mut hi = bbox(&mesh.vertices).1.map(|x| x as f64);
    for p in parts {
        let (a, b) = bbox(&p.surface_mesh().vertices);
        for k in 0..3 {
            lo[k] = lo[k].min(a[k] as f64);
            hi[k] = hi[k].max(b[k] as f64);
        }
    }
    let ext = [0, 1, 2].map(|k| (hi[k] - lo[k]).max(1e-9));
    let h = ext.iter().cloned().fold(0.0, f64::max) / cells as f64;
    let n = ext.map(|e| ((e / h).ceil() as usize).max(1));
    let tri =
        closed_volume.and_then(|_| ParryTriMesh::with_flags(to_parry(&mesh.vertices), mesh.faces.clone(), TriMeshFlags::ORIENTED).ok());
    let (mut in_mesh, mut in_coll, mut in_one) = (0usize, 0usize, 0usize);
    for i in 0..n[0] {
        for j in 0..n[1] {
            for k in 0..n[2] {
                let p = [lo[0] + (i as f64 + 0.5) * h, lo[1] + (j as f64 + 0.5) * h, lo[2] + (k as f64 + 0.5) * h];
                let c = q.inside_any(p);
                in_coll += c as usize;
                if let Some(t) = &tri {
                    let m = t.contains_local_point(Vector::new(p[0] as f32, p[1] as f32, p[2] as f32));
                    in_mesh += m as usize;
                    in_one += (m != c) as usize;
                }
            }
        }
    }
    let cell = h * h * h;
    let mesh_grid = in_mesh as f64 * cell;
    let ok = tri.is_some() && in_mesh > 0;
    VolumeReport {
        mesh_m3: closed_volume,
        parts_sum_m3: parts_sum,
        collision_union_m3: in_coll as f64 * cell,
        relative_error: ok.then(|| (in_coll as f64 * cell - mesh_grid) / mesh_grid),
        symmetric_difference_ratio: ok.then(|| in_one as f64 / in_mesh as f64),
        grid_cells: n,
    }
}

fn surface_report(mesh: &Mesh, parts: &[Part], mesh_samples: &[[f64; 3]], n: usize, seed: u64) -> SurfaceReport {
    let q = PartQuery::new(parts);
    let d1: Vec<f64> = mesh_samples.iter().map(|p| q.distance(*p)).collect();
    // Collision surface samples, per part proportional to its area; samples
    // inside (or on) another part lie on internal faces such as shared cut
    // planes, not on the outer surface.
    let meshes: Vec<Mesh> = parts.iter().map(|p| p.surface_mesh()).collect();
    let areas: Vec<f64> = meshes.iter().map(|m| m.area()).collect();
    let total: f64 = areas.iter().sum::<f64>().max(1e-30);
    let tol = 1e-4 * bbox_diagonal(&mesh.vertices);
    let mut pts = Vec::new();
    for (i, m) in meshes.iter().enumerate() {
        let k = ((n as f64 * areas[i] / total).ceil() as usize).max(1);
        for p in surface_samples(m, k, seed.wrapping_add(i as u64 + 1)) {
            if !(0..parts.len()).any(|j| j != i && q.inside(j, p, tol)) {
                pts.push(p);
            }
        }
    }
    let tm = ParryTriMesh::new(to_parry(&mesh.vertices), mesh.faces.clone()).ok();
    let d2: Vec<f64> = match &tm {
        Some(t) => pts
            .iter()
            .map(|p| {
                let v = Vector::new(p[0] as f32, p[1] as f32, p[2] as f32);
                (t.project_local_point(v, false).point - v).length() as f64
            })
            .collect(),
        None => vec![],
    };
    let mean = |v: &[f64]| if v.is_empty() { 0.0 } else { v.iter().sum::<f64>() / v.len() as f64 };
    let max = |v: &[f64]| v.iter().cloned().fold(0.0, f64::max);
    SurfaceReport {
        samples: mesh_samples.len(),
        mesh_to_collision_mean_m: mean(&d1),
        mesh_to_collision_max_m: max(&d1),
        collision_to_mesh_mean_m: mean(&d2),
        collision_to_mesh_max_m: max(&d2),
    }
}

type Mat3 = [[f64; 3]; 3];

/// Candidate orthonormal frames (columns = axes): the principal axes of the
/// surface samples, and pairs of normals of the largest hull faces.
fn candidate_frames(hull: &Mesh, samples: &[[f64; 3]]) -> Vec<Mat3> {
    let mut frames = Vec::new();
    let n = samples.len().max(1) as f64;
    let c = [0, 1, 2].map(|k| samples.iter().map(|p| p[k]).sum::<f64>() / n);
    let mut cov = nalgebra::Matrix3::<f64>::zeros();
    for p in samples {
        let d = nalgebra::Vector3::new(p[0] - c[0], p[1] - c[1], p[2] - c[2]);
        cov += d * d.transpose();
    }
    let e = cov.symmetric_eigen();
    frames.push(std::array::from_fn(|i| std::array::from_fn(|j| e.eigenvectors[(i, j)])));
    let mut faces: Vec<(f64, [f64; 3])> = hull
        .faces
        .iter()
        .filter_map(|f| {
            let [a, b, d] = f.map(|i| hull.vertices[i as usize].map(|x| x as f64));
            let nrm = cross(sub(b, a), sub(d, a));
            let l = norm(nrm);
            (l > 0.0).then(|| (l, nrm.map(|x| x / l)))
        })
        .collect();
    faces.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut normals: Vec<[f64; 3]> = Vec::new();
    for (_, nrm) in faces {
        if normals.iter().all(|m| dot(*m, nrm).abs() < 0.999) {
            normals.push(nrm);
        }
        if normals.len() == 12 {
            break;
        }
    }
    for a in &normals {
        for b in &normals {
            let d = dot(*a, *b);
            if d.abs() > 0.3 {
                continue;
            }
            let b2 = sub(*b, a.map(|x| x * d));
            let l = norm(b2);
            let b2 = b2.map(|x| x / l);
            let c3 = cross(*a, b2);
            frames.push(std::array::from_fn(|i| [a[i], b2[i], c3[i]]));
        }
    }
    frames
}

fn project(p: [f32; 3], r: &Mat3) -> [f64; 3] {
    [0, 1, 2].map(|j| (0..3).map(|i| r[i][j] * p[i] as f64).sum())
}

fn frame_f32(r: &Mat3) -> [[f32; 3]; 3] {
    r.map(|row| row.map(|x| x as f32))
}

fn fit_primitive(
    mesh: &Mesh,
    hull: &Mesh,
    mesh_volume: f64,
    samples: &[[f64; 3]],
    tol: &PrimitiveTolerances,
    seed: u64,
) -> (PrimitiveFitReport, Option<Primitive>) {
    let frames = candidate_frames(hull, samples);
    let extents = |r: &Mat3| {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for v in &hull.vertices {
            let q = project(*v, r);
            for k in 0..3 {
                lo[k] = lo[k].min(q[k]);
                hi[k] = hi[k].max(q[k]);
            }
        }
        (lo, hi)
    };
    // Box: tightest axis-aligned box over the candidate frames.
    let mut best_box: Option<(f64, Primitive, Mat3)> = None;
    for r in &frames {
        let (lo, hi) = extents(r);
        let vol: f64 = (0..3).map(|k| hi[k] - lo[k]).product();
        if best_box.as_ref().is_none_or(|(v, _, _)| vol < *v) {
            let mid = [0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k]));
            let center = [0, 1, 2].map(|i| (0..3).map(|j| r[i][j] * mid[j]).sum::<f64>() as f32);
            let half_extents = [0, 1, 2].map(|k| (0.5 * (hi[k] - lo[k])) as f32);
            best_box = Some((vol, Primitive::Box { center, rotation: frame_f32(r), half_extents }, *r));
        }
    }
    let Some((_, boxp, box_frame)) = best_box else {
        return (PrimitiveFitReport { criterion: criterion(tol), candidates: vec![], chosen: None }, None);
    };
    // Cylinder: axis along each axis of the box frame and of the principal frame.
    let mut best_cyl: Option<(f64, Primitive)> = None;
    let mut rng = SeededRng::new(seed ^ 0x5eed);
    for r in [box_frame, frames[0]] {
        for ax in 0..3 {
            let (u, v, w) = ((ax + 1) % 3, (ax + 2) % 3, ax);
            let mut pts2: Vec<[f64; 2]> = hull.vertices.iter().map(|p| project(*p, &r)).map(|q| [q[u], q[v]]).collect();
            let (c2, rad) = min_enclosing_circle(&mut pts2, &mut rng);
            let (lo, hi) = extents(&r);
            let hh = 0.5 * (hi[w] - lo[w]);
            let vol = std::f64::consts::PI * rad * rad * 2.0 * hh;
            if best_cyl.as_ref().is_none_or(|(bv, _)| vol < *bv) {
                let mut local = [0.0; 3];
                local[u] = c2[0];
                local[v] = c2[1];
                local[w] = 0.5 * (lo[w] + hi[w]);
                let center = [0, 1, 2].map(|i| (0..3).map(|j| r[i][j] * local[j]).sum::<f64>() as f32);
                // Columns (u, v, w) so the local z is the axis, right-handed.
                let axes: Mat3 = std::array::from_fn(|i| [r[i][u], r[i][v], r[i][w]]);
                best_cyl =
                    Some((vol, Primitive::Cylinder { center, rotation: frame_f32(&axes), radius: rad as f32, half_height: hh as f32 }));
            }
        }
    }
    // Sphere: centred on the box, through the furthest hull vertex.
    let sphere = {
        let Primitive::Box { center, .. } = boxp else { unreachable!() };
        let r = hull.vertices.iter().map(|v| ((0..3).map(|k| ((v[k] - center[k]) as f64).powi(2)).sum::<f64>()).sqrt()).fold(0.0, f64::max);
        Primitive::Sphere { center, radius: r as f32 }
    };
    let diag = bbox_diagonal(&mesh.vertices);
    let mut candidates = Vec::new();
    let mut chosen: Option<(f64, Primitive)> = None;
    for p in [Some(boxp), best_cyl.map(|c| c.1), Some(sphere)].into_iter().flatten() {
        let ratio = p.volume() / mesh_volume;
        let dev = samples.iter().map(|s| p.sdf(*s).abs()).fold(0.0, f64::max);
        let accepted = ratio <= 1.0 + tol.volume_tolerance && dev <= tol.surface_tolerance * diag;
        candidates.push(PrimitiveCandidate { kind: p.name(), volume_ratio: ratio, max_surface_deviation_m: dev, accepted });
        if accepted && chosen.as_ref().is_none_or(|(r, _)| ratio < *r) {
            chosen = Some((ratio, p));
        }
    }
    let best = chosen.map(|c| c.1);
    (PrimitiveFitReport { criterion: criterion(tol), candidates, chosen: best.map(|p| p.name()) }, best)
}

fn criterion(t: &PrimitiveTolerances) -> String {
    format!(
        "enclosing primitive accepted when volume <= {:.0}% above the mesh volume and every mesh surface sample lies within {:.1}% of the bounding-box diagonal of its surface; tightest accepted wins",
        100.0 * t.volume_tolerance,
        100.0 * t.surface_tolerance
    )
}

/// Smallest enclosing circle (Welzl, iterative, seeded shuffle).
fn min_enclosing_circle(p: &mut [[f64; 2]], rng: &mut SeededRng) -> ([f64; 2], f64) {
    for i in (1..p.len()).rev() {
        let j = (rng.next_u64() % (i as u64 + 1)) as usize;
        p.swap(i, j);
    }
    let inside = |c: [f64; 2], r: f64, q: [f64; 2]| ((q[0] - c[0]).powi(2) + (q[1] - c[1]).powi(2)).sqrt() <= r * (1.0 + 1e-9) + 1e-12;
    let mut c = p.first().copied().unwrap_or([0.0; 2]);
    let mut r = 0.0;
    for i in 1..p.len() {
        if inside(c, r, p[i]) {
            continue;
        }
        c = p[i];
        r = 0.0;
        for j in 0..i {
            if inside(c, r, p[j]) {
                continue;
            }
            c = [(p[i][0] + p[j][0]) / 2.0, (p[i][1] + p[j][1]) / 2.0];
            r = ((p[i][0] - c[0]).powi(2) + (p[i][1] - c[1]).powi(2)).sqrt();
            for k in 0..j {
                if inside(c, r, p[k]) {
                    continue;
                }
                if let Some((cc, rr)) = circumcircle(p[i], p[j], p[k]) {
                    c = cc;
                    r = rr;
                }
            }
        }
    }
    (c, r)
}

fn circumcircle(a: [f64; 2], b: [f64; 2], c: [f64; 2]) -> Option<([f64; 2], f64)> {
    let d = 2.0 * (a[0] * (b[1] - c[1]) + b[0] * (c[1] - a[1]) + c[0] * (a[1] - b[1]));
    if d.abs() < 1e-18 {
        return None;
    }
    let (a2, b2, c2) = (a[0] * a[0] + a[1] * a[1], b[0] * b[0] + b[1] * b[1], c[0] * c[0] + c[1] * c[1]);
    let ux = (a2 * (b[1] - c[1]) + b2 * (c[1] - a[1]) + c2 * (a[1] - b[1])) / d;
    let uy = (a2 * (c[0] - b[0]) + b2 * (a[0] - c[0]) + c2 * (b[0] - a[0])) / d;
    Some(([ux, uy], ((a[0] - ux).powi(2) + (a[1] - uy).powi(2)).sqrt()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::check_mesh;
    use crate::physics::tests::{box_at, sphere_mesh, tray_mesh};
    use recon_testkit::meshes::plain_cylinder;

    /// L-shaped solid: two boxes fused (a non-convex closed mesh).
    pub fn l_mesh() -> Mesh {
        // Built as a prism over an L polygon.
        let poly: [[f32; 2]; 6] = [[0.0, 0.0], [0.2, 0.0], [0.2, 0.05], [0.05, 0.05], [0.05, 0.2], [0.0, 0.2]];
        let h = 0.05;
        let mut vertices = Vec::new();
        for p in poly {
            vertices.push([p[0], p[1], 0.0]);
            vertices.push([p[0], p[1], h]);
        }
        let mut faces = Vec::new();
        let n = poly.len() as u32;
        for i in 0..n {
            let j = (i + 1) % n;
            faces.push([2 * i, 2 * j, 2 * j + 1]);
            faces.push([2 * i, 2 * j + 1, 2 * i + 1]);
        }
        // Caps of the (counter-clockwise) L: triangulated as 4 triangles.
        for t in [[0u32, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]] {
            faces.push([2 * t[0], 2 * t[2], 2 * t[1]]);
            faces.push([2 * t[0] + 1, 2 * t[1] + 1, 2 * t[2] + 1]);
        }
        Mesh { vertices, faces, vertex_attrs: None }
    }

    fn build(m: &Mesh, method: CollisionMethod) -> Collision {
        let (mesh, rep) = check_mesh(m, "t").unwrap();
        build_collision(&mesh, rep.volume_m3, method, &CollisionOptions::new(), "t").unwrap()
    }

    #[test]
    fn primitives_fit_their_own_shapes_and_nothing_else() {
        let rot = recon_core::math::axis_angle([0.3, -0.5, 0.8], 0.7);
        let rotate = |m: Mesh| Mesh {
            vertices: m.vertices.iter().map(|v| [0, 1, 2].map(|i| (0..3).map(|k| rot[i][k] as f32 * v[k]).sum::<f32>() + 0.1)).collect(),
            ..m
        };
        let c = build(&rotate(box_at([0.05, 0.03, 0.08], [0.0; 3])), CollisionMethod::Primitive);
        assert_eq!(c.report.used, "box", "{:?}", c.report.primitive_fit);
        let Part::Primitive(Primitive::Box { half_extents, .. }) = c.parts[0] else { panic!() };
        let mut h = half_extents;
        h.sort_by(f32::total_cmp);
        assert!((h[0] - 0.03).abs() < 1e-4 && (h[1] - 0.05).abs() < 1e-4 && (h[2] - 0.08).abs() < 1e-4, "{h:?}");
        assert!(c.report.volume.relative_error.unwrap().abs() < 0.05);

        let c = build(&rotate(plain_cylinder(0.04, 0.12, 48)), CollisionMethod::Primitive);
        assert_eq!(c.report.used, "cylinder", "{:?}", c.report.primitive_fit);
        let Part::Primitive(Primitive::Cylinder { radius, half_height, .. }) = c.parts[0] else { panic!() };
        assert!((radius - 0.04).abs() < 2e-4 && (half_height - 0.06).abs() < 2e-4, "{radius} {half_height}");

        let c = build(&sphere_mesh(0.05, 24, 48), CollisionMethod::Primitive);
        assert_eq!(c.report.used, "sphere", "{:?}", c.report.primitive_fit);

        // The L fits no primitive: falls back to the decomposition, recorded.
        let c = build(&l_mesh(), CollisionMethod::Primitive);
        assert_eq!(c.report.used, "vhacd");
        assert!(c.report.primitive_fit.as_ref().unwrap().candidates.iter().all(|k| !k.accepted));
        assert!(c.report.notes.iter().any(|n| n.contains("no primitive matched")));
    }

    #[test]
    fn decomposition_of_a_concave_solid_beats_its_hull() {
        let hull = build(&l_mesh(), CollisionMethod::Hull);
        let dec = build(&l_mesh(), CollisionMethod::Convex);
        assert_eq!(hull.report.parts, 1);
        assert!(dec.report.hull_count >= 2, "{} hulls", dec.report.hull_count);
        let (eh, ed) = (hull.report.volume.relative_error.unwrap(), dec.report.volume.relative_error.unwrap());
        // The L's hull adds the missing 0.15×0.15/2 triangle: +64% of its volume.
        assert!(eh > 0.4, "hull volume error {eh}");
        assert!(ed.abs() < 0.15, "decomposition volume error {ed}");
        assert!(dec.report.surface.collision_to_mesh_max_m < hull.report.surface.collision_to_mesh_max_m);
        // Deterministic.
        let again = build(&l_mesh(), CollisionMethod::Convex);
        let verts = |c: &Collision| c.parts.iter().map(|p| p.surface_mesh().vertices).collect::<Vec<_>>();
        assert_eq!(verts(&again), verts(&dec));
    }

    #[test]
    fn open_tray_keeps_its_cavity_in_the_decomposition() {
        let c = build(&tray_mesh([0.1, 0.1, 0.04]), CollisionMethod::Primitive);
        assert_eq!(c.report.used, "vhacd");
        assert!(c.report.notes.iter().any(|n| n.contains("open mesh")));
        assert!(c.report.volume.mesh_m3.is_none());
        // The tray's inside (centre, mid-height) is not covered.
        let q = PartQuery::new(&c.parts);
        assert!(!q.inside_any([0.0, 0.0, 0.0]));
        assert!(c.report.surface.mesh_to_collision_max_m < 0.01, "{:#?}", c.report);
    }

    #[test]
    fn circle_through_three_points() {
        let mut pts = vec![[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0], [0.1, 0.2], [0.5, 0.5]];
        let (c, r) = min_enclosing_circle(&mut pts, &mut SeededRng::new(0));
        assert!(c[0].abs() < 1e-12 && c[1].abs() < 1e-12 && (r - 1.0).abs() < 1e-12);
    }
}
