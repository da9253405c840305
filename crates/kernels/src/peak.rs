//! Measured arithmetic peak of each instruction set: independent
//! register-only FMA (ymm for AVX2, zmm for AVX-512) or `vdpbf16ps` chains
//! on every pool thread, so GEMM efficiency can be reported against what
//! this machine actually sustains (clock, SMT sharing and other load
//! included) rather than a datasheet.

use crate::isa::{Isa, Simd};
use std::sync::atomic::{AtomicU8, Ordering};
use std::time::Instant;

/// Which multiply-accumulate to time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PeakKind {
    /// f32 FMA (`vfmadd231ps` on ymm / zmm, or scalar-vectorised portable code).
    F32,
    /// bf16 pair dot product with f32 accumulation (`vdpbf16ps zmm`); 2 FLOP per bf16 product.
    Bf16,
}

/// GFLOP/s over all threads of the current rayon pool (best of `reps` runs of
/// `iters` iterations each). `None` when `isa` cannot run `kind`.
pub fn measure_peak_gflops(isa: Isa, kind: PeakKind, iters: usize, reps: usize) -> Option<f64> {
    if !isa.supported() || (kind == PeakKind::Bf16 && isa != Isa::Avx512Bf16) {
        return None;
    }
    let threads = rayon::current_num_threads().max(1);
    let mut best = 0f64;
    for _ in 0..reps.max(1) {
        let t0 = Instant::now();
        let flops: f64 = rayon::broadcast(|_| run(isa, kind, iters)).into_iter().sum();
        let s = t0.elapsed().as_secs_f64();
        best = best.max(flops / s / 1e9);
    }
    let _ = threads;
    Some(best)
}

/// `vdpbf16ps` must beat f32 FMA by this factor (same-thread peaks) to be
/// used: below it, bf16 weights are widened to f32 in registers and run on
/// FMA, so bf16 is never slower than f32. Zen 4 gives about 2; the 2-core
/// Xeon of issue 21 gave 0.5 (half-rate `vdpbf16ps`).
pub const BF16_DOT_MIN_GAIN: f64 = 1.25;

/// Whether bf16 pair dot products pay over f32 FMA, from two peaks.
pub fn bf16_dot_pays_given(bf16_gflops: f64, f32_gflops: f64) -> bool {
    bf16_gflops >= BF16_DOT_MIN_GAIN * f32_gflops
}

/// No override set: measure.
const MEASURE: u8 = 0;
const ON: u8 = 1;
const OFF: u8 = 2;
static BF16_DOT: AtomicU8 = AtomicU8::new(MEASURE);

/// Force (`Some(true)`) or forbid (`Some(false)`) `vdpbf16ps` for bf16
/// weights instead of measuring whether it pays (`None`), process-wide.
/// Programs set it once at start, from their settings (`RECON_BF16_DOT`),
/// before the first [`bf16_isa`] call fixes the choice.
pub fn set_bf16_dot(choice: Option<bool>) {
    BF16_DOT.store(
        match choice {
            None => MEASURE,
            Some(true) => ON,
            Some(false) => OFF,
        },
        Ordering::Release,
    );
}

/// The instruction set bf16 weights run on: [`Isa::best`], except that
/// [`Isa::Avx512Bf16`] falls back to [`Isa::Avx512`] (bf16 storage, f32
/// FMA) where `vdpbf16ps` does not pay. Measured once per process on the
/// calling thread (about a millisecond); [`set_bf16_dot`] overrides the
/// measurement.
pub fn bf16_isa() -> Isa {
    static CHOICE: std::sync::OnceLock<Isa> = std::sync::OnceLock::new();
    *CHOICE.get_or_init(|| {
        let best = Isa::best();
        if best != Isa::Avx512Bf16 {
            return best;
        }
        let pays = match BF16_DOT.load(Ordering::Acquire) {
            ON => true,
            OFF => false,
            _ => {
                let peak = |kind| (0..3).map(|_| timed(best, kind, 100_000)).fold(0f64, f64::max);
                bf16_dot_pays_given(peak(PeakKind::Bf16), peak(PeakKind::F32))
            }
        };
        if pays {
            best
        } else {
            Isa::Avx512
        }
    })
}

/// GFLOP/s of one `run` on the calling thread.
fn timed(isa: Isa, kind: PeakKind, iters: usize) -> f64 {
    let t0 = Instant::now();
    let flops = run(isa, kind, iters);
    flops / t0.elapsed().as_secs_f64().max(1e-9) / 1e9
}

fn run(isa: Isa, kind: PeakKind, iters: usize) -> f64 {
    #[cfg(target_arch = "x86_64")]
    match isa.simd() {
        // SAFETY (both): support checked by the caller.
        Simd::Avx512 => {
            return unsafe {
                match kind {
                    PeakKind::F32 => x86::fma(iters),
                    PeakKind::Bf16 => x86::dpbf16(iters),
                }
            }
        }
        Simd::Avx2 => return unsafe { x86::fma_avx2(iters) },
        Simd::Scalar => {}
    }
    let _ = (isa, kind);
    portable(iters)
}

fn portable(iters: usize) -> f64 {
    let mut acc = [[0f32; 16]; 8];
    let a = std::hint::black_box(1.000_000_1f32);
    let b = std::hint::black_box(0.999_999f32);
    for _ in 0..iters {
        for row in acc.iter_mut() {
            for v in row.iter_mut() {
                *v = *v * a + b;
            }
        }
    }
    std::hint::black_box(acc);
    (iters * 8 * 16 * 2) as f64
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    const CHAINS: usize = 24;

    #[target_feature(enable = "avx512f,fma")]
    pub unsafe fn fma(iters: usize) -> f64 {
        let mut acc = [_mm512_setzero_ps(); CHAINS];
        let a = _mm512_set1_ps(std::hint::black_box(1.000_000_1));
        let b = _mm512_set1_ps(std::hint::black_box(0.999_999));
        for _ in 0..iters {
            for v in acc.iter_mut() {
                *v = _mm512_fmadd_ps(a, b, *v);
            }
        }
        std::hint::black_box(acc);
        (iters * CHAINS * 32) as f64
    }

    /// Chains of the AVX2 loop: enough to keep both FMA pipes busy through
    /// their latency, few enough for the 16 ymm registers.
    const CHAINS_YMM: usize = 12;

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn fma_avx2(iters: usize) -> f64 {
        let mut acc = [_mm256_setzero_ps(); CHAINS_YMM];
        let a = _mm256_set1_ps(std::hint::black_box(1.000_000_1));
        let b = _mm256_set1_ps(std::hint::black_box(0.999_999));
        for _ in 0..iters {
            for v in acc.iter_mut() {
                *v = _mm256_fmadd_ps(a, b, *v);
            }
        }
        std::hint::black_box(acc);
        (iters * CHAINS_YMM * 16) as f64
    }

    #[target_feature(enable = "avx512f,avx512bf16")]
    pub unsafe fn dpbf16(iters: usize) -> f64 {
        let mut acc = [_mm512_setzero_ps(); CHAINS];
        let one: __m512bh = std::mem::transmute(_mm512_set1_epi16(std::hint::black_box(0x3f80)));
        for _ in 0..iters {
            for v in acc.iter_mut() {
                *v = _mm512_dpbf16_ps(*v, one, one);
            }
        }
        std::hint::black_box(acc);
        (iters * CHAINS * 64) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bf16_dot_is_used_only_where_it_pays() {
        // Zen 4-like (full-rate vdpbf16ps: twice the FMA peak) and the Xeon of issue 21 (half rate).
        assert!(bf16_dot_pays_given(2.0 * 470.0, 470.0));
        assert!(!bf16_dot_pays_given(238.9, 475.6));
        assert!(!bf16_dot_pays_given(470.0, 470.0));
        let isa = bf16_isa();
        assert!(isa <= Isa::best() && isa.supported());
        // Every family has an f32 peak; only AVX512-BF16 a bf16 one.
        for isa in Isa::all_supported() {
            assert!(measure_peak_gflops(isa, PeakKind::F32, 1000, 1).is_some_and(|g| g > 0.0), "{isa:?}");
            assert_eq!(measure_peak_gflops(isa, PeakKind::Bf16, 1000, 1).is_some(), isa == Isa::Avx512Bf16, "{isa:?}");
        }
        if Isa::best() != Isa::Avx512Bf16 {
            assert_eq!(isa, Isa::best());
        }
    }
}
