//! Stage 2: a sparse transformer generates structured latents on the active
//! voxels, conditioned on the pose through extra cross-attention tokens; the
//! SLat VAE's decoders turn them into a mesh (FlexiCubes) and 3D Gaussians.

pub mod slat_flow;
pub mod slat_vae;
