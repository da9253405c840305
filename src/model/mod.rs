//! Model stages. Stage 1: image conditioning (DINOv2 + point-map/mask
//! embedders), sparse-structure flow with pose tokens, sampler, SS decoder
//! (and the SS VAE encoder, which only training uses).
//! Stage 2: structured-latent flow (and the SLat encoder, which only training uses).

pub mod common;
pub mod fast;
pub mod config;
pub mod embedders;
pub mod sampler;
pub mod ss_flow;
pub mod dense3d;
pub mod ss_decoder;
pub mod ss_encoder;
pub mod slat_flow;
pub mod slat_encoder;
pub mod dinov2;
