//! Stage 1: the crop's DINOv2 features plus mask and point-map embeddings
//! condition a rectified-flow transformer that jointly denoises the
//! sparse-structure latent and one pose token per view; the SS VAE decodes
//! the latent to 64³ occupancy.

pub mod dinov2;
pub mod embedders;
pub mod ss_flow;
pub mod ss_vae;
