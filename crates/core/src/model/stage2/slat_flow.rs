//! Stage 2: structured-latent flow transformer (TRELLIS `SLatFlowModel`,
//! RecGen `SLatCondFlowModel`).
//!
//! Sparse voxels at full resolution go through sparse conv ResBlocks that
//! downsample ×2 per io stage; the transformer runs on the coarse tokens
//! (full attention within each batch item, cross-attention to the condition);
//! out blocks upsample back and take the matching skip features.
//!
//! RecGen's additions are optional and enabled by config flags: a pose
//! Linear(D→C) whose tokens are appended to the cross-attention context, and
//! Conv2d(k14, s14) point-map / mask embedders added to the image patch tokens
//! (see [`SLatFlowModel::build_cond`]).

use crate::geometry::pose::PoseRepresentation;
use crate::model::nn::common::Linear;
use crate::model::nn::common::PeMode;
use crate::model::nn::common::{
    abs_position_embedding, layer_norm_plain, linear, CrossBlockConfig, LayerNorm, ModulatedTransformerCrossBlock, PreparedCondition,
    TimestepEmbedder,
};
use crate::model::nn::fast::Compute;
use crate::model::sampler::{PrepareCondition, PreparedRun, VelocityModel};
use crate::model::sparse::conv::neighbour_map;
use crate::model::sparse::spatial::xyz_tensor;
use crate::model::sparse::{sparse_downsample, sparse_upsample, DownsampleCache, SparseConv3d, SparseTensor};
use crate::model::stage1::embedders::{build_condition, CondEmbedderConfig, CondEmbedders, MaskEmbedder, PointmapEmbedder, ViewInputs};
use crate::util::profile::{region, Region};
use crate::{Error, Result};
use candle_core::{Module, Tensor, D};
use candle_nn::VarBuilder;
use serde::Deserialize;

fn default_head_channels() -> usize {
    64
}
fn default_mlp_ratio() -> f64 {
    4.0
}
fn default_patch() -> usize {
    2
}
fn default_io_blocks() -> usize {
    2
}
fn default_true() -> bool {
    true
}
fn default_embed_channels() -> usize {
    1024
}
fn default_pose_repr() -> PoseRepresentation {
    PoseRepresentation::QuaternionTranslationScale
}

/// Constructor args of `SLatFlowModel` / `SLatCondFlowModel` (checkpoint
/// `args`). Unknown fields (`use_fp16`, `use_checkpoint`) are ignored.
#[derive(Debug, Clone, Deserialize)]
pub struct SLatFlowConfig {
    /// Side of the sparse voxel grid the latents live on (upstream `resolution`); the forward pass does not read it.
    pub resolution: usize,
    /// Latent channels per input voxel (upstream `in_channels`).
    pub in_channels: usize,
    /// Channels of the predicted velocity per voxel (upstream `out_channels`).
    pub out_channels: usize,
    /// Transformer width (upstream `model_channels`).
    pub model_channels: usize,
    /// Width of the condition tokens (upstream `cond_channels`).
    pub cond_channels: usize,
    /// Number of transformer blocks (upstream `num_blocks`).
    pub num_blocks: usize,
    /// Attention heads (upstream `num_heads`); `None`: `model_channels / num_head_channels`.
    #[serde(default)]
    pub num_heads: Option<usize>,
    /// Channels per head when `num_heads` is unset (upstream `num_head_channels`, default 64).
    #[serde(default = "default_head_channels")]
    pub num_head_channels: usize,
    /// Feed-forward hidden width over `model_channels` (upstream `mlp_ratio`, default 4).
    #[serde(default = "default_mlp_ratio")]
    pub mlp_ratio: f64,
    /// Total downsampling of the io stages (upstream `patch_size`, default 2): `log2(patch_size)` must equal
    /// the number of `io_block_channels`.
    #[serde(default = "default_patch")]
    pub patch_size: usize,
    /// ResBlocks per io stage on each side, the last input one downsampling and the first output one
    /// upsampling (upstream `num_io_res_blocks`, default 2).
    #[serde(default = "default_io_blocks")]
    pub num_io_res_blocks: usize,
    /// Width of each io stage, finest first (upstream `io_block_channels`); `None`: no io stages.
    #[serde(default)]
    pub io_block_channels: Option<Vec<usize>>,
    /// Position embedding (upstream `pe_mode`); only `ape` is supported.
    #[serde(default)]
    pub pe_mode: PeMode,
    /// Concatenate each input block's output to the matching output block's input (upstream
    /// `use_skip_connection`, default true).
    #[serde(default = "default_true")]
    pub use_skip_connection: bool,
    /// One adaLN modulation shared by all transformer blocks (upstream `share_mod`).
    #[serde(default)]
    pub share_mod: bool,
    /// RMS-normalise queries and keys in self-attention (upstream `qk_rms_norm`).
    #[serde(default)]
    pub qk_rms_norm: bool,
    /// RMS-normalise queries and keys in cross-attention (upstream `qk_rms_norm_cross`).
    #[serde(default)]
    pub qk_rms_norm_cross: bool,
    // RecGen `SLatCondFlowModel` extras.
    /// Point-map and mask embedders (their args, flattened).
    #[serde(flatten)]
    pub embedders: CondEmbedderConfig,
    /// Build the pose embedder, a Linear(`pose_dim` → `pose_embedder_out_channels`) whose tokens join the
    /// context (RecGen `use_pose_embedder`).
    #[serde(default)]
    pub use_pose_embedder: bool,
    /// Width of the pose tokens (RecGen `pose_embedder_out_channels`, default 1024); must equal
    /// `cond_channels` for them to join the context.
    #[serde(default = "default_embed_channels")]
    pub pose_embedder_out_channels: usize,
    /// Layout of the pose vectors (RecGen `pose_representation`, default `quaternion_translation_scale`).
    #[serde(default = "default_pose_repr")]
    pub pose_representation: PoseRepresentation,
}

impl SLatFlowConfig {
    /// Parse an `args` object; errors name `file` and the field. Checked
    /// when the model is built ([`SLatFlowModel::new`]).
    pub fn from_json(v: &serde_json::Value, file: &str) -> Result<Self> {
        crate::util::json::from_value(v, file)
    }

    /// Attention heads: `num_heads`, else `model_channels / num_head_channels`.
    pub fn heads(&self) -> usize {
        self.num_heads.unwrap_or(self.model_channels / self.num_head_channels.max(1))
    }

    /// Input width of the pose embedder for the configured representation.
    pub fn pose_dim(&self) -> usize {
        self.pose_representation.channels()
    }

    fn validate(&self) -> Result<()> {
        if self.pe_mode != PeMode::Ape {
            return Err(Error::msg("SLat flow: pe_mode `rope` is not supported (only `ape`)"));
        }
        if let Some(io) = &self.io_block_channels {
            if !self.patch_size.is_power_of_two() || self.patch_size.trailing_zeros() as usize != io.len() {
                return Err(Error::msg("SLat flow: log2(patch_size) must equal the number of io stages"));
            }
            if io.is_empty() || self.num_io_res_blocks == 0 {
                return Err(Error::msg("SLat flow: io_block_channels and num_io_res_blocks must be non-empty"));
            }
        }
        let heads = self.heads();
        if heads == 0 || !self.model_channels.is_multiple_of(heads) {
            return Err(Error::msg("SLat flow: model_channels must be divisible by num_heads"));
        }
        Ok(())
    }
}

/// Which sparse conv implementation the ResBlocks use.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvPath {
    /// Hand-written multi-threaded kernel (inference).
    Fast,
    /// Plain candle ops, differentiable.
    Differentiable,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum UpDown {
    None,
    Down,
    Up,
}

/// TRELLIS `SparseResBlock3d` (spec §3.2).
#[derive(Debug, Clone)]
pub struct SparseResBlock3d {
    norm1: LayerNorm,
    conv1: SparseConv3d,
    conv2: SparseConv3d,
    emb_layers: Linear,
    skip: Option<Linear>,
    updown: UpDown,
}

impl SparseResBlock3d {
    fn new(channels: usize, emb: usize, out: usize, updown: UpDown, vb: VarBuilder, compute: Compute) -> Result<Self> {
        Ok(Self {
            norm1: LayerNorm::new(channels, 1e-6, vb.pp("norm1"), compute)?,
            conv1: SparseConv3d::new(channels, out, 3, vb.pp("conv1"), compute)?,
            conv2: SparseConv3d::new(out, out, 3, vb.pp("conv2"), compute)?,
            emb_layers: linear(emb, 2 * out, vb.pp("emb_layers.1"), compute)?,
            skip: if channels != out { Some(linear(channels, out, vb.pp("skip_connection"), compute)?) } else { None },
            updown,
        })
    }

    /// `caches` is the stack of downsample caches: a downsampling block
    /// pushes, an upsampling block pops the most recent.
    fn forward(&self, x: &SparseTensor, emb: &Tensor, caches: &mut Vec<DownsampleCache>, path: ConvPath) -> Result<SparseTensor> {
        let e = self.emb_layers.forward(&emb.silu()?)?;
        let ch = e.chunk(2, 1)?;
        let (scale, shift) = (&ch[0], &ch[1]);
        let x = match self.updown {
            UpDown::None => x.clone(),
            UpDown::Down => {
                let (y, cache) = sparse_downsample(x, 2)?;
                caches.push(cache);
                y
            }
            UpDown::Up => {
                let cache = caches.pop().ok_or_else(|| Error::msg("SLat flow: upsample without a matching downsample"))?;
                sparse_upsample(x, &cache)?
            }
        };
        let map = neighbour_map(&x, 3)?;
        let conv = |c: &SparseConv3d, t: &SparseTensor| match path {
            ConvPath::Fast => c.forward_with_map(t, &map),
            ConvPath::Differentiable => c.forward_differentiable(t, &map),
        };
        let h = x.with_feats(self.norm1.forward(&x.feats)?.silu()?)?;
        let h = conv(&self.conv1, &h)?;
        let scale = x.batch_broadcast(&(scale + 1.0)?)?;
        let shift = x.batch_broadcast(shift)?;
        let hf = layer_norm_plain(&h.feats, 1e-6)?.mul(&scale)?.add(&shift)?.silu()?;
        let h = conv(&self.conv2, &h.with_feats(hf)?)?;
        let skip = match &self.skip {
            Some(l) => l.forward(&x.feats)?,
            None => x.feats.clone(),
        };
        x.with_feats((h.feats + skip)?)
    }
}

/// Intermediate values recorded by [`SLatFlowModel::forward_with_taps`].
#[derive(Debug, Clone, Default)]
pub struct SLatFlowTaps {
    /// Timestep embedding `[B, model_channels]` (before the shared adaLN, if any).
    pub t_emb: Option<Tensor>,
    /// Output of each input block.
    pub input_blocks: Vec<SparseTensor>,
    /// Output feats of each transformer block (coarse tokens).
    pub blocks: Vec<Tensor>,
}

/// The stage-2 structured-latent flow transformer (TRELLIS `SLatFlowModel`, RecGen `SLatCondFlowModel`).
#[derive(Debug, Clone)]
pub struct SLatFlowModel {
    /// The config it was built from.
    pub cfg: SLatFlowConfig,
    t_embedder: TimestepEmbedder,
    ada_ln: Option<Linear>,
    input_layer: Linear,
    input_blocks: Vec<SparseResBlock3d>,
    blocks: Vec<ModulatedTransformerCrossBlock>,
    out_blocks: Vec<SparseResBlock3d>,
    out_layer: Linear,
    /// Shared Conv2d(k14, s14) patch embedders (`point_embedder.*`, `mask_embedder.*`).
    pub point_embedder: Option<PointmapEmbedder>,
    /// Mask embedder (`mask_embedder.*`); `None` unless `use_mask_embedder`.
    pub mask_embedder: Option<MaskEmbedder>,
    pose_embedder: Option<Linear>,
    conv_path: ConvPath,
    /// Whether the shortcuts that round differently are on (see [`SLatFlowModel::set_shortcuts`]).
    shortcuts: bool,
}

/// The condition of one forward: a tensor (plain path), or prepared once for many (fast path).
#[derive(Clone, Copy)]
enum Cond<'a> {
    Tensor(&'a Tensor),
    Prepared(&'a PreparedCondition),
}

impl SLatFlowModel {
    /// Build the model from `cfg` (validated first) with the checkpoint weights under `vb`.
    pub fn new(cfg: &SLatFlowConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        cfg.validate()?;
        let c = cfg.model_channels;
        let io = cfg.io_block_channels.clone().unwrap_or_default();
        let first = io.first().copied().unwrap_or(c);

        let mut input_blocks = Vec::new();
        let mut idx = 0;
        for (s, &chs) in io.iter().enumerate() {
            let next = io.get(s + 1).copied().unwrap_or(c);
            for _ in 0..cfg.num_io_res_blocks - 1 {
                input_blocks.push(SparseResBlock3d::new(chs, c, chs, UpDown::None, vb.pp(format!("input_blocks.{idx}")), compute)?);
                idx += 1;
            }
            input_blocks.push(SparseResBlock3d::new(chs, c, next, UpDown::Down, vb.pp(format!("input_blocks.{idx}")), compute)?);
            idx += 1;
        }

        let bcfg = CrossBlockConfig {
            channels: c,
            ctx_channels: cfg.cond_channels,
            heads: cfg.heads(),
            mlp_ratio: cfg.mlp_ratio,
            share_mod: cfg.share_mod,
            qk_rms_norm: cfg.qk_rms_norm,
            qk_rms_norm_cross: cfg.qk_rms_norm_cross,
        };
        let blocks = (0..cfg.num_blocks)
            .map(|i| ModulatedTransformerCrossBlock::new(&bcfg, vb.pp(format!("blocks.{i}")), compute))
            .collect::<candle_core::Result<Vec<_>>>()?;

        let mut out_blocks = Vec::new();
        let mut idx = 0;
        let skip_mul = if cfg.use_skip_connection { 2 } else { 1 };
        for (s, &chs) in io.iter().enumerate().rev() {
            let prev = io.get(s + 1).copied().unwrap_or(c);
            out_blocks.push(SparseResBlock3d::new(prev * skip_mul, c, chs, UpDown::Up, vb.pp(format!("out_blocks.{idx}")), compute)?);
            idx += 1;
            for _ in 0..cfg.num_io_res_blocks - 1 {
                out_blocks.push(SparseResBlock3d::new(chs * skip_mul, c, chs, UpDown::None, vb.pp(format!("out_blocks.{idx}")), compute)?);
                idx += 1;
            }
        }

        Ok(Self {
            t_embedder: TimestepEmbedder::new(c, vb.pp("t_embedder"), compute)?,
            ada_ln: if cfg.share_mod { Some(linear(c, 6 * c, vb.pp("adaLN_modulation.1"), compute)?) } else { None },
            input_layer: linear(cfg.in_channels, first, vb.pp("input_layer"), compute)?,
            input_blocks,
            blocks,
            out_blocks,
            out_layer: linear(first, cfg.out_channels, vb.pp("out_layer"), compute)?,
            point_embedder: if cfg.embedders.use_point_embedder {
                Some(PointmapEmbedder::new(cfg.embedders.point_embedder_out_channels, vb.clone())?)
            } else {
                None
            },
            mask_embedder: if cfg.embedders.use_mask_embedder {
                Some(MaskEmbedder::new(cfg.embedders.mask_embedder_out_channels, vb.clone())?)
            } else {
                None
            },
            pose_embedder: if cfg.use_pose_embedder {
                Some(linear(cfg.pose_dim(), cfg.pose_embedder_out_channels, vb.pp("pose_embedder"), compute)?)
            } else {
                None
            },
            cfg: cfg.clone(),
            conv_path: ConvPath::Fast,
            shortcuts: true,
        })
    }

    /// Turn on (the default) or off the fast path's shortcuts whose results
    /// equal the full computation's up to float rounding: the constant-context
    /// shortcut (a condition item whose rows are all equal, such as the
    /// all-zero `neg_cond`, gives each block's cross-attention output without
    /// the query projection, scores and weighted sum) and, in a guided step,
    /// the input stage run once for both passes ([`Self::forward_guided`]).
    /// Off, the fast path computes everything, as the plain path always does.
    pub fn set_shortcuts(&mut self, on: bool) {
        self.shortcuts = on;
    }

    /// Every block's cross-attention keys and values for `cond` `[B, L, Cc]`,
    /// computed once for many [`Self::forward_prepared`] calls (a sampler's
    /// condition is the same at every step); fast path only.
    pub fn prepare_condition(&self, cond: &Tensor) -> Result<PreparedCondition> {
        let fast = self.input_layer.fast().is_some();
        Ok(PreparedCondition::for_model("SLat flow", &self.blocks, cond, self.cfg.cond_channels, fast, self.shortcuts)?)
    }

    /// [`Self::forward`] with a condition prepared by [`Self::prepare_condition`]
    /// (one item per batch item); fast path only.
    pub fn forward_prepared(&self, x: &SparseTensor, t: &Tensor, cond: &PreparedCondition) -> Result<SparseTensor> {
        self.forward_impl(x, t, Cond::Prepared(cond), None)
    }

    /// Select the sparse conv implementation (default: fast kernel).
    pub fn set_conv_path(&mut self, path: ConvPath) {
        self.conv_path = path;
    }

    /// Velocity for noisy latents `x` (`[N, in_channels]` feats), model-scale
    /// timesteps `t` `[B]` (1000·t) and condition tokens `cond` `[B, L, cond_channels]`.
    /// On the fast path the condition is prepared here
    /// ([`Self::prepare_condition`]); a sampler prepares it once per run and
    /// calls [`Self::forward_prepared`].
    pub fn forward(&self, x: &SparseTensor, t: &Tensor, cond: &Tensor) -> Result<SparseTensor> {
        self.forward_tensor(x, t, cond, None)
    }

    /// As [`forward`](Self::forward), also recording intermediates.
    pub fn forward_with_taps(&self, x: &SparseTensor, t: &Tensor, cond: &Tensor) -> Result<(SparseTensor, SLatFlowTaps)> {
        let mut taps = SLatFlowTaps::default();
        let y = self.forward_tensor(x, t, cond, Some(&mut taps))?;
        Ok((y, taps))
    }

    fn forward_tensor(&self, x: &SparseTensor, t: &Tensor, cond: &Tensor, taps: Option<&mut SLatFlowTaps>) -> Result<SparseTensor> {
        let b = x.batch_size;
        let (cb, _, cc) = cond.dims3()?;
        if cb != b || cc != self.cfg.cond_channels {
            return Err(Error::msg(format!("SLat flow: cond has shape {:?}, expected [{b}, L, {}]", cond.dims(), self.cfg.cond_channels)));
        }
        if self.input_layer.fast().is_some() {
            return self.forward_impl(x, t, Cond::Prepared(&self.prepare_condition(cond)?), taps);
        }
        self.forward_impl(x, t, Cond::Tensor(cond), taps)
    }

    fn forward_impl(&self, x: &SparseTensor, t: &Tensor, cond: Cond, mut taps: Option<&mut SLatFlowTaps>) -> Result<SparseTensor> {
        let b = x.batch_size;
        if t.dims() != [b] {
            return Err(Error::msg(format!("SLat flow: t has shape {:?}, expected [{b}]", t.dims())));
        }
        let cb = match cond {
            Cond::Tensor(c) => c.dim(0)?,
            Cond::Prepared(p) => p.batch(),
        };
        if cb != b {
            return Err(Error::msg(format!("SLat flow: condition of {cb} items for batch {b}")));
        }
        let stem = self.input_stage(x, t, taps.as_deref_mut())?;
        self.output_stage(stem, cond, taps)
    }

    /// Both passes of a guided step, conditional then unconditional, on the
    /// voxels of `x` (one item): a batch of two items, as [`Self::forward`]
    /// of `x` twice with `t` `[1]` for both and `cond` (two items, prepared by
    /// [`Self::prepare_condition`]). With the shortcuts on, the input layer and
    /// blocks, which see neither condition, run once for both items (the
    /// same algebra; the sparse convolutions round the rows of a lone item
    /// slightly differently than in a batch of two). Fast path only.
    pub fn forward_guided(&self, x: &SparseTensor, t: &Tensor, cond: &PreparedCondition) -> Result<SparseTensor> {
        if x.batch_size != 1 || t.dims() != [1] || cond.batch() != 2 {
            return Err(Error::msg(format!(
                "SLat flow: a guided step takes one item, t [1] and two conditions, got {} items, t {:?}, {} conditions",
                x.batch_size,
                t.dims(),
                cond.batch()
            )));
        }
        if self.shortcuts {
            return self.output_stage(self.input_stage(x, t, None)?.doubled()?, Cond::Prepared(cond), None);
        }
        let coords: Vec<[i32; 4]> = x.coords.iter().copied().chain(x.coords.iter().map(|c| [1, c[1], c[2], c[3]])).collect();
        let xs = SparseTensor::new(coords, Tensor::cat(&[&x.feats, &x.feats], 0)?, 2)?;
        self.forward_impl(&xs, &Tensor::cat(&[t, t], 0)?, Cond::Prepared(cond), None)
    }

    fn check_input(&self, x: &SparseTensor) -> Result<()> {
        if x.feats.dim(1)? != self.cfg.in_channels {
            return Err(Error::msg(format!("SLat flow: input has {} channels, expected {}", x.feats.dim(1)?, self.cfg.in_channels)));
        }
        Ok(())
    }

    /// The input layer and input blocks.
    fn input_stage(&self, x: &SparseTensor, t: &Tensor, mut taps: Option<&mut SLatFlowTaps>) -> Result<Stem> {
        self.check_input(x)?;
        let mut h = x.with_feats(self.input_layer.forward(&x.feats)?)?;
        let t_emb = self.t_embedder.forward(t)?;
        if let Some(tp) = taps.as_deref_mut() {
            tp.t_emb = Some(t_emb.clone());
        }
        let mut caches = Vec::new();
        let mut skips = Vec::new();
        for blk in &self.input_blocks {
            h = region(Region::IoBlocks, || blk.forward(&h, &t_emb, &mut caches, self.conv_path))?;
            skips.push(h.feats.clone());
            if let Some(tp) = taps.as_deref_mut() {
                tp.input_blocks.push(h.clone());
            }
        }
        Ok(Stem { h, t_emb, skips, caches })
    }

    /// The transformer blocks, output blocks and output layer.
    fn output_stage(&self, stem: Stem, cond: Cond, mut taps: Option<&mut SLatFlowTaps>) -> Result<SparseTensor> {
        let Stem { mut h, t_emb, mut skips, mut caches } = stem;
        let b = h.batch_size;
        let emb = match &self.ada_ln {
            Some(l) => l.forward(&t_emb.silu()?)?,
            None => t_emb.clone(),
        };

        let pe = abs_position_embedding(&xyz_tensor(&h)?, self.cfg.model_channels)?.to_dtype(h.feats.dtype())?;
        let mut feats = (&h.feats + pe)?;
        let ranges = h.batch_ranges();
        // Full attention within each item = the dense block applied per item.
        // On the fast path, items of one size (a guided step's two, on the
        // same voxels) are one dense batch: its kernels compute every row of
        // every product on its own, so this gives the bits of the item-by-item
        // loop. The plain path keeps the loop (candle's batched products round
        // differently, and it is the reference).
        let n0 = ranges.first().map_or(0, |r| r.len());
        let uniform =
            matches!(cond, Cond::Prepared(_)) && n0 > 0 && ranges.iter().enumerate().all(|(i, r)| r.start == i * n0 && r.len() == n0);
        let c = feats.dim(1)?;
        for (j, blk) in self.blocks.iter().enumerate() {
            let run = |x: &Tensor, emb: &Tensor, items: std::ops::Range<usize>| -> Result<Tensor> {
                Ok(match cond {
                    Cond::Tensor(cond) => blk.forward(x, emb, &cond.narrow(0, items.start, items.len())?)?,
                    Cond::Prepared(p) => blk.forward_prepared(x, emb, &p.block(j)?.narrow(items.start, items.len())?)?,
                })
            };
            feats = region(Region::Transformer, || -> Result<Tensor> {
                if uniform {
                    return Ok(run(&feats.reshape((b, n0, c))?, &emb, 0..b)?.reshape((b * n0, c))?);
                }
                let mut parts = Vec::with_capacity(b);
                for (i, r) in ranges.iter().enumerate() {
                    if r.is_empty() {
                        continue;
                    }
                    let xi = feats.narrow(0, r.start, r.len())?.unsqueeze(0)?;
                    parts.push(run(&xi, &emb.narrow(0, i, 1)?, i..i + 1)?.squeeze(0)?);
                }
                Ok(if parts.is_empty() { feats.clone() } else { Tensor::cat(&parts, 0)? })
            })?;
            if let Some(tp) = taps.as_deref_mut() {
                tp.blocks.push(feats.clone());
            }
        }
        h = h.with_feats(feats)?;

        for blk in &self.out_blocks {
            let skip = skips.pop().ok_or_else(|| Error::msg("SLat flow: more out blocks than skips"))?;
            h = region(Region::IoBlocks, || {
                let inp = if self.cfg.use_skip_connection { h.with_feats(Tensor::cat(&[&h.feats, &skip], 1)?)? } else { h };
                blk.forward(&inp, &t_emb, &mut caches, self.conv_path)
            })?;
        }

        let out = self.out_layer.forward(&layer_norm_plain(&h.feats, 1e-5)?)?;
        h.with_feats(out)
    }

    /// Build the cross-attention context (RecGen stage 2):
    /// - `image_tokens` `[B, L, C]` (DINOv2 tokens; RecGen passes patch tokens only);
    /// - `pointmap` `[B, 3, H, W]` and `mask` `[B, 1, H, W]`: embedded by the
    ///   Conv2d(k14, s14) embedders to `P = (H/14)(W/14)` tokens and added to the
    ///   last `P` image tokens (all of them when `P == L`, i.e. the patch tokens);
    /// - `pose` `[B, D]` or `[B, K, D]`: embedded and appended as extra tokens.
    ///
    /// Passing an input whose embedder is not enabled is an error.
    pub fn build_cond(
        &self,
        image_tokens: &Tensor,
        pointmap: Option<&Tensor>,
        mask: Option<&Tensor>,
        pose: Option<&Tensor>,
    ) -> Result<Tensor> {
        let (_, l, _) = image_tokens.dims3()?;
        let mut cond = image_tokens.clone();
        let embedded: [(&str, Option<&Tensor>, Option<&crate::model::stage1::embedders::PatchEmbedder>); 2] =
            [("pointmap", pointmap, self.point_embedder.as_ref().map(|e| &e.0)), ("mask", mask, self.mask_embedder.as_ref().map(|e| &e.0))];
        for (name, input, emb) in embedded {
            let Some(input) = input else { continue };
            let emb = emb.ok_or_else(|| Error::msg(format!("SLat flow: {name} given but its embedder is disabled")))?;
            let f = emb.forward(input)?; // [B, P, C]
            let p = f.dim(1)?;
            if p > l {
                return Err(Error::msg(format!("SLat flow: {name} gives {p} tokens but the image has only {l}")));
            }
            let tail = (cond.narrow(1, l - p, p)? + f)?;
            cond = if p == l { tail } else { Tensor::cat(&[&cond.narrow(1, 0, l - p)?, &tail], 1)? };
        }
        if let Some(pose) = pose {
            cond = Tensor::cat(&[&cond, &self.pose_tokens(pose)?], 1)?;
        }
        Ok(cond)
    }

    /// `pose_embedder(pose)` as context tokens: `[B, D]` → `[B, 1, C]`, `[B, K, D]` → `[B, K, C]`.
    pub fn pose_tokens(&self, pose: &Tensor) -> Result<Tensor> {
        let pe = self.pose_embedder.as_ref().ok_or_else(|| Error::msg("SLat flow: pose given but pose_embedder is disabled"))?;
        let d = self.cfg.pose_dim();
        if pose.dims().last() != Some(&d) || !(pose.rank() == 2 || pose.rank() == 3) {
            return Err(Error::msg(format!("SLat flow: pose has shape {:?}, expected [B, {d}] or [B, K, {d}]", pose.dims())));
        }
        let p = pe.forward(pose)?;
        Ok(if p.rank() == 2 { p.unsqueeze(1)? } else { p })
    }

    /// `(cond, neg_cond)` for one or more views, as RecGen's `get_cond` /
    /// `get_cond_multiview` + `_add_pose_cond_to_slat` with this model's
    /// embedders: views' patch tokens concatenated (no frame-token embedding
    /// in stage 2), `neg_cond` = zeros taken before the pointmap / mask
    /// features are added, then the pose tokens appended to `cond` and zeros
    /// of the same shape appended to `neg_cond`.
    pub fn condition(&self, views: &[ViewInputs], pose: Option<&Tensor>) -> Result<(Tensor, Tensor)> {
        let emb = CondEmbedders { point: self.point_embedder.as_ref(), mask: self.mask_embedder.as_ref(), frame: None };
        let (mut cond, mut neg) = build_condition(views, emb)?;
        if let Some(pose) = pose {
            let p = self.pose_tokens(pose)?;
            neg = Tensor::cat(&[&neg, &p.zeros_like()?], 1)?;
            cond = Tensor::cat(&[&cond, &p], 1)?;
        }
        Ok((cond, neg))
    }
}

/// What the input stage hands on: the coarse tokens, the timestep
/// embedding, the skip features and the downsample caches.
struct Stem {
    h: SparseTensor,
    t_emb: Tensor,
    skips: Vec<Tensor>,
    caches: Vec<DownsampleCache>,
}

impl Stem {
    /// The stem of a batch of two copies of this one-item stem: what the
    /// input stage gives for the same item twice (item 1's rows after item
    /// 0's, as a downsample orders them).
    fn doubled(self) -> Result<Self> {
        let twice = |c: &[[i32; 4]]| -> Vec<[i32; 4]> { c.iter().copied().chain(c.iter().map(|c| [1, c[1], c[2], c[3]])).collect() };
        let cat = |t: &Tensor| Tensor::cat(&[t, t], 0);
        let h = SparseTensor::new(twice(&self.h.coords), cat(&self.h.feats)?, 2)?;
        let skips = self.skips.iter().map(cat).collect::<candle_core::Result<_>>()?;
        let caches = self
            .caches
            .into_iter()
            .map(|c| {
                // Every coarse row has a fine row, so the coarse count is the largest index + 1.
                let coarse = c.inverse.iter().max().map_or(0, |&m| m + 1);
                let inverse = c.inverse.iter().copied().chain(c.inverse.iter().map(|&i| i + coarse)).collect();
                DownsampleCache { factor: c.factor, fine_coords: twice(&c.fine_coords), fine_batch_size: 2, inverse }
            })
            .collect();
        Ok(Self { h, t_emb: cat(&self.t_emb)?, skips, caches })
    }
}

/// Per-channel SLat normalisation (`slat_config … normalization`: mean/std).
#[derive(Debug, Clone)]
pub struct SLatNormalization {
    /// Per-channel mean `[C]`.
    pub mean: Vec<f32>,
    /// Per-channel standard deviation `[C]`.
    pub std: Vec<f32>,
}

impl SLatNormalization {
    /// From a JSON object `{"mean": [...], "std": [...]}`; errors name `file`.
    pub fn from_json(v: &serde_json::Value, file: &str) -> Result<Self> {
        #[derive(Deserialize)]
        struct Stats {
            mean: Vec<f32>,
            std: Vec<f32>,
        }
        let Stats { mean, std } = crate::util::json::from_value(v, file)?;
        if mean.len() != std.len() || mean.is_empty() {
            return Err(Error::config(file, "mean", "mean and std must be non-empty and of equal length"));
        }
        Ok(Self { mean, std })
    }

    fn stats(&self, feats: &Tensor) -> Result<(Tensor, Tensor)> {
        let c = feats.dim(D::Minus1)?;
        if c != self.mean.len() {
            return Err(Error::msg(format!("SLat normalization: {} channels, stats have {}", c, self.mean.len())));
        }
        let m = Tensor::from_slice(&self.mean, (1, c), feats.device())?.to_dtype(feats.dtype())?;
        let s = Tensor::from_slice(&self.std, (1, c), feats.device())?.to_dtype(feats.dtype())?;
        Ok((m, s))
    }

    /// `(x - mean) / std`.
    pub fn normalize(&self, feats: &Tensor) -> Result<Tensor> {
        let (m, s) = self.stats(feats)?;
        Ok(feats.broadcast_sub(&m)?.broadcast_div(&s)?)
    }

    /// `x · std + mean` (applied to sampled latents before decoding).
    pub fn denormalize(&self, feats: &Tensor) -> Result<Tensor> {
        let (m, s) = self.stats(feats)?;
        Ok(feats.broadcast_mul(&s)?.broadcast_add(&m)?)
    }
}

/// The stage-2 flow as a sampler model: the state is the `[N, C]` feature
/// tensor of a batch-1 sparse tensor on fixed coordinates.
pub struct SlatVelocity<'a> {
    /// The flow model.
    pub model: &'a SLatFlowModel,
    /// Voxel coordinates `(b, x, y, z)` of the state's rows, batch index 0.
    pub coords: &'a [[i32; 4]],
}

impl SlatVelocity<'_> {
    fn run(&self, state: &[Tensor], t_model: f32, cond: Cond) -> Result<Vec<Tensor>> {
        let [x] = state else { return Err(Error::msg("SLat sampler: state must be one feature tensor")) };
        let x = SparseTensor::new(self.coords.to_vec(), x.clone(), 1)?;
        let t = Tensor::full(t_model, 1, x.feats.device())?;
        let v = match cond {
            Cond::Tensor(c) => self.model.forward(&x, &t, c)?,
            Cond::Prepared(c) => self.model.forward_prepared(&x, &t, c)?,
        };
        Ok(vec![v.feats])
    }

    /// Conditional and unconditional passes as one batch of two items on
    /// the same coordinates; `cond` holds both conditions.
    fn run_cfg(&self, state: &[Tensor], t_model: f32, cond: Cond) -> Result<(Vec<Tensor>, Vec<Tensor>)> {
        let [x] = state else { return Err(Error::msg("SLat sampler: state must be one feature tensor")) };
        let n = self.coords.len();
        let v = match cond {
            Cond::Tensor(c) => {
                let coords: Vec<[i32; 4]> = self.coords.iter().copied().chain(self.coords.iter().map(|c| [1, c[1], c[2], c[3]])).collect();
                let xs = SparseTensor::new(coords, Tensor::cat(&[x, x], 0)?, 2)?;
                self.model.forward(&xs, &Tensor::full(t_model, 2, x.device())?, c)?
            }
            Cond::Prepared(c) => {
                let x1 = SparseTensor::new(self.coords.to_vec(), x.clone(), 1)?;
                self.model.forward_guided(&x1, &Tensor::full(t_model, 1, x.device())?, c)?
            }
        }
        .feats;
        Ok((vec![v.narrow(0, 0, n)?], vec![v.narrow(0, n, n)?]))
    }
}

impl VelocityModel for SlatVelocity<'_> {
    fn velocity(&self, state: &[Tensor], t_model: f32, cond: &Tensor) -> Result<Vec<Tensor>> {
        self.run(state, t_model, Cond::Tensor(cond))
    }

    /// Conditional and unconditional passes as one batch of two items on
    /// the same coordinates.
    fn velocity_cfg(&self, state: &[Tensor], t_model: f32, cond: &Tensor, neg: &Tensor) -> Result<(Vec<Tensor>, Vec<Tensor>)> {
        if cond.dims() != neg.dims() {
            return Err(Error::msg(format!("SLat sampler: cond {:?} and neg_cond {:?} differ in shape", cond.dims(), neg.dims())));
        }
        let both = Tensor::cat(&[cond, neg], 0)?;
        if self.model.input_layer.fast().is_some() {
            return self.run_cfg(state, t_model, Cond::Prepared(&self.model.prepare_condition(&both)?));
        }
        self.run_cfg(state, t_model, Cond::Tensor(&both))
    }

    /// On the fast path: the conditions prepared once for the run
    /// ([`SLatFlowModel::prepare_condition`]).
    fn prepare<'a>(&'a self, cond: &Tensor, neg_cond: Option<&Tensor>) -> Result<Option<Box<dyn VelocityModel + 'a>>> {
        if self.model.input_layer.fast().is_none() {
            return Ok(None);
        }
        Ok(Some(Box::new(PreparedRun::new(self, cond, neg_cond)?)))
    }
}

impl PrepareCondition for SlatVelocity<'_> {
    type Prepared = PreparedCondition;

    fn prepare_condition(&self, cond: &Tensor) -> Result<PreparedCondition> {
        self.model.prepare_condition(cond)
    }

    fn velocity_prepared(&self, state: &[Tensor], t_model: f32, cond: &PreparedCondition) -> Result<Vec<Tensor>> {
        self.run(state, t_model, Cond::Prepared(cond))
    }

    fn velocity_cfg_prepared(
        &self,
        state: &[Tensor],
        t_model: f32,
        cond: &PreparedCondition,
        neg: &PreparedCondition,
    ) -> Result<(Vec<Tensor>, Vec<Tensor>)> {
        self.run_cfg(state, t_model, Cond::Prepared(&PreparedCondition::cat(&[cond, neg])?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::VarMap;

    fn tiny_cfg() -> SLatFlowConfig {
        SLatFlowConfig::from_json(
            &serde_json::json!({
                "resolution": 8, "in_channels": 4, "out_channels": 4, "model_channels": 32, "cond_channels": 16,
                "num_blocks": 1, "num_heads": 2, "mlp_ratio": 2, "patch_size": 2, "num_io_res_blocks": 2,
                "io_block_channels": [8], "qk_rms_norm": true,
                "use_point_embedder": true, "point_embedder_out_channels": 16,
                "use_mask_embedder": true, "mask_embedder_out_channels": 16,
                "use_pose_embedder": true, "pose_embedder_out_channels": 16, "pose_representation": "9d_translation_scale"
            }),
            "t",
        )
        .unwrap()
    }

    fn random_model(cfg: &SLatFlowConfig) -> SLatFlowModel {
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        SLatFlowModel::new(cfg, vb.clone(), Compute::Plain).unwrap();
        // VarMap defaults many tensors to zero: randomise, then rebuild so the
        // conv host copies see the new values.
        for v in vm.all_vars() {
            let r = Tensor::randn(0f32, 0.2, v.shape(), &Device::Cpu).unwrap();
            v.set(&r).unwrap();
        }
        SLatFlowModel::new(cfg, vb, Compute::Plain).unwrap()
    }

    fn blob() -> SparseTensor {
        let mut coords = Vec::new();
        for b in 0..2 {
            for x in 0..8 {
                for y in 0..8 {
                    for z in 0..8 {
                        if (x - 4) * (x - 4) + (y - 3) * (y - 3) + (z - 4) * (z - 4) <= 6 + b {
                            coords.push([b, x, y, z]);
                        }
                    }
                }
            }
        }
        let feats = Tensor::randn(0f32, 1.0, (coords.len(), 4), &Device::Cpu).unwrap();
        SparseTensor::new(coords, feats, 2).unwrap()
    }

    #[test]
    fn conv_paths_agree_and_shapes_hold() -> Result<()> {
        let cfg = tiny_cfg();
        let mut m = random_model(&cfg);
        let x = blob();
        let t = Tensor::new(&[100f32, 900.], &Device::Cpu)?;
        let img = Tensor::randn(0f32, 1.0, (2, 5, 16), &Device::Cpu)?;
        let pm = Tensor::randn(0f32, 1.0, (2, 3, 28, 28), &Device::Cpu)?;
        let mask = Tensor::ones((2, 1, 28, 28), DType::F32, &Device::Cpu)?;
        let pose = Tensor::randn(0f32, 1.0, (2, 13), &Device::Cpu)?;
        let cond = m.build_cond(&img, Some(&pm), Some(&mask), Some(&pose))?;
        assert_eq!(cond.dims(), &[2, 6, 16]);
        // The first token (not a patch token) is untouched.
        assert_eq!(crate::util::max_abs_diff(&cond.narrow(1, 0, 1)?, &img.narrow(1, 0, 1)?)?, 0.0);
        let fast = m.forward(&x, &t, &cond)?;
        m.set_conv_path(ConvPath::Differentiable);
        let slow = m.forward(&x, &t, &cond)?;
        assert_eq!(fast.coords, x.coords);
        assert_eq!(fast.feats.dims(), &[x.len(), 4]);
        let d = crate::util::max_abs_diff(&fast.feats, &slow.feats)?;
        assert!(d < 1e-4, "fast vs differentiable: {d}");
        Ok(())
    }

    #[test]
    fn two_view_condition_with_pose_tokens() -> Result<()> {
        let m = random_model(&tiny_cfg());
        let dev = Device::Cpu;
        let view = |seed: f64| -> Result<ViewInputs> {
            Ok(ViewInputs {
                patch_tokens: Tensor::randn(seed as f32, 1.0, (1, 4, 16), &dev)?,
                pointmap: Some(Tensor::randn(0f32, 1.0, (1, 3, 28, 28), &dev)?),
                mask: Some(Tensor::ones((1, 1, 28, 28), DType::F32, &dev)?),
            })
        };
        let views = vec![view(0.0)?, view(1.0)?];
        let pose = Tensor::randn(0f32, 1.0, (1, 2, 13), &dev)?;
        let (cond, neg) = m.condition(&views, Some(&pose))?;
        assert_eq!(cond.dims(), &[1, 10, 16]);
        assert_eq!(neg.dims(), &[1, 10, 16]);
        assert_eq!(neg.abs()?.sum_all()?.to_scalar::<f32>()?, 0.0);
        // Each view's tokens are what the single-view builder gives; pose tokens last.
        for (i, v) in views.iter().enumerate() {
            let one = m.build_cond(&v.patch_tokens, v.pointmap.as_ref(), v.mask.as_ref(), None)?;
            assert!(crate::util::max_abs_diff(&cond.narrow(1, 4 * i, 4)?, &one)? < 1e-6);
        }
        assert!(crate::util::max_abs_diff(&cond.narrow(1, 8, 2)?, &m.pose_tokens(&pose)?)? < 1e-6);
        assert!(m.pose_tokens(&Tensor::zeros((1, 10), DType::F32, &dev)?).is_err());
        Ok(())
    }

    #[test]
    fn rejects_bad_inputs() -> Result<()> {
        let cfg = tiny_cfg();
        let m = random_model(&cfg);
        let x = blob();
        let t = Tensor::new(&[1f32], &Device::Cpu)?;
        let cond = Tensor::zeros((2, 3, 16), DType::F32, &Device::Cpu)?;
        assert!(m.forward(&x, &t, &cond).is_err());
        Ok(())
    }

    /// A guided step: the two items of one size run the blocks as one batch
    /// with the bits of item-by-item passes (plain and fast); the fast
    /// path's condition prepared once per run gives the bits of preparing it
    /// at every step; the shortcuts (the input stage once for both passes,
    /// the constant-context output for the all-zero `neg_cond`) move the
    /// velocities by float rounding only (QK norm in cross-attention on and off).
    #[test]
    fn guided_step_batched_and_prepared_match_full_computation() -> Result<()> {
        use crate::model::nn::fast::Precision;
        use crate::model::sampler::{FlowEulerGuidanceIntervalSampler, SamplerSettings, Unprepared};
        use crate::util::testing::{max_rel_diff, same_bits};
        let dev = Device::Cpu;
        for qk_cross in [false, true] {
            let mut cfg = tiny_cfg();
            cfg.qk_rms_norm_cross = qk_cross;
            // Seeded draws: the rounding differences below depend on the weights (over 30
            // random draws: 2e-7 to 2.3e-6 relative), so the test must not draw anew each run.
            let mut rng = crate::rng::SeededRng::new(31 + qk_cross as u64);
            let vm = VarMap::new();
            let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
            SLatFlowModel::new(&cfg, vb.clone(), Compute::Plain)?;
            // (By name: the VarMap's own order changes from run to run.)
            let mut vars: Vec<(String, candle_core::Var)> = vm.data().lock().unwrap().iter().map(|(k, v)| (k.clone(), v.clone())).collect();
            vars.sort_by(|a, b| a.0.cmp(&b.0));
            for (_, v) in vars {
                v.set(&(rng.randn(v.shape().dims(), &dev)? * 0.2)?)?;
            }
            let plain = SLatFlowModel::new(&cfg, vb.clone(), Compute::Plain)?;
            let fast = SLatFlowModel::new(&cfg, vb.clone(), Compute::fast(Precision::F32))?;
            let mut full = SLatFlowModel::new(&cfg, vb, Compute::fast(Precision::F32))?;
            full.set_shortcuts(false);
            let coords: Vec<[i32; 4]> = blob().coords.into_iter().filter(|c| c[0] == 0).collect();
            let x = rng.randn(&[coords.len(), 4], &dev)?;
            let cond = rng.randn(&[1, 6, 16], &dev)?;
            let neg = cond.zeros_like()?;
            let state = [x];
            // The blocks of a batch of two equal items against the item-by-item loop
            // (each block run on its recorded input, one item at a time, unprepared).
            let two: Vec<[i32; 4]> = coords.iter().copied().chain(coords.iter().map(|c| [1, c[1], c[2], c[3]])).collect();
            let xs = SparseTensor::new(two, Tensor::cat(&[&state[0], &state[0]], 0)?, 2)?;
            let t = Tensor::new(&[700f32, 700.], &dev)?;
            let conds = Tensor::cat(&[&cond, &rng.randn(&[1, 6, 16], &dev)?], 0)?;
            for (name, m) in [("plain", &plain), ("fast", &full), ("fast + shortcut", &fast)] {
                let (_, taps) = m.forward_with_taps(&xs, &t, &conds)?;
                let h = taps.input_blocks.last().unwrap();
                let pe = abs_position_embedding(&xyz_tensor(h)?, cfg.model_channels)?;
                let mut input = (&h.feats + pe)?;
                let emb = taps.t_emb.clone().unwrap();
                let k = h.len() / 2;
                for (blk, got) in m.blocks.iter().zip(&taps.blocks) {
                    let items = (0..2)
                        .map(|i| {
                            Ok(blk
                                .forward(&input.narrow(0, i * k, k)?.unsqueeze(0)?, &emb.narrow(0, i, 1)?, &conds.narrow(0, i, 1)?)?
                                .squeeze(0)?)
                        })
                        .collect::<Result<Vec<_>>>()?;
                    let want = Tensor::cat(&items, 0)?;
                    let d = crate::util::max_abs_diff(got, &want)?;
                    assert!(same_bits(got, &want)?, "qk_cross {qk_cross}, {name}: batched blocks change the bits (max diff {d:e})");
                    input = got.clone();
                }
            }
            // The input stage once for both passes, against the batch of two copies.
            let pc = fast.prepare_condition(&conds)?;
            let once = fast.forward_guided(&SparseTensor::new(coords.clone(), state[0].clone(), 1)?, &t.narrow(0, 0, 1)?, &pc)?;
            let twice = fast.forward_prepared(&xs, &t, &pc)?;
            assert_eq!(once.coords, twice.coords);
            let d = max_rel_diff(&once.feats, &twice.feats)?;
            eprintln!("slat_flow qk_cross {qk_cross}: input stage once {d:.2e} from twice");
            assert!(d <= 5e-6, "qk_cross {qk_cross}: input stage once {d:e} from twice");

            let vf = SlatVelocity { model: &full, coords: &coords };
            let (c0, u0) = vf.velocity_cfg(&state, 700.0, &cond, &neg)?;
            let vs = SlatVelocity { model: &fast, coords: &coords };
            let run = vs.prepare(&cond, Some(&neg))?.expect("the fast path prepares");
            let (c1, u1) = run.velocity_cfg(&state, 700.0, &cond, &neg)?;
            for (half, a, b) in [("conditional", &c1[0], &c0[0]), ("unconditional", &u1[0], &u0[0])] {
                let d = max_rel_diff(a, b)?;
                eprintln!("slat_flow qk_cross {qk_cross}: {half} velocity {d:.2e} from the full computation");
                assert!(d <= 5e-6, "qk_cross {qk_cross}: {half} velocity {d:e} from the full computation");
            }
            let (_, up) = SlatVelocity { model: &plain, coords: &coords }.velocity_cfg(&state, 700.0, &cond, &neg)?;
            assert!(max_rel_diff(&u1[0], &up[0])? <= 1e-5, "qk_cross {qk_cross}: fast vs plain");

            // Whole runs: keys and values once per run give the bits of once per step.
            let sampler = FlowEulerGuidanceIntervalSampler::new(SamplerSettings { steps: 3, ..Default::default() });
            let sample = |m: &dyn VelocityModel| sampler.sample(m, state.to_vec(), &cond, Some(&neg));
            let each_step = sample(&Unprepared(&vf))?;
            assert!(same_bits(&sample(&vf)?[0], &each_step[0])?, "qk_cross {qk_cross}: prepared run changes the bits");
            // s = 5: the unconditional rounding difference reaches the state times s.
            let d = max_rel_diff(&sample(&vs)?[0], &each_step[0])?;
            eprintln!("slat_flow qk_cross {qk_cross}: shortcut run {d:.2e} from the full run");
            assert!(d <= 1e-5, "qk_cross {qk_cross}: shortcut run {d:e} from the full run");
        }
        Ok(())
    }

    #[test]
    fn normalization_round_trips() -> Result<()> {
        let n = SLatNormalization::from_json(&serde_json::json!({"mean": [1.0, -2.0], "std": [2.0, 0.5]}), "t")?;
        let x = Tensor::new(&[[3f32, -1.0]], &Device::Cpu)?;
        let y = n.normalize(&x)?;
        assert_eq!(y.to_vec2::<f32>()?, vec![vec![1.0, 2.0]]);
        assert_eq!(n.denormalize(&y)?.to_vec2::<f32>()?, x.to_vec2::<f32>()?);
        Ok(())
    }
}
