//! The structured-latent VAE: [`encoder`] (training only), the shared sparse
//! transformer `trunk`, the [`mesh`] decoder with [`flexicubes`] extraction,
//! and the [`gaussian`] decoder.

pub mod encoder;
pub mod flexicubes;
pub mod gaussian;
pub mod mesh;
pub(crate) mod trunk;
