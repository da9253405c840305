//! Geometry: object poses (rotation encodings, normalisation).

pub mod pose;
