//! Structured-latent encoder (TRELLIS `SLatEncoder`): the sparse transformer
//! trunk of the decoders on per-voxel input features, then a plain
//! LayerNorm and a linear to the posterior's mean and log-variance.
//!
//! Upstream encodes DINOv2 features projected onto the voxels; recon's nano
//! model is trained on synthetic objects whose geometry is known exactly, so
//! its input features are local signed distances and surface colours
//! (`train::slat`). Only training needs the encoder.

use candle_core::{Module, Tensor};
use candle_nn::VarBuilder;

use crate::model::nn::common::{layer_norm_plain, linear, Linear};
use crate::model::nn::fast::Compute;
use crate::model::sparse::SparseTensor;
use crate::model::stage2::slat_vae::trunk::{SparseTransformerBase, TrunkArgs, TrunkConfig};
use crate::Result;
use serde::{Deserialize, Serialize};

/// Constructor args of `SLatEncoder` (checkpoint `args`): the trunk's plus
/// `in_channels` (the per-voxel input features).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SLatEncoderConfig {
    /// The trunk's args (flattened).
    #[serde(flatten)]
    pub trunk: TrunkArgs,
    /// Width of the per-voxel input features (upstream `in_channels`).
    pub in_channels: usize,
}

impl SLatEncoderConfig {
    /// Parse the encoder's `args`; errors name `file` and the field.
    pub fn from_json(v: &serde_json::Value, file: &str) -> Result<Self> {
        crate::model::stage2::slat_vae::trunk::from_json_with_trunk(v, file)
    }
}

/// The structured-latent encoder (TRELLIS `SLatEncoder`).
pub struct SLatEncoder {
    /// The sparse transformer trunk.
    pub trunk: SparseTransformerBase,
    out_layer: Linear,
    /// Latent channels per voxel.
    pub latent_channels: usize,
}

/// The posterior of each voxel's latent.
pub struct SLatPosterior {
    /// Mean `[N, latent_channels]`.
    pub mean: Tensor,
    /// Log-variance `[N, latent_channels]`, clamped to [-30, 20].
    pub logvar: Tensor,
}

impl SLatEncoder {
    /// Built from its config (upstream's `args`).
    pub fn new(args: &SLatEncoderConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let mut tcfg = TrunkConfig::new(&args.trunk)?;
        let latent_channels = tcfg.in_channels;
        tcfg.in_channels = args.in_channels;
        let trunk = SparseTransformerBase::new(&tcfg, vb.clone(), compute)?;
        let out_layer = linear(tcfg.model_channels, 2 * latent_channels, vb.pp("out_layer"), compute)?;
        Ok(Self { trunk, out_layer, latent_channels })
    }

    /// The posterior of each voxel's latent, for input voxels `x` (feats `[N, in_channels]`).
    pub fn forward(&self, x: &SparseTensor) -> Result<SLatPosterior> {
        let h = layer_norm_plain(&self.trunk.forward(x)?, 1e-5)?;
        let h = self.out_layer.forward(&h)?;
        let c = self.latent_channels;
        Ok(SLatPosterior { mean: h.narrow(1, 0, c)?, logvar: h.narrow(1, c, c)?.clamp(-30.0, 20.0)? })
    }
}
