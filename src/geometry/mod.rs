//! Geometry: object poses (rotation encodings, normalisation).

pub mod pose;
pub mod pointmap;
pub mod camera_pose;
