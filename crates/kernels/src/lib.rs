//! Hand-written CPU compute kernels used by recon's model stages.
//!
//! Kernels work on plain row-major slices so they can be tested against
//! straightforward reference loops; the candle wrappers live in the main crate.
//! Fast paths are picked at run time by CPU feature detection ([`isa::Isa`]),
//! each with a portable fallback.

// Clippy lints allowed crate-wide, each for a reason:
// - needless_range_loop: register-tile loops index several accumulators with one counter;
// - too_many_arguments: kernels take their shapes, strides and buffers explicitly.
#![allow(clippy::needless_range_loop, clippy::too_many_arguments)]
#![warn(missing_docs)]

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
