//! Reading what recon is given: RGB-D frames and their intrinsics, masks,
//! images (with the DINOv2 preprocessing), MAT v5 (YCB-Video meta), meshes
//! (PLY, and OBJ and GLB for user assets), and BOP / YCB-Video datasets.

pub mod bop;
pub mod frame;
pub(crate) mod glb;
pub mod image;
pub mod masks;
pub mod matv5;
pub(crate) mod mesh_file;
pub(crate) mod obj;
pub mod ply;
pub(crate) mod visibility;
pub use self::bop::{load_dataset, load_ycbv, Dataset, Layout};
pub use self::frame::{FrameOptions, Intrinsics, RgbdFrame};
pub use self::glb::parse_glb;
pub use self::image::{pointmap_to_tensor, square_crop_box, trellis_preprocess_rgba, CropBox, DINO_SIZE};
pub use self::masks::{
    check_object, load_binary_masks, load_masks, validate_objects, InstanceMap, MaskOptions, MaskSkip, ObjectMask, Run, SkipReason,
};
pub use self::matv5::MatFile;
pub use self::mesh_file::{parse_mesh, read_mesh_file, MeshFormat};
pub use self::obj::parse_obj;
pub use self::ply::read_ply;
pub use self::visibility::{surface_patches, visible_fraction};
