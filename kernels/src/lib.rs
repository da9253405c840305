//! Hand-written CPU compute kernels used by recon's model stages.
//!
//! Kernels work on plain row-major slices so they can be tested against
//! straightforward reference loops; the candle wrappers live in the main crate.
//! Fast paths are picked at run time by CPU feature detection ([`isa::Isa`]),
//! each with a portable fallback.

pub mod attention;
pub mod buf;
pub mod conv3d;
pub mod gemm;
pub mod isa;
pub mod peak;
pub mod sparse;
#[cfg(test)]
mod test_rng;
pub mod vecmath;
