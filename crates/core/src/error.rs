//! Typed errors at the library boundary. The CLI adds context with anyhow.

use std::path::PathBuf;

/// Every error the recon crates return.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// Reading or writing a file failed.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's error.
        source: std::io::Error,
    },

    /// A JSON file does not parse or does not match its schema.
    #[error("{path}: invalid JSON: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The parser's error.
        source: serde_json::Error,
    },

    /// A configuration value is missing or out of range.
    #[error("config {file}: field `{field}`: {msg}")]
    Config {
        /// The configuration file (or the command, for flags).
        file: String,
        /// The field (or flag).
        field: String,
        /// What is wrong.
        msg: String,
    },

    /// A tensor required by the architecture is absent from the checkpoint.
    #[error("weights {file}: missing tensor `{name}` (expected shape {expected:?})")]
    MissingTensor {
        /// The checkpoint file.
        file: String,
        /// The tensor's name.
        name: String,
        /// The shape the architecture expects.
        expected: Vec<usize>,
    },

    /// A checkpoint tensor does not match the shape the config implies.
    #[error("weights {file}: tensor `{name}` has shape {found:?}, expected {expected:?}")]
    ShapeMismatch {
        /// The checkpoint file.
        file: String,
        /// The tensor's name.
        name: String,
        /// The shape in the checkpoint.
        found: Vec<usize>,
        /// The shape the architecture expects.
        expected: Vec<usize>,
    },

    /// The checkpoint holds tensors the architecture does not use.
    #[error("weights {file}: unexpected tensor(s) {names:?}")]
    UnexpectedTensors {
        /// The checkpoint file.
        file: String,
        /// The unused tensors' names.
        names: Vec<String>,
    },

    /// A file's SHA-256 differs from the one its weights manifest pins.
    #[error(
        "weights {file}: SHA-256 is {actual}, but the manifest pins {expected} (a damaged, partial or different file: \
         fetch it again; for another revision, `recon weights manifest NAME --pin CACHE --out FILE` writes a manifest of what is there)"
    )]
    ChecksumMismatch {
        /// The file.
        file: String,
        /// The pinned SHA-256 (hex).
        expected: String,
        /// The file's SHA-256 (hex).
        actual: String,
    },

    /// User input (images, masks, depth, JSON) is not what was expected.
    #[error("{file}: {msg}")]
    Input {
        /// The input file (or what names the input).
        file: String,
        /// What is wrong.
        msg: String,
    },

    /// An input claims a size beyond a stated bound; raised before anything
    /// of that size is allocated.
    #[error("{0}")]
    TooLarge(Box<SizeBound>),

    /// A tensor operation failed.
    #[error(transparent)]
    Candle(#[from] candle_core::Error),

    /// Anything else, in words.
    #[error("{0}")]
    Msg(String),
}

/// What [`Error::TooLarge`] reports: the file, the field whose claim was
/// refused, the claimed size and the bound it exceeds.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SizeBound {
    /// The input file.
    pub file: String,
    /// The field whose claim was refused.
    pub field: String,
    /// The size the input claims.
    pub claimed: u128,
    /// The largest size accepted.
    pub limit: u128,
    /// Unit of both sizes (`bytes`, `elements`, ...).
    pub unit: &'static str,
    /// Why the bound is what it is.
    pub why: String,
}

impl std::fmt::Display for SizeBound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let SizeBound { file, field, claimed, limit, unit, why } = self;
        write!(f, "{file}: {field} claims {claimed} {unit}, more than the limit of {limit} ({why})")
    }
}

/// `Result` with recon's [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// An [`Error::Msg`].
    pub fn msg(m: impl Into<String>) -> Self {
        Error::Msg(m.into())
    }
    /// An [`Error::Io`] for `path`.
    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        Error::Io { path: path.into(), source }
    }
    /// An [`Error::Input`] for `file`.
    pub fn input(file: impl Into<String>, msg: impl Into<String>) -> Self {
        Error::Input { file: file.into(), msg: msg.into() }
    }
    /// An [`Error::TooLarge`]: `field` of `file` claims `claimed` `unit`, over `limit`, because `why`.
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
    /// An [`Error::Config`] for `field` of `file`.
    pub fn config(file: impl Into<String>, field: impl Into<String>, msg: impl Into<String>) -> Self {
        Error::Config { file: file.into(), field: field.into(), msg: msg.into() }
    }
}
