//! Stage 1: the sparse-structure flow transformer (TRELLIS
//! `SparseStructureFlowModel`) with RecGen's `SparseStructurePoseFlowModel`
//! additions: pose tokens appended to the voxel tokens, and the pointmap /
//! mask / frame-token conditioning embedders (spec §2, §9.1).
//!
//! Forward: patchify `[B, C, R, R, R]` → tokens `[B, (R/p)³, C·p³]` →
//! `input_layer` + `pos_emb` → (append `input_layer_pose(pose)` +
//! `pose_token_embedder`, no pos-emb) → N × modulated cross blocks → plain
//! LayerNorm (eps 1e-5) → split → `out_layer` + unpatchify, `out_layer_pose`.

use crate::model::nn::common::Linear;
use crate::model::nn::fast::Compute;
use candle_core::{DType, Device, Module, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

use crate::geometry::pose::PoseRepresentation;
use crate::model::nn::common::PeMode;
use crate::model::nn::common::{self, CrossBlockConfig, ModulatedTransformerCrossBlock, PreparedCondition, TimestepEmbedder};
use crate::model::sampler::{PrepareCondition, PreparedRun, VelocityModel};
use crate::model::stage1::embedders::{
    build_condition, CondEmbedderConfig, CondEmbedders, FrameTokenEmbedder, MaskEmbedder, PointmapEmbedder, ViewInputs,
};
use crate::rng::SeededRng;
use crate::util::profile::{region, Region};
use crate::{Error, Result};

/// Constructor arguments, named as upstream (`args` of the checkpoint JSON).
/// Pose tokens are built iff `pose_representation` is set (RecGen); without
/// it this is the plain TRELLIS model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SsFlowConfig {
    /// Side R of the dense latent grid (upstream `resolution`).
    pub resolution: usize,
    /// Latent channels Cin of the input (upstream `in_channels`).
    pub in_channels: usize,
    /// Channels Cout of the predicted velocity (upstream `out_channels`).
    pub out_channels: usize,
    /// Transformer width C (upstream `model_channels`).
    pub model_channels: usize,
    /// Condition token width Cc (upstream `cond_channels`).
    pub cond_channels: usize,
    /// Number of transformer blocks (upstream `num_blocks`).
    pub num_blocks: usize,
    /// Attention heads (upstream `num_heads`); None derives them from `num_head_channels`.
    #[serde(default)]
    pub num_heads: Option<usize>,
    /// Channels per head when `num_heads` is unset (upstream `num_head_channels`; default 64).
    #[serde(default = "default_head_channels")]
    pub num_head_channels: usize,
    /// MLP hidden width as a multiple of C (upstream `mlp_ratio`; default 4).
    #[serde(default = "default_mlp_ratio")]
    pub mlp_ratio: f64,
    /// Patch side p of the voxel patchify (upstream `patch_size`; default 2).
    #[serde(default = "default_patch_size")]
    pub patch_size: usize,
    /// Position embedding (upstream `pe_mode`); only `ape` is accepted.
    #[serde(default)]
    pub pe_mode: PeMode,
    /// Upstream runs the torso in fp16; this port computes in f32 (ignored).
    #[serde(default)]
    pub use_fp16: bool,
    /// Gradient checkpointing; no effect on values (ignored).
    #[serde(default)]
    pub use_checkpoint: bool,
    /// One model-level adaLN modulation shared by all blocks (upstream `share_mod`).
    #[serde(default)]
    pub share_mod: bool,
    /// RMS-normalise q and k in self-attention (upstream `qk_rms_norm`).
    #[serde(default)]
    pub qk_rms_norm: bool,
    /// RMS-normalise q and k in cross-attention (upstream `qk_rms_norm_cross`).
    #[serde(default)]
    pub qk_rms_norm_cross: bool,
    /// Point-map and mask embedders (their args, flattened).
    #[serde(flatten)]
    pub embedders: CondEmbedderConfig,
    /// Build the `frame_token_embedder` (`[2, cond_channels]` per-view embedding; RecGen `use_frame_token_embedder`).
    #[serde(default)]
    pub use_frame_token_embedder: bool,
    /// RecGen `use_asymmetric_mask`: not supported, must be false.
    #[serde(default)]
    pub use_asymmetric_mask: bool,
    /// Pose vector layout of the pose tokens (RecGen `pose_representation`); None: no pose tokens.
    #[serde(default)]
    pub pose_representation: Option<PoseRepresentation>,
    /// Pose tokens K (RecGen `num_pose_tokens`; default 1); K > 1 adds a `[K, C]` `pose_token_embedder`.
    #[serde(default = "default_pose_tokens")]
    pub num_pose_tokens: usize,
}

fn default_head_channels() -> usize {
    64
}
fn default_mlp_ratio() -> f64 {
    4.0
}
fn default_patch_size() -> usize {
    2
}
fn default_pose_tokens() -> usize {
    1
}

impl SsFlowConfig {
    /// Deserialise from an `args` object and check consistency; `file` names the source in errors.
    pub fn from_json(v: &serde_json::Value, file: &str) -> Result<Self> {
        let cfg: Self = crate::util::json::from_value(v, file)?;
        cfg.validate(file)?;
        Ok(cfg)
    }

    /// Attention heads: `num_heads`, else `model_channels / num_head_channels`.
    pub fn heads(&self) -> usize {
        self.num_heads.unwrap_or(self.model_channels / self.num_head_channels.max(1))
    }

    /// Pose vector width, or None for the plain TRELLIS model.
    pub fn pose_channels(&self) -> Option<usize> {
        self.pose_representation.map(PoseRepresentation::channels)
    }

    /// Number of voxel tokens, `(R/p)³`.
    pub fn num_tokens(&self) -> usize {
        (self.resolution / self.patch_size).pow(3)
    }

    /// Check the args are consistent and supported; `file` names the source in errors.
    pub fn validate(&self, file: &str) -> Result<()> {
        let err = |f: &str, m: String| Err(Error::config(file, f, m));
        if self.patch_size == 0 || self.resolution == 0 || !self.resolution.is_multiple_of(self.patch_size) {
            return err(
                "patch_size",
                format!("resolution {} must be a positive multiple of patch_size {}", self.resolution, self.patch_size),
            );
        }
        let h = self.heads();
        if h == 0 || !self.model_channels.is_multiple_of(h) {
            return err("num_heads", format!("model_channels {} not divisible by {h} heads", self.model_channels));
        }
        if self.pe_mode != PeMode::Ape {
            return err("pe_mode", "`rope` not supported (only \"ape\" is used by TRELLIS/RecGen)".into());
        }
        if self.use_asymmetric_mask {
            return err("use_asymmetric_mask", "not supported (false in the released RecGen config)".into());
        }
        if self.pose_representation.is_some() && self.num_pose_tokens == 0 {
            return err("num_pose_tokens", "must be ≥ 1".into());
        }
        if self.embedders.use_point_embedder && self.embedders.point_embedder_out_channels != self.cond_channels {
            return err("point_embedder_out_channels", "must equal cond_channels (its tokens are added to the condition)".into());
        }
        if self.embedders.use_mask_embedder && self.embedders.mask_embedder_out_channels != self.cond_channels {
            return err("mask_embedder_out_channels", "must equal cond_channels (its tokens are added to the condition)".into());
        }
        if self.mlp_ratio <= 0.0 || !self.mlp_ratio.is_finite() {
            return err("mlp_ratio", "must be positive".into());
        }
        Ok(())
    }

    fn block_config(&self) -> CrossBlockConfig {
        CrossBlockConfig {
            channels: self.model_channels,
            ctx_channels: self.cond_channels,
            heads: self.heads(),
            mlp_ratio: self.mlp_ratio,
            share_mod: self.share_mod,
            qk_rms_norm: self.qk_rms_norm,
            qk_rms_norm_cross: self.qk_rms_norm_cross,
        }
    }
}

/// The condition of one forward: a tensor (plain path), or prepared once for many (fast path).
#[derive(Clone, Copy)]
enum Cond<'a> {
    Tensor(&'a Tensor),
    Prepared(&'a PreparedCondition),
}

/// RecGen pose token I/O.
#[derive(Debug, Clone)]
struct PoseIo {
    input_layer_pose: Linear,
    out_layer_pose: Linear,
    /// `[K, C]` view-id embedding, present when `num_pose_tokens > 1`.
    pose_token_embedder: Option<Tensor>,
}

/// The stage-1 flow transformer over the dense `[B, Cin, R, R, R]` latent, with RecGen's optional pose tokens.
#[derive(Debug, Clone)]
pub struct SparseStructureFlowModel {
    /// The args it was built with.
    pub cfg: SsFlowConfig,
    input_layer: Linear,
    pos_emb: Tensor,
    t_embedder: TimestepEmbedder,
    /// Model-level `adaLN_modulation.1` with `share_mod`.
    share_mod: Option<Linear>,
    blocks: Vec<ModulatedTransformerCrossBlock>,
    out_layer: Linear,
    pose: Option<PoseIo>,
    /// `point_embedder`, when `use_point_embedder` is set.
    pub point_embedder: Option<PointmapEmbedder>,
    /// `mask_embedder`, when `use_mask_embedder` is set.
    pub mask_embedder: Option<MaskEmbedder>,
    /// `frame_token_embedder`, when `use_frame_token_embedder` is set.
    pub frame_token_embedder: Option<FrameTokenEmbedder>,
    /// Whether the constant-context shortcut is on (see [`SparseStructureFlowModel::set_shortcuts`]).
    shortcuts: bool,
}

impl SparseStructureFlowModel {
    /// Validate `cfg` and load the weights under `vb` (upstream names); a missing `pos_emb` is computed.
    pub fn new(cfg: &SsFlowConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        cfg.validate("ss_flow config")?;
        let c = cfg.model_channels;
        let p3 = cfg.patch_size.pow(3);
        let n = cfg.num_tokens();
        let pos_emb = if vb.contains_tensor("pos_emb") {
            vb.get((n, c), "pos_emb")?
        } else {
            Self::grid_position_embedding(cfg.resolution / cfg.patch_size, c, vb.device())?
        };
        let pose = match cfg.pose_channels() {
            Some(pc) => Some(PoseIo {
                input_layer_pose: common::linear(pc, c, vb.pp("input_layer_pose"), compute)?,
                out_layer_pose: common::linear(c, pc, vb.pp("out_layer_pose"), compute)?,
                pose_token_embedder: if cfg.num_pose_tokens > 1 {
                    Some(vb.get((cfg.num_pose_tokens, c), "pose_token_embedder")?)
                } else {
                    None
                },
            }),
            None => None,
        };
        let bcfg = cfg.block_config();
        let blocks = (0..cfg.num_blocks)
            .map(|i| ModulatedTransformerCrossBlock::new(&bcfg, vb.pp(format!("blocks.{i}")), compute))
            .collect::<candle_core::Result<Vec<_>>>()?;
        Ok(Self {
            cfg: cfg.clone(),
            input_layer: common::linear(cfg.in_channels * p3, c, vb.pp("input_layer"), compute)?,
            pos_emb,
            t_embedder: TimestepEmbedder::new(c, vb.pp("t_embedder"), compute)?,
            share_mod: if cfg.share_mod { Some(common::linear(c, 6 * c, vb.pp("adaLN_modulation.1"), compute)?) } else { None },
            blocks,
            out_layer: common::linear(c, cfg.out_channels * p3, vb.pp("out_layer"), compute)?,
            pose,
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
            frame_token_embedder: if cfg.use_frame_token_embedder {
                Some(FrameTokenEmbedder::new(cfg.cond_channels, vb.clone())?)
            } else {
                None
            },
            shortcuts: true,
        })
    }

    /// Turn on (the default) or off the fast path's shortcut whose results
    /// equal the full computation's up to float rounding: the constant-context
    /// shortcut (a condition item whose rows are all equal, such as the
    /// all-zero `neg_cond`, gives each block's cross-attention output without
    /// the query projection, scores and weighted sum). Off, the fast path
    /// computes everything, as the plain path always does.
    pub fn set_shortcuts(&mut self, on: bool) {
        self.shortcuts = on;
    }

    /// Every block's cross-attention keys and values for `cond` `[B, L, Cc]`,
    /// computed once for many [`Self::forward_prepared`] calls (a sampler's
    /// condition is the same at every step); fast path only.
    pub fn prepare_condition(&self, cond: &Tensor) -> Result<PreparedCondition> {
        let fast = self.input_layer.fast().is_some();
        Ok(PreparedCondition::for_model("ss_flow", &self.blocks, cond, self.cfg.cond_channels, fast, self.shortcuts)?)
    }

    /// APE of the `g³` token grid, coordinates in meshgrid-`ij` order (z fastest),
    /// equal to the upstream `pos_emb` buffer.
    pub fn grid_position_embedding(g: usize, channels: usize, device: &Device) -> Result<Tensor> {
        let coords: Vec<u32> = (0..g * g * g).flat_map(|i| [(i / (g * g)) as u32, ((i / g) % g) as u32, (i % g) as u32]).collect();
        let coords = Tensor::from_vec(coords, (g * g * g, 3), device)?;
        Ok(common::abs_position_embedding(&coords, channels)?)
    }

    /// `[B, C, R, R, R]` → `[B, (R/p)³, C·p³]`, channel index `c·p³ + (a·p² + b·p + c')`.
    pub fn patchify(&self, x: &Tensor) -> Result<Tensor> {
        let (b, c, d, h, w) = x.dims5()?;
        let p = self.cfg.patch_size;
        if p == 1 {
            return Ok(x.reshape((b, c, d * h * w))?.transpose(1, 2)?.contiguous()?);
        }
        let (dp, hp, wp) = (d / p, h / p, w / p);
        let y = x.reshape(vec![b, c, dp, p, hp, p, wp, p])?.permute(vec![0, 2, 4, 6, 1, 3, 5, 7])?.contiguous()?;
        Ok(y.reshape((b, dp * hp * wp, c * p * p * p))?)
    }

    /// Inverse of `patchify`: `[B, (R/p)³, C·p³]` → `[B, C, R, R, R]`.
    pub fn unpatchify(&self, h: &Tensor, channels: usize) -> Result<Tensor> {
        let (b, _, _) = h.dims3()?;
        let p = self.cfg.patch_size;
        let g = self.cfg.resolution / p;
        let r = self.cfg.resolution;
        if p == 1 {
            return Ok(h.transpose(1, 2)?.contiguous()?.reshape((b, channels, r, r, r))?);
        }
        let y = h.reshape(vec![b, g, g, g, channels, p, p, p])?.permute(vec![0, 4, 1, 5, 2, 6, 3, 7])?.contiguous()?;
        Ok(y.reshape((b, channels, r, r, r))?)
    }

    /// `t_embedder(t)` for model-scale `t` `[B]` → `[B, C]`.
    pub fn timestep_embedding(&self, t: &Tensor) -> Result<Tensor> {
        Ok(self.t_embedder.forward(t)?)
    }

    /// What the blocks receive: `t_emb`, or with `share_mod` the shared
    /// modulation `adaLN_modulation(t_emb)` `[B, 6C]`.
    pub fn block_modulation(&self, t_emb: &Tensor) -> Result<Tensor> {
        Ok(match &self.share_mod {
            Some(l) => l.forward(&t_emb.silu()?)?,
            None => t_emb.clone(),
        })
    }

    /// Velocity for the voxel latent `x` `[B, Cin, R, R, R]` and, for RecGen,
    /// the pose tokens `pose` `[B, K, P]` (or `[B, P]` for one token).
    /// `t` `[B]` is on the model scale; `cond` `[B or 1, L, Cc]`.
    /// Returns `(v [B, Cout, R, R, R], v_pose)` with `v_pose` shaped like
    /// upstream: `[B, K, P]`, squeezed to `[B, P]` when K = 1.
    ///
    /// On the fast path the condition is prepared here
    /// ([`Self::prepare_condition`]); a sampler prepares it once per run and
    /// calls [`Self::forward_prepared`].
    pub fn forward(&self, x: &Tensor, pose: Option<&Tensor>, t: &Tensor, cond: &Tensor) -> Result<(Tensor, Option<Tensor>)> {
        let b = x.dim(0)?;
        match cond.dims3()? {
            (cb, _, cc) if cc != self.cfg.cond_channels || (cb != b && cb != 1) => {
                Err(Error::msg(format!("ss_flow: cond shape {:?}, expected [{b} or 1, L, {}]", cond.dims(), self.cfg.cond_channels)))
            }
            // A batch-1 condition is prepared once for the whole batch.
            _ if self.input_layer.fast().is_some() => self.forward_impl(x, pose, t, Cond::Prepared(&self.prepare_condition(cond)?)),
            // The sampler repeats a batch-1 condition over the batch.
            (1, l, cc) if b > 1 => self.forward_impl(x, pose, t, Cond::Tensor(&cond.broadcast_as((b, l, cc))?.contiguous()?)),
            _ => self.forward_impl(x, pose, t, Cond::Tensor(cond)),
        }
    }

    /// [`Self::forward`] with a condition prepared by [`Self::prepare_condition`]
    /// (B items, or one for the whole batch); fast path only.
    pub fn forward_prepared(
        &self,
        x: &Tensor,
        pose: Option<&Tensor>,
        t: &Tensor,
        cond: &PreparedCondition,
    ) -> Result<(Tensor, Option<Tensor>)> {
        self.forward_impl(x, pose, t, Cond::Prepared(cond))
    }

    fn forward_impl(&self, x: &Tensor, pose: Option<&Tensor>, t: &Tensor, cond: Cond) -> Result<(Tensor, Option<Tensor>)> {
        let cfg = &self.cfg;
        let (b, c_in, d, hh, ww) = x.dims5()?;
        let r = cfg.resolution;
        if c_in != cfg.in_channels || d != r || hh != r || ww != r {
            return Err(Error::msg(format!("ss_flow: input shape {:?}, expected [B, {}, {r}, {r}, {r}]", x.dims(), cfg.in_channels)));
        }
        if t.dims() != [b] {
            return Err(Error::msg(format!("ss_flow: t shape {:?}, expected [{b}]", t.dims())));
        }

        let h = self.input_layer.forward(&self.patchify(x)?)?.broadcast_add(&self.pos_emb)?;
        let emb = self.block_modulation(&self.timestep_embedding(t)?)?;

        let (h, n_pose) = match pose {
            None => (h, 0),
            Some(pose) => {
                let Some(io) = &self.pose else {
                    return Err(Error::msg("ss_flow: pose given but the model has no pose tokens (pose_representation unset)"));
                };
                let pc = cfg.pose_channels().unwrap_or(0);
                let pose3 = match pose.dims() {
                    [pb, p] if *pb == b && *p == pc => pose.unsqueeze(1)?,
                    [pb, _, p] if *pb == b && *p == pc => pose.clone(),
                    _ => return Err(Error::msg(format!("ss_flow: pose shape {:?}, expected [{b}, K, {pc}]", pose.dims()))),
                };
                let k = pose3.dim(1)?;
                let mut hp = io.input_layer_pose.forward(&pose3)?;
                if let Some(e) = &io.pose_token_embedder {
                    if k > e.dim(0)? {
                        return Err(Error::msg(format!("ss_flow: {k} pose tokens but only {} pose_token_embedder rows", e.dim(0)?)));
                    }
                    hp = hp.broadcast_add(&e.narrow(0, 0, k)?.unsqueeze(0)?)?;
                }
                (Tensor::cat(&[h, hp], 1)?, k)
            }
        };

        let h = region(Region::Transformer, || -> Result<Tensor> {
            let mut h = h;
            match cond {
                Cond::Tensor(cond) => {
                    for block in &self.blocks {
                        h = block.forward(&h, &emb, cond)?;
                    }
                }
                Cond::Prepared(cond) => {
                    let cond = cond.expand(b)?;
                    for (i, block) in self.blocks.iter().enumerate() {
                        h = block.forward_prepared(&h, &emb, cond.block(i)?)?;
                    }
                }
            }
            Ok(h)
        })?;
        let h = common::layer_norm_plain(&h, 1e-5)?;
        let n = cfg.num_tokens();
        let v = self.unpatchify(&self.out_layer.forward(&h.narrow(1, 0, n)?)?, cfg.out_channels)?;
        let vp = match (&self.pose, n_pose) {
            (Some(io), k) if k > 0 => {
                let vp = io.out_layer_pose.forward(&h.narrow(1, n, k)?)?;
                Some(if k == 1 { vp.squeeze(1)? } else { vp })
            }
            _ => None,
        };
        Ok((v, vp))
    }

    /// `(cond, neg_cond)` from one or two views (RecGen `get_cond` /
    /// `get_cond_multiview`), using this model's embedders.
    pub fn condition(&self, views: &[ViewInputs]) -> Result<(Tensor, Tensor)> {
        let emb = CondEmbedders {
            point: self.point_embedder.as_ref(),
            mask: self.mask_embedder.as_ref(),
            frame: self.frame_token_embedder.as_ref(),
        };
        Ok(build_condition(views, emb)?)
    }

    /// Initial sampler state at t = 1: the latent noise `[B, Cin, R, R, R]`,
    /// then (RecGen) pose noise `[B, K, P]` (`[B, P]` when K = 1), drawn in
    /// that order from `rng`.
    pub fn initial_state(&self, rng: &mut SeededRng, batch: usize, device: &Device) -> Result<Vec<Tensor>> {
        let r = self.cfg.resolution;
        let mut s = vec![rng.randn(&[batch, self.cfg.in_channels, r, r, r], device)?];
        if let Some(pc) = self.cfg.pose_channels() {
            let k = self.cfg.num_pose_tokens;
            s.push(if k > 1 { rng.randn(&[batch, k, pc], device)? } else { rng.randn(&[batch, pc], device)? });
        }
        Ok(s)
    }

    fn run_state(&self, state: &[Tensor], t_model: f32, cond: Cond) -> Result<Vec<Tensor>> {
        if state.is_empty() || state.len() > 2 {
            return Err(Error::msg(format!("ss_flow: state must be [latent] or [latent, pose], got {} tensors", state.len())));
        }
        let b = state[0].dim(0)?;
        let t = Tensor::full(t_model, b, state[0].device())?.to_dtype(DType::F32)?;
        let (v, vp) = match cond {
            Cond::Tensor(c) => self.forward(&state[0], state.get(1), &t, c)?,
            Cond::Prepared(c) => self.forward_prepared(&state[0], state.get(1), &t, c)?,
        };
        Ok(match vp {
            Some(p) => vec![v, p],
            None => vec![v],
        })
    }
}

impl VelocityModel for SparseStructureFlowModel {
    fn velocity(&self, state: &[Tensor], t_model: f32, cond: &Tensor) -> Result<Vec<Tensor>> {
        self.run_state(state, t_model, Cond::Tensor(cond))
    }

    /// Conditional and unconditional passes batched into one forward (the
    /// state is duplicated along the batch); per-sample results are the same
    /// as two passes up to float rounding.
    fn velocity_cfg(&self, state: &[Tensor], t_model: f32, cond: &Tensor, neg: &Tensor) -> Result<(Vec<Tensor>, Vec<Tensor>)> {
        let b = state.first().ok_or_else(|| Error::msg("ss_flow: empty state"))?.dim(0)?;
        let over_batch = |c: &Tensor| -> Result<[usize; 3]> {
            let (cb, l, cc) = c.dims3()?;
            Ok([if cb == 1 { b } else { cb }, l, cc])
        };
        if over_batch(cond)? != over_batch(neg)? {
            return Err(Error::msg(format!("ss_flow: cond {:?} and neg_cond {:?} differ in shape", cond.dims(), neg.dims())));
        }
        if self.input_layer.fast().is_some() {
            let (c, n) = (self.prepare_condition(cond)?, self.prepare_condition(neg)?);
            return self.velocity_cfg_prepared(state, t_model, &c, &n);
        }
        let expand = |c: &Tensor| -> Result<Tensor> {
            let (cb, l, cc) = c.dims3()?;
            Ok(if cb == 1 && b > 1 { c.broadcast_as((b, l, cc))?.contiguous()? } else { c.clone() })
        };
        let (c, n) = (expand(cond)?, expand(neg)?);
        let doubled: Vec<Tensor> = state.iter().map(|s| Tensor::cat(&[s, s], 0)).collect::<candle_core::Result<_>>()?;
        split_cfg(self.run_state(&doubled, t_model, Cond::Tensor(&Tensor::cat(&[&c, &n], 0)?))?, b)
    }

    /// On the fast path: the conditions prepared once for the run
    /// ([`Self::prepare_condition`]).
    fn prepare<'a>(&'a self, cond: &Tensor, neg_cond: Option<&Tensor>) -> Result<Option<Box<dyn VelocityModel + 'a>>> {
        if self.input_layer.fast().is_none() {
            return Ok(None);
        }
        Ok(Some(Box::new(PreparedRun::new(self, cond, neg_cond)?)))
    }
}

impl PrepareCondition for SparseStructureFlowModel {
    type Prepared = PreparedCondition;

    fn prepare_condition(&self, cond: &Tensor) -> Result<PreparedCondition> {
        SparseStructureFlowModel::prepare_condition(self, cond)
    }

    fn velocity_prepared(&self, state: &[Tensor], t_model: f32, cond: &PreparedCondition) -> Result<Vec<Tensor>> {
        self.run_state(state, t_model, Cond::Prepared(cond))
    }

    /// As [`VelocityModel::velocity_cfg`]: one forward of the doubled batch.
    fn velocity_cfg_prepared(
        &self,
        state: &[Tensor],
        t_model: f32,
        cond: &PreparedCondition,
        neg: &PreparedCondition,
    ) -> Result<(Vec<Tensor>, Vec<Tensor>)> {
        let b = state.first().ok_or_else(|| Error::msg("ss_flow: empty state"))?.dim(0)?;
        let both = PreparedCondition::cat(&[&cond.expand(b)?, &neg.expand(b)?])?;
        let doubled: Vec<Tensor> = state.iter().map(|s| Tensor::cat(&[s, s], 0)).collect::<candle_core::Result<_>>()?;
        split_cfg(self.run_state(&doubled, t_model, Cond::Prepared(&both))?, b)
    }
}

/// The conditional and unconditional halves of a doubled batch's velocities.
fn split_cfg(both: Vec<Tensor>, b: usize) -> Result<(Vec<Tensor>, Vec<Tensor>)> {
    let split = |i: usize| -> Result<Vec<Tensor>> { Ok(both.iter().map(|v| v.narrow(0, i * b, b)).collect::<candle_core::Result<_>>()?) };
    Ok((split(0)?, split(1)?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_nn::VarMap;

    fn tiny_cfg(p: usize, pose: bool) -> SsFlowConfig {
        let mut v = serde_json::json!({
            "resolution": 4, "in_channels": 2, "out_channels": 2, "model_channels": 24,
            "cond_channels": 16, "num_blocks": 1, "num_heads": 2, "mlp_ratio": 2, "patch_size": p,
            "qk_rms_norm": true, "use_point_embedder": true, "point_embedder_out_channels": 16,
            "use_mask_embedder": true, "mask_embedder_out_channels": 16, "use_frame_token_embedder": true
        });
        if pose {
            v["pose_representation"] = "6d_translation_scale".into();
            v["num_pose_tokens"] = 2.into();
        }
        SsFlowConfig::from_json(&v, "test").unwrap()
    }

    fn random_model(cfg: &SsFlowConfig) -> Result<SparseStructureFlowModel> {
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        // Build once to create the variables, then fill them with seeded noise.
        let m = SparseStructureFlowModel::new(cfg, vb.clone(), Compute::Plain)?;
        let mut rng = SeededRng::new(7);
        for (_, var) in vm.data().lock().unwrap().iter() {
            let t = (rng.randn(var.dims(), &Device::Cpu)? * 0.2)?;
            var.set(&t)?;
        }
        let _ = m;
        SparseStructureFlowModel::new(cfg, vb, Compute::Plain)
    }

    #[test]
    fn patchify_roundtrip_and_channel_order() -> Result<()> {
        let cfg = tiny_cfg(2, false);
        let m = random_model(&cfg)?;
        let x = SeededRng::new(1).randn(&[1, 2, 4, 4, 4], &Device::Cpu)?;
        let tok = m.patchify(&x)?;
        assert_eq!(tok.dims(), &[1, 8, 16]);
        // token (1,0,1) = index 1·4 + 0·2 + 1 = 5; channel c·8 + (a·4 + b·2 + c') = x[c, 2+a, 0+b, 2+c'].
        let xv = x.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        let tv = tok.flatten_all()?.to_vec1::<f32>()?;
        for (c, a, bb, cc) in [(1usize, 1usize, 0usize, 1usize), (0, 0, 1, 0)] {
            let ch = c * 8 + a * 4 + bb * 2 + cc;
            let want = xv[((c * 4 + 2 + a) * 4 + bb) * 4 + 2 + cc];
            assert_eq!(tv[5 * 16 + ch], want);
        }
        let back = m.unpatchify(&tok, 2)?;
        assert_eq!((back - &x)?.abs()?.sum_all()?.to_scalar::<f32>()?, 0.0);
        Ok(())
    }

    #[test]
    fn pose_forward_shapes_and_computed_pos_emb() -> Result<()> {
        let cfg = tiny_cfg(1, true);
        let m = random_model(&cfg)?;
        let want = SparseStructureFlowModel::grid_position_embedding(4, 24, &Device::Cpu)?;
        assert_eq!((&m.pos_emb - want)?.abs()?.sum_all()?.to_scalar::<f32>()?, 0.0);
        let mut rng = SeededRng::new(3);
        let state = m.initial_state(&mut rng, 2, &Device::Cpu)?;
        assert_eq!(state[1].dims(), &[2, 2, 10]);
        let cond = rng.randn(&[1, 5, 16], &Device::Cpu)?;
        let t = Tensor::new(&[500f32, 100.0], &Device::Cpu)?;
        let (v, vp) = m.forward(&state[0], Some(&state[1]), &t, &cond)?;
        assert_eq!(v.dims(), &[2, 2, 4, 4, 4]);
        assert_eq!(vp.unwrap().dims(), &[2, 2, 10]);
        // Batched CFG equals two separate passes.
        let neg = cond.zeros_like()?;
        let (c2, u2) = m.velocity_cfg(&state, 300.0, &cond, &neg)?;
        let c1 = m.velocity(&state, 300.0, &cond)?;
        let u1 = m.velocity(&state, 300.0, &neg)?;
        for (a, b) in c1.iter().chain(&u1).zip(c2.iter().chain(&u2)) {
            let d = (a - b)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "batched CFG differs by {d}");
        }
        // Voxel velocity depends on the pose tokens (they share self-attention).
        let (v2, _) = m.forward(&state[0], Some(&(&state[1] + 1.0)?), &t, &cond)?;
        assert!((v - v2)?.abs()?.sum_all()?.to_scalar::<f32>()? > 0.0);
        // Pose shape errors are reported, not panicked.
        assert!(m.forward(&state[0], Some(&Tensor::zeros((2, 3), DType::F32, &Device::Cpu)?), &t, &cond).is_err());
        Ok(())
    }

    /// The whole model built on the fast kernels agrees with the plain one
    /// (same weights): f32 tightly, bf16 within its rounding.
    #[test]
    fn fast_model_matches_plain() -> Result<()> {
        use crate::model::nn::fast::Precision;
        let cfg = tiny_cfg(1, true);
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu);
        let plain = SparseStructureFlowModel::new(&cfg, vb.clone(), Compute::Plain)?;
        let mut rng = SeededRng::new(7);
        for (_, var) in vm.data().lock().unwrap().iter() {
            var.set(&(rng.randn(var.dims(), &Device::Cpu)? * 0.2)?)?;
        }
        let state = plain.initial_state(&mut rng, 2, &Device::Cpu)?;
        let cond = rng.randn(&[2, 5, 16], &Device::Cpu)?;
        let t = Tensor::new(&[500f32, 100.0], &Device::Cpu)?;
        let (v0, p0) = plain.forward(&state[0], Some(&state[1]), &t, &cond)?;
        for (p, tol) in [(Precision::F32, 2e-5f32), (Precision::Bf16, 5e-2)] {
            let fast = SparseStructureFlowModel::new(&cfg, vb.clone(), Compute::fast(p))?;
            let (v1, p1) = fast.forward(&state[0], Some(&state[1]), &t, &cond)?;
            let scale = v0.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?.max(1.0);
            let dv = (&v1 - &v0)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            let dp = (p1.unwrap() - p0.as_ref().unwrap())?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(dv <= tol * scale && dp <= tol * scale, "{p}: v diff {dv}, pose diff {dp} (scale {scale})");
        }
        Ok(())
    }

    /// The fast model's condition prepared once per sampling run against the
    /// full computation, with and without QK norm in cross-attention: the
    /// keys and values computed once give the same bits as computing them at
    /// every step; the constant-context shortcut of the all-zero `neg_cond`
    /// keeps the conditional half's bits and moves the unconditional half by
    /// float rounding only. Thread counts do not change the bits.
    #[test]
    fn prepared_sampling_matches_full_computation() -> Result<()> {
        use crate::model::nn::fast::Precision;
        use crate::model::sampler::{FlowEulerGuidanceIntervalSampler, SamplerSettings, Unprepared};
        use crate::util::testing::{max_rel_diff, same_bits};
        let dev = Device::Cpu;
        for qk_cross in [false, true] {
            let mut cfg = tiny_cfg(1, true);
            cfg.qk_rms_norm_cross = qk_cross;
            let vm = VarMap::new();
            let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
            SparseStructureFlowModel::new(&cfg, vb.clone(), Compute::Plain)?;
            let mut rng = SeededRng::new(17);
            for (_, var) in vm.data().lock().unwrap().iter() {
                var.set(&(rng.randn(var.dims(), &dev)? * 0.2)?)?;
            }
            let fast = SparseStructureFlowModel::new(&cfg, vb.clone(), Compute::fast(Precision::F32))?;
            let mut full = SparseStructureFlowModel::new(&cfg, vb.clone(), Compute::fast(Precision::F32))?;
            full.set_shortcuts(false);
            let plain = SparseStructureFlowModel::new(&cfg, vb, Compute::Plain)?;
            let state = fast.initial_state(&mut rng, 1, &dev)?;
            let cond = rng.randn(&[1, 5, 16], &dev)?;
            let neg = cond.zeros_like()?;

            // One guided step.
            let (c0, u0) = full.velocity_cfg(&state, 700.0, &cond, &neg)?;
            let run = fast.prepare(&cond, Some(&neg))?.expect("the fast path prepares");
            let (c1, u1) = run.velocity_cfg(&state, 700.0, &cond, &neg)?;
            for (a, b) in c1.iter().zip(&c0) {
                assert!(same_bits(a, b)?, "qk_cross {qk_cross}: the conditional velocity changed");
            }
            for (a, b) in u1.iter().zip(&u0) {
                let d = max_rel_diff(a, b)?;
                eprintln!("ss_flow qk_cross {qk_cross}: unconditional velocity {d:.2e} from the full computation");
                assert!(d <= 1e-6, "qk_cross {qk_cross}: unconditional velocity {d:e} from the full computation");
            }
            let (cp, up) = plain.velocity_cfg(&state, 700.0, &cond, &neg)?;
            for (a, b) in c1.iter().chain(&u1).zip(cp.iter().chain(&up)) {
                assert!(max_rel_diff(a, b)? <= 1e-5, "qk_cross {qk_cross}: fast vs plain");
            }

            // Whole runs (4 steps, 2 guided).
            let sampler = FlowEulerGuidanceIntervalSampler::new(SamplerSettings { steps: 4, ..Default::default() });
            let sample = |m: &dyn VelocityModel| sampler.sample(m, state.clone(), &cond, Some(&neg));
            // Unprepared: every step computes the condition's keys and values itself.
            let each_step = sample(&Unprepared(&full))?;
            let once = sample(&full)?;
            for (a, b) in once.iter().zip(&each_step) {
                assert!(same_bits(a, b)?, "qk_cross {qk_cross}: keys and values once per run change the bits");
            }
            // The guided velocity is (1+s)·v(cond) − s·v(neg) with s = 5 here: the
            // unconditional rounding difference reaches the state times s, step after step.
            let short = sample(&fast)?;
            for (a, b) in short.iter().zip(&once) {
                let d = max_rel_diff(a, b)?;
                eprintln!("ss_flow qk_cross {qk_cross}: shortcut run {d:.2e} from the full run");
                assert!(d <= 1e-5, "qk_cross {qk_cross}: shortcut run {d:e} from the full run");
            }
            for threads in [1, 3] {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().map_err(|e| Error::msg(e.to_string()))?;
                let again = pool.install(|| sample(&fast))?;
                for (a, b) in again.iter().zip(&short) {
                    assert!(same_bits(a, b)?, "{threads} threads change the bits");
                }
            }
        }
        Ok(())
    }

    #[test]
    fn config_validation() {
        let mut v = serde_json::to_value(tiny_cfg(1, true)).unwrap();
        v["pose_representation"] = "euler".into();
        assert!(SsFlowConfig::from_json(&v, "t").is_err());
        let mut v = serde_json::to_value(tiny_cfg(1, false)).unwrap();
        v["num_heads"] = 5.into();
        assert!(SsFlowConfig::from_json(&v, "t").is_err());
    }
}
