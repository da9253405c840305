//! Training of the recgen-nano models on CPU, in candle (issue 9).
//!
//! Modules follow the data's path: `data` (what a dataset provides and how
//! a sample becomes inputs and targets; `bop` reads `recon synth`'s BOP
//! output, `toy` renders primitive objects for tests), `params`
//! (`VarMap`-backed parameters and their initialisation), `flow` (the
//! flow-matching objective in the sampler's conventions), `objective`
//! (the SS VAE and SS flow losses), `optim` (AdamW with checkpointable
//! state, gradient clipping), `trainer` (loop, checkpoints, resume) and
//! `log` (loss log and plot).
//!
//! Every model is built unchanged on `VarBuilder::from_varmap` and trained
//! through its plain candle-ops path: the SS decoder's
//! `forward_differentiable` (its fast kernels are inference-only), and the
//! transformers' attention softmax, whose forward is candle's kernel and
//! whose backward is `recon_core::model::nn::common::softmax_last_dim`'s.
//!
//! Recipe (stage 1): `recon train ss-vae` learns the SS VAE on the
//! voxelised object models; `recon train ss-flow --vae <ss-vae out>` then
//! learns the image encoder (DINOv2 architecture, from scratch) and the flow
//! transformer with pose tokens on the frozen encoder's latents, and writes
//! the pose statistics of its training set. Stage 2: `recon train slat-ae`
//! learns the structured-latent encoder and the mesh and Gaussian decoders
//! from exact signed distances and colours of the object models (`slat`).
//! `recon train slat-flow` then learns the structured-latent flow on the
//! frozen encoder's latents (`slat_flow`) and writes the complete model
//! folder (every module, pose statistics, latent normalisation).

// Clippy lints allowed crate-wide, for the reasons given in recon-core's lib.rs.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord, clippy::too_many_arguments, clippy::type_complexity)]
#![warn(missing_docs)]

pub(crate) mod bop;
pub(crate) mod data;
pub(crate) mod flow;
pub(crate) mod log;
pub(crate) mod objective;
pub(crate) mod optim;
pub(crate) mod params;
pub(crate) mod run;
pub(crate) mod slat;
pub(crate) mod slat_flow;
pub(crate) mod toy;
pub(crate) mod trainer;
pub use self::bop::{BopOptions, BopSource};
pub use self::data::{canonical_frame, pose_stats_json, prepare_train_view, scan, TrainingSource};
pub use self::flow::FlowMatching;
pub use self::objective::{FlowObjective, Objective, VaeObjective};
pub use self::optim::{clip_grad_norm, AdamW};
pub use self::params::ModuleParams;
pub use self::run::{run, Resume, Stage, TrainOptions};
pub use self::toy::{micro_architecture, ToyConfig, ToySource};
