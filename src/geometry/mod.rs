//! Geometry: object poses (rotation encodings, normalisation) and mesh voxelisation.

pub mod pose;
pub mod pointmap;
pub mod camera_pose;
pub mod voxelize;
