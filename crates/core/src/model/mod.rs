//! The networks, in the order data passes through them.
//!
//! - `nn`: shared layers (linear, norms, attention, feed-forward, dense 3D
//!   convolutions) and the fast inference path;
//! - `sparse`: sparse voxel tensors, sparse convolution and attention;
//! - `sampler`: the rectified-flow Euler sampler with classifier-free
//!   guidance, generic over [`sampler::VelocityModel`];
//! - `stage1`: image conditioning (DINOv2 + point-map/mask embedders), the
//!   sparse-structure flow with pose tokens, and the SS VAE;
//! - `stage2`: the structured-latent flow and the SLat VAE (encoder, mesh
//!   and Gaussian decoders, FlexiCubes);
//! - `key`: the modules by key (`ss_flow`, ...) and by kind (class);
//! - `config`: the architecture file that names every module.

pub mod config;
pub mod key;
pub mod nn;
pub mod sampler;
pub mod sparse;
pub mod stage1;
pub mod stage2;
pub use self::config::{ArchArgs, ModuleArgs, ModuleSpec, RecGenConfig};
pub use self::key::{ModuleKey, ModuleKind};
pub use self::nn::common::layer_norm_plain;
pub use self::nn::common::PeMode;
pub use self::nn::common::PreparedCondition;
pub use self::nn::dense3d::{ChannelLayerNorm, Conv3d, NormType};
pub use self::nn::fast::{Compute, Precision};
pub use self::sampler::{
    FlowEulerGuidanceIntervalSampler, FnVelocity, PrepareCondition, PreparedRun, SamplerSettings, StepRecord, Unprepared, VelocityModel,
};
pub use self::sparse::{neighbour_map, varlen_attention, varlen_attention_with, SparseConv3d};
pub use self::sparse::{sparse_downsample, SparseTensor};
pub use self::stage1::dinov2::{recgen_cond, Dinov2, Dinov2Config};
pub use self::stage1::ss_flow::SparseStructureFlowModel;
pub use self::stage1::ss_vae::decoder::{occupied_coords, SparseStructureDecoder, SparseStructureDecoderConfig};
pub use self::stage1::ss_vae::encoder::{ReconLoss, SparseStructureEncoderConfig};
pub use self::stage2::slat_flow::{SLatFlowConfig, SLatFlowModel};
pub use self::stage2::slat_flow::{SLatNormalization, SlatVelocity};
pub use self::stage2::slat_vae::gaussian::sh0_to_rgb;
pub use self::stage2::slat_vae::gaussian::SLatGaussianDecoder;
pub use self::stage2::slat_vae::mesh::SLatMeshDecoder;
pub use self::stage2::slat_vae::trunk::SparseTransformerBase;
