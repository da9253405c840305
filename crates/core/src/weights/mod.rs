//! Checkpoints: loading (memory-mapped safetensors, torch `.pt`), validation
//! against the tensor list a config implies, manifests of the upstream files
//! (pins, tensor lists, the release's own configs), the Hugging Face cache,
//! download, and labelled random initialisation.

pub mod fetch;
pub mod hf_cache;
pub mod init;
pub(crate) mod load;
pub(crate) mod manifest;
pub(crate) mod pt;
pub(crate) mod record;
pub mod registry;
pub(crate) mod validate;
pub(crate) mod verify;

pub use self::fetch::fetch;
pub use self::init::{is_random_init, write_random_init, write_random_init_as, InitFormat};
pub use self::load::{mmaped_safetensors_vb, read_safetensors_header};
pub use self::manifest::{
    release_architecture, resolve_manifest, resolve_module_files, Download, Manifest, ManifestFile, ReadFile, WeightFiles,
};
pub use self::record::RandomInit;
pub use self::registry::{build_ss_encoder, expected_tensors, ModuleConfig};
pub use self::verify::{print_table, verify_dir};
pub use load::Checkpoint;
pub use pt::{write_pt, PtFile, PtTensorInfo};
pub use record::{record_with, TensorSpec};
pub use validate::{compare, load_validated, validate_checkpoint, ValidationReport};
