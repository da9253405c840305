//! The whole two-stage RecGen model as one library call.
//!
//! # API
//!
//! ```no_run
//! use recon_core::engine::{LoadOptions, ObjectInputs, Pipeline, RunOptions, Stages, ViewInput, Weights};
//! # fn main() -> recon_core::Result<()> {
//! // Trained (or `recon weights init`) weights: `<dir>/<key>.safetensors` per module.
//! let p = Pipeline::load("models/recgen-large.json".as_ref(), Weights::Dir("weights/".as_ref()), Stages::All, &LoadOptions::default())?;
//! // Or in-memory random weights (labelled as such in the output metadata):
//! let p = Pipeline::load("models/recgen-tiny.json".as_ref(), Weights::Random(0), Stages::All, &LoadOptions::default())?;
//! let s = p.image_size(); // DINO input side
//! let zeros = |c: usize| candle_core::Tensor::zeros((1, c, s, s), candle_core::DType::F32, &candle_core::Device::Cpu);
//! let (pixels, pointmap, mask) = (zeros(3)?, zeros(3)?, zeros(1)?); // real inputs come from preprocessing
//! let inputs = ObjectInputs { views: vec![ViewInput { pixels, pointmap, mask }] };
//! let out = p.run(&inputs, &RunOptions { seed: 42, ..Default::default() })?;
//! println!("{} voxels, {:?} faces, {:?}", out.coords.len(), out.mesh.map(|m| m.faces.len()), out.timings);
//! # Ok(()) }
//! ```
//!
//! **Inputs** ([`ObjectInputs`]): one or more views, view 0 being the
//! anchor. Up to the stage-1 model's `num_pose_tokens` views condition one
//! run together; more (at most [`MAX_SECOND_VIEWS`] besides the anchor) run
//! as fused pairs (**Pair fusion** below). Each view holds, at
//! the DINO input size `S` (`image_cond_model.args.image_size`: 518 for
//! recgen-large, 56 for recgen-tiny), f32 tensors
//! - `pixels` `[1, 3, S, S]`: RGB in [0, 1] already normalised with the
//!   ImageNet mean/std (what DINOv2 receives),
//! - `pointmap` `[1, 3, S, S]`: the normalised pointmap (finite values),
//! - `mask` `[1, 1, S, S]`: object mask in {0, 1}.
//!
//! Producing them from RGB-D frames is the job of the preprocessing code.
//!
//! **Kernels, precision, memory** ([`LoadOptions`], given to
//! [`Pipeline::load`]): by default every layer runs the fast
//! inference kernels in f32 and all modules stay resident. `compute:
//! Compute::fast(Precision::Bf16 | F16)` stores weights in bf16/f16 (half
//! the memory; bf16 also computes in bf16 with f32 accumulation, see
//! [`crate::model::nn::fast`]); `Compute::Plain` runs the differentiable candle
//! path. `per_stage: true` builds each module when its stage runs and frees
//! it afterwards, so the peak is the largest stage plus activations
//! ([`RunOptions::measure_memory`] reports it per stage).
//!
//! **Weights** ([`Pipeline::load`]): the architecture file names six modules;
//! module `<key>` is read from `<weights_dir>/<key>.safetensors` (or `.pt`/
//! `.pth`), keys `image_cond_model`, `ss_flow`, `ss_decoder`, `slat_flow`,
//! `slat_dec_mesh`, `slat_dec_gs` ([`RecGenConfig::modules`]). Each file is
//! checked against the tensor list its config implies before anything is
//! built (missing tensor or wrong shape → an error naming file, tensor and
//! both shapes; extra tensors are tolerated as upstream's `strict=False`).
//! `recon weights init --config <arch>.json --out DIR` writes exactly this
//! layout. Pose statistics are read from the files the architecture names.
//!
//! **Steps** of [`Pipeline::run`] (spec §8, §9; RecGen `run_pointmap` /
//! `run_pointmap_multiview`):
//! 1. DINOv2 per view → RecGen condition (LayerNorm'd patch tokens).
//! 2. Stage-1 condition `ss_flow.condition` (frame-token embedding for two
//!    views, + pointmap and mask embeddings; `neg_cond` = zeros).
//! 3. Stage-1 Euler/CFG sampling of the `[1, 8, R, R, R]` latent together
//!    with the `[1, K, 10]` pose tokens.
//! 4. SS decoder → occupied voxels (`logits > 0`); none → an error.
//! 5. Pose: tokens denormalised with the stage-1 stats and Gram–Schmidt
//!    ([`PoseStats::decode_10d`]); the stage-2 13-D tokens via
//!    [`ss_pose_to_slat_pose`].
//! 6. Stage-2 condition `slat_flow.condition` (views concatenated, +
//!    pointmap/mask embeddings, + pose tokens; `neg_cond` = zeros).
//! 7. Stage-2 sampling on the sparse voxels, then `slat·std + mean`.
//! 8. Mesh decoder (FlexiCubes; vertex colours in `Mesh::vertex_attrs`) and
//!    Gaussian decoder (activated [`Gaussians`]).
//!
//! **Pair fusion** (RecGen `generate_multiview` with N > 1 second views,
//! `run_pointmap_many_views`): with more views than pose tokens the model
//! stays in its two-view regime. Every (anchor, view i) pair is a condition
//! of its own, and stage 1 samples one latent and one set of pose tokens
//! from the one noise with the pairs fused at every step
//! ([`RunOptions::fusion`]: the mean of the pairs' guided velocities, or one
//! pair per step in turn; [`FlowEulerGuidanceIntervalSampler::sample_fused`]).
//! The anchor's pose token (token 0) is the result; the other tokens blend
//! the second views of every pair, so no view but the anchor has a token of
//! its own ([`PredictedPose::view_tokens`] = 1). Stage 2 then runs on the
//! anchor and the first second view with the fused pose, or, with
//! [`RunOptions::slat_fusion`], on every pair fused the same way: each pair
//! past the first first gets its own plain stage-1 run for its pose tokens,
//! its anchor token replaced by the fused run's (every pair must agree where
//! the anchor camera is), and pair 1 takes the fused run's tokens.
//!
//! **Noise order** (determinism): one [`SeededRng`] seeded with
//! `RunOptions::seed` draws, in order, the stage-1 latent `[1, Cin, R, R, R]`,
//! the stage-1 pose tokens `[1, K, P]` (`[1, P]` when K = 1), then the
//! stage-2 features `[N, Cin]` (rows in occupied-voxel order). With stage-2
//! pair fusion, each later pair's own stage-1 latent and pose tokens come
//! between (pair 2 first), as upstream draws them. The same seed and inputs
//! give bit-identical outputs. (torch's RNG is not reproduced, so results
//! match upstream in distribution, not sample by sample.)
//!
//! **Frames**: the mesh and Gaussians are in the decoders' object frame
//! ([-0.5, 0.5]³, z up); [`PredictedPose::pose`] maps that frame into the
//! normalised pointmap frame as RecGen predicts it (`x = s·R·x_obj + t`).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use serde::Serialize;

use crate::gaussians::Gaussians;
use crate::geometry::pose::{ss_pose_to_slat_pose, NineDLayout, Pose, PoseStats};
use crate::mesh::Mesh;
use crate::model::config::{ModuleArgs, ModuleKey, RecGenConfig};
use crate::model::nn::fast::{Compute, Precision};
use crate::model::sampler::{FlowEulerGuidanceIntervalSampler, Fusion, SamplerSettings, SlatFusion};
use crate::model::sparse::SparseTensor;
use crate::model::stage1::dinov2::{Dinov2, Dinov2Config};
use crate::model::stage1::embedders::ViewInputs;
use crate::model::stage1::ss_flow::{SparseStructureFlowModel, SsFlowConfig};
use crate::model::stage1::ss_vae::decoder::{occupied_coords, SparseStructureDecoder};
use crate::model::stage2::slat_flow::{SLatFlowConfig, SLatFlowModel, SLatNormalization, SlatVelocity};
use crate::model::stage2::slat_vae::gaussian::SLatGaussianDecoder;
use crate::model::stage2::slat_vae::mesh::SLatMeshDecoder;
use crate::rng::SeededRng;
use crate::weights::load::Checkpoint;
use crate::weights::registry;
use crate::weights::WeightFiles;
use crate::{Error, Result};

/// One view of the object (see the module docs for shapes and ranges).
#[derive(Debug, Clone)]
pub struct ViewInput {
    /// ImageNet-normalised RGB `[1, 3, S, S]`.
    pub pixels: Tensor,
    /// Normalised pointmap `[1, 3, S, S]`.
    pub pointmap: Tensor,
    /// Mask `[1, 1, S, S]` in {0, 1}.
    pub mask: Tensor,
}

/// All views of one object; view 0 is the anchor whose pose is reported.
#[derive(Debug, Clone)]
pub struct ObjectInputs {
    /// The views, anchor first: 1 to [`Pipeline::max_views`] condition one
    /// run together; more (with a two-view model, at most
    /// [`MAX_SECOND_VIEWS`] besides the anchor) run as fused (anchor, view i)
    /// pairs (module docs, **Pair fusion**).
    pub views: Vec<ViewInput>,
}

/// Most views besides the anchor one run takes with pair fusion: each is a
/// condition prepared in every fused stage (memory) and, with
/// [`Fusion::Multidiffusion`], a model pass per step (time).
pub const MAX_SECOND_VIEWS: usize = 16;

/// Per-run settings. Sampler values not overridden come from the
/// architecture file's `samplers` section.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunOptions {
    /// Seed of all the run's noise (module docs, **Noise order**).
    pub seed: u64,
    /// Stage-1 sampler steps (`None`: the architecture file's).
    pub ss_steps: Option<usize>,
    /// Stage-1 classifier-free guidance strength (`None`: the architecture file's).
    pub ss_cfg_strength: Option<f64>,
    /// Stage-2 sampler steps (`None`: the architecture file's).
    pub slat_steps: Option<usize>,
    /// Stage-2 classifier-free guidance strength (`None`: the architecture file's).
    pub slat_cfg_strength: Option<f64>,
    /// Stop after stage 1 (occupancy + pose): no stage-2 sampling, no decoding.
    pub stage1_only: bool,
    /// Decode the mesh (mesh decoder and FlexiCubes) after stage 2.
    pub decode_mesh: bool,
    /// Decode the Gaussians after stage 2.
    pub decode_gaussians: bool,
    /// Record the peak resident memory of each stage in
    /// [`ObjectReconstruction::memory`]. Resets the process-wide high-water
    /// mark (Linux `clear_refs`) before every stage, so leave it off when
    /// something else in the process reads VmHWM.
    pub measure_memory: bool,
    /// Condition both stages on each view's point map (RecGen's `use_pointmap`); off, the
    /// point-map embedding is left out of the condition, as upstream passes `pointmap=None`.
    pub use_pointmap: bool,
    /// With pair fusion (more views than pose tokens), how stage 1 fuses the
    /// (anchor, view i) pairs at every step; unused otherwise.
    pub fusion: Fusion,
    /// With pair fusion, whether and how stage 2 fuses the pairs too (each
    /// pair past the first then costs a stage-1 run for its pose tokens).
    pub slat_fusion: SlatFusion,
}

impl Default for RunOptions {
    fn default() -> Self {
        Self {
            seed: 42,
            ss_steps: None,
            ss_cfg_strength: None,
            slat_steps: None,
            slat_cfg_strength: None,
            stage1_only: false,
            decode_mesh: true,
            decode_gaussians: true,
            measure_memory: false,
            use_pointmap: true,
            fusion: Fusion::default(),
            slat_fusion: SlatFusion::default(),
        }
    }
}

/// Wall-clock seconds per stage (0 for stages that did not run).
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct StageTimings {
    /// DINOv2 on every view.
    pub image_encoder: f64,
    /// The stage-1 condition (`ss_flow.condition`).
    pub ss_condition: f64,
    /// Stage-1 sampling of the latent and the pose tokens.
    pub ss_sampling: f64,
    /// The SS decoder (occupied voxels).
    pub ss_decoder: f64,
    /// Decoding the pose tokens.
    pub pose: f64,
    /// The occupancy hook of [`Pipeline::run_guided`] (the shape fit).
    pub shape_fit: f64,
    /// The stage-2 condition (`slat_flow.condition`).
    pub slat_condition: f64,
    /// Stage-2 sampling on the occupied voxels.
    pub slat_sampling: f64,
    /// The mesh decoder's network (FlexiCubes features per cube).
    pub mesh_decoder: f64,
    /// FlexiCubes surface extraction from those features.
    pub flexicubes: f64,
    /// The Gaussian decoder.
    pub gaussian_decoder: f64,
    /// Building modules during the run ([`LoadOptions::per_stage`]); also
    /// counted in the stage it belongs to.
    pub loading: f64,
    /// The whole run.
    pub total: f64,
}

/// Peak resident memory (VmHWM, MiB) of each stage, module building
/// included; `None` for stages that did not run or where unavailable.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct StageMemory {
    /// The image encoder.
    pub image_encoder: Option<f64>,
    /// Stage-1 condition and sampling.
    pub ss_flow: Option<f64>,
    /// The SS decoder.
    pub ss_decoder: Option<f64>,
    /// Stage-2 condition and sampling.
    pub slat_flow: Option<f64>,
    /// The mesh decoder and FlexiCubes extraction.
    pub mesh_decoder: Option<f64>,
    /// The Gaussian decoder.
    pub gaussian_decoder: Option<f64>,
}

/// The stages of [`Pipeline::run`], reported to an observer as each starts
/// ([`Pipeline::run_observed`]), e.g. to drive a progress bar.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// DINOv2 on every view.
    ImageEncoder,
    /// Stage-1 condition and sampling (occupancy latent and pose tokens).
    SsSampling,
    /// The SS decoder: occupied voxels.
    SsDecoder,
    /// Stage-2 condition and sampling on the occupied voxels.
    SlatSampling,
    /// The mesh decoder and FlexiCubes extraction.
    MeshDecoder,
    /// The Gaussian decoder.
    GaussianDecoder,
}

impl Stage {
    /// Lower-case name for progress displays (`"ss sampling"`).
    pub fn name(self) -> &'static str {
        match self {
            Stage::ImageEncoder => "image encoder",
            Stage::SsSampling => "ss sampling",
            Stage::SsDecoder => "ss decoder",
            Stage::SlatSampling => "slat sampling",
            Stage::MeshDecoder => "mesh decoder",
            Stage::GaussianDecoder => "gaussian decoder",
        }
    }
}

/// The stage-1 pose prediction.
#[derive(Debug, Clone, PartialEq)]
pub struct PredictedPose {
    /// Token 0 (anchor view) decoded: denormalised with the stage-1 stats,
    /// rotation by Gram–Schmidt. Object frame → normalised pointmap frame.
    pub pose: Pose,
    /// Every pose token decoded; token k belongs to view k (the model always
    /// samples `num_pose_tokens` tokens, also for a single view).
    pub per_token: Vec<Pose>,
    /// The sampled tokens as they leave the sampler (normalised 10-D).
    pub tokens_10d: Vec<[f32; 10]>,
    /// The stage-2 pose tokens (13-D, normalised with the stage-2 stats).
    pub slat_tokens_13d: Vec<[f32; 13]>,
    /// Views `0..view_tokens` have their own token (`per_token[k]` is view
    /// k's): every view of a run with up to `num_pose_tokens` views; the
    /// anchor alone with pair fusion, whose other tokens blend the pairs'
    /// second views.
    pub view_tokens: usize,
}

/// Where the weights came from.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum WeightsSource {
    /// In-memory random weights ([`Weights::Random`]): NOT a trained model.
    Random {
        /// The seed the weights were generated from.
        seed: u64,
    },
    /// Files per module; `random_init` when any carries `recon.random_init`.
    Files {
        /// The weights folder ([`WeightFiles::dir`]).
        dir: PathBuf,
        /// The checkpoint file of every loaded module.
        files: Vec<PathBuf>,
        /// Whether any safetensors file carries the random-init label.
        random_init: bool,
        /// Every file taken from a weights manifest (checkpoints, configs,
        /// pose statistics), with its checked SHA-256 pin and tensor count.
        #[serde(skip_serializing_if = "Vec::is_empty")]
        manifest_files: Vec<crate::weights::ReadFile>,
        /// What the release's own files set (module args, normalisation,
        /// samplers) and other remarks of the manifest load.
        #[serde(skip_serializing_if = "Vec::is_empty")]
        notes: Vec<String>,
        /// The weights' identity: SHA-256 over one line `<module> <SHA-256 of its file>` per
        /// loaded module, in the architecture's module order (a manifest's checked pin stands
        /// for its file's hash). The same checkpoints give the same value from any folder.
        sha256: String,
    },
}

/// Which model answered, as outputs record it beside `recon_version` (`pose.json`, the
/// server's answers, `recon eval`'s index): the architecture's name and the weights' hash.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ModelIdentity {
    /// The architecture's name (the config's `name`: `recgen-nano`, `recgen-large`, …).
    pub name: String,
    /// [`WeightsSource::sha256`]; `None` for in-memory random weights.
    pub sha256: Option<String>,
}

impl ModelIdentity {
    /// The model a run's [`RunMetadata`] names.
    pub fn of(run: &RunMetadata) -> Self {
        ModelIdentity { name: run.architecture.clone(), sha256: run.weights.sha256().map(str::to_string) }
    }
}

impl WeightsSource {
    /// The weights' hash ([`WeightsSource::Files`]'s `sha256`); `None` for in-memory random weights.
    pub fn sha256(&self) -> Option<&str> {
        match self {
            WeightsSource::Random { .. } => None,
            WeightsSource::Files { sha256, .. } => Some(sha256),
        }
    }

    /// True for random weights, in memory or from labelled files.
    pub fn is_random(&self) -> bool {
        match self {
            WeightsSource::Random { .. } => true,
            WeightsSource::Files { random_init, .. } => *random_init,
        }
    }
}

/// What produced a result.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RunMetadata {
    /// The architecture's name (the config's `name`).
    pub architecture: String,
    /// Where the weights came from.
    pub weights: WeightsSource,
    /// Same as `weights.is_random()`, spelled out for readers of the JSON.
    pub random_weights: bool,
    /// The run's seed ([`RunOptions::seed`]).
    pub seed: u64,
    /// Views the run was conditioned on.
    pub num_views: usize,
    /// Stage-1 sampler settings as run.
    pub ss_sampler: SamplerSettings,
    /// Stage-2 sampler settings as run (`None`: stage 1 only).
    pub slat_sampler: Option<SamplerSettings>,
    /// The order the seeded noise is drawn in (module docs, **Noise order**).
    pub noise_order: &'static str,
    /// Whether the point maps conditioned the run ([`RunOptions::use_pointmap`]); written
    /// only when they did not (earlier outputs: they did).
    #[serde(skip_serializing_if = "is_true")]
    pub use_pointmap: bool,
    /// How the views were fused, when the run had more views than pose
    /// tokens (module docs, **Pair fusion**); absent otherwise.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fusion: Option<FusionMetadata>,
}

/// How a run with pair fusion fused its views ([`RunMetadata::fusion`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FusionMetadata {
    /// The (anchor, view i) pairs.
    pub pairs: usize,
    /// Stage 1's fusion of the pairs.
    pub ss: Fusion,
    /// Stage 2's (`none`: the anchor and the first second view).
    pub slat: SlatFusion,
}

fn is_true(b: &bool) -> bool {
    *b
}

/// The occupancy hook of [`Pipeline::run_guided`]: `(pose, voxels, resolution) → voxels`.
pub type OccupancyFit<'a> = dyn FnMut(&PredictedPose, &[[i32; 3]], usize) -> Result<Vec<[i32; 3]>> + 'a;

/// Everything one run produces.
#[derive(Debug, Clone)]
pub struct ObjectReconstruction {
    /// The stage-1 pose prediction.
    pub pose: PredictedPose,
    /// Occupied voxels `(x, y, z)` of the SS decoder grid (resolution
    /// `ss_resolution`), in argwhere order.
    pub coords: Vec<[i32; 3]>,
    /// Side of the SS decoder grid, in voxels.
    pub ss_resolution: usize,
    /// Mesh in the object frame with vertex colours (`vertex_attrs`).
    pub mesh: Option<Mesh>,
    /// Activated Gaussians in the object frame.
    pub gaussians: Option<Gaussians>,
    /// Wall-clock seconds per stage.
    pub timings: StageTimings,
    /// Filled when [`RunOptions::measure_memory`] is set.
    pub memory: Option<StageMemory>,
    /// What produced this result.
    pub metadata: RunMetadata,
}

/// Which modules to build.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stages {
    /// Every module: both stages and both decoders.
    All,
    /// Image encoder, stage-1 flow and SS decoder only (occupancy + pose).
    SparseStructure,
}

/// How a pipeline builds and keeps its modules.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LoadOptions {
    /// Kernels and precision of every layer. Default: the fast inference
    /// kernels in f32 ([`Compute::fast`]); [`Compute::Plain`] runs the
    /// differentiable candle path (what the conformance fixtures check).
    pub compute: Compute,
    /// Build each module when its stage runs and free it right after, so the
    /// peak memory is the largest stage plus activations instead of the whole
    /// pipeline. Every run then pays the build (weight loading and packing)
    /// time, reported in [`StageTimings::loading`].
    pub per_stage: bool,
}

impl Default for LoadOptions {
    fn default() -> Self {
        Self { compute: Compute::fast(Precision::F32), per_stage: false }
    }
}

impl LoadOptions {
    /// Fast kernels at `precision` (the `--dtype` of the CLI), all modules resident.
    pub fn precision(precision: Precision) -> Self {
        Self { compute: Compute::fast(precision), per_stage: false }
    }
}

/// The `--dtype` of the CLI and Python: a precision, or `auto`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Dtype {
    /// The fastest precision within the stated budget for this model (see [`Dtype::resolve`]).
    #[default]
    Auto,
    /// f32 weights and arithmetic.
    F32,
    /// bf16 weights, bf16-rounded GEMM and attention inputs, f32 accumulation.
    Bf16,
    /// f16 weights widened to f32 for the arithmetic.
    F16,
}

/// Flow transformers at least this wide run bf16 under [`Dtype::Auto`].
pub const AUTO_BF16_MIN_CHANNELS: usize = 512;

impl Dtype {
    /// The precision to build `arch` with. `auto`: bf16 when the flow
    /// transformers are at least [`AUTO_BF16_MIN_CHANNELS`] wide (recgen-large:
    /// the packed GEMMs dominate, bf16 is the faster path — `vdpbf16ps` where it
    /// pays, else bf16 storage on f32 FMA — and stays within the 1 % budget of
    /// `recon bench --sections precision`); f32 for narrower models, whose time
    /// is outside the GEMMs, so they keep the conformance-exact path and
    /// byte-stable outputs.
    pub fn resolve(self, arch: &RecGenConfig) -> Result<Precision> {
        Ok(match self {
            Dtype::F32 => Precision::F32,
            Dtype::Bf16 => Precision::Bf16,
            Dtype::F16 => Precision::F16,
            Dtype::Auto => {
                let width = arch.ss_flow_config().model_channels;
                if width >= AUTO_BF16_MIN_CHANNELS {
                    Precision::Bf16
                } else {
                    Precision::F32
                }
            }
        })
    }
}

/// Where a module's weights come from.
#[derive(Debug, Clone)]
enum Source {
    File(PathBuf),
    Random(u64),
}

/// Modules built at load time (all of them unless `per_stage`).
#[derive(Default)]
struct Resident {
    dino: Option<Dinov2>,
    ss_flow: Option<SparseStructureFlowModel>,
    ss_decoder: Option<SparseStructureDecoder>,
    slat_flow: Option<SLatFlowModel>,
    mesh_decoder: Option<SLatMeshDecoder>,
    gs_decoder: Option<SLatGaussianDecoder>,
}

/// A module for the duration of a stage: the resident one, or one built for it.
enum Held<'a, T> {
    Resident(&'a T),
    Built(T),
}

impl<T> std::ops::Deref for Held<'_, T> {
    type Target = T;
    fn deref(&self) -> &T {
        match self {
            Held::Resident(t) => t,
            Held::Built(t) => t,
        }
    }
}

/// Where a pipeline's weights come from.
#[derive(Debug, Clone, Copy)]
pub enum Weights<'a> {
    /// `<dir>/<key>.safetensors` (or `.pt`/`.pth`) per module key.
    Dir(&'a Path),
    /// Explicit checkpoint files, e.g. resolved through a weights manifest.
    Files(&'a WeightFiles),
    /// In-memory random weights from this seed: NOT a trained model.
    Random(u64),
}

/// All modules of one architecture file with their weights.
pub struct Pipeline {
    /// The architecture file, parsed.
    pub config: RecGenConfig,
    options: LoadOptions,
    stages: Stages,
    sources: HashMap<ModuleKey, Source>,
    resident: Resident,
    dino_cfg: Dinov2Config,
    ss_cfg: SsFlowConfig,
    slat_cfg: Option<SLatFlowConfig>,
    ss_stats: PoseStats,
    slat_stats: PoseStats,
    layout: NineDLayout,
    slat_norm: SLatNormalization,
    weights: WeightsSource,
}

const NOISE_ORDER: &str = "SeededRng(seed): ss latent [1,Cin,R,R,R], ss pose tokens [1,K,P], slat feats [N,Cin]";

fn secs(t: Instant) -> f64 {
    t.elapsed().as_secs_f64()
}

/// Timings and peak memory of one run's stages, as they are measured.
struct Meter {
    /// Peak RSS of each stage (module building included) when set.
    measure_memory: bool,
    tm: StageTimings,
    mem: StageMemory,
}

impl Meter {
    /// Start a stage's peak-RSS window.
    fn mark(&self) {
        if self.measure_memory {
            crate::util::memory::reset_peak_rss();
        }
    }
    /// Peak RSS since the last [`Meter::mark`].
    fn peak(&self) -> Option<f64> {
        if self.measure_memory {
            crate::util::memory::peak_rss_mib()
        } else {
            None
        }
    }
}

impl Pipeline {
    /// Build the modules of `stages` from `weights`: the one constructor.
    /// Checkpoints are validated against the architecture here, also when the
    /// modules are built later (`options.per_stage`).
    pub fn load(config_path: &Path, weights: Weights<'_>, stages: Stages, options: &LoadOptions) -> Result<Self> {
        match weights {
            Weights::Dir(dir) => Self::from_dir(config_path, dir, stages, options),
            Weights::Files(files) => Self::from_files(config_path, files, stages, options),
            Weights::Random(seed) => Self::from_random(config_path, seed, stages, options),
        }
    }

    fn from_dir(config_path: &Path, weights_dir: &Path, stages: Stages, options: &LoadOptions) -> Result<Self> {
        let config = RecGenConfig::load(config_path)?;
        let mut files = WeightFiles { dir: weights_dir.to_path_buf(), ..Default::default() };
        for (key, spec) in config.modules() {
            if stages == Stages::SparseStructure && !key.is_stage1() {
                continue;
            }
            let path = ["safetensors", "pt", "pth"]
                .iter()
                .map(|ext| weights_dir.join(format!("{key}.{ext}")))
                .find(|p| p.exists())
                .ok_or_else(|| {
                    Error::input(
                        weights_dir.display().to_string(),
                        format!("no weights for module `{key}` ({}): expected {key}.safetensors (or .pt/.pth) in this folder", spec.name),
                    )
                })?;
            files.modules.insert(key, path);
        }
        Self::from_files(config_path, &files, stages, options)
    }

    fn from_files(config_path: &Path, weight_files: &WeightFiles, stages: Stages, options: &LoadOptions) -> Result<Self> {
        // A manifest load brings the architecture its release's configs describe.
        let config = match &weight_files.architecture {
            Some(a) => a.clone(),
            None => RecGenConfig::load(config_path)?,
        };
        let mut sources = HashMap::new();
        let mut files = Vec::new();
        let mut random_init = false;
        let mut identity = ring::digest::Context::new(&ring::digest::SHA256);
        for (key, spec) in config.modules() {
            if stages == Stages::SparseStructure && !key.is_stage1() {
                continue;
            }
            let path = weight_files.modules.get(&key).cloned().ok_or_else(|| {
                Error::input(weight_files.dir.display().to_string(), format!("no checkpoint file for module `{key}` ({})", spec.name))
            })?;
            let label = format!("{}: {key}", config_path.display());
            let expected = registry::expected_tensors(&config.module_args(key)?, &label)?;
            let ck = Checkpoint::open(&path, None)?;
            crate::weights::validate_checkpoint(&ck, &expected, true)?;
            if path.extension().is_some_and(|e| e == "safetensors" || e == "pt" || e == "pth") {
                random_init |= crate::weights::init::is_random_init(&path)?;
            }
            // A manifest load has checked the file against its pin already: no second read.
            let pinned = weight_files.read.iter().find(|r| r.local == path).and_then(|r| r.sha256.clone());
            let file_sha = match pinned {
                Some(s) => s.to_ascii_lowercase(),
                None => crate::weights::hf_cache::sha256_file(&path)?,
            };
            identity.update(format!("{key} {file_sha}\n").as_bytes());
            sources.insert(key, Source::File(path.clone()));
            files.push(path);
        }
        let weights = WeightsSource::Files {
            dir: weight_files.dir.clone(),
            files,
            random_init,
            manifest_files: weight_files.read.clone(),
            notes: weight_files.notes.clone(),
            sha256: identity.finish().as_ref().iter().map(|b| format!("{b:02x}")).collect(),
        };
        let mut p = Self::build(config, sources, weights, stages, *options)?;
        if let Some(f) = &weight_files.ss_stats {
            p.ss_stats = PoseStats::from_json_file(f)?;
        }
        if let Some(f) = &weight_files.slat_stats {
            p.slat_stats = PoseStats::from_json_file(f)?;
        }
        Ok(p)
    }

    /// Random tensors are generated one at a time while a module is built,
    /// identical to what `recon weights init --config <config> --seed <seed>` writes.
    fn from_random(config_path: &Path, seed: u64, stages: Stages, options: &LoadOptions) -> Result<Self> {
        let config = RecGenConfig::load(config_path)?;
        let mut sources = HashMap::new();
        for (key, _) in config.modules() {
            if stages == Stages::SparseStructure && !key.is_stage1() {
                continue;
            }
            sources.insert(key, Source::Random(registry::module_seed(seed, key.name())));
        }
        Self::build(config, sources, WeightsSource::Random { seed }, stages, *options)
    }

    fn build(
        config: RecGenConfig,
        sources: HashMap<ModuleKey, Source>,
        weights: WeightsSource,
        stages: Stages,
        options: LoadOptions,
    ) -> Result<Self> {
        let dino_cfg = config.args.image_cond_model.clone();
        let ss_cfg = config.args.ss_flow.clone();
        if ss_cfg.pose_channels() != Some(10) {
            return Err(Error::config(
                &config.name,
                "ss_flow.args.pose_representation",
                "the pipeline needs RecGen pose tokens (6d_translation_scale)",
            ));
        }
        let slat_cfg = match stages {
            Stages::SparseStructure => None,
            Stages::All => {
                let c = config.args.slat_flow.clone();
                if c.cond_channels != ss_cfg.cond_channels || !c.use_pose_embedder || c.pose_dim() != 13 {
                    return Err(Error::config(
                        &config.name,
                        "slat_flow.args",
                        "needs cond_channels equal to the SS flow's and a 9d_translation_scale pose embedder",
                    ));
                }
                if config.slat_normalization.mean.len() != c.out_channels {
                    return Err(Error::config(&config.name, "slat_normalization", "length must equal slat_flow out_channels"));
                }
                Some(c)
            }
        };
        let slat_norm = SLatNormalization { mean: config.slat_normalization.mean.clone(), std: config.slat_normalization.std.clone() };
        let mut p = Self {
            ss_stats: config.ss_pose_stats()?,
            slat_stats: config.slat_pose_stats()?,
            layout: config.pose.nine_d_layout,
            slat_norm,
            options,
            stages,
            sources,
            resident: Resident::default(),
            dino_cfg,
            ss_cfg,
            slat_cfg,
            weights,
            config,
        };
        if !options.per_stage {
            p.resident.dino = Some(p.build_module(ModuleKey::ImageCondModel, registry::build_dinov2)?);
            p.resident.ss_flow = Some(p.build_module(ModuleKey::SsFlow, registry::build_ss_flow)?);
            p.resident.ss_decoder = Some(p.build_module(ModuleKey::SsDecoder, registry::build_ss_decoder)?);
            if stages == Stages::All {
                p.resident.slat_flow = Some(p.build_module(ModuleKey::SlatFlow, registry::build_slat_flow)?);
                p.resident.mesh_decoder = Some(p.build_module(ModuleKey::SlatDecMesh, registry::build_mesh_decoder)?);
                p.resident.gs_decoder = Some(p.build_module(ModuleKey::SlatDecGs, registry::build_gaussian_decoder)?);
            }
        }
        Ok(p)
    }

    /// Build module `key` from its source with this pipeline's compute setting.
    fn build_module<T>(&self, key: ModuleKey, f: fn(&ModuleArgs, VarBuilder, &str, Compute) -> Result<T>) -> Result<T> {
        let spec = self.config.module_args(key)?;
        let label = format!("{}: {key}", self.config.name);
        let vb = match self.sources.get(&key) {
            Some(Source::File(path)) => Checkpoint::open(path, None)?.into_var_builder(DType::F32, &Device::Cpu),
            Some(Source::Random(seed)) => registry::random_var_builder(&spec, *seed)?,
            None => return Err(Error::msg(format!("pipeline: module `{key}` was not loaded (stage-1-only pipeline?)"))),
        };
        let m = f(&spec, vb, &label, self.options.compute);
        // The build's temporaries (f32 weights before packing) do not recur.
        crate::util::release_cached_buffers();
        m
    }

    /// The resident module, or one built now (counted in `loading`).
    fn hold<'a, T>(
        &'a self,
        resident: &'a Option<T>,
        key: ModuleKey,
        f: fn(&ModuleArgs, VarBuilder, &str, Compute) -> Result<T>,
        loading: &mut f64,
    ) -> Result<Held<'a, T>> {
        match resident {
            Some(m) => Ok(Held::Resident(m)),
            None => {
                let t = Instant::now();
                let m = self.build_module(key, f)?;
                *loading += secs(t);
                Ok(Held::Built(m))
            }
        }
    }

    /// Kernels/precision and residency of this pipeline.
    pub fn load_options(&self) -> &LoadOptions {
        &self.options
    }

    /// Where the weights came from (random weights are labelled).
    pub fn weights(&self) -> &WeightsSource {
        &self.weights
    }

    /// The model's name and weights' hash, as outputs record it.
    pub fn identity(&self) -> ModelIdentity {
        ModelIdentity { name: self.config.name.clone(), sha256: self.weights.sha256().map(str::to_string) }
    }

    /// DINO input side `S`.
    pub fn image_size(&self) -> usize {
        self.dino_cfg.img_size
    }

    /// Most views that condition one run together (the stage-1 model's
    /// pose-token count); a two-view model takes more as fused pairs
    /// ([`Self::fuses_pairs`]).
    pub fn max_views(&self) -> usize {
        self.ss_cfg.num_pose_tokens.max(1)
    }

    /// Whether `views` views run as fused (anchor, view i) pairs (module
    /// docs, **Pair fusion**): more views than pose tokens.
    pub fn fuses_pairs(&self, views: usize) -> bool {
        views > self.max_views()
    }

    /// The groups of views that condition a run: all views together, or
    /// with pair fusion each (anchor, view i) pair, in view order.
    fn condition_groups(&self, views: &[ViewInputs]) -> Vec<Vec<ViewInputs>> {
        if !self.fuses_pairs(views.len()) {
            return vec![views.to_vec()];
        }
        views[1..].iter().map(|v| vec![views[0].clone(), v.clone()]).collect()
    }

    fn sampler_settings(base: &SamplerSettings, steps: Option<usize>, cfg: Option<f64>) -> Result<SamplerSettings> {
        let mut s = base.clone();
        if let Some(n) = steps {
            s.steps = n;
        }
        if let Some(w) = cfg {
            s.cfg_strength = w;
        }
        s.validate("run options")?;
        Ok(s)
    }

    fn check_inputs(&self, inputs: &ObjectInputs) -> Result<()> {
        let n = inputs.views.len();
        if n == 0 || (n > self.max_views() && self.max_views() < 2) {
            return Err(Error::input("pipeline inputs", format!("{n} views given; this model takes 1 to {}", self.max_views())));
        }
        if self.fuses_pairs(n) && n - 1 > MAX_SECOND_VIEWS {
            return Err(Error::too_large(
                "pipeline inputs",
                "views",
                (n - 1) as u128,
                MAX_SECOND_VIEWS as u128,
                "views besides the anchor",
                "each is a fused condition: memory in every fused stage and, with multidiffusion, a model pass per step",
            ));
        }
        let s = self.image_size();
        for (i, v) in inputs.views.iter().enumerate() {
            for (name, t, c) in [("pixels", &v.pixels, 3), ("pointmap", &v.pointmap, 3), ("mask", &v.mask, 1)] {
                if t.dims() != [1, c, s, s] {
                    return Err(Error::input(
                        "pipeline inputs",
                        format!("view {i}: {name} has shape {:?}, expected [1, {c}, {s}, {s}]", t.dims()),
                    ));
                }
                if t.dtype() != DType::F32 {
                    return Err(Error::input("pipeline inputs", format!("view {i}: {name} must be f32, got {:?}", t.dtype())));
                }
                let finite = t.flatten_all()?.to_vec1::<f32>()?.iter().all(|x| x.is_finite());
                if !finite {
                    return Err(Error::input(
                        "pipeline inputs",
                        format!("view {i}: {name} has non-finite values (preprocessing must fill invalid points)"),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Run both stages (or stage 1 only) on one object.
    pub fn run(&self, inputs: &ObjectInputs, opts: &RunOptions) -> Result<ObjectReconstruction> {
        self.run_observed(inputs, opts, &|_| {})
    }

    /// [`Self::run`], calling `on_stage` as each stage starts.
    pub fn run_observed(&self, inputs: &ObjectInputs, opts: &RunOptions, on_stage: &dyn Fn(Stage)) -> Result<ObjectReconstruction> {
        self.run_guided(inputs, opts, on_stage, None)
    }

    /// [`Self::run_observed`], with `fit` given the stage-1 pose and occupied
    /// voxels (grid resolution last) and returning the voxels stage 2 runs on
    /// (e.g. [`crate::engine::fit_occupancy`]'s shell).
    pub fn run_guided(
        &self,
        inputs: &ObjectInputs,
        opts: &RunOptions,
        on_stage: &dyn Fn(Stage),
        fit: Option<&mut OccupancyFit<'_>>,
    ) -> Result<ObjectReconstruction> {
        let t_all = Instant::now();
        self.check_inputs(inputs)?;
        let built_stage2 = self.stages == Stages::All;
        let stage1_only = opts.stage1_only || (!opts.decode_mesh && !opts.decode_gaussians && !built_stage2);
        if !stage1_only && !built_stage2 {
            return Err(Error::msg("pipeline: built for stage 1 only; set RunOptions::stage1_only"));
        }
        let ss_settings = Self::sampler_settings(&self.config.samplers.sparse_structure, opts.ss_steps, opts.ss_cfg_strength)?;
        let slat_settings = Self::sampler_settings(&self.config.samplers.slat, opts.slat_steps, opts.slat_cfg_strength)?;
        let mut meter = Meter { measure_memory: opts.measure_memory, tm: StageTimings::default(), mem: StageMemory::default() };

        // 1. Image encoder.
        let views = self.encode_images(inputs, opts.use_pointmap, on_stage, &mut meter)?;
        // 2–3. Stage 1: condition, then latent + pose sampling. The same
        // generator then draws the stage-2 noise.
        let mut rng = SeededRng::new(opts.seed);
        let groups = self.condition_groups(&views);
        let (z, pose_tok) = self.sample_structure(&groups, &ss_settings, opts.fusion, &mut rng, on_stage, &mut meter)?;
        // 4. Occupancy.
        let (ss_resolution, coords4) = self.decode_occupancy(&z, opts.seed, on_stage, &mut meter)?;
        // 5. Pose, then the optional shape fit.
        let fused = groups.len() > 1;
        let (mut pose, slat_pose) = self.decode_pose(&pose_tok, &mut meter)?;
        pose.view_tokens = if fused { 1 } else { inputs.views.len() };
        let (coords, coords4) = Self::fit_occupancy(fit, &pose, coords4, ss_resolution, &mut meter)?;
        let mut metadata = RunMetadata {
            architecture: self.config.name.clone(),
            weights: self.weights.clone(),
            random_weights: self.weights.is_random(),
            seed: opts.seed,
            num_views: inputs.views.len(),
            ss_sampler: ss_settings.clone(),
            slat_sampler: None,
            noise_order: NOISE_ORDER,
            use_pointmap: opts.use_pointmap,
            fusion: fused.then_some(FusionMetadata { pairs: groups.len(), ss: opts.fusion, slat: opts.slat_fusion }),
        };
        let (mut mesh, mut gaussians) = (None, None);

        if !stage1_only {
            // 6–7. Stage 2 on the occupied voxels: conditioned on every view
            // together, or with pair fusion on the first pair or on every pair fused.
            let slat_fusion = opts.slat_fusion.fusion().filter(|_| fused);
            let conditions: Vec<(Vec<ViewInputs>, Tensor)> = match slat_fusion {
                Some(_) => {
                    let poses = self.pair_poses(&groups, &pose_tok, slat_pose, &ss_settings, &mut rng, &mut meter)?;
                    groups.into_iter().zip(poses).collect()
                }
                None => groups.into_iter().take(1).map(|g| (g, slat_pose.clone())).collect(),
            };
            let fusion = slat_fusion.unwrap_or_default();
            let slat = self.sample_slat(&conditions, fusion, &coords4, ss_resolution, &slat_settings, &mut rng, on_stage, &mut meter)?;
            metadata.slat_sampler = Some(slat_settings);
            // 8. Decoders.
            (mesh, gaussians) = self.decode_slat(&slat, opts, on_stage, &mut meter)?;
        }
        let Meter { mut tm, mem, .. } = meter;
        tm.total = secs(t_all);
        let memory = opts.measure_memory.then_some(mem);
        Ok(ObjectReconstruction { pose, coords, ss_resolution, mesh, gaussians, timings: tm, memory, metadata })
    }

    /// Step 1: DINOv2 tokens of every view, with the view's point map (unless
    /// `use_pointmap` is off) and mask.
    fn encode_images(
        &self,
        inputs: &ObjectInputs,
        use_pointmap: bool,
        on_stage: &dyn Fn(Stage),
        meter: &mut Meter,
    ) -> Result<Vec<ViewInputs>> {
        on_stage(Stage::ImageEncoder);
        meter.mark();
        let dino = self.hold(&self.resident.dino, ModuleKey::ImageCondModel, registry::build_dinov2, &mut meter.tm.loading)?;
        let t = Instant::now();
        let tokens: Vec<Tensor> = inputs.views.iter().map(|v| dino.recgen_cond(&v.pixels)).collect::<candle_core::Result<_>>()?;
        drop(dino);
        meter.tm.image_encoder = secs(t);
        meter.mem.image_encoder = meter.peak();
        Ok(inputs
            .views
            .iter()
            .zip(&tokens)
            .map(|(v, tok)| ViewInputs {
                patch_tokens: tok.clone(),
                pointmap: use_pointmap.then(|| v.pointmap.clone()),
                mask: Some(v.mask.clone()),
            })
            .collect())
    }

    /// Steps 2–3: the stage-1 condition of each group of views (one group, or
    /// with pair fusion one per pair), then the sparse-structure latent and
    /// the pose tokens sampled from `rng`, the groups fused as `fusion` says.
    fn sample_structure(
        &self,
        groups: &[Vec<ViewInputs>],
        settings: &SamplerSettings,
        fusion: Fusion,
        rng: &mut SeededRng,
        on_stage: &dyn Fn(Stage),
        meter: &mut Meter,
    ) -> Result<(Tensor, Tensor)> {
        on_stage(Stage::SsSampling);
        meter.mark();
        // The build counts in `loading`, not in the condition's time.
        let ss_flow = self.hold(&self.resident.ss_flow, ModuleKey::SsFlow, registry::build_ss_flow, &mut meter.tm.loading)?;
        let t = Instant::now();
        let (mut conds, mut neg) = (Vec::with_capacity(groups.len()), None);
        for g in groups {
            let (c, n) = ss_flow.condition(g)?;
            conds.push(c);
            // Every group's negative condition is zeros of one shape: upstream passes the first pair's to all.
            neg.get_or_insert(n);
        }
        let neg = neg.ok_or_else(|| Error::msg("pipeline: no views to condition stage 1 on"))?;
        meter.tm.ss_condition = secs(t);
        let t = Instant::now();
        let noise = ss_flow.initial_state(rng, 1, &Device::Cpu)?;
        let sampler = FlowEulerGuidanceIntervalSampler::new(settings.clone());
        let out = match conds.as_slice() {
            [cond] => sampler.sample(&*ss_flow, noise, cond, Some(&neg))?,
            _ => sampler.sample_fused(&*ss_flow, noise, &conds, Some(&neg), fusion)?,
        };
        drop(ss_flow);
        let (z, pose_tok) = match out.as_slice() {
            [z, p] => (z.clone(), p.clone()),
            _ => return Err(Error::msg("pipeline: stage-1 sampler returned no pose tokens")),
        };
        meter.tm.ss_sampling = secs(t);
        meter.mem.ss_flow = meter.peak();
        Ok((z, pose_tok))
    }

    /// Step 4: the occupied voxels `[0, x, y, z]` of latent `z` and the grid
    /// side; an empty occupancy is an error (`seed` named in it).
    fn decode_occupancy(&self, z: &Tensor, seed: u64, on_stage: &dyn Fn(Stage), meter: &mut Meter) -> Result<(usize, Vec<[i32; 4]>)> {
        on_stage(Stage::SsDecoder);
        meter.mark();
        let ss_decoder = self.hold(&self.resident.ss_decoder, ModuleKey::SsDecoder, registry::build_ss_decoder, &mut meter.tm.loading)?;
        let t = Instant::now();
        let logits = ss_decoder.forward(z)?;
        drop(ss_decoder);
        let ss_resolution = logits.dim(2)?;
        let coords4 = occupied_coords(&logits)?;
        meter.tm.ss_decoder = secs(t);
        meter.mem.ss_decoder = meter.peak();
        if coords4.is_empty() {
            let max = logits.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            return Err(Error::msg(format!(
                "stage 1 produced an empty occupancy: no SS decoder logit > 0 (max {max:.4}) with seed {seed}; \
                 try another seed or more sampling steps"
            )));
        }
        Ok((ss_resolution, coords4))
    }

    /// Step 5: the pose of every pose token, and the stage-2 pose tokens.
    fn decode_pose(&self, pose_tok: &Tensor, meter: &mut Meter) -> Result<(PredictedPose, Tensor)> {
        let t = Instant::now();
        let k = self.ss_cfg.num_pose_tokens.max(1);
        let rows = pose_tok.reshape((k, 10))?.to_vec2::<f32>()?;
        let per_token = rows.iter().map(|r| self.ss_stats.decode_10d(r)).collect::<Result<Vec<_>>>()?;
        let tokens_10d: Vec<[f32; 10]> = rows.iter().map(|r| std::array::from_fn(|i| r[i])).collect();
        let slat_pose = ss_pose_to_slat_pose(pose_tok, &self.ss_stats, &self.slat_stats, self.layout)?;
        let slat_tokens_13d: Vec<[f32; 13]> =
            slat_pose.reshape((k, 13))?.to_vec2::<f32>()?.iter().map(|r| std::array::from_fn(|i| r[i])).collect();
        let pose = PredictedPose { pose: per_token[0], view_tokens: per_token.len(), per_token, tokens_10d, slat_tokens_13d };
        meter.tm.pose = secs(t);
        Ok((pose, slat_pose))
    }

    /// The occupied voxels as `[x, y, z]` and `[0, x, y, z]`, after `fit` when given.
    fn fit_occupancy(
        fit: Option<&mut OccupancyFit<'_>>,
        pose: &PredictedPose,
        coords4: Vec<[i32; 4]>,
        ss_resolution: usize,
        meter: &mut Meter,
    ) -> Result<(Vec<[i32; 3]>, Vec<[i32; 4]>)> {
        let coords: Vec<[i32; 3]> = coords4.iter().map(|c| [c[1], c[2], c[3]]).collect();
        let Some(fit) = fit else { return Ok((coords, coords4)) };
        let t = Instant::now();
        let coords = fit(pose, &coords, ss_resolution)?;
        meter.tm.shape_fit = secs(t);
        if coords.is_empty() {
            return Err(Error::msg("the shape fit left no occupied voxel (the depth leaves no room for the object in its pose)"));
        }
        let coords4 = coords.iter().map(|c| [0, c[0], c[1], c[2]]).collect();
        Ok((coords, coords4))
    }

    /// Stage-2 pair fusion: every pair's stage-2 pose tokens. Pair 1 takes
    /// the fused run's (`slat_pose`); each later pair gets a plain stage-1
    /// run of its own (noise from `rng`, after the fused run's and before the
    /// stage-2 noise), its anchor token replaced by the fused run's
    /// (`pose_tok`, normalised 10-D `[1, K, 10]`).
    fn pair_poses(
        &self,
        groups: &[Vec<ViewInputs>],
        pose_tok: &Tensor,
        slat_pose: Tensor,
        settings: &SamplerSettings,
        rng: &mut SeededRng,
        meter: &mut Meter,
    ) -> Result<Vec<Tensor>> {
        let ss_flow = self.hold(&self.resident.ss_flow, ModuleKey::SsFlow, registry::build_ss_flow, &mut meter.tm.loading)?;
        let t = Instant::now();
        let sampler = FlowEulerGuidanceIntervalSampler::new(settings.clone());
        let k = pose_tok.dim(1)?;
        let anchor = pose_tok.narrow(1, 0, 1)?;
        let mut poses = vec![slat_pose];
        for g in groups.iter().skip(1) {
            let (cond, neg) = ss_flow.condition(g)?;
            let noise = ss_flow.initial_state(rng, 1, &Device::Cpu)?;
            let out = sampler.sample(&*ss_flow, noise, &cond, Some(&neg))?;
            let own = out.get(1).ok_or_else(|| Error::msg("pipeline: stage-1 sampler returned no pose tokens"))?;
            let pinned = Tensor::cat(&[&anchor, &own.narrow(1, 1, k - 1)?], 1)?;
            poses.push(ss_pose_to_slat_pose(&pinned, &self.ss_stats, &self.slat_stats, self.layout)?);
        }
        drop(ss_flow);
        meter.tm.ss_sampling += secs(t);
        Ok(poses)
    }

    /// Steps 6–7: the stage-2 condition of each group of views with its pose
    /// tokens (one, or with stage-2 pair fusion one per pair, fused as
    /// `fusion` says), then the structured latent sampled on the occupied
    /// voxels (noise from `rng`), denormalised.
    fn sample_slat(
        &self,
        conditions: &[(Vec<ViewInputs>, Tensor)],
        fusion: Fusion,
        coords4: &[[i32; 4]],
        ss_resolution: usize,
        settings: &SamplerSettings,
        rng: &mut SeededRng,
        on_stage: &dyn Fn(Stage),
        meter: &mut Meter,
    ) -> Result<SparseTensor> {
        let slat_cfg = self.slat_cfg.as_ref().ok_or_else(|| Error::msg("pipeline: stage 2 not built"))?;
        let res = slat_cfg.resolution;
        if ss_resolution != res {
            return Err(Error::config(
                &self.config.name,
                "slat_flow.args.resolution",
                format!("{res} differs from the SS decoder's output grid {ss_resolution}"),
            ));
        }
        on_stage(Stage::SlatSampling);
        meter.mark();
        let slat_flow = self.hold(&self.resident.slat_flow, ModuleKey::SlatFlow, registry::build_slat_flow, &mut meter.tm.loading)?;
        let t = Instant::now();
        let (mut conds, mut neg) = (Vec::with_capacity(conditions.len()), None);
        for (views, pose) in conditions {
            let (c, n) = slat_flow.condition(views, Some(pose))?;
            conds.push(c);
            neg.get_or_insert(n);
        }
        let neg = neg.ok_or_else(|| Error::msg("pipeline: no views to condition stage 2 on"))?;
        meter.tm.slat_condition = secs(t);

        let t = Instant::now();
        let noise = rng.randn(&[coords4.len(), slat_cfg.in_channels], &Device::Cpu)?;
        let model = SlatVelocity { model: &slat_flow, coords: coords4 };
        let sampler = FlowEulerGuidanceIntervalSampler::new(settings.clone());
        let out = match conds.as_slice() {
            [cond] => sampler.sample(&model, vec![noise], cond, Some(&neg))?,
            _ => sampler.sample_fused(&model, vec![noise], &conds, Some(&neg), fusion)?,
        };
        drop(slat_flow);
        let feats = self.slat_norm.denormalize(&out[0])?;
        let slat = SparseTensor::new(coords4.to_vec(), feats, 1)?;
        meter.tm.slat_sampling = secs(t);
        meter.mem.slat_flow = meter.peak();
        Ok(slat)
    }

    /// Step 8: the mesh and the Gaussians of `slat`, each when `opts` asks.
    fn decode_slat(
        &self,
        slat: &SparseTensor,
        opts: &RunOptions,
        on_stage: &dyn Fn(Stage),
        meter: &mut Meter,
    ) -> Result<(Option<Mesh>, Option<Gaussians>)> {
        let r = &self.resident;
        let (mut mesh, mut gaussians) = (None, None);
        if opts.decode_mesh {
            on_stage(Stage::MeshDecoder);
            meter.mark();
            let dec = self.hold(&r.mesh_decoder, ModuleKey::SlatDecMesh, registry::build_mesh_decoder, &mut meter.tm.loading)?;
            let t = Instant::now();
            let feats = dec.forward_feats_fused(slat)?;
            meter.tm.mesh_decoder = secs(t);
            let t = Instant::now();
            mesh = Some(dec.extractor.extract_sparse(&feats)?.into_iter().next().unwrap_or_default());
            drop((dec, feats));
            meter.tm.flexicubes = secs(t);
            meter.mem.mesh_decoder = meter.peak();
        }
        if opts.decode_gaussians {
            on_stage(Stage::GaussianDecoder);
            meter.mark();
            let dec = self.hold(&r.gs_decoder, ModuleKey::SlatDecGs, registry::build_gaussian_decoder, &mut meter.tm.loading)?;
            let t = Instant::now();
            let g = dec.forward(slat)?;
            drop(dec);
            let g = g.first().ok_or_else(|| Error::msg("pipeline: Gaussian decoder returned no batch item"))?;
            gaussians = Some(g.to_gaussians()?);
            meter.tm.gaussian_decoder = secs(t);
            meter.mem.gaussian_decoder = meter.peak();
        }
        Ok((mesh, gaussians))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fake Hugging Face cache for a custom manifest: tiny random weights at
    /// the manifest's paths resolve to a loadable pipeline; an empty cache is
    /// a clear error naming the missing files and the fetch command.
    #[test]
    fn manifest_files_resolve_from_a_cache() {
        use crate::model::config::RecGenConfig;
        let root = crate::util::testing::tmp("manifest-resolve");
        let cfg_path = crate::util::testing::repo().join("models/recgen-tiny.json");
        let cfg = RecGenConfig::load(&cfg_path).unwrap();
        let files: Vec<serde_json::Value> = cfg
            .modules()
            .iter()
            .map(|(k, spec)| serde_json::json!({"path": format!("sub/{k}.safetensors"), "kind": "safetensors", "module": spec.name}))
            .collect();
        let manifest =
            serde_json::json!({"name": "tiny-test", "source": "huggingface", "repo": "recon-test/tiny", "revision": "abc", "files": files});
        let mpath = root.join("tiny-test.json");
        std::fs::create_dir_all(&root).unwrap();
        std::fs::write(&mpath, manifest.to_string()).unwrap();
        let cache = root.join("hub");
        std::fs::create_dir_all(&cache).unwrap();
        let e = crate::weights::manifest::resolve_module_files(mpath.to_str().unwrap(), &cfg, &cache, None).unwrap_err().to_string();
        assert!(e.contains("recon weights fetch --manifest tiny-test") && e.contains("ss_flow.safetensors"), "{e}");
        let snap = cache.join("models--recon-test--tiny/snapshots/abc/sub");
        crate::weights::init::write_random_architecture(&cfg_path, &snap, 3).unwrap();
        let wf = crate::weights::manifest::resolve_module_files(mpath.to_str().unwrap(), &cfg, &cache, None).unwrap();
        assert_eq!(wf.modules.len(), 6);
        assert!(wf.modules[&ModuleKey::SlatDecGs].ends_with("sub/slat_dec_gs.safetensors"));
        let p = Pipeline::load(&cfg_path, Weights::Files(&wf), Stages::All, &LoadOptions::default()).unwrap();
        assert!(p.weights().is_random());
        let _ = std::fs::remove_dir_all(&root);
    }
}
