//! The engine: both model stages on a frame's objects ([`pipeline`]), pose
//! fitting and selection against the measured depth ([`pose_fit`]), the
//! user-facing [`infer::Engine`] with its [`source::ModelSource`], and its output
//! folder ([`output`]).

pub(crate) mod infer;
pub(crate) mod output;
pub(crate) mod pipeline;
pub(crate) mod pose_fit;
pub(crate) mod source;
pub use self::infer::{match_views, Engine, InferOptions, ObjectResult, Progress, RigidTransform, SecondView, DEFAULT_MAX_FACES};
pub use self::output::{begin_output, finish_output, write_outputs, MARKER};
pub use self::pipeline::{
    LoadOptions, ObjectInputs, ObjectReconstruction, Pipeline, RunOptions, Stage, Stages, ViewInput, Weights, WeightsSource,
};
pub use self::pose_fit::{free_space, geodesic_angle, mean_rotation, refine_pose, view_score, DepthView, Refined, FREE_SPACE_SAMPLES};
pub use self::pose_fit::{pose_spread, score_candidate, select_best, AlignOptions, PoseFit, SelectMethod, Surface, ViewPoints};
pub use self::source::ModelSource;
