//! Subcommands of the `recon` binary, one file each.
pub mod bench;
pub mod infer;
pub mod weights;
