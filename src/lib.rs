//! recon: RGB-D frames + object masks → posed meshes and 3D Gaussians.
//!
//! This crate is the `recon` command line and its tools, and a facade over the
//! workspace's crates so that one dependency reaches all of them:
//!
//! - the engine, [`recon_core`]: [`error`], [`math`], [`rng`], [`util`],
//!   [`settings`], [`spatial`], [`mesh`], [`gaussians`], [`dataset`], [`sensor`], [`render`],
//!   [`export`], [`geometry`], [`model`], [`weights`], [`engine`];
//! - the applications: [`synth`] (`recon-synth`), [`eval`] (`recon-eval`),
//!   [`sim`] (`recon-sim`), [`audit`] (`recon-audit`), [`train`] (`recon-train`);
//! - [`tools`]: bench, conformance, fuzz targets.
//!
//! `use recon::prelude::*;` brings in what reconstructing a frame needs
//! (the engine, its options, frames, masks, results, [`Error`] and [`Result`]).
//!
//! A program that only reconstructs objects depends on `recon-core` alone
//! (with `default-features = false` it leaves out the hub download too).

#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord, clippy::too_many_arguments, clippy::type_complexity)]

pub use recon_audit as audit;
pub use recon_core::prelude;
pub use recon_core::{
    dataset, engine, error, export, gaussians, geometry, math, mesh, model, render, rng, sensor, settings, spatial, util, weights,
};
pub use recon_core::{Error, Result, SizeBound, FEATURES, VERSION};
pub use recon_eval as eval;
pub use recon_sim as sim;
pub use recon_synth as synth;
pub use recon_train as train;

pub mod tools;
