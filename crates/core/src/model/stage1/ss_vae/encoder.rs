//! Sparse-structure VAE encoder (TRELLIS `models/sparse_structure_vae.py`,
//! `SparseStructureEncoder`, ℰ_S of the paper) and the VAE training loss of
//! TRELLIS's `trainers/vae/sparse_structure_vae.py`.
//!
//! The encoder turns a binary occupancy grid `[B, 1, 4R, 4R, 4R]` into the
//! Gaussian posterior (`mean`, `logvar`, each `[B, latent, R, R, R]`) whose
//! mean is the latent the stage-1 flow learns to generate and the decoder
//! ([`crate::model::stage1::ss_vae::decoder`]) turns back into occupancy.
//!
//! Module tree (so tensor names match `ss_enc_conv3d_16l8_fp16.safetensors`):
//! `input_layer` conv, `blocks.{i}` ResBlock3d / DownsampleBlock3d (`.conv`,
//! a 2³ stride-2 convolution), `middle_block.{i}` ResBlock3d, then
//! `out_layer.0` norm, SiLU, `out_layer.2` conv to `2·latent` channels split
//! into mean and logvar. Only the differentiable candle path exists: the
//! encoder is needed for training and for encoding training targets, never
//! at inference.

use crate::model::nn::dense3d::NormType;
use crate::model::nn::dense3d::{ChannelLayerNorm, Conv3d};
use crate::model::nn::fast::Compute;
use crate::model::stage1::ss_vae::decoder::ResBlock3d;
use crate::{Error, Result};
use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

/// Constructor args as in the TRELLIS VAE config (`models.encoder.args`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SparseStructureEncoderConfig {
    /// Channels of the input occupancy grid (upstream `in_channels`).
    pub in_channels: usize,
    /// Channels of the latent (upstream `latent_channels`); the last conv outputs twice as many (mean, logvar).
    pub latent_channels: usize,
    /// ResBlock3d per resolution level (upstream `num_res_blocks`).
    pub num_res_blocks: usize,
    /// Width of each resolution level, fine to coarse; each step down halves the side (upstream `channels`).
    pub channels: Vec<usize>,
    /// ResBlock3d in the middle block, at the coarsest level (upstream `num_res_blocks_middle`; default 2).
    #[serde(default = "default_middle")]
    pub num_res_blocks_middle: usize,
    /// Normalisation of the blocks (upstream `norm_type`); only `layer` is accepted.
    #[serde(default)]
    pub norm_type: NormType,
    /// Upstream runs the torso in fp16; this port computes in f32 throughout.
    #[serde(default)]
    pub use_fp16: bool,
}

fn default_middle() -> usize {
    2
}

impl SparseStructureEncoderConfig {
    /// The released TRELLIS encoder (`ss_enc_conv3d_16l8_fp16`): 64³ → 8 × 16³.
    pub fn release() -> Self {
        Self {
            in_channels: 1,
            latent_channels: 8,
            num_res_blocks: 2,
            channels: vec![32, 128, 512],
            num_res_blocks_middle: 2,
            norm_type: NormType::Layer,
            use_fp16: true,
        }
    }

    /// Parse an `args` object and validate it; errors name `file` and the field.
    pub fn from_json(args: &serde_json::Value, file: &str) -> Result<Self> {
        let cfg: Self = crate::util::json::from_value(args, file)?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Check the args are supported: `layer` norm, non-empty positive `channels`, positive channel counts.
    pub fn validate(&self) -> Result<()> {
        let err = |field: &str, msg: String| Err(Error::config("SparseStructureEncoder args", field, msg));
        if self.norm_type != NormType::Layer {
            return err("norm_type", "`group` is not supported (only \"layer\", ChannelLayerNorm32, is implemented)".into());
        }
        if self.channels.is_empty() || self.channels.contains(&0) {
            return err("channels", format!("{:?} must be a non-empty list of positive sizes", self.channels));
        }
        if self.in_channels == 0 || self.latent_channels == 0 {
            return err("in_channels", "in_channels and latent_channels must be positive".into());
        }
        Ok(())
    }

    /// Side of the input grid per latent cell: one ×2 per downsample block.
    pub fn downsample_factor(&self) -> usize {
        1 << (self.channels.len() - 1)
    }
}

/// `DownsampleBlock3d(Cin → Cout, mode="conv")`: `nn.Conv3d(Cin, Cout, 2, stride=2)`
/// (`conv.weight` `[Cout, Cin, 2, 2, 2]`, `conv.bias`). A 2³ stride-2
/// convolution sees disjoint cells, so it is computed as space-to-depth
/// followed by one matrix product (plain candle ops, differentiable).
#[derive(Debug, Clone)]
pub struct DownsampleBlock3d {
    weight: Tensor,
    bias: Tensor,
    cin: usize,
    cout: usize,
}

impl DownsampleBlock3d {
    /// Load `conv.weight` `[cout, cin, 2, 2, 2]` and `conv.bias` `[cout]` under `vb`.
    pub fn new(cin: usize, cout: usize, vb: VarBuilder) -> Result<Self> {
        let vb = vb.pp("conv");
        Ok(Self { weight: vb.get((cout, cin, 2, 2, 2), "weight")?, bias: vb.get(cout, "bias")?, cin, cout })
    }

    /// `[B, Cin, D, H, W]` (even sides) → `[B, Cout, D/2, H/2, W/2]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, c, d, h, w) = x.dims5()?;
        if c != self.cin || d % 2 != 0 || h % 2 != 0 || w % 2 != 0 {
            return Err(Error::msg(format!("downsample: input {:?}, expected [B, {}, even, even, even]", x.dims(), self.cin)));
        }
        let (d2, h2, w2) = (d / 2, h / 2, w / 2);
        // Cell (i, j, k) gathers x[c, 2i+a, 2j+b, 2k+e] at column c·8 + a·4 + b·2 + e,
        // the flattening order of the weight's (Cin, 2, 2, 2) axes.
        let cells = x
            .reshape(vec![b, c, d2, 2, h2, 2, w2, 2])?
            .permute(vec![0, 2, 4, 6, 1, 3, 5, 7])?
            .contiguous()?
            .reshape((b * d2 * h2 * w2, c * 8))?;
        let wm = self.weight.reshape((self.cout, c * 8))?;
        let y = cells.matmul(&wm.t()?)?.broadcast_add(&self.bias)?;
        Ok(y.reshape((b, d2, h2, w2, self.cout))?.permute((0, 4, 1, 2, 3))?.contiguous()?)
    }
}

#[derive(Debug, Clone)]
enum Block {
    Res(ResBlock3d),
    Down(DownsampleBlock3d),
}

/// The posterior the encoder predicts.
#[derive(Debug, Clone)]
pub struct Posterior {
    /// `[B, latent, R, R, R]`
    pub mean: Tensor,
    /// `[B, latent, R, R, R]`
    pub logvar: Tensor,
}

impl Posterior {
    /// `mean + exp(½·logvar)·noise` (upstream `sample_posterior=True`);
    /// `noise` has the shape of `mean`.
    pub fn sample(&self, noise: &Tensor) -> Result<Tensor> {
        if noise.dims() != self.mean.dims() {
            return Err(Error::msg(format!("posterior: noise {:?} does not match mean {:?}", noise.dims(), self.mean.dims())));
        }
        Ok((&self.mean + (self.logvar.affine(0.5, 0.0)?.exp()? * noise)?)?)
    }
}

/// The SS VAE encoder: occupancy `[B, in_channels, S, S, S]` → [`Posterior`] over the latent.
#[derive(Debug, Clone)]
pub struct SparseStructureEncoder {
    cfg: SparseStructureEncoderConfig,
    input_layer: Conv3d,
    blocks: Vec<Block>,
    middle_block: Vec<ResBlock3d>,
    out_norm: ChannelLayerNorm,
    out_conv: Conv3d,
}

impl SparseStructureEncoder {
    /// Validate `cfg` and load the weights under `vb` (upstream names).
    pub fn new(cfg: &SparseStructureEncoderConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        cfg.validate()?;
        let ch = &cfg.channels;
        let input_layer = Conv3d::new(cfg.in_channels, ch[0], 3, 1, vb.pp("input_layer"), compute)?;
        let mut blocks = Vec::new();
        let vbb = vb.pp("blocks");
        for (i, &c) in ch.iter().enumerate() {
            for _ in 0..cfg.num_res_blocks {
                blocks.push(Block::Res(ResBlock3d::new(c, vbb.pp(blocks.len()), compute)?));
            }
            if let Some(&next) = ch.get(i + 1) {
                blocks.push(Block::Down(DownsampleBlock3d::new(c, next, vbb.pp(blocks.len()))?));
            }
        }
        let last = *ch.last().expect("validated non-empty");
        let middle_block = (0..cfg.num_res_blocks_middle)
            .map(|i| ResBlock3d::new(last, vb.pp("middle_block").pp(i), compute))
            .collect::<Result<Vec<_>>>()?;
        let out_norm = ChannelLayerNorm::new(last, vb.pp("out_layer.0"))?;
        let out_conv = Conv3d::new(last, 2 * cfg.latent_channels, 3, 1, vb.pp("out_layer.2"), compute)?;
        Ok(Self { cfg: cfg.clone(), input_layer, blocks, middle_block, out_norm, out_conv })
    }

    /// The args it was built with.
    pub fn config(&self) -> &SparseStructureEncoderConfig {
        &self.cfg
    }

    /// Posterior of an occupancy batch `[B, in, S, S, S]` (S a multiple of
    /// the downsample factor; values in {0, 1}, any float dtype).
    pub fn forward(&self, x: &Tensor) -> Result<Posterior> {
        let (_, c, d, h, w) =
            x.dims5().map_err(|_| Error::msg(format!("ss encoder: input must be [B, C, D, H, W], got {:?}", x.dims())))?;
        let f = self.cfg.downsample_factor();
        if c != self.cfg.in_channels || d % f != 0 || h % f != 0 || w % f != 0 {
            return Err(Error::msg(format!(
                "ss encoder: input {:?}, expected [B, {}, S, S, S] with S a multiple of {f}",
                x.dims(),
                self.cfg.in_channels
            )));
        }
        let mut h = self.input_layer.forward(&x.to_dtype(DType::F32)?)?;
        for b in &self.blocks {
            h = match b {
                Block::Res(r) => r.forward(&h)?,
                Block::Down(dn) => dn.forward(&h)?,
            };
        }
        for b in &self.middle_block {
            h = b.forward(&h)?;
        }
        let h = self.out_conv.forward(&candle_nn::ops::silu(&self.out_norm.forward(&h)?)?)?;
        let l = self.cfg.latent_channels;
        Ok(Posterior { mean: h.narrow(1, 0, l)?, logvar: h.narrow(1, l, l)? })
    }
}

/// Reconstruction term of the VAE loss (TRELLIS `loss_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ReconLoss {
    /// `binary_cross_entropy_with_logits`, mean over every voxel.
    Bce,
    /// `l1(sigmoid(logits), occupancy)`, mean.
    L1,
    /// `1 − (2·Σ p·y + 1) / (Σ p + Σ y + 1)` over the whole batch, `p = sigmoid(logits)`.
    Dice,
}

/// The terms of one VAE loss evaluation (scalars; `total` is differentiable).
#[derive(Debug, Clone)]
pub struct VaeLossTerms {
    /// `recon + lambda_kl · kl`.
    pub total: Tensor,
    /// The reconstruction term ([`ReconLoss`]).
    pub recon: Tensor,
    /// The KL term `½·mean(μ² + e^{logvar} − logvar − 1)`, before `lambda_kl`.
    pub kl: Tensor,
}

/// TRELLIS `SparseStructureVaeTrainer.training_losses`: reconstruction term
/// on decoder `logits` against the `target` occupancy (same shape, {0, 1})
/// plus `lambda_kl · ½·mean(μ² + e^{logvar} − logvar − 1)`.
pub fn vae_loss(logits: &Tensor, target: &Tensor, post: &Posterior, kind: ReconLoss, lambda_kl: f64) -> Result<VaeLossTerms> {
    if logits.dims() != target.dims() {
        return Err(Error::msg(format!("vae loss: logits {:?} and target {:?} differ in shape", logits.dims(), target.dims())));
    }
    let y = target.to_dtype(DType::F32)?;
    let recon = match kind {
        ReconLoss::Bce => bce_with_logits(logits, &y)?,
        ReconLoss::L1 => (candle_nn::ops::sigmoid(logits)? - &y)?.abs()?.mean_all()?,
        ReconLoss::Dice => {
            let p = candle_nn::ops::sigmoid(logits)?;
            let inter = (&p * &y)?.sum_all()?;
            let denom = ((p.sum_all()? + y.sum_all()?)? + 1.0)?;
            ((inter.affine(2.0, 1.0)? / denom)?.affine(-1.0, 1.0))?
        }
    };
    let lv = &post.logvar;
    let kl = ((post.mean.sqr()? + lv.exp()?)? - lv)?.affine(1.0, -1.0)?.mean_all()?.affine(0.5, 0.0)?;
    let total = (&recon + kl.affine(lambda_kl, 0.0)?)?;
    Ok(VaeLossTerms { total, recon, kl })
}

/// Numerically stable `mean(max(x, 0) − x·y + log(1 + e^{−|x|}))`.
pub fn bce_with_logits(x: &Tensor, y: &Tensor) -> Result<Tensor> {
    let softplus_neg_abs = (x.abs()?.neg()?.exp()? + 1.0)?.log()?;
    Ok(((x.relu()? - (x * y)?)? + softplus_neg_abs)?.mean_all()?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::stage1::ss_vae::decoder::{SparseStructureDecoder, SparseStructureDecoderConfig};
    use crate::rng::SeededRng;
    use candle_core::Device;
    use candle_nn::VarMap;

    fn small_cfg() -> SparseStructureEncoderConfig {
        SparseStructureEncoderConfig {
            in_channels: 1,
            latent_channels: 2,
            num_res_blocks: 1,
            channels: vec![4, 6],
            num_res_blocks_middle: 1,
            norm_type: NormType::Layer,
            use_fp16: false,
        }
    }

    fn randomised(vm: &VarMap, seed: u64) {
        let mut rng = SeededRng::new(seed);
        for (name, var) in vm.data().lock().unwrap().iter() {
            let t = if name.contains("norm") || name.contains("out_layer.0") {
                (rng.randn(var.dims(), &Device::Cpu).unwrap() * 0.1).unwrap() + 1.0
            } else {
                rng.randn(var.dims(), &Device::Cpu).unwrap() * 0.2
            };
            var.set(&t.unwrap()).unwrap();
        }
    }

    #[test]
    fn tensor_names_and_shapes_follow_upstream() {
        let cfg = SparseStructureEncoderConfig { channels: vec![8, 16, 32], num_res_blocks: 2, num_res_blocks_middle: 2, ..small_cfg() };
        let vm = VarMap::new();
        SparseStructureEncoder::new(&cfg, VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu), Compute::Plain).unwrap();
        let data = vm.data().lock().unwrap();
        // blocks: res, res, down(8→16), res, res, down(16→32), res, res.
        for (name, shape) in [
            ("input_layer.weight", vec![8, 1, 3, 3, 3]),
            ("blocks.1.conv2.weight", vec![8, 8, 3, 3, 3]),
            ("blocks.2.conv.weight", vec![16, 8, 2, 2, 2]),
            ("blocks.5.conv.bias", vec![32]),
            ("blocks.7.norm1.weight", vec![32]),
            ("middle_block.1.conv1.weight", vec![32, 32, 3, 3, 3]),
            ("out_layer.0.bias", vec![32]),
            ("out_layer.2.weight", vec![4, 32, 3, 3, 3]),
        ] {
            assert_eq!(data.get(name).unwrap_or_else(|| panic!("missing {name}")).dims(), shape.as_slice(), "{name}");
        }
        assert!(!data.contains_key("blocks.8.conv1.weight"));
        assert_eq!(SparseStructureEncoderConfig::release().downsample_factor(), 4);
    }

    /// The space-to-depth downsample equals a direct 2³ stride-2 convolution.
    #[test]
    fn downsample_matches_direct_strided_conv() -> Result<()> {
        let dev = Device::Cpu;
        let (b, cin, cout, d, h, w) = (2, 3, 5, 4, 6, 2);
        let vm = VarMap::new();
        let blk = DownsampleBlock3d::new(cin, cout, VarBuilder::from_varmap(&vm, DType::F32, &dev))?;
        randomised(&vm, 3);
        let x = SeededRng::new(4).randn(&[b, cin, d, h, w], &dev)?;
        let got = blk.forward(&x)?;
        assert_eq!(got.dims(), &[b, cout, d / 2, h / 2, w / 2]);
        let xv = x.flatten_all()?.to_vec1::<f32>()?;
        let wv = blk.weight.flatten_all()?.to_vec1::<f32>()?;
        let bv = blk.bias.to_vec1::<f32>()?;
        let gv = got.flatten_all()?.to_vec1::<f32>()?;
        let mut worst = 0f32;
        for bi in 0..b {
            for co in 0..cout {
                for (i, j, k) in (0..d / 2).flat_map(|i| (0..h / 2).flat_map(move |j| (0..w / 2).map(move |k| (i, j, k)))) {
                    let mut s = bv[co];
                    for ci in 0..cin {
                        for (a, bb, e) in (0..2).flat_map(|a| (0..2).flat_map(move |bb| (0..2).map(move |e| (a, bb, e)))) {
                            let xi = (((bi * cin + ci) * d + 2 * i + a) * h + 2 * j + bb) * w + 2 * k + e;
                            let wi = (((co * cin + ci) * 2 + a) * 2 + bb) * 2 + e;
                            s += xv[xi] * wv[wi];
                        }
                    }
                    let gi = (((bi * cout + co) * (d / 2) + i) * (h / 2) + j) * (w / 2) + k;
                    worst = worst.max((gv[gi] - s).abs());
                }
            }
        }
        assert!(worst < 1e-5, "max diff {worst}");
        Ok(())
    }

    #[test]
    fn encoder_shapes_and_posterior_sampling() -> Result<()> {
        let dev = Device::Cpu;
        let cfg = small_cfg();
        let vm = VarMap::new();
        let enc = SparseStructureEncoder::new(&cfg, VarBuilder::from_varmap(&vm, DType::F32, &dev), Compute::Plain)?;
        randomised(&vm, 1);
        let x = SeededRng::new(2).randn(&[2, 1, 8, 8, 8], &dev)?.gt(0.5)?.to_dtype(DType::F32)?;
        let post = enc.forward(&x)?;
        assert_eq!(post.mean.dims(), &[2, 2, 4, 4, 4]);
        assert_eq!(post.logvar.dims(), &[2, 2, 4, 4, 4]);
        // Zero noise gives the mean; unit noise adds exp(logvar/2).
        let z0 = post.sample(&post.mean.zeros_like()?)?;
        assert_eq!(crate::util::max_abs_diff(&z0, &post.mean)?, 0.0);
        let z1 = post.sample(&post.mean.ones_like()?)?;
        let want = (&post.mean + (&post.logvar * 0.5)?.exp()?)?;
        assert!(crate::util::max_abs_diff(&z1, &want)? < 1e-6);
        // Grids that do not divide into latent cells are refused.
        assert!(enc.forward(&Tensor::zeros((1, 1, 5, 8, 8), DType::F32, &dev)?).is_err());
        assert!(SparseStructureEncoderConfig::from_json(
            &serde_json::json!({"in_channels": 1, "latent_channels": 8, "num_res_blocks": 1, "channels": []}),
            "t"
        )
        .is_err());
        Ok(())
    }

    /// Loss terms against hand-computed values.
    #[test]
    fn vae_loss_terms_match_formulas() -> Result<()> {
        let dev = Device::Cpu;
        let logits = Tensor::new(&[[0.0f32, 2.0], [-1.0, 3.0]], &dev)?.reshape((1, 1, 1, 2, 2))?;
        let target = Tensor::new(&[[1.0f32, 0.0], [0.0, 1.0]], &dev)?.reshape((1, 1, 1, 2, 2))?;
        let post = Posterior {
            mean: Tensor::new(&[1.0f32, 0.0], &dev)?.reshape((1, 2, 1, 1, 1))?,
            logvar: Tensor::new(&[0.0f32, 1.0], &dev)?.reshape((1, 2, 1, 1, 1))?,
        };
        let sp = |x: f64| (1.0 + x.exp()).ln();
        // BCE = mean of softplus(−x) for y = 1 and softplus(x) for y = 0.
        let bce = (sp(-0.0) + sp(2.0) + sp(-1.0) + sp(-3.0)) / 4.0;
        let kl = 0.5 * ((1.0 + 1.0 - 0.0 - 1.0) + (0.0 + 1f64.exp() - 1.0 - 1.0)) / 2.0;
        let t = vae_loss(&logits, &target, &post, ReconLoss::Bce, 0.5)?;
        assert!((t.recon.to_scalar::<f32>()? as f64 - bce).abs() < 1e-6);
        assert!((t.kl.to_scalar::<f32>()? as f64 - kl).abs() < 1e-6);
        assert!((t.total.to_scalar::<f32>()? as f64 - (bce + 0.5 * kl)).abs() < 1e-6);
        let sig = |x: f64| 1.0 / (1.0 + (-x).exp());
        let p = [sig(0.0), sig(2.0), sig(-1.0), sig(3.0)];
        let dice = 1.0 - (2.0 * (p[0] + p[3]) + 1.0) / (p.iter().sum::<f64>() + 2.0 + 1.0);
        let t = vae_loss(&logits, &target, &post, ReconLoss::Dice, 0.0)?;
        assert!((t.recon.to_scalar::<f32>()? as f64 - dice).abs() < 1e-6);
        let l1 = ((1.0 - p[0]) + p[1] + p[2] + (1.0 - p[3])) / 4.0;
        let t = vae_loss(&logits, &target, &post, ReconLoss::L1, 0.0)?;
        assert!((t.recon.to_scalar::<f32>()? as f64 - l1).abs() < 1e-6);
        // BCE stays finite for huge logits.
        let big = Tensor::new(&[200f32, -200.0], &dev)?;
        let v = bce_with_logits(&big, &Tensor::new(&[0f32, 1.0], &dev)?)?.to_scalar::<f32>()?;
        assert!((v - 200.0).abs() < 1e-3, "{v}");
        Ok(())
    }

    /// Encoder + decoder + loss are differentiable end to end: the gradient
    /// along a random direction over every parameter equals the central
    /// finite difference of the loss.
    #[test]
    fn vae_loss_gradient_matches_finite_difference() -> Result<()> {
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
        let enc = SparseStructureEncoder::new(&small_cfg(), vb.pp("encoder"), Compute::Plain)?;
        let dcfg = SparseStructureDecoderConfig {
            out_channels: 1,
            latent_channels: 2,
            num_res_blocks: 1,
            channels: vec![6, 4],
            num_res_blocks_middle: 1,
            norm_type: NormType::Layer,
            use_fp16: false,
        };
        let dec = SparseStructureDecoder::new(&dcfg, vb.pp("decoder"), Compute::Plain)?;
        randomised(&vm, 5);
        let x = SeededRng::new(6).randn(&[1, 1, 4, 4, 4], &dev)?.gt(0.0)?.to_dtype(DType::F32)?;
        let noise = SeededRng::new(7).randn(&[1, 2, 2, 2, 2], &dev)?;
        let loss = || -> Result<Tensor> {
            let post = enc.forward(&x)?;
            let logits = dec.forward_differentiable(&post.sample(&noise)?)?;
            Ok(vae_loss(&logits, &x, &post, ReconLoss::Bce, 0.1)?.total)
        };
        crate::model::nn::gradcheck::directional_check(&crate::model::nn::gradcheck::sorted_vars(&vm), &[], loss, 11, 1e-2)?;
        Ok(())
    }
}
