//! The sparse-structure VAE: [`decoder`] (16³ latent → 64³ occupancy logits)
//! and [`encoder`] (occupancy → latent; only training uses it).

pub mod decoder;
pub mod encoder;
