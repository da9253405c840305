//! sim: posed meshes → a physically plausible, simulator-ready scene.
//!
//! 1. `scene_file`: the versioned scene description (objects, camera,
//!    support plane), read from JSON or built from `recon infer` output.
//! 2. `plane`: the support plane from the observed depth (RANSAC + least
//!    squares) and the world frame (gravity −z, plane z = 0).
//! 3. `physics` + `materials`: mesh checks, solid or shell, mass and
//!    inertia from the mesh and a material table.
//! 4. `collision`: convex decomposition, single hull or primitive fits.
//! 5. `settle`: rapier3d settling with bounded depenetration.
//! 6. `variations`: many re-arranged, settled scenes from one, under
//!    spatial predicates, with distractors and object variants.
//!
//! The simulator formats (`urdf`, `mjcf`, `usd`) live here; the asset
//! formats (GLB, PLY, OBJ) in `recon_core::export`. [`write_outputs`] writes the
//! whole folder atomically.

// Clippy lints allowed crate-wide, for the reasons given in recon-core's lib.rs.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord, clippy::too_many_arguments, clippy::type_complexity)]
#![warn(missing_docs)]

pub(crate) mod collision;
pub(crate) mod inputs;
pub(crate) mod materials;
pub(crate) mod mjcf;
mod options;
pub(crate) mod physics;
mod scene;
pub(crate) mod scene_file;
pub(crate) mod settle;
pub(crate) mod urdf;
pub(crate) mod usd;
pub(crate) mod variations;
mod write;

pub use self::collision::{CollisionMethod, VhacdOptions};
pub use self::inputs::{infer_frame, scene_from_bop, scene_from_infer_output, scene_from_meshes, support_plane_from_frame};
pub use self::materials::MaterialTable;
pub use self::options::SceneOptions;
pub use self::scene_file::SceneFile;
pub use self::settle::{body_distance, Body};
pub use recon_core::geometry::PlaneFitOptions;
pub use scene::{build_scene, hull_file, principal, ObjectSummary, PlaneMaterial, SceneSettings, SimObject, SimScene, Timings};
pub use variations::{
    run_variations, Asset, AssetLibrary, AssetPhysics, AssetSpec, Category, DirFrame, Manifest as VariationsManifest, Predicate,
    RunSummary, UpAxis, VariationOptions, VariationSpec, MANIFEST as VARIATIONS_MANIFEST,
};
pub use write::{write_outputs, write_outputs_with, Written, MARKER};
