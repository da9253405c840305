//! The engine: both model stages on a frame's objects (`pipeline`), pose
//! fitting and selection against the measured depth (`pose_fit`), the
//! user-facing [`infer::Engine`] with its [`source::ModelSource`], RecGen's result
//! fields of an object (`recgen_result`), its output folder (`output`), the JSON
//! description of a view besides the anchor (`views`), and the post-hoc colour
//! calibration of its Gaussians against the photo (`posthoc_color`).

pub mod infer;
pub mod options;
pub mod output;
pub mod pipeline;
pub(crate) mod pose_fit;
pub mod posthoc_color;
pub mod recgen_result;
pub(crate) mod shape_fit;
pub(crate) mod source;
pub mod views;
pub use self::infer::*;
pub use self::options::*;
pub use self::output::*;
pub use self::pipeline::*;
pub use self::pose_fit::{free_space, geodesic_angle, mean_rotation, refine_pose, view_score, DepthView, Refined, FREE_SPACE_SAMPLES};
pub use self::pose_fit::{pose_spread, score_candidate, select_best, AlignOptions, PoseFit, SelectMethod, Surface, ViewPoints};
pub use self::recgen_result::*;
pub use self::shape_fit::{
    fit_in_pose, fit_occupancy, fit_solid, observe, rest_on_supports, Grid, MeshFrom, Observation, ShapeFit, ShapeFitOptions,
    ShapeFitReport,
};
pub use self::source::*;
pub use self::views::{OpenedView, ViewSpec, VIEW_KEYS};
pub use crate::model::sampler::{Fusion, SlatFusion};
