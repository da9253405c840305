//! Module configs by name: `{"name": ClassName, "args": {...}}` files (the
//! TRELLIS `ckpts/<name>.json` format) map to a builder that constructs the
//! module on any VarBuilder. Building on a `Recorder` (`weights::record`)
//! yields the expected tensor list; on a [`crate::weights::RandomInit`]
//! random weights. New modules plug in by adding a match arm to [`build`].
//!
//! Every module of the architecture file (`models/recgen-*.json`) is known:
//! the DINOv2 image encoder, the stage-1 flow (`SparseStructureFlowModel`,
//! RecGen `SparseStructurePoseFlowModel`), `SparseStructureDecoder`, the
//! SS VAE encoder (`SparseStructureEncoder`, training only), the
//! stage-2 flow (`SLatFlowModel`, RecGen `SLatCondFlowModel`, and their
//! `Elastic*` checkpoint aliases), `SLatMeshDecoder`, `SLatGaussianDecoder`.

use crate::model::config::{ModuleArgs, ModuleSpec};
use crate::model::nn::fast::Compute;
use crate::model::stage1::dinov2::Dinov2;
use crate::model::stage1::ss_flow::SparseStructureFlowModel;
use crate::model::stage1::ss_vae::decoder::SparseStructureDecoder;
use crate::model::stage1::ss_vae::encoder::SparseStructureEncoder;
use crate::model::stage2::slat_flow::SLatFlowModel;
use crate::model::stage2::slat_vae::encoder::SLatEncoder;
use crate::model::stage2::slat_vae::gaussian::{offset_perturbation, GaussianConfig, SLatGaussianDecoder};
use crate::model::stage2::slat_vae::mesh::SLatMeshDecoder;
use crate::weights::record::{RandomInit, RandomStream, Recorder, TensorSpec};
use crate::{Error, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use std::collections::BTreeMap;

/// A module config file (`{"name", "args"}`, args as written); parse it with
/// [`ModuleArgs::from_spec`].
pub type ModuleConfig = ModuleSpec;

pub use crate::model::key::{ModuleKind, KNOWN_MODULES};

/// The DINOv2 image encoder of `cfg`.
pub fn build_dinov2(cfg: &ModuleArgs, vb: VarBuilder, file: &str, compute: Compute) -> Result<Dinov2> {
    Ok(Dinov2::new(cfg.dinov2(file)?, vb, compute)?)
}

/// The stage-1 flow of `cfg`.
pub fn build_ss_flow(cfg: &ModuleArgs, vb: VarBuilder, file: &str, compute: Compute) -> Result<SparseStructureFlowModel> {
    SparseStructureFlowModel::new(cfg.ss_flow(file)?, vb, compute)
}

/// The SS VAE decoder of `cfg`.
pub fn build_ss_decoder(cfg: &ModuleArgs, vb: VarBuilder, file: &str, compute: Compute) -> Result<SparseStructureDecoder> {
    SparseStructureDecoder::new(cfg.ss_decoder(file)?, vb, compute)
}

/// The SS VAE encoder of `cfg` (training only).
pub fn build_ss_encoder(cfg: &ModuleArgs, vb: VarBuilder, file: &str, compute: Compute) -> Result<SparseStructureEncoder> {
    SparseStructureEncoder::new(cfg.ss_encoder(file)?, vb, compute)
}

/// The stage-2 flow of `cfg`.
pub fn build_slat_flow(cfg: &ModuleArgs, vb: VarBuilder, file: &str, compute: Compute) -> Result<SLatFlowModel> {
    SLatFlowModel::new(cfg.slat_flow(file)?, vb, compute)
}

/// The SLat mesh decoder of `cfg`.
pub fn build_mesh_decoder(cfg: &ModuleArgs, vb: VarBuilder, file: &str, compute: Compute) -> Result<SLatMeshDecoder> {
    SLatMeshDecoder::new(cfg.mesh_decoder(file)?, vb, compute)
}

/// The SLat VAE encoder of `cfg` (training only).
pub fn build_slat_encoder(cfg: &ModuleArgs, vb: VarBuilder, file: &str, compute: Compute) -> Result<SLatEncoder> {
    SLatEncoder::new(cfg.slat_encoder(file)?, vb, compute)
}

/// The SLat Gaussian decoder of `cfg`.
pub fn build_gaussian_decoder(cfg: &ModuleArgs, vb: VarBuilder, file: &str, compute: Compute) -> Result<SLatGaussianDecoder> {
    SLatGaussianDecoder::new(cfg.gaussian_decoder(file)?, vb, compute)
}

/// Build the module `cfg` describes on `vb` (the module is dropped; the
/// point is what the builder requests from `vb`, the same on every compute
/// path, so it is built plain).
pub fn build(cfg: &ModuleArgs, vb: VarBuilder, file: &str) -> Result<()> {
    let c = Compute::Plain;
    match cfg.kind() {
        ModuleKind::Dinov2 => drop(build_dinov2(cfg, vb, file, c)?),
        ModuleKind::SsFlow => drop(build_ss_flow(cfg, vb, file, c)?),
        ModuleKind::SsDecoder => drop(build_ss_decoder(cfg, vb, file, c)?),
        ModuleKind::SsEncoder => drop(build_ss_encoder(cfg, vb, file, c)?),
        ModuleKind::SlatFlow => drop(build_slat_flow(cfg, vb, file, c)?),
        ModuleKind::MeshDecoder => drop(build_mesh_decoder(cfg, vb, file, c)?),
        ModuleKind::GaussianDecoder => drop(build_gaussian_decoder(cfg, vb, file, c)?),
        ModuleKind::SlatEncoder => drop(build_slat_encoder(cfg, vb, file, c)?),
    }
    Ok(())
}

/// The expected (name, shape) list of a module, sorted by name.
pub fn expected_tensors(cfg: &ModuleArgs, file: &str) -> Result<Vec<TensorSpec>> {
    let r = Recorder::new();
    build(cfg, r.var_builder(DType::F32, &Device::Cpu), file)?;
    Ok(r.specs())
}

/// Deterministic random weights for a module (f32). Non-learned buffers that
/// checkpoints carry (`pos_emb` of the SS flow, `offset_perturbation` of the
/// Gaussian decoder) get their computed values, not noise.
///
/// One deliberate prior: the SS decoder's output bias (`out_layer.2.bias`) is
/// [`SS_DECODER_OCCUPANCY_PRIOR`] · σ below zero, where σ = 0.01·√(27·C) is
/// the logit std this init gives (weight std 0.02 × √fan-in × ≈½ for the
/// SiLU of a unit-variance LayerNorm output). With a zero bias about a third
/// of the grid is "occupied", which no trained decoder produces and which
/// makes stage 2 and the mesh needlessly big; with the prior a few hundred
/// voxels are, the sparse shell a real object gives.
pub fn random_weights(cfg: &ModuleArgs, seed: u64, file: &str) -> Result<BTreeMap<String, Tensor>> {
    let init = RandomInit::new(seed);
    build(cfg, init.var_builder(&Device::Cpu), file)?;
    let mut t = init.tensors();
    fill_buffers(cfg, &mut t, file)?;
    Ok(t)
}

/// Logit standard deviations below zero of the random-init SS decoder output
/// bias (see [`random_weights`]).
pub const SS_DECODER_OCCUPANCY_PRIOR: f64 = 2.0;

/// Replace random values of deterministic buffers by what upstream registers,
/// and set the random-init occupancy prior.
fn fill_buffers(cfg: &ModuleArgs, t: &mut BTreeMap<String, Tensor>, file: &str) -> Result<()> {
    for (name, v) in buffer_overrides(cfg)? {
        if let Some(old) = t.get(&name) {
            if old.dims() != v.dims() {
                return Err(Error::msg(format!("{file}: buffer `{name}` has shape {:?}, computed {:?}", old.dims(), v.dims())));
            }
            t.insert(name, v);
        }
    }
    Ok(())
}

/// Computed values of the module's deterministic buffers (see [`random_weights`]).
fn buffer_overrides(cfg: &ModuleArgs) -> Result<BTreeMap<String, Tensor>> {
    let dev = Device::Cpu;
    let mut t = BTreeMap::new();
    match cfg {
        ModuleArgs::SsFlow(c) => {
            let pe = SparseStructureFlowModel::grid_position_embedding(c.resolution / c.patch_size, c.model_channels, &dev)?;
            t.insert("pos_emb".into(), pe.to_dtype(DType::F32)?);
        }
        ModuleArgs::SsDecoder(c) => {
            let last = *c.channels.last().unwrap_or(&1) as f64;
            let sigma = 0.01 * (27.0 * last).sqrt();
            let prior = Tensor::full((-SS_DECODER_OCCUPANCY_PRIOR * sigma) as f32, c.out_channels, &dev)?;
            t.insert("out_layer.2.bias".into(), prior);
        }
        ModuleArgs::GaussianDecoder(c) => {
            let g = GaussianConfig::new(c);
            t.insert("offset_perturbation".into(), offset_perturbation(g.num_gaussians, g.voxel_size, &dev)?);
        }
        _ => {}
    }
    Ok(t)
}

/// A VarBuilder giving exactly the tensors of [`random_weights`], generated
/// one at a time when the module asks for them (nothing is kept).
pub fn random_var_builder(cfg: &ModuleArgs, seed: u64) -> Result<VarBuilder<'static>> {
    Ok(RandomStream::new(seed, buffer_overrides(cfg)?).var_builder(&Device::Cpu))
}

/// Per-module seed derived from a run seed and the module's key, so modules
/// with equal parameter names (`blocks.0.*`) do not get equal values. (Also
/// used with tensor names, hence `&str`; pass `key.name()` for a module.)
pub fn module_seed(seed: u64, key: &str) -> u64 {
    key.bytes()
        .fold(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xcbf2_9ce4_8422_2325, |h, b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::config::RecGenConfig;
    use crate::model::key::ModuleKey;

    /// The SLat mesh decoder on the random weights benchmarks and `Source::Random` use:
    /// its fused output layer gives the unfused result.
    #[test]
    fn slat_mesh_decoder_fused_output_layer_matches_unfused() -> Result<()> {
        let args = serde_json::json!({
            "resolution": 8, "model_channels": 256, "latent_channels": 8, "num_blocks": 1,
            "num_heads": 2, "mlp_ratio": 1, "window_size": 4, "representation_config": {"use_color": true}
        });
        let cfg = ModuleArgs::from_spec(&ModuleConfig { name: "SLatMeshDecoder".into(), args }, "slat_dec_mesh")?;
        let vb = random_var_builder(&cfg, 7)?;
        let dec = build_mesh_decoder(&cfg, vb, "slat_dec_mesh", Compute::Plain)?;
        let coords: Vec<[i32; 4]> = (0..20).map(|i| [0, 2 + i % 4, 3 + (i / 4) % 3, 1 + i / 12]).collect();
        let feats = Tensor::randn(0f32, 1.0, (coords.len(), 8), &Device::Cpu)?;
        let x = crate::model::sparse::SparseTensor::new(coords, feats, 1)?;
        let a = dec.forward_feats(&x, &mut |_, _| {})?;
        let b = dec.forward_feats_fused(&x)?;
        assert_eq!(a.coords, b.coords);
        assert_eq!(a.feats.dims(), &[20 * 64, 101]);
        let d = (a.feats - b.feats)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert!(d < 1e-5, "fused vs unfused {d}");
        Ok(())
    }

    #[test]
    fn slat_gaussian_decoder_splats_are_well_formed() -> Result<()> {
        let args = serde_json::json!({
            "resolution": 16, "model_channels": 32, "latent_channels": 8, "num_blocks": 2, "num_heads": 2,
            "window_size": 4, "representation_config": {
                "num_gaussians": 4, "perturb_offset": true, "voxel_size": 1.5, "lr": {"_rotation": 0.1},
                "3d_filter_kernel_size": 9e-4, "scaling_bias": 4e-3, "opacity_bias": 0.1, "scaling_activation": "softplus"
            }
        });
        let cfg = ModuleArgs::from_spec(&ModuleConfig { name: "SLatGaussianDecoder".into(), args }, "slat_dec_gs")?;
        let vb = random_var_builder(&cfg, 3)?;
        let dec = build_gaussian_decoder(&cfg, vb, "slat_dec_gs", Compute::Plain)?;
        let coords: Vec<[i32; 4]> = (0..10).map(|i| [i / 6, i % 5, 3, 15 - i]).collect();
        let x = crate::model::sparse::SparseTensor::new(coords.clone(), Tensor::randn(0f32, 1.0, (10, 8), &Device::Cpu)?, 2)?;
        let reps = dec.forward(&x)?;
        assert_eq!(reps.len(), 2);
        let g = reps[0].to_gaussians()?;
        g.validate()?;
        assert_eq!(g.len(), 6 * 4);
        for (i, p) in g.positions.iter().enumerate() {
            // Within 0.75 voxel of its voxel centre (tanh bound · voxel_size / 2).
            let c = coords[i / 4];
            for a in 0..3 {
                let centre = (c[a + 1] as f32 + 0.5) / 16.0 - 0.5;
                assert!((p[a] - centre).abs() <= 0.75 / 16.0 + 1e-6);
            }
        }
        assert!(g.rotations.iter().all(|q| (q.iter().map(|v| v * v).sum::<f32>() - 1.0).abs() < 1e-5));
        assert!(g.scales.iter().flatten().all(|&s| s >= 9e-4));
        assert!(g.opacities.iter().all(|&o| o > 0.0 && o < 1.0));
        Ok(())
    }

    /// Every module of the tiny architecture builds on the recorder and on
    /// random weights, norm weights are 1, and buffers are computed values.
    #[test]
    fn tiny_architecture_modules_are_registered() -> Result<()> {
        let path = std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("models/recgen-tiny.json");
        let arch = RecGenConfig::load(&path)?;
        for (key, _) in arch.modules() {
            let cfg = arch.module_args(key)?;
            let specs = expected_tensors(&cfg, key.name())?;
            assert!(!specs.is_empty(), "{key}");
            let w = random_weights(&cfg, 1, key.name())?;
            assert_eq!(w.len(), specs.len(), "{key}");
            for s in &specs {
                assert_eq!(w[&s.name].dims(), s.shape.as_slice(), "{key} {}", s.name);
            }
        }
        let w = random_weights(&arch.module_args(ModuleKey::SsFlow)?, 1, "ss")?;
        let want = SparseStructureFlowModel::grid_position_embedding(8, 64, &Device::Cpu)?;
        assert_eq!(crate::util::max_abs_diff(&w["pos_emb"], &want)?, 0.0);
        assert!(ModuleKind::of("NoSuchModel").is_none());
        // The streaming builder hands out the same tensors.
        for (key, _) in arch.modules() {
            let cfg = arch.module_args(key)?;
            let w = random_weights(&cfg, 3, key.name())?;
            let vb = random_var_builder(&cfg, 3)?;
            for s in expected_tensors(&cfg, key.name())? {
                let got = vb.get(s.shape.as_slice(), &s.name)?;
                assert_eq!(crate::util::max_abs_diff(&got, &w[&s.name])?, 0.0, "{key} {}", s.name);
            }
        }
        assert_ne!(module_seed(1, ModuleKey::SsFlow.name()), module_seed(1, ModuleKey::SlatFlow.name()));
        // A builder handed another kind's config says so.
        let e = build_ss_flow(
            &arch.module_args(ModuleKey::SsDecoder)?,
            Recorder::new().var_builder(DType::F32, &Device::Cpu),
            "x",
            Compute::Plain,
        );
        assert!(e.is_err_and(|e| e.to_string().contains("SsFlow")));
        Ok(())
    }
}
