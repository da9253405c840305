//! The structured-latent VAE: [`encoder`] (training only), the shared sparse
//! transformer [`trunk`], the [`mesh`] decoder with [`flexicubes`] extraction,
//! and the [`gaussian`] decoder.

pub(crate) mod encoder;
pub(crate) mod flexicubes;
pub(crate) mod gaussian;
pub(crate) mod mesh;
pub(crate) mod trunk;
