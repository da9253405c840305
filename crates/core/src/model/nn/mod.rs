//! Shared layers: [`common`] (linear, norms, attention, feed-forward, adaLN
//! blocks), [`fast`] (the packed-weight inference kernels behind them),
//! `dense3d` (3D convolutions of the SS VAE) and `gradcheck` (directional
//! gradient checks for training).

pub mod common;
pub(crate) mod dense3d;
pub mod fast;
#[doc(hidden)]
pub mod gradcheck;
