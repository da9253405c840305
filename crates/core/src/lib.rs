//! recon-core: RGB-D frames + object masks → posed meshes and 3D Gaussians.
//!
//! The engine without its applications. Modules follow the data's path through
//! the system, each layer importing only the layers above it in this list
//! (`docs/ARCHITECTURE.md`; checked by `tests/layers.rs`):
//!
//! - ground floor: [`error`], [`math`], [`rng`], [`util`], [`spatial`],
//!   [`mesh`], [`gaussians`];
//! - data: [`dataset`] (frames, masks, BOP/YCB-Video, PLY, MAT v5),
//!   [`sensor`] (depth sensor models), [`render`] (CPU ray caster),
//!   [`export`] (GLB, PLY, OBJ, splat PLY);
//! - [`geometry`]: point maps, pose encodings, voxelisation;
//! - [`model`]: the networks (stage 1, stage 2, sampler) and [`weights`];
//! - [`engine`]: both stages on a frame, pose fitting, outputs.
//!
//! The applications are crates of their own on top of this one: `recon-synth`,
//! `recon-eval`, `recon-sim`, `recon-audit`, `recon-train`, and the `recon` CLI.
//!
//! Features: `hub` (default) downloads weights from the Hugging Face hub;
//! `clap` derives `clap::ValueEnum` on the option enums for command lines.

// Clippy lints allowed crate-wide, each for a reason:
// - needless_range_loop: index loops over 3×3 matrices and channel triples read as the maths does;
// - neg_cmp_op_on_partial_ord: `!(x > 0.0)` deliberately rejects NaN along with out-of-range values;
// - too_many_arguments: kernel and fitting entry points take their shapes and buffers explicitly;
// - type_complexity: tuples returned by internal helpers, used once each.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord, clippy::too_many_arguments, clippy::type_complexity)]
#![warn(missing_docs)]

pub mod dataset;
// documented after the options/keys refactor lands
#[allow(missing_docs)]
pub mod engine;
pub mod error;
pub mod export;
pub mod gaussians;
pub mod geometry;
pub mod math;
pub mod mesh;
// documented after the options/keys refactor lands
#[allow(missing_docs)]
pub mod model;
pub mod render;
pub mod rng;
pub mod sensor;
pub mod spatial;
// documented after the options/keys refactor lands
#[allow(missing_docs)]
pub mod util;
// documented after the options/keys refactor lands
#[allow(missing_docs)]
pub mod weights;

pub use error::{Error, Result, SizeBound};
