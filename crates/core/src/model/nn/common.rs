//! Building blocks shared by the transformer models (TRELLIS `modules/`):
//! norms, timestep and position embeddings, attention, MLP, and the
//! adaLN-modulated cross-attention block. Every constructor takes the
//! [`Compute`] path of its layers: with [`Compute::Plain`] everything is plain
//! candle ops, differentiable for training; with a fast compute the same layers
//! run the inference kernels of `recon-kernels` (see [`crate::model::nn::fast`]).

use std::sync::Arc;

use candle_core::{CpuStorage, DType, Layout, Module, Result, Shape, Tensor, D};
use candle_nn::VarBuilder;
use rayon::prelude::*;

pub use crate::model::nn::fast::Linear;
use crate::model::nn::fast::{self, Activation, AttnLayout, AttnSegment, Compute};

/// Position embedding of the transformers (`pe_mode`): TRELLIS offers
/// absolute (`ape`) and rotary (`rope`); RecGen uses `ape`, the only one here.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PeMode {
    /// Absolute sin/cos position embedding (`ape`), see [`abs_position_embedding`].
    #[default]
    Ape,
    /// Rotary position embedding (`rope`); parsed, but the models here refuse it.
    Rope,
}

/// Linear layer with bias, named as in the checkpoint (`{prefix}.weight`,
/// `{prefix}.bias`), on the `compute` path.
pub fn linear(in_dim: usize, out_dim: usize, vb: VarBuilder, compute: Compute) -> Result<Linear> {
    Linear::new(candle_nn::linear(in_dim, out_dim, vb)?, compute)
}

/// LayerNorm over the last dim without affine parameters (computed in f32).
pub fn layer_norm_plain(x: &Tensor, eps: f64) -> Result<Tensor> {
    crate::util::profile::timed(
        crate::util::profile::Kind::Norm,
        || 0,
        || {
            let dtype = x.dtype();
            let x = x.to_dtype(DType::F32)?;
            let mean = x.mean_keepdim(D::Minus1)?;
            let xc = x.broadcast_sub(&mean)?;
            let var = xc.sqr()?.mean_keepdim(D::Minus1)?;
            xc.broadcast_div(&(var + eps)?.sqrt()?)?.to_dtype(dtype)
        },
    )
}

/// Affine LayerNorm over the last dim (`{prefix}.weight`, `{prefix}.bias`).
#[derive(Debug, Clone)]
pub struct LayerNorm {
    weight: Tensor,
    bias: Tensor,
    eps: f64,
    compute: Compute,
}

impl LayerNorm {
    /// Load `{prefix}.weight` and `{prefix}.bias`, both `[dim]`, with epsilon `eps`.
    pub fn new(dim: usize, eps: f64, vb: VarBuilder, compute: Compute) -> Result<Self> {
        Ok(Self { weight: vb.get(dim, "weight")?, bias: vb.get(dim, "bias")?, eps, compute })
    }
    /// Normalise `x` `[..., dim]` over its last dim, then scale and shift.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if let Some((_, isa)) = self.compute.fast_parts() {
            return fast::layer_norm(isa, x, self.eps, Some(&self.weight), Some(&self.bias));
        }
        layer_norm_plain(x, self.eps)?.broadcast_mul(&self.weight)?.broadcast_add(&self.bias)
    }
}

/// Sinusoidal timestep embedding followed by an MLP (`t_embedder.mlp.{0,2}`).
/// `t` is on the model scale (the sampler passes 1000·t). Embedding is [cos, sin].
#[derive(Debug, Clone)]
pub struct TimestepEmbedder {
    mlp0: Linear,
    mlp2: Linear,
    freq_size: usize,
}

impl TimestepEmbedder {
    /// A 256-frequency embedder with MLP `256 → hidden → hidden` (`mlp.0`, `mlp.2`).
    pub fn new(hidden: usize, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let freq_size = 256;
        Ok(Self {
            mlp0: linear(freq_size, hidden, vb.pp("mlp.0"), compute)?,
            mlp2: linear(hidden, hidden, vb.pp("mlp.2"), compute)?,
            freq_size,
        })
    }

    /// `t` `[N]` → `[N, 2·(dim/2)]` f32: `[cos(t·f_k), sin(t·f_k)]` with `f_k = 10000^(−k/(dim/2))`.
    pub fn sinusoidal(t: &Tensor, dim: usize) -> Result<Tensor> {
        let half = dim / 2;
        let freqs: Vec<f32> = (0..half).map(|k| (-(10000f64.ln()) * k as f64 / half as f64).exp() as f32).collect();
        let freqs = Tensor::from_vec(freqs, (1, half), t.device())?;
        let args = t.to_dtype(DType::F32)?.unsqueeze(1)?.broadcast_mul(&freqs)?;
        Tensor::cat(&[args.cos()?, args.sin()?], 1)
    }

    /// Timesteps `t` `[N]` (model scale) → embeddings `[N, hidden]` (MLP with SiLU).
    pub fn forward(&self, t: &Tensor) -> Result<Tensor> {
        let e = Self::sinusoidal(t, self.freq_size)?;
        self.mlp2.forward(&self.mlp0.forward(&e)?.silu()?)
    }
}

/// Absolute sin/cos position embedding of integer coordinates (TRELLIS
/// `AbsolutePositionEmbedder`): per axis [sin(x·f), cos(x·f)] with
/// `freq_dim = C/3/2` frequencies, axes concatenated, zero-padded to C.
/// `coords` is `[N, 3]` (any numeric dtype); returns `[N, C]` f32.
pub fn abs_position_embedding(coords: &Tensor, channels: usize) -> Result<Tensor> {
    let n = coords.dim(0)?;
    let ndim = coords.dim(1)?;
    let freq_dim = channels / ndim / 2;
    let freqs: Vec<f32> = (0..freq_dim).map(|k| (1.0 / 10000f64.powf(k as f64 / freq_dim as f64)) as f32).collect();
    let freqs = Tensor::from_vec(freqs, (1, 1, freq_dim), coords.device())?;
    let x = coords.to_dtype(DType::F32)?.unsqueeze(2)?.broadcast_mul(&freqs)?; // [N, 3, F]
    let emb = Tensor::cat(&[x.sin()?, x.cos()?], 2)?.reshape((n, ndim * 2 * freq_dim))?;
    let used = ndim * 2 * freq_dim;
    if used < channels {
        let pad = Tensor::zeros((n, channels - used), DType::F32, coords.device())?;
        Tensor::cat(&[emb, pad], 1)
    } else {
        Ok(emb)
    }
}

/// `MultiHeadRMSNorm`: L2-normalise each head vector, times gamma[h, :]·√d.
#[derive(Debug, Clone)]
pub struct MultiHeadRmsNorm {
    pub(crate) gamma: Tensor, // [H, D]
    scale: f64,
}

impl MultiHeadRmsNorm {
    /// Load `{prefix}.gamma` `[heads, head_dim]`.
    pub fn new(heads: usize, head_dim: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self { gamma: vb.get((heads, head_dim), "gamma")?, scale: (head_dim as f64).sqrt() })
    }
    /// `x`: `[B, L, H, D]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let dtype = x.dtype();
        let x = x.to_dtype(DType::F32)?;
        // F.normalize uses max(norm, 1e-12).
        let norm = x.sqr()?.sum_keepdim(D::Minus1)?.sqrt()?.clamp(1e-12, f64::INFINITY)?;
        (x.broadcast_div(&norm)?.broadcast_mul(&self.gamma)? * self.scale)?.to_dtype(dtype)
    }
}

/// Softmax attention. `q`: `[B, H, Lq, D]`, `k`/`v`: `[B, H, Lk, D]` → `[B, H, Lq, D]`.
/// Query rows are processed in chunks so the score matrix never exceeds
/// about 32 M elements, whatever the sequence length.
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
    let (b, h, lq, d) = q.dims4()?;
    let lk = k.dim(2)?;
    let scale = 1.0 / (d as f64).sqrt();
    let kt = k.transpose(2, 3)?.contiguous()?;
    let v = v.contiguous()?;
    let budget = 32usize << 20;
    let chunk = (budget / (b * h * lk).max(1)).clamp(1, lq.max(1));
    let mut outs = Vec::with_capacity(lq.div_ceil(chunk));
    let mut start = 0;
    while start < lq {
        let len = chunk.min(lq - start);
        let qc = (q.narrow(2, start, len)? * scale)?.contiguous()?;
        let s = qc.matmul(&kt)?;
        let p = softmax_last_dim(&s)?;
        outs.push(p.matmul(&v)?);
        start += len;
    }
    if outs.len() == 1 {
        Ok(outs.pop().unwrap())
    } else {
        Tensor::cat(&outs, 2)
    }
}

/// Softmax over the last dim with a backward pass. The forward is candle's
/// `softmax_last_dim` kernel step for step (so inference results are
/// bit-identical to it), but candle's op has no gradient, and every
/// transformer here must stay trainable.
pub fn softmax_last_dim(x: &Tensor) -> Result<Tensor> {
    if x.device().is_cpu() && x.dtype() == DType::F32 {
        x.contiguous()?.apply_op1(SoftmaxLastDim)
    } else {
        candle_nn::ops::softmax(x, D::Minus1)
    }
}

struct SoftmaxLastDim;

impl candle_core::CustomOp1 for SoftmaxLastDim {
    fn name(&self) -> &'static str {
        "recon-softmax-last-dim"
    }

    fn cpu_fwd(&self, storage: &CpuStorage, layout: &Layout) -> Result<(CpuStorage, Shape)> {
        use candle_core::cpu::kernels::VecOps;
        let CpuStorage::F32(src) = storage else { candle_core::bail!("softmax: f32 only") };
        let Some((o1, o2)) = layout.contiguous_offsets() else { candle_core::bail!("softmax: input must be contiguous") };
        let src = &src[o1..o2];
        let dims = layout.shape().dims();
        let n = dims[dims.len() - 1];
        let mut dst = vec![0f32; src.len()];
        src.par_chunks(n).zip(dst.par_chunks_mut(n)).for_each(|(s, d)| {
            let mut max = f32::NEG_INFINITY;
            // SAFETY: both slices hold exactly `n` elements.
            unsafe { f32::vec_reduce_max(s.as_ptr(), &mut max, n) };
            for (a, b) in s.iter().zip(d.iter_mut()) {
                *b = (*a - max).exp();
            }
            let mut sum = 0f32;
            unsafe { f32::vec_reduce_sum(d.as_ptr(), &mut sum, n) };
            for b in d.iter_mut() {
                *b /= sum;
            }
        });
        Ok((CpuStorage::F32(dst), Shape::from_dims(dims)))
    }

    /// dL/dx = y ⊙ (g − Σ g ⊙ y) along the last dim.
    fn bwd(&self, _arg: &Tensor, res: &Tensor, grad_res: &Tensor) -> Result<Option<Tensor>> {
        let dot = (grad_res * res)?.sum_keepdim(D::Minus1)?;
        Ok(Some(res.mul(&grad_res.broadcast_sub(&dot)?)?))
    }
}

/// TRELLIS `FeedForwardNet`: Linear → GELU(tanh) → Linear (`mlp.0`, `mlp.2`).
#[derive(Debug, Clone)]
pub struct FeedForward {
    fc1: Linear,
    fc2: Linear,
}

/// Rows of a fast feed-forward's hidden activations alive at once (32 MB at
/// 1024 channels × 4).
pub const FFN_ROWS: usize = 2048;

impl FeedForward {
    /// `channels → channels·mlp_ratio → channels` (`mlp.0`, `mlp.2`).
    pub fn new(channels: usize, mlp_ratio: f64, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let hidden = (channels as f64 * mlp_ratio) as usize;
        Ok(Self { fc1: linear(channels, hidden, vb.pp("mlp.0"), compute)?, fc2: linear(hidden, channels, vb.pp("mlp.2"), compute)? })
    }
    /// GELU (tanh form) is fused into `fc1` on the fast path, which also
    /// runs [`FFN_ROWS`] rows at a time (bounded hidden activations).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if let (Some(f1), Some(f2)) = (self.fc1.fast(), self.fc2.fast()) {
            return fast::mlp_by_rows(f1, f2, x, Activation::GeluTanh, FFN_ROWS);
        }
        self.fc2.forward(&self.fc1.forward_act(x, Activation::GeluTanh)?)
    }
}

/// TRELLIS `MultiHeadAttention` (self: `to_qkv`; cross: `to_q` + `to_kv`; `to_out`),
/// with optional QK RMS-norm.
#[derive(Debug, Clone)]
pub struct MultiHeadAttention {
    /// Number of attention heads.
    pub heads: usize,
    /// Channels per head (`channels / heads`).
    pub head_dim: usize,
    to_qkv: Option<Linear>,
    to_q: Option<Linear>,
    to_kv: Option<Linear>,
    q_norm: Option<MultiHeadRmsNorm>,
    k_norm: Option<MultiHeadRmsNorm>,
    to_out: Linear,
    compute: Compute,
}

impl MultiHeadAttention {
    /// `ctx_channels = None` builds self-attention.
    pub fn new(
        channels: usize,
        heads: usize,
        ctx_channels: Option<usize>,
        qk_rms_norm: bool,
        vb: VarBuilder,
        compute: Compute,
    ) -> Result<Self> {
        let head_dim = channels / heads;
        let (to_qkv, to_q, to_kv) = match ctx_channels {
            None => (Some(linear(channels, 3 * channels, vb.pp("to_qkv"), compute)?), None, None),
            Some(c) => {
                (None, Some(linear(channels, channels, vb.pp("to_q"), compute)?), Some(linear(c, 2 * channels, vb.pp("to_kv"), compute)?))
            }
        };
        let (q_norm, k_norm) = if qk_rms_norm {
            (
                Some(MultiHeadRmsNorm::new(heads, head_dim, vb.pp("q_rms_norm"))?),
                Some(MultiHeadRmsNorm::new(heads, head_dim, vb.pp("k_rms_norm"))?),
            )
        } else {
            (None, None)
        };
        Ok(Self {
            heads,
            head_dim,
            to_qkv,
            to_q,
            to_kv,
            q_norm,
            k_norm,
            to_out: linear(channels, channels, vb.pp("to_out"), compute)?,
            compute,
        })
    }

    /// Whether this layer runs the fast kernels.
    pub fn is_fast(&self) -> bool {
        self.compute.is_fast()
    }

    /// Project to per-head q, k, v, each `[B, L, H, D]` (qk-norm applied).
    /// For cross-attention `ctx` supplies k and v.
    pub fn qkv(&self, x: &Tensor, ctx: Option<&Tensor>) -> Result<(Tensor, Tensor, Tensor)> {
        let (b, l, _) = x.dims3()?;
        let (h, d) = (self.heads, self.head_dim);
        let (q, k, v) = match (&self.to_qkv, ctx) {
            (Some(to_qkv), None) => {
                let qkv = to_qkv.forward(x)?.reshape((b, l, 3, h, d))?;
                (qkv.narrow(2, 0, 1)?.squeeze(2)?, qkv.narrow(2, 1, 1)?.squeeze(2)?, qkv.narrow(2, 2, 1)?.squeeze(2)?)
            }
            (None, Some(ctx)) => {
                let lc = ctx.dim(1)?;
                let q = self.to_q.as_ref().unwrap().forward(x)?.reshape((b, l, h, d))?;
                let kv = self.to_kv.as_ref().unwrap().forward(ctx)?.reshape((b, lc, 2, h, d))?;
                (q, kv.narrow(2, 0, 1)?.squeeze(2)?, kv.narrow(2, 1, 1)?.squeeze(2)?)
            }
            _ => candle_core::bail!("attention: context given to self-attention or missing for cross-attention"),
        };
        let q = match &self.q_norm {
            Some(n) => n.forward(&q)?,
            None => q,
        };
        let k = match &self.k_norm {
            Some(n) => n.forward(&k)?,
            None => k,
        };
        Ok((q, k, v))
    }

    /// Output projection of `[B, L, H, D]` attention results.
    pub fn out(&self, o: &Tensor) -> Result<Tensor> {
        let (b, l, h, d) = o.dims4()?;
        self.to_out.forward(&o.reshape((b, l, h * d))?)
    }

    /// Full attention: `x` `[B, L, C]`, optional context `[B or 1, Lc, Cc]`.
    pub fn forward(&self, x: &Tensor, ctx: Option<&Tensor>) -> Result<Tensor> {
        if self.is_fast() {
            let (b, l, c) = x.dims3()?;
            let (ctx_rows, lc, cb) = match ctx {
                Some(cx) => {
                    let (cb, lc, cc) = cx.dims3()?;
                    (Some(cx.reshape((cb * lc, cc))?), lc, cb)
                }
                None => (None, l, b),
            };
            if cb != b && cb != 1 {
                candle_core::bail!("attention: context batch {cb} for input batch {b}");
            }
            let segs: Vec<AttnSegment> = (0..b)
                .map(|i| {
                    let kv0 = if cb == 1 { 0 } else { i * lc };
                    AttnSegment { q: i * l..(i + 1) * l, kv: kv0..kv0 + lc }
                })
                .collect();
            let y = self.forward_rows(&x.reshape((b * l, c))?, ctx_rows.as_ref(), &segs)?;
            return y.reshape((b, l, c));
        }
        let (q, k, v) = self.qkv(x, ctx)?;
        let o = attention(&q.transpose(1, 2)?, &k.transpose(1, 2)?, &v.transpose(1, 2)?)?;
        self.out(&o.transpose(1, 2)?)
    }

    /// Fast path on rows: `x` `[N, C]`, context rows `[Nc, Cc]` for
    /// cross-attention; query rows of each segment attend to its key rows
    /// (rows of `x` for self-attention). Returns `[N, C]`; rows outside every
    /// segment get the output projection of zeros (its bias).
    pub fn forward_rows(&self, x: &Tensor, ctx: Option<&Tensor>, segments: &[AttnSegment]) -> Result<Tensor> {
        let Some((precision, isa)) = self.compute.fast_parts() else {
            candle_core::bail!("attention: forward_rows needs a layer built with fast kernels");
        };
        let (n, _) = x.dims2()?;
        let (h, d) = (self.heads, self.head_dim);
        let c = h * d;
        let (fl, gamma) = (fast_layer, head_gamma);
        let o = match (&self.to_qkv, ctx) {
            (Some(to_qkv), None) => {
                let mut qkv = fast::with_f32(x, |xs| fl(to_qkv)?.forward_slice(xs, n, Activation::None))?;
                if let Some(g) = gamma(&self.q_norm)? {
                    fast::rms_norm_heads(&mut qkv, n, 3 * c, 0, &g, h, d);
                }
                if let Some(g) = gamma(&self.k_norm)? {
                    fast::rms_norm_heads(&mut qkv, n, 3 * c, c, &g, h, d);
                }
                let lay = |off| AttnLayout::new(3 * c, off);
                fast::attention_rows(isa, precision, h, d, (&qkv, lay(0)), (&qkv, lay(c)), (&qkv, lay(2 * c)), n, segments)?
            }
            (None, Some(ctx)) => {
                let (nc, _) = ctx.dims2()?;
                let mut q = fast::with_f32(x, |xs| fl(self.to_q.as_ref().unwrap())?.forward_slice(xs, n, Activation::None))?;
                let mut kv = fast::with_f32(ctx, |cs| fl(self.to_kv.as_ref().unwrap())?.forward_slice(cs, nc, Activation::None))?;
                if let Some(g) = gamma(&self.q_norm)? {
                    fast::rms_norm_heads(&mut q, n, c, 0, &g, h, d);
                }
                if let Some(g) = gamma(&self.k_norm)? {
                    fast::rms_norm_heads(&mut kv, nc, 2 * c, 0, &g, h, d);
                }
                let (ql, kl, vl) = (AttnLayout::new(c, 0), AttnLayout::new(2 * c, 0), AttnLayout::new(2 * c, c));
                fast::attention_rows(isa, precision, h, d, (&q, ql), (&kv, kl), (&kv, vl), n, segments)?
            }
            _ => candle_core::bail!("attention: context given to self-attention or missing for cross-attention"),
        };
        let y = fl(&self.to_out)?.forward_slice(&o, n, Activation::None)?;
        Tensor::from_vec(y, (n, c), x.device())
    }
}

/// For each item of a context `[B, L, C]`: whether it has at least one row
/// and all its rows are the same finite row, bit for bit. A cross-attention
/// to such a context gives every query the same output (see [`CrossContext`]);
/// the unconditional branch's condition (all zeros) is the case that matters.
pub fn constant_rows(ctx: &Tensor) -> Result<Vec<bool>> {
    let (b, l, c) = ctx.dims3()?;
    fast::with_f32(ctx, |v| {
        Ok((0..b)
            .map(|i| {
                let item = &v[i * l * c..(i + 1) * l * c];
                let first = &item[..c.min(item.len())];
                // Compared as bits: exact, and conservative (rows of 0.0 and
                // -0.0 only miss the shortcut). A non-finite row is left to the
                // full computation, whose scores it would turn into NaN.
                l > 0
                    && first.iter().all(|x| x.is_finite())
                    && item.chunks_exact(c.max(1)).all(|row| row.iter().zip(first).all(|(a, b)| a.to_bits() == b.to_bits()))
            })
            .collect())
    })
}

/// One batch item of a [`CrossContext`].
#[derive(Debug)]
enum ContextItem {
    /// Keys and values of the item's context rows, `[Lc, 2C]` (K then V per
    /// row, keys RMS-normalised when the layer has QK norm).
    Kv { kv: Vec<f32>, rows: usize },
    /// All context rows are equal: every key is the same, so the softmax is
    /// uniform whatever the query and the attention output is the common
    /// value row. The layer's output for every query, `to_out(v)` `[C]`.
    Constant(Vec<f32>),
}

/// A cross-attention layer's context prepared once and reused by every
/// forward on that context, as a sampler's steps are: the condition does not
/// change from step to step, so neither do its keys and values. Items whose
/// rows are all equal keep only the layer's output row (an exact shortcut:
/// no query projection, scores or weighted sum for them). Built by
/// [`MultiHeadAttention::prepare`]; fast path only.
#[derive(Debug, Clone)]
pub struct CrossContext {
    items: Vec<Arc<ContextItem>>,
}

impl CrossContext {
    /// Number of batch items.
    pub fn batch(&self) -> usize {
        self.items.len()
    }

    /// Which items take the constant-context shortcut.
    pub fn constant_items(&self) -> Vec<bool> {
        self.items.iter().map(|i| matches!(**i, ContextItem::Constant(_))).collect()
    }

    /// Items `start..start + len` (shared, not copied).
    pub fn narrow(&self, start: usize, len: usize) -> Result<Self> {
        match self.items.get(start..start + len) {
            Some(items) => Ok(Self { items: items.to_vec() }),
            None => candle_core::bail!("cross context: items {start}..{} of {}", start + len, self.items.len()),
        }
    }

    /// The items of `parts` one after the other (shared, not copied).
    pub fn cat(parts: &[&Self]) -> Self {
        Self { items: parts.iter().flat_map(|p| p.items.iter().cloned()).collect() }
    }

    /// A batch-1 context repeated to `batch` items; any other context must already have `batch` items.
    pub fn expand(&self, batch: usize) -> Result<Self> {
        match self.items.len() {
            n if n == batch => Ok(self.clone()),
            1 => Ok(Self { items: vec![self.items[0].clone(); batch] }),
            n => candle_core::bail!("cross context: {n} items for batch {batch}"),
        }
    }
}

impl MultiHeadAttention {
    /// Keys and values of cross-attention context `ctx` `[B, Lc, Cc]`, once,
    /// for [`Self::forward_prepared`]. With `shortcut`, items whose rows are
    /// all equal ([`constant_rows`]) keep only their output row. Fast path only.
    pub fn prepare(&self, ctx: &Tensor, shortcut: bool) -> Result<CrossContext> {
        let constant = if shortcut { constant_rows(ctx)? } else { vec![false; ctx.dim(0)?] };
        self.prepare_flagged(ctx, &constant)
    }

    /// [`Self::prepare`] with the items' [`constant_rows`] flags computed by
    /// the caller (once for a stack of blocks); they are trusted.
    fn prepare_flagged(&self, ctx: &Tensor, constant: &[bool]) -> Result<CrossContext> {
        let (to_kv, to_out) = match (&self.to_kv, self.compute.is_fast()) {
            (Some(kv), true) => (fast_layer(kv)?, fast_layer(&self.to_out)?),
            _ => candle_core::bail!("attention: prepared contexts are for fast cross-attention layers"),
        };
        let (b, lc, cc) = ctx.dims3()?;
        if constant.len() != b {
            candle_core::bail!("attention: {} constant-row flags for {b} context items", constant.len());
        }
        let (h, d) = (self.heads, self.head_dim);
        let c = h * d;
        let gamma = head_gamma(&self.k_norm)?;
        let items = fast::with_f32(ctx, |v| {
            (0..b)
                .map(|i| {
                    let item = &v[i * lc * cc..(i + 1) * lc * cc];
                    if constant[i] {
                        // One row: its value row through the output projection. The keys
                        // (and any QK norm) only shape the scores, which are all equal.
                        let kv = to_kv.forward_slice(&item[..cc], 1, Activation::None)?;
                        return Ok(Arc::new(ContextItem::Constant(to_out.forward_slice(&kv[c..], 1, Activation::None)?)));
                    }
                    let mut kv = to_kv.forward_slice(item, lc, Activation::None)?;
                    if let Some(g) = &gamma {
                        fast::rms_norm_heads(&mut kv, lc, 2 * c, 0, g, h, d);
                    }
                    Ok(Arc::new(ContextItem::Kv { kv, rows: lc }))
                })
                .collect::<Result<Vec<_>>>()
        })?;
        Ok(CrossContext { items })
    }

    /// Cross-attention of `x` `[B, L, C]` to a prepared context of B items:
    /// the same as [`Self::forward`] on the context it was prepared from, up
    /// to float rounding for constant items (exactly for the others). Each
    /// item is its own GEMMs and attention call; every row of those is
    /// computed independently, so batching items would give the same bits.
    pub fn forward_prepared(&self, x: &Tensor, ctx: &CrossContext) -> Result<Tensor> {
        let Some((precision, isa)) = self.compute.fast_parts() else {
            candle_core::bail!("attention: prepared contexts are for fast cross-attention layers");
        };
        let (Some(to_q), Some(_)) = (&self.to_q, &self.to_kv) else {
            candle_core::bail!("attention: prepared context given to self-attention")
        };
        let (to_q, to_out) = (fast_layer(to_q)?, fast_layer(&self.to_out)?);
        let (b, l, c) = x.dims3()?;
        let (h, d) = (self.heads, self.head_dim);
        if c != h * d || ctx.batch() != b {
            candle_core::bail!("attention: input {:?} for a prepared context of {} items and {h}×{d} channels", x.dims(), ctx.batch());
        }
        let gamma = head_gamma(&self.q_norm)?;
        let mut y = vec![0f32; b * l * c];
        fast::with_f32(x, |xs| {
            for (i, item) in ctx.items.iter().enumerate() {
                let yi = &mut y[i * l * c..(i + 1) * l * c];
                match &**item {
                    ContextItem::Constant(row) => yi.par_chunks_mut(c).for_each(|r| r.copy_from_slice(row)),
                    ContextItem::Kv { kv, rows } => {
                        let mut q = to_q.forward_slice(&xs[i * l * c..(i + 1) * l * c], l, Activation::None)?;
                        if let Some(g) = &gamma {
                            fast::rms_norm_heads(&mut q, l, c, 0, g, h, d);
                        }
                        let (ql, kl, vl) = (AttnLayout::new(c, 0), AttnLayout::new(2 * c, 0), AttnLayout::new(2 * c, c));
                        let seg = [AttnSegment { q: 0..l, kv: 0..*rows }];
                        let o = fast::attention_rows(isa, precision, h, d, (&q, ql), (kv, kl), (kv, vl), l, &seg)?;
                        drop(q);
                        to_out.forward_into(&o, l, Activation::None, yi)?;
                    }
                }
            }
            Ok(())
        })?;
        Tensor::from_vec(y, (b, l, c), x.device())
    }
}

fn fast_layer(l: &Linear) -> Result<&fast::FastLinear> {
    l.fast().ok_or_else(|| candle_core::Error::Msg("attention: layer not packed".into()))
}

/// A QK norm's gamma `[H·D]` as f32 values.
fn head_gamma(n: &Option<MultiHeadRmsNorm>) -> Result<Option<Vec<f32>>> {
    n.as_ref().map(|m| m.gamma.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()).transpose()
}

/// TRELLIS `ModulatedTransformerCrossBlock`: adaLN-modulated self-attention,
/// un-modulated cross-attention (affine norm2), modulated MLP.
#[derive(Debug, Clone)]
pub struct ModulatedTransformerCrossBlock {
    /// Self-attention (`self_attn`).
    pub self_attn: MultiHeadAttention,
    /// Cross-attention to the condition tokens (`cross_attn`).
    pub cross_attn: MultiHeadAttention,
    norm2: LayerNorm,
    mlp: FeedForward,
    ada_ln: Option<Linear>,
    compute: Compute,
}

/// Hyper-parameters of a modulated cross block.
#[derive(Debug, Clone, Copy)]
pub struct CrossBlockConfig {
    /// Token width C (upstream `channels`).
    pub channels: usize,
    /// Condition token width Cc (upstream `ctx_channels`).
    pub ctx_channels: usize,
    /// Attention heads (upstream `num_heads`).
    pub heads: usize,
    /// MLP hidden width as a multiple of C (upstream `mlp_ratio`).
    pub mlp_ratio: f64,
    /// Take the shared `[B, 6C]` modulation instead of a per-block adaLN layer (upstream `share_mod`).
    pub share_mod: bool,
    /// RMS-normalise q and k in self-attention (upstream `qk_rms_norm`).
    pub qk_rms_norm: bool,
    /// RMS-normalise q and k in cross-attention (upstream `qk_rms_norm_cross`).
    pub qk_rms_norm_cross: bool,
}

impl ModulatedTransformerCrossBlock {
    /// Load the block's layers (`self_attn`, `cross_attn`, `norm2`, `mlp`, and `adaLN_modulation.1` unless `share_mod`).
    pub fn new(cfg: &CrossBlockConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let c = cfg.channels;
        Ok(Self {
            self_attn: MultiHeadAttention::new(c, cfg.heads, None, cfg.qk_rms_norm, vb.pp("self_attn"), compute)?,
            cross_attn: MultiHeadAttention::new(c, cfg.heads, Some(cfg.ctx_channels), cfg.qk_rms_norm_cross, vb.pp("cross_attn"), compute)?,
            norm2: LayerNorm::new(c, 1e-6, vb.pp("norm2"), compute)?,
            mlp: FeedForward::new(c, cfg.mlp_ratio, vb.pp("mlp"), compute)?,
            ada_ln: if cfg.share_mod { None } else { Some(linear(c, 6 * c, vb.pp("adaLN_modulation.1"), compute)?) },
            compute,
        })
    }

    /// `x` `[B, L, C]`; `emb` is the timestep embedding `[B, C]` or, with
    /// `share_mod`, the shared modulation `[B, 6C]`; `cond` `[B, Lc, Cc]`.
    pub fn forward(&self, x: &Tensor, emb: &Tensor, cond: &Tensor) -> Result<Tensor> {
        let m = match &self.ada_ln {
            Some(l) => l.forward(&emb.silu()?)?,
            None => emb.clone(),
        };
        let ch = m.chunk(6, 1)?;
        if self.compute.is_fast() {
            return self.forward_fast(x, &ch, |h| self.cross_attn.forward(h, Some(cond)));
        }
        let (shift_msa, scale_msa, gate_msa) = (ch[0].unsqueeze(1)?, ch[1].unsqueeze(1)?, ch[2].unsqueeze(1)?);
        let (shift_mlp, scale_mlp, gate_mlp) = (ch[3].unsqueeze(1)?, ch[4].unsqueeze(1)?, ch[5].unsqueeze(1)?);

        let h = layer_norm_plain(x, 1e-6)?.broadcast_mul(&(scale_msa + 1.0)?)?.broadcast_add(&shift_msa)?;
        let h = self.self_attn.forward(&h, None)?.broadcast_mul(&gate_msa)?;
        let x = (x + h)?;

        let h = self.cross_attn.forward(&self.norm2.forward(&x)?, Some(cond))?;
        let x = (x + h)?;

        let h = layer_norm_plain(&x, 1e-6)?.broadcast_mul(&(scale_mlp + 1.0)?)?.broadcast_add(&shift_mlp)?;
        let h = self.mlp.forward(&h)?.broadcast_mul(&gate_mlp)?;
        x + h
    }

    /// [`Self::forward`] with the cross-attention context prepared once
    /// ([`MultiHeadAttention::prepare`], B items or one for all); fast path only.
    pub fn forward_prepared(&self, x: &Tensor, emb: &Tensor, ctx: &CrossContext) -> Result<Tensor> {
        if !self.compute.is_fast() {
            candle_core::bail!("cross block: prepared contexts are for the fast path");
        }
        let m = match &self.ada_ln {
            Some(l) => l.forward(&emb.silu()?)?,
            None => emb.clone(),
        };
        let ctx = ctx.expand(x.dim(0)?)?;
        self.forward_fast(x, &m.chunk(6, 1)?, |h| self.cross_attn.forward_prepared(h, &ctx))
    }

    /// The fast path with the modulation chunks `ch`; `cross` maps `norm2`'s
    /// output to the cross-attention output. Fused kernels: LN + modulation,
    /// gated residuals (same math). Each activation is dropped as soon as it
    /// is used: at full size one is 33.5 MB, and shadowed bindings would live
    /// to the end.
    fn forward_fast(&self, x: &Tensor, ch: &[Tensor], cross: impl FnOnce(&Tensor) -> Result<Tensor>) -> Result<Tensor> {
        let Some((_, isa)) = self.compute.fast_parts() else { candle_core::bail!("cross block: not built for the fast path") };
        let h = fast::layer_norm(isa, x, 1e-6, Some(&(&ch[1] + 1.0)?), Some(&ch[0]))?;
        let a = self.self_attn.forward(&h, None)?;
        drop(h);
        let x1 = fast::gated_residual(x, &a, Some(&ch[2]))?;
        drop(a);
        let a = cross(&self.norm2.forward(&x1)?)?;
        let x2 = fast::gated_residual(&x1, &a, None)?;
        drop((a, x1));
        let h = fast::layer_norm(isa, &x2, 1e-6, Some(&(&ch[4] + 1.0)?), Some(&ch[3]))?;
        let f = self.mlp.forward(&h)?;
        drop(h);
        fast::gated_residual(&x2, &f, Some(&ch[5]))
    }
}

/// A condition prepared for many forwards of a stack of cross blocks: each
/// block's [`CrossContext`]. A sampler's condition is the same at every
/// step, so its keys and values are computed once per run instead of once
/// per step; items whose rows are all equal (the all-zero unconditional
/// condition) take the constant-context shortcut in every block.
#[derive(Debug, Clone)]
pub struct PreparedCondition {
    blocks: Vec<CrossContext>,
    batch: usize,
}

impl PreparedCondition {
    /// [`Self::new`] for a flow model named `model` (in the errors) after the
    /// checks both flows make: `cond` is `[B, L, cond_channels]` and the model
    /// runs the fast path (`fast`).
    pub fn for_model(
        model: &str,
        blocks: &[ModulatedTransformerCrossBlock],
        cond: &Tensor,
        cond_channels: usize,
        fast: bool,
        shortcut: bool,
    ) -> Result<Self> {
        let (_, _, cc) = cond.dims3()?;
        if cc != cond_channels {
            return Err(candle_core::Error::Msg(format!("{model}: cond shape {:?}, expected [B, L, {cond_channels}]", cond.dims())));
        }
        if !fast {
            return Err(candle_core::Error::Msg(format!("{model}: prepared conditions are for the fast path")));
        }
        Self::new(blocks, cond, shortcut)
    }

    /// Prepare `cond` `[B, Lc, Cc]` for `blocks` (fast path). With
    /// `shortcut`, items whose rows are all equal ([`constant_rows`]) keep
    /// only each block's output row; without it every item keeps its keys and
    /// values (the full computation).
    pub fn new(blocks: &[ModulatedTransformerCrossBlock], cond: &Tensor, shortcut: bool) -> Result<Self> {
        let batch = cond.dim(0)?;
        let constant = if shortcut { constant_rows(cond)? } else { vec![false; batch] };
        let blocks = blocks.iter().map(|b| b.cross_attn.prepare_flagged(cond, &constant)).collect::<Result<Vec<_>>>()?;
        Ok(Self { blocks, batch })
    }

    /// Number of batch items.
    pub fn batch(&self) -> usize {
        self.batch
    }

    /// Which items take the constant-context shortcut.
    pub fn constant_items(&self) -> Vec<bool> {
        self.blocks.first().map(CrossContext::constant_items).unwrap_or_else(|| vec![false; self.batch])
    }

    /// The context of block `i`.
    pub fn block(&self, i: usize) -> Result<&CrossContext> {
        self.blocks.get(i).ok_or_else(|| candle_core::Error::Msg(format!("prepared condition: no block {i} of {}", self.blocks.len())))
    }

    /// Items `start..start + len` (shared, not copied).
    pub fn narrow(&self, start: usize, len: usize) -> Result<Self> {
        Ok(Self { blocks: self.blocks.iter().map(|c| c.narrow(start, len)).collect::<Result<_>>()?, batch: len })
    }

    /// The items of `parts` one after the other (shared, not copied); all must be for the same blocks.
    pub fn cat(parts: &[&Self]) -> Result<Self> {
        let n = parts.first().map_or(0, |p| p.blocks.len());
        if parts.iter().any(|p| p.blocks.len() != n) {
            candle_core::bail!("prepared condition: parts for different numbers of blocks");
        }
        let blocks = (0..n).map(|i| CrossContext::cat(&parts.iter().map(|p| &p.blocks[i]).collect::<Vec<_>>())).collect();
        Ok(Self { blocks, batch: parts.iter().map(|p| p.batch).sum() })
    }

    /// A batch-1 condition repeated to `batch` items; any other must already have `batch` items.
    pub fn expand(&self, batch: usize) -> Result<Self> {
        Ok(Self { blocks: self.blocks.iter().map(|c| c.expand(batch)).collect::<Result<_>>()?, batch })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn chunked_attention_matches_unchunked() -> Result<()> {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (1, 2, 37, 8), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (1, 2, 53, 8), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (1, 2, 53, 8), &dev)?;
        let got = attention(&q, &k, &v)?;
        let s = (q.matmul(&k.t()?)? / (8f64).sqrt())?;
        let want = candle_nn::ops::softmax_last_dim(&s)?.matmul(&v)?;
        let d = (got - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert!(d < 1e-5, "diff {d}");
        Ok(())
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    /// A modulated cross block built on the fast kernels matches the plain
    /// (differentiable) one: f32 tightly, bf16/f16 within their rounding.
    #[test]
    fn fast_cross_block_matches_plain() -> crate::Result<()> {
        use crate::model::nn::fast::{Compute, Precision};
        use candle_nn::VarMap;
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
        let cfg = CrossBlockConfig {
            channels: 64,
            ctx_channels: 24,
            heads: 4,
            mlp_ratio: 4.0,
            share_mod: false,
            qk_rms_norm: true,
            qk_rms_norm_cross: true,
        };
        let plain = ModulatedTransformerCrossBlock::new(&cfg, vb.pp("blk"), Compute::Plain)?;
        // Non-trivial weights (VarMap init gives zero biases / unit norms).
        let mut rng = crate::rng::SeededRng::new(3);
        for (_, var) in vm.data().lock().unwrap().iter() {
            var.set(&((rng.randn(var.dims(), &dev)? * 0.1)? + 0.05)?)?;
        }
        let x = rng.randn(&[2, 37, 64], &dev)?;
        let emb = rng.randn(&[2, 64], &dev)?;
        let cond = rng.randn(&[2, 29, 24], &dev)?;
        let want = plain.forward(&x, &emb, &cond)?;
        let scale = want.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        for (p, tol) in [(Precision::F32, 1e-5f32), (Precision::F16, 2e-3), (Precision::Bf16, 3e-2)] {
            let fast = ModulatedTransformerCrossBlock::new(&cfg, vb.pp("blk"), Compute::fast(p))?;
            assert!(fast.self_attn.is_fast() && fast.mlp.fc1.fast().is_some());
            let got = fast.forward(&x, &emb, &cond)?;
            let d = max_diff(&got, &want);
            assert!(d <= tol * scale, "{p}: max diff {d} (output scale {scale})");
        }
        // Cross-attention to a batch-1 context is broadcast over the batch.
        let fast = MultiHeadAttention::new(64, 4, Some(24), true, vb.pp("blk.cross_attn"), Compute::fast(Precision::F32))?;
        let c1 = cond.narrow(0, 0, 1)?;
        let a = fast.forward(&x, Some(&c1))?;
        let b = plain.cross_attn.forward(&x, Some(&c1.broadcast_as((2, 29, 24))?.contiguous()?))?;
        assert!(max_diff(&a, &b) < 1e-4);
        Ok(())
    }

    /// The constant-row test: all-equal finite rows, bit for bit.
    #[test]
    fn constant_rows_needs_equal_finite_rows() -> Result<()> {
        let dev = Device::Cpu;
        let row = Tensor::new(&[[0.5f32, -2.0, 3.0]], &dev)?;
        let same = row.broadcast_as((4, 3))?.contiguous()?.unsqueeze(0)?;
        let zeros = Tensor::zeros((1, 4, 3), DType::F32, &dev)?;
        let mut v = same.flatten_all()?.to_vec1::<f32>()?;
        v[10] = f32::from_bits(v[10].to_bits() + 1);
        let one_ulp = Tensor::from_vec(v, (1, 4, 3), &dev)?;
        let nan = Tensor::full(f32::NAN, (1, 4, 3), &dev)?;
        let empty = Tensor::zeros((1, 0, 3), DType::F32, &dev)?;
        let all = Tensor::cat(&[&same, &zeros, &one_ulp, &nan], 0)?;
        assert_eq!(constant_rows(&all)?, vec![true, true, false, false]);
        assert_eq!(constant_rows(&empty)?, vec![false]);
        Ok(())
    }

    /// Prepared cross-attention contexts against the full computation, with
    /// and without QK norm in cross-attention: items with keys and values
    /// give the same bits; the constant-context shortcut (all-zero and
    /// constant non-zero conditions) is within 1e-6 of the output's scale.
    #[test]
    fn prepared_context_matches_full_computation() -> crate::Result<()> {
        use crate::model::nn::fast::{Compute, Precision};
        use crate::util::testing::{max_rel_diff, same_bits};
        use candle_nn::VarMap;
        let dev = Device::Cpu;
        for qk_cross in [false, true] {
            let vm = VarMap::new();
            let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
            let cfg = CrossBlockConfig {
                channels: 64,
                ctx_channels: 24,
                heads: 4,
                mlp_ratio: 2.0,
                share_mod: false,
                qk_rms_norm: true,
                qk_rms_norm_cross: qk_cross,
            };
            ModulatedTransformerCrossBlock::new(&cfg, vb.pp("blk"), Compute::Plain)?;
            let mut rng = crate::rng::SeededRng::new(5);
            for (_, var) in vm.data().lock().unwrap().iter() {
                var.set(&((rng.randn(var.dims(), &dev)? * 0.2)? + 0.05)?)?;
            }
            let plain = ModulatedTransformerCrossBlock::new(&cfg, vb.pp("blk"), Compute::Plain)?;
            let fast = ModulatedTransformerCrossBlock::new(&cfg, vb.pp("blk"), Compute::fast(Precision::F32))?;
            let x = rng.randn(&[3, 37, 64], &dev)?;
            let emb = rng.randn(&[3, 64], &dev)?;
            // Item 0 a real condition, item 1 all zeros (`neg_cond`), item 2 one non-zero row repeated.
            let row = rng.randn(&[1, 1, 24], &dev)?;
            let cond = Tensor::cat(
                &[&rng.randn(&[1, 29, 24], &dev)?, &Tensor::zeros((1, 29, 24), DType::F32, &dev)?, &row.repeat((1, 29, 1))?],
                0,
            )?;
            assert_eq!(constant_rows(&cond)?, vec![false, true, true]);

            let full = fast.forward(&x, &emb, &cond)?;
            let kept = fast.forward_prepared(&x, &emb, &fast.cross_attn.prepare(&cond, false)?)?;
            assert!(same_bits(&kept, &full)?, "qk_cross {qk_cross}: prepared keys and values change the bits");
            let short = fast.cross_attn.prepare(&cond, true)?;
            assert_eq!(short.constant_items(), vec![false, true, true]);
            let got = fast.forward_prepared(&x, &emb, &short)?;
            assert!(same_bits(&got.get(0)?, &full.get(0)?)?, "qk_cross {qk_cross}: the real condition changed");
            for i in 1..3 {
                let d = max_rel_diff(&got.get(i)?, &full.get(i)?)?;
                eprintln!("cross block qk_cross {qk_cross}, item {i}: {d:.2e} from the full computation");
                assert!(d <= 1e-6, "qk_cross {qk_cross}, item {i}: block output {d:e} from the full computation");
                // The attention layer alone: one row for every query.
                let h = x.narrow(0, i, 1)?;
                let a_full = fast.cross_attn.forward(&h, Some(&cond.narrow(0, i, 1)?))?;
                let a_short = fast.cross_attn.forward_prepared(&h, &short.narrow(i, 1)?)?;
                let d = max_rel_diff(&a_short, &a_full)?;
                assert!(d <= 1e-6, "qk_cross {qk_cross}, item {i}: attention output {d:e} from the full computation");
                let first = a_short.narrow(1, 0, 1)?.broadcast_as(a_short.dims())?;
                assert!(same_bits(&a_short, &first.contiguous()?)?);
            }
            // Against the plain (reference) block, within the fast path's usual tolerance.
            let d = max_rel_diff(&got, &plain.forward(&x, &emb, &cond)?)?;
            assert!(d <= 1e-5, "qk_cross {qk_cross}: fast prepared vs plain {d:e}");
            // One prepared item serves a whole batch.
            let one = fast.cross_attn.prepare(&cond.narrow(0, 1, 1)?, true)?;
            let b = fast.forward_prepared(&x, &emb.narrow(0, 1, 1)?.repeat((3, 1))?, &one)?;
            assert!(same_bits(&b.get(1)?, &got.get(1)?)?);
        }
        Ok(())
    }

    #[test]
    fn softmax_matches_candle_kernel_and_has_gradient() -> Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 3.0, (3, 5, 37), &dev)?;
        let fast = candle_nn::ops::softmax_last_dim(&x)?;
        let ours = softmax_last_dim(&x)?;
        assert_eq!(fast.flatten_all()?.to_vec1::<f32>()?, ours.flatten_all()?.to_vec1::<f32>()?, "forward must be bit-identical");
        // Gradient equals the one of the composed (differentiable) softmax.
        let v = candle_core::Var::from_tensor(&x)?;
        let w = Tensor::randn(0f32, 1.0, (3, 5, 37), &dev)?;
        let g1 = (softmax_last_dim(v.as_tensor())? * &w)?.sum_all()?.backward()?;
        let g2 = (candle_nn::ops::softmax(v.as_tensor(), D::Minus1)? * &w)?.sum_all()?.backward()?;
        let d = (g1.get(v.as_tensor()).unwrap() - g2.get(v.as_tensor()).unwrap())?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert!(d < 1e-6, "gradient diff {d}");
        Ok(())
    }

    #[test]
    fn position_embedding_pads_to_channels() -> Result<()> {
        let c = Tensor::new(&[[0u32, 1, 2], [3, 4, 5]], &Device::Cpu)?;
        let e = abs_position_embedding(&c, 64)?;
        assert_eq!(e.dims(), &[2, 64]);
        // freq_dim 10: channel 0 is sin(x·1), channel 10 is cos(x·1).
        let v = e.to_vec2::<f32>()?;
        assert!((v[1][0] - 3f32.sin()).abs() < 1e-6);
        assert!((v[1][10] - 3f32.cos()).abs() < 1e-6);
        assert_eq!(&v[1][60..], &[0.0; 4]);
        Ok(())
    }
}
