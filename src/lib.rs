//! recon: RGB-D frames + object masks → posed meshes and 3D Gaussians.
//!
//! Modules follow the data's path through the system:
//! inputs → geometry → model (stage 1, stage 2) → sparse → decoders → export;
//! `train` fits the models on synthetic data.
//! `conformance` checks every model stage against upstream golden fixtures.

pub mod error;
pub mod config;
pub mod weights;
pub mod inputs;
pub mod geometry;
pub mod model;
pub mod sparse;
pub mod decoders;
pub mod export;
pub mod pipeline;
pub mod infer;
pub mod bench;
pub mod conformance;
pub mod eval;
pub mod sensor;
pub mod train;
pub mod synth;
pub mod audit;
pub mod sim;

pub use error::{Error, Result};
