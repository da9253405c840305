//! Opening checkpoints: memory-mapped safetensors and PyTorch `.pt`/`.pth`
//! state dicts, exposed as a candle `VarBuilder` that converts every tensor
//! to the requested dtype (f16/bf16 checkpoints → f32 by default).

use super::pt::PtFile;
use crate::{Error, Result};
use candle_core::safetensors::MmapedSafetensors;
use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Keys under which training scripts commonly wrap a state dict. Tried in
/// order when the top level of a `.pt` file holds no tensors.
pub const PT_WRAPPER_KEYS: &[&str] = &["state_dict", "model", "ema", "model_state_dict", "module", "net", "params"];

/// Storage shape and dtype of one checkpoint tensor (its name is the map key).
#[derive(Debug, Clone, PartialEq)]
pub struct StoredTensor {
    /// Shape as stored.
    pub shape: Vec<usize>,
    /// Dtype as stored.
    pub dtype: DType,
}

enum Inner {
    Safetensors(MmapedSafetensors),
    Pth(PtFile),
}

/// An opened checkpoint. Names are the logical (prefix-stripped) names.
pub struct Checkpoint {
    /// The checkpoint file.
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
                read_safetensors_header(path)?;
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
            Inner::Pth(p) => p.tensors.keys().cloned().collect(),
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
            Inner::Pth(pth) => {
                pth.tensors.iter().map(|(n, ti)| (strip(n), StoredTensor { shape: ti.shape.clone(), dtype: ti.dtype })).collect()
            }
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
            Inner::Pth(p) => p.load(&full),
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
            Inner::Pth(p) => p.tensors.contains_key(&full),
        }
    }
}

/// Largest safetensors header read (the safetensors crate's own bound).
const MAX_SAFETENSORS_HEADER: u64 = 100 << 20;

/// Read and check a safetensors header before the file is mapped: the header
/// length against the file, every tensor's dtype, shape and offsets against
/// the data that follows (so a header claiming a 10¹² element tensor is
/// refused naming that tensor). Returns the parsed header.
pub fn read_safetensors_header(path: &Path) -> Result<serde_json::Map<String, serde_json::Value>> {
    use std::io::Read;
    let file = path.display().to_string();
    let bad = |m: String| Error::input(&file, format!("safetensors header: {m}"));
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let file_len = f.metadata().map_err(|e| Error::io(path, e))?.len();
    let mut len = [0u8; 8];
    f.read_exact(&mut len).map_err(|e| bad(format!("not a safetensors file (no 8-byte length): {e}")))?;
    let n = u64::from_le_bytes(len);
    let room = file_len.saturating_sub(8).min(MAX_SAFETENSORS_HEADER);
    if n > room {
        return Err(Error::too_large(
            &file,
            "header length",
            n as u128,
            room as u128,
            "bytes",
            "the file after the length field, at most 100 MiB",
        ));
    }
    let mut h = vec![0u8; n as usize];
    f.read_exact(&mut h).map_err(|e| bad(format!("truncated: {e}")))?;
    let v: serde_json::Value = serde_json::from_slice(&h).map_err(|e| bad(format!("invalid JSON: {e}")))?;
    let serde_json::Value::Object(map) = v else { return Err(bad("not a JSON object".into())) };
    let data_len = (file_len - 8 - n) as u128;
    for (name, t) in &map {
        if name == "__metadata__" {
            continue;
        }
        let field = |k: &str| format!("tensor `{name}` {k}");
        let dtype = t.get("dtype").and_then(|d| d.as_str()).ok_or_else(|| bad(format!("{} missing", field("dtype"))))?;
        let size: u128 = match dtype {
            "BOOL" | "U8" | "I8" | "F8_E5M2" | "F8_E4M3" => 1,
            "I16" | "U16" | "F16" | "BF16" => 2,
            "I32" | "U32" | "F32" => 4,
            "I64" | "U64" | "F64" => 8,
            other => return Err(bad(format!("{} `{other}` is not a safetensors dtype", field("dtype")))),
        };
        let nums = |k: &str| -> Result<Vec<u128>> {
            t.get(k)
                .and_then(|s| s.as_array())
                .ok_or_else(|| bad(format!("{} is not a list", field(k))))?
                .iter()
                .map(|x| x.as_u64().map(u128::from).ok_or_else(|| bad(format!("{} holds a non-integer", field(k)))))
                .collect()
        };
        let shape = nums("shape")?;
        let offs = nums("data_offsets")?;
        let [start, end] = offs[..] else { return Err(bad(format!("{} needs two numbers", field("data_offsets")))) };
        let bytes = crate::util::checked_product(shape.iter().copied()).and_then(|e| e.checked_mul(size)).unwrap_or(u128::MAX);
        if bytes > data_len {
            return Err(Error::too_large(
                &file,
                field("shape"),
                bytes,
                data_len,
                "bytes",
                format!("shape {shape:?} of {dtype}; the file's data holds {data_len} bytes"),
            ));
        }
        if start > end || end > data_len || end - start != bytes {
            return Err(bad(format!(
                "{} [{start}, {end}] do not hold shape {shape:?} of {dtype} in {data_len} data bytes",
                field("data_offsets")
            )));
        }
    }
    Ok(map)
}

fn open_pth(path: &Path, key: Option<&str>) -> Result<(PtFile, Option<String>)> {
    if let Some(k) = key {
        return Ok((PtFile::open(path, Some(k))?, Some(k.to_string())));
    }
    let top = PtFile::open(path, None)?;
    if !top.tensors.is_empty() {
        return Ok((top, None));
    }
    for k in PT_WRAPPER_KEYS {
        if let Ok(p) = PtFile::open(path, Some(k)) {
            if !p.tensors.is_empty() {
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
        read_safetensors_header(p)?;
    }
    // SAFETY: read-only maps of files we do not modify while loading.
    Ok(unsafe { VarBuilder::from_mmaped_safetensors(paths, dtype, dev) }?)
}
