//! Hand-written CPU compute kernels used by recon's model stages.
//!
//! Kernels work on plain row-major `f32` slices so they can be tested against
//! straightforward reference loops; the candle wrappers live in the main crate.

pub mod sparse;
