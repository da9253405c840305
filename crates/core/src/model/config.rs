//! The architecture file (`models/recgen-*.json`): one section per module with
//! its upstream class `name` and constructor `args`, the samplers, the SLat
//! latent normalisation and the pose settings. [`RecGenConfig::load`] parses
//! it once: every module's `args` into its typed config ([`ModuleArgs`],
//! [`ArchArgs`]), which is what the modules are built from.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::geometry::pose::{NineDLayout, PoseRepresentation, PoseStats};
pub use crate::model::key::{ModuleKey, ModuleKind, KNOWN_MODULES};
use crate::model::sampler::SamplerSettings;
use crate::model::stage1::dinov2::Dinov2Config;
use crate::model::stage1::ss_flow::SsFlowConfig;
use crate::model::stage1::ss_vae::decoder::SparseStructureDecoderConfig;
use crate::model::stage1::ss_vae::encoder::SparseStructureEncoderConfig;
use crate::model::stage2::slat_flow::SLatFlowConfig;
use crate::model::stage2::slat_vae::encoder::SLatEncoderConfig;
use crate::model::stage2::slat_vae::gaussian::GaussianDecoderConfig;
use crate::model::stage2::slat_vae::mesh::MeshDecoderConfig;
use crate::{Error, Result};

/// One module section or module config file (`{"name": ClassName, "args":
/// {...}}`, the TRELLIS `ckpts/<name>.json` format), as written: the args
/// stay JSON so copies of the section (random-init folders, training run
/// settings) are written back unchanged. [`ModuleArgs::from_spec`] parses them.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModuleSpec {
    /// Upstream class name (e.g. `SparseStructureFlowModel`); selects the [`ModuleKind`].
    pub name: String,
    /// Constructor args, kept as JSON (null when the section has none).
    #[serde(default)]
    pub args: serde_json::Value,
}

impl ModuleSpec {
    /// Read a module config file.
    pub fn read(path: &Path) -> Result<Self> {
        crate::util::json::read_json(path)
    }

    /// The module family its class name names; `file` labels the error.
    pub fn kind(&self, file: &str) -> Result<ModuleKind> {
        ModuleKind::of(&self.name).ok_or_else(|| {
            let hint = if self.args.is_null() {
                "; an architecture file (models/recgen-*.json) holds several modules: its sections are module configs"
            } else {
                ""
            };
            Error::config(file, "name", format!("module `{}` is not available in this build (known: {KNOWN_MODULES:?}){hint}", self.name))
        })
    }
}

/// A module's constructor args, parsed into the typed config of its kind.
#[derive(Debug, Clone)]
pub enum ModuleArgs {
    /// DINOv2 image encoder args.
    Dinov2(Dinov2Config),
    /// Sparse-structure (stage-1) flow transformer args.
    SsFlow(SsFlowConfig),
    /// SS VAE decoder args.
    SsDecoder(SparseStructureDecoderConfig),
    /// SS VAE encoder args (training only).
    SsEncoder(SparseStructureEncoderConfig),
    /// Structured-latent (stage-2) flow transformer args.
    SlatFlow(SLatFlowConfig),
    /// SLat VAE mesh decoder args.
    MeshDecoder(MeshDecoderConfig),
    /// SLat VAE Gaussian decoder args.
    GaussianDecoder(GaussianDecoderConfig),
    /// SLat VAE encoder args (training only).
    SlatEncoder(SLatEncoderConfig),
}

/// `ModuleArgs::$fn(&self, file) -> Result<&$ty>`: the typed config when the
/// args are of that kind, else an error naming `file`.
macro_rules! typed_getter {
    ($($fn:ident: $variant:ident => $ty:ty),* $(,)?) => {
        $(
            /// The typed config when the args are of this kind, else an error naming `file`.
            pub fn $fn(&self, file: &str) -> Result<&$ty> {
                match self {
                    Self::$variant(c) => Ok(c),
                    other => Err(Error::config(
                        file,
                        "name",
                        format!("a {:?} module was expected, the config names a {:?} module", ModuleKind::$variant, other.kind()),
                    )),
                }
            }
        )*
    };
}

impl ModuleArgs {
    /// Parse `spec.args` as the config of the class `spec.name` names;
    /// errors name `file` and the field.
    pub fn from_spec(spec: &ModuleSpec, file: &str) -> Result<Self> {
        let a = &spec.args;
        Ok(match spec.kind(file)? {
            ModuleKind::Dinov2 => Self::Dinov2(Dinov2Config::from_json(a, file)?),
            ModuleKind::SsFlow => Self::SsFlow(SsFlowConfig::from_json(a, file)?),
            ModuleKind::SsDecoder => Self::SsDecoder(SparseStructureDecoderConfig::from_json(a, file)?),
            ModuleKind::SsEncoder => Self::SsEncoder(SparseStructureEncoderConfig::from_json(a, file)?),
            ModuleKind::SlatFlow => Self::SlatFlow(SLatFlowConfig::from_json(a, file)?),
            ModuleKind::MeshDecoder => Self::MeshDecoder(MeshDecoderConfig::from_json(a, file)?),
            ModuleKind::GaussianDecoder => Self::GaussianDecoder(GaussianDecoderConfig::from_json(a, file)?),
            ModuleKind::SlatEncoder => Self::SlatEncoder(SLatEncoderConfig::from_json(a, file)?),
        })
    }

    /// The module family these args belong to.
    pub fn kind(&self) -> ModuleKind {
        match self {
            Self::Dinov2(_) => ModuleKind::Dinov2,
            Self::SsFlow(_) => ModuleKind::SsFlow,
            Self::SsDecoder(_) => ModuleKind::SsDecoder,
            Self::SsEncoder(_) => ModuleKind::SsEncoder,
            Self::SlatFlow(_) => ModuleKind::SlatFlow,
            Self::MeshDecoder(_) => ModuleKind::MeshDecoder,
            Self::GaussianDecoder(_) => ModuleKind::GaussianDecoder,
            Self::SlatEncoder(_) => ModuleKind::SlatEncoder,
        }
    }

    typed_getter! {
        dinov2: Dinov2 => Dinov2Config,
        ss_flow: SsFlow => SsFlowConfig,
        ss_decoder: SsDecoder => SparseStructureDecoderConfig,
        ss_encoder: SsEncoder => SparseStructureEncoderConfig,
        slat_flow: SlatFlow => SLatFlowConfig,
        mesh_decoder: MeshDecoder => MeshDecoderConfig,
        gaussian_decoder: GaussianDecoder => GaussianDecoderConfig,
        slat_encoder: SlatEncoder => SLatEncoderConfig,
    }
}

/// Every module section of an architecture file, parsed.
#[derive(Debug, Clone)]
pub struct ArchArgs {
    /// `image_cond_model`: the DINOv2 image encoder.
    pub image_cond_model: Dinov2Config,
    /// `ss_flow`: the sparse-structure flow transformer.
    pub ss_flow: SsFlowConfig,
    /// `ss_decoder`: the SS VAE decoder.
    pub ss_decoder: SparseStructureDecoderConfig,
    /// `slat_flow`: the structured-latent flow transformer.
    pub slat_flow: SLatFlowConfig,
    /// `slat_dec_mesh`: the SLat VAE mesh decoder.
    pub slat_dec_mesh: MeshDecoderConfig,
    /// `slat_dec_gs`: the SLat VAE Gaussian decoder.
    pub slat_dec_gs: GaussianDecoderConfig,
    /// `ss_encoder`: the SS VAE encoder (training only; None when the file lacks it).
    pub ss_encoder: Option<SparseStructureEncoderConfig>,
    /// `slat_encoder`: the SLat VAE encoder (training only; None when the file lacks it).
    pub slat_encoder: Option<SLatEncoderConfig>,
}

impl ArchArgs {
    /// The args of module `key` (None: an optional encoder the file lacks).
    pub fn get(&self, key: ModuleKey) -> Option<ModuleArgs> {
        Some(match key {
            ModuleKey::ImageCondModel => ModuleArgs::Dinov2(self.image_cond_model.clone()),
            ModuleKey::SsFlow => ModuleArgs::SsFlow(self.ss_flow.clone()),
            ModuleKey::SsDecoder => ModuleArgs::SsDecoder(self.ss_decoder.clone()),
            ModuleKey::SlatFlow => ModuleArgs::SlatFlow(self.slat_flow.clone()),
            ModuleKey::SlatDecMesh => ModuleArgs::MeshDecoder(self.slat_dec_mesh.clone()),
            ModuleKey::SlatDecGs => ModuleArgs::GaussianDecoder(self.slat_dec_gs.clone()),
            ModuleKey::SsEncoder => ModuleArgs::SsEncoder(self.ss_encoder.clone()?),
            ModuleKey::SlatEncoder => ModuleArgs::SlatEncoder(self.slat_encoder.clone()?),
        })
    }
}

/// The `samplers` section: one sampler setting per flow.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SamplerSpecs {
    /// Stage-1 (sparse-structure flow) sampler.
    pub sparse_structure: SamplerSettings,
    /// Stage-2 (structured-latent flow) sampler.
    pub slat: SamplerSettings,
}

/// Per-channel mean/std of the SLat latent (`slat = x·std + mean` after sampling).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SlatNormalization {
    /// Per-channel mean, one per SLat latent channel.
    pub mean: Vec<f32>,
    /// Per-channel standard deviation (positive), one per SLat latent channel.
    pub std: Vec<f32>,
}

/// The `pose` section: pose representations and z-score stats of both stages.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PoseSpec {
    /// Pose representation of the stage-1 pose tokens (must match `ss_flow.args.pose_representation`).
    pub ss_representation: PoseRepresentation,
    /// Pose representation of the stage-2 pose condition (must match `slat_flow.args.pose_representation`).
    pub slat_representation: PoseRepresentation,
    /// Stage-1 z-score stats file, relative to the config file's folder.
    pub ss_stats: String,
    /// Stage-2 z-score stats file, relative to the config file's folder.
    pub slat_stats: String,
    /// `pipeline_columns` (released pipeline) or `row_major` (training data).
    pub nine_d_layout: NineDLayout,
}

/// The file as written (module args still JSON).
#[derive(Deserialize)]
struct RecGenFile {
    pub name: String,
    pub image_cond_model: ModuleSpec,
    pub ss_flow: ModuleSpec,
    pub ss_decoder: ModuleSpec,
    pub slat_flow: ModuleSpec,
    pub slat_dec_mesh: ModuleSpec,
    pub slat_dec_gs: ModuleSpec,
    /// SS VAE encoder: only training needs it (`recon train ss-vae`), so it
    /// is optional and not one of [`Self::modules`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ss_encoder: Option<ModuleSpec>,
    /// SLat VAE encoder: only training needs it (`recon train slat-ae`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slat_encoder: Option<ModuleSpec>,
    pub samplers: SamplerSpecs,
    pub slat_normalization: SlatNormalization,
    pub pose: PoseSpec,
}

/// A parsed and validated architecture file (`models/recgen-*.json`).
#[derive(Debug, Clone, Serialize)]
pub struct RecGenConfig {
    /// Architecture name (e.g. `recgen-tiny`).
    pub name: String,
    /// DINOv2 image encoder section.
    pub image_cond_model: ModuleSpec,
    /// Sparse-structure flow transformer section.
    pub ss_flow: ModuleSpec,
    /// SS VAE decoder section.
    pub ss_decoder: ModuleSpec,
    /// Structured-latent flow transformer section.
    pub slat_flow: ModuleSpec,
    /// SLat VAE mesh decoder section.
    pub slat_dec_mesh: ModuleSpec,
    /// SLat VAE Gaussian decoder section.
    pub slat_dec_gs: ModuleSpec,
    /// SS VAE encoder: only training needs it (`recon train ss-vae`), so it
    /// is optional and not one of [`Self::modules`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ss_encoder: Option<ModuleSpec>,
    /// SLat VAE encoder: only training needs it (`recon train slat-ae`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slat_encoder: Option<ModuleSpec>,
    /// Sampler settings of both flows.
    pub samplers: SamplerSpecs,
    /// Per-channel SLat latent normalisation.
    pub slat_normalization: SlatNormalization,
    /// Pose representations and stats files.
    pub pose: PoseSpec,
    /// Folder of the file, for resolving relative paths (not serialised).
    #[serde(skip)]
    pub base_dir: PathBuf,
    /// The module sections' args, parsed once (not serialised: the
    /// sections above are the file's form).
    #[serde(skip)]
    pub args: ArchArgs,
}

impl RecGenConfig {
    /// Read, parse and validate a config file.
    pub fn load(path: &Path) -> Result<Self> {
        let v: serde_json::Value = crate::util::json::read_json(path)?;
        let mut cfg = Self::from_json(&v, &path.display().to_string())?;
        cfg.base_dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Ok(cfg)
    }

    /// Parse and validate an architecture file's JSON (`file` labels errors;
    /// relative paths resolve against the current folder until `base_dir` is
    /// set). Every module section is parsed here, once.
    pub fn from_json(v: &serde_json::Value, file: &str) -> Result<Self> {
        let f: RecGenFile = crate::util::json::from_value(v, file)?;
        // Before any module is parsed or built: an architecture that cannot
        // fit this machine is refused with the part that does not fit.
        if let Some(budget) = crate::util::memory_budget_bytes() {
            let (need, what) =
                min_memory_bytes(&f.image_cond_model, &f.ss_flow, &f.ss_decoder, [&f.slat_flow, &f.slat_dec_mesh, &f.slat_dec_gs]);
            if need > budget as u128 {
                return Err(Error::too_large(
                    file,
                    what,
                    need,
                    budget as u128,
                    "bytes of memory",
                    "a lower bound of one stage's memory vs this machine's (RECON_MEMORY_LIMIT_MB caps it)",
                ));
            }
        }
        // A JSON array would parse positionally into a struct: refuse it.
        for (key, spec) in [
            (ModuleKey::ImageCondModel, Some(&f.image_cond_model)),
            (ModuleKey::SsFlow, Some(&f.ss_flow)),
            (ModuleKey::SsDecoder, Some(&f.ss_decoder)),
            (ModuleKey::SlatFlow, Some(&f.slat_flow)),
            (ModuleKey::SlatDecMesh, Some(&f.slat_dec_mesh)),
            (ModuleKey::SlatDecGs, Some(&f.slat_dec_gs)),
            (ModuleKey::SsEncoder, f.ss_encoder.as_ref()),
            (ModuleKey::SlatEncoder, f.slat_encoder.as_ref()),
        ] {
            if spec.is_some_and(|s| !s.args.is_object()) {
                return Err(Error::config(file, format!("{key}.args"), "must be an object"));
            }
        }
        let parse = |key: ModuleKey, spec: &ModuleSpec| -> Result<ModuleArgs> {
            let label = format!("{file}: {key}");
            // The kind first: a section naming another kind of module is refused as such,
            // not by the first field its args lack.
            let kind = spec.kind(&label)?;
            if kind != key.kind() {
                return Err(Error::config(
                    label,
                    "name",
                    format!("`{}` is a {:?} module; this section needs a {:?} module", spec.name, kind, key.kind()),
                ));
            }
            ModuleArgs::from_spec(spec, &label)
        };
        // `parse` checked the kind, so each getter finds its variant.
        let label = |key: ModuleKey| format!("{file}: {key}");
        let k = ModuleKey::ImageCondModel;
        let image_cond_model = parse(k, &f.image_cond_model)?.dinov2(&label(k))?.clone();
        let k = ModuleKey::SsFlow;
        let ss_flow = parse(k, &f.ss_flow)?.ss_flow(&label(k))?.clone();
        let k = ModuleKey::SsDecoder;
        let ss_decoder = parse(k, &f.ss_decoder)?.ss_decoder(&label(k))?.clone();
        let k = ModuleKey::SlatFlow;
        let slat_flow = parse(k, &f.slat_flow)?.slat_flow(&label(k))?.clone();
        let k = ModuleKey::SlatDecMesh;
        let slat_dec_mesh = parse(k, &f.slat_dec_mesh)?.mesh_decoder(&label(k))?.clone();
        let k = ModuleKey::SlatDecGs;
        let slat_dec_gs = parse(k, &f.slat_dec_gs)?.gaussian_decoder(&label(k))?.clone();
        let k = ModuleKey::SsEncoder;
        let ss_encoder = f.ss_encoder.as_ref().map(|s| parse(k, s)?.ss_encoder(&label(k)).cloned()).transpose()?;
        let k = ModuleKey::SlatEncoder;
        let slat_encoder = f.slat_encoder.as_ref().map(|s| parse(k, s)?.slat_encoder(&label(k)).cloned()).transpose()?;
        let args = ArchArgs { image_cond_model, ss_flow, ss_decoder, slat_flow, slat_dec_mesh, slat_dec_gs, ss_encoder, slat_encoder };
        let cfg = Self {
            name: f.name,
            image_cond_model: f.image_cond_model,
            ss_flow: f.ss_flow,
            ss_decoder: f.ss_decoder,
            slat_flow: f.slat_flow,
            slat_dec_mesh: f.slat_dec_mesh,
            slat_dec_gs: f.slat_dec_gs,
            ss_encoder: f.ss_encoder,
            slat_encoder: f.slat_encoder,
            samplers: f.samplers,
            slat_normalization: f.slat_normalization,
            pose: f.pose,
            base_dir: PathBuf::new(),
            args,
        };
        cfg.validate(file)?;
        Ok(cfg)
    }

    /// The section of module `key` (None: an optional encoder the file lacks).
    pub fn module(&self, key: ModuleKey) -> Option<&ModuleSpec> {
        match key {
            ModuleKey::ImageCondModel => Some(&self.image_cond_model),
            ModuleKey::SsFlow => Some(&self.ss_flow),
            ModuleKey::SsDecoder => Some(&self.ss_decoder),
            ModuleKey::SlatFlow => Some(&self.slat_flow),
            ModuleKey::SlatDecMesh => Some(&self.slat_dec_mesh),
            ModuleKey::SlatDecGs => Some(&self.slat_dec_gs),
            ModuleKey::SsEncoder => self.ss_encoder.as_ref(),
            ModuleKey::SlatEncoder => self.slat_encoder.as_ref(),
        }
    }

    /// The parsed args of module `key`, or an error naming the missing section.
    pub fn module_args(&self, key: ModuleKey) -> Result<ModuleArgs> {
        self.args.get(key).ok_or_else(|| Error::config(&self.name, key.name(), "missing: this architecture has no such section"))
    }

    /// Every inference module section as `(key, spec)`, in pipeline order
    /// ([`ModuleKey::ALL`]). The keys name the per-module weight files
    /// (`<key>.safetensors`).
    pub fn modules(&self) -> Vec<(ModuleKey, &ModuleSpec)> {
        ModuleKey::ALL.into_iter().filter_map(|k| Some((k, self.module(k)?))).collect()
    }

    /// The stage-1 flow model config.
    pub fn ss_flow_config(&self) -> &SsFlowConfig {
        &self.args.ss_flow
    }

    /// Load the stage-1 pose z-score stats (`pose.ss_stats`, relative to [`Self::base_dir`]).
    pub fn ss_pose_stats(&self) -> Result<PoseStats> {
        PoseStats::from_json_file(&self.base_dir.join(&self.pose.ss_stats))
    }

    /// Load the stage-2 pose z-score stats (`pose.slat_stats`, relative to [`Self::base_dir`]).
    pub fn slat_pose_stats(&self) -> Result<PoseStats> {
        PoseStats::from_json_file(&self.base_dir.join(&self.pose.slat_stats))
    }

    /// A lower bound of the peak memory running this architecture takes, in
    /// bytes, with the part that sets it (see [`min_memory_bytes`]).
    pub fn min_memory_bytes(&self) -> (u128, String) {
        min_memory_bytes(&self.image_cond_model, &self.ss_flow, &self.ss_decoder, [&self.slat_flow, &self.slat_dec_mesh, &self.slat_dec_gs])
    }

    /// Checks across sections (each section's own were made when it was parsed).
    fn validate(&self, file: &str) -> Result<()> {
        let a = &self.args;
        let ss = &a.ss_flow;
        if ss.pose_representation != Some(self.pose.ss_representation) {
            return Err(Error::config(file, "pose.ss_representation", "must match ss_flow.args.pose_representation"));
        }
        if a.slat_flow.pose_representation != self.pose.slat_representation {
            return Err(Error::config(file, "pose.slat_representation", "must match slat_flow.args.pose_representation"));
        }
        self.samplers.sparse_structure.validate(file)?;
        self.samplers.slat.validate(file)?;
        let n = &self.slat_normalization;
        if n.mean.len() != n.std.len() || n.std.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(Error::config(file, "slat_normalization", "mean and std need equal lengths and positive std"));
        }
        if a.ss_decoder.latent_channels != ss.out_channels {
            return Err(Error::config(file, "ss_decoder.args.latent_channels", "must equal ss_flow out_channels"));
        }
        if let Some(e) = &a.ss_encoder {
            if e.latent_channels != a.ss_decoder.latent_channels {
                return Err(Error::config(file, "ss_encoder.args.latent_channels", "must equal ss_decoder latent_channels"));
            }
            if a.ss_decoder.channels.len() != e.channels.len() {
                return Err(Error::config(
                    file,
                    "ss_encoder.args.channels",
                    "needs as many levels as ss_decoder.args.channels (the encoder must downsample as much as the decoder upsamples)",
                ));
            }
        }
        if a.image_cond_model.embed_dim != ss.cond_channels {
            return Err(Error::config(file, "image_cond_model.args.hidden_size", "must equal ss_flow cond_channels"));
        }
        Ok(())
    }
}

/// Read from the raw sections, before any of them is parsed: the check must
/// refuse absurd sizes before anything allocates for them.
/// A lower bound of the peak memory running this architecture takes, in
/// bytes, with the part that sets it: the largest of any module's
/// weights (at 2 bytes a parameter, counting only the attention and MLP
/// matrices) and any dense grid of activations (f32; the stage-1 flow's
/// tokens, DINOv2's patch tokens, each level of the stage-1 decoder). All
/// in saturating u128 arithmetic, so absurd sizes cannot overflow.
fn min_memory_bytes(dino: &ModuleSpec, ss: &ModuleSpec, ss_decoder: &ModuleSpec, stage2: [&ModuleSpec; 3]) -> (u128, String) {
    let arg = |m: &ModuleSpec, k: &str| m.args.get(k).and_then(|v| v.as_u64()).unwrap_or(0) as u128;
    let ratio = |m: &ModuleSpec| {
        m.args.get("mlp_ratio").and_then(|v| v.as_f64()).filter(|r| r.is_finite()).unwrap_or(1.0).clamp(0.0, 1e6).ceil() as u128
    };
    let mut best = (0u128, String::new());
    let mut consider = |bytes: u128, what: String| {
        if bytes > best.0 {
            best = (bytes, what);
        }
    };
    let weights = |m: &ModuleSpec, c: &str, b: &str| {
        let c = arg(m, c);
        arg(m, b).saturating_mul(4 + 2 * ratio(m)).saturating_mul(c.saturating_mul(c)).saturating_mul(2)
    };
    let [slat_flow, slat_dec_mesh, slat_dec_gs] = stage2;
    for (key, m) in [
        (ModuleKey::SsFlow, ss),
        (ModuleKey::SlatFlow, slat_flow),
        (ModuleKey::SlatDecMesh, slat_dec_mesh),
        (ModuleKey::SlatDecGs, slat_dec_gs),
    ] {
        consider(weights(m, "model_channels", "num_blocks"), format!("{key} weights (args.model_channels, args.num_blocks)"));
    }
    consider(
        weights(dino, "hidden_size", "num_hidden_layers"),
        "image_cond_model weights (args.hidden_size, args.num_hidden_layers)".into(),
    );
    let side = arg(dino, "image_size") / arg(dino, "patch_size").max(1);
    let tokens = side.saturating_mul(side);
    consider(
        tokens.saturating_mul(arg(dino, "hidden_size")).saturating_mul(1 + ratio(dino)).saturating_mul(4),
        "image_cond_model tokens (args.image_size / args.patch_size)²".into(),
    );
    let res = arg(ss, "resolution");
    let side = res / arg(ss, "patch_size").max(1);
    let tokens = side.saturating_mul(side).saturating_mul(side);
    consider(
        tokens.saturating_mul(arg(ss, "model_channels")).saturating_mul(1 + ratio(ss)).saturating_mul(4),
        "ss_flow dense tokens (args.resolution / args.patch_size)³".into(),
    );
    if let Some(chs) = ss_decoder.args.get("channels").and_then(|v| v.as_array()) {
        for (i, c) in chs.iter().enumerate() {
            let r = res.saturating_mul(1u128.checked_shl(i as u32).unwrap_or(u128::MAX));
            let c = c.as_u64().unwrap_or(0) as u128;
            consider(
                r.saturating_mul(r).saturating_mul(r).saturating_mul(c).saturating_mul(4),
                format!("ss_decoder grid at level {i} (ss_flow.args.resolution · 2^{i})³ × ss_decoder.args.channels[{i}]"),
            );
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    fn models_dir() -> PathBuf {
        crate::util::testing::repo().join("models")
    }

    #[test]
    fn shipped_configs_parse() -> Result<()> {
        for (file, c, blocks) in [("recgen-large.json", 1024, 24), ("recgen-tiny.json", 64, 2), ("recgen-nano.json", 128, 8)] {
            let cfg = RecGenConfig::load(&models_dir().join(file))?;
            let ss = cfg.ss_flow_config();
            assert_eq!((ss.model_channels, ss.num_blocks), (c, blocks), "{file}");
            assert_eq!(ss.num_pose_tokens, 2);
            assert_eq!(ss.pose_channels(), Some(10));
            assert!(ss.embedders.use_point_embedder && ss.embedders.use_mask_embedder && ss.use_frame_token_embedder);
            assert_eq!(cfg.slat_normalization.mean.len(), 8);
            assert_eq!(cfg.pose.nine_d_layout, NineDLayout::PipelineColumns);
            cfg.ss_pose_stats()?;
            cfg.slat_pose_stats()?;
            // Both flows read the embedder settings through one struct.
            assert_eq!(cfg.args.ss_flow.embedders, cfg.args.slat_flow.embedders, "{file}");
            assert_eq!(cfg.args.ss_flow.embedders.point_embedder_out_channels, c, "{file}");
            // Module sections keep the upstream arg names.
            assert!(cfg.slat_flow.args.get("io_block_channels").is_some());
            assert!(cfg.slat_dec_mesh.args.get("representation_config").is_some());
        }
        // Only the nano config carries the (training-only) SS VAE encoder.
        let nano = RecGenConfig::load(&models_dir().join("recgen-nano.json"))?;
        assert!(nano.ss_encoder.is_some() && !nano.modules().iter().any(|(k, _)| *k == ModuleKey::SsEncoder));
        assert!(nano.args.ss_encoder.is_some() && nano.module_args(ModuleKey::SlatEncoder).is_ok());
        assert_eq!(nano.modules().iter().map(|(k, _)| *k).collect::<Vec<_>>(), ModuleKey::ALL);
        let large = RecGenConfig::load(&models_dir().join("recgen-large.json"))?;
        assert_eq!(large.samplers.sparse_structure.steps, 25);
        assert_eq!(large.ss_flow_config().heads(), 16);
        assert!(large.module_args(ModuleKey::SsEncoder).is_err());
        Ok(())
    }

    #[test]
    fn architecture_beyond_the_machine_is_refused() {
        let large = RecGenConfig::load(&models_dir().join("recgen-large.json")).unwrap();
        let (need, _) = large.min_memory_bytes();
        // The full model fits this 24 GiB machine: its largest part (a flow's
        // weights at 2 bytes a parameter) is about 0.6 GB.
        assert!(need > 500_000_000 && need < 2_000_000_000, "{need}");
        let mut v: serde_json::Value = crate::util::json::read_json(&models_dir().join("recgen-tiny.json")).unwrap();
        v["ss_flow"]["args"]["resolution"] = 100_000.into();
        let dir = crate::util::testing::tmp("cfg-big");
        let p = dir.join("big.json");
        std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
        let e = RecGenConfig::load(&p).unwrap_err();
        match &e {
            Error::TooLarge(b) => {
                assert!(b.field.contains("ss_flow.args.resolution"), "{e}");
                assert!(b.claimed > b.limit, "{e}");
            }
            other => panic!("expected TooLarge, got {other}"),
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn inconsistent_config_is_rejected() {
        let mut v: serde_json::Value = crate::util::json::read_json(&models_dir().join("recgen-tiny.json")).unwrap();
        v["pose"]["ss_representation"] = "9d_translation_scale".into();
        let dir = crate::util::testing::tmp("cfg-bad");
        let p = dir.join("bad.json");
        std::fs::write(&p, serde_json::to_string(&v).unwrap()).unwrap();
        assert!(RecGenConfig::load(&p).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Errors from parsing a section name the file, the section and the
    /// field; a section naming another kind of module, or an unknown class,
    /// is refused with what was expected.
    #[test]
    fn bad_sections_are_named() {
        let tiny: serde_json::Value = crate::util::json::read_json(&models_dir().join("recgen-tiny.json")).unwrap();
        let err = |edit: &dyn Fn(&mut serde_json::Value)| {
            let mut v = tiny.clone();
            edit(&mut v);
            RecGenConfig::from_json(&v, "arch.json").unwrap_err().to_string()
        };
        let e = err(&|v| v["slat_dec_mesh"]["args"]["model_channels"] = "wide".into());
        assert!(e.contains("arch.json") && e.contains("slat_dec_mesh") && e.contains("model_channels"), "{e}");
        let e = err(&|v| v["slat_dec_gs"]["args"]["representation_config"]["scaling_activation"] = "relu".into());
        assert!(e.contains("slat_dec_gs") && e.contains("representation_config.scaling_activation"), "{e}");
        let e = err(&|v| {
            v["slat_flow"]["args"].as_object_mut().unwrap().remove("model_channels");
        });
        assert!(e.contains("slat_flow") && e.contains("model_channels"), "{e}");
        let e = err(&|v| v["ss_decoder"]["name"] = "SLatMeshDecoder".into());
        assert!(e.contains("ss_decoder") && e.contains("SsDecoder") && e.contains("MeshDecoder"), "{e}");
        let e = err(&|v| v["ss_flow"]["name"] = "NoSuchFlow".into());
        assert!(e.contains("NoSuchFlow") && e.contains("SparseStructureFlowModel"), "{e}");
        let e = err(&|v| v["image_cond_model"]["args"] = serde_json::json!([1, 2]));
        assert!(e.contains("image_cond_model.args") && e.contains("object"), "{e}");
        // Unknown keys are ignored, as before.
        let mut v = tiny.clone();
        v["slat_dec_mesh"]["args"]["some_future_flag"] = true.into();
        assert!(RecGenConfig::from_json(&v, "arch.json").is_ok());
    }
}
