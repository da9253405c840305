use crate::util::max_abs_diff;
use crate::{Error, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// One compared output of a fixture.
#[derive(Debug, Clone)]
pub struct Check {
    pub output: String,
    pub max_abs: f64,
    pub tol: f64,
    pub pass: bool,
    pub note: Option<String>,
}

impl Check {
    pub fn new(output: impl Into<String>, max_abs: f64, tol: f64) -> Self {
        Check { output: output.into(), max_abs, tol, pass: max_abs <= tol, note: None }
    }
    /// An exact (integer) comparison: `mismatches` counts differing entries.
    pub fn exact(output: impl Into<String>, mismatches: usize) -> Self {
        Check { output: output.into(), max_abs: mismatches as f64, tol: 0.0, pass: mismatches == 0, note: Some("exact".into()) }
    }
    pub fn with_note(mut self, note: impl Into<String>) -> Self {
        self.note = Some(note.into());
        self
    }
}

/// A loaded fixture: config plus every tensor of `data.safetensors` on the CPU.
pub struct Fixture {
    pub dir: PathBuf,
    pub config: serde_json::Value,
    pub tensors: HashMap<String, Tensor>,
}

impl Fixture {
    pub fn load(dir: &Path) -> Result<Self> {
        let cfg_path = dir.join("config.json");
        let config: serde_json::Value = crate::util::json::read_json(&cfg_path)?;
        let data = dir.join("data.safetensors");
        if !data.exists() {
            return Err(Error::input(data.display().to_string(), "fixture data file not found"));
        }
        let tensors = candle_core::safetensors::load(&data, &Device::Cpu)
            .map_err(|e| Error::input(data.display().to_string(), format!("cannot read safetensors: {e}")))?;
        Ok(Fixture { dir: dir.to_path_buf(), config, tensors })
    }

    pub fn name(&self) -> String {
        self.dir.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default()
    }

    /// The config's `module` string (which upstream class produced the data).
    pub fn module(&self) -> &str {
        self.config.get("module").and_then(|v| v.as_str()).unwrap_or("")
    }

    /// A config field by key, e.g. `args` or `flow_model_args`.
    pub fn field(&self, key: &str) -> Result<&serde_json::Value> {
        self.config.get(key).ok_or_else(|| self.config_err(key, "missing"))
    }

    pub fn config_err(&self, field: &str, msg: impl Into<String>) -> Error {
        Error::config(self.dir.join("config.json").display().to_string(), field, msg)
    }

    /// A tensor by its full key (`input.x`, `output.v`, ...).
    pub fn tensor(&self, key: &str) -> Result<&Tensor> {
        self.tensors
            .get(key)
            .ok_or_else(|| Error::input(self.dir.join("data.safetensors").display().to_string(), format!("missing tensor `{key}`")))
    }

    /// The weights (every key without an `input.`/`output.`/`intermediate.`/`time.` prefix),
    /// with an optional extra prefix stripped (e.g. `hub.`).
    pub fn weights(&self) -> HashMap<String, Tensor> {
        self.tensors
            .iter()
            .filter(|(k, _)| !["input.", "output.", "intermediate.", "time."].iter().any(|p| k.starts_with(p)))
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect()
    }

    /// A VarBuilder over the fixture's weights (f32, CPU).
    pub fn var_builder(&self) -> VarBuilder<'static> {
        VarBuilder::from_tensors(self.weights(), DType::F32, &Device::Cpu)
    }

    /// The suggested absolute tolerance: the first number after "abs" in
    /// `observed_tolerance.suggested_port_tolerance`, else `default`.
    pub fn abs_tolerance(&self, default: f64) -> f64 {
        let s =
            self.config.get("observed_tolerance").and_then(|t| t.get("suggested_port_tolerance")).and_then(|v| v.as_str()).unwrap_or("");
        parse_abs_tol(s).unwrap_or(default)
    }

    /// Compare `got` with `output.*`/`intermediate.*` tensor `key` at tolerance `tol`.
    pub fn check(&self, key: &str, got: &Tensor, tol: f64) -> Result<Check> {
        let want = self.tensor(key)?;
        Ok(Check::new(key, max_abs_diff(got, want)?, tol))
    }
}

fn parse_abs_tol(s: &str) -> Option<f64> {
    let idx = s.find("abs")?;
    s[idx + 3..].split_whitespace().next()?.trim_end_matches([';', ',']).parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn parses_tolerances() {
        assert_eq!(parse_abs_tol("abs 1e-4 for model outputs"), Some(1e-4));
        assert_eq!(parse_abs_tol("vertices abs 1e-5; faces exact"), Some(1e-5));
        assert_eq!(parse_abs_tol("abs 1e-4 / rel 1e-4 on logits"), Some(1e-4));
        assert_eq!(parse_abs_tol("none"), None);
    }
}
