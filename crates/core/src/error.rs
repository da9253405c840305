//! Typed errors at the library boundary. The CLI adds context with anyhow.

use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: std::io::Error },

    #[error("{path}: invalid JSON: {source}")]
    Json { path: PathBuf, source: serde_json::Error },

    /// A configuration value is missing or out of range.
    #[error("config {file}: field `{field}`: {msg}")]
    Config { file: String, field: String, msg: String },

    /// A tensor required by the architecture is absent from the checkpoint.
    #[error("weights {file}: missing tensor `{name}` (expected shape {expected:?})")]
    MissingTensor { file: String, name: String, expected: Vec<usize> },

    /// A checkpoint tensor does not match the shape the config implies.
    #[error("weights {file}: tensor `{name}` has shape {found:?}, expected {expected:?}")]
    ShapeMismatch { file: String, name: String, found: Vec<usize>, expected: Vec<usize> },

    /// The checkpoint holds tensors the architecture does not use.
    #[error("weights {file}: unexpected tensor(s) {names:?}")]
    UnexpectedTensors { file: String, names: Vec<String> },

    /// User input (images, masks, depth, JSON) is not what was expected.
    #[error("{file}: {msg}")]
    Input { file: String, msg: String },

    /// An input claims a size beyond a stated bound; raised before anything
    /// of that size is allocated.
    #[error("{0}")]
    TooLarge(Box<SizeBound>),

    #[error(transparent)]
    Candle(#[from] candle_core::Error),

    #[error("{0}")]
    Msg(String),
}

/// What [`Error::TooLarge`] reports: the file, the field whose claim was
/// refused, the claimed size and the bound it exceeds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SizeBound {
    pub file: String,
    pub field: String,
    pub claimed: u128,
    pub limit: u128,
    pub unit: &'static str,
    pub why: String,
}

impl std::fmt::Display for SizeBound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let SizeBound { file, field, claimed, limit, unit, why } = self;
        write!(f, "{file}: {field} claims {claimed} {unit}, more than the limit of {limit} ({why})")
    }
}

pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    pub fn msg(m: impl Into<String>) -> Self {
        Error::Msg(m.into())
    }
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }
    pub fn input(file: impl Into<String>, msg: impl Into<String>) -> Self {
        Error::Input { file: file.into(), msg: msg.into() }
    }
    pub fn too_large(
        file: impl Into<String>,
        field: impl Into<String>,
        claimed: u128,
        limit: u128,
        unit: &'static str,
        why: impl Into<String>,
    ) -> Self {
        Error::TooLarge(Box::new(SizeBound { file: file.into(), field: field.into(), claimed, limit, unit, why: why.into() }))
    }
    pub fn config(file: impl Into<String>, field: impl Into<String>, msg: impl Into<String>) -> Self {
        Error::Config { file: file.into(), field: field.into(), msg: msg.into() }
    }
}
