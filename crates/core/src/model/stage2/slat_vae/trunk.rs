//! Shared transformer trunk of the structured-latent decoders (TRELLIS
//! `SparseTransformerBase`): input linear, absolute position embedding at the
//! model resolution, then pre-norm transformer blocks with swin (shifted
//! window) or full self-attention over sparse voxels.

use crate::model::nn::common::Linear;
use crate::model::nn::common::{abs_position_embedding, layer_norm_plain, linear, FeedForward, MultiHeadAttention};
use crate::model::nn::fast::Compute;
use crate::model::sparse::windowed::{sparse_self_attention, WindowPartition};
use crate::model::sparse::SparseTensor;
use crate::{Error, Result};
use candle_core::{Module, Tensor};
use candle_nn::VarBuilder;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AttnMode {
    /// Window `window_size`, shift `window_size/2` on odd blocks.
    Swin,
    /// All voxels of a batch item attend to each other.
    Full,
}

#[derive(Debug, Clone)]
pub struct TrunkConfig {
    pub in_channels: usize,
    pub model_channels: usize,
    pub num_blocks: usize,
    pub num_heads: usize,
    pub mlp_ratio: f64,
    pub attn_mode: AttnMode,
    pub window_size: usize,
    /// Absolute position embedding (`pe_mode = "ape"`); otherwise none.
    pub ape: bool,
}

impl TrunkConfig {
    /// Parse the upstream constructor args (`model_channels`, `latent_channels`,
    /// `num_blocks`, `num_heads` or `num_head_channels`, `mlp_ratio`,
    /// `attn_mode`, `window_size`, `pe_mode`).
    pub fn from_args(args: &serde_json::Value) -> Result<Self> {
        let get = |k: &str| args.get(k).and_then(|v| v.as_u64()).map(|v| v as usize);
        let model_channels = get("model_channels").ok_or_else(|| Error::msg("args: model_channels missing"))?;
        let in_channels = get("latent_channels").ok_or_else(|| Error::msg("args: latent_channels missing"))?;
        let num_blocks = get("num_blocks").ok_or_else(|| Error::msg("args: num_blocks missing"))?;
        let num_heads = match get("num_heads") {
            Some(h) => h,
            None => model_channels / get("num_head_channels").unwrap_or(64),
        };
        let mlp_ratio = args.get("mlp_ratio").and_then(|v| v.as_f64()).unwrap_or(4.0);
        let attn_mode = match args.get("attn_mode").and_then(|v| v.as_str()).unwrap_or("swin") {
            "swin" => AttnMode::Swin,
            "full" => AttnMode::Full,
            m => return Err(Error::msg(format!("args: attn_mode `{m}` not supported (swin, full)"))),
        };
        let window_size = get("window_size").unwrap_or(8);
        let ape = match args.get("pe_mode").and_then(|v| v.as_str()).unwrap_or("ape") {
            "ape" => true,
            m => return Err(Error::msg(format!("args: pe_mode `{m}` not supported (ape)"))),
        };
        if num_heads == 0 || model_channels % num_heads != 0 {
            return Err(Error::msg("args: model_channels must be a multiple of num_heads"));
        }
        Ok(Self { in_channels, model_channels, num_blocks, num_heads, mlp_ratio, attn_mode, window_size, ape })
    }
}

/// `SparseTransformerBlock`: `x + attn(LN(x))`, `x + mlp(LN(x))`, LN without
/// affine, eps 1e-6.
#[derive(Debug, Clone)]
pub struct SparseTransformerBlock {
    pub attn: MultiHeadAttention,
    pub mlp: FeedForward,
    /// Window shift (swin mode).
    pub shift: usize,
}

impl SparseTransformerBlock {
    pub fn forward(&self, feats: &Tensor, part: &WindowPartition) -> Result<Tensor> {
        let h = sparse_self_attention(&self.attn, &layer_norm_plain(feats, 1e-6)?, part)?;
        let x = (feats + h)?;
        let h = self.mlp.forward(&layer_norm_plain(&x, 1e-6)?)?;
        Ok((x + h)?)
    }
}

#[derive(Debug, Clone)]
pub struct SparseTransformerBase {
    pub cfg: TrunkConfig,
    input_layer: Linear,
    pub blocks: Vec<SparseTransformerBlock>,
}

impl SparseTransformerBase {
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

    pub fn forward(&self, x: &SparseTensor) -> Result<Tensor> {
        self.forward_with(x, &mut |_, _| {})
    }
}
