//! Evaluation of reconstructions against ground truth (RecGen metrics + BOP ADD/ADD-S).
//!
//! - `metrics`: the metric definitions (pure functions), `icp`: ICP alignment
//!   (surface sampling and nearest neighbours are `crate::mesh` and `crate::spatial`;
//!   the BOP and YCB-Video readers are `crate::dataset`).
//! - `report`: prediction files, [`evaluate`] and the report (JSON, text, SVG).
//! - `baseline`: the non-learned `observed` predictor (visible points → box + hull).
//! - `recgen`: the model as a predictor on every GT instance.
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
