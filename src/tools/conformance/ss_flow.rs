//! Runners for the sparse-structure flow fixtures (`ss_flow_*`) and the
//! guidance-interval sampler fixtures (`ss_sampler_*`).

use super::fixture::{Check, Fixture};
use crate::model::sampler::{FlowEulerGuidanceIntervalSampler, SamplerSettings};
use crate::model::stage1::ss_flow::{SparseStructureFlowModel, SsFlowConfig};
use crate::model::Compute;
use crate::{Error, Result};
use candle_core::Tensor;

fn config_file(fx: &Fixture) -> String {
    fx.dir.join("config.json").display().to_string()
}

/// One forward of `SparseStructureFlowModel`: `output.v`, `intermediate.t_emb`,
/// and `intermediate.shared_mod` when the fixture has it.
pub fn run_model(fx: &Fixture, compute: Compute) -> Result<Vec<Check>> {
    let cfg = SsFlowConfig::from_json(fx.field("args")?, &config_file(fx))?;
    let model = SparseStructureFlowModel::new(&cfg, fx.var_builder(), compute)?;
    let tol = fx.abs_tolerance(1e-4);
    let (x, t, cond) = (fx.tensor("input.x")?, fx.tensor("input.t")?, fx.tensor("input.cond")?);

    let mut checks = Vec::new();
    // The model loads the `pos_emb` buffer; checkpoints without it use the
    // computed table, which must equal the buffer.
    if fx.tensors.contains_key("pos_emb") {
        let g = cfg.resolution / cfg.patch_size;
        let computed = SparseStructureFlowModel::grid_position_embedding(g, cfg.model_channels, &candle_core::Device::Cpu)?;
        checks.push(fx.check("pos_emb", &computed, tol)?.with_note("computed APE vs checkpoint buffer"));
    }
    let t_emb = model.timestep_embedding(t)?;
    if fx.tensors.contains_key("intermediate.t_emb") {
        checks.push(fx.check("intermediate.t_emb", &t_emb, tol)?);
    }
    if fx.tensors.contains_key("intermediate.shared_mod") {
        checks.push(fx.check("intermediate.shared_mod", &model.block_modulation(&t_emb)?, tol)?);
    }
    let (v, _) = model.forward(x, None, t, cond)?;
    checks.push(fx.check("output.v", &v, tol)?);
    Ok(checks)
}

fn exact_check<T: PartialEq + Copy>(key: &str, got: &[T], want: &[T]) -> Check {
    let mismatches = if got.len() != want.len() { got.len().max(want.len()) } else { got.iter().zip(want).filter(|(a, b)| a != b).count() };
    Check::exact(key, mismatches)
}

struct StepOut {
    model_t: f32,
    cfg_applied: bool,
    v_cond: Tensor,
    v_uncond: Option<Tensor>,
    pred_x0: Tensor,
    x_prev: Tensor,
}

/// A full sampling run: the time grid and per-step CFG flags exactly, then
/// every `x_t.{i}`, `pred_x_0.{i}`, the raw velocities and the final sample.
pub fn run_sampler(fx: &Fixture, compute: Compute) -> Result<Vec<Check>> {
    let file = config_file(fx);
    let cfg = SsFlowConfig::from_json(fx.field("flow_model_args")?, &file)?;
    let settings = SamplerSettings::from_json(fx.field("sampler")?, &file)?;
    let model = SparseStructureFlowModel::new(&cfg, fx.var_builder(), compute)?;
    let tol = fx.abs_tolerance(1e-4);
    let noise = fx.tensor("input.noise")?.clone();
    let cond = fx.tensor("input.cond")?;
    let neg = fx.tensor("input.neg_cond")?;

    let sampler = FlowEulerGuidanceIntervalSampler::new(settings.clone());
    let mut steps: Vec<StepOut> = Vec::new();
    let out = sampler.sample_traced(&model, vec![noise], cond, Some(neg), |r| {
        steps.push(StepOut {
            model_t: r.model_t,
            cfg_applied: r.cfg_applied,
            v_cond: r.v_cond[0].clone(),
            v_uncond: r.v_uncond.map(|u| u[0].clone()),
            pred_x0: r.pred_x0[0].clone(),
            x_prev: r.x_prev[0].clone(),
        });
        Ok(())
    })?;

    let mut checks = Vec::new();
    let want_grid = fx.tensor("time.t_seq_f64")?.to_vec1::<f64>()?;
    checks.push(exact_check("time.t_seq_f64", &settings.time_grid(), &want_grid));
    let want_mt = fx.tensor("time.model_t")?.to_vec1::<f32>()?;
    let got_mt: Vec<f32> = steps.iter().map(|s| s.model_t).collect();
    checks.push(exact_check("time.model_t", &got_mt, &want_mt));
    let want_cfg = fx.tensor("time.cfg_applied")?.to_vec1::<u8>()?;
    let got_cfg: Vec<u8> = steps.iter().map(|s| s.cfg_applied as u8).collect();
    checks.push(exact_check("time.cfg_applied", &got_cfg, &want_cfg));

    for (i, s) in steps.iter().enumerate() {
        let key = format!("intermediate.step{i}.v_cond");
        if fx.tensors.contains_key(&key) {
            checks.push(fx.check(&key, &s.v_cond, tol)?);
        }
        let key = format!("intermediate.step{i}.v_uncond");
        match (&s.v_uncond, fx.tensors.contains_key(&key)) {
            (Some(u), true) => checks.push(fx.check(&key, u, tol)?),
            (None, false) => {}
            (Some(_), false) => checks.push(Check::exact(key, 1).with_note("port ran an unconditional pass upstream did not")),
            (None, true) => checks.push(Check::exact(key, 1).with_note("upstream ran an unconditional pass the port did not")),
        }
        checks.push(fx.check(&format!("output.pred_x_0.{i}"), &s.pred_x0, tol)?);
        checks.push(fx.check(&format!("output.x_t.{i}"), &s.x_prev, tol)?);
    }
    let samples = out.into_iter().next().ok_or_else(|| Error::msg("sampler returned no state"))?;
    checks.push(fx.check("output.samples", &samples, tol)?);
    Ok(checks)
}
