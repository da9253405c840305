//! A tiny in-memory training set of primitive objects (boxes, cylinders,
//! ellipsoids, cones) rendered into RGB-D views, for the CI smoke training
//! and the tests. It is not the training data of recgen-nano: that comes
//! from `recon synth` (BOP folders read by [`crate::bop::BopSource`]).
//!
//! Each sample is one primitive at a random pose 0.45–0.8 m in front of a
//! pinhole camera, over a back plane, optionally half-hidden by a second
//! primitive in front of it, and optionally seen in a second view (a second
//! random pose, i.e. a moved camera). Depth gets Gaussian noise growing with
//! z² (a crude stereo model: realistic sensor noise is `recon synth`'s job).
//! Rendering is a plain z-buffer rasteriser (pixel centres at integer
//! coordinates, perspective-correct depth, head-light Lambert shading).

use std::sync::Arc;

use crate::data::{ModelEntry, ObjectSample, ObjectView, TrainingSource};
use recon_core::dataset::frame::{Intrinsics, RgbdFrame};
use recon_core::math::axis_angle;
use recon_core::mesh::primitives::{box_corners, BOX_FACES};
use recon_core::mesh::trimesh::TriMesh;
use recon_core::rng::SeededRng;
use recon_core::Result;

/// What to generate.
#[derive(Debug, Clone)]
pub struct ToyConfig {
    /// Number of object models.
    pub models: usize,
    /// Number of samples.
    pub samples: usize,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Seed of everything generated.
    pub seed: u64,
    /// Put a second primitive in front of half the objects.
    pub occluders: bool,
    /// Give every sample a second view.
    pub second_view: bool,
}

impl Default for ToyConfig {
    fn default() -> Self {
        Self { models: 4, samples: 8, width: 160, height: 120, seed: 0, occluders: true, second_view: false }
    }
}

/// A primitive triangle mesh in metres, centred near (not at) the origin.
pub fn primitive(kind: usize, dims: [f64; 3], offset: [f64; 3]) -> TriMesh {
    let (mut v, f): (Vec<[f64; 3]>, Vec<[u32; 3]>) = match kind % 4 {
        0 => {
            let h = dims.map(|d| d / 2.0);
            (box_corners(h.map(|x| -x), h), BOX_FACES.to_vec())
        }
        k @ (1 | 3) => {
            // Cylinder (k = 1) or cone (k = 3) along z: radius dims[0], height dims[2].
            let n = 24;
            let (r, h) = (dims[0] / 2.0, dims[2] / 2.0);
            let top_r = if k == 1 { r } else { 0.0 };
            let mut v = vec![[0.0, 0.0, -h], [0.0, 0.0, h]];
            for i in 0..n {
                let a = std::f64::consts::TAU * i as f64 / n as f64;
                v.push([r * a.cos(), r * a.sin(), -h]);
                v.push([top_r * a.cos(), top_r * a.sin(), h]);
            }
            let mut f = Vec::new();
            for i in 0..n as u32 {
                let j = (i + 1) % n as u32;
                let (b0, t0, b1, t1) = (2 + 2 * i, 3 + 2 * i, 2 + 2 * j, 3 + 2 * j);
                f.extend([[0, b1, b0], [1, t0, t1], [b0, b1, t1], [b0, t1, t0]]);
            }
            (v, f)
        }
        _ => {
            let (nl, nm) = (10usize, 20usize);
            let r = dims.map(|d| d / 2.0);
            let mut v = vec![[0.0, 0.0, r[2]], [0.0, 0.0, -r[2]]];
            for i in 1..nl {
                let th = std::f64::consts::PI * i as f64 / nl as f64;
                for j in 0..nm {
                    let ph = std::f64::consts::TAU * j as f64 / nm as f64;
                    v.push([r[0] * th.sin() * ph.cos(), r[1] * th.sin() * ph.sin(), r[2] * th.cos()]);
                }
            }
            let idx = |i: usize, j: usize| (2 + (i - 1) * nm + j % nm) as u32;
            let mut f = Vec::new();
            for j in 0..nm {
                f.push([0, idx(1, j), idx(1, j + 1)]);
                f.push([1, idx(nl - 1, j + 1), idx(nl - 1, j)]);
                for i in 1..nl - 1 {
                    f.push([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)]);
                    f.push([idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]);
                }
            }
            (v, f)
        }
    };
    for p in &mut v {
        for a in 0..3 {
            p[a] += offset[a];
        }
    }
    TriMesh { vertices: v, faces: f }
}

/// A rendered view: depth in metres (0 = nothing), object id per pixel
/// (0 = background), RGB.
pub struct Render {
    pub depth: Vec<f32>,
    pub ids: Vec<u32>,
    pub rgb: Vec<u8>,
}

/// Z-buffer render of camera-frame meshes `(mesh, id, rgb in [0, 1])`.
pub fn rasterize(meshes: &[(TriMesh, u32, [f32; 3])], k: &Intrinsics, w: usize, h: usize) -> Render {
    let mut depth = vec![f32::INFINITY; w * h];
    let mut ids = vec![0u32; w * h];
    let mut rgb = vec![0u8; w * h * 3];
    for (mesh, id, col) in meshes {
        for f in &mesh.faces {
            let p = f.map(|i| mesh.vertices[i as usize]);
            if p.iter().any(|q| q[2] <= 1e-3) {
                continue;
            }
            let s: [[f64; 2]; 3] = p.map(|q| [k.fx * q[0] / q[2] + k.cx, k.fy * q[1] / q[2] + k.cy]);
            let area = (s[1][0] - s[0][0]) * (s[2][1] - s[0][1]) - (s[2][0] - s[0][0]) * (s[1][1] - s[0][1]);
            if area.abs() < 1e-12 {
                continue;
            }
            // Head-light Lambert shading from the face normal.
            let e1 = [p[1][0] - p[0][0], p[1][1] - p[0][1], p[1][2] - p[0][2]];
            let e2 = [p[2][0] - p[0][0], p[2][1] - p[0][1], p[2][2] - p[0][2]];
            let n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]];
            let c = [(p[0][0] + p[1][0] + p[2][0]) / 3.0, (p[0][1] + p[1][1] + p[2][1]) / 3.0, (p[0][2] + p[1][2] + p[2][2]) / 3.0];
            let (nn, cn) = ((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt(), (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt());
            let lambert = ((n[0] * c[0] + n[1] * c[1] + n[2] * c[2]) / (nn * cn).max(1e-12)).abs();
            let shade = (0.25 + 0.75 * lambert) as f32;
            let x0 = s.iter().map(|q| q[0]).fold(f64::INFINITY, f64::min).ceil().max(0.0) as usize;
            let x1 = s.iter().map(|q| q[0]).fold(f64::NEG_INFINITY, f64::max).floor().min(w as f64 - 1.0);
            let y0 = s.iter().map(|q| q[1]).fold(f64::INFINITY, f64::min).ceil().max(0.0) as usize;
            let y1 = s.iter().map(|q| q[1]).fold(f64::NEG_INFINITY, f64::max).floor().min(h as f64 - 1.0);
            if x1 < 0.0 || y1 < 0.0 {
                continue;
            }
            for y in y0..=y1 as usize {
                for x in x0..=x1 as usize {
                    let (px, py) = (x as f64, y as f64);
                    let b1 = ((px - s[0][0]) * (s[2][1] - s[0][1]) - (s[2][0] - s[0][0]) * (py - s[0][1])) / area;
                    let b2 = ((s[1][0] - s[0][0]) * (py - s[0][1]) - (px - s[0][0]) * (s[1][1] - s[0][1])) / area;
                    let b0 = 1.0 - b1 - b2;
                    if b0 < 0.0 || b1 < 0.0 || b2 < 0.0 {
                        continue;
                    }
                    let z = 1.0 / (b0 / p[0][2] + b1 / p[1][2] + b2 / p[2][2]);
                    let i = y * w + x;
                    if (z as f32) < depth[i] {
                        depth[i] = z as f32;
                        ids[i] = *id;
                        for ch in 0..3 {
                            rgb[3 * i + ch] = (col[ch] * shade * 255.0).round().clamp(0.0, 255.0) as u8;
                        }
                    }
                }
            }
        }
    }
    for d in &mut depth {
        if !d.is_finite() {
            *d = 0.0;
        }
    }
    Render { depth, ids, rgb }
}

/// The generated dataset (everything rendered up front).
pub struct ToySource {
    /// What was generated.
    pub config: ToyConfig,
    models: Vec<ModelEntry>,
    colours: Vec<[f32; 3]>,
    samples: Vec<ObjectSample>,
}

fn random_rotation(rng: &mut SeededRng) -> [[f64; 3]; 3] {
    let axis = [rng.normal(), rng.normal(), rng.normal()];
    axis_angle(axis, rng.uniform() * std::f64::consts::TAU)
}

fn transform(mesh: &TriMesh, r: &[[f64; 3]; 3], t: [f64; 3]) -> TriMesh {
    let v = mesh.vertices.iter().map(|p| std::array::from_fn(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2] + t[i])).collect();
    TriMesh { vertices: v, faces: mesh.faces.clone() }
}

impl ToySource {
    /// Renders the whole dataset up front.
    pub fn new(config: ToyConfig) -> Result<Self> {
        let mut rng = SeededRng::new(config.seed);
        let models: Vec<ModelEntry> = (0..config.models.max(1))
            .map(|i| {
                let dims = [0.04 + 0.08 * rng.uniform(), 0.04 + 0.08 * rng.uniform(), 0.04 + 0.10 * rng.uniform()];
                let offset = [0.01 * rng.normal(), 0.01 * rng.normal(), 0.01 * rng.normal()];
                ModelEntry { key: format!("toy-{i}"), mesh: Arc::new(primitive(i, dims, offset)), colors: None }
            })
            .collect();
        let colours: Vec<[f32; 3]> = models.iter().map(|_| std::array::from_fn(|_| 0.2 + 0.8 * rng.uniform() as f32)).collect();
        let k = Intrinsics {
            fx: 0.9 * config.width as f64,
            fy: 0.9 * config.width as f64,
            cx: config.width as f64 / 2.0,
            cy: config.height as f64 / 2.0,
        };
        let mut src = Self { config: config.clone(), models, colours, samples: Vec::new() };
        let mut attempts = 0;
        while src.samples.len() < config.samples {
            attempts += 1;
            if attempts > 20 * config.samples + 20 {
                return Err(recon_core::Error::msg("toy data: could not place visible objects"));
            }
            let model = rng.next_u64() as usize % src.models.len();
            let occluder = (config.occluders && rng.uniform() < 0.5).then(|| rng.next_u64() as usize % src.models.len());
            let n_views = if config.second_view { 2 } else { 1 };
            let mut views = Vec::new();
            for _ in 0..n_views {
                match src.render_view(model, occluder, &k, &mut rng)? {
                    Some(v) => views.push(v),
                    None => break,
                }
            }
            if views.len() == n_views {
                src.samples.push(ObjectSample { model, views });
            }
        }
        Ok(src)
    }

    /// Render `model` at a random pose (plus an occluder and a back plane);
    /// `None` when too little of the object is visible.
    fn render_view(&self, model: usize, occluder: Option<usize>, k: &Intrinsics, rng: &mut SeededRng) -> Result<Option<ObjectView>> {
        let (w, h) = (self.config.width, self.config.height);
        let r = random_rotation(rng);
        let z = 0.45 + 0.35 * rng.uniform();
        let t = [0.15 * z * rng.normal().clamp(-2.0, 2.0), 0.1 * z * rng.normal().clamp(-2.0, 2.0), z];
        let mut scene = vec![(transform(&self.models[model].mesh, &r, t), 1u32, self.colours[model])];
        if let Some(o) = occluder {
            // In front of the object, shifted sideways by about its size.
            let ro = random_rotation(rng);
            let side = 0.05 * if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
            let to = [t[0] + side, t[1] + 0.02 * rng.normal(), t[2] - 0.12];
            scene.push((transform(&self.models[o].mesh, &ro, to), 2, self.colours[o]));
        }
        let back = primitive(0, [2.0, 2.0, 0.01], [0.0, 0.0, 0.0]);
        scene.push((transform(&back, &[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.0, 0.0, z + 0.25]), 3, [0.55, 0.5, 0.45]));
        let img = rasterize(&scene, k, w, h);
        let mask: Vec<bool> = img.ids.iter().map(|&i| i == 1).collect();
        if mask.iter().filter(|&&m| m).count() < 150 {
            return Ok(None);
        }
        let depth_m: Vec<f32> =
            img.depth.iter().map(|&d| if d > 0.0 { d + (0.002 * (d as f64).powi(2) * rng.normal()) as f32 } else { 0.0 }).collect();
        let frame = RgbdFrame {
            width: w,
            height: h,
            rgb: img.rgb,
            depth_m,
            intrinsics: *k,
            rgb_path: format!("toy/{}/rgb.png", self.config.seed).into(),
            depth_path: "toy/depth.png".into(),
            intrinsics_source: "toy generator".into(),
            depth_scale_m: 1.0,
        };
        Ok(Some(ObjectView { frame: Arc::new(frame), mask, r, t }))
    }
}

impl TrainingSource for ToySource {
    fn describe(&self) -> String {
        let c = &self.config;
        format!("toy primitives (seed {}, {} models, {} samples, {}x{})", c.seed, self.models.len(), self.samples.len(), c.width, c.height)
    }
    fn num_models(&self) -> usize {
        self.models.len()
    }
    fn model(&self, i: usize) -> Result<ModelEntry> {
        self.models.get(i).cloned().ok_or_else(|| recon_core::Error::msg(format!("toy data: no model {i}")))
    }
    fn num_samples(&self) -> usize {
        self.samples.len()
    }
    fn sample(&self, i: usize) -> Result<ObjectSample> {
        self.samples.get(i).cloned().ok_or_else(|| recon_core::Error::msg(format!("toy data: no sample {i}")))
    }
}

/// A micro variant of an architecture file (JSON), for tests and smoke runs
/// that must take seconds: 28 px images (2×2 patches), 4³×4 latents,
/// occupancy 16³, one 32-channel flow block. Stage-2 sections are kept.
pub fn micro_architecture(arch: &serde_json::Value) -> serde_json::Value {
    let mut v = arch.clone();
    v["name"] = "recgen-micro".into();
    let d = &mut v["image_cond_model"]["args"];
    d["hidden_size"] = 32.into();
    d["num_hidden_layers"] = 1.into();
    d["num_attention_heads"] = 2.into();
    d["image_size"] = 28.into();
    let f = &mut v["ss_flow"]["args"];
    for (k, x) in [
        ("resolution", 4),
        ("in_channels", 4),
        ("out_channels", 4),
        ("model_channels", 32),
        ("cond_channels", 32),
        ("num_blocks", 1),
        ("num_heads", 2),
        ("point_embedder_out_channels", 32),
        ("mask_embedder_out_channels", 32),
    ] {
        f[k] = x.into();
    }
    v["ss_decoder"]["args"]["latent_channels"] = 4.into();
    v["ss_decoder"]["args"]["channels"] = serde_json::json!([16, 8, 8]);
    v["ss_encoder"]["args"]["latent_channels"] = 4.into();
    v["ss_encoder"]["args"]["channels"] = serde_json::json!([8, 8, 16]);
    // Stage 2 at the SS occupancy resolution (4 · 4 = 16); the mesh decoder
    // keeps 256 channels (its GroupNorm(32) runs on C/8).
    for key in ["slat_encoder", "slat_dec_mesh", "slat_dec_gs", "slat_flow"] {
        v[key]["args"]["resolution"] = 16.into();
        v[key]["args"]["num_blocks"] = 1.into();
    }
    for key in ["slat_encoder", "slat_dec_gs"] {
        v[key]["args"]["model_channels"] = 32.into();
        v[key]["args"]["num_heads"] = 2.into();
    }
    let f = &mut v["slat_flow"]["args"];
    for (k, x) in [
        ("model_channels", 32),
        ("cond_channels", 32),
        ("num_heads", 2),
        ("num_io_res_blocks", 1),
        ("point_embedder_out_channels", 32),
        ("mask_embedder_out_channels", 32),
        ("pose_embedder_out_channels", 32),
    ] {
        f[k] = x.into();
    }
    f["io_block_channels"] = serde_json::json!([16]);
    v
}

#[cfg(test)]
mod tests {
    use super::*;
    use recon_core::geometry::pointmap::backproject;

    /// Rendered depth back-projects onto the posed mesh surface, and the
    /// ground-truth pose maps the mesh onto the observed points.
    #[test]
    fn render_is_consistent_with_pose_and_intrinsics() -> Result<()> {
        let src = ToySource::new(ToyConfig { occluders: false, samples: 3, ..Default::default() })?;
        for i in 0..src.num_samples() {
            let s = src.sample(i)?;
            let v = &s.views[0];
            let mesh = transform(&src.model(s.model)?.mesh, &v.r, v.t);
            let f = &v.frame;
            let pts = backproject(&f.depth_m, f.width, f.height, &f.intrinsics)?;
            // Every masked point lies within noise of the posed mesh (all
            // primitives are convex: distance to the nearest face plane that
            // the point is behind is 0 for surface points).
            let verts = mesh.used_vertices();
            let (lo, hi) = verts.iter().fold(([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]), |(mut lo, mut hi), p| {
                for a in 0..3 {
                    lo[a] = lo[a].min(p[a]);
                    hi[a] = hi[a].max(p[a]);
                }
                (lo, hi)
            });
            let n_mask = v.mask.iter().filter(|&&m| m).count();
            assert!(n_mask >= 150);
            for (p, _) in pts.iter().zip(&v.mask).filter(|(_, &m)| m) {
                for a in 0..3 {
                    assert!(p[a] > lo[a] - 0.01 && p[a] < hi[a] + 0.01, "point {p:?} outside the posed box {lo:?} {hi:?}");
                }
            }
        }
        // Determinism.
        let a = ToySource::new(ToyConfig::default())?;
        let b = ToySource::new(ToyConfig::default())?;
        assert_eq!(a.sample(5)?.views[0].frame.depth_m, b.sample(5)?.views[0].frame.depth_m);
        Ok(())
    }
}
