//! Vectorised element-wise math: exp, GELU (tanh and erf forms), SiLU,
//! row LayerNorm and per-head RMS normalisation.
//!
//! The AVX-512, AVX2 and portable versions evaluate the same formulas (same
//! range reduction, same polynomials), so they agree to a few ulp; the
//! portable one is written so the compiler can vectorise it at the baseline ISA.
//! exp is accurate to about 2 ulp on [-87, 88]; the erf used by the exact
//! GELU has an absolute error below 1.5e-7 (Abramowitz & Stegun 7.1.26).

use crate::isa::{Isa, Simd};

/// Element-wise function applied after a GEMM (in its epilogue).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Activation {
    /// Identity.
    None,
    /// `0.5·x·(1 + tanh(√(2/π)(x + 0.044715x³)))` (PyTorch `approximate="tanh"`; TRELLIS MLPs).
    GeluTanh,
    /// `0.5·x·(1 + erf(x/√2))` (PyTorch default; DINOv2 MLPs).
    GeluErf,
    /// `x·sigmoid(x)`.
    Silu,
}

const LOG2E: f32 = std::f32::consts::LOG2_E;
const LN2_HI: f32 = 0.693_145_75;
const LN2_LO: f32 = 1.428_606_8e-6;
// Clamps keep 2^n a normal float in the portable bit construction.
const EXP_LO: f32 = -87.3;
const EXP_HI: f32 = 88.0;
const SQRT_2_OVER_PI: f32 = 0.797_884_6;
const ERF_P: f32 = 0.327_591_1;
const ERF_A: [f32; 5] = [0.254_829_6, -0.284_496_74, 1.421_413_7, -1.453_152, 1.061_405_4];

/// exp(x) (scalar, same algorithm as the vector versions).
#[inline(always)]
pub fn exp_approx(x: f32) -> f32 {
    let x = x.clamp(EXP_LO, EXP_HI);
    // Round to nearest by the 1.5·2^23 trick (vectorises without SSE4.1).
    let n = (x * LOG2E + 12_582_912.0) - 12_582_912.0;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = exp_poly(r);
    p * f32::from_bits(((n as i32 + 127) as u32) << 23)
}

#[inline(always)]
fn exp_poly(r: f32) -> f32 {
    // Taylor to degree 7 on |r| ≤ ln2/2: truncation error < 5e-9 relative.
    let mut p = 1.0 / 5040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * r + 1.0;
    p * r + 1.0
}

#[inline(always)]
fn erf_approx(x: f32) -> f32 {
    let a = x.abs();
    let t = 1.0 / (1.0 + ERF_P * a);
    let poly = ((((ERF_A[4] * t + ERF_A[3]) * t + ERF_A[2]) * t + ERF_A[1]) * t + ERF_A[0]) * t;
    let y = 1.0 - poly * exp_approx(-a * a);
    if x < 0.0 {
        -y
    } else {
        y
    }
}

#[inline(always)]
fn act_scalar(x: f32, act: Activation) -> f32 {
    match act {
        Activation::None => x,
        Activation::GeluTanh => {
            let u = SQRT_2_OVER_PI * (x + 0.044715 * x * x * x);
            x / (1.0 + exp_approx(-2.0 * u))
        }
        Activation::GeluErf => 0.5 * x * (1.0 + erf_approx(x * std::f32::consts::FRAC_1_SQRT_2)),
        Activation::Silu => x / (1.0 + exp_approx(-x)),
    }
}

/// `x[i] = act(x[i] + bias[i])` (bias optional).
pub fn bias_act(isa: Isa, x: &mut [f32], bias: Option<&[f32]>, act: Activation) {
    if let Some(b) = bias {
        assert!(b.len() >= x.len(), "bias shorter than the row");
    }
    if bias.is_none() && act == Activation::None {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    match isa.simd() {
        // SAFETY (all vector paths): kernels only get an `isa` the CPU runs
        // (Isa::supported), and the slices are in bounds.
        Simd::Avx512 => return unsafe { x86::bias_act(x, bias, act) },
        Simd::Avx2 => return unsafe { avx2::bias_act(x, bias, act) },
        Simd::Scalar => {}
    }
    let _ = isa;
    match bias {
        Some(b) => x.iter_mut().zip(b).for_each(|(v, &bb)| *v = act_scalar(*v + bb, act)),
        None => x.iter_mut().for_each(|v| *v = act_scalar(*v, act)),
    }
}

/// In-place `x[i] = exp(x[i])`.
pub fn exp_inplace(isa: Isa, x: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    match isa.simd() {
        // SAFETY: see `bias_act`.
        Simd::Avx512 => return unsafe { x86::exp_inplace(x) },
        Simd::Avx2 => return unsafe { avx2::exp_inplace(x) },
        Simd::Scalar => {}
    }
    let _ = isa;
    x.iter_mut().for_each(|v| *v = exp_approx(*v));
}

/// LayerNorm of one row: `out = (x − mean)/√(var + eps) · mul + add`, with
/// `mul`/`add` per channel (affine weights, adaLN `1 + scale` / `shift`, or both
/// folded by the caller). Statistics in f32 with the biased variance, as torch.
pub fn layer_norm_row(isa: Isa, x: &[f32], out: &mut [f32], eps: f32, mul: Option<&[f32]>, add: Option<&[f32]>) {
    let c = x.len();
    assert!(out.len() == c && mul.is_none_or(|m| m.len() == c) && add.is_none_or(|a| a.len() == c), "layer_norm_row: length mismatch");
    if c == 0 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    match isa.simd() {
        // SAFETY: see `bias_act`.
        Simd::Avx512 => return unsafe { x86::layer_norm_row(x, out, eps, mul, add) },
        Simd::Avx2 => return unsafe { avx2::layer_norm_row(x, out, eps, mul, add) },
        Simd::Scalar => {}
    }
    let _ = isa;
    let mean = sum8(x.iter().copied()) / c as f32;
    let var = sum8(x.iter().map(|&v| (v - mean) * (v - mean))) / c as f32;
    let rstd = 1.0 / (var + eps).sqrt();
    for i in 0..c {
        let mut y = (x[i] - mean) * rstd;
        if let Some(m) = mul {
            y *= m[i];
        }
        if let Some(a) = add {
            y += a[i];
        }
        out[i] = y;
    }
}

/// Sum with 16 interleaved partial sums (the AVX-512 lane order), so the
/// portable and vector paths add in a similar order.
fn sum8(it: impl Iterator<Item = f32>) -> f32 {
    let mut acc = [0f32; 16];
    for (i, v) in it.enumerate() {
        acc[i % 16] += v;
    }
    acc.iter().sum()
}

/// `x = x / max(‖x‖₂, 1e-12) · gamma · scale` on one head vector
/// (TRELLIS `MultiHeadRMSNorm`: F.normalize · gamma · √d).
pub fn rms_norm_head(x: &mut [f32], gamma: &[f32], scale: f32) {
    let ss: f32 = sum8(x.iter().map(|&v| v * v));
    let inv = scale / ss.sqrt().max(1e-12);
    x.iter_mut().zip(gamma).for_each(|(v, &g)| *v = *v * inv * g);
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod x86 {
    use super::*;
    use std::arch::x86_64::*;

    #[inline(always)]
    pub unsafe fn exp512(x: __m512) -> __m512 {
        let x = _mm512_max_ps(_mm512_min_ps(x, _mm512_set1_ps(EXP_HI)), _mm512_set1_ps(EXP_LO));
        let n = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(_mm512_mul_ps(x, _mm512_set1_ps(LOG2E)));
        let r = _mm512_fnmadd_ps(n, _mm512_set1_ps(LN2_HI), x);
        let r = _mm512_fnmadd_ps(n, _mm512_set1_ps(LN2_LO), r);
        let mut p = _mm512_set1_ps(1.0 / 5040.0);
        for c in [1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
            p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(c));
        }
        _mm512_scalef_ps(p, n)
    }

    #[inline(always)]
    unsafe fn erf512(x: __m512) -> __m512 {
        let sign = _mm512_and_si512(_mm512_castps_si512(x), _mm512_set1_epi32(i32::MIN));
        let a = _mm512_castsi512_ps(_mm512_andnot_si512(_mm512_set1_epi32(i32::MIN), _mm512_castps_si512(x)));
        let one = _mm512_set1_ps(1.0);
        let t = _mm512_div_ps(one, _mm512_fmadd_ps(_mm512_set1_ps(ERF_P), a, one));
        let mut p = _mm512_set1_ps(ERF_A[4]);
        for c in [ERF_A[3], ERF_A[2], ERF_A[1], ERF_A[0]] {
            p = _mm512_fmadd_ps(p, t, _mm512_set1_ps(c));
        }
        p = _mm512_mul_ps(p, t);
        let e = exp512(_mm512_sub_ps(_mm512_setzero_ps(), _mm512_mul_ps(a, a)));
        let y = _mm512_fnmadd_ps(p, e, one);
        _mm512_castsi512_ps(_mm512_or_si512(_mm512_castps_si512(y), sign))
    }

    #[inline(always)]
    pub unsafe fn act512(x: __m512, act: Activation) -> __m512 {
        let one = _mm512_set1_ps(1.0);
        match act {
            Activation::None => x,
            Activation::GeluTanh => {
                let x3 = _mm512_mul_ps(_mm512_mul_ps(x, x), x);
                let u = _mm512_mul_ps(_mm512_set1_ps(SQRT_2_OVER_PI), _mm512_fmadd_ps(_mm512_set1_ps(0.044715), x3, x));
                let e = exp512(_mm512_mul_ps(_mm512_set1_ps(-2.0), u));
                _mm512_div_ps(x, _mm512_add_ps(one, e))
            }
            Activation::GeluErf => {
                let e = erf512(_mm512_mul_ps(x, _mm512_set1_ps(std::f32::consts::FRAC_1_SQRT_2)));
                _mm512_mul_ps(_mm512_mul_ps(_mm512_set1_ps(0.5), x), _mm512_add_ps(one, e))
            }
            Activation::Silu => {
                let e = exp512(_mm512_sub_ps(_mm512_setzero_ps(), x));
                _mm512_div_ps(x, _mm512_add_ps(one, e))
            }
        }
    }

    #[inline(always)]
    pub fn tail_mask(n: usize) -> __mmask16 {
        if n >= 16 {
            0xffff
        } else {
            ((1u32 << n) - 1) as __mmask16
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,fma")]
    pub unsafe fn bias_act(x: &mut [f32], bias: Option<&[f32]>, act: Activation) {
        let n = x.len();
        let mut i = 0;
        while i < n {
            let m = tail_mask(n - i);
            let p = x.as_mut_ptr().add(i);
            let mut v = _mm512_maskz_loadu_ps(m, p);
            if let Some(b) = bias {
                v = _mm512_add_ps(v, _mm512_maskz_loadu_ps(m, b.as_ptr().add(i)));
            }
            _mm512_mask_storeu_ps(p, m, act512(v, act));
            i += 16;
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,fma")]
    pub unsafe fn exp_inplace(x: &mut [f32]) {
        let n = x.len();
        let mut i = 0;
        while i < n {
            let m = tail_mask(n - i);
            let p = x.as_mut_ptr().add(i);
            _mm512_mask_storeu_ps(p, m, exp512(_mm512_maskz_loadu_ps(m, p)));
            i += 16;
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,fma")]
    pub unsafe fn layer_norm_row(x: &[f32], out: &mut [f32], eps: f32, mul: Option<&[f32]>, add: Option<&[f32]>) {
        let c = x.len();
        let xp = x.as_ptr();
        let mut s = _mm512_setzero_ps();
        let mut i = 0;
        while i < c {
            s = _mm512_add_ps(s, _mm512_maskz_loadu_ps(tail_mask(c - i), xp.add(i)));
            i += 16;
        }
        let mean = _mm512_reduce_add_ps(s) / c as f32;
        let vm = _mm512_set1_ps(mean);
        let mut q = _mm512_setzero_ps();
        i = 0;
        while i < c {
            let m = tail_mask(c - i);
            let d = _mm512_maskz_sub_ps(m, _mm512_maskz_loadu_ps(m, xp.add(i)), vm);
            q = _mm512_fmadd_ps(d, d, q);
            i += 16;
        }
        let var = _mm512_reduce_add_ps(q) / c as f32;
        let rstd = _mm512_set1_ps(1.0 / (var + eps).sqrt());
        i = 0;
        while i < c {
            let m = tail_mask(c - i);
            let mut y = _mm512_mul_ps(_mm512_sub_ps(_mm512_maskz_loadu_ps(m, xp.add(i)), vm), rstd);
            if let Some(w) = mul {
                y = _mm512_mul_ps(y, _mm512_maskz_loadu_ps(m, w.as_ptr().add(i)));
            }
            if let Some(b) = add {
                y = _mm512_add_ps(y, _mm512_maskz_loadu_ps(m, b.as_ptr().add(i)));
            }
            _mm512_mask_storeu_ps(out.as_mut_ptr().add(i), m, y);
            i += 16;
        }
    }
}

/// The AVX2 + FMA versions: the AVX-512 ones on 8 lanes, with the integer
/// `2^n` construction of the portable exp (no `vscalefps`) and
/// `vmaskmovps` tails. LayerNorm sums in 16 lanes (two vectors) as AVX-512 does.
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::*;
    use std::arch::x86_64::*;

    /// The first `min(n, 8)` lanes set, as `vmaskmovps` wants (gemm's AVX2
    /// tails use it too: vecmath is the layer below gemm).
    #[inline(always)]
    pub(crate) unsafe fn lane_mask(n: usize) -> __m256i {
        _mm256_cmpgt_epi32(_mm256_set1_epi32(n.min(8) as i32), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7))
    }

    #[inline(always)]
    pub unsafe fn exp256(x: __m256) -> __m256 {
        let x = _mm256_max_ps(_mm256_min_ps(x, _mm256_set1_ps(EXP_HI)), _mm256_set1_ps(EXP_LO));
        let n = _mm256_round_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(_mm256_mul_ps(x, _mm256_set1_ps(LOG2E)));
        let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(LN2_HI), x);
        let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(LN2_LO), r);
        let mut p = _mm256_set1_ps(1.0 / 5040.0);
        for c in [1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
            p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(c));
        }
        // The clamps keep n in [-126, 127]: 2^n is a normal float.
        let pow2 = _mm256_slli_epi32::<23>(_mm256_add_epi32(_mm256_cvtps_epi32(n), _mm256_set1_epi32(127)));
        _mm256_mul_ps(p, _mm256_castsi256_ps(pow2))
    }

    #[inline(always)]
    unsafe fn erf256(x: __m256) -> __m256 {
        let sign_bit = _mm256_set1_ps(-0.0);
        let sign = _mm256_and_ps(x, sign_bit);
        let a = _mm256_andnot_ps(sign_bit, x);
        let one = _mm256_set1_ps(1.0);
        let t = _mm256_div_ps(one, _mm256_fmadd_ps(_mm256_set1_ps(ERF_P), a, one));
        let mut p = _mm256_set1_ps(ERF_A[4]);
        for c in [ERF_A[3], ERF_A[2], ERF_A[1], ERF_A[0]] {
            p = _mm256_fmadd_ps(p, t, _mm256_set1_ps(c));
        }
        p = _mm256_mul_ps(p, t);
        let e = exp256(_mm256_sub_ps(_mm256_setzero_ps(), _mm256_mul_ps(a, a)));
        let y = _mm256_fnmadd_ps(p, e, one);
        _mm256_or_ps(y, sign)
    }

    #[inline(always)]
    pub unsafe fn act256(x: __m256, act: Activation) -> __m256 {
        let one = _mm256_set1_ps(1.0);
        match act {
            Activation::None => x,
            Activation::GeluTanh => {
                let x3 = _mm256_mul_ps(_mm256_mul_ps(x, x), x);
                let u = _mm256_mul_ps(_mm256_set1_ps(SQRT_2_OVER_PI), _mm256_fmadd_ps(_mm256_set1_ps(0.044715), x3, x));
                let e = exp256(_mm256_mul_ps(_mm256_set1_ps(-2.0), u));
                _mm256_div_ps(x, _mm256_add_ps(one, e))
            }
            Activation::GeluErf => {
                let e = erf256(_mm256_mul_ps(x, _mm256_set1_ps(std::f32::consts::FRAC_1_SQRT_2)));
                _mm256_mul_ps(_mm256_mul_ps(_mm256_set1_ps(0.5), x), _mm256_add_ps(one, e))
            }
            Activation::Silu => {
                let e = exp256(_mm256_sub_ps(_mm256_setzero_ps(), x));
                _mm256_div_ps(x, _mm256_add_ps(one, e))
            }
        }
    }

    /// `f` on every 8 lanes of `x` in place (the tail masked: its missing lanes read as zero).
    #[inline(always)]
    unsafe fn map(x: &mut [f32], f: impl Fn(__m256, usize, __m256i) -> __m256) {
        let n = x.len();
        let p = x.as_mut_ptr();
        let full = n / 8 * 8;
        let all = _mm256_set1_epi32(-1);
        for i in (0..full).step_by(8) {
            _mm256_storeu_ps(p.add(i), f(_mm256_loadu_ps(p.add(i)), i, all));
        }
        if full < n {
            let m = lane_mask(n - full);
            _mm256_maskstore_ps(p.add(full), m, f(_mm256_maskload_ps(p.add(full), m), full, m));
        }
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn bias_act(x: &mut [f32], bias: Option<&[f32]>, act: Activation) {
        map(x, |v, i, m| {
            let v = match bias {
                Some(b) => _mm256_add_ps(v, _mm256_maskload_ps(b.as_ptr().add(i), m)),
                None => v,
            };
            act256(v, act)
        });
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn exp_inplace(x: &mut [f32]) {
        map(x, |v, _, _| exp256(v));
    }

    /// Sum of the 8 lanes.
    #[inline(always)]
    pub unsafe fn hsum(v: __m256) -> f32 {
        let s = _mm_add_ps(_mm256_castps256_ps128(v), _mm256_extractf128_ps::<1>(v));
        let s = _mm_add_ps(s, _mm_movehl_ps(s, s));
        _mm_cvtss_f32(_mm_add_ss(s, _mm_movehdup_ps(s)))
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn layer_norm_row(x: &[f32], out: &mut [f32], eps: f32, mul: Option<&[f32]>, add: Option<&[f32]>) {
        let c = x.len();
        let xp = x.as_ptr();
        let load = |i: usize| _mm256_maskload_ps(xp.add(i), lane_mask(c - i));
        let mut s = [_mm256_setzero_ps(); 2];
        for i in (0..c).step_by(8) {
            s[(i / 8) % 2] = _mm256_add_ps(s[(i / 8) % 2], load(i));
        }
        let mean = hsum(_mm256_add_ps(s[0], s[1])) / c as f32;
        let vm = _mm256_set1_ps(mean);
        let mut q = [_mm256_setzero_ps(); 2];
        for i in (0..c).step_by(8) {
            // Lanes past the end read as zero: keep them out of the sum.
            let d = _mm256_and_ps(_mm256_sub_ps(load(i), vm), _mm256_castsi256_ps(lane_mask(c - i)));
            q[(i / 8) % 2] = _mm256_fmadd_ps(d, d, q[(i / 8) % 2]);
        }
        let var = hsum(_mm256_add_ps(q[0], q[1])) / c as f32;
        let rstd = _mm256_set1_ps(1.0 / (var + eps).sqrt());
        for i in (0..c).step_by(8) {
            let m = lane_mask(c - i);
            let mut y = _mm256_mul_ps(_mm256_sub_ps(load(i), vm), rstd);
            if let Some(w) = mul {
                y = _mm256_mul_ps(y, _mm256_maskload_ps(w.as_ptr().add(i), m));
            }
            if let Some(b) = add {
                y = _mm256_add_ps(y, _mm256_maskload_ps(b.as_ptr().add(i), m));
            }
            _mm256_maskstore_ps(out.as_mut_ptr().add(i), m, y);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gelu_tanh_ref(x: f64) -> f64 {
        0.5 * x * (1.0 + ((2.0 / std::f64::consts::PI).sqrt() * (x + 0.044715 * x * x * x)).tanh())
    }

    /// erf in f64: Maclaurin series for |x| ≤ 3, asymptotic erfc beyond.
    fn erf_ref(x: f64) -> f64 {
        let z = x.abs();
        if z > 3.0 {
            let z2 = z * z;
            let erfc = (-z2).exp() / (z * std::f64::consts::PI.sqrt())
                * (1.0 - 1.0 / (2.0 * z2) + 3.0 / (4.0 * z2 * z2) - 15.0 / (8.0 * z2 * z2 * z2));
            return x.signum() * (1.0 - erfc);
        }
        let (mut sum, mut term, mut n) = (0.0, x, 0.0);
        while n < 60.0 {
            sum += term / (2.0 * n + 1.0);
            n += 1.0;
            term *= -x * x / n;
        }
        sum * 2.0 / std::f64::consts::PI.sqrt()
    }

    fn inputs() -> Vec<f32> {
        let mut v: Vec<f32> = (-2000..=2000).map(|i| i as f32 * 0.01).collect();
        v.extend([-100.0, -88.5, -87.0, 87.0, 88.5, 100.0, 0.0, -0.0, 1e-30, -1e-30]);
        v
    }

    #[test]
    fn exp_matches_std_on_every_isa() {
        for isa in Isa::all_supported() {
            let xs = inputs();
            let mut y = xs.clone();
            exp_inplace(isa, &mut y);
            for (&x, &e) in xs.iter().zip(&y) {
                let want = (x.clamp(EXP_LO, EXP_HI) as f64).exp();
                let rel = ((e as f64 - want) / want).abs();
                assert!(rel < 4e-7, "{isa:?} exp({x}) = {e}, want {want} (rel {rel:.2e})");
            }
        }
    }

    #[test]
    fn activations_match_f64_reference_on_every_isa() {
        for isa in Isa::all_supported() {
            for act in [Activation::GeluTanh, Activation::GeluErf, Activation::Silu, Activation::None] {
                let xs = inputs();
                // Odd length exercises the masked tail.
                let xs = &xs[..xs.len() - 3];
                let bias: Vec<f32> = (0..xs.len()).map(|i| (i % 7) as f32 * 0.01).collect();
                let mut y = xs.to_vec();
                bias_act(isa, &mut y, Some(&bias), act);
                for i in 0..xs.len() {
                    let x = (xs[i] + bias[i]) as f64;
                    let want = match act {
                        Activation::None => x,
                        Activation::GeluTanh => gelu_tanh_ref(x),
                        Activation::GeluErf => 0.5 * x * (1.0 + erf_ref(x / 2f64.sqrt())),
                        Activation::Silu => x / (1.0 + (-x).exp()),
                    };
                    let err = (y[i] as f64 - want).abs();
                    assert!(err <= 2e-6 * want.abs().max(1.0), "{isa:?} {act:?}({x}) = {}, want {want}", y[i]);
                }
            }
        }
    }

    #[test]
    fn layer_norm_matches_reference_on_every_isa() {
        for isa in Isa::all_supported() {
            for c in [1usize, 5, 16, 33, 1024] {
                let x: Vec<f32> = (0..c).map(|i| ((i * 37) % 11) as f32 * 0.3 - 1.0 + 5.0).collect();
                let mul: Vec<f32> = (0..c).map(|i| 1.0 + i as f32 * 0.01).collect();
                let add: Vec<f32> = (0..c).map(|i| i as f32 * -0.02).collect();
                let mut out = vec![0f32; c];
                layer_norm_row(isa, &x, &mut out, 1e-6, Some(&mul), Some(&add));
                let mean = x.iter().map(|&v| v as f64).sum::<f64>() / c as f64;
                let var = x.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / c as f64;
                for i in 0..c {
                    let want = (x[i] as f64 - mean) / (var + 1e-6).sqrt() * mul[i] as f64 + add[i] as f64;
                    assert!((out[i] as f64 - want).abs() < 2e-5 * want.abs().max(1.0), "{isa:?} c={c} i={i}: {} vs {want}", out[i]);
                }
            }
        }
    }

    #[test]
    fn rms_norm_head_normalises() {
        let mut x = vec![3.0f32, 4.0];
        rms_norm_head(&mut x, &[1.0, 2.0], 2f32.sqrt());
        assert!((x[0] - 0.6 * 2f32.sqrt()).abs() < 1e-6 && (x[1] - 1.6 * 2f32.sqrt()).abs() < 1e-6);
        let mut z = vec![0.0f32; 4];
        rms_norm_head(&mut z, &[1.0; 4], 2.0);
        assert!(z.iter().all(|v| *v == 0.0));
    }
}
