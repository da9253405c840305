//! Sparse-structure VAE decoder (TRELLIS `models/sparse_structure_vae.py`,
//! `SparseStructureDecoder`): a dense 3D conv net turning the `[B, 8, 16³]`
//! latent into `[B, 1, 64³]` occupancy logits. Occupied voxels are `logit > 0`.
//!
//! Module tree (and so tensor names): `input_layer` conv, `middle_block.{i}`
//! ResBlock3d, `blocks.{i}` ResBlock3d / UpsampleBlock3d (`.conv`), then
//! `out_layer.0` norm, SiLU, `out_layer.2` conv.

use crate::model::nn::dense3d::NormType;
use crate::model::nn::dense3d::{pixel_shuffle_3d, pixel_shuffle_3d_fast, ChannelLayerNorm, Conv3d, Volume};
use crate::model::nn::fast::Compute;
use crate::{Error, Result};
use candle_core::Tensor;
use candle_nn::VarBuilder;
use serde::Deserialize;

/// Constructor args as stored in the checkpoint JSON / fixture `args`.
#[derive(Debug, Clone, Deserialize)]
pub struct SparseStructureDecoderConfig {
    /// Channels of the output logits (upstream `out_channels`; 1 = occupancy).
    pub out_channels: usize,
    /// Channels of the input latent (upstream `latent_channels`).
    pub latent_channels: usize,
    /// ResBlock3d per resolution level (upstream `num_res_blocks`).
    pub num_res_blocks: usize,
    /// Width of each resolution level, coarse to fine; each step up doubles the side (upstream `channels`).
    pub channels: Vec<usize>,
    /// ResBlock3d in the middle block, at the coarsest level (upstream `num_res_blocks_middle`; default 2).
    #[serde(default = "default_middle")]
    pub num_res_blocks_middle: usize,
    /// Normalisation of the blocks (upstream `norm_type`); only `layer` is accepted.
    #[serde(default)]
    pub norm_type: NormType,
    /// Upstream runs the torso in fp16; this port computes in the precision of
    /// the compute it is built with (bf16 for the wide convolutions at bf16, else f32; see `Conv3d`).
    #[serde(default)]
    pub use_fp16: bool,
}

fn default_middle() -> usize {
    2
}

impl SparseStructureDecoderConfig {
    /// The released TRELLIS-image-large decoder (`ss_dec_conv3d_16l8_fp16`).
    pub fn release() -> Self {
        Self {
            out_channels: 1,
            latent_channels: 8,
            num_res_blocks: 2,
            channels: vec![512, 128, 32],
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
        let err = |field: &str, msg: String| Err(Error::config("SparseStructureDecoder args", field, msg));
        if self.norm_type != NormType::Layer {
            return err("norm_type", "`group` is not supported (only \"layer\", ChannelLayerNorm32, is implemented)".into());
        }
        if self.channels.is_empty() || self.channels.contains(&0) {
            return err("channels", format!("{:?} must be a non-empty list of positive sizes", self.channels));
        }
        if self.out_channels == 0 || self.latent_channels == 0 {
            return err("out_channels", "out_channels and latent_channels must be positive".into());
        }
        Ok(())
    }
}

/// `ResBlock3d(C → C)`: `x + conv2(silu(norm2(conv1(silu(norm1(x))))))`.
#[derive(Debug, Clone)]
pub struct ResBlock3d {
    norm1: ChannelLayerNorm,
    conv1: Conv3d,
    norm2: ChannelLayerNorm,
    conv2: Conv3d,
}

impl ResBlock3d {
    /// Load `norm1`, `conv1`, `norm2`, `conv2` (3³ convolutions, C → C) under `vb`.
    pub fn new(c: usize, vb: VarBuilder, compute: Compute) -> Result<Self> {
        Ok(Self {
            norm1: ChannelLayerNorm::new(c, vb.pp("norm1"))?,
            conv1: Conv3d::new(c, c, 3, 1, vb.pp("conv1"), compute)?,
            norm2: ChannelLayerNorm::new(c, vb.pp("norm2"))?,
            conv2: Conv3d::new(c, c, 3, 1, vb.pp("conv2"), compute)?,
        })
    }

    /// Differentiable path: `x` `[B, C, D, H, W]` → same shape.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = self.conv1.forward(&candle_nn::ops::silu(&self.norm1.forward(x)?)?)?;
        let h = self.conv2.forward(&candle_nn::ops::silu(&self.norm2.forward(&h)?)?)?;
        Ok((h + x)?)
    }

    /// Fast path; the residual add is fused into conv2 (it accumulates onto `x`).
    pub fn forward_fast(&self, x: Volume) -> Result<Volume> {
        let h = self.conv1.forward_fast(&self.norm1.forward_fast(&x, true)?, None)?;
        let h = self.norm2.forward_fast(&h, true)?;
        self.conv2.forward_fast(&h, Some(x))
    }
}

/// `UpsampleBlock3d(Cin → Cout, mode="conv")`: conv to `Cout·8` channels, then pixel shuffle.
#[derive(Debug, Clone)]
pub struct UpsampleBlock3d {
    conv: Conv3d,
}

impl UpsampleBlock3d {
    /// Load the 3³ convolution `conv` (`cin → cout·8`) under `vb`.
    pub fn new(cin: usize, cout: usize, vb: VarBuilder, compute: Compute) -> Result<Self> {
        Ok(Self { conv: Conv3d::new(cin, cout * 8, 3, 1, vb.pp("conv"), compute)? })
    }
    /// Differentiable path: `[B, Cin, D, H, W]` → `[B, Cout, 2D, 2H, 2W]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        pixel_shuffle_3d(&self.conv.forward(x)?)
    }
    /// Fast path of [`Self::forward`].
    pub fn forward_fast(&self, x: &Volume) -> Result<Volume> {
        pixel_shuffle_3d_fast(&self.conv.forward_fast(x, None)?)
    }
}

#[derive(Debug, Clone)]
enum Block {
    Res(ResBlock3d),
    Up(UpsampleBlock3d),
}

/// Decoder outputs plus the intermediates the conformance fixture records.
#[derive(Debug, Clone)]
pub struct DecoderTrace {
    /// Output of `input_layer`: `[B, channels[0], R, R, R]`.
    pub input_layer: Tensor,
    /// Output of the middle block: `[B, channels[0], R, R, R]`.
    pub middle_block: Tensor,
    /// Final occupancy logits `[B, out_channels, R', R', R']`, `R' = R·2^(channels.len()−1)`.
    pub logits: Tensor,
}

/// The SS VAE decoder: dense latent `[B, latent_channels, R, R, R]` → occupancy logits.
#[derive(Debug, Clone)]
pub struct SparseStructureDecoder {
    cfg: SparseStructureDecoderConfig,
    input_layer: Conv3d,
    middle_block: Vec<ResBlock3d>,
    blocks: Vec<Block>,
    out_norm: ChannelLayerNorm,
    out_conv: Conv3d,
}

impl SparseStructureDecoder {
    /// Validate `cfg` and load the weights under `vb` (upstream names).
    pub fn new(cfg: &SparseStructureDecoderConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        cfg.validate()?;
        let ch = &cfg.channels;
        let input_layer = Conv3d::new(cfg.latent_channels, ch[0], 3, 1, vb.pp("input_layer"), compute)?;
        let middle_block = (0..cfg.num_res_blocks_middle)
            .map(|i| ResBlock3d::new(ch[0], vb.pp("middle_block").pp(i), compute))
            .collect::<Result<Vec<_>>>()?;
        let mut blocks = Vec::new();
        let vbb = vb.pp("blocks");
        for (i, &c) in ch.iter().enumerate() {
            for _ in 0..cfg.num_res_blocks {
                blocks.push(Block::Res(ResBlock3d::new(c, vbb.pp(blocks.len()), compute)?));
            }
            if let Some(&next) = ch.get(i + 1) {
                blocks.push(Block::Up(UpsampleBlock3d::new(c, next, vbb.pp(blocks.len()), compute)?));
            }
        }
        let last = *ch.last().expect("validated non-empty");
        let out_norm = ChannelLayerNorm::new(last, vb.pp("out_layer.0"))?;
        let out_conv = Conv3d::new(last, cfg.out_channels, 3, 1, vb.pp("out_layer.2"), compute)?;
        Ok(Self { cfg: cfg.clone(), input_layer, middle_block, blocks, out_norm, out_conv })
    }

    /// The args it was built with.
    pub fn config(&self) -> &SparseStructureDecoderConfig {
        &self.cfg
    }

    fn check_input(&self, x: &Tensor) -> Result<()> {
        let (_, c, _, _, _) =
            x.dims5().map_err(|_| Error::msg(format!("ss decoder: input must be [B, C, D, H, W], got {:?}", x.dims())))?;
        if c != self.cfg.latent_channels {
            return Err(Error::msg(format!("ss decoder: input has {c} channels, expected {}", self.cfg.latent_channels)));
        }
        Ok(())
    }

    /// Inference forward (fast kernels): `[B, latent, R, R, R]` → logits `[B, out, 4R, 4R, 4R]`
    /// (one ×2 per upsample block).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(self.forward_traced(x)?.logits)
    }

    /// Fast forward that also returns the `input_layer` and `middle_block` outputs.
    pub fn forward_traced(&self, x: &Tensor) -> Result<DecoderTrace> {
        self.check_input(x)?;
        let h = self.input_layer.forward_fast(&Volume::from_tensor(x)?, None)?;
        let input_layer = h.to_tensor()?;
        let mut h = h;
        for b in &self.middle_block {
            h = b.forward_fast(h)?;
        }
        let middle_block = h.to_tensor()?;
        for b in &self.blocks {
            h = match b {
                Block::Res(r) => r.forward_fast(h)?,
                Block::Up(u) => u.forward_fast(&h)?,
            };
        }
        let h = self.out_norm.forward_fast(&h, true)?;
        let logits = self.out_conv.forward_fast(&h, None)?.to_tensor()?;
        Ok(DecoderTrace { input_layer, middle_block, logits })
    }

    /// Differentiable forward with plain candle ops (training, and the
    /// reference the fast path is tested against).
    pub fn forward_differentiable(&self, x: &Tensor) -> Result<Tensor> {
        self.check_input(x)?;
        let mut h = self.input_layer.forward(x)?;
        for b in &self.middle_block {
            h = b.forward(&h)?;
        }
        for b in &self.blocks {
            h = match b {
                Block::Res(r) => r.forward(&h)?,
                Block::Up(u) => u.forward(&h)?,
            };
        }
        self.out_conv.forward(&candle_nn::ops::silu(&self.out_norm.forward(&h)?)?)
    }
}

/// Occupied voxels of decoder logits `[B, C, X, Y, Z]`: every entry `> 0` as
/// `(batch, x, y, z)`, in `torch.argwhere(logits > 0)[:, [0, 2, 3, 4]]` order
/// (row-major over `b, c, x, y, z`).
pub fn occupied_coords(logits: &Tensor) -> Result<Vec<[i32; 4]>> {
    let (b, c, nx, ny, nz) = logits.dims5()?;
    let v = logits.to_dtype(candle_core::DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    let mut out = Vec::new();
    let mut i = 0;
    for bi in 0..b {
        for _ in 0..c {
            for x in 0..nx {
                for y in 0..ny {
                    for z in 0..nz {
                        if v[i] > 0.0 {
                            out.push([bi as i32, x as i32, y as i32, z as i32]);
                        }
                        i += 1;
                    }
                }
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::max_abs_diff;
    use candle_core::{DType, Device};
    use std::collections::HashMap;

    fn small_cfg() -> SparseStructureDecoderConfig {
        SparseStructureDecoderConfig {
            out_channels: 2,
            latent_channels: 3,
            num_res_blocks: 1,
            channels: vec![6, 5],
            num_res_blocks_middle: 1,
            norm_type: NormType::Layer,
            use_fp16: false,
        }
    }

    /// Random weights under every name the decoder asks for.
    fn random_vb(cfg: &SparseStructureDecoderConfig) -> VarBuilder<'static> {
        let probe = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&probe, DType::F32, &Device::Cpu);
        SparseStructureDecoder::new(cfg, vb, Compute::Plain).unwrap();
        let mut ws = HashMap::new();
        for (name, var) in probe.data().lock().unwrap().iter() {
            let t = var.as_tensor();
            let offset = if name.contains("norm") || name.contains("out_layer.0") { 1.0 } else { 0.0 };
            let r = (Tensor::randn(0f32, 0.3, t.shape(), &Device::Cpu).unwrap() + offset).unwrap();
            ws.insert(name.clone(), r);
        }
        VarBuilder::from_tensors(ws, DType::F32, &Device::Cpu)
    }

    #[test]
    fn fast_and_differentiable_paths_agree() {
        let cfg = small_cfg();
        let dec = SparseStructureDecoder::new(&cfg, random_vb(&cfg), Compute::Plain).unwrap();
        let x = Tensor::randn(0f32, 1.0, (2, 3, 3, 4, 2), &Device::Cpu).unwrap();
        let fast = dec.forward(&x).unwrap();
        assert_eq!(fast.dims(), &[2, 2, 6, 8, 4]);
        let slow = dec.forward_differentiable(&x).unwrap();
        let d = max_abs_diff(&fast, &slow).unwrap();
        assert!(d < 1e-4, "max diff {d}");
    }

    #[test]
    fn fast_path_agrees_at_winograd_widths() {
        // 64 channels and a 64→8·8 upsample conv select the Winograd kernel.
        let cfg = SparseStructureDecoderConfig { channels: vec![64, 8], ..small_cfg() };
        let dec = SparseStructureDecoder::new(&cfg, random_vb(&cfg), Compute::Plain).unwrap();
        let x = Tensor::randn(0f32, 1.0, (1, 3, 3, 2, 3), &Device::Cpu).unwrap();
        let d = max_abs_diff(&dec.forward(&x).unwrap(), &dec.forward_differentiable(&x).unwrap()).unwrap();
        assert!(d < 1e-4, "max diff {d}");
    }

    #[test]
    fn tensor_names_follow_upstream() {
        let cfg = SparseStructureDecoderConfig { channels: vec![8, 8, 8], num_res_blocks: 2, num_res_blocks_middle: 2, ..small_cfg() };
        let probe = candle_nn::VarMap::new();
        SparseStructureDecoder::new(&cfg, VarBuilder::from_varmap(&probe, DType::F32, &Device::Cpu), Compute::Plain).unwrap();
        let data = probe.data().lock().unwrap();
        for name in [
            "input_layer.weight",
            "middle_block.1.conv2.bias",
            "blocks.1.norm1.weight",
            "blocks.2.conv.weight",
            "blocks.5.conv.bias",
            "blocks.7.conv1.weight",
            "out_layer.0.weight",
            "out_layer.2.bias",
        ] {
            assert!(data.contains_key(name), "missing {name}");
        }
        assert!(!data.contains_key("blocks.8.conv1.weight"));
        assert_eq!(data["blocks.2.conv.weight"].as_tensor().dims(), &[64, 8, 3, 3, 3]);
    }

    #[test]
    fn rejects_unsupported_norm_type() {
        let args =
            serde_json::json!({"out_channels": 1, "latent_channels": 8, "num_res_blocks": 2, "channels": [32], "norm_type": "group"});
        let e = SparseStructureDecoderConfig::from_json(&args, "t").unwrap_err().to_string();
        assert!(e.contains("norm_type"), "{e}");
    }

    #[test]
    fn occupied_coords_in_argwhere_order() {
        let mut v = vec![-1f32; 2 * 2 * 2 * 2];
        v[1] = 0.5; // b0 (0,0,1)
        v[6] = 2.0; // b0 (1,1,0)
        v[8 + 3] = 0.1; // b1 (0,1,1)
        v[8 + 4] = 0.0; // not > 0
        let t = Tensor::from_vec(v, (2, 1, 2, 2, 2), &Device::Cpu).unwrap();
        assert_eq!(occupied_coords(&t).unwrap(), vec![[0, 0, 0, 1], [0, 1, 1, 0], [1, 0, 1, 1]]);
    }
}
