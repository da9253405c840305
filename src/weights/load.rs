//! Opening checkpoints: memory-mapped safetensors and PyTorch `.pt`/`.pth`
//! state dicts, exposed as a candle `VarBuilder` that converts every tensor
//! to the requested dtype (f16/bf16 checkpoints → f32 by default).

use crate::{Error, Result};
use candle_core::pickle::PthTensors;
use candle_core::safetensors::MmapedSafetensors;
use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Keys under which training scripts commonly wrap a state dict. Tried in
/// order when the top level of a `.pt` file holds no tensors.
pub const PT_WRAPPER_KEYS: &[&str] = &["state_dict", "model", "ema", "model_state_dict", "module", "net", "params"];

/// Name and storage dtype/shape of one checkpoint tensor.
#[derive(Debug, Clone, PartialEq)]
pub struct StoredTensor {
    pub shape: Vec<usize>,
    pub dtype: DType,
}

enum Inner {
    Safetensors(MmapedSafetensors),
    Pth(PthTensors),
}

/// An opened checkpoint. Names are the logical (prefix-stripped) names.
pub struct Checkpoint {
    pub path: PathBuf,
    inner: Inner,
    /// Prefix present in the file and stripped from every name (`module.` for DDP checkpoints).
    pub stripped_prefix: String,
    /// Key under which a `.pt` state dict was found (`None` = top level).
    pub pt_key: Option<String>,
}

fn load_err(path: &Path, e: impl std::fmt::Display) -> Error {
    Error::input(path.display().to_string(), format!("cannot read checkpoint: {e}"))
}

impl Checkpoint {
    /// Open by extension: `.safetensors` (memory-mapped), `.pt`/`.pth`/`.bin` (torch zip pickle).
    /// For torch files, `pt_key` selects a wrapped state dict; when `None` the
    /// top level is tried first, then `PT_WRAPPER_KEYS`.
    pub fn open(path: &Path, pt_key: Option<&str>) -> Result<Self> {
        if !path.exists() {
            return Err(Error::input(path.display().to_string(), "checkpoint file not found"));
        }
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
        match ext.as_str() {
            "safetensors" => {
                // SAFETY: the file is mapped read-only; like every mmap user we
                // assume it is not truncated while the checkpoint is alive.
                let st = unsafe { MmapedSafetensors::new(path) }.map_err(|e| load_err(path, e))?;
                let mut c =
                    Checkpoint { path: path.to_path_buf(), inner: Inner::Safetensors(st), stripped_prefix: String::new(), pt_key: None };
                c.detect_prefix();
                Ok(c)
            }
            "pt" | "pth" | "bin" | "ckpt" => {
                let (pth, key) = open_pth(path, pt_key)?;
                let mut c = Checkpoint { path: path.to_path_buf(), inner: Inner::Pth(pth), stripped_prefix: String::new(), pt_key: key };
                c.detect_prefix();
                Ok(c)
            }
            _ => Err(Error::input(path.display().to_string(), "unknown checkpoint extension (expected .safetensors, .pt or .pth)")),
        }
    }

    fn raw_names(&self) -> Vec<String> {
        match &self.inner {
            Inner::Safetensors(st) => st.tensors().into_iter().map(|(n, _)| n).collect(),
            Inner::Pth(p) => p.tensor_infos().keys().cloned().collect(),
        }
    }

    /// DistributedDataParallel saves every name with `module.`; strip it when all names have it.
    fn detect_prefix(&mut self) {
        let names = self.raw_names();
        if !names.is_empty() && names.iter().all(|n| n.starts_with("module.")) {
            self.stripped_prefix = "module.".into();
        }
    }

    /// Every tensor with its stored shape and dtype, by logical name.
    pub fn tensors(&self) -> BTreeMap<String, StoredTensor> {
        let p = &self.stripped_prefix;
        let strip = |n: &str| n.strip_prefix(p.as_str()).unwrap_or(n).to_string();
        match &self.inner {
            Inner::Safetensors(st) => st
                .tensors()
                .into_iter()
                .filter_map(|(n, v)| {
                    let dtype = DType::try_from(v.dtype()).ok()?;
                    Some((strip(&n), StoredTensor { shape: v.shape().to_vec(), dtype }))
                })
                .collect(),
            Inner::Pth(pth) => pth
                .tensor_infos()
                .iter()
                .map(|(n, ti)| (strip(n), StoredTensor { shape: ti.layout.dims().to_vec(), dtype: ti.dtype }))
                .collect(),
        }
    }

    /// Read one tensor by logical name, in its stored dtype.
    pub fn get(&self, name: &str) -> Result<Option<Tensor>> {
        let full = format!("{}{}", self.stripped_prefix, name);
        match &self.inner {
            Inner::Safetensors(st) => {
                if st.get(&full).is_err() {
                    return Ok(None);
                }
                Ok(Some(st.load(&full, &Device::Cpu)?))
            }
            Inner::Pth(p) => Ok(p.get(&full)?),
        }
    }

    /// A VarBuilder over this checkpoint producing `dtype` tensors on `dev`.
    pub fn into_var_builder(self, dtype: DType, dev: &Device) -> VarBuilder<'static> {
        VarBuilder::from_backend(Box::new(self), dtype, dev.clone())
    }
}

impl SimpleBackend for Checkpoint {
    fn get(&self, s: Shape, name: &str, _h: candle_nn::Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let t = self.get_unchecked(name, dtype, dev)?;
        if t.shape() != &s {
            return Err(candle_core::Error::UnexpectedShape {
                msg: format!("shape mismatch for {name} in {}", self.path.display()),
                expected: s,
                got: t.shape().clone(),
            }
            .bt());
        }
        Ok(t)
    }

    fn get_unchecked(&self, name: &str, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let t = Checkpoint::get(self, name)
            .map_err(|e| candle_core::Error::Msg(e.to_string()))?
            .ok_or_else(|| candle_core::Error::CannotFindTensor { path: name.to_string() }.bt())?;
        t.to_dtype(dtype)?.to_device(dev)
    }

    fn contains_tensor(&self, name: &str) -> bool {
        let full = format!("{}{}", self.stripped_prefix, name);
        match &self.inner {
            Inner::Safetensors(st) => st.get(&full).is_ok(),
            Inner::Pth(p) => p.tensor_infos().contains_key(&full),
        }
    }
}

fn open_pth(path: &Path, key: Option<&str>) -> Result<(PthTensors, Option<String>)> {
    if let Some(k) = key {
        let p = PthTensors::new(path, Some(k)).map_err(|e| load_err(path, e))?;
        return Ok((p, Some(k.to_string())));
    }
    let top = PthTensors::new(path, None).map_err(|e| load_err(path, e))?;
    if !top.tensor_infos().is_empty() {
        return Ok((top, None));
    }
    for k in PT_WRAPPER_KEYS {
        if let Ok(p) = PthTensors::new(path, Some(k)) {
            if !p.tensor_infos().is_empty() {
                return Ok((p, Some(k.to_string())));
            }
        }
    }
    Err(Error::input(path.display().to_string(), format!("no tensors found at the top level or under any of the keys {PT_WRAPPER_KEYS:?}")))
}

/// Open several memory-mapped safetensors files as one VarBuilder (candle's
/// own backend; dtype conversion happens per tensor on load).
pub fn mmaped_safetensors_vb(paths: &[PathBuf], dtype: DType, dev: &Device) -> Result<VarBuilder<'static>> {
    for p in paths {
        if !p.exists() {
            return Err(Error::input(p.display().to_string(), "checkpoint file not found"));
        }
    }
    // SAFETY: read-only maps of files we do not modify while loading.
    Ok(unsafe { VarBuilder::from_mmaped_safetensors(paths, dtype, dev) }?)
}
