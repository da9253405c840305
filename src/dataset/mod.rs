//! Reading what recon is given: RGB-D frames and their intrinsics, masks,
//! images (with the DINOv2 preprocessing), MAT v5 (YCB-Video meta), PLY, and
//! BOP / YCB-Video datasets.

pub(crate) mod bop;
pub(crate) mod frame;
pub(crate) mod image;
pub(crate) mod masks;
pub(crate) mod matv5;
pub(crate) mod ply;
pub(crate) mod visibility;
pub use self::bop::{load_dataset, load_ycbv};
pub use self::frame::{FrameOptions, Intrinsics, RgbdFrame};
pub use self::image::{pointmap_to_tensor, square_crop_box, trellis_preprocess_rgba, CropBox, DINO_SIZE};
pub use self::masks::{load_binary_masks, validate_objects, InstanceMap, MaskOptions, MaskSkip, ObjectMask, SkipReason};
pub use self::matv5::MatFile;
pub use self::ply::read_ply;
pub use self::visibility::{surface_patches, visible_fraction};

/// The shared real-data folder (`realdata/` beside the repository, as on the
/// development machines), for tests and examples that use the real frames:
/// `RECON_REALDATA` if set, else `<repo>/../shared/realdata`, else
/// `/work/shared/realdata`. None when none of them exists.
pub fn shared_realdata() -> Option<std::path::PathBuf> {
    use std::path::PathBuf;
    let candidates = [
        std::env::var_os("RECON_REALDATA").map(PathBuf::from),
        Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/realdata")),
        Some(PathBuf::from("/work/shared/realdata")),
    ];
    candidates.into_iter().flatten().find(|p| p.is_dir())
}

/// One dataset folder of [`shared_realdata`] (e.g. `ycbv_video_oprb`), when present.
pub fn shared_dataset(name: &str) -> Option<std::path::PathBuf> {
    shared_realdata().map(|p| p.join(name)).filter(|p| p.is_dir())
}
