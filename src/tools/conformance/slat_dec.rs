//! Conformance runners for the structured-latent decoders.

use super::fixture::{Check, Fixture};
use crate::model::sparse::SparseTensor;
use crate::model::stage2::slat_vae::gaussian::{offset_perturbation, GaussianDecoderConfig, SLatGaussianDecoder};
use crate::model::stage2::slat_vae::mesh::{MeshDecoderConfig, SLatMeshDecoder};
use crate::model::Compute;
use crate::{Error, Result};
use candle_core::{Device, Tensor};
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

pub fn run_gs(fx: &Fixture, compute: Compute) -> Result<Vec<Check>> {
    let file = fx.dir.join("config.json").display().to_string();
    let args = GaussianDecoderConfig::from_json(fx.field("args")?, &file)?;
    let dec = SLatGaussianDecoder::new(&args, fx.var_builder(), compute)?;
    let x = input_sparse(fx)?;
    let tol = fx.abs_tolerance(1e-4);
    let mut checks = Vec::new();

    // The recomputed Hammersley table must equal the shipped buffer.
    if let Ok(buf) = fx.tensor("offset_perturbation") {
        let ours = offset_perturbation(dec.cfg.num_gaussians, dec.cfg.voxel_size, &candle_core::Device::Cpu)?;
        checks.push(Check::new("offset_perturbation (recomputed)", crate::util::max_abs_diff(&ours, buf)?, 1e-6));
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

fn coords_mismatches(got: &SparseTensor, want: &Tensor) -> Result<usize> {
    let want = want.to_dtype(candle_core::DType::I64)?.to_vec2::<i64>()?;
    if want.len() != got.coords.len() {
        return Ok(want.len().max(got.coords.len()));
    }
    Ok(got.coords.iter().zip(&want).filter(|(a, b)| a.iter().zip(b.iter()).any(|(&x, &y)| x as i64 != y)).count())
}

pub fn run_mesh(fx: &Fixture, compute: Compute) -> Result<Vec<Check>> {
    let file = fx.dir.join("config.json").display().to_string();
    let args = MeshDecoderConfig::from_json(fx.field("args")?, &file)?;
    let dec = SLatMeshDecoder::new(&args, fx.var_builder(), compute)?;
    let x = input_sparse(fx)?;
    // The suggested tolerance is for vertices; model features use the README's 1e-4.
    let tol = 1e-4;
    let mut checks = Vec::new();
    // Taps in pipeline order, so the first failing stage is reported first.
    let mut taps: Vec<(String, SparseTensor)> = Vec::new();
    let feats = dec.forward_feats(&x, &mut |name, t| taps.push((name.to_string(), t.clone())))?;
    for (name, t) in &taps {
        let fk = format!("intermediate.{name}.feats");
        if fx.tensors.contains_key(&fk) {
            checks.push(fx.check(&fk, &t.feats, tol)?);
        }
        let ck = format!("intermediate.{name}.coords");
        if let Ok(want) = fx.tensor(&ck) {
            checks.push(Check::exact(ck, coords_mismatches(t, want)?));
        }
    }

    let meshes = dec.extractor.extract_sparse(&feats)?;
    let mesh = meshes.first().ok_or_else(|| Error::msg("mesh decoder: empty batch"))?;
    mesh.validate()?;
    let want_v = fx.tensor("output.vertices")?;
    let nv = want_v.dim(0)?;
    checks.push(Check::exact("num_vertices", mesh.vertices.len().abs_diff(nv)).with_note(format!("got {} want {nv}", mesh.vertices.len())));
    if mesh.vertices.len() == nv {
        let v: Vec<f32> = mesh.vertices.iter().flatten().copied().collect();
        checks.push(fx.check("output.vertices", &Tensor::from_vec(v, (nv, 3), &Device::Cpu)?, fx.abs_tolerance(1e-5).max(1e-5))?);
        if let (Some(a), Ok(_)) = (&mesh.vertex_attrs, fx.tensor("output.vertex_attrs")) {
            let a: Vec<f32> = a.iter().flatten().copied().collect();
            checks.push(fx.check("output.vertex_attrs", &Tensor::from_vec(a, (nv, 6), &Device::Cpu)?, 1e-4)?);
        }
    }
    let want_f = fx.tensor("output.faces")?.to_dtype(candle_core::DType::I64)?.to_vec2::<i64>()?;
    let mismatches = if want_f.len() == mesh.faces.len() {
        mesh.faces.iter().zip(&want_f).filter(|(a, b)| a.iter().zip(b.iter()).any(|(&p, &q)| p as i64 != q)).count()
    } else {
        want_f.len().max(mesh.faces.len())
    };
    checks.push(Check::exact("output.faces", mismatches).with_note(format!("exact, in upstream order ({} faces)", want_f.len())));
    Ok(checks)
}
