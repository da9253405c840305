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
//!
//! # Example
//!
//! Reconstruct one object of the shipped YCB-Video sample frame with the
//! shipped recgen-nano model ([`prelude`] holds every name used here):
//!
//! ```
//! use recon_core::prelude::*;
//!
//! # fn main() -> recon_core::Result<()> {
//! let repo = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."));
//! // The trained default; `ModelSource::Default` finds the same model from a
//! // checkout's root (or the copy compiled in) without naming a folder.
//! let model = repo.join("models/recgen-nano");
//! let source = ModelSource::Dir { dir: model.clone(), config: Some(model.join("recgen-nano.json")) };
//! let engine = Engine::load(&source, &LoadOptions::default())?;
//!
//! // Colour, depth (found beside it: `000001-depth.png`) and intrinsics (`000001-meta.mat`).
//! let frame = RgbdFrame::open(&repo.join("data/sample/000001-color.png"), &FrameOptions::default())?;
//! // Instance 8 of the label map: the gelatin box.
//! let labels = InstanceMap::open(&repo.join("data/sample/000001-label.png"))?;
//! let (objects, skipped) = labels.objects(Some(&[8]));
//! assert!(skipped.is_empty());
//!
//! let result: FrameResult = engine.reconstruct(&frame, objects, &InferOptions::default().settings()?)?;
//! let box_8: &ObjectResult = &result.objects[0];
//! // Pose: canonical object frame → camera frame, metres; the box is about 0.7 m away.
//! let [x, y, z] = box_8.pose_camera.translation;
//! assert!(z > 0.3 && z < 2.0, "{x} {y} {z}");
//! let mesh = box_8.mesh_camera.as_ref().expect("a mesh is decoded by default");
//! assert!(!mesh.is_empty());
//! // write_outputs(&result, "out".as_ref())? writes the GLB, PLY and pose files.
//! # Ok(())
//! # }
//! ```

// Clippy lints allowed crate-wide, each for a reason:
// - needless_range_loop: index loops over 3×3 matrices and channel triples read as the maths does;
// - neg_cmp_op_on_partial_ord: `!(x > 0.0)` deliberately rejects NaN along with out-of-range values;
// - too_many_arguments: kernel and fitting entry points take their shapes and buffers explicitly;
// - type_complexity: tuples returned by internal helpers, used once each.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord, clippy::too_many_arguments, clippy::type_complexity)]
#![warn(missing_docs)]

pub mod dataset;
pub mod engine;
pub mod error;
pub mod export;
pub mod gaussians;
pub mod geometry;
pub mod math;
pub mod mesh;
pub mod model;
pub mod render;
pub mod rng;
pub mod sensor;
pub mod settings;
pub mod spatial;
pub mod util;
pub mod weights;

pub use engine::Engine;
pub use error::{Error, Result, SizeBound};

/// recon's version (every crate of the workspace shares it): what outputs record as
/// `recon_version`.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// The cargo features this build of recon-core has (`recon --version` lists them).
pub const FEATURES: &[&str] = &[
    #[cfg(feature = "hub")]
    "hub",
    #[cfg(feature = "clap")]
    "clap",
];

/// What a program needs to reconstruct objects from a frame: `use recon_core::prelude::*;`.
pub mod prelude {
    pub use crate::dataset::{FrameOptions, InstanceMap, Intrinsics, MaskSkip, ObjectMask, RgbdFrame, SkipReason};
    pub use crate::engine::{
        write_outputs, Dtype, Engine, FrameResult, InferOptions, LoadOptions, ModelSource, ObjectResult, WrittenObject,
    };
    pub use crate::error::{Error, Result};
    pub use crate::gaussians::Gaussians;
    pub use crate::geometry::Pose;
    pub use crate::math::Similarity;
    pub use crate::mesh::Mesh;
}
