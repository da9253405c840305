//! Subcommands of the `recon` binary, one file each.
pub mod audit;
pub mod infer;
pub mod weights;
