//! Trainable parameters of one module: a candle `VarMap` (so every model is
//! built unchanged from `VarBuilder::from_varmap`) plus the name-sorted list
//! of its variables, the order everything order-sensitive (gradient norm,
//! checkpoints) uses, because `VarMap` iterates a `HashMap`.
//!
//! Initialisation for training from scratch follows the upstream schemes by
//! parameter name (TRELLIS `initialize_weights`, DINOv2 `init_weights`,
//! PyTorch layer defaults), drawn from [`SeededRng`] seeded per name, so the
//! same seed gives the same network whatever order modules ask for tensors.

use std::collections::BTreeMap;

use candle_core::{DType, Device, Tensor, Var};
use candle_nn::{VarBuilder, VarMap};

use recon_core::model::config::{ModuleArgs, ModuleKey};
use recon_core::model::stage1::ss_flow::SparseStructureFlowModel;
use recon_core::rng::SeededRng;
use recon_core::weights::registry::{self, ModuleConfig, ModuleKind};
use recon_core::{Error, Result};

/// How one parameter starts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Init {
    Const(f32),
    Normal(f32),
}

/// The trainable parameters of one module.
pub struct ModuleParams {
    /// Module key, used in file names.
    pub key: ModuleKey,
    /// The section as written (recorded in run settings).
    pub config: ModuleConfig,
    /// Its args, parsed (what the module is built from).
    pub args: ModuleArgs,
    /// The variables, as candle's `VarBuilder` reads them.
    pub varmap: VarMap,
    /// `(name, var)` sorted by name.
    pub vars: Vec<(String, Var)>,
}

impl ModuleParams {
    /// Fresh parameters for `config` (module kind from its class name).
    pub fn init(key: ModuleKey, config: &ModuleConfig, seed: u64) -> Result<Self> {
        let args = ModuleArgs::from_spec(config, key.name())?;
        let kind = args.kind();
        let specs = registry::expected_tensors(&args, key.name())?;
        let varmap = VarMap::new();
        {
            let mut data = varmap.data().lock().map_err(|_| Error::msg("varmap poisoned"))?;
            for s in specs {
                if is_buffer(kind, &s.name) {
                    continue;
                }
                let rule = init_rule(kind, &s.name, &s.shape, &config.args);
                let n: usize = s.shape.iter().product();
                let vals = match rule {
                    Init::Const(c) => vec![c; n],
                    Init::Normal(std) => {
                        let mut rng = SeededRng::new(registry::module_seed(seed, &s.name));
                        (0..n).map(|_| rng.normal() as f32 * std).collect()
                    }
                };
                let t = Tensor::from_vec(vals, s.shape.as_slice(), &Device::Cpu)?;
                data.insert(s.name.clone(), Var::from_tensor(&t)?);
            }
        }
        Self::from_varmap(key, config, args, varmap)
    }

    /// Parameters from stored tensors (a checkpoint); buffers are ignored,
    /// every trainable tensor the config implies must be present.
    pub fn from_tensors(key: ModuleKey, config: &ModuleConfig, tensors: &BTreeMap<String, Tensor>, file: &str) -> Result<Self> {
        let args = ModuleArgs::from_spec(config, key.name())?;
        let kind = args.kind();
        let varmap = VarMap::new();
        {
            let mut data = varmap.data().lock().map_err(|_| Error::msg("varmap poisoned"))?;
            for s in registry::expected_tensors(&args, key.name())? {
                if is_buffer(kind, &s.name) {
                    continue;
                }
                let t = tensors.get(&s.name).ok_or_else(|| Error::MissingTensor {
                    file: file.to_string(),
                    name: s.name.clone(),
                    expected: s.shape.clone(),
                })?;
                if t.dims() != s.shape.as_slice() {
                    return Err(Error::ShapeMismatch {
                        file: file.to_string(),
                        name: s.name.clone(),
                        found: t.dims().to_vec(),
                        expected: s.shape.clone(),
                    });
                }
                data.insert(s.name.clone(), Var::from_tensor(&t.to_dtype(DType::F32)?.to_device(&Device::Cpu)?)?);
            }
        }
        Self::from_varmap(key, config, args, varmap)
    }

    fn from_varmap(key: ModuleKey, config: &ModuleConfig, args: ModuleArgs, varmap: VarMap) -> Result<Self> {
        let mut vars: Vec<(String, Var)> =
            varmap.data().lock().map_err(|_| Error::msg("varmap poisoned"))?.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        Ok(Self { key, config: config.clone(), args, varmap, vars })
    }

    /// A VarBuilder handing out these variables (build the model on it).
    pub fn var_builder(&self) -> VarBuilder<'static> {
        VarBuilder::from_varmap(&self.varmap, DType::F32, &Device::Cpu)
    }

    /// Number of scalar parameters.
    pub fn num_params(&self) -> usize {
        self.vars.iter().map(|(_, v)| v.elem_count()).sum()
    }

    /// Current values plus the module's computed buffers: exactly the tensor
    /// set `Pipeline::load` / `recon weights verify` expect for this module.
    pub fn export(&self) -> Result<BTreeMap<String, Tensor>> {
        // `copy`: the optimizer later overwrites the variables' storage in place.
        let mut out = BTreeMap::new();
        for (k, v) in &self.vars {
            out.insert(k.clone(), v.as_tensor().copy()?.detach());
        }
        for s in registry::expected_tensors(&self.args, self.key.name())? {
            if out.contains_key(&s.name) {
                continue;
            }
            let t = buffer_value(&s.name, &self.args, self.key.name())?;
            out.insert(s.name.clone(), t);
        }
        Ok(out)
    }
}

/// Tensors upstream registers as buffers (computed, never trained).
fn is_buffer(kind: ModuleKind, name: &str) -> bool {
    matches!((kind, name), (ModuleKind::SsFlow, "pos_emb") | (ModuleKind::GaussianDecoder, "offset_perturbation"))
}

fn buffer_value(name: &str, cfg: &ModuleArgs, file: &str) -> Result<Tensor> {
    match (cfg, name) {
        (ModuleArgs::SsFlow(c), "pos_emb") => {
            SparseStructureFlowModel::grid_position_embedding(c.resolution / c.patch_size, c.model_channels, &Device::Cpu)
        }
        (ModuleArgs::GaussianDecoder(c), "offset_perturbation") => {
            let g = recon_core::model::stage2::slat_vae::gaussian::GaussianConfig::new(c);
            recon_core::model::stage2::slat_vae::gaussian::offset_perturbation(g.num_gaussians, g.voxel_size, &Device::Cpu)
        }
        _ => Err(Error::msg(format!("{file}: tensor `{name}` is neither trained nor a known buffer"))),
    }
}

fn fan_in(shape: &[usize]) -> usize {
    shape.iter().skip(1).product::<usize>().max(1)
}

/// The initial distribution of parameter `name` of a module of `kind`.
pub fn init_rule(kind: ModuleKind, name: &str, shape: &[usize], args: &serde_json::Value) -> Init {
    let last = name.rsplit('.').next().unwrap_or(name);
    let parent = name.rsplit('.').nth(1).unwrap_or("");
    if last == "bias" {
        return Init::Const(0.0);
    }
    // Norm scales (LayerNorm / ChannelLayerNorm weights, QK RMS-norm gamma).
    if shape.len() == 1 && last == "weight" || last == "gamma" && !parent.starts_with("ls") {
        return Init::Const(1.0);
    }
    match kind {
        ModuleKind::Dinov2 => match last {
            // DINOv2 `init_weights`: cls N(0, 1e-6), registers N(0, 1e-6),
            // pos_embed trunc-normal 0.02, mask token zeros, LayerScale = init value.
            "cls_token" | "register_tokens" => Init::Normal(1e-6),
            "mask_token" => Init::Const(0.0),
            "gamma" => Init::Const(args.get("layerscale_value").and_then(|v| v.as_f64()).unwrap_or(1.0) as f32),
            _ if name.starts_with("patch_embed") => Init::Normal((1.0 / (3.0 * fan_in(shape) as f64)).sqrt() as f32),
            _ => Init::Normal(0.02),
        },
        ModuleKind::SsFlow | ModuleKind::SlatFlow => {
            // TRELLIS `initialize_weights`: xavier for every Linear, N(0, 0.02)
            // for the timestep MLP, zeros for adaLN modulation and the output
            // layers (so the untrained model predicts zero velocity).
            if name.contains("adaLN_modulation") || name == "out_layer.weight" || name == "out_layer_pose.weight" {
                Init::Const(0.0)
            } else if name.starts_with("t_embedder") || matches!(last, "pose_token_embedder" | "frame_token_embedder") {
                Init::Normal(0.02)
            } else if shape.len() == 2 {
                Init::Normal((2.0 / (shape[0] + shape[1]) as f64).sqrt() as f32)
            } else {
                // Conv patch embedders: PyTorch's default (std 1/√(3·fan_in)).
                Init::Normal((1.0 / (3.0 * fan_in(shape) as f64)).sqrt() as f32)
            }
        }
        // Small output layer: the decoded SDF starts near the −1/R bias (a
        // unit-scale output would be an object-sized distance).
        ModuleKind::MeshDecoder if name == "out_layer.weight" => Init::Normal(1e-3),
        _ => {
            // Conv nets (SS VAE): PyTorch default; ResBlock conv2 is `zero_module` upstream.
            if parent == "conv2" {
                Init::Const(0.0)
            } else if shape.len() == 2 {
                Init::Normal((2.0 / (shape[0] + shape[1]) as f64).sqrt() as f32)
            } else {
                Init::Normal((1.0 / (3.0 * fan_in(shape) as f64)).sqrt() as f32)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn init_is_seeded_by_name_and_follows_rules() -> Result<()> {
        let path = recon_testkit::repo().join("models/recgen-tiny.json");
        let arch = recon_core::model::config::RecGenConfig::load(&path)?;
        let cfg = arch.ss_flow.clone();
        let a = ModuleParams::init(ModuleKey::SsFlow, &cfg, 3)?;
        let b = ModuleParams::init(ModuleKey::SsFlow, &cfg, 3)?;
        let c = ModuleParams::init(ModuleKey::SsFlow, &cfg, 4)?;
        let get = |p: &ModuleParams, n: &str| {
            p.vars.iter().find(|(k, _)| k == n).unwrap().1.as_tensor().flatten_all().unwrap().to_vec1::<f32>().unwrap()
        };
        let w = "blocks.0.self_attn.to_qkv.weight";
        assert_eq!(get(&a, w), get(&b, w));
        assert_ne!(get(&a, w), get(&c, w));
        assert!(get(&a, "blocks.0.adaLN_modulation.1.weight").iter().all(|&v| v == 0.0));
        assert!(get(&a, "out_layer.weight").iter().all(|&v| v == 0.0));
        assert!(get(&a, "blocks.0.norm2.weight").iter().all(|&v| v == 1.0));
        // xavier std for a [192, 64] matrix: √(2/256) ≈ 0.088.
        let v = get(&a, w);
        let std = (v.iter().map(|x| x * x).sum::<f32>() / v.len() as f32).sqrt();
        assert!((std - (2.0f32 / 256.0).sqrt()).abs() < 0.01, "std {std}");
        // The position embedding is a buffer: not trained, exported computed.
        assert!(a.vars.iter().all(|(k, _)| k != "pos_emb"));
        let ex = a.export()?;
        let want = SparseStructureFlowModel::grid_position_embedding(8, 64, &Device::Cpu)?;
        assert_eq!(recon_core::util::max_abs_diff(&ex["pos_emb"], &want)?, 0.0);
        let expected = registry::expected_tensors(&arch.module_args(ModuleKey::SsFlow)?, "ss_flow")?;
        assert_eq!(ex.len(), expected.len());
        // Names are sorted.
        assert!(a.vars.windows(2).all(|w| w[0].0 < w[1].0));
        // Round trip through exported tensors.
        let r = ModuleParams::from_tensors(ModuleKey::SsFlow, &cfg, &ex, "mem")?;
        assert_eq!(get(&r, w), get(&a, w));
        let mut broken = ex.clone();
        broken.remove(w);
        assert!(matches!(ModuleParams::from_tensors(ModuleKey::SsFlow, &cfg, &broken, "mem"), Err(Error::MissingTensor { .. })));
        Ok(())
    }
}
