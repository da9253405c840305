//! Geometry: object poses (rotation encodings, normalisation), point maps and
//! their crops, and mesh voxelisation.

pub mod camera_pose;
pub mod pointmap;
pub mod pose;
pub mod voxelize;
