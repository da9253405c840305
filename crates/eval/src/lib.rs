//! Evaluation of reconstructions against ground truth (RecGen metrics + BOP ADD/ADD-S).
//!
//! - `metrics`: the metric definitions (pure functions), `icp`: ICP alignment
//!   (surface sampling and nearest neighbours are `recon_core::mesh` and `recon_core::spatial`;
//!   the BOP and YCB-Video readers are `recon_core::dataset`).
//! - `report`: prediction files, [`evaluate`] and the report (JSON, text, SVG).
//! - `baseline`: the non-learned `observed` predictor (visible points → box + hull).
//! - `recgen`: the model as a predictor on every GT instance.
//! - `correction`: a depth audit's depth correction applied to a dataset's frames first.
//!
//! Entry point for the CLI: [`run_eval`].

// Clippy lints allowed crate-wide, for the reasons given in recon-core's lib.rs.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord, clippy::too_many_arguments, clippy::type_complexity)]
#![warn(missing_docs)]

pub(crate) mod icp;
pub(crate) mod metrics;

pub(crate) mod baseline;
pub(crate) mod correction;
pub(crate) mod recgen;
pub(crate) mod report;

pub use self::baseline::fit_obb;
pub use self::baseline::{observe_dataset, observe_dataset_corrected, ObservedOptions, Shape};
pub use self::correction::DatasetCorrection;
pub use self::icp::IcpResult;
pub use self::metrics::{add, add_s};
pub use self::metrics::{add_sb, f1_score};
pub use self::recgen::{recgen_dataset, recgen_dataset_corrected, recgen_dataset_views};
pub use report::{evaluate, read_predictions, run_eval, EvalOptions, Prediction, PredictionsFile, Report};
