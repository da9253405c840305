//! Conformance runners for the structured-latent decoders.

use super::{Check, Fixture};
use crate::decoders::gaussian::{offset_perturbation, SLatGaussianDecoder};
use crate::sparse::SparseTensor;
use crate::{Error, Result};
use candle_core::Tensor;
use std::collections::HashMap;

fn input_sparse(fx: &Fixture) -> Result<SparseTensor> {
    SparseTensor::from_tensors(fx.tensor("input.coords")?, fx.tensor("input.feats")?.clone())
}

/// Record every tap into a map `intermediate.{name}.feats`.
fn recorder(map: &mut HashMap<String, Tensor>) -> impl FnMut(&str, &Tensor) + '_ {
    move |name, t| {
        map.insert(format!("intermediate.{name}.feats"), t.clone());
    }
}

/// Check every recorded tap the fixture also holds.
fn check_taps(fx: &Fixture, taps: &HashMap<String, Tensor>, tol: f64, checks: &mut Vec<Check>) -> Result<()> {
    let mut keys: Vec<&String> = taps.keys().filter(|k| fx.tensors.contains_key(*k)).collect();
    keys.sort();
    for k in keys {
        checks.push(fx.check(k, &taps[k], tol)?);
    }
    Ok(())
}

pub fn run_gs(fx: &Fixture) -> Result<Vec<Check>> {
    let args = fx.field("args")?;
    let dec = SLatGaussianDecoder::new(args, fx.var_builder())?;
    let x = input_sparse(fx)?;
    let tol = fx.abs_tolerance(1e-4);
    let mut checks = Vec::new();

    // The recomputed Hammersley table must equal the shipped buffer.
    if let Ok(buf) = fx.tensor("offset_perturbation") {
        let ours = offset_perturbation(dec.cfg.num_gaussians, dec.cfg.voxel_size, &candle_core::Device::Cpu)?;
        checks.push(Check::new("offset_perturbation (recomputed)", super::max_abs_diff(&ours, buf)?, 1e-6));
    }

    let mut taps = HashMap::new();
    let feats = dec.forward_feats(&x, &mut recorder(&mut taps))?;
    check_taps(fx, &taps, tol, &mut checks)?;
    let reps = dec.to_representation(&x, &feats)?;
    for (b, g) in reps.iter().enumerate() {
        let outs: [(&str, Tensor); 9] = [
            ("_xyz", g.xyz.clone()),
            ("_features_dc", g.features_dc.clone()),
            ("_scaling", g.scaling.clone()),
            ("_rotation", g.rotation.clone()),
            ("_opacity", g.opacity.clone()),
            ("get_xyz", g.get_xyz()?),
            ("get_scaling", g.get_scaling()?),
            ("get_opacity", g.get_opacity()?),
            ("get_rotation", g.get_rotation()?),
        ];
        for (name, t) in outs {
            let key = format!("output.{b}.{name}");
            if fx.tensors.contains_key(&key) {
                checks.push(fx.check(&key, &t, tol)?);
            } else {
                return Err(Error::msg(format!("{}: fixture lacks `{key}`", fx.name())));
            }
        }
    }
    Ok(checks)
}

pub fn run_mesh(fx: &Fixture) -> Result<Vec<Check>> {
    Err(Error::msg(format!("{}: runner for `{}` not built yet", fx.name(), fx.module())))
}
