//! Structured-latent Gaussian decoder (TRELLIS `SLatGaussianDecoder`) and the
//! 3D Gaussian representation it produces (`representations/gaussian`).
//!
//! Trunk → plain LayerNorm (eps 1e-5) → linear to `14·G` channels per voxel,
//! split as `_xyz (G,3) | _features_dc (G,1,3) | _scaling (G,3) |
//! _rotation (G,4) | _opacity (G,1)`. Positions are voxel centres plus a
//! tanh-bounded offset (with a fixed quasi-random per-Gaussian perturbation).

use crate::model::nn::common::Linear;
use crate::model::nn::common::{layer_norm_plain, linear};
use crate::model::nn::fast::Compute;
use crate::model::sparse::SparseTensor;
use crate::model::stage2::slat_vae::trunk::{SparseTransformerBase, TrunkArgs, TrunkConfig};
use crate::Result;
use candle_core::{DType, Device, Module, Tensor, D};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

pub use crate::gaussians::SH_C0;

/// Resolved settings of the Gaussian representation (from a [`GaussianDecoderConfig`]).
#[derive(Debug, Clone)]
pub struct GaussianConfig {
    /// Side of the decoder's voxel grid.
    pub resolution: usize,
    /// Gaussians per voxel, `G`.
    pub num_gaussians: usize,
    /// Offset range: Gaussians lie within `voxel_size / 2` voxel widths of their voxel centre, per axis.
    pub voxel_size: f64,
    /// Add the fixed [`offset_perturbation`] to the raw offsets.
    pub perturb_offset: bool,
    /// Per-field learning-rate multipliers, order: xyz, features_dc, scaling, rotation, opacity.
    pub lr: [f64; 5],
    /// `3d_filter_kernel_size` (minimum kernel size).
    pub min_kernel_size: f64,
    /// Activated scale at raw 0, before the `min_kernel_size` floor.
    pub scaling_bias: f64,
    /// Opacity at raw 0.
    pub opacity_bias: f64,
    /// `softplus` (true) or `exp` (false) scaling activation.
    pub softplus_scaling: bool,
}

/// Constructor args of `SLatGaussianDecoder` (checkpoint `args`): the trunk's
/// plus `resolution` and `representation_config`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GaussianDecoderConfig {
    /// The trunk's args (flattened).
    #[serde(flatten)]
    pub trunk: TrunkArgs,
    /// Side of the latent voxel grid (upstream `resolution`).
    pub resolution: usize,
    /// Representation settings (upstream `representation_config`).
    pub representation_config: GaussianRepresentationConfig,
}

/// `representation_config` of the Gaussian decoder; absent keys take
/// upstream's defaults, unknown ones (`2d_filter_kernel_size`) are ignored.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct GaussianRepresentationConfig {
    /// Gaussians per voxel (upstream `num_gaussians`, default 32).
    #[serde(default = "default_num_gaussians")]
    pub num_gaussians: usize,
    /// Offset range in voxel widths (upstream `voxel_size`, default 1.5).
    #[serde(default = "default_voxel_size")]
    pub voxel_size: f64,
    /// Add the fixed offset perturbation (upstream `perturb_offset`, default false).
    #[serde(default)]
    pub perturb_offset: bool,
    /// Per-field multipliers of the network output (upstream `lr`).
    #[serde(default)]
    pub lr: GaussianLr,
    /// Minimum Gaussian scale, added in quadrature (upstream `3d_filter_kernel_size`, default 0).
    #[serde(rename = "3d_filter_kernel_size", default)]
    pub filter_3d_kernel_size: f64,
    /// Activated scale at raw 0 (upstream `scaling_bias`, default 0.01).
    #[serde(default = "default_scaling_bias")]
    pub scaling_bias: f64,
    /// Opacity at raw 0 (upstream `opacity_bias`, default 0.1).
    #[serde(default = "default_opacity_bias")]
    pub opacity_bias: f64,
    /// Scale activation (upstream `scaling_activation`, default `exp`).
    #[serde(default)]
    pub scaling_activation: ScalingActivation,
}

/// Per-field learning-rate multipliers (default 1 each).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GaussianLr {
    /// Multiplier of the raw position offsets (`_xyz`).
    #[serde(rename = "_xyz", default = "one")]
    pub xyz: f64,
    /// Multiplier of the SH degree-0 coefficients (`_features_dc`).
    #[serde(rename = "_features_dc", default = "one")]
    pub features_dc: f64,
    /// Multiplier of the raw scales (`_scaling`).
    #[serde(rename = "_scaling", default = "one")]
    pub scaling: f64,
    /// Multiplier of the raw quaternions (`_rotation`).
    #[serde(rename = "_rotation", default = "one")]
    pub rotation: f64,
    /// Multiplier of the raw opacities (`_opacity`).
    #[serde(rename = "_opacity", default = "one")]
    pub opacity: f64,
}

impl Default for GaussianLr {
    fn default() -> Self {
        Self { xyz: 1.0, features_dc: 1.0, scaling: 1.0, rotation: 1.0, opacity: 1.0 }
    }
}

/// Activation from raw to actual Gaussian scales (upstream `scaling_activation`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ScalingActivation {
    /// `exp(raw + ln(scaling_bias))`.
    #[default]
    Exp,
    /// `softplus(raw + softplus⁻¹(scaling_bias))`.
    Softplus,
}

fn default_num_gaussians() -> usize {
    32
}
fn default_voxel_size() -> f64 {
    1.5
}
fn default_scaling_bias() -> f64 {
    0.01
}
fn default_opacity_bias() -> f64 {
    0.1
}
fn one() -> f64 {
    1.0
}

impl GaussianDecoderConfig {
    /// Parse the decoder's `args`; errors name `file` and the field.
    pub fn from_json(v: &serde_json::Value, file: &str) -> Result<Self> {
        crate::model::stage2::slat_vae::trunk::from_json_with_trunk(v, file)
    }
}

impl GaussianConfig {
    /// The representation settings of a decoder config.
    pub fn new(cfg: &GaussianDecoderConfig) -> Self {
        let rc = &cfg.representation_config;
        let lr = rc.lr;
        Self {
            resolution: cfg.resolution,
            num_gaussians: rc.num_gaussians,
            voxel_size: rc.voxel_size,
            perturb_offset: rc.perturb_offset,
            lr: [lr.xyz, lr.features_dc, lr.scaling, lr.rotation, lr.opacity],
            min_kernel_size: rc.filter_3d_kernel_size,
            scaling_bias: rc.scaling_bias,
            opacity_bias: rc.opacity_bias,
            softplus_scaling: rc.scaling_activation == ScalingActivation::Softplus,
        }
    }

    /// Channels of the output layer: G·(3 + 3 + 3 + 4 + 1).
    pub fn out_channels(&self) -> usize {
        self.num_gaussians * 14
    }
}

fn radical_inverse(base: u64, mut n: u64) -> f64 {
    let inv = 1.0 / base as f64;
    let (mut val, mut f) = (0.0, inv);
    while n > 0 {
        val += (n % base) as f64 * f;
        n /= base;
        f *= inv;
    }
    val
}

/// Upstream's deterministic offset perturbation `[G, 3]`: Hammersley points
/// `(i/G, φ2(i), φ3(i))` mapped through `atanh((2h - 1)/voxel_size)`, so that
/// `tanh(perturbation)·voxel_size/2` spreads the Gaussians over the voxel.
pub fn offset_perturbation(num_gaussians: usize, voxel_size: f64, device: &Device) -> Result<Tensor> {
    let mut v = Vec::with_capacity(num_gaussians * 3);
    for i in 0..num_gaussians {
        let h = [i as f64 / num_gaussians as f64, radical_inverse(2, i as u64), radical_inverse(3, i as u64)];
        v.extend(h.iter().map(|&h| (((h * 2.0 - 1.0) / voxel_size).atanh()) as f32));
    }
    Ok(Tensor::from_vec(v, (num_gaussians, 3), device)?)
}

/// One batch item's Gaussians as stored upstream: raw (pre-activation)
/// parameters, plus the activations of `Gaussian.get_*`.
#[derive(Debug, Clone)]
pub struct GaussianModel {
    /// `[M, 3]` positions in the unit cube [0, 1]³ (aabb-normalised).
    pub xyz: Tensor,
    /// `[M, 1, 3]` SH degree-0 coefficients.
    pub features_dc: Tensor,
    /// `[M, 3]` raw scales.
    pub scaling: Tensor,
    /// `[M, 4]` raw quaternions (wxyz) before the identity bias.
    pub rotation: Tensor,
    /// `[M, 1]` raw opacity.
    pub opacity: Tensor,
    cfg: GaussianConfig,
}

impl GaussianModel {
    /// World positions: aabb `[-0.5, -0.5, -0.5, 1, 1, 1]` → `xyz·1 - 0.5`.
    pub fn get_xyz(&self) -> Result<Tensor> {
        Ok((&self.xyz - 0.5)?)
    }

    /// Activated scales `[M, 3]`: `sqrt(act(raw + bias)² + min_kernel_size²)`.
    pub fn get_scaling(&self) -> Result<Tensor> {
        let c = &self.cfg;
        let s = if c.softplus_scaling {
            // inverse softplus of the bias: y + log(-expm1(-y))
            let y = c.scaling_bias;
            let bias = y + (-(-y).exp_m1()).ln();
            softplus(&(&self.scaling + bias)?)?
        } else {
            (&self.scaling + c.scaling_bias.ln())?.exp()?
        };
        Ok((s.sqr()? + c.min_kernel_size * c.min_kernel_size)?.sqrt()?)
    }

    /// Opacities `[M, 1]` in (0, 1): `sigmoid(raw + logit(opacity_bias))`.
    pub fn get_opacity(&self) -> Result<Tensor> {
        let p = self.cfg.opacity_bias;
        let bias = (p / (1.0 - p)).ln();
        Ok(candle_nn::ops::sigmoid(&(&self.opacity + bias)?)?)
    }

    /// Unit quaternions (wxyz): normalize(raw + [1, 0, 0, 0]), norm clamped at 1e-12.
    pub fn get_rotation(&self) -> Result<Tensor> {
        let bias = Tensor::new(&[1f32, 0., 0., 0.], self.rotation.device())?.to_dtype(self.rotation.dtype())?;
        let r = self.rotation.broadcast_add(&bias)?;
        let n = r.sqr()?.sum_keepdim(D::Minus1)?.sqrt()?.clamp(1e-12, f64::INFINITY)?;
        Ok(r.broadcast_div(&n)?)
    }

    /// Plain activated splats (positions in the decoder's object frame,
    /// [-0.5, 0.5]³ z-up) for export and rendering.
    pub fn to_gaussians(&self) -> Result<Gaussians> {
        let rows3 = |t: Tensor| -> Result<Vec<[f32; 3]>> {
            Ok(t.to_dtype(DType::F32)?.to_vec2::<f32>()?.into_iter().map(|r| [r[0], r[1], r[2]]).collect())
        };
        let m = self.xyz.dim(0)?;
        Ok(Gaussians {
            positions: rows3(self.get_xyz()?)?,
            scales: rows3(self.get_scaling()?)?,
            rotations: self.get_rotation()?.to_dtype(DType::F32)?.to_vec2::<f32>()?.into_iter().map(|r| [r[0], r[1], r[2], r[3]]).collect(),
            opacities: self.get_opacity()?.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?,
            dc: rows3(self.features_dc.reshape((m, 3))?)?,
        })
    }
}

/// softplus(x) = log(1 + eˣ), computed stably (torch uses x itself above 20).
fn softplus(x: &Tensor) -> Result<Tensor> {
    // max(x, 0) + log1p(exp(-|x|)) per element with std's ln_1p: candle has no log1p, and
    // ln(1 + u) loses ~1e-5 relative in f32 where the scaling bias puts x (≈ -5.5, u ≈ 4e-3);
    // the full-size Gaussian decoder check found it (docs/conformance.md).
    let v = x.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    let y: Vec<f64> = v.iter().map(|&x| x.max(0.0) + (-x.abs()).exp().ln_1p()).collect();
    Ok(Tensor::from_vec(y, x.shape(), x.device())?.to_dtype(x.dtype())?)
}

/// Base colour of an SH degree-0 coefficient: `C0·dc + 0.5`, clamped at 0
/// like the rasteriser.
pub fn sh0_to_rgb(dc: [f32; 3]) -> [f32; 3] {
    dc.map(|d| (SH_C0 * d + 0.5).max(0.0))
}

/// The activated Gaussians are the export type (one struct for decoder
/// output, transforms and the splat PLY writer).
pub use crate::gaussians::Gaussians;

/// The structured-latent Gaussian decoder (TRELLIS `SLatGaussianDecoder`).
pub struct SLatGaussianDecoder {
    /// The sparse transformer trunk.
    pub trunk: SparseTransformerBase,
    out_layer: Linear,
    offset_perturbation: Tensor,
    /// Representation settings.
    pub cfg: GaussianConfig,
}

impl SLatGaussianDecoder {
    /// Built from its config (upstream's args: trunk + `representation_config`).
    pub fn new(args: &GaussianDecoderConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let tcfg = TrunkConfig::new(&args.trunk)?;
        let cfg = GaussianConfig::new(args);
        let trunk = SparseTransformerBase::new(&tcfg, vb.clone(), compute)?;
        let out_layer = linear(tcfg.model_channels, cfg.out_channels(), vb.pp("out_layer"), compute)?;
        // The buffer ships in checkpoints; recompute it when absent.
        let offset_perturbation = if vb.contains_tensor("offset_perturbation") {
            vb.get((cfg.num_gaussians, 3), "offset_perturbation")?
        } else {
            offset_perturbation(cfg.num_gaussians, cfg.voxel_size, vb.device())?.to_dtype(vb.dtype())?
        };
        Ok(Self { trunk, out_layer, offset_perturbation, cfg })
    }

    /// Per-voxel output features `[N, 14·G]`; `tap` sees the trunk taps and `out_layer`.
    pub fn forward_feats(&self, x: &SparseTensor, tap: &mut dyn FnMut(&str, &Tensor)) -> Result<Tensor> {
        let h = self.trunk.forward_with(x, tap)?;
        let h = layer_norm_plain(&h, 1e-5)?;
        let h = self.out_layer.forward(&h)?;
        tap("out_layer", &h);
        Ok(h)
    }

    /// The output linear alone (after the trunk and its final LayerNorm).
    pub fn out_layer_forward(&self, h: &Tensor) -> Result<Tensor> {
        Ok(self.out_layer.forward(h)?)
    }

    /// Split network output into one Gaussian model per batch item.
    pub fn to_representation(&self, x: &SparseTensor, feats: &Tensor) -> Result<Vec<GaussianModel>> {
        let c = &self.cfg;
        let g = c.num_gaussians;
        let res = c.resolution as f64;
        let mut reps = Vec::with_capacity(x.batch_size);
        for range in x.batch_ranges() {
            let n = range.len();
            let f = feats.narrow(0, range.start, n)?;
            let field = |start: usize, width: usize, lr: f64| -> Result<Tensor> {
                Ok((f.narrow(1, start * g, width * g)?.reshape((n, g, width))? * lr)?)
            };
            let mut off = field(0, 3, c.lr[0])?;
            if c.perturb_offset {
                off = off.broadcast_add(&self.offset_perturbation.unsqueeze(0)?)?;
            }
            let off = (off.tanh()? * (0.5 * c.voxel_size / res))?;
            let centres: Vec<f32> =
                x.coords[range.clone()].iter().flat_map(|cc| [1, 2, 3].map(|a| ((cc[a] as f64 + 0.5) / res) as f32)).collect();
            let centres = Tensor::from_vec(centres, (n, 1, 3), feats.device())?.to_dtype(feats.dtype())?;
            let xyz = centres.broadcast_add(&off)?.reshape((n * g, 3))?;
            reps.push(GaussianModel {
                xyz,
                features_dc: field(3, 3, c.lr[1])?.reshape((n * g, 1, 3))?,
                scaling: field(6, 3, c.lr[2])?.reshape((n * g, 3))?,
                rotation: field(9, 4, c.lr[3])?.reshape((n * g, 4))?,
                opacity: field(13, 1, c.lr[4])?.reshape((n * g, 1))?,
                cfg: c.clone(),
            });
        }
        Ok(reps)
    }

    /// One Gaussian model per batch item of the latents `x` (feats `[N, latent_channels]`).
    pub fn forward(&self, x: &SparseTensor) -> Result<Vec<GaussianModel>> {
        let h = self.forward_feats(x, &mut |_, _| {})?;
        self.to_representation(x, &h)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sh0_to_rgb_values() {
        assert_eq!(sh0_to_rgb([0.0, -10.0, 1.0]), [0.5, 0.0, SH_C0 + 0.5]);
    }

    #[test]
    fn radical_inverse_values() {
        assert_eq!(radical_inverse(2, 1), 0.5);
        assert_eq!(radical_inverse(2, 6), 0.375); // 110b → 0.011b
        assert!((radical_inverse(3, 5) - (2.0 / 3.0 + 1.0 / 9.0)).abs() < 1e-12);
        // 12₃ → 0.21₃
    }

    #[test]
    fn softplus_matches_definition() -> Result<()> {
        let xs = [-30f32, -8.0, -5.5, -1.0, 0.0, 2.0, 40.0];
        let got = softplus(&Tensor::new(&xs, &Device::Cpu)?)?.to_vec1::<f32>()?;
        for (g, &v) in got.iter().zip(&xs) {
            // Relative to the value, also far below zero (where the scaling bias sits).
            let want = if v > 20.0 { v as f64 } else { (v as f64).exp().ln_1p() };
            assert!((*g as f64 - want).abs() <= 1.2e-7 * want.abs(), "{v}: {g} vs {want}");
        }
        Ok(())
    }
}
