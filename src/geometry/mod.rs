//! Geometry: object poses (rotation encodings, normalisation), point-map ↔ mesh
//! alignment, and mesh voxelisation.

pub mod pose;
pub mod pointmap;
pub mod camera_pose;
pub mod alignment;
pub mod refine;
pub mod voxelize;
