//! Subcommands of the `recon` binary, one file each.
pub mod eval;
pub mod infer;
pub mod train;
pub mod synth;
pub mod weights;
