//! The CPU ray caster that `recon synth`, the `recon infer` preview and the
//! audit share (`raycast`), the preview picture (`preview`), and the Gaussian
//! splatting rasteriser (`splat`), and texture baking from the input views (`bake`).

pub mod bake;
pub(crate) mod preview;
pub(crate) mod raycast;
pub(crate) mod splat;
pub use self::bake::{bake_texture, texture_mesh, BakeOptions, BakeReport, BakeView};
pub use self::preview::{overlay_rgb, save_overlay, save_preview};
pub use self::raycast::*;
pub use self::splat::{render_gaussians, SplatImage, SplatOptions, MAX_SPLAT_SIDE};
