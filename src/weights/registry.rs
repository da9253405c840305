//! Module configs by name: `{"name": ClassName, "args": {...}}` files (the
//! TRELLIS `ckpts/<name>.json` format) map to a builder that constructs the
//! module on any VarBuilder. Building on a [`Recorder`](super::record::Recorder)
//! yields the expected tensor list; on [`RandomInit`](super::record::RandomInit)
//! random weights. New modules plug in by adding a match arm to [`build`].

use super::record::{RandomInit, Recorder, TensorSpec};
use crate::model::dinov2::{Dinov2, Dinov2Config};
use crate::{Error, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use std::collections::BTreeMap;
use std::path::Path;

/// A module config file: upstream class name plus constructor args.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ModuleConfig {
    pub name: String,
    #[serde(default)]
    pub args: serde_json::Value,
}

impl ModuleConfig {
    pub fn read(path: &Path) -> Result<Self> {
        crate::config::read_json(path)
    }
}

/// Names accepted by [`build`].
pub const KNOWN_MODULES: &[&str] = &["DinoVisionTransformer"];

/// Build module `cfg.name` from `cfg.args` on `vb` (the module is dropped;
/// the point is what the builder requests from `vb`).
pub fn build(cfg: &ModuleConfig, vb: VarBuilder, file: &str) -> Result<()> {
    match cfg.name.as_str() {
        "DinoVisionTransformer" | "Dinov2" => {
            let c: Dinov2Config = crate::config::from_value(&cfg.args, file)?;
            c.validate(file)?;
            Dinov2::new(&c, vb)?;
            Ok(())
        }
        other => Err(Error::config(
            file,
            "name",
            format!("module `{other}` is not available in this build (known: {KNOWN_MODULES:?})"),
        )),
    }
}

/// The expected (name, shape) list of a module, sorted by name.
pub fn expected_tensors(cfg: &ModuleConfig, file: &str) -> Result<Vec<TensorSpec>> {
    let r = Recorder::new();
    build(cfg, r.var_builder(DType::F32, &Device::Cpu), file)?;
    Ok(r.specs())
}

/// Deterministic random weights for a module (f32).
pub fn random_weights(cfg: &ModuleConfig, seed: u64, file: &str) -> Result<BTreeMap<String, Tensor>> {
    let init = RandomInit::new(seed);
    build(cfg, init.var_builder(&Device::Cpu), file)?;
    Ok(init.tensors())
}
