//! Conformance runner for TRELLIS `SLatFlowModel` (stage-2 flow transformer).

use super::fixture::{Check, Fixture};
use crate::model::sparse::SparseTensor;
use crate::model::stage2::slat_flow::{SLatFlowConfig, SLatFlowModel};
use crate::model::Compute;
use crate::Result;

/// Count of differing coordinate entries (`None` when the row counts differ).
fn coord_mismatches(got: &SparseTensor, want: &candle_core::Tensor) -> Result<usize> {
    let want = want.to_dtype(candle_core::DType::I64)?.to_vec2::<i64>()?;
    if want.len() != got.coords.len() {
        return Ok(want.len().max(got.coords.len()) * 4);
    }
    Ok(got.coords.iter().zip(&want).map(|(g, w)| (0..4).filter(|&i| g[i] as i64 != w[i]).count()).sum())
}

pub fn run(fx: &Fixture, compute: Compute) -> Result<Vec<Check>> {
    let cfg = SLatFlowConfig::from_json(fx.field("args")?, &fx.dir.join("config.json").display().to_string())?;
    let model = SLatFlowModel::new(&cfg, fx.var_builder(), compute)?;
    let tol = fx.abs_tolerance(1e-4);

    let x = SparseTensor::from_tensors(fx.tensor("input.coords")?, fx.tensor("input.feats")?.clone())?;
    let (y, taps) = model.forward_with_taps(&x, fx.tensor("input.t")?, fx.tensor("input.cond")?)?;

    // Intermediates first, in network order, so the first failure localises a bug.
    let mut checks = Vec::new();
    if let Some(t_emb) = &taps.t_emb {
        checks.push(fx.check("intermediate.t_emb", t_emb, tol)?);
    }
    for (i, h) in taps.input_blocks.iter().enumerate() {
        let key = format!("intermediate.input_blocks.{i}.feats");
        if fx.tensors.contains_key(&key) {
            checks.push(fx.check(&key, &h.feats, tol)?);
        }
        let key = format!("intermediate.input_blocks.{i}.coords");
        if let Ok(want) = fx.tensor(&key) {
            checks.push(Check::exact(key, coord_mismatches(h, want)?));
        }
    }
    for (i, f) in taps.blocks.iter().enumerate() {
        let key = format!("intermediate.blocks.{i}.feats");
        if fx.tensors.contains_key(&key) {
            checks.push(fx.check(&key, f, tol)?);
        }
    }
    checks.push(fx.check("output.feats", &y.feats, tol)?);
    if let Ok(want) = fx.tensor("output.coords") {
        checks.push(Check::exact("output.coords", coord_mismatches(&y, want)?));
    }
    Ok(checks)
}
