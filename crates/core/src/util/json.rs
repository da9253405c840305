//! Reading JSON configuration files with errors that name the file.

use crate::{Error, Result};
use serde::de::DeserializeOwned;
use std::path::Path;

/// Read and parse a JSON file; errors name the file and what was wrong.
pub fn read_json<T: DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&text).map_err(|e| Error::Json { path: path.to_path_buf(), source: e })
}

/// Parse a JSON value into a typed config; errors name `file` and the field
/// (its path in `v`) that did not parse.
pub fn from_value<T: DeserializeOwned>(v: &serde_json::Value, file: &str) -> Result<T> {
    serde_path_to_error::deserialize(v.clone()).map_err(|e| {
        let path = e.path().to_string();
        let field = if path == "." { "args".to_string() } else { path };
        Error::config(file, field, e.into_inner().to_string())
    })
}
