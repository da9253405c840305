//! `recon weights init`: random-initialised weights for a module config,
//! written as safetensors with metadata `recon.random_init = "true"` so they
//! can never be mistaken for trained weights. With [`InitFormat::Pt`] they are
//! written as `torch.save` writes a state dict (the format of RecGen's released
//! denoisers and torch.hub's DINOv2), for building a fake release; the label is
//! then an extra archive record, [`PT_RANDOM_INIT_RECORD`], that torch ignores.
//!
//! Given an architecture file (`models/recgen-*.json`, recognised by its
//! `ss_flow` section) instead of a module config, every module is written as
//! `<out>/<key>.safetensors` (keys: [`crate::model::config::RecGenConfig::modules`]),
//! with a copy of the architecture file and its pose-stat files, so that
//! `Pipeline::load(<out>/<arch file>, Weights::Dir(<out>), Stages::All, &LoadOptions::default())` runs it.

use crate::model::config::{ModuleArgs, ModuleKey};
use crate::weights::registry::{random_weights, ModuleConfig};
use crate::{Error, Result};
use candle_core::{DType, Tensor};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Safetensors metadata key whose value `"true"` labels random-initialised weights.
pub const RANDOM_INIT_KEY: &str = "recon.random_init";

/// The record a random-initialised torch archive carries beside `archive/data.pkl`
/// (its content is the safetensors metadata as JSON).
pub const PT_RANDOM_INIT_RECORD: &str = "archive/recon_random_init.json";

/// The file format of random-initialised weights.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum InitFormat {
    /// `.safetensors` with the label in its metadata.
    #[default]
    Safetensors,
    /// `.pt`, a torch zip archive of the state dict, as `torch.save` writes it.
    Pt,
}

impl InitFormat {
    fn extension(self) -> &'static str {
        match self {
            Self::Safetensors => "safetensors",
            Self::Pt => "pt",
        }
    }

    fn write(self, tensors: &BTreeMap<String, Tensor>, meta: &BTreeMap<String, String>, path: &Path) -> Result<()> {
        match self {
            Self::Safetensors => write_safetensors(tensors, meta, path),
            Self::Pt => {
                let label = serde_json::to_vec_pretty(meta).map_err(|e| Error::msg(e.to_string()))?;
                crate::weights::pt::write_pt_with_records(tensors, &[(PT_RANDOM_INIT_RECORD, &label)], path)
            }
        }
    }
}

/// Write `<out>/<config stem>.safetensors` and a copy of the config as
/// `<out>/<config stem>.json`. Returns the weights path. For an architecture
/// file see `write_random_architecture` (returns `out`).
pub fn write_random_init(config: &Path, out: &Path, seed: u64) -> Result<PathBuf> {
    write_random_init_as(config, out, seed, InitFormat::Safetensors)
}

/// [`write_random_init`] in `format` (`<stem>.pt` for [`InitFormat::Pt`]).
pub fn write_random_init_as(config: &Path, out: &Path, seed: u64, format: InitFormat) -> Result<PathBuf> {
    let v: serde_json::Value = crate::util::json::read_json(config)?;
    if v.get(ModuleKey::SsFlow.name()).is_some() && v.get("args").is_none() {
        write_random_architecture_as(config, out, seed, format)?;
        return Ok(out.to_path_buf());
    }
    let cfg = ModuleConfig::read(config)?;
    let file = config.display().to_string();
    let tensors = random_weights(&ModuleArgs::from_spec(&cfg, &file)?, seed, &file)?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let stem = config.file_stem().and_then(|s| s.to_str()).unwrap_or("model");
    let path = out.join(format!("{stem}.{}", format.extension()));
    let meta: BTreeMap<String, String> = [
        (RANDOM_INIT_KEY.to_string(), "true".to_string()),
        ("recon.seed".to_string(), seed.to_string()),
        ("recon.module".to_string(), cfg.name.clone()),
        ("recon.note".to_string(), "random weights for tests and plumbing; NOT a trained model".to_string()),
    ]
    .into_iter()
    .collect();
    format.write(&tensors, &meta, &path)?;
    let cfg_out = out.join(format!("{stem}.json"));
    let text = serde_json::to_string_pretty(&cfg).map_err(|e| Error::msg(e.to_string()))?;
    std::fs::write(&cfg_out, text).map_err(|e| Error::io(&cfg_out, e))?;
    Ok(path)
}

/// Random weights for every module of an architecture file: one labelled
/// `<out>/<key>.safetensors` per module (seed per module:
/// [`module_seed`](crate::weights::registry::module_seed)`(seed, key)`), the
/// architecture file copied under its own name, and its pose-stat files at
/// the same relative paths. Returns the written weight files.
pub fn write_random_architecture(config: &Path, out: &Path, seed: u64) -> Result<Vec<PathBuf>> {
    write_random_architecture_as(config, out, seed, InitFormat::Safetensors)
}

/// [`write_random_architecture`] in `format` (`<key>.pt` for [`InitFormat::Pt`]).
pub fn write_random_architecture_as(config: &Path, out: &Path, seed: u64, format: InitFormat) -> Result<Vec<PathBuf>> {
    use crate::model::config::RecGenConfig;
    let arch = RecGenConfig::load(config)?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let mut written = Vec::new();
    for (key, spec) in arch.modules() {
        let mseed = crate::weights::registry::module_seed(seed, key.name());
        let tensors = random_weights(&arch.module_args(key)?, mseed, &format!("{}: {key}", config.display()))?;
        let meta: BTreeMap<String, String> = [
            (RANDOM_INIT_KEY, "true".to_string()),
            ("recon.seed", seed.to_string()),
            ("recon.module_seed", mseed.to_string()),
            ("recon.module", spec.name.clone()),
            ("recon.key", key.to_string()),
            ("recon.architecture", arch.name.clone()),
            ("recon.note", "random weights for tests and plumbing; NOT a trained model".to_string()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), v))
        .collect();
        let path = out.join(format!("{key}.{}", format.extension()));
        format.write(&tensors, &meta, &path)?;
        written.push(path);
    }
    let name = config.file_name().ok_or_else(|| Error::input(config.display().to_string(), "not a file"))?;
    let dest = out.join(name);
    if dest != config {
        std::fs::copy(config, &dest).map_err(|e| Error::io(&dest, e))?;
    }
    for rel in [&arch.pose.ss_stats, &arch.pose.slat_stats] {
        let (src, dst) = (arch.base_dir.join(rel), out.join(rel));
        if src != dst {
            if let Some(parent) = dst.parent() {
                std::fs::create_dir_all(parent).map_err(|e| Error::io(parent, e))?;
            }
            std::fs::copy(&src, &dst).map_err(|e| Error::io(&src, e))?;
        }
    }
    Ok(written)
}

/// True when a safetensors file carries the random-init label (reads the header only),
/// or a torch archive the [`PT_RANDOM_INIT_RECORD`] record.
pub fn is_random_init(path: &Path) -> Result<bool> {
    if path.extension().is_some_and(|e| e == "pt" || e == "pth") {
        return crate::weights::pt::has_record(path, PT_RANDOM_INIT_RECORD);
    }
    let h = super::load::read_safetensors_header(path)?;
    Ok(h.get("__metadata__").and_then(|m| m.get(RANDOM_INIT_KEY)).and_then(|x| x.as_str()) == Some("true"))
}

fn dtype_name(d: DType) -> Result<&'static str> {
    Ok(match d {
        DType::F32 => "F32",
        DType::F16 => "F16",
        DType::BF16 => "BF16",
        DType::F64 => "F64",
        other => return Err(Error::msg(format!("cannot write dtype {other:?}"))),
    })
}

/// Write a safetensors file with sorted tensors and sorted metadata, so the
/// same inputs always give the same bytes (the `safetensors` crate takes the
/// metadata as a `HashMap`, whose order varies from run to run).
pub fn write_safetensors(tensors: &BTreeMap<String, Tensor>, meta: &BTreeMap<String, String>, path: &Path) -> Result<()> {
    let mut header = serde_json::Map::new();
    header.insert("__metadata__".into(), serde_json::to_value(meta).map_err(|e| Error::msg(e.to_string()))?);
    let mut data: Vec<u8> = Vec::new();
    for (name, t) in tensors {
        let t = t.contiguous()?;
        let start = data.len();
        match t.dtype() {
            DType::F32 => t.flatten_all()?.to_vec1::<f32>()?.iter().for_each(|v| data.extend_from_slice(&v.to_le_bytes())),
            DType::F16 => t.flatten_all()?.to_vec1::<half::f16>()?.iter().for_each(|v| data.extend_from_slice(&v.to_le_bytes())),
            DType::BF16 => t.flatten_all()?.to_vec1::<half::bf16>()?.iter().for_each(|v| data.extend_from_slice(&v.to_le_bytes())),
            DType::F64 => t.flatten_all()?.to_vec1::<f64>()?.iter().for_each(|v| data.extend_from_slice(&v.to_le_bytes())),
            _ => {}
        }
        header.insert(
            name.clone(),
            serde_json::json!({"dtype": dtype_name(t.dtype())?, "shape": t.dims(), "data_offsets": [start, data.len()]}),
        );
    }
    let mut h = serde_json::to_vec(&serde_json::Value::Object(header)).map_err(|e| Error::msg(e.to_string()))?;
    while h.len() % 8 != 0 {
        h.push(b' ');
    }
    let mut out = Vec::with_capacity(8 + h.len() + data.len());
    out.extend_from_slice(&(h.len() as u64).to_le_bytes());
    out.extend_from_slice(&h);
    out.extend_from_slice(&data);
    std::fs::write(path, out).map_err(|e| Error::io(path, e))
}
