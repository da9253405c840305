//! Evaluation of reconstructions against ground truth (RecGen metrics + BOP ADD/ADD-S).
//!
//! - [`metrics`]: the metric definitions (pure functions).
//! - [`mesh`], [`knn`], [`icp`]: surface sampling, nearest neighbours, ICP alignment.
//! - [`ply`], [`mat`], [`bop`]: reading BOP-format and YCB-Video datasets.
//! - [`report`]: prediction files, [`report::evaluate`] and the report (JSON, text, SVG).
//! - [`baseline`]: the non-learned `observed` predictor (visible points → box + hull).
//!
//! Entry point for the CLI: [`run_eval`].

pub mod icp;
pub mod metrics;

pub mod baseline;
pub mod recgen;
pub mod report;

pub use report::{evaluate, read_predictions, run_eval, EvalOptions, Prediction, PredictionsFile, Report};
