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

use crate::model::nn::fast::Compute;
use crate::model::stage1::dinov2::{Dinov2, Dinov2Config};
use crate::model::stage1::ss_flow::{SparseStructureFlowModel, SsFlowConfig};
use crate::model::stage1::ss_vae::decoder::{SparseStructureDecoder, SparseStructureDecoderConfig};
use crate::model::stage1::ss_vae::encoder::{SparseStructureEncoder, SparseStructureEncoderConfig};
use crate::model::stage2::slat_flow::{SLatFlowConfig, SLatFlowModel};
use crate::model::stage2::slat_vae::gaussian::{offset_perturbation, GaussianConfig, SLatGaussianDecoder};
use crate::model::stage2::slat_vae::mesh::SLatMeshDecoder;
use crate::weights::record::{RandomInit, RandomStream, Recorder, TensorSpec};
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
        crate::util::json::read_json(path)
    }
}

/// Names accepted by [`build`] (upstream class names; `dinov2_*` hub names
/// are accepted for the image encoder as the architecture file uses them).
pub const KNOWN_MODULES: &[&str] = &[
    "DinoVisionTransformer",
    "SparseStructureFlowModel",
    "SparseStructurePoseFlowModel",
    "SparseStructureDecoder",
    "SparseStructureEncoder",
    "SLatFlowModel",
    "ElasticSLatFlowModel",
    "SLatCondFlowModel",
    "ElasticSLatCondFlowModel",
    "SLatMeshDecoder",
    "ElasticSLatMeshDecoder",
    "SLatGaussianDecoder",
    "ElasticSLatGaussianDecoder",
    "SLatEncoder",
];

/// Module families, by class name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModuleKind {
    Dinov2,
    SsFlow,
    SsDecoder,
    SsEncoder,
    SlatFlow,
    MeshDecoder,
    GaussianDecoder,
    SlatEncoder,
}

impl ModuleKind {
    pub fn of(name: &str) -> Option<Self> {
        Some(match name {
            "DinoVisionTransformer" | "Dinov2" => Self::Dinov2,
            n if n.starts_with("dinov2_") => Self::Dinov2,
            "SparseStructureFlowModel" | "SparseStructurePoseFlowModel" => Self::SsFlow,
            "SparseStructureDecoder" => Self::SsDecoder,
            "SparseStructureEncoder" => Self::SsEncoder,
            "SLatFlowModel" | "ElasticSLatFlowModel" | "SLatCondFlowModel" | "ElasticSLatCondFlowModel" => Self::SlatFlow,
            "SLatMeshDecoder" | "ElasticSLatMeshDecoder" => Self::MeshDecoder,
            "SLatGaussianDecoder" | "ElasticSLatGaussianDecoder" => Self::GaussianDecoder,
            "SLatEncoder" | "ElasticSLatEncoder" => Self::SlatEncoder,
            _ => return None,
        })
    }
}

fn kind(cfg: &ModuleConfig, file: &str) -> Result<ModuleKind> {
    ModuleKind::of(&cfg.name).ok_or_else(|| {
        let hint = if cfg.args.is_null() {
            "; an architecture file (models/recgen-*.json) holds several modules: its sections are module configs"
        } else {
            ""
        };
        Error::config(file, "name", format!("module `{}` is not available in this build (known: {KNOWN_MODULES:?}){hint}", cfg.name))
    })
}

/// DINOv2 args in either form: hub (`embed_dim`, `depth`, ...) or HF
/// (`hidden_size`, `num_hidden_layers`, ..., as in the architecture file).
pub fn dinov2_config(args: &serde_json::Value, file: &str) -> Result<Dinov2Config> {
    if args.get("hidden_size").is_some() {
        return Dinov2Config::from_hf_config(args, file);
    }
    let c: Dinov2Config = crate::util::json::from_value(args, file)?;
    c.validate(file)?;
    Ok(c)
}

pub fn build_dinov2(cfg: &ModuleConfig, vb: VarBuilder, file: &str, compute: Compute) -> Result<Dinov2> {
    Ok(Dinov2::new(&dinov2_config(&cfg.args, file)?, vb, compute)?)
}

pub fn build_ss_flow(cfg: &ModuleConfig, vb: VarBuilder, file: &str, compute: Compute) -> Result<SparseStructureFlowModel> {
    SparseStructureFlowModel::new(&SsFlowConfig::from_value(&cfg.args, file)?, vb, compute)
}

pub fn build_ss_decoder(cfg: &ModuleConfig, vb: VarBuilder, _file: &str, compute: Compute) -> Result<SparseStructureDecoder> {
    SparseStructureDecoder::new(&SparseStructureDecoderConfig::from_json(&cfg.args)?, vb, compute)
}

pub fn build_ss_encoder(cfg: &ModuleConfig, vb: VarBuilder, _file: &str, compute: Compute) -> Result<SparseStructureEncoder> {
    SparseStructureEncoder::new(&SparseStructureEncoderConfig::from_json(&cfg.args)?, vb, compute)
}

pub fn build_slat_flow(cfg: &ModuleConfig, vb: VarBuilder, _file: &str, compute: Compute) -> Result<SLatFlowModel> {
    SLatFlowModel::new(&SLatFlowConfig::from_json(&cfg.args)?, vb, compute)
}

pub fn build_mesh_decoder(cfg: &ModuleConfig, vb: VarBuilder, _file: &str, compute: Compute) -> Result<SLatMeshDecoder> {
    SLatMeshDecoder::new(&cfg.args, vb, compute)
}

pub fn build_slat_encoder(
    cfg: &ModuleConfig,
    vb: VarBuilder,
    _file: &str,
    compute: Compute,
) -> Result<crate::model::stage2::slat_vae::encoder::SLatEncoder> {
    crate::model::stage2::slat_vae::encoder::SLatEncoder::new(&cfg.args, vb, compute)
}

pub fn build_gaussian_decoder(cfg: &ModuleConfig, vb: VarBuilder, _file: &str, compute: Compute) -> Result<SLatGaussianDecoder> {
    SLatGaussianDecoder::new(&cfg.args, vb, compute)
}

/// Build module `cfg.name` from `cfg.args` on `vb` (the module is dropped;
/// the point is what the builder requests from `vb`, the same on every
/// compute path, so it is built plain).
pub fn build(cfg: &ModuleConfig, vb: VarBuilder, file: &str) -> Result<()> {
    match kind(cfg, file)? {
        ModuleKind::Dinov2 => drop(build_dinov2(cfg, vb, file, Compute::Plain)?),
        ModuleKind::SsFlow => drop(build_ss_flow(cfg, vb, file, Compute::Plain)?),
        ModuleKind::SsDecoder => drop(build_ss_decoder(cfg, vb, file, Compute::Plain)?),
        ModuleKind::SsEncoder => drop(build_ss_encoder(cfg, vb, file, Compute::Plain)?),
        ModuleKind::SlatFlow => drop(build_slat_flow(cfg, vb, file, Compute::Plain)?),
        ModuleKind::MeshDecoder => drop(build_mesh_decoder(cfg, vb, file, Compute::Plain)?),
        ModuleKind::GaussianDecoder => drop(build_gaussian_decoder(cfg, vb, file, Compute::Plain)?),
        ModuleKind::SlatEncoder => drop(build_slat_encoder(cfg, vb, file, Compute::Plain)?),
    }
    Ok(())
}

/// The expected (name, shape) list of a module, sorted by name.
pub fn expected_tensors(cfg: &ModuleConfig, file: &str) -> Result<Vec<TensorSpec>> {
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
/// SiLU of a unit-variance LayerNorm output; measured 0.15 for recgen-tiny).
/// With a zero bias about a third of the grid is "occupied", which no
/// trained decoder produces and which makes stage 2 and the mesh needlessly
/// big; with the prior a few hundred voxels are (123 of 32³ for
/// recgen-tiny, seed 0), the sparse shell a real object gives.
pub fn random_weights(cfg: &ModuleConfig, seed: u64, file: &str) -> Result<BTreeMap<String, Tensor>> {
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
fn fill_buffers(cfg: &ModuleConfig, t: &mut BTreeMap<String, Tensor>, file: &str) -> Result<()> {
    for (name, v) in buffer_overrides(cfg, file)? {
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
fn buffer_overrides(cfg: &ModuleConfig, file: &str) -> Result<BTreeMap<String, Tensor>> {
    let dev = Device::Cpu;
    let mut t = BTreeMap::new();
    match kind(cfg, file)? {
        ModuleKind::SsFlow => {
            let c = SsFlowConfig::from_value(&cfg.args, file)?;
            let pe = SparseStructureFlowModel::grid_position_embedding(c.resolution / c.patch_size, c.model_channels, &dev)?;
            t.insert("pos_emb".into(), pe.to_dtype(DType::F32)?);
        }
        ModuleKind::SsDecoder => {
            let c = SparseStructureDecoderConfig::from_json(&cfg.args)?;
            let last = *c.channels.last().unwrap_or(&1) as f64;
            let sigma = 0.01 * (27.0 * last).sqrt();
            let prior = Tensor::full((-SS_DECODER_OCCUPANCY_PRIOR * sigma) as f32, c.out_channels, &dev)?;
            t.insert("out_layer.2.bias".into(), prior);
        }
        ModuleKind::GaussianDecoder => {
            let g = GaussianConfig::from_args(&cfg.args)?;
            t.insert("offset_perturbation".into(), offset_perturbation(g.num_gaussians, g.voxel_size, &dev)?);
        }
        _ => {}
    }
    Ok(t)
}

/// A VarBuilder giving exactly the tensors of [`random_weights`], generated
/// one at a time when the module asks for them (nothing is kept).
pub fn random_var_builder(cfg: &ModuleConfig, seed: u64, file: &str) -> Result<VarBuilder<'static>> {
    Ok(RandomStream::new(seed, buffer_overrides(cfg, file)?).var_builder(&Device::Cpu))
}

/// Per-module seed derived from a run seed and the module's key, so modules
/// with equal parameter names (`blocks.0.*`) do not get equal values.
pub fn module_seed(seed: u64, key: &str) -> u64 {
    key.bytes()
        .fold(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xcbf2_9ce4_8422_2325, |h, b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::config::RecGenConfig;

    /// The SLat mesh decoder on the random weights benchmarks and `Source::Random` use:
    /// its fused output layer gives the unfused result.
    #[test]
    fn slat_mesh_decoder_fused_output_layer_matches_unfused() -> Result<()> {
        let args = serde_json::json!({
            "resolution": 8, "model_channels": 256, "latent_channels": 8, "num_blocks": 1,
            "num_heads": 2, "mlp_ratio": 1, "window_size": 4, "representation_config": {"use_color": true}
        });
        let vb = random_var_builder(&ModuleConfig { name: "SLatMeshDecoder".into(), args: args.clone() }, 7, "slat_dec_mesh")?;
        let dec = SLatMeshDecoder::new(&args, vb, Compute::Plain)?;
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
        let vb = random_var_builder(&ModuleConfig { name: "SLatGaussianDecoder".into(), args: args.clone() }, 3, "slat_dec_gs")?;
        let dec = SLatGaussianDecoder::new(&args, vb, Compute::Plain)?;
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
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("models/recgen-tiny.json");
        let arch = RecGenConfig::load(&path)?;
        for (key, spec) in arch.modules() {
            let cfg = ModuleConfig { name: spec.name.clone(), args: spec.args.clone() };
            let specs = expected_tensors(&cfg, key)?;
            assert!(!specs.is_empty(), "{key}");
            let w = random_weights(&cfg, 1, key)?;
            assert_eq!(w.len(), specs.len(), "{key}");
            for s in &specs {
                assert_eq!(w[&s.name].dims(), s.shape.as_slice(), "{key} {}", s.name);
            }
        }
        let ss = arch.modules().into_iter().find(|(k, _)| *k == "ss_flow").unwrap().1;
        let w = random_weights(&ModuleConfig { name: ss.name.clone(), args: ss.args.clone() }, 1, "ss")?;
        let want = SparseStructureFlowModel::grid_position_embedding(8, 64, &Device::Cpu)?;
        assert_eq!(crate::util::max_abs_diff(&w["pos_emb"], &want)?, 0.0);
        assert!(ModuleKind::of("NoSuchModel").is_none());
        // The streaming builder hands out the same tensors.
        for (key, spec) in arch.modules() {
            let cfg = ModuleConfig { name: spec.name.clone(), args: spec.args.clone() };
            let w = random_weights(&cfg, 3, key)?;
            let vb = random_var_builder(&cfg, 3, key)?;
            for s in expected_tensors(&cfg, key)? {
                let got = vb.get(s.shape.as_slice(), &s.name)?;
                assert_eq!(crate::util::max_abs_diff(&got, &w[&s.name])?, 0.0, "{key} {}", s.name);
            }
        }
        assert_ne!(module_seed(1, "ss_flow"), module_seed(1, "slat_flow"));
        Ok(())
    }
}
