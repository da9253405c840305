//! The architecture file (`models/recgen-*.json`): one section per module with
//! its upstream class `name` and constructor `args` (kept as JSON so each
//! module's own config deserialiser reads it), the samplers, the SLat latent
//! normalisation and the pose settings.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::geometry::pose::{NineDLayout, PoseRepresentation, PoseStats};
use crate::model::sampler::SamplerSettings;
use crate::model::stage1::ss_flow::SsFlowConfig;
use crate::model::stage2::slat_flow::SLatFlowConfig;
use crate::{Error, Result};

/// One module: upstream class name plus constructor args.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModuleSpec {
    pub name: String,
    pub args: serde_json::Value,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SamplerSpecs {
    pub sparse_structure: SamplerSettings,
    pub slat: SamplerSettings,
}

/// Per-channel mean/std of the SLat latent (`slat = x·std + mean` after sampling).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SlatNormalization {
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PoseSpec {
    pub ss_representation: PoseRepresentation,
    pub slat_representation: PoseRepresentation,
    /// Stage-1 z-score stats file, relative to the config file's folder.
    pub ss_stats: String,
    /// Stage-2 z-score stats file, relative to the config file's folder.
    pub slat_stats: String,
    /// `pipeline_columns` (released pipeline) or `row_major` (training data).
    pub nine_d_layout: NineDLayout,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RecGenConfig {
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
    /// Folder of the file, for resolving relative paths (not serialised).
    #[serde(skip)]
    pub base_dir: PathBuf,
}

impl RecGenConfig {
    /// Read and validate a config file.
    pub fn load(path: &Path) -> Result<Self> {
        let mut cfg: Self = crate::util::json::read_json(path)?;
        cfg.base_dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        cfg.validate(&path.display().to_string())?;
        Ok(cfg)
    }

    /// Every module section as `(key, spec)`, in pipeline order. The keys
    /// name the per-module weight files (`<key>.safetensors`).
    pub fn modules(&self) -> Vec<(&'static str, &ModuleSpec)> {
        vec![
            ("image_cond_model", &self.image_cond_model),
            ("ss_flow", &self.ss_flow),
            ("ss_decoder", &self.ss_decoder),
            ("slat_flow", &self.slat_flow),
            ("slat_dec_mesh", &self.slat_dec_mesh),
            ("slat_dec_gs", &self.slat_dec_gs),
        ]
    }

    /// The stage-1 flow model config.
    pub fn ss_flow_config(&self) -> Result<SsFlowConfig> {
        SsFlowConfig::from_value(&self.ss_flow.args, "ss_flow.args")
    }

    pub fn ss_pose_stats(&self) -> Result<PoseStats> {
        PoseStats::from_json_file(&self.base_dir.join(&self.pose.ss_stats))
    }

    pub fn slat_pose_stats(&self) -> Result<PoseStats> {
        PoseStats::from_json_file(&self.base_dir.join(&self.pose.slat_stats))
    }

    /// A lower bound of the peak memory running this architecture takes, in
    /// bytes, with the part that sets it: the largest of any module's
    /// weights (at 2 bytes a parameter, counting only the attention and MLP
    /// matrices) and any dense grid of activations (f32; the stage-1 flow's
    /// tokens, DINOv2's patch tokens, each level of the stage-1 decoder). All
    /// in saturating u128 arithmetic, so absurd sizes cannot overflow.
    pub fn min_memory_bytes(&self) -> (u128, String) {
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
        for (key, m) in [
            ("ss_flow", &self.ss_flow),
            ("slat_flow", &self.slat_flow),
            ("slat_dec_mesh", &self.slat_dec_mesh),
            ("slat_dec_gs", &self.slat_dec_gs),
        ] {
            consider(weights(m, "model_channels", "num_blocks"), format!("{key} weights (args.model_channels, args.num_blocks)"));
        }
        let dino = &self.image_cond_model;
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
        let ss = &self.ss_flow;
        let res = arg(ss, "resolution");
        let side = res / arg(ss, "patch_size").max(1);
        let tokens = side.saturating_mul(side).saturating_mul(side);
        consider(
            tokens.saturating_mul(arg(ss, "model_channels")).saturating_mul(1 + ratio(ss)).saturating_mul(4),
            "ss_flow dense tokens (args.resolution / args.patch_size)³".into(),
        );
        if let Some(chs) = self.ss_decoder.args.get("channels").and_then(|v| v.as_array()) {
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

    fn validate(&self, file: &str) -> Result<()> {
        // Before any module is parsed or built: an architecture that cannot
        // fit this machine is refused with the part that does not fit.
        if let Some(budget) = crate::util::memory_budget_bytes() {
            let (need, what) = self.min_memory_bytes();
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
        let ss = SsFlowConfig::from_value(&self.ss_flow.args, file)?;
        if ss.pose_representation != Some(self.pose.ss_representation) {
            return Err(Error::config(file, "pose.ss_representation", "must match ss_flow.args.pose_representation"));
        }
        let slat = SLatFlowConfig::from_json(&self.slat_flow.args)?;
        if slat.pose_representation != self.pose.slat_representation {
            return Err(Error::config(file, "pose.slat_representation", "must match slat_flow.args.pose_representation"));
        }
        self.samplers.sparse_structure.validate(file)?;
        self.samplers.slat.validate(file)?;
        let n = &self.slat_normalization;
        if n.mean.len() != n.std.len() || n.std.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(Error::config(file, "slat_normalization", "mean and std need equal lengths and positive std"));
        }
        for (key, spec) in [
            ("image_cond_model", &self.image_cond_model),
            ("ss_decoder", &self.ss_decoder),
            ("slat_flow", &self.slat_flow),
            ("slat_dec_mesh", &self.slat_dec_mesh),
            ("slat_dec_gs", &self.slat_dec_gs),
        ] {
            if !spec.args.is_object() {
                return Err(Error::config(file, format!("{key}.args"), "must be an object"));
            }
        }
        let lat = self.ss_decoder.args.get("latent_channels").and_then(|v| v.as_u64());
        if lat != Some(ss.out_channels as u64) {
            return Err(Error::config(file, "ss_decoder.args.latent_channels", "must equal ss_flow out_channels"));
        }
        if let Some(enc) = &self.ss_encoder {
            let e = crate::model::stage1::ss_vae::encoder::SparseStructureEncoderConfig::from_json(&enc.args)?;
            if Some(e.latent_channels as u64) != lat {
                return Err(Error::config(file, "ss_encoder.args.latent_channels", "must equal ss_decoder latent_channels"));
            }
            let dec_up = self.ss_decoder.args.get("channels").and_then(|v| v.as_array()).map(|a| a.len());
            if dec_up != Some(e.channels.len()) {
                return Err(Error::config(
                    file,
                    "ss_encoder.args.channels",
                    "needs as many levels as ss_decoder.args.channels (the encoder must downsample as much as the decoder upsamples)",
                ));
            }
        }
        let dino = self.image_cond_model.args.get("hidden_size").and_then(|v| v.as_u64());
        if dino != Some(ss.cond_channels as u64) {
            return Err(Error::config(file, "image_cond_model.args.hidden_size", "must equal ss_flow cond_channels"));
        }
        Ok(())
    }
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
            let ss = cfg.ss_flow_config()?;
            assert_eq!((ss.model_channels, ss.num_blocks), (c, blocks), "{file}");
            assert_eq!(ss.num_pose_tokens, 2);
            assert_eq!(ss.pose_channels(), Some(10));
            assert!(ss.embedders.use_point_embedder && ss.embedders.use_mask_embedder && ss.use_frame_token_embedder);
            assert_eq!(cfg.slat_normalization.mean.len(), 8);
            assert_eq!(cfg.pose.nine_d_layout, NineDLayout::PipelineColumns);
            cfg.ss_pose_stats()?;
            cfg.slat_pose_stats()?;
            // Module sections keep the upstream arg names.
            assert!(cfg.slat_flow.args.get("io_block_channels").is_some());
            assert!(cfg.slat_dec_mesh.args.get("representation_config").is_some());
        }
        // Only the nano config carries the (training-only) SS VAE encoder.
        let nano = RecGenConfig::load(&models_dir().join("recgen-nano.json"))?;
        assert!(nano.ss_encoder.is_some() && !nano.modules().iter().any(|(k, _)| *k == "ss_encoder"));
        let large = RecGenConfig::load(&models_dir().join("recgen-large.json"))?;
        assert_eq!(large.samplers.sparse_structure.steps, 25);
        assert_eq!(large.ss_flow_config()?.heads(), 16);
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
}
