//! Instruction-set selection. Every fast kernel has a portable version that
//! runs anywhere; the AVX2 and AVX-512 versions are chosen at run time from
//! what the CPU reports, never at compile time, so one binary serves every
//! x86-64 machine.
//!
//! Kernels dispatch on [`Isa::simd`], matched exhaustively, so a new vector
//! family (e.g. ARM NEON) makes the compiler list every place that needs a
//! version of it. All families read the same packed weights (`NR`-column
//! panels of B, packed once at load time); a narrower vector unit covers a
//! register tile in several sub-tiles, as AVX2 does, and may ask for A
//! tiles of another height (A is packed per call).
//!
//! AMX is not implemented: the development machine (AMD Zen 4) has no AMX
//! unit, and untested tile code is not shipped.

use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::OnceLock;

/// A kernel family. Ordered from most portable to most specialised.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Isa {
    /// Plain Rust (compiler auto-vectorisation at the target's baseline).
    Portable,
    /// AVX2 + FMA + F16C (8-lane f32 FMA; bf16/f16 weights widened to f32 in registers).
    Avx2,
    /// AVX-512 F + BW (f32 FMA; bf16/f16 weights widened to f32 in registers).
    Avx512,
    /// AVX-512 BF16 (`vdpbf16ps`: bf16 pairs, f32 accumulation) on top of [`Isa::Avx512`].
    Avx512Bf16,
}

impl Isa {
    /// Every family, most portable first.
    pub const ALL: [Isa; 4] = [Isa::Portable, Isa::Avx2, Isa::Avx512, Isa::Avx512Bf16];

    /// Lower-case name, as accepted by [`Isa::parse`].
    pub fn name(self) -> &'static str {
        match self {
            Isa::Portable => "portable",
            Isa::Avx2 => "avx2",
            Isa::Avx512 => "avx512",
            Isa::Avx512Bf16 => "avx512bf16",
        }
    }

    /// The family named `s` (case-insensitive, surrounding space ignored).
    pub fn parse(s: &str) -> Option<Isa> {
        Isa::ALL.into_iter().find(|i| i.name() == s.trim().to_ascii_lowercase())
    }

    /// Whether this CPU can run the family. A family's support implies that of
    /// every family before it, so a cap always leaves a supported one.
    pub fn supported(self) -> bool {
        match self {
            Isa::Portable => true,
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma") && is_x86_feature_detected!("f16c"),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => Isa::Avx2.supported() && is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("avx512bw"),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512Bf16 => Isa::Avx512.supported() && is_x86_feature_detected!("avx512bf16"),
            #[cfg(not(target_arch = "x86_64"))]
            _ => false,
        }
    }

    /// Every family this CPU runs (tests exercise each of them).
    pub fn all_supported() -> Vec<Isa> {
        Isa::ALL.into_iter().filter(|i| i.supported()).collect()
    }

    /// The family used by default: the most specialised supported one (detected
    /// once per process), capped by [`set_cap`] when a program set one.
    pub fn best() -> Isa {
        static DETECTED: OnceLock<Isa> = OnceLock::new();
        let detected = *DETECTED.get_or_init(|| Isa::ALL.into_iter().rev().find(|i| i.supported()).unwrap_or(Isa::Portable));
        capped(detected, cap())
    }
}

/// `detected` capped at `cap` (support is downward closed, so the result runs).
fn capped(detected: Isa, cap: Option<Isa>) -> Isa {
    match cap {
        Some(cap) => cap.min(detected),
        None => detected,
    }
}

/// The vector unit a family's f32 kernels use: what dispatch sites match on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Simd {
    /// Portable Rust.
    Scalar,
    /// 256-bit AVX2 + FMA (+ F16C).
    Avx2,
    /// 512-bit AVX-512 F + BW.
    Avx512,
}

impl Isa {
    /// The vector unit of this family's kernels.
    pub(crate) fn simd(self) -> Simd {
        match self {
            Isa::Portable => Simd::Scalar,
            Isa::Avx2 => Simd::Avx2,
            Isa::Avx512 | Isa::Avx512Bf16 => Simd::Avx512,
        }
    }
}

/// No cap set (a value no [`Isa`] has).
const NO_CAP: u8 = u8::MAX;
static CAP: AtomicU8 = AtomicU8::new(NO_CAP);

/// Cap [`Isa::best`] at `cap` (`None`: no cap), process-wide. Programs set it
/// once at start, from their settings (`RECON_ISA`), before any kernel runs.
pub fn set_cap(cap: Option<Isa>) {
    CAP.store(cap.map_or(NO_CAP, |i| i as u8), Ordering::Release);
}

/// The cap set by [`set_cap`].
pub fn cap() -> Option<Isa> {
    Isa::ALL.get(CAP.load(Ordering::Acquire) as usize).copied()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cap_round_trips_and_bounds_best() {
        assert_eq!(Isa::parse(" AVX512bf16 "), Some(Isa::Avx512Bf16));
        assert_eq!(Isa::parse("avx2"), Some(Isa::Avx2));
        // Support is downward closed: capping never lands on a family the CPU lacks.
        for w in Isa::ALL.windows(2) {
            assert!(!w[1].supported() || w[0].supported(), "{:?} without {:?}", w[1], w[0]);
        }
        assert_eq!(Isa::parse("sse"), None);
        // Capping at the current best changes nothing for tests running beside this one.
        let best = Isa::best();
        set_cap(Some(best));
        assert_eq!(cap(), Some(best));
        assert_eq!(Isa::best(), best);
        set_cap(None);
        assert_eq!(cap(), None);
        assert_eq!(Isa::best(), best);
        assert!(Isa::best().supported());
        // RECON_ISA=avx2 on an AVX-512 machine runs the AVX2 kernels.
        assert_eq!(capped(Isa::Avx512Bf16, Some(Isa::Avx2)), Isa::Avx2);
        assert_eq!(capped(Isa::Avx2, Some(Isa::Avx512)), Isa::Avx2);
        assert_eq!(capped(Isa::Avx512, None), Isa::Avx512);
        for cap in Isa::ALL {
            assert!(capped(best, Some(cap)).supported() && capped(best, Some(cap)) <= cap);
        }
    }
}
