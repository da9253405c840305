//! Model stages. Stage 1: image conditioning (DINOv2 + point-map/mask
//! embedders), sparse-structure flow with pose tokens, sampler, SS decoder.
//! Stage 2: structured-latent flow.

pub mod common;
pub mod slat_flow;
