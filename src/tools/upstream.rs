//! recon against upstream PyTorch on the same machine, from what
//! `benches/upstream/harness.py` writes:
//! - a timing report in `recon bench`'s JSON schema, compared row by row
//!   with recon's module rows (`recon bench --compare FILE`);
//! - full-size checkpoints in the released layout (fp16 safetensors and
//!   `{name, args}` JSON under `ckpts/`, released file names) with upstream's
//!   outputs on them, loaded here through the real, strict loading path
//!   (`recon bench --released DIR`, `tests/upstream_fullsize.rs`): the
//!   full-size counterpart of the tiny conformance fixtures.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::model::config::{ModuleArgs, ModuleKey};
use crate::model::nn::fast::{Compute, Precision};
use crate::weights::registry::{self, ModuleConfig};
use crate::{Error, Result};

/// The released TRELLIS-image-large file stems of the modules the harness
/// can build on a CPU (the sparse ones need spconv and CUDA).
pub const RELEASED: [(ModuleKey, &str); 2] =
    [(ModuleKey::SsFlow, "ss_flow_img_dit_L_16l8_fp16"), (ModuleKey::SsDecoder, "ss_dec_conv3d_16l8_fp16")];

/// One module timing: a row of an upstream report, or recon's
/// module rows reduced to what the comparison reads.
#[derive(Debug, Clone, Deserialize)]
pub struct TimingRow {
    pub module: String,
    pub precision: String,
    pub forward_seconds: f64,
    #[serde(default)]
    pub peak_rss_mib: Option<f64>,
    #[serde(default)]
    pub load_average: Option<f64>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct UpstreamMachine {
    pub cpu: String,
    pub threads: usize,
}

/// What `harness.py --json` writes.
#[derive(Debug, Clone, Deserialize)]
pub struct UpstreamReport {
    pub machine: UpstreamMachine,
    pub modules: Vec<TimingRow>,
    #[serde(default)]
    pub notes: Vec<String>,
}

impl UpstreamReport {
    pub fn read(path: &Path) -> Result<Self> {
        let r: Self = crate::util::json::read_json(path)?;
        if let Some(bad) = r.modules.iter().find(|m| !(m.forward_seconds.is_finite() && m.forward_seconds > 0.0)) {
            return Err(Error::input(
                path.display().to_string(),
                format!("modules[{}].forward_seconds: expected a positive number of seconds, found {}", bad.module, bad.forward_seconds),
            ));
        }
        Ok(r)
    }
}

/// The arithmetic a row ran in: `f32`, or `bf16` (recon's bf16 kernels,
/// upstream's bf16 autocast). The instruction set in parentheses is not
/// read (`fast f32 (avx512bf16)` is f32).
pub fn row_dtype(precision: &str) -> Option<Precision> {
    let p = precision.split('(').next().unwrap_or("").to_ascii_lowercase();
    if p.contains("bf16") {
        Some(Precision::Bf16)
    } else if p.contains("f16") {
        Some(Precision::F16)
    } else if p.contains("f32") {
        Some(Precision::F32)
    } else {
        None
    }
}

/// recon vs upstream for one module in one precision (`speedup` > 1: recon faster).
#[derive(Debug, Clone, Serialize)]
pub struct CompareRow {
    pub module: String,
    pub precision: String,
    pub recon_seconds: f64,
    pub upstream_seconds: f64,
    pub speedup: f64,
    pub recon_peak_mib: Option<f64>,
    pub upstream_peak_mib: Option<f64>,
}

/// Matching rows by module and precision, then each module's best recon
/// precision against upstream's best (the "best vs best" row, precision `best`).
pub fn compare(recon: &[TimingRow], upstream: &UpstreamReport) -> Vec<CompareRow> {
    let mut rows = Vec::new();
    let mut modules: Vec<&str> = recon.iter().map(|r| r.module.as_str()).collect();
    modules.dedup();
    for module in modules {
        let ours: Vec<&TimingRow> = recon.iter().filter(|r| r.module == module).collect();
        let theirs: Vec<&TimingRow> = upstream.modules.iter().filter(|r| r.module == module).collect();
        for r in &ours {
            let Some(dtype) = row_dtype(&r.precision) else { continue };
            if let Some(u) = theirs.iter().find(|u| row_dtype(&u.precision) == Some(dtype)) {
                rows.push(CompareRow {
                    module: module.into(),
                    precision: dtype.name().into(),
                    recon_seconds: r.forward_seconds,
                    upstream_seconds: u.forward_seconds,
                    speedup: u.forward_seconds / r.forward_seconds,
                    recon_peak_mib: r.peak_rss_mib,
                    upstream_peak_mib: u.peak_rss_mib,
                });
            }
        }
        let best_ours = ours.iter().min_by(|a, b| a.forward_seconds.total_cmp(&b.forward_seconds));
        let best_theirs = theirs.iter().min_by(|a, b| a.forward_seconds.total_cmp(&b.forward_seconds));
        if let (Some(r), Some(u)) = (best_ours, best_theirs) {
            rows.push(CompareRow {
                module: module.into(),
                precision: format!(
                    "best ({} vs {})",
                    row_dtype(&r.precision).map_or("?", Precision::name),
                    row_dtype(&u.precision).map_or("?", Precision::name)
                ),
                recon_seconds: r.forward_seconds,
                upstream_seconds: u.forward_seconds,
                speedup: u.forward_seconds / r.forward_seconds,
                recon_peak_mib: r.peak_rss_mib,
                upstream_peak_mib: u.peak_rss_mib,
            });
        }
    }
    rows
}

/// `max|a−b| / max|b|` and `mean|a−b| / mean|b|` over all elements, in f64
/// (a float64 reference keeps its digits).
pub(crate) fn rel_errors(a: &Tensor, b: &Tensor) -> Result<(f64, f64)> {
    let a = a.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    let b = b.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?;
    if a.len() != b.len() {
        return Err(crate::Error::msg("bench: outputs of different sizes"));
    }
    let (mut maxd, mut maxb, mut sumd, mut sumb) = (0f64, 0f64, 0f64, 0f64);
    for (&x, &y) in a.iter().zip(&b) {
        let d = (x - y).abs();
        maxd = maxd.max(d);
        maxb = maxb.max(y.abs());
        sumd += d;
        sumb += y.abs();
    }
    Ok((maxd / maxb.max(1e-30), sumd / sumb.max(1e-30)))
}

/// recon's output on a released-layout checkpoint against upstream's.
#[derive(Debug, Clone, Serialize)]
pub struct ReleasedRow {
    pub module: String,
    pub file: String,
    pub compute: String,
    /// `upstream f32` (upstream in f32 on the stored fp16 values) or
    /// `upstream bf16 autocast`.
    pub reference: String,
    pub forward_seconds: f64,
    pub max_rel: f64,
    pub mean_rel: f64,
}

fn reference_tensors(dir: &Path) -> Result<(PathBuf, HashMap<String, Tensor>)> {
    let path = dir.join("reference.safetensors");
    if !path.is_file() {
        return Err(Error::input(
            dir.display().to_string(),
            "no reference.safetensors: expected a folder written by `benches/upstream/harness.py --save`".to_string(),
        ));
    }
    let t = candle_core::safetensors::load(&path, &Device::Cpu)
        .map_err(|e| Error::input(path.display().to_string(), format!("not a readable safetensors file: {e}")))?;
    Ok((path, t))
}

fn tensor<'a>(t: &'a HashMap<String, Tensor>, file: &Path, name: &str) -> Result<&'a Tensor> {
    t.get(name).ok_or_else(|| Error::input(file.display().to_string(), format!("tensor `{name}`: missing")))
}

/// Load each released module found under `dir/ckpts` strictly (every tensor
/// named and shaped as the config expects, no extras), run it with each of
/// `computes` on the stored inputs, and measure it against upstream's outputs.
pub fn check_released(dir: &Path, computes: &[Compute]) -> Result<Vec<ReleasedRow>> {
    let (ref_path, t) = reference_tensors(dir)?;
    let mut rows = Vec::new();
    for (key, stem) in RELEASED {
        let json = dir.join("ckpts").join(format!("{stem}.json"));
        let st = dir.join("ckpts").join(format!("{stem}.safetensors"));
        if !json.is_file() || !st.is_file() {
            continue;
        }
        let label = json.display().to_string();
        let cfg = ModuleArgs::from_spec(&ModuleConfig::read(&json)?, &label)?;
        let expected = registry::expected_tensors(&cfg, &label)?;
        for &compute in computes {
            let vb = crate::weights::load_validated(&st, &expected, false, DType::F32, &Device::Cpu)?;
            let (out, seconds) = match key {
                ModuleKey::SsFlow => {
                    let m = registry::build_ss_flow(&cfg, vb, &label, compute)?;
                    crate::util::release_cached_buffers();
                    let (x, tt, cond) = (
                        tensor(&t, &ref_path, "input.ss_flow.x")?,
                        tensor(&t, &ref_path, "input.ss_flow.t")?,
                        tensor(&t, &ref_path, "input.ss_flow.cond")?,
                    );
                    let s = Instant::now();
                    let (v, _) = m.forward(x, None, tt, cond)?;
                    (v, s.elapsed().as_secs_f64())
                }
                _ => {
                    let m = registry::build_ss_decoder(&cfg, vb, &label, compute)?;
                    crate::util::release_cached_buffers();
                    let x = tensor(&t, &ref_path, "input.ss_decoder.x")?;
                    let s = Instant::now();
                    let o = m.forward(x)?;
                    (o, s.elapsed().as_secs_f64())
                }
            };
            for (dtype, reference) in [("f32", "upstream f32"), ("bf16", "upstream bf16 autocast")] {
                let want = tensor(&t, &ref_path, &format!("output.{key}.{dtype}"))?;
                if want.dims() != out.dims() {
                    return Err(Error::input(
                        ref_path.display().to_string(),
                        format!("output.{key}.{dtype}: shape {:?}, recon's output is {:?}", want.dims(), out.dims()),
                    ));
                }
                let (max_rel, mean_rel) = rel_errors(&out, want)?;
                rows.push(ReleasedRow {
                    module: key.to_string(),
                    file: st.display().to_string(),
                    compute: compute.describe(),
                    reference: reference.into(),
                    forward_seconds: seconds,
                    max_rel,
                    mean_rel,
                });
            }
        }
        // Upstream's own bf16 error, for the budget.
        let (a, b) = (tensor(&t, &ref_path, &format!("output.{key}.bf16"))?, tensor(&t, &ref_path, &format!("output.{key}.f32"))?);
        let (max_rel, mean_rel) = rel_errors(a, b)?;
        rows.push(ReleasedRow {
            module: key.to_string(),
            file: ref_path.display().to_string(),
            compute: "upstream bf16 autocast".into(),
            reference: "upstream f32".into(),
            forward_seconds: 0.0,
            max_rel,
            mean_rel,
        });
    }
    rows.extend(check_dinov2(dir, &t, &ref_path, computes)?);
    if rows.is_empty() {
        return Err(Error::input(
            dir.join("ckpts").display().to_string(),
            format!(
                "no released checkpoint found: expected {}",
                RELEASED.iter().map(|(_, s)| format!("{s}.json + {s}.safetensors")).collect::<Vec<_>>().join(" or ")
            ),
        ));
    }
    Ok(rows)
}

/// torch.hub's file of `dinov2_vitl14_reg`, under `hub/checkpoints/` as `TORCH_HOME` lays it out.
pub const DINOV2_HUB_FILE: &str = "dinov2_vitl14_reg4_pretrain.pth";

/// DINOv2 as torch.hub stores it (`hub/checkpoints/`), when the harness wrote it: TRELLIS's
/// condition (layer norm of `x_prenorm`) against upstream's in f32 and float64 (and bf16
/// autocast), plus upstream f32's own distance from float64, by which full-size f32
/// agreement is judged. The model is ViT-L/14-reg unless `dinov2_args.json` beside the
/// checkpoint gives another size (the tiny CI fixture).
fn check_dinov2(dir: &Path, t: &HashMap<String, Tensor>, ref_path: &Path, computes: &[Compute]) -> Result<Vec<ReleasedRow>> {
    use crate::model::stage1::dinov2::{trellis_cond, Dinov2, Dinov2Config};
    let hub = dir.join("hub").join("checkpoints");
    let pth = hub.join(DINOV2_HUB_FILE);
    if !pth.is_file() {
        return Ok(Vec::new());
    }
    let args = hub.join("dinov2_args.json");
    let cfg = if args.is_file() {
        let text = std::fs::read_to_string(&args).map_err(|e| Error::io(&args, e))?;
        let v: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| Error::input(args.display().to_string(), format!("not JSON: {e}")))?;
        Dinov2Config::from_json(&v, &args.display().to_string())?
    } else {
        Dinov2Config::vitl14_reg()
    };
    let label = pth.display().to_string();
    let expected = registry::expected_tensors(&ModuleArgs::Dinov2(cfg.clone()), &label)?;
    let pixels = tensor(t, ref_path, "input.dinov2.pixel_values")?;
    let mut rows = Vec::new();
    let row = |compute: String, reference: &str, seconds: f64, (max_rel, mean_rel): (f64, f64)| ReleasedRow {
        module: "dinov2".into(),
        file: label.clone(),
        compute,
        reference: reference.into(),
        forward_seconds: seconds,
        max_rel,
        mean_rel,
    };
    for &compute in computes {
        let vb = crate::weights::load_validated(&pth, &expected, false, DType::F32, &Device::Cpu)?;
        let m = Dinov2::new(&cfg, vb, compute)?;
        crate::util::release_cached_buffers();
        let s = Instant::now();
        let cond = trellis_cond(&m.forward(pixels)?.x_prenorm)?;
        let seconds = s.elapsed().as_secs_f64();
        for (dtype, reference) in [("f32", "upstream f32"), ("f64", "upstream f64"), ("bf16", "upstream bf16 autocast")] {
            let want = tensor(t, ref_path, &format!("output.dinov2.{dtype}"))?;
            if want.dims() != cond.dims() {
                return Err(Error::input(
                    ref_path.display().to_string(),
                    format!("output.dinov2.{dtype}: shape {:?}, recon's condition is {:?}", want.dims(), cond.dims()),
                ));
            }
            rows.push(row(compute.describe(), reference, seconds, rel_errors(&cond, want)?));
        }
    }
    let f64_ref = tensor(t, ref_path, "output.dinov2.f64")?;
    for (dtype, name) in [("f32", "upstream f32"), ("bf16", "upstream bf16 autocast")] {
        let theirs = tensor(t, ref_path, &format!("output.dinov2.{dtype}"))?;
        rows.push(row(name.into(), "upstream f64", 0.0, rel_errors(theirs, f64_ref)?));
    }
    let (a, b) = (tensor(t, ref_path, "output.dinov2.bf16")?, tensor(t, ref_path, "output.dinov2.f32")?);
    rows.push(row("upstream bf16 autocast".into(), "upstream f32", 0.0, rel_errors(a, b)?));
    Ok(rows)
}

/// RecGen's stage-2 denoiser as released: a `torch.save` state dict beside the
/// training config whose `models.denoiser` is its `{name, args}`.
pub const SLAT_FLOW_PT: &str = "slat_denoiser_ema0.9999_step0075000.pt";
pub const SLAT_FLOW_CONFIG: &str = "slat_config.json";
/// TRELLIS-image-large's SLat Gaussian decoder (`ckpts/<stem>.json` + fp16 `.safetensors`).
pub const SLAT_DEC_GS: &str = "slat_dec_gs_swin8_B_64l8gs32_fp16";
/// What `benches/upstream/sparse_fullsize.py --save` writes beside the checkpoints.
pub const SPARSE_REFERENCE: &str = "sparse_reference.safetensors";

/// The stage-2 sparse modules that `sparse_fullsize.py --save` wrote under `dir`
/// (`Ok(empty)` when it wrote none), each loaded strictly through recon's
/// loaders and run with each of `computes` on the stored inputs, against
/// upstream's float32 and float64 outputs; plus upstream f32's own distance
/// from float64, by which full-size agreement is judged.
///
/// `slat_flow`: RecGen's `SLatCondFlowModel` from the released `.pt` and
/// `slat_config.json`; the condition is built by recon (`condition`: patch
/// tokens + point-map and mask embeddings, pose token appended) and compared
/// (module `slat_flow.cond`), then the velocity on the voxels (`slat_flow`).
pub fn check_sparse(dir: &Path, computes: &[Compute]) -> Result<Vec<ReleasedRow>> {
    let ref_path = dir.join(SPARSE_REFERENCE);
    if !ref_path.is_file() {
        return Ok(Vec::new());
    }
    let t = candle_core::safetensors::load(&ref_path, &Device::Cpu)
        .map_err(|e| Error::input(ref_path.display().to_string(), format!("not a readable safetensors file: {e}")))?;
    let mut rows = Vec::new();
    let pt = dir.join(SLAT_FLOW_PT);
    if pt.is_file() {
        rows.extend(check_slat_flow(dir, &pt, &t, &ref_path, computes)?);
    }
    let gs = dir.join("ckpts").join(format!("{SLAT_DEC_GS}.safetensors"));
    if gs.is_file() {
        rows.extend(check_slat_dec_gs(dir, &gs, &t, &ref_path, computes)?);
    }
    if rows.is_empty() {
        return Err(Error::input(
            dir.display().to_string(),
            format!(
                "{SPARSE_REFERENCE} but no sparse module's checkpoint: expected {SLAT_FLOW_PT} + {SLAT_FLOW_CONFIG} \
                 or ckpts/{SLAT_DEC_GS}.json + .safetensors"
            ),
        ));
    }
    Ok(rows)
}

/// Rows of `module` (recon with `compute` against upstream f32 and f64, then
/// upstream f32 against f64) for output `name` of the reference file.
fn f64_rows(
    module: &str,
    file: &str,
    ours: &[(String, f64, Tensor)],
    t: &HashMap<String, Tensor>,
    ref_path: &Path,
    name: &str,
) -> Result<Vec<ReleasedRow>> {
    let (f32_ref, f64_ref) = (tensor(t, ref_path, &format!("{name}.f32"))?, tensor(t, ref_path, &format!("{name}.f64"))?);
    let mut rows = Vec::new();
    let row = |compute: String, reference: &str, seconds: f64, (max_rel, mean_rel): (f64, f64)| ReleasedRow {
        module: module.into(),
        file: file.into(),
        compute,
        reference: reference.into(),
        forward_seconds: seconds,
        max_rel,
        mean_rel,
    };
    for (compute, seconds, out) in ours {
        for (want, reference) in [(f32_ref, "upstream f32"), (f64_ref, "upstream f64")] {
            // Element order is the same; the shapes may group the Gaussians' fields differently.
            if want.elem_count() != out.elem_count() || want.dim(0)? != out.dim(0)? {
                return Err(Error::input(
                    ref_path.display().to_string(),
                    format!("{name}: shape {:?}, recon's is {:?}", want.dims(), out.dims()),
                ));
            }
            rows.push(row(compute.clone(), reference, *seconds, rel_errors(out, want)?));
        }
    }
    rows.push(row("upstream f32".into(), "upstream f64", 0.0, rel_errors(f32_ref, f64_ref)?));
    Ok(rows)
}

fn check_slat_flow(dir: &Path, pt: &Path, t: &HashMap<String, Tensor>, ref_path: &Path, computes: &[Compute]) -> Result<Vec<ReleasedRow>> {
    use crate::model::stage1::embedders::ViewInputs;
    use crate::model::{ModuleSpec, SparseTensor};
    let cfg_path = dir.join(SLAT_FLOW_CONFIG);
    let label = cfg_path.display().to_string();
    let v: serde_json::Value = crate::util::json::read_json(&cfg_path)?;
    let spec = v
        .pointer("/models/denoiser")
        .ok_or_else(|| Error::config(&label, "models.denoiser", "missing: expected the denoiser's {name, args}"))?;
    let spec: ModuleSpec = serde_json::from_value(spec.clone())
        .map_err(|e| Error::config(&label, "models.denoiser", format!("expected {{name, args}}: {e}")))?;
    let cfg = ModuleArgs::from_spec(&spec, &label)?;
    let expected = registry::expected_tensors(&cfg, &label)?;
    let input = |name: &str| tensor(t, ref_path, &format!("input.slat_flow.{name}"));
    let x = SparseTensor::from_tensors(input("coords")?, input("feats")?.clone())?;
    let view = ViewInputs {
        patch_tokens: input("patch_tokens")?.clone(),
        pointmap: Some(input("pointmap")?.clone()),
        mask: Some(input("mask")?.clone()),
    };
    let (tt, pose) = (input("t")?, input("pose")?);
    let (mut conds, mut outs) = (Vec::new(), Vec::new());
    for &compute in computes {
        let vb = crate::weights::load_validated(pt, &expected, false, DType::F32, &Device::Cpu)?;
        let m = registry::build_slat_flow(&cfg, vb, &pt.display().to_string(), compute)?;
        crate::util::release_cached_buffers();
        let s = Instant::now();
        let (cond, _) = m.condition(std::slice::from_ref(&view), Some(pose))?;
        let out = m.forward(&x, tt, &cond)?;
        let seconds = s.elapsed().as_secs_f64();
        if out.coords != x.coords {
            return Err(Error::msg("slat_flow: recon's output rows are not in the input's order"));
        }
        conds.push((compute.describe(), seconds, cond));
        outs.push((compute.describe(), seconds, out.feats));
    }
    let file = pt.display().to_string();
    let mut rows = f64_rows("slat_flow.cond", &file, &conds, t, ref_path, "output.slat_flow.cond")?;
    rows.extend(f64_rows("slat_flow", &file, &outs, t, ref_path, "output.slat_flow")?);
    Ok(rows)
}

/// TRELLIS's SLat Gaussian decoder from `ckpts/`: the out layer's features (module
/// `slat_dec_gs.feats`) and the Gaussians (`slat_dec_gs.xyz`: positions; `.features_dc`;
/// the activated `.scaling`, `.rotation`, `.opacity`).
fn check_slat_dec_gs(
    dir: &Path,
    st: &Path,
    t: &HashMap<String, Tensor>,
    ref_path: &Path,
    computes: &[Compute],
) -> Result<Vec<ReleasedRow>> {
    use crate::model::{ModuleSpec, SparseTensor};
    let json = dir.join("ckpts").join(format!("{SLAT_DEC_GS}.json"));
    let label = json.display().to_string();
    let cfg = ModuleArgs::from_spec(&ModuleSpec::read(&json)?, &label)?;
    let expected = registry::expected_tensors(&cfg, &label)?;
    let x = SparseTensor::from_tensors(
        tensor(t, ref_path, "input.slat_dec_gs.coords")?,
        tensor(t, ref_path, "input.slat_dec_gs.feats")?.clone(),
    )?;
    let names = ["feats", "xyz", "features_dc", "scaling", "rotation", "opacity"];
    let mut outs: Vec<Vec<(String, f64, Tensor)>> = vec![Vec::new(); names.len()];
    for &compute in computes {
        let vb = crate::weights::load_validated(st, &expected, false, DType::F32, &Device::Cpu)?;
        let m = registry::build_gaussian_decoder(&cfg, vb, &st.display().to_string(), compute)?;
        crate::util::release_cached_buffers();
        let s = Instant::now();
        let feats = m.forward_feats(&x, &mut |_, _| {})?;
        let reps = m.to_representation(&x, &feats)?;
        let seconds = s.elapsed().as_secs_f64();
        let g = reps.first().ok_or_else(|| Error::msg("slat_dec_gs: no Gaussians"))?;
        let n = g.xyz.elem_count() / 3;
        let flat = |t: Tensor| -> Result<Tensor> {
            let w = t.elem_count() / n;
            Ok(t.reshape((n, w))?)
        };
        let ours = [
            feats,
            flat(g.xyz.clone())?,
            flat(g.features_dc.clone())?,
            flat(g.get_scaling()?)?,
            flat(g.get_rotation()?)?,
            flat(g.get_opacity()?)?,
        ];
        for (o, v) in outs.iter_mut().zip(ours) {
            o.push((compute.describe(), seconds, v));
        }
    }
    let file = st.display().to_string();
    let mut rows = Vec::new();
    for (name, ours) in names.iter().zip(&outs) {
        rows.extend(f64_rows(&format!("slat_dec_gs.{name}"), &file, ours, t, ref_path, &format!("output.slat_dec_gs.{name}"))?);
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(module: &str, precision: &str, s: f64) -> TimingRow {
        TimingRow { module: module.into(), precision: precision.into(), forward_seconds: s, peak_rss_mib: None, load_average: None }
    }

    #[test]
    fn rows_pair_by_module_and_precision() {
        let ours = vec![row("ss_flow", "fast f32 (avx512bf16)", 40.0), row("ss_flow", "fast bf16 (avx512bf16)", 20.0)];
        // Upstream's bf16 row first: the pairing must not depend on the order.
        let up = UpstreamReport {
            machine: UpstreamMachine { cpu: "x".into(), threads: 2 },
            modules: vec![
                TimingRow {
                    module: "ss_flow".into(),
                    precision: "upstream torch bf16 autocast (AVX512)".into(),
                    forward_seconds: 15.0,
                    peak_rss_mib: None,
                    load_average: None,
                },
                TimingRow {
                    module: "ss_flow".into(),
                    precision: "upstream torch f32 (AVX512)".into(),
                    forward_seconds: 48.0,
                    peak_rss_mib: None,
                    load_average: None,
                },
            ],
            notes: vec![],
        };
        let c = compare(&ours, &up);
        assert_eq!(c.len(), 3);
        assert_eq!((c[0].precision.as_str(), c[0].speedup), ("f32", 1.2));
        assert_eq!((c[1].precision.as_str(), c[1].speedup), ("bf16", 0.75));
        assert_eq!(c[2].precision, "best (bf16 vs bf16)");
        assert!((c[2].speedup - 0.75).abs() < 1e-12);
        assert_eq!(row_dtype("plain candle f32"), Some(Precision::F32));
        assert_eq!(row_dtype("fast f32 (avx512bf16)"), Some(Precision::F32));
        assert_eq!(row_dtype("upstream torch bf16 autocast (AVX512)"), Some(Precision::Bf16));
        assert_eq!(row_dtype("what"), None);
    }
}
