//! Pose fitting: every predicted pose is scored against the observed points
//! ([`score`]), optionally refined against the measured depth with a
//! free-space term ([`free_space`], [`refine`]), and the best candidate over
//! views and samples is chosen ([`select`]).

pub(crate) mod free_space;
pub(crate) mod options;
pub(crate) mod refine;
pub(crate) mod score;
pub(crate) mod select;

pub use free_space::{free_space, DepthView, ViewPoints};
pub use options::{AlignOptions, PoseFit, FREE_SPACE_SAMPLES};
pub use refine::{refine_pose, Refined};
pub use score::{score_candidate, view_score, CandidateScore, Surface};
pub use select::{geodesic_angle, mean_rotation, pose_spread, select_best, PoseSpread, SelectMethod};
