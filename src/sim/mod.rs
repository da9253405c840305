//! sim: posed meshes → a physically plausible, simulator-ready scene.
//!
//! 1. [`scene_file`]: the versioned scene description (objects, camera,
//!    support plane), read from JSON or built from `recon infer` output.
//! 2. [`plane`]: the support plane from the observed depth (RANSAC + least
//!    squares) and the world frame (gravity −z, plane z = 0).
//! 3. [`physics`] + [`materials`]: mesh checks, solid or shell, mass and
//!    inertia from the mesh and a material table.
//! 4. [`collision`]: convex decomposition, single hull or primitive fits.
//! 5. [`settle`]: rapier3d settling with bounded depenetration.
//! 6. [`variations`]: many re-arranged, settled scenes from one, under
//!    spatial predicates, with distractors and object variants.
//!
//! The simulator formats ([`urdf`], [`mjcf`], [`usd`]) live here; the asset
//! formats (GLB, PLY, OBJ) in `crate::export`. [`write_outputs`] writes the
//! whole folder atomically.

pub mod collision;
pub mod inputs;
pub mod materials;
pub mod mjcf;
pub mod physics;
pub mod plane;
mod scene;
pub mod scene_file;
pub mod settle;
pub mod urdf;
pub mod usd;
pub mod variations;
mod write;

pub use scene::{build_scene, hull_file, principal, ObjectSummary, PlaneMaterial, SceneOptions, SimObject, SimScene, Timings};
pub use variations::{run_variations, VariationOptions, VariationSpec};
pub use write::{write_outputs, write_outputs_with, Written, MARKER};
