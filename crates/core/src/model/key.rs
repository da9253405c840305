//! The modules of the model by key (the section names of the architecture
//! file and the stems of the per-module weight files, `<key>.safetensors`)
//! and by kind (the upstream class a section names).

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::Error;

/// One module of the model. [`ModuleKey::name`] is the checkpoint/file name.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum ModuleKey {
    /// `image_cond_model`: the DINOv2 image encoder.
    ImageCondModel,
    /// `ss_flow`: the sparse-structure flow transformer.
    SsFlow,
    /// `ss_decoder`: the SS VAE decoder.
    SsDecoder,
    /// `slat_flow`: the structured-latent flow transformer.
    SlatFlow,
    /// `slat_dec_mesh`: the SLat VAE mesh decoder.
    SlatDecMesh,
    /// `slat_dec_gs`: the SLat VAE Gaussian decoder.
    SlatDecGs,
    /// SS VAE encoder: training only (`recon train ss-vae`).
    SsEncoder,
    /// SLat VAE encoder: training only (`recon train slat-ae`).
    SlatEncoder,
}

impl ModuleKey {
    /// The six modules inference runs, in pipeline order.
    pub const ALL: [ModuleKey; 6] =
        [Self::ImageCondModel, Self::SsFlow, Self::SsDecoder, Self::SlatFlow, Self::SlatDecMesh, Self::SlatDecGs];
    /// The stage-1 modules (all a sparse-structure-only pipeline builds).
    pub const STAGE1: [ModuleKey; 3] = [Self::ImageCondModel, Self::SsFlow, Self::SsDecoder];
    /// The encoders only training needs.
    pub const TRAINING_ONLY: [ModuleKey; 2] = [Self::SsEncoder, Self::SlatEncoder];
    /// Every key a file may use: [`Self::ALL`] then [`Self::TRAINING_ONLY`].
    pub const EVERY: [ModuleKey; 8] = [
        Self::ImageCondModel,
        Self::SsFlow,
        Self::SsDecoder,
        Self::SlatFlow,
        Self::SlatDecMesh,
        Self::SlatDecGs,
        Self::SsEncoder,
        Self::SlatEncoder,
    ];

    /// Section name in the architecture file and weight file stem.
    pub const fn name(self) -> &'static str {
        match self {
            Self::ImageCondModel => "image_cond_model",
            Self::SsFlow => "ss_flow",
            Self::SsDecoder => "ss_decoder",
            Self::SlatFlow => "slat_flow",
            Self::SlatDecMesh => "slat_dec_mesh",
            Self::SlatDecGs => "slat_dec_gs",
            Self::SsEncoder => "ss_encoder",
            Self::SlatEncoder => "slat_encoder",
        }
    }

    /// Whether a sparse-structure-only pipeline builds this module.
    pub fn is_stage1(self) -> bool {
        Self::STAGE1.contains(&self)
    }
}

/// Module families, by upstream class name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModuleKind {
    /// DINOv2 image encoder (`DinoVisionTransformer`, `dinov2_*`).
    Dinov2,
    /// Sparse-structure flow (`SparseStructureFlowModel`, `SparseStructurePoseFlowModel`).
    SsFlow,
    /// SS VAE decoder (`SparseStructureDecoder`).
    SsDecoder,
    /// SS VAE encoder (`SparseStructureEncoder`).
    SsEncoder,
    /// Structured-latent flow (`SLatFlowModel`, `SLatCondFlowModel` and their `Elastic*` forms).
    SlatFlow,
    /// SLat VAE mesh decoder (`SLatMeshDecoder`, `ElasticSLatMeshDecoder`).
    MeshDecoder,
    /// SLat VAE Gaussian decoder (`SLatGaussianDecoder`, `ElasticSLatGaussianDecoder`).
    GaussianDecoder,
    /// SLat VAE encoder (`SLatEncoder`, `ElasticSLatEncoder`).
    SlatEncoder,
}

/// Class names [`ModuleKind::of`] knows (upstream class names; `dinov2_*` hub
/// names are accepted for the image encoder as the architecture file uses them).
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
    "ElasticSLatEncoder",
];

impl ModuleKind {
    /// The kind an upstream class name names, or None for an unknown class.
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

impl ModuleKey {
    /// The kind of module this key's section must name.
    pub fn kind(self) -> ModuleKind {
        match self {
            Self::ImageCondModel => ModuleKind::Dinov2,
            Self::SsFlow => ModuleKind::SsFlow,
            Self::SsDecoder => ModuleKind::SsDecoder,
            Self::SlatFlow => ModuleKind::SlatFlow,
            Self::SlatDecMesh => ModuleKind::MeshDecoder,
            Self::SlatDecGs => ModuleKind::GaussianDecoder,
            Self::SsEncoder => ModuleKind::SsEncoder,
            Self::SlatEncoder => ModuleKind::SlatEncoder,
        }
    }
}

impl fmt::Display for ModuleKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for ModuleKey {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self, Error> {
        Self::EVERY.into_iter().find(|k| k.name() == s).ok_or_else(|| {
            let valid: Vec<&str> = Self::EVERY.iter().map(|k| k.name()).collect();
            Error::input(s, format!("unknown module key; valid keys: {}", valid.join(", ")))
        })
    }
}

impl Serialize for ModuleKey {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for ModuleKey {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let s = String::deserialize(d)?;
        s.parse().map_err(serde::de::Error::custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_key_round_trips_through_its_name() {
        for k in ModuleKey::EVERY {
            assert_eq!(k.name().parse::<ModuleKey>().unwrap(), k);
            assert_eq!(k.to_string(), k.name());
            let j = serde_json::to_string(&k).unwrap();
            assert_eq!(j, format!("\"{}\"", k.name()));
            assert_eq!(serde_json::from_str::<ModuleKey>(&j).unwrap(), k);
        }
        // ALL and TRAINING_ONLY partition EVERY, in its order.
        let joined: Vec<ModuleKey> = ModuleKey::ALL.iter().chain(&ModuleKey::TRAINING_ONLY).copied().collect();
        assert_eq!(joined, ModuleKey::EVERY);
        assert!(ModuleKey::STAGE1.iter().all(|k| ModuleKey::ALL.contains(k)));
    }

    #[test]
    fn unknown_key_names_the_valid_ones() {
        let e = "ss_flw".parse::<ModuleKey>().unwrap_err().to_string();
        assert!(e.contains("ss_flw"), "{e}");
        for k in ModuleKey::EVERY {
            assert!(e.contains(k.name()), "{e} lacks {k}");
        }
        let e = serde_json::from_str::<ModuleKey>("\"dino\"").unwrap_err().to_string();
        assert!(e.contains("image_cond_model") && e.contains("slat_encoder"), "{e}");
    }
}
