//! Subcommands of the `recon` binary, one file each.
pub mod infer;
pub mod scene;
pub mod weights;
