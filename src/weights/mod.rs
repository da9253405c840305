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

use std::collections::HashMap;
use std::path::PathBuf;

/// Where each module's checkpoint is, for layouts other than
/// `<dir>/<key>.safetensors` (e.g. the upstream files resolved through a
/// weights manifest).
#[derive(Debug, Clone, Default)]
pub struct WeightFiles {
    /// Reported as the weights' origin.
    pub dir: PathBuf,
    /// Module key ([`crate::model::config::RecGenConfig::modules`]) → checkpoint file.
    pub modules: HashMap<String, PathBuf>,
    /// Pose statistics to use instead of the files the architecture names.
    pub ss_stats: Option<PathBuf>,
    pub slat_stats: Option<PathBuf>,
}
