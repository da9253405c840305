//! Subcommands of the `recon` binary, one file each.
pub mod audit;
pub mod bench;
pub mod eval;
pub mod infer;
pub mod meta;
pub mod model_args;
pub mod scene;
pub mod serve;
pub mod synth;
pub mod train;
pub mod weights;
