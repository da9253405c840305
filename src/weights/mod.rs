//! Checkpoints: loading (memory-mapped safetensors, torch `.pt`), validation
//! against the tensor list a config implies, manifests of the upstream files,
//! download, and labelled random initialisation.

pub mod fetch;
pub mod init;
pub mod load;
pub mod manifest;
pub mod record;
pub mod registry;
pub mod validate;
pub mod verify;

pub use load::Checkpoint;
pub use record::{record_with, TensorSpec};
pub use validate::{compare, load_validated, validate_checkpoint, ValidationReport};
