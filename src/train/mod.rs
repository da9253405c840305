//! Training of the recgen-nano models on CPU, in candle (issue 9).
//!
//! Modules follow the data's path: [`data`] (what a dataset provides and how
//! a sample becomes inputs and targets; [`bop`] reads `recon synth`'s BOP
//! output, [`toy`] renders primitive objects for tests), [`params`]
//! (`VarMap`-backed parameters and their initialisation), [`flow`] (the
//! flow-matching objective in the sampler's conventions), [`objective`]
//! (the SS VAE and SS flow losses), [`optim`] (AdamW with checkpointable
//! state, gradient clipping), [`trainer`] (loop, checkpoints, resume) and
//! [`log`] (loss log and plot).
//!
//! Every model is built unchanged on `VarBuilder::from_varmap` and trained
//! through its plain candle-ops path: the SS decoder's
//! `forward_differentiable` (its fast kernels are inference-only), and the
//! transformers' attention softmax, whose forward is candle's kernel and
//! whose backward is [`crate::model::nn::common::softmax_last_dim`]'s.
//!
//! Recipe (stage 1): `recon train ss-vae` learns the SS VAE on the
//! voxelised object models; `recon train ss-flow --vae <ss-vae out>` then
//! learns the image encoder (DINOv2 architecture, from scratch) and the flow
//! transformer with pose tokens on the frozen encoder's latents, and writes
//! the pose statistics of its training set. Stage 2: `recon train slat-ae`
//! learns the structured-latent encoder and the mesh and Gaussian decoders
//! from exact signed distances and colours of the object models ([`slat`]).
//! `recon train slat-flow` then learns the structured-latent flow on the
//! frozen encoder's latents ([`slat_flow`]) and writes the complete model
//! folder (every module, pose statistics, latent normalisation).

pub mod bop;
pub mod data;
pub mod flow;
pub mod log;
pub mod objective;
pub mod optim;
pub mod params;
pub mod run;
pub mod slat;
pub mod slat_flow;
pub mod toy;
pub mod trainer;
