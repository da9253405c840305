//! The CPU ray caster that `recon synth`, the `recon infer` preview and the
//! audit share (`raycast`), and the preview picture (`preview`).

pub(crate) mod preview;
pub(crate) mod raycast;
pub use self::preview::{overlay_rgb, save_overlay, save_preview};
pub use self::raycast::*;
