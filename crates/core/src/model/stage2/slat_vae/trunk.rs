//! Shared transformer trunk of the structured-latent decoders (TRELLIS
//! `SparseTransformerBase`): input linear, absolute position embedding at the
//! model resolution, then pre-norm transformer blocks with swin (shifted
//! window) or full self-attention over sparse voxels.

use crate::model::nn::common::Linear;
use crate::model::nn::common::{abs_position_embedding, layer_norm_plain, linear, FeedForward, MultiHeadAttention, PeMode};
use crate::model::nn::fast::{self, Compute};
use crate::model::sparse::windowed::{sparse_self_attention, WindowPartition};
use crate::model::sparse::SparseTensor;
use crate::{Error, Result};
use candle_core::{Module, Tensor};
use candle_nn::VarBuilder;
use serde::{Deserialize, Serialize};

/// Self-attention pattern of the trunk's blocks (upstream `attn_mode`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AttnMode {
    /// Window `window_size`, shift `window_size/2` on odd blocks.
    #[default]
    Swin,
    /// All voxels of a batch item attend to each other.
    Full,
}

/// A config with [`TrunkArgs`] flattened in, from an `args` object. serde loses the
/// field path inside a flattened struct, so the trunk's fields are parsed on their own
/// first: a bad `model_channels` is named as such, not as "`args`".
pub(crate) fn from_json_with_trunk<T: serde::de::DeserializeOwned>(v: &serde_json::Value, file: &str) -> Result<T> {
    crate::util::json::from_value::<TrunkArgs>(v, file)?;
    crate::util::json::from_value(v, file)
}

/// The trunk's upstream constructor args, shared by the SLat decoders and
/// the SLat encoder (flattened into their configs). Unknown keys
/// (`use_fp16`, `qk_rms_norm`, ...) are ignored, as upstream's are.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrunkArgs {
    /// Transformer width (upstream `model_channels`).
    pub model_channels: usize,
    /// Latent channels per voxel (upstream `latent_channels`): the decoders' input, the encoder's output.
    pub latent_channels: usize,
    /// Number of transformer blocks (upstream `num_blocks`).
    pub num_blocks: usize,
    /// `None`: `model_channels / num_head_channels`.
    #[serde(default)]
    pub num_heads: Option<usize>,
    /// Default 64.
    #[serde(default)]
    pub num_head_channels: Option<usize>,
    /// Default 4.
    #[serde(default)]
    pub mlp_ratio: Option<f64>,
    /// Self-attention pattern (upstream `attn_mode`, default `swin`).
    #[serde(default)]
    pub attn_mode: AttnMode,
    /// Default 8.
    #[serde(default)]
    pub window_size: Option<usize>,
    /// Position embedding (upstream `pe_mode`); only `ape` is supported.
    #[serde(default)]
    pub pe_mode: PeMode,
}

/// Resolved trunk settings: [`TrunkArgs`] with defaults filled in and the head count computed.
#[derive(Debug, Clone)]
pub struct TrunkConfig {
    /// Width of the per-voxel input features.
    pub in_channels: usize,
    /// Transformer width.
    pub model_channels: usize,
    /// Number of transformer blocks.
    pub num_blocks: usize,
    /// Attention heads.
    pub num_heads: usize,
    /// Feed-forward hidden width over `model_channels`.
    pub mlp_ratio: f64,
    /// Self-attention pattern.
    pub attn_mode: AttnMode,
    /// Window side in voxels (swin mode).
    pub window_size: usize,
    /// Absolute position embedding (`pe_mode = "ape"`); otherwise none.
    pub ape: bool,
}

impl TrunkConfig {
    /// The trunk the args describe, its input being `latent_channels` wide
    /// (the decoders; the encoder sets its own `in_channels`).
    pub fn new(args: &TrunkArgs) -> Result<Self> {
        let model_channels = args.model_channels;
        let num_heads = match args.num_heads {
            Some(h) => h,
            None => model_channels / args.num_head_channels.unwrap_or(64).max(1),
        };
        let ape = match args.pe_mode {
            PeMode::Ape => true,
            PeMode::Rope => return Err(Error::msg("args: pe_mode `rope` not supported (ape)")),
        };
        if num_heads == 0 || !model_channels.is_multiple_of(num_heads) {
            return Err(Error::msg("args: model_channels must be a multiple of num_heads"));
        }
        Ok(Self {
            in_channels: args.latent_channels,
            model_channels,
            num_blocks: args.num_blocks,
            num_heads,
            mlp_ratio: args.mlp_ratio.unwrap_or(4.0),
            attn_mode: args.attn_mode,
            window_size: args.window_size.unwrap_or(8),
            ape,
        })
    }
}

/// `SparseTransformerBlock`: `x + attn(LN(x))`, `x + mlp(LN(x))`, LN without
/// affine, eps 1e-6.
#[derive(Debug, Clone)]
pub struct SparseTransformerBlock {
    /// Self-attention.
    pub attn: MultiHeadAttention,
    /// Feed-forward.
    pub mlp: FeedForward,
    /// Window shift (swin mode).
    pub shift: usize,
    compute: Compute,
}

impl SparseTransformerBlock {
    /// Apply the block to `feats` `[N, C]`, attention within the windows of `part`.
    /// On the fast path the norms are the fused LayerNorm kernel and the
    /// residuals one pass each (no candle temporaries for the mean, centred
    /// values and variance); the plain path is the differentiable reference.
    pub fn forward(&self, feats: &Tensor, part: &WindowPartition) -> Result<Tensor> {
        if let Some((_, isa)) = self.compute.fast_parts() {
            let h = sparse_self_attention(&self.attn, &fast::layer_norm(isa, feats, 1e-6, None, None)?, part)?;
            let x = fast::gated_residual(feats, &h, None)?;
            drop(h);
            let h = self.mlp.forward(&fast::layer_norm(isa, &x, 1e-6, None, None)?)?;
            return Ok(fast::gated_residual(&x, &h, None)?);
        }
        let h = sparse_self_attention(&self.attn, &layer_norm_plain(feats, 1e-6)?, part)?;
        let x = (feats + h)?;
        let h = self.mlp.forward(&layer_norm_plain(&x, 1e-6)?)?;
        Ok((x + h)?)
    }
}

/// The shared trunk (TRELLIS `SparseTransformerBase`): input linear, optional APE, transformer blocks.
#[derive(Debug, Clone)]
pub struct SparseTransformerBase {
    /// Its resolved settings.
    pub cfg: TrunkConfig,
    input_layer: Linear,
    /// The transformer blocks, in order.
    pub blocks: Vec<SparseTransformerBlock>,
}

impl SparseTransformerBase {
    /// Build the trunk with weights under `vb` (`input_layer.*`, `blocks.{j}.*`).
    pub fn new(cfg: &TrunkConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let c = cfg.model_channels;
        let input_layer = linear(cfg.in_channels, c, vb.pp("input_layer"), compute)?;
        let mut blocks = Vec::with_capacity(cfg.num_blocks);
        for j in 0..cfg.num_blocks {
            let b = vb.pp(format!("blocks.{j}"));
            blocks.push(SparseTransformerBlock {
                attn: MultiHeadAttention::new(c, cfg.num_heads, None, false, b.pp("attn"), compute)?,
                mlp: FeedForward::new(c, cfg.mlp_ratio, b.pp("mlp"), compute)?,
                shift: if j % 2 == 1 { cfg.window_size / 2 } else { 0 },
                compute,
            });
        }
        Ok(Self { cfg: cfg.clone(), input_layer, blocks })
    }

    fn partition(&self, x: &SparseTensor, shift: usize) -> Result<WindowPartition> {
        match self.cfg.attn_mode {
            AttnMode::Swin => WindowPartition::new(&x.coords, self.cfg.window_size, shift),
            AttnMode::Full => Ok(WindowPartition::per_batch(x)),
        }
    }

    /// Run the trunk; `tap(name, feats)` sees `input_layer` (before the
    /// position embedding, like a forward hook) and each `blocks.{j}` output.
    pub fn forward_with(&self, x: &SparseTensor, tap: &mut dyn FnMut(&str, &Tensor)) -> Result<Tensor> {
        let mut h = self.input_layer.forward(&x.feats)?;
        tap("input_layer", &h);
        if self.cfg.ape {
            let xyz: Vec<f32> = x.coords.iter().flat_map(|c| [c[1] as f32, c[2] as f32, c[3] as f32]).collect();
            let xyz = Tensor::from_vec(xyz, (x.len(), 3), h.device())?;
            h = (h + abs_position_embedding(&xyz, self.cfg.model_channels)?)?;
        }
        // Windows depend only on coords and the shift: compute each once.
        let parts = [self.partition(x, 0)?, self.partition(x, self.cfg.window_size / 2)?];
        for (j, blk) in self.blocks.iter().enumerate() {
            let part = if blk.shift == 0 { &parts[0] } else { &parts[1] };
            h = blk.forward(&h, part)?;
            tap(&format!("blocks.{j}"), &h);
        }
        Ok(h)
    }

    /// Run the trunk on `x` (feats `[N, in_channels]`): output feats `[N, model_channels]`.
    pub fn forward(&self, x: &SparseTensor) -> Result<Tensor> {
        self.forward_with(x, &mut |_, _| {})
    }
}
