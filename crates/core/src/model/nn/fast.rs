//! Inference kernels for the model layers, and the setting that selects them.
//!
//! Every layer has two paths:
//! - **plain**: candle ops in f32, differentiable (training), and the path the
//!   conformance fixtures check;
//! - **fast**: the hand-written kernels of `recon-kernels` (packed GEMM with
//!   fused bias/GELU, flash attention, fused LayerNorm/modulation and gated
//!   residuals), inference only: results carry no gradient.
//!
//! The path is fixed when a module is built: every module constructor takes a
//! [`Compute`] and hands it to its sub-layers (a different path is a different
//! constructor argument, chosen once). Fast linear layers pack their weights once, at construction, into
//! the kernel layout and [`Precision`], and drop the f32 copy.
//!
//! Precision modes (weights as stored; activations between layers are f32):
//! - `f32`: f32 weights and arithmetic;
//! - `bf16`: bf16 weights; GEMM and attention inputs rounded to bf16, products
//!   accumulated in f32 (`vdpbf16ps` where the CPU has AVX512-BF16); norms,
//!   softmax statistics and residuals in f32 (as torch bf16 autocast);
//! - `f16`: f16 weights (half the memory of f32), widened to f32 in registers;
//!   activations and attention stay f32 (x86 CPUs without AVX512-FP16 have no
//!   faster f16 arithmetic).

use std::str::FromStr;
use std::sync::Arc;

use candle_core::{DType, Device, Result, Storage, Tensor};
use rayon::prelude::*;
use recon_kernels::attention::{flash_attention, AttnPrecision, AttnSpec, HeadLayout, Segment};
use recon_kernels::gemm::{gemm, PackedMatrix, WeightFormat};
pub use recon_kernels::isa::Isa;
use recon_kernels::vecmath;
pub use recon_kernels::vecmath::Activation;

use crate::util::profile;

/// Storage/arithmetic precision of the fast path (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// f32 weights and arithmetic (`f32`).
    #[default]
    F32,
    /// bf16 weights, bf16-rounded GEMM/attention inputs, f32 accumulation (`bf16`).
    Bf16,
    /// f16 weights widened to f32 in registers; f32 activations and attention (`f16`).
    F16,
}

impl Precision {
    /// Every precision, in the order f32, bf16, f16.
    pub const ALL: [Precision; 3] = [Precision::F32, Precision::Bf16, Precision::F16];

    /// Lower-case name (`f32`, `bf16`, `f16`), as parsed and printed.
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::Bf16 => "bf16",
            Precision::F16 => "f16",
        }
    }
    /// Storage format of packed GEMM weights at this precision.
    pub fn weight_format(self) -> WeightFormat {
        match self {
            Precision::F32 => WeightFormat::F32,
            Precision::Bf16 => WeightFormat::Bf16,
            Precision::F16 => WeightFormat::F16,
        }
    }
    /// Flash-attention precision: bf16 inputs for [`Precision::Bf16`], f32 otherwise.
    pub fn attention(self) -> AttnPrecision {
        match self {
            Precision::Bf16 => AttnPrecision::Bf16,
            _ => AttnPrecision::F32,
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Precision {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        Precision::ALL
            .into_iter()
            .find(|p| p.name() == s.trim().to_ascii_lowercase())
            .ok_or_else(|| format!("unknown precision `{s}` (expected f32, bf16 or f16)"))
    }
}

/// Which implementation a module's layers use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Compute {
    /// candle ops in f32 (differentiable; the conformance reference).
    #[default]
    Plain,
    /// recon-kernels at `precision`, with the kernels of `isa` (inference only).
    Fast {
        /// Weight storage and arithmetic precision.
        precision: Precision,
        /// Instruction set the kernels are dispatched for.
        isa: Isa,
    },
}

impl Compute {
    /// Fast kernels with the best instruction set of this CPU ([`Isa::best`]);
    /// bf16 on the family where it is fastest ([`recon_kernels::peak::bf16_isa`]:
    /// `vdpbf16ps` only where it beats f32 FMA, else bf16 storage on FMA).
    pub fn fast(precision: Precision) -> Self {
        let isa = if precision == Precision::Bf16 { recon_kernels::peak::bf16_isa() } else { Isa::best() };
        Compute::Fast { precision, isa }
    }
    /// Whether this is [`Compute::Fast`].
    pub fn is_fast(&self) -> bool {
        matches!(self, Compute::Fast { .. })
    }
    /// `(precision, isa)` of a fast compute.
    pub fn fast_parts(&self) -> Option<(Precision, Isa)> {
        match *self {
            Compute::Fast { precision, isa } => Some((precision, isa)),
            Compute::Plain => None,
        }
    }
    /// Human-readable label, e.g. `plain candle f32` or `fast bf16 (<isa>)`.
    pub fn describe(&self) -> String {
        match self {
            Compute::Plain => "plain candle f32".into(),
            Compute::Fast { precision, isa } => format!("fast {precision} ({})", isa.name()),
        }
    }
}

fn kerr(e: String) -> candle_core::Error {
    candle_core::Error::Msg(e)
}

/// Run `f` on the f32 values of `t` (converted / made contiguous only if needed).
pub fn with_f32<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> Result<R>) -> Result<R> {
    let t = if t.dtype() == DType::F32 { t.clone() } else { t.to_dtype(DType::F32)? };
    let t = t.contiguous()?;
    let (storage, layout) = t.storage_and_layout();
    let (a, b) = layout.contiguous_offsets().ok_or_else(|| candle_core::Error::Msg("fast kernels: tensor not contiguous".into()))?;
    match &*storage {
        Storage::Cpu(cpu) => f(&cpu.as_slice::<f32>()?[a..b]),
        _ => candle_core::bail!("fast kernels run on the CPU only"),
    }
}

fn tensor(v: Vec<f32>, dims: &[usize]) -> Result<Tensor> {
    Tensor::from_vec(v, dims, &Device::Cpu)
}

/// A linear layer packed for the GEMM kernels (`y = x·Wᵀ + b`).
#[derive(Debug)]
pub struct FastLinear {
    w: PackedMatrix,
    bias: Option<Vec<f32>>,
    isa: Isa,
}

impl FastLinear {
    /// Pack `weight` `[N, K]` (and `bias` `[N]`) once, in `precision`.
    pub fn new(weight: &Tensor, bias: Option<&Tensor>, precision: Precision, isa: Isa) -> Result<Self> {
        let (n, k) = weight.dims2()?;
        let w = with_f32(weight, |w| PackedMatrix::from_linear_weight(w, n, k, precision.weight_format()).map_err(kerr))?;
        let bias = match bias {
            Some(b) => Some(b.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?),
            None => None,
        };
        if bias.as_ref().is_some_and(|b| b.len() != n) {
            candle_core::bail!("linear: bias length differs from the {n} outputs");
        }
        Ok(Self { w, bias, isa })
    }
    /// Input features K.
    pub fn in_dim(&self) -> usize {
        self.w.k()
    }
    /// Output features N.
    pub fn out_dim(&self) -> usize {
        self.w.n()
    }
    /// Bytes of packed weights.
    pub fn bytes(&self) -> usize {
        self.w.bytes()
    }

    /// `act(x·Wᵀ + b)` on `m` rows of `x` (`[m, K]`), `[m, N]` out.
    pub fn forward_slice(&self, x: &[f32], m: usize, act: Activation) -> Result<Vec<f32>> {
        let mut out = vec![0f32; m * self.out_dim()];
        self.forward_into(x, m, act, &mut out)?;
        Ok(out)
    }

    /// [`Self::forward_slice`] into `out` (`[m, N]`).
    pub fn forward_into(&self, x: &[f32], m: usize, act: Activation, out: &mut [f32]) -> Result<()> {
        let (k, n) = (self.in_dim(), self.out_dim());
        profile::timed(
            profile::Kind::Gemm,
            || 2 * (m * k * n) as u64,
            || gemm(self.isa, x, m, k, &self.w, self.bias.as_deref(), act, out, n).map_err(kerr),
        )
    }

    /// `act(x·Wᵀ + b)` over the last dim of `x`.
    pub fn forward(&self, x: &Tensor, act: Activation) -> Result<Tensor> {
        let dims = x.dims().to_vec();
        let k = *dims.last().ok_or_else(|| candle_core::Error::Msg("linear: scalar input".into()))?;
        if k != self.in_dim() {
            candle_core::bail!("linear: input has {k} features, layer expects {}", self.in_dim());
        }
        let m = x.elem_count() / k.max(1);
        let out = with_f32(x, |xs| self.forward_slice(xs, m, act))?;
        let mut od = dims;
        *od.last_mut().unwrap() = self.out_dim();
        tensor(out, &od)
    }
}

/// `fc2(act(fc1(x)))` over the last dim of `x`, at most `rows` rows at a time (equal chunks), so
/// the wide hidden activations of only one block of rows are alive (the
/// 4×-wide hidden of a guided SS-flow step is 134 MB at once). Each GEMM row
/// is computed independently with a fixed summation order, so the result is
/// the same as in one pass.
pub fn mlp_by_rows(fc1: &FastLinear, fc2: &FastLinear, x: &Tensor, act: Activation, rows: usize) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let k = *dims.last().ok_or_else(|| candle_core::Error::Msg("mlp: scalar input".into()))?;
    if k != fc1.in_dim() || fc1.out_dim() != fc2.in_dim() {
        candle_core::bail!("mlp: input has {k} features, layers expect {} → {} → {}", fc1.in_dim(), fc1.out_dim(), fc2.out_dim());
    }
    let m = x.elem_count() / k.max(1);
    let n = fc2.out_dim();
    // Equal chunks of at most `rows` (2184 rows at 2048 made a 136-row tail whose GEMMs reuse
    // the weights poorly); a row's result does not depend on its chunk.
    let rows = m.div_ceil(m.div_ceil(rows.max(1)).max(1)).max(1);
    let out = with_f32(x, |xs| {
        let mut out = vec![0f32; m * n];
        for (xc, oc) in xs.chunks(rows * k).zip(out.chunks_mut(rows * n)) {
            let r = xc.len() / k;
            fc2.forward_into(&fc1.forward_slice(xc, r, act)?, r, Activation::None, oc)?;
        }
        Ok(out)
    })?;
    let mut od = dims;
    *od.last_mut().unwrap() = n;
    tensor(out, &od)
}

/// Linear layer with bias (`{prefix}.weight`, `{prefix}.bias`): candle's on
/// the plain path, packed weights on the fast path (the f32 copy is dropped).
#[derive(Debug, Clone)]
pub struct Linear {
    plain: Option<candle_nn::Linear>,
    fast: Option<Arc<FastLinear>>,
}

impl Linear {
    /// Wrap a candle layer for `compute` (packing its weights for a fast one).
    pub fn new(l: candle_nn::Linear, compute: Compute) -> Result<Self> {
        match compute.fast_parts() {
            None => Ok(Self { plain: Some(l), fast: None }),
            Some((p, isa)) => Ok(Self { plain: None, fast: Some(Arc::new(FastLinear::new(l.weight(), l.bias(), p, isa)?)) }),
        }
    }
    /// The packed layer (fast path).
    pub fn fast(&self) -> Option<&FastLinear> {
        self.fast.as_deref()
    }
    /// Weight `[N, K]` (plain path only).
    pub fn weight(&self) -> Option<&Tensor> {
        self.plain.as_ref().map(|l| l.weight())
    }
    /// `act(linear(x))`; on the fast path the activation is fused into the GEMM.
    pub fn forward_act(&self, x: &Tensor, act: Activation) -> Result<Tensor> {
        if let Some(f) = &self.fast {
            return f.forward(x, act);
        }
        let l = self.plain.as_ref().ok_or_else(|| candle_core::Error::Msg("linear: no weights".into()))?;
        let y = candle_core::Module::forward(l, x)?;
        match act {
            Activation::None => Ok(y),
            Activation::GeluTanh => y.gelu(),
            Activation::GeluErf => y.gelu_erf(),
            Activation::Silu => y.silu(),
        }
    }
}

impl candle_core::Module for Linear {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        self.forward_act(x, Activation::None)
    }
}

/// Rows per parallel work item of the row-wise kernels (fixed, so results
/// never depend on the thread count).
const ROW_BLOCK: usize = 64;

/// Per-item vectors `[B or 1, C]` (or `[C]`) as a flat Vec and item count.
fn per_item(t: Option<&Tensor>, c: usize) -> Result<Option<(Vec<f32>, usize)>> {
    let Some(t) = t else { return Ok(None) };
    let v = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    if v.is_empty() || v.len() % c != 0 {
        candle_core::bail!("fast kernels: per-item vector of {} values for {c} channels", v.len());
    }
    let items = v.len() / c;
    Ok(Some((v, items)))
}

/// LayerNorm over the last dim of `x` `[B, L, C]` (or `[N, C]`, B = 1):
/// `LN(x)·mul + add` with `mul`/`add` `[C]` or per item `[B, C]`
/// (adaLN: `mul = 1 + scale`, `add = shift`).
pub fn layer_norm(isa: Isa, x: &Tensor, eps: f64, mul: Option<&Tensor>, add: Option<&Tensor>) -> Result<Tensor> {
    profile::timed(profile::Kind::Norm, || 0, || layer_norm_impl(isa, x, eps, mul, add))
}

fn layer_norm_impl(isa: Isa, x: &Tensor, eps: f64, mul: Option<&Tensor>, add: Option<&Tensor>) -> Result<Tensor> {
    let dims = x.dims().to_vec();
    let c = *dims.last().unwrap_or(&1);
    let rows = x.elem_count() / c.max(1);
    let b = if dims.len() == 3 { dims[0] } else { 1 };
    let per_b = rows / b.max(1);
    let mul = per_item(mul, c)?;
    let add = per_item(add, c)?;
    for (v, items) in [&mul, &add].into_iter().flatten() {
        if *items != 1 && *items != b {
            candle_core::bail!("layer norm: {items} modulation rows for batch {b}");
        }
        let _ = v;
    }
    let pick = |m: &Option<(Vec<f32>, usize)>, row: usize| -> Option<std::ops::Range<usize>> {
        m.as_ref().map(|(_, items)| {
            let i = if *items == 1 { 0 } else { row / per_b };
            i * c..(i + 1) * c
        })
    };
    let mut out = vec![0f32; rows * c];
    with_f32(x, |xs| {
        out.par_chunks_mut(ROW_BLOCK * c).enumerate().for_each(|(bi, oc)| {
            for (r, o) in oc.chunks_exact_mut(c).enumerate() {
                let row = bi * ROW_BLOCK + r;
                let mm = pick(&mul, row).map(|rg| &mul.as_ref().unwrap().0[rg]);
                let aa = pick(&add, row).map(|rg| &add.as_ref().unwrap().0[rg]);
                vecmath::layer_norm_row(isa, &xs[row * c..(row + 1) * c], o, eps as f32, mm, aa);
            }
        });
        Ok(())
    })?;
    tensor(out, &dims)
}

/// `x + h·gate` with `gate` `[C]` or per item `[B, C]` (None: `x + h`).
pub fn gated_residual(x: &Tensor, h: &Tensor, gate: Option<&Tensor>) -> Result<Tensor> {
    if x.dims() != h.dims() {
        candle_core::bail!("residual: shapes {:?} and {:?} differ", x.dims(), h.dims());
    }
    let dims = x.dims().to_vec();
    let c = *dims.last().unwrap_or(&1);
    let rows = x.elem_count() / c.max(1);
    let b = if dims.len() == 3 { dims[0] } else { 1 };
    let per_b = rows / b.max(1);
    let gate = per_item(gate, c)?;
    if let Some((_, items)) = &gate {
        if *items != 1 && *items != b {
            candle_core::bail!("residual: {items} gate rows for batch {b}");
        }
    }
    let mut out = vec![0f32; rows * c];
    with_f32(x, |xs| {
        with_f32(h, |hs| {
            out.par_chunks_mut(ROW_BLOCK * c).enumerate().for_each(|(bi, oc)| {
                for (r, o) in oc.chunks_exact_mut(c).enumerate() {
                    let row = bi * ROW_BLOCK + r;
                    let (xr, hr) = (&xs[row * c..(row + 1) * c], &hs[row * c..(row + 1) * c]);
                    match &gate {
                        Some((g, items)) => {
                            let i = if *items == 1 { 0 } else { row / per_b };
                            let g = &g[i * c..(i + 1) * c];
                            for j in 0..c {
                                o[j] = xr[j] + hr[j] * g[j];
                            }
                        }
                        None => {
                            for j in 0..c {
                                o[j] = xr[j] + hr[j];
                            }
                        }
                    }
                }
            });
            Ok(())
        })
    })?;
    tensor(out, &dims)
}

/// TRELLIS `MultiHeadRMSNorm` in place on rows of a buffer: each head vector
/// (at `row·stride + offset + h·d`) → `x/‖x‖·gamma[h]·√d`.
pub fn rms_norm_heads(buf: &mut [f32], rows: usize, stride: usize, offset: usize, gamma: &[f32], heads: usize, d: usize) {
    let scale = (d as f32).sqrt();
    profile::timed(
        profile::Kind::Norm,
        || 0,
        || {
            buf.par_chunks_mut(stride).take(rows).for_each(|row| {
                for h in 0..heads {
                    vecmath::rms_norm_head(&mut row[offset + h * d..offset + (h + 1) * d], &gamma[h * d..(h + 1) * d], scale);
                }
            })
        },
    );
}

/// Flash attention on row buffers: q rows `[.., q_stride]`, k/v rows; heads
/// of width `d` at the given offsets; output `[rows, heads·d]`.
#[allow(clippy::too_many_arguments)]
pub fn attention_rows(
    isa: Isa,
    precision: Precision,
    heads: usize,
    d: usize,
    q: (&[f32], HeadLayout),
    k: (&[f32], HeadLayout),
    v: (&[f32], HeadLayout),
    out_rows: usize,
    segments: &[Segment],
) -> Result<Vec<f32>> {
    let c = heads * d;
    let mut out = vec![0f32; out_rows * c];
    let spec = AttnSpec {
        heads,
        head_dim: d,
        scale: 1.0 / (d as f32).sqrt(),
        q: q.1,
        k: k.1,
        v: v.1,
        out: HeadLayout::new(c, 0),
        precision: precision.attention(),
    };
    // Scores and weighted sum: 2·d each per (query, key, head).
    let flops = || segments.iter().map(|s| 4 * (s.q.len() * s.kv.len() * c) as u64).sum();
    profile::timed(profile::Kind::Attention, flops, || flash_attention(isa, &spec, q.0, k.0, v.0, segments, &mut out)).map_err(kerr)?;
    Ok(out)
}

pub use recon_kernels::attention::{HeadLayout as AttnLayout, Segment as AttnSegment};

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Module;

    #[test]
    fn precision_parses_and_compute_parts() {
        assert_eq!("BF16".parse::<Precision>().unwrap(), Precision::Bf16);
        assert!("fp8".parse::<Precision>().unwrap_err().contains("expected f32, bf16 or f16"));
        assert_eq!(Compute::default(), Compute::Plain);
        assert_eq!(Compute::Plain.fast_parts(), None);
        let f16 = Compute::fast(Precision::F16);
        assert!(f16.is_fast());
        assert_eq!(f16.fast_parts(), Some((Precision::F16, Isa::best())));
    }

    #[test]
    fn fast_linear_matches_candle_in_every_precision() -> Result<()> {
        let dev = Device::Cpu;
        let w = Tensor::randn(0f32, 0.1, (37, 70), &dev)?;
        let b = Tensor::randn(0f32, 0.1, 37, &dev)?;
        let x = Tensor::randn(0f32, 1.0, (2, 9, 70), &dev)?;
        let plain = candle_nn::Linear::new(w.clone(), Some(b.clone()));
        let want = plain.forward(&x)?.gelu()?;
        for (p, tol) in [(Precision::F32, 1e-5f32), (Precision::F16, 2e-3), (Precision::Bf16, 2e-2)] {
            for isa in Isa::all_supported() {
                let l = Linear::new(plain.clone(), Compute::Fast { precision: p, isa })?;
                assert!(l.weight().is_none(), "fast layer keeps no f32 copy");
                let got = l.forward_act(&x, Activation::GeluTanh)?;
                assert_eq!(got.dims(), &[2, 9, 37]);
                let d = (got - &want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
                assert!(d < tol, "{p} {isa:?}: max diff {d}");
            }
        }
        let l = Linear::new(plain, Compute::fast(Precision::F32))?;
        assert!(l.forward(&Tensor::zeros((3, 5), DType::F32, &dev)?).is_err(), "wrong width is an error");
        Ok(())
    }

    #[test]
    fn fused_norm_and_residual_match_candle() -> Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::randn(0f32, 2.0, (2, 70, 48), &dev)?;
        let h = Tensor::randn(0f32, 1.0, (2, 70, 48), &dev)?;
        let scale = Tensor::randn(0f32, 0.3, (2, 48), &dev)?;
        let shift = Tensor::randn(0f32, 0.3, (2, 48), &dev)?;
        let mul = (&scale + 1.0)?;
        let want =
            crate::model::nn::common::layer_norm_plain(&x, 1e-6)?.broadcast_mul(&mul.unsqueeze(1)?)?.broadcast_add(&shift.unsqueeze(1)?)?;
        for isa in Isa::all_supported() {
            let got = layer_norm(isa, &x, 1e-6, Some(&mul), Some(&shift))?;
            let d = (got - &want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "{isa:?}: layer norm diff {d}");
        }
        let want = (&x + h.broadcast_mul(&scale.unsqueeze(1)?)?)?;
        let got = gated_residual(&x, &h, Some(&scale))?;
        assert_eq!((got - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?, 0.0);
        let shared = scale.get(0)?;
        let want = (&x + h.broadcast_mul(&shared)?)?;
        let got = gated_residual(&x, &h, Some(&shared))?;
        assert_eq!((got - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?, 0.0);
        assert!(gated_residual(&x, &h.narrow(1, 0, 3)?, None).is_err());
        Ok(())
    }
}
