//! The networks, in the order data passes through them.
//!
//! - [`nn`]: shared layers (linear, norms, attention, feed-forward, dense 3D
//!   convolutions) and the fast inference path;
//! - [`sparse`]: sparse voxel tensors, sparse convolution and attention;
//! - [`sampler`]: the rectified-flow Euler sampler with classifier-free
//!   guidance, generic over [`sampler::VelocityModel`];
//! - [`stage1`]: image conditioning (DINOv2 + point-map/mask embedders), the
//!   sparse-structure flow with pose tokens, and the SS VAE;
//! - [`stage2`]: the structured-latent flow and the SLat VAE (encoder, mesh
//!   and Gaussian decoders, FlexiCubes);
//! - [`config`]: the architecture file that names every module.

pub mod config;
pub mod nn;
pub mod sampler;
pub mod sparse;
pub mod stage1;
pub mod stage2;
