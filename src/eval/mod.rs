//! Evaluation of reconstructions against ground truth (RecGen metrics + BOP ADD/ADD-S).
//!
//! - [`metrics`]: the metric definitions (pure functions).
//! - [`mesh`], [`knn`], [`icp`]: surface sampling, nearest neighbours, ICP alignment.
//! - [`ply`], [`mat`], [`bop`]: reading BOP-format and YCB-Video datasets.
//! - [`report`]: prediction files, [`report::evaluate`] and the report (JSON, text, SVG).
//! - [`baseline`]: the non-learned `observed` predictor (visible points → box + hull).
//!
//! Entry point for the CLI: [`run_eval`].

pub(crate) mod icp;
pub(crate) mod metrics;

pub(crate) mod baseline;
pub(crate) mod recgen;
pub(crate) mod report;

pub use self::baseline::fit_obb;
pub use self::baseline::{observe_dataset, ObservedOptions, Shape};
pub use self::icp::IcpResult;
pub use self::metrics::{add, add_s};
pub use self::metrics::{add_sb, f1_score};
pub use self::recgen::recgen_dataset;
pub use report::{evaluate, read_predictions, run_eval, EvalOptions, Prediction, PredictionsFile, Report};
