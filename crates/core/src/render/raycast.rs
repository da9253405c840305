//! CPU ray-casting renderer: metric depth, instance ids, face normals, incidence, shaded
//! RGB, visible and amodal masks, and the per-pixel covariates of the sensor model.
//!
//! Camera: pinhole in the OpenCV convention (x right, y down, z forward); integer pixel
//! coordinates are pixel centres, so pixel (u, v) is the ray through
//! `((u − cx)/fx, (v − cy)/fy, 1)`. Casting that un-normalised ray makes the hit
//! parameter the z-depth directly. Units are those of the poses and meshes (metres for
//! the covariates).
//!
//! Each mesh gets its own parry BVH in its own frame, built once ([`RenderMesh`]) and
//! reused across poses and views; rays are moved into the instance frame. Every instance
//! whose projected bounds contain a pixel is cast against, so the amodal masks (each
//! object as if alone) come out of the same pass as the visible image. Rows run in
//! parallel (rayon) and each pixel is a pure function of the inputs, so the result does
//! not depend on the thread count.
//!
//! Rendering a BOP frame's GT (models read with `eval::bop`, already in metres):
//! `RenderMesh::from_trimesh(&model.mesh, name)` once per model, then per frame
//! `Instance::new(&mesh, Similarity::rigid(gt.r, gt.t), obj_id as i64)` for each GT
//! instance, `render(&instances, &Camera::new(w, h, k), &RenderOptions::default())`, and
//! `covariates_full(frame_index, Some(&measured_rgb), None)` for the sensor covariates.

use crate::dataset::frame::Intrinsics;
use crate::math::{cross, dot, normalize, sub, Similarity};
use crate::mesh::trimesh::TriMesh;
use crate::mesh::Mesh;
use crate::sensor::PixelCovariates;
use crate::{Error, Result};
use parry3d::math::Vector;
use parry3d::query::{Ray, RayCast};
use parry3d::shape::TriMesh as BvhMesh;
use rayon::prelude::*;

/// A mesh prepared for ray casting (a BVH over its triangles, in its own frame).
pub struct RenderMesh {
    bvh: BvhMesh,
    /// Unit face normals in the mesh frame (`normalize((b − a) × (c − a))`).
    normals: Vec<[f64; 3]>,
    lo: [f64; 3],
    hi: [f64; 3],
}

impl RenderMesh {
    /// `name` is used in error messages (e.g. the model file).
    pub fn new(vertices: &[[f64; 3]], faces: &[[u32; 3]], name: &str) -> Result<Self> {
        if faces.is_empty() {
            return Err(Error::input(name, "mesh has no faces to render"));
        }
        if let Some(v) = vertices.iter().find(|v| v.iter().any(|x| !x.is_finite())) {
            return Err(Error::input(name, format!("mesh vertex {v:?} is not finite")));
        }
        if let Some(f) = faces.iter().find(|f| f.iter().any(|&i| i as usize >= vertices.len())) {
            return Err(Error::input(name, format!("face {f:?} indexes past {} vertices", vertices.len())));
        }
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for f in faces {
            for &i in f {
                for k in 0..3 {
                    lo[k] = lo[k].min(vertices[i as usize][k]);
                    hi[k] = hi[k].max(vertices[i as usize][k]);
                }
            }
        }
        let normals = faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| vertices[i as usize]);
                let n = cross(sub(b, a), sub(c, a));
                let l = dot(n, n).sqrt();
                if l > 0.0 {
                    [n[0] / l, n[1] / l, n[2] / l]
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        let verts: Vec<Vector> = vertices.iter().map(|v| Vector::new(v[0] as f32, v[1] as f32, v[2] as f32)).collect();
        let bvh = BvhMesh::new(verts, faces.to_vec()).map_err(|e| Error::input(name, format!("cannot build a ray-casting mesh: {e}")))?;
        Ok(RenderMesh { bvh, normals, lo, hi })
    }

    /// A ray-casting mesh from a [`Mesh`] (f32 vertices); `name` labels errors.
    pub fn from_mesh(m: &Mesh, name: &str) -> Result<Self> {
        let v: Vec<[f64; 3]> = m.vertices.iter().map(|v| v.map(|x| x as f64)).collect();
        Self::new(&v, &m.faces, name)
    }

    /// From an evaluation mesh (e.g. a BOP model read with `eval::ply`, in metres).
    pub fn from_trimesh(m: &TriMesh, name: &str) -> Result<Self> {
        Self::new(&m.vertices, &m.faces, name)
    }

    /// Number of triangles.
    pub fn num_triangles(&self) -> usize {
        self.normals.len()
    }

    /// Axis-aligned bounds of the referenced vertices (mesh frame).
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        (self.lo, self.hi)
    }
}

/// Surface appearance, evaluated in the instance's own (mesh) frame, so textures stick
/// to the object whatever its pose.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
#[serde(tag = "pattern", rename_all = "snake_case")]
pub enum Pattern {
    /// One colour (`color`).
    Solid,
    /// 3D checkerboard of cubes with side `cell` (mesh units).
    Checker {
        /// Cube side, mesh units.
        cell: f64,
    },
    /// Slabs of width `period / 2` across mesh axis `axis` (0 = x, 1 = y, 2 = z).
    Stripes {
        /// Mesh axis across the stripes (0 = x, 1 = y, 2 = z).
        axis: usize,
        /// Period of the stripes, mesh units.
        period: f64,
    },
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
/// Surface colours and pattern of an instance.
pub struct Material {
    /// Linear RGB in [0, 1].
    pub color: [f32; 3],
    /// Second colour of the pattern.
    pub color2: [f32; 3],
    #[serde(flatten)]
    /// How the two colours are laid out.
    pub pattern: Pattern,
}

impl Default for Material {
    fn default() -> Self {
        Material { color: [0.7, 0.7, 0.7], color2: [0.7, 0.7, 0.7], pattern: Pattern::Solid }
    }
}

impl Material {
    fn albedo(&self, p: [f64; 3]) -> [f32; 3] {
        let second = match self.pattern {
            Pattern::Solid => false,
            Pattern::Checker { cell } => ((p[0] / cell).floor() + (p[1] / cell).floor() + (p[2] / cell).floor()).rem_euclid(2.0) >= 1.0,
            Pattern::Stripes { axis, period } => (2.0 * p[axis.min(2)] / period).floor().rem_euclid(2.0) >= 1.0,
        };
        if second {
            self.color2
        } else {
            self.color
        }
    }
}

/// One object to draw.
#[derive(Clone, Copy)]
pub struct Instance<'a> {
    /// The mesh drawn.
    pub mesh: &'a RenderMesh,
    /// Mesh → world (`X_world = s·R·X_mesh + t`, s > 0).
    pub pose: Similarity,
    /// Reported in [`Rendered::ids`] and the `object` covariate.
    pub id: i64,
    /// Surface appearance.
    pub material: Material,
}

impl<'a> Instance<'a> {
    /// An instance of `mesh` at `pose` with the default material.
    pub fn new(mesh: &'a RenderMesh, pose: Similarity, id: i64) -> Self {
        Instance { mesh, pose, id, material: Material::default() }
    }
}

/// Pinhole camera with its pose. `world_to_cam` is identity when poses are already in
/// the camera frame (BOP `cam_R_m2c`, `cam_t_m2c`).
#[derive(Clone, Copy, Debug)]
pub struct Camera {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Pinhole intrinsics.
    pub k: Intrinsics,
    /// World → camera transform.
    pub world_to_cam: Similarity,
}

impl Camera {
    /// A camera at the world origin (`world_to_cam` identity).
    pub fn new(width: usize, height: usize, k: Intrinsics) -> Self {
        Camera { width, height, k, world_to_cam: Similarity::identity() }
    }

    /// World → camera transform of a camera at `eye` looking at `target`, with world
    /// `up` appearing upwards in the image (OpenCV axes: y down).
    pub fn look_at(eye: [f64; 3], target: [f64; 3], up: [f64; 3]) -> Similarity {
        let z = normalize(sub(target, eye));
        let x = normalize(cross(z, up));
        let y = cross(z, x);
        let r = [x, y, z];
        let t = [-dot(x, eye), -dot(y, eye), -dot(z, eye)];
        Similarity::rigid(r, t)
    }

    /// Camera centre in world coordinates.
    pub fn eye(&self) -> [f64; 3] {
        let p = &self.world_to_cam;
        let r = p.rotation;
        // x_w = Rᵀ (x_c − t) / s at x_c = 0.
        [0, 1, 2].map(|j| -(0..3).map(|i| r[i][j] * p.translation[i]).sum::<f64>() / p.scale)
    }
}

/// Directional light plus ambient; `direction_cam` points from the surface towards the
/// light, in the camera frame.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Light {
    /// Unit direction from the surface to the light, camera frame.
    pub direction_cam: [f64; 3],
    /// Ambient intensity.
    pub ambient: f32,
    /// Diffuse (Lambertian) intensity.
    pub diffuse: f32,
}

impl Default for Light {
    fn default() -> Self {
        // Above and a little left of the camera (image up is −y).
        Light { direction_cam: normalize([-0.3, -0.6, -1.0]), ambient: 0.3, diffuse: 0.7 }
    }
}

#[derive(Clone, Copy, Debug)]
/// Lighting and background of a render.
pub struct RenderOptions {
    /// The light.
    pub light: Light,
    /// RGB of pixels that hit nothing.
    pub background: [u8; 3],
}

impl Default for RenderOptions {
    fn default() -> Self {
        RenderOptions { light: Light::default(), background: [40, 40, 40] }
    }
}

/// Relative depth jump between 4-neighbours that counts as a discontinuity (also the
/// sensor model's edge-fattening criterion).
pub const EDGE_JUMP_REL: f64 = 0.02;

/// Everything rendered for one view; images are row-major `width × height`.
#[derive(Clone, Debug)]
pub struct Rendered {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Pinhole intrinsics.
    pub k: Intrinsics,
    /// z-depth along the optical axis (0 = no surface).
    pub depth: Vec<f32>,
    /// Index into the instance list of the visible surface (−1 = none).
    pub index: Vec<i32>,
    /// Instance ids, by instance index.
    pub ids: Vec<i64>,
    /// Hit triangle's unit face normal (as the mesh orients it) in the camera / world frame; 0 where no hit.
    pub normal_cam: Vec<[f32; 3]>,
    /// Face normal of the hit triangle in the world frame (0 where no hit).
    pub normal_world: Vec<[f32; 3]>,
    /// Angle between the viewing ray and the hit face normal, degrees in [0, 90].
    pub incidence: Vec<f32>,
    /// Shaded colour, 3 bytes per pixel.
    pub rgb: Vec<u8>,
    /// Per instance: the pixels it covers when rendered alone.
    pub amodal: Vec<Vec<bool>>,
}

struct Prepared {
    /// Camera → mesh: `x_mesh = m · x_cam + o`.
    m: [[f64; 3]; 3],
    o: [f64; 3],
    /// Mesh → camera rotation (for normals).
    r_cam: [[f64; 3]; 3],
    /// Pixel rectangle that can contain the instance (inclusive), or None if off-screen.
    rect: Option<(usize, usize, usize, usize)>,
}

fn prepare(inst: &Instance, cam: &Camera) -> Prepared {
    let m2c = cam.world_to_cam.compose(&inst.pose);
    let s = m2c.scale;
    let mut m = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = m2c.rotation[j][i] / s;
        }
    }
    let o = [0, 1, 2].map(|i| -(0..3).map(|j| m[i][j] * m2c.translation[j]).sum::<f64>());
    // Project the eight bound corners; a corner at or behind the camera plane makes the
    // rectangle the whole image (a conservative bound).
    let (lo, hi) = inst.mesh.bounds();
    let (w, h) = (cam.width as f64, cam.height as f64);
    let k = cam.k;
    let mut r = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
    let mut full = false;
    let mut all_behind = true;
    for c in 0..8 {
        let p = [if c & 1 == 0 { lo[0] } else { hi[0] }, if c & 2 == 0 { lo[1] } else { hi[1] }, if c & 4 == 0 { lo[2] } else { hi[2] }];
        let q = m2c.apply(&p);
        if q[2] > 1e-9 {
            all_behind = false;
            let (u, v) = (k.fx * q[0] / q[2] + k.cx, k.fy * q[1] / q[2] + k.cy);
            r = [r[0].min(u), r[1].min(v), r[2].max(u), r[3].max(v)];
        } else {
            full = true;
        }
    }
    let rect = if all_behind {
        None
    } else if full {
        Some((0, 0, cam.width - 1, cam.height - 1))
    } else if r[2] < -1.0 || r[3] < -1.0 || r[0] > w || r[1] > h {
        None
    } else {
        let cl = |x: f64, n: usize| x.clamp(0.0, (n - 1) as f64) as usize;
        Some((
            cl(r[0].floor() - 1.0, cam.width),
            cl(r[1].floor() - 1.0, cam.height),
            cl(r[2].ceil() + 1.0, cam.width),
            cl(r[3].ceil() + 1.0, cam.height),
        ))
    };
    Prepared { m, o, r_cam: m2c.rotation, rect }
}

struct Row {
    depth: Vec<f32>,
    index: Vec<i32>,
    normal_cam: Vec<[f32; 3]>,
    normal_world: Vec<[f32; 3]>,
    incidence: Vec<f32>,
    rgb: Vec<u8>,
    /// (instance, column) of every hit, nearest or not.
    hits: Vec<(u32, u32)>,
}

/// Render `instances` seen by `camera`.
pub fn render(instances: &[Instance], camera: &Camera, opts: &RenderOptions) -> Result<Rendered> {
    let (w, h) = (camera.width, camera.height);
    if w == 0 || h == 0 {
        return Err(Error::input("camera", format!("image size {w}×{h}: both must be ≥ 1")));
    }
    if !(camera.world_to_cam.scale > 0.0) || instances.iter().any(|i| !(i.pose.scale > 0.0)) {
        return Err(Error::input("pose", "scales must be positive"));
    }
    let prep: Vec<Prepared> = instances.iter().map(|i| prepare(i, camera)).collect();
    let k = camera.k;
    let light = normalize(opts.light.direction_cam);
    let rows: Vec<Row> = (0..h)
        .into_par_iter()
        .map(|v| {
            let mut row = Row {
                depth: vec![0.0; w],
                index: vec![-1; w],
                normal_cam: vec![[0.0; 3]; w],
                normal_world: vec![[0.0; 3]; w],
                incidence: vec![0.0; w],
                rgb: opts.background.iter().copied().cycle().take(3 * w).collect(),
                hits: Vec::new(),
            };
            let active: Vec<usize> = (0..prep.len()).filter(|&i| prep[i].rect.is_some_and(|r| v >= r.1 && v <= r.3)).collect();
            if active.is_empty() {
                return row;
            }
            let dy = (v as f64 - k.cy) / k.fy;
            for u in 0..w {
                let d = [(u as f64 - k.cx) / k.fx, dy, 1.0];
                let mut best: Option<(f32, usize, u32, [f64; 3])> = None;
                for &i in &active {
                    let p = &prep[i];
                    let rc = p.rect.unwrap_or((0, 0, 0, 0));
                    if u < rc.0 || u > rc.2 {
                        continue;
                    }
                    let dir = mat_vec(&p.m, d);
                    let ray = Ray::new(
                        Vector::new(p.o[0] as f32, p.o[1] as f32, p.o[2] as f32),
                        Vector::new(dir[0] as f32, dir[1] as f32, dir[2] as f32),
                    );
                    if let Some(hit) = instances[i].mesh.bvh.cast_local_ray_and_get_normal(&ray, f32::MAX, false) {
                        let t = hit.time_of_impact;
                        if !(t > 0.0) {
                            continue;
                        }
                        row.hits.push((i as u32, u as u32));
                        if best.is_none_or(|b| t < b.0) {
                            let local = [0, 1, 2].map(|j| p.o[j] + t as f64 * dir[j]);
                            best = Some((t, i, hit.subshape, local));
                        }
                    }
                }
                let Some((t, i, tri, local)) = best else { continue };
                let n_mesh = instances[i].mesh.normals.get(tri as usize).copied().unwrap_or([0.0; 3]);
                let n_cam = mat_vec(&prep[i].r_cam, n_mesh);
                let n_world = mat_vec(&instances[i].pose.rotation, n_mesh);
                let dn = normalize(d);
                let c = dot(n_cam, dn);
                row.depth[u] = t;
                row.index[u] = i as i32;
                row.normal_cam[u] = n_cam.map(|x| x as f32);
                row.normal_world[u] = n_world.map(|x| x as f32);
                row.incidence[u] = c.abs().min(1.0).acos().to_degrees() as f32;
                // Shade the side facing the camera (open meshes show their inside).
                let facing = if c > 0.0 { n_cam.map(|x| -x) } else { n_cam };
                let lambert = dot(facing, light).max(0.0) as f32;
                let albedo = instances[i].material.albedo(local);
                let shade = opts.light.ambient + opts.light.diffuse * lambert;
                for ch in 0..3 {
                    row.rgb[3 * u + ch] = (albedo[ch] * shade * 255.0).round().clamp(0.0, 255.0) as u8;
                }
            }
            row
        })
        .collect();
    let n = w * h;
    let mut out = Rendered {
        width: w,
        height: h,
        k,
        depth: Vec::with_capacity(n),
        index: Vec::with_capacity(n),
        ids: instances.iter().map(|i| i.id).collect(),
        normal_cam: Vec::with_capacity(n),
        normal_world: Vec::with_capacity(n),
        incidence: Vec::with_capacity(n),
        rgb: Vec::with_capacity(3 * n),
        amodal: vec![vec![false; n]; instances.len()],
    };
    for (v, r) in rows.into_iter().enumerate() {
        out.depth.extend(r.depth);
        out.index.extend(r.index);
        out.normal_cam.extend(r.normal_cam);
        out.normal_world.extend(r.normal_world);
        out.incidence.extend(r.incidence);
        out.rgb.extend(r.rgb);
        for (i, u) in r.hits {
            out.amodal[i as usize][v * w + u as usize] = true;
        }
    }
    Ok(out)
}

impl Rendered {
    /// Pixels where instance `i` is the visible surface.
    pub fn visible_mask(&self, i: usize) -> Vec<bool> {
        self.index.iter().map(|&x| x == i as i32).collect()
    }

    /// Instance id of the visible surface per pixel (−1 = none).
    pub fn object_ids(&self) -> Vec<i64> {
        self.index.iter().map(|&x| if x >= 0 { self.ids[x as usize] } else { -1 }).collect()
    }

    /// Depth restricted to the instances flagged in `include` (all when `None`).
    fn depth_of(&self, include: Option<&[bool]>) -> Vec<f32> {
        match include {
            None => self.depth.clone(),
            Some(inc) => self
                .depth
                .iter()
                .zip(&self.index)
                .map(|(&z, &i)| if i >= 0 && inc.get(i as usize).copied().unwrap_or(false) { z } else { 0.0 })
                .collect(),
        }
    }

    /// Pixels on a depth discontinuity: a surface pixel whose 4-neighbour has no surface
    /// or a depth differing by more than [`EDGE_JUMP_REL`] of the nearer one. With
    /// `include`, only those instances' surfaces count (e.g. the GT objects without the
    /// table, as the audit defines `edge_distance`).
    pub fn discontinuities(&self, include: Option<&[bool]>) -> Vec<bool> {
        let (w, h) = (self.width, self.height);
        let z = self.depth_of(include);
        let mut e = vec![false; w * h];
        for v in 0..h {
            for u in 0..w {
                let a = z[v * w + u] as f64;
                if !(a > 0.0) {
                    continue;
                }
                let mut edge = false;
                for (du, dv) in [(-1i64, 0i64), (1, 0), (0, -1), (0, 1)] {
                    let (uu, vv) = (u as i64 + du, v as i64 + dv);
                    if uu < 0 || vv < 0 || uu >= w as i64 || vv >= h as i64 {
                        continue;
                    }
                    let b = z[vv as usize * w + uu as usize] as f64;
                    if !(b > 0.0) || (a - b).abs() > EDGE_JUMP_REL * a.min(b) {
                        edge = true;
                        break;
                    }
                }
                e[v * w + u] = edge;
            }
        }
        e
    }

    /// Euclidean distance in pixels to the nearest discontinuity (exact distance
    /// transform). Without any discontinuity every pixel gets `width + height`.
    pub fn edge_distance(&self, include: Option<&[bool]>) -> Vec<f32> {
        let e = self.discontinuities(include);
        let cap = (self.width + self.height) as f64;
        if !e.iter().any(|&x| x) {
            return vec![cap as f32; e.len()];
        }
        let d2 = distance_transform_sq(&e, self.width, self.height);
        d2.into_iter().map(|x| x.sqrt().min(cap) as f32).collect()
    }

    /// The sensor-model covariates of every pixel (row-major): `intensity` from the
    /// rendered RGB, `edge_distance` over all rendered instances. Pixels without a
    /// surface have depth 0 and object −1.
    pub fn covariates(&self, frame: i64) -> Vec<PixelCovariates> {
        self.covariates_full(frame, None, None)
    }

    /// As [`Self::covariates`], with `intensity` from `rgb` (e.g. the measured colour
    /// image, 3 bytes per pixel, same size) when given, and `edge_distance` from the
    /// discontinuities of the instances flagged in `edge_instances` when given.
    pub fn covariates_full(&self, frame: i64, rgb: Option<&[u8]>, edge_instances: Option<&[bool]>) -> Vec<PixelCovariates> {
        let (w, h) = (self.width, self.height);
        let rgb = rgb.filter(|c| c.len() == 3 * w * h).unwrap_or(&self.rgb);
        let edge = self.edge_distance(edge_instances);
        let half_diag = 0.5 * ((w * w + h * h) as f64).sqrt();
        let k = self.k;
        (0..w * h)
            .map(|i| {
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                let c = &rgb[3 * i..3 * i + 3];
                PixelCovariates {
                    depth: self.depth[i] as f64,
                    radius: ((u - k.cx).powi(2) + (v - k.cy).powi(2)).sqrt() / half_diag,
                    incidence: self.incidence[i] as f64,
                    edge_distance: edge[i] as f64,
                    intensity: (0.299 * c[0] as f64 + 0.587 * c[1] as f64 + 0.114 * c[2] as f64) / 255.0,
                    object: if self.index[i] >= 0 { self.ids[self.index[i] as usize] } else { -1 },
                    frame,
                    u,
                    v,
                }
            })
            .collect()
    }
}

/// Squared Euclidean distance transform of a binary image (Felzenszwalb & Huttenlocher's
/// separable lower-envelope algorithm; exact).
pub fn distance_transform_sq(feature: &[bool], w: usize, h: usize) -> Vec<f64> {
    const INF: f64 = 1e20;
    let mut f: Vec<f64> = feature.iter().map(|&b| if b { 0.0 } else { INF }).collect();
    let mut buf_in = vec![0.0; w.max(h)];
    let mut buf_out = vec![0.0; w.max(h)];
    for u in 0..w {
        for v in 0..h {
            buf_in[v] = f[v * w + u];
        }
        dt_1d(&buf_in[..h], &mut buf_out[..h]);
        for v in 0..h {
            f[v * w + u] = buf_out[v];
        }
    }
    for v in 0..h {
        buf_in[..w].copy_from_slice(&f[v * w..(v + 1) * w]);
        dt_1d(&buf_in[..w], &mut buf_out[..w]);
        f[v * w..(v + 1) * w].copy_from_slice(&buf_out[..w]);
    }
    f
}

fn dt_1d(f: &[f64], d: &mut [f64]) {
    let n = f.len();
    let mut vtx = vec![0usize; n];
    let mut z = vec![0.0f64; n + 1];
    let mut k = 0;
    z[0] = f64::NEG_INFINITY;
    z[1] = f64::INFINITY;
    for q in 1..n {
        loop {
            let p = vtx[k];
            let s = ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * q as f64 - 2.0 * p as f64);
            if s <= z[k] && k > 0 {
                k -= 1;
                continue;
            }
            if s <= z[k] {
                // k == 0: replace the first parabola.
                vtx[0] = q;
                z[0] = f64::NEG_INFINITY;
                z[1] = f64::INFINITY;
                break;
            }
            k += 1;
            vtx[k] = q;
            z[k] = s;
            z[k + 1] = f64::INFINITY;
            break;
        }
    }
    let mut k = 0;
    for (q, out) in d.iter_mut().enumerate() {
        while z[k + 1] < q as f64 {
            k += 1;
        }
        let p = vtx[k];
        *out = (q as f64 - p as f64).powi(2) + f[p];
    }
}

fn mat_vec(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::axis_angle;
    use crate::mesh::primitives::{box_mesh, sphere_mesh};

    fn cam(w: usize, h: usize, f: f64) -> Camera {
        Camera::new(w, h, Intrinsics { fx: f, fy: f, cx: (w as f64 - 1.0) / 2.0, cy: (h as f64 - 1.0) / 2.0 })
    }

    fn quad(size: f64) -> RenderMesh {
        // A square in the z = 0 plane facing −z (towards a camera at the origin looking down +z).
        let s = size / 2.0;
        RenderMesh::new(&[[-s, -s, 0.0], [s, -s, 0.0], [s, s, 0.0], [-s, s, 0.0]], &[[0, 2, 1], [0, 3, 2]], "quad").unwrap()
    }

    #[test]
    fn fronto_parallel_plane_depth_and_pixel_centres() {
        let m = quad(10.0);
        let at = |t: [f64; 3], r: [[f64; 3]; 3]| Similarity::rigid(r, t);
        let i = Instance::new(&m, at([0.0, 0.0, 2.0], Similarity::identity().rotation), 7);
        let r = render(&[i], &cam(8, 6, 10.0), &RenderOptions::default()).unwrap();
        assert!(r.depth.iter().all(|&z| (z - 2.0).abs() < 1e-6), "{:?}", r.depth);
        // Incidence is the angle between the ray and the normal: the ray's angle off the axis here.
        for (i, &a) in r.incidence.iter().enumerate() {
            let (x, y) = ((i % 8) as f64 - 3.5, (i / 8) as f64 - 2.5);
            let want = (x * x + y * y).sqrt().atan2(10.0).to_degrees();
            assert!((a as f64 - want).abs() < 1e-3, "pixel {i}: {a} vs {want}");
        }
        assert!(r.normal_cam.iter().all(|n| (n[2] + 1.0).abs() < 1e-6));
        assert_eq!(r.object_ids(), vec![7; 48]);
        // Tilted plane z = 2 + 0.5·y (rotation about x): depth at row v solves
        // z = 2 + 0.5·z·(v − cy)/fy exactly — pixel centres, not corners.
        let rot = axis_angle([1.0, 0.0, 0.0], (0.5f64).atan());
        let r = render(&[Instance::new(&m, at([0.0, 0.0, 2.0], rot), 1)], &cam(8, 6, 10.0), &RenderOptions::default()).unwrap();
        for v in 0..6 {
            let y = (v as f64 - 2.5) / 10.0;
            let z = 2.0 / (1.0 - 0.5 * y);
            for u in 0..8 {
                assert!((r.depth[v * 8 + u] as f64 - z).abs() < 1e-5, "v {v}: {} vs {z}", r.depth[v * 8 + u]);
            }
        }
        // Incidence: angle between the ray and the plane normal (0, −0.5, 1)/|·| ... at the centre column.
        let n = normalize([0.0f64, 0.5, -1.0]);
        let d = normalize([(0.0 - 3.5) / 10.0, (0.0 - 2.5) / 10.0, 1.0]);
        let want = dot(n, d).abs().acos().to_degrees();
        assert!((r.incidence[0] as f64 - want).abs() < 1e-3, "{} vs {want}", r.incidence[0]);
    }

    #[test]
    fn sphere_silhouette_occlusion_and_amodal_masks() {
        let s = RenderMesh::from_mesh(&sphere_mesh(0.1), "sphere").unwrap();
        let b = RenderMesh::from_mesh(&box_mesh(0.1, 0.1, 0.1), "box").unwrap();
        let c = cam(128, 96, 300.0);
        let far = Instance::new(&s, Similarity::rigid(Similarity::identity().rotation, [0.0, 0.0, 1.0]), 1);
        // A box in front of the sphere's left half.
        let near = Instance::new(&b, Similarity::rigid(Similarity::identity().rotation, [-0.05, 0.0, 0.6]), 2);
        let alone = render(&[far], &c, &RenderOptions::default()).unwrap();
        let both = render(&[far, near], &c, &RenderOptions::default()).unwrap();
        // The sphere's amodal mask does not depend on the occluder.
        assert_eq!(alone.amodal[0], both.amodal[0]);
        let area = alone.amodal[0].iter().filter(|&&x| x).count() as f64;
        // Projected disc radius ≈ f·r/sqrt(d² − r²) (the polygonal sphere is slightly smaller).
        let rp = 300.0 * 0.1 / (1.0f64 - 0.01).sqrt();
        let expect = std::f64::consts::PI * rp * rp;
        assert!(area > 0.9 * expect && area < 1.05 * expect, "{area} vs {expect}");
        let vis = both.visible_mask(0).iter().filter(|&&x| x).count() as f64;
        assert!(vis < 0.8 * area && vis > 0.2 * area, "visible {vis} of {area}");
        // Nearest depth at the centre column is the sphere's front (1 − 0.1) where not occluded.
        let centre = 48 * 128 + 64;
        assert_eq!(both.index[centre], 0);
        assert!((both.depth[centre] - 0.9).abs() < 0.01, "{}", both.depth[centre]);
        // Where the box covers the sphere, the box is visible and nearer.
        let i = (0..128 * 96).find(|&i| both.amodal[0][i] && both.index[i] == 1).unwrap();
        assert!(both.depth[i] < 0.7);
        // Deterministic.
        let again = render(&[far, near], &c, &RenderOptions::default()).unwrap();
        assert_eq!(again.depth, both.depth);
        assert_eq!(again.rgb, both.rgb);
    }

    #[test]
    fn distance_transform_is_exact() {
        let (w, h) = (13, 9);
        let mut f = vec![false; w * h];
        for &(u, v) in &[(2usize, 3usize), (10, 7), (6, 0)] {
            f[v * w + u] = true;
        }
        let d = distance_transform_sq(&f, w, h);
        for v in 0..h {
            for u in 0..w {
                let want = [(2, 3), (10, 7), (6, 0)]
                    .iter()
                    .map(|&(a, b): &(i64, i64)| (u as i64 - a).pow(2) + (v as i64 - b).pow(2))
                    .min()
                    .unwrap();
                assert_eq!(d[v * w + u], want as f64, "({u}, {v})");
            }
        }
    }

    #[test]
    fn covariates_of_a_rendered_frame() {
        let b = RenderMesh::from_mesh(&box_mesh(0.2, 0.2, 0.2), "box").unwrap();
        let c = cam(40, 30, 40.0);
        let mut inst = Instance::new(&b, Similarity::rigid(Similarity::identity().rotation, [0.0, 0.0, 1.0]), 5);
        inst.material = Material { color: [1.0, 0.0, 0.0], ..Material::default() };
        let r = render(
            &[inst],
            &c,
            &RenderOptions { light: Light { direction_cam: [0.0, 0.0, -1.0], ambient: 0.0, diffuse: 1.0 }, ..Default::default() },
        )
        .unwrap();
        let cov = r.covariates(3);
        assert_eq!(cov.len(), 40 * 30);
        let centre = &cov[15 * 40 + 20];
        assert_eq!((centre.object, centre.frame, centre.u, centre.v), (5, 3, 20.0, 15.0));
        assert!((centre.depth - 0.9).abs() < 1e-6);
        // Red, fully lit face seen head-on: luminance 0.299.
        assert!((centre.intensity - 0.299).abs() < 1e-9, "{}", centre.intensity);
        let half_diag = 0.5 * (40f64 * 40.0 + 30.0 * 30.0).sqrt();
        assert!((centre.radius - (0.5f64 * 0.5 + 0.5 * 0.5).sqrt() / half_diag).abs() < 1e-12);
        // The box's front face covers columns 16..=23 and rows 11..=18 (±0.1/0.9·40 px
        // around (19.5, 14.5)); its rim pixels are discontinuities, the nearest 3 px away.
        assert_eq!(centre.edge_distance, 3.0);
        let corner = &cov[0];
        assert_eq!((corner.object, corner.depth), (-1, 0.0));
        // Intensity from a supplied image instead.
        let grey = vec![128u8; 3 * 40 * 30];
        assert!((r.covariates_full(0, Some(&grey), None)[0].intensity - 128.0 / 255.0).abs() < 1e-12);
    }

    #[test]
    fn edge_distance_can_ignore_the_background() {
        // A box face 0.9 m away in front of a wall at 0.91 m: a 1 % depth step is no
        // discontinuity, so with the wall the box face has no edges; over the box alone
        // its silhouette is one.
        let b = RenderMesh::from_mesh(&box_mesh(0.2, 0.2, 0.2), "box").unwrap();
        let wall = quad(10.0);
        let c = cam(40, 30, 40.0);
        let id = Similarity::identity().rotation;
        let r = render(
            &[
                Instance::new(&wall, Similarity::rigid(id, [0.0, 0.0, 0.91]), 0),
                Instance::new(&b, Similarity::rigid(id, [0.0, 0.0, 1.0]), 1),
            ],
            &c,
            &RenderOptions::default(),
        )
        .unwrap();
        let all = r.edge_distance(None);
        assert!(all.iter().all(|&d| d == 70.0), "no discontinuity anywhere: capped at w + h");
        let boxed = r.edge_distance(Some(&[false, true]));
        assert_eq!(boxed[15 * 40 + 20], 3.0);
        assert_eq!(r.covariates_full(0, None, Some(&[false, true]))[15 * 40 + 20].edge_distance, 3.0);
    }

    #[test]
    fn bad_meshes_are_refused_with_their_name() {
        let e = RenderMesh::new(&[[0.0; 3]], &[[0, 1, 2]], "obj_000003.ply").err().unwrap().to_string();
        assert!(e.contains("obj_000003.ply") && e.contains("indexes past"), "{e}");
        let e = RenderMesh::new(&[[0.0; 3]], &[], "m.ply").err().unwrap().to_string();
        assert!(e.contains("no faces"), "{e}");
    }
}
