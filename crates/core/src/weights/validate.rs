//! Checking a checkpoint against the tensor list a config implies, before
//! any model is built, so a wrong file fails with the tensor's name and both
//! shapes instead of deep inside a forward pass.

use crate::weights::load::Checkpoint;
use crate::weights::record::TensorSpec;
use crate::{Error, Result};
use std::collections::{BTreeMap, BTreeSet};

/// Everything that differs between a checkpoint and the expected list.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ValidationReport {
    /// Expected tensors the checkpoint lacks.
    pub missing: Vec<TensorSpec>,
    /// (name, found, expected)
    pub mismatched: Vec<(String, Vec<usize>, Vec<usize>)>,
    /// Checkpoint tensors not in the expected list (left empty when extras are ignored).
    pub unexpected: Vec<String>,
    /// Expected tensors found with the expected shape.
    pub matched: usize,
}

impl ValidationReport {
    /// True when nothing is missing, mis-shaped or unexpected.
    pub fn is_ok(&self) -> bool {
        self.missing.is_empty() && self.mismatched.is_empty() && self.unexpected.is_empty()
    }

    /// The first problem as a typed error (missing, then shape, then unexpected).
    pub fn into_result(self, file: &str) -> Result<()> {
        if let Some(m) = self.missing.into_iter().next() {
            return Err(Error::MissingTensor { file: file.into(), name: m.name, expected: m.shape });
        }
        if let Some((name, found, expected)) = self.mismatched.into_iter().next() {
            return Err(Error::ShapeMismatch { file: file.into(), name, found, expected });
        }
        if !self.unexpected.is_empty() {
            return Err(Error::UnexpectedTensors { file: file.into(), names: self.unexpected });
        }
        Ok(())
    }
}

/// Compare found shapes with the expected list. `ignore_unexpected` mirrors
/// torch's `strict=False` for extra tensors only (missing ones still fail).
pub fn compare(expected: &[TensorSpec], found: &BTreeMap<String, Vec<usize>>, ignore_unexpected: bool) -> ValidationReport {
    let mut r = ValidationReport::default();
    let want: BTreeSet<&str> = expected.iter().map(|s| s.name.as_str()).collect();
    for spec in expected {
        match found.get(&spec.name) {
            None => r.missing.push(spec.clone()),
            Some(shape) if shape != &spec.shape => r.mismatched.push((spec.name.clone(), shape.clone(), spec.shape.clone())),
            Some(_) => r.matched += 1,
        }
    }
    if !ignore_unexpected {
        r.unexpected = found.keys().filter(|k| !want.contains(k.as_str())).cloned().collect();
    }
    r
}

/// Validate an opened checkpoint; `Ok(report)` only when it matches.
pub fn validate_checkpoint(ckpt: &Checkpoint, expected: &[TensorSpec], ignore_unexpected: bool) -> Result<ValidationReport> {
    let found: BTreeMap<String, Vec<usize>> = ckpt.tensors().into_iter().map(|(k, v)| (k, v.shape)).collect();
    let r = compare(expected, &found, ignore_unexpected);
    r.clone().into_result(&ckpt.path.display().to_string())?;
    Ok(r)
}

/// Open `path`, validate it against `expected`, and return a VarBuilder
/// producing `dtype` tensors: the one-call path for loading real weights.
pub fn load_validated(
    path: &std::path::Path,
    expected: &[TensorSpec],
    ignore_unexpected: bool,
    dtype: candle_core::DType,
    dev: &candle_core::Device,
) -> Result<candle_nn::VarBuilder<'static>> {
    let ck = Checkpoint::open(path, None)?;
    validate_checkpoint(&ck, expected, ignore_unexpected)?;
    Ok(ck.into_var_builder(dtype, dev))
}
