//! Stage-2 autoencoder training (`recon train slat-ae`): the structured-latent
//! encoder and the mesh and Gaussian decoders, supervised by what synthetic
//! objects know exactly instead of by rendering.
//!
//! Geometry of one object, in its canonical frame (`[-0.5, 0.5]³`):
//! - the active voxels: its surface voxels at the SLat resolution (the shells
//!   `recon train ss-vae --fill surface` teaches stage 1 to produce);
//! - signed distances (pseudo-normal inside test on the oriented mesh,
//!   negative inside) at the vertices of the mesh decoder's cubes, 4 per
//!   voxel side;
//! - surface samples with the mesh's vertex colours.
//!
//! Encoder input per voxel: the signed distances at its 5³ fine lattice
//! vertices (fine-voxel units, truncated at ±3, divided by 3) and the mean
//! colour of its surface samples. Decoder losses:
//! - mesh: truncated-SDF L1 on the 8 corner distances of every fine cube
//!   (inside the ±3-voxel band, and one-sided beyond it, so a far corner
//!   only has to be on the right side), colour MSE (sigmoid of the first
//!   three colour channels) at near-surface corners, small L2 on the
//!   deformation and weight channels (no supervision pulls them);
//! - Gaussians: per-voxel two-sided Chamfer between its Gaussians and the
//!   voxel's surface samples, colour of the nearest sample, opacity pushed
//!   to 1, scales towards a third of a voxel;
//! - KL of the posterior (λ 1e-6, TRELLIS's SLat VAE weight).
//!
//! Training runs on random crops (all active voxels within a cube of
//! `crop` voxels around a random one, absolute coordinates kept), which
//! the local decoders (shifted-window attention, 3×3×3 convs) allow; the
//! finest level holds 64 cubes per voxel and whole objects would not fit
//! a CPU step.

use std::collections::HashMap;

use candle_core::{DType, Device, Tensor, D};
use parry3d::math::Vector;
use parry3d::query::PointQuery;
use parry3d::shape::{TriMesh as PMesh, TriMeshFlags};
use rayon::prelude::*;

use crate::data::TrainingSource;
use crate::objective::{BatchLoss, Objective, Terms};
use crate::params::ModuleParams;
use recon_core::geometry::voxelize::{voxelize, CanonicalFrame, Fill};
use recon_core::mesh::trimesh::TriMesh;
use recon_core::model::config::ModuleKey;
use recon_core::model::sparse::SparseTensor;
use recon_core::model::stage2::slat_vae::encoder::SLatEncoder;
use recon_core::model::stage2::slat_vae::flexicubes::{COLOR, CUBE_CORNERS, DEFORM, SDF, WEIGHTS};
use recon_core::model::stage2::slat_vae::gaussian::{SLatGaussianDecoder, SH_C0};
use recon_core::model::stage2::slat_vae::mesh::{subdivide_coords, SLatMeshDecoder};
use recon_core::model::Compute;
use recon_core::rng::SeededRng;
use recon_core::spatial::KdTree;
use recon_core::weights::registry;
use recon_core::{Error, Result};

/// Fine cubes per voxel side (two subdivisions of the mesh decoder).
pub const SUB: usize = 4;
/// SDF truncation, in fine voxels.
pub const BAND: f32 = 3.0;
/// Surface samples per voxel targeted by the Gaussian loss.
pub const GS_SAMPLES: usize = 8;

/// Encoder input channels: `(SUB+1)³` distances + RGB.
pub fn in_channels() -> usize {
    (SUB + 1).pow(3) + 3
}

/// Exact geometry of one object for stage-2 supervision (module docs).
pub struct SlatGeometry {
    pub res: usize,
    /// Active (surface) voxels, sorted.
    pub voxels: Vec<[i32; 3]>,
    mesh: PMesh,
    samples: Vec<[f64; 3]>,
    colours: Vec<[f32; 3]>,
    kd: KdTree,
    /// Sample indices inside each active voxel.
    by_voxel: HashMap<[i32; 3], Vec<u32>>,
}

impl SlatGeometry {
    /// `mesh` in model units with optional per-vertex colours (grey without).
    pub fn new(mesh: &TriMesh, colors: Option<&[[f32; 3]]>, res: usize, seed: u64) -> Result<Self> {
        let canon = CanonicalFrame::of(&mesh.vertices, &mesh.faces)?;
        let v: Vec<[f64; 3]> = mesh.vertices.iter().map(|p| canon.to_canonical(*p)).collect();
        let occ = voxelize(&v, &mesh.faces, res, Fill::Surface)?;
        let r = res as i32;
        let voxels: Vec<[i32; 3]> = occ
            .iter()
            .enumerate()
            .filter(|(_, &o)| o)
            .map(|(i, _)| {
                let i = i as i32;
                [i / (r * r), (i / r) % r, i % r]
            })
            .collect();
        if voxels.is_empty() {
            return Err(Error::msg("slat geometry: the mesh has no surface voxels"));
        }
        let pts: Vec<Vector> = v.iter().map(|p| Vector::new(p[0] as f32, p[1] as f32, p[2] as f32)).collect();
        let pm = PMesh::with_flags(pts, mesh.faces.clone(), TriMeshFlags::ORIENTED | TriMeshFlags::MERGE_DUPLICATE_VERTICES)
            .map_err(|e| Error::msg(format!("slat geometry: cannot build the mesh's inside test: {e:?}")))?;
        let canon_mesh = TriMesh { vertices: v, faces: mesh.faces.clone() };
        let (samples, faces) = canon_mesh.sample_surface_faces(voxels.len() * 16, seed);
        let colours: Vec<[f32; 3]> = faces
            .iter()
            .map(|&f| match (colors, mesh.faces.get(f as usize)) {
                (Some(c), Some(t)) => {
                    std::array::from_fn(|k| t.iter().map(|&i| c.get(i as usize).map_or(0.5, |c| c[k])).sum::<f32>() / 3.0)
                }
                _ => [0.5; 3],
            })
            .collect();
        let mut by_voxel: HashMap<[i32; 3], Vec<u32>> = HashMap::new();
        for (i, p) in samples.iter().enumerate() {
            let c = p.map(|x| (((x + 0.5) * res as f64).floor() as i32).clamp(0, r - 1));
            by_voxel.entry(c).or_default().push(i as u32);
        }
        let kd = KdTree::new(&samples);
        Ok(Self { res, voxels, mesh: pm, samples, colours, kd, by_voxel })
    }

    /// Signed distance (canonical units, negative inside).
    pub fn sdf(&self, p: [f32; 3]) -> f32 {
        let q = Vector::new(p[0], p[1], p[2]);
        let proj = self.mesh.project_local_point(q, false);
        let d = (proj.point - q).length();
        if proj.is_inside {
            -d
        } else {
            d
        }
    }

    /// Colour of the nearest surface sample.
    pub fn colour_at(&self, p: [f64; 3]) -> [f32; 3] {
        self.kd.nearest(&p).map_or([0.5; 3], |(i, _)| self.colours[i])
    }

    /// Signed distances at fine lattice vertices (`res·SUB` lattice), memoised.
    fn lattice_sdf(&self, cache: &mut HashMap<[i32; 3], f32>, v: [i32; 3]) -> f32 {
        let fine = (self.res * SUB) as f32;
        *cache.entry(v).or_insert_with(|| self.sdf(v.map(|x| x as f32 / fine - 0.5)))
    }

    /// Encoder input `[N, in_channels()]` of `voxels` (row-major).
    pub fn input_features(&self, voxels: &[[i32; 3]]) -> Vec<f32> {
        let fine = 1.0 / (self.res * SUB) as f32;
        let mut cache = HashMap::new();
        let mut out = Vec::with_capacity(voxels.len() * in_channels());
        let s = SUB as i32;
        for c in voxels {
            for i in 0..=s {
                for j in 0..=s {
                    for k in 0..=s {
                        let d = self.lattice_sdf(&mut cache, [c[0] * s + i, c[1] * s + j, c[2] * s + k]);
                        out.push((d / fine).clamp(-BAND, BAND) / BAND);
                    }
                }
            }
            let col = match self.by_voxel.get(c) {
                Some(ix) if !ix.is_empty() => {
                    let mut m = [0f32; 3];
                    for &i in ix {
                        for a in 0..3 {
                            m[a] += self.colours[i as usize][a] / ix.len() as f32;
                        }
                    }
                    m
                }
                _ => self.colour_at(voxel_centre(*c, self.res)),
            };
            out.extend_from_slice(&col);
        }
        out
    }

    /// The active voxels within a cube of side `crop` around a random one
    /// (all of them when `crop` is 0 or covers the grid), nearest first
    /// when more than `max` remain.
    pub fn crop(&self, rng: &mut SeededRng, crop: usize, max: usize) -> Vec<[i32; 3]> {
        if crop == 0 || crop >= self.res {
            return self.voxels.clone();
        }
        let c = self.voxels[(rng.next_u64() % self.voxels.len() as u64) as usize];
        let half = crop as i32 / 2;
        let mut sel: Vec<[i32; 3]> = self.voxels.iter().copied().filter(|v| (0..3).all(|a| (v[a] - c[a]).abs() <= half)).collect();
        if sel.len() > max {
            let d2 = |v: &[i32; 3]| (0..3).map(|a| (v[a] - c[a]).pow(2)).sum::<i32>();
            sel.sort_by_key(|v| (d2(v), *v));
            sel.truncate(max);
            sel.sort();
        }
        sel
    }
}

fn voxel_centre(c: [i32; 3], res: usize) -> [f64; 3] {
    c.map(|x| (x as f64 + 0.5) / res as f64 - 0.5)
}

/// Supervision of one crop, in the decoders' row orders.
struct CropTargets {
    voxels: Vec<[i32; 3]>,
    feats: Vec<f32>,
    /// `[64·N, 8]` corner SDF (canonical units, truncated at ±BAND fine voxels).
    cube_sdf: Vec<f32>,
    /// `[64·N, 8, 3]` colour at the corners (only near-surface ones count).
    cube_col: Vec<f32>,
    /// `[N, GS_SAMPLES, 3]` surface samples in the Gaussians' `[0, 1]³` frame.
    gs_pts: Vec<f32>,
    gs_col: Vec<f32>,
    /// `[N]` 1 where the voxel holds surface samples.
    gs_valid: Vec<f32>,
}

fn crop_targets(g: &SlatGeometry, voxels: Vec<[i32; 3]>) -> CropTargets {
    let feats = g.input_features(&voxels);
    let b0: Vec<[i32; 4]> = voxels.iter().map(|v| [0, v[0], v[1], v[2]]).collect();
    let fine_cubes = subdivide_coords(&subdivide_coords(&b0));
    let fine = 1.0 / (g.res * SUB) as f32;
    let tau = BAND * fine;
    let mut cache = HashMap::new();
    let mut cube_sdf = Vec::with_capacity(fine_cubes.len() * 8);
    let mut cube_col = Vec::with_capacity(fine_cubes.len() * 24);
    for c in &fine_cubes {
        for o in CUBE_CORNERS {
            let v = [c[1] + o[0] as i32, c[2] + o[1] as i32, c[3] + o[2] as i32];
            let d = g.lattice_sdf(&mut cache, v);
            cube_sdf.push(d.clamp(-tau, tau));
            let col = if d.abs() < tau { g.colour_at(v.map(|x| (x as f32 * fine - 0.5) as f64)) } else { [0.0; 3] };
            cube_col.extend_from_slice(&col);
        }
    }
    let mut gs_pts = Vec::with_capacity(voxels.len() * GS_SAMPLES * 3);
    let mut gs_col = Vec::with_capacity(voxels.len() * GS_SAMPLES * 3);
    let mut gs_valid = Vec::with_capacity(voxels.len());
    for v in &voxels {
        let ix = g.by_voxel.get(v).map(Vec::as_slice).unwrap_or(&[]);
        gs_valid.push(if ix.is_empty() { 0.0 } else { 1.0 });
        for k in 0..GS_SAMPLES {
            let (p, c) = if ix.is_empty() {
                (voxel_centre(*v, g.res), [0.5; 3])
            } else {
                // Evenly spaced through the (randomly ordered) samples, cyclic when few.
                let i = ix[(k * ix.len() / GS_SAMPLES).min(ix.len() - 1)] as usize;
                (g.samples[i], g.colours[i])
            };
            gs_pts.extend(p.iter().map(|x| (x + 0.5) as f32));
            gs_col.extend_from_slice(&c);
        }
    }
    CropTargets { voxels, feats, cube_sdf, cube_col, gs_pts, gs_col, gs_valid }
}

/// Loss weights of the autoencoder.
#[derive(Debug, Clone, serde::Serialize)]
pub struct SlatAeWeights {
    pub color: f64,
    pub reg: f64,
    pub gs_xyz: f64,
    pub gs_color: f64,
    pub gs_opacity: f64,
    pub gs_scale: f64,
    pub kl: f64,
}

impl Default for SlatAeWeights {
    fn default() -> Self {
        Self { color: 1.0, reg: 1e-3, gs_xyz: 1.0, gs_color: 1.0, gs_opacity: 0.1, gs_scale: 0.1, kl: 1e-6 }
    }
}

/// SLat encoder → posterior sample → mesh decoder + Gaussian decoder.
pub struct SlatAeObjective<'a> {
    params: Vec<ModuleParams>,
    enc: SLatEncoder,
    mesh_dec: SLatMeshDecoder,
    gs_dec: SLatGaussianDecoder,
    source: &'a dyn TrainingSource,
    pub res: usize,
    /// Crop side in voxels (0: whole objects).
    pub crop: usize,
    /// Most voxels per crop.
    pub max_voxels: usize,
    pub weights: SlatAeWeights,
}

impl<'a> SlatAeObjective<'a> {
    pub fn new(source: &'a dyn TrainingSource, enc: ModuleParams, mesh_dec: ModuleParams, gs_dec: ModuleParams) -> Result<Self> {
        let e = registry::build_slat_encoder(&enc.args, enc.var_builder(), enc.key.name(), Compute::Plain)?;
        let m = registry::build_mesh_decoder(&mesh_dec.args, mesh_dec.var_builder(), mesh_dec.key.name(), Compute::Plain)?;
        let g = registry::build_gaussian_decoder(&gs_dec.args, gs_dec.var_builder(), gs_dec.key.name(), Compute::Plain)?;
        let in_ch = e.trunk.cfg.in_channels;
        if in_ch != in_channels() {
            return Err(Error::config(
                ModuleKey::SlatEncoder.name(),
                "in_channels",
                format!("{in_ch}; the geometry features have {}", in_channels()),
            ));
        }
        for (name, lc) in [(ModuleKey::SlatDecMesh.name(), m.trunk.cfg.in_channels), (ModuleKey::SlatDecGs.name(), g.trunk.cfg.in_channels)]
        {
            if lc != e.latent_channels {
                return Err(Error::config(name, "latent_channels", format!("{lc} differs from the encoder's {}", e.latent_channels)));
            }
        }
        if g.cfg.resolution != m.resolution {
            return Err(Error::config(
                ModuleKey::SlatDecGs.name(),
                "resolution",
                format!("{} differs from the mesh decoder's {}", g.cfg.resolution, m.resolution),
            ));
        }
        let res = m.resolution;
        Ok(Self {
            params: vec![enc, mesh_dec, gs_dec],
            enc: e,
            mesh_dec: m,
            gs_dec: g,
            source,
            res,
            crop: 10,
            max_voxels: 400,
            weights: SlatAeWeights::default(),
        })
    }

    /// The geometry of model `i` (built on demand: a few tens of ms).
    pub fn geometry(&self, i: usize, seed: u64) -> Result<SlatGeometry> {
        let m = self.source.model(i)?;
        SlatGeometry::new(&m.mesh, m.colors.as_deref().map(Vec::as_slice), self.res, seed)
    }
}

fn softplus(x: &Tensor) -> Result<Tensor> {
    Ok((x.relu()? + (x.abs()?.neg()?.exp()? + 1.0)?.log()?)?)
}

impl Objective for SlatAeObjective<'_> {
    fn name(&self) -> &'static str {
        "slat-ae"
    }
    fn trainable(&self) -> &[ModuleParams] {
        &self.params
    }
    fn loss(&self, rng: &mut SeededRng, batch: usize) -> Result<BatchLoss> {
        let dev = Device::Cpu;
        let picks: Vec<(usize, u64)> =
            (0..batch).map(|_| ((rng.next_u64() % self.source.num_models() as u64) as usize, rng.next_u64())).collect();
        let crops: Vec<CropTargets> = picks
            .par_iter()
            .map(|&(i, seed)| {
                let g = self.geometry(i, seed)?;
                let mut r = SeededRng::new(seed ^ 0xC40B);
                Ok(crop_targets(&g, g.crop(&mut r, self.crop, self.max_voxels)))
            })
            .collect::<Result<_>>()?;
        let b = crops.len();
        let mut coords = Vec::new();
        let cat = |f: &dyn Fn(&CropTargets) -> &Vec<f32>| -> Vec<f32> { crops.iter().flat_map(|c| f(c).iter().copied()).collect() };
        for (bi, c) in crops.iter().enumerate() {
            coords.extend(c.voxels.iter().map(|v| [bi as i32, v[0], v[1], v[2]]));
        }
        let n = coords.len();
        let feats = Tensor::from_vec(cat(&|c| &c.feats), (n, in_channels()), &dev)?;
        let x = SparseTensor::new(coords, feats, b)?;
        // Encode, sample the posterior.
        let post = self.enc.forward(&x)?;
        let eps = rng.randn(post.mean.dims(), &dev)?;
        let z = (&post.mean + ((&post.logvar * 0.5)?.exp()? * eps)?)?;
        let kl = ((post.mean.sqr()? + post.logvar.exp()?)? - &post.logvar)?.affine(0.5, -0.5)?.mean_all()?;
        let zx = x.with_feats(z)?;

        // Mesh decoder: per fine cube, 8 corner distances + colours.
        let out = self.mesh_dec.forward_feats(&zx, &mut |_, _| {})?.feats;
        let m = out.dim(0)?;
        let fine = 1.0 / (self.res * SUB) as f64;
        let tau = BAND as f64 * fine;
        let t = Tensor::from_vec(cat(&|c| &c.cube_sdf), (m, 8), &dev)?;
        let p = (out.narrow(1, SDF.start, 8)? - fine)?; // upstream's sdf bias −1/R
        let inband = t.abs()?.lt(tau * (1.0 - 1e-6))?.to_dtype(DType::F32)?;
        let pos = t.ge(tau * (1.0 - 1e-6))?.to_dtype(DType::F32)?;
        let neg = t.le(-tau * (1.0 - 1e-6))?.to_dtype(DType::F32)?;
        let diff = (&p - &t)?;
        let l_sdf = ((inband.mul(&diff.abs()?)? + pos.mul(&diff.neg()?.relu()?)?)? + neg.mul(&diff.relu()?)?)?
            .mean_all()?
            .affine(1.0 / fine, 0.0)?;
        let near_n = crate::objective::scalar_of(&inband.sum_all()?)?;
        let col = candle_nn::ops::sigmoid(&out.narrow(1, COLOR.start, 48)?.reshape((m, 8, 6))?.narrow(2, 0, 3)?)?;
        let col_t = Tensor::from_vec(cat(&|c| &c.cube_col), (m, 8, 3), &dev)?;
        let l_col = ((col - col_t)?.sqr()?.broadcast_mul(&inband.unsqueeze(2)?)?.sum_all()? / (3.0 * near_n.max(1.0)))?;
        let reg = (out.narrow(1, DEFORM.start, DEFORM.len())?.sqr()?.mean_all()?
            + out.narrow(1, WEIGHTS.start, WEIGHTS.len())?.sqr()?.mean_all()?)?;
        // Sign accuracy at near-surface corners (logged).
        let sign_ok =
            crate::objective::scalar_of(&p.ge(0.0)?.eq(&t.ge(0.0)?)?.to_dtype(DType::F32)?.mul(&inband)?.sum_all()?)? / near_n.max(1.0);

        // Gaussian decoder: per voxel, its Gaussians against its surface samples.
        let h = self.gs_dec.forward_feats(&zx, &mut |_, _| {})?;
        let reps = self.gs_dec.to_representation(&zx, &h)?;
        let gk = self.gs_dec.cfg.num_gaussians;
        let xyz = Tensor::cat(&reps.iter().map(|r| r.xyz.clone()).collect::<Vec<_>>(), 0)?.reshape((n, gk, 3))?;
        let dc = Tensor::cat(&reps.iter().map(|r| r.features_dc.clone()).collect::<Vec<_>>(), 0)?.reshape((n, gk, 3))?;
        let opa = Tensor::cat(&reps.iter().map(|r| r.opacity.clone()).collect::<Vec<_>>(), 0)?;
        let scale = Tensor::cat(&reps.iter().map(|r| r.get_scaling()).collect::<Result<Vec<_>>>()?, 0)?;
        let tp = Tensor::from_vec(cat(&|c| &c.gs_pts), (n, GS_SAMPLES, 3), &dev)?;
        let tc = Tensor::from_vec(cat(&|c| &c.gs_col), (n, GS_SAMPLES, 3), &dev)?;
        let valid = Tensor::from_vec(cat(&|c| &c.gs_valid), n, &dev)?;
        let n_valid = crate::objective::scalar_of(&valid.sum_all()?)?.max(1.0);
        let vox2 = (1.0 / self.res as f64).powi(2);
        let d = xyz.unsqueeze(2)?.broadcast_sub(&tp.unsqueeze(1)?)?.sqr()?.sum(D::Minus1)?.affine(1.0 / vox2, 0.0)?; // [n, G, K]
        let chamfer = (d.min(2)?.mean(1)? + d.min(1)?.mean(1)?)?;
        let l_gs = (chamfer.mul(&valid)?.sum_all()? / n_valid)?;
        let nearest = d.detach().argmin(2)?; // [n, G]
        let tc_g = tc.gather(&nearest.unsqueeze(2)?.broadcast_as((n, gk, 3))?.contiguous()?, 1)?;
        let rgb = dc.affine(SH_C0 as f64, 0.5)?;
        let l_gs_col = ((rgb - tc_g)?.sqr()?.mean(2)?.mean(1)?.mul(&valid)?.sum_all()? / n_valid)?;
        let ob = self.gs_dec.cfg.opacity_bias;
        let l_op = softplus(&(opa + (ob / (1.0 - ob)).ln())?.neg()?)?.mean_all()?;
        let s0 = (1.0 / (3.0 * self.res as f64)).ln();
        let l_scale = scale.log()?.affine(1.0, -s0)?.sqr()?.mean_all()?;

        let w = &self.weights;
        let total = [
            (&l_sdf, 1.0),
            (&l_col, w.color),
            (&reg, w.reg),
            (&l_gs, w.gs_xyz),
            (&l_gs_col, w.gs_color),
            (&l_op, w.gs_opacity),
            (&l_scale, w.gs_scale),
            (&kl, w.kl),
        ]
        .into_iter()
        .try_fold(Tensor::zeros((), DType::F32, &dev)?, |acc, (l, k)| acc + (l * k)?)?;
        let s = crate::objective::scalar_of;
        let terms: Terms = [
            ("sdf".to_string(), s(&l_sdf)?),
            ("color".to_string(), s(&l_col)?),
            ("gs_xyz".to_string(), s(&l_gs)?),
            ("gs_color".to_string(), s(&l_gs_col)?),
            ("kl".to_string(), s(&kl)?),
        ]
        .into();
        let info: Terms = [
            ("voxels".to_string(), n as f64),
            ("sign_acc".to_string(), sign_ok),
            ("gs_opacity".to_string(), s(&l_op)?),
            ("gs_scale".to_string(), s(&l_scale)?),
        ]
        .into();
        Ok(BatchLoss { total, terms, info })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toy::primitive;

    /// Signed distances of a box are exact in its canonical frame: negative
    /// inside, the distance to the nearest face, positive outside; the
    /// active voxels are the surface shell and every one holds samples.
    #[test]
    fn geometry_of_a_box_is_exact() -> Result<()> {
        // primitive 0 is a box: 0.1 × 0.05 × 0.04 m, so the canonical box is 1 × 0.5 × 0.4.
        let mesh = primitive(0, [0.1, 0.05, 0.04], [0.0; 3]);
        let canon = CanonicalFrame::of(&mesh.vertices, &mesh.faces)?;
        let g = SlatGeometry::new(&mesh, None, 16, 1)?;
        let lo: [f64; 3] = std::array::from_fn(|a| mesh.vertices.iter().map(|p| canon.to_canonical(*p)[a]).fold(f64::INFINITY, f64::min));
        let half: [f32; 3] = lo.map(|x| -x as f32);
        assert!((half[0] - 0.5).abs() < 1e-6, "{half:?}");
        let exact = |p: [f32; 3]| {
            let q: [f32; 3] = std::array::from_fn(|a| p[a].abs() - half[a]);
            let outside = q.iter().map(|x| x.max(0.0).powi(2)).sum::<f32>().sqrt();
            outside + q.iter().copied().fold(f32::NEG_INFINITY, f32::max).min(0.0)
        };
        for p in [[0.0, 0.0, 0.0], [0.1, 0.05, -0.02], [0.45, 0.0, 0.0], [0.6, 0.1, 0.0], [0.3, 0.4, 0.35], [-0.2, -0.1, 0.19]] {
            assert!((g.sdf(p) - exact(p)).abs() < 1e-5, "{p:?}: {} vs {}", g.sdf(p), exact(p));
        }
        assert!(g.sdf([0.0; 3]) < 0.0 && g.sdf([0.0, 0.0, 0.45]) > 0.0);
        // Shell voxels only: none deep inside.
        assert!(g.voxels.iter().all(|v| exact(voxel_centre(*v, 16).map(|x| x as f32)) > -1.0 / 16.0));
        let feats = g.input_features(&g.voxels[..3]);
        assert_eq!(feats.len(), 3 * in_channels());
        assert!(feats.iter().all(|x| x.is_finite() && (-1.0..=1.0).contains(x)));
        assert!(g.voxels.iter().filter(|v| g.by_voxel.contains_key(*v)).count() * 10 >= g.voxels.len() * 9);
        Ok(())
    }

    #[test]
    fn crop_targets_follow_the_decoder_row_order() -> Result<()> {
        let mesh = primitive(1, [0.06, 0.06, 0.08], [0.0; 3]);
        let g = SlatGeometry::new(&mesh, None, 16, 2)?;
        let mut rng = SeededRng::new(3);
        let crop = g.crop(&mut rng, 4, 10);
        assert!(!crop.is_empty() && crop.len() <= 10);
        let t = crop_targets(&g, crop.clone());
        assert_eq!(t.cube_sdf.len(), crop.len() * 64 * 8);
        // Cube row 0 is the first child of the first child of voxel 0: its
        // corner 0 is the voxel's lowest lattice vertex.
        let fine = 1.0 / 64.0;
        let v0 = crop[0].map(|x| (x * 4) as f32 * fine - 0.5);
        let tau = BAND * fine;
        assert!((t.cube_sdf[0] - g.sdf(v0).clamp(-tau, tau)).abs() < 1e-6);
        // Row 63 (last grandchild) has its corner 7 at the voxel's highest vertex.
        let v1 = crop[0].map(|x| (x * 4 + 4) as f32 * fine - 0.5);
        assert!((t.cube_sdf[63 * 8 + 7] - g.sdf(v1).clamp(-tau, tau)).abs() < 1e-6);
        assert!(t.gs_pts.iter().all(|x| (0.0..=1.0).contains(x)));
        Ok(())
    }
}
