//! Mesh post-processing.
