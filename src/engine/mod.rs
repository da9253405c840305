//! The engine: both model stages on a frame's objects ([`pipeline`]), pose
//! fitting and selection against the measured depth ([`pose_fit`]), the
//! user-facing [`infer::Engine`] with its [`source::ModelSource`], and its output
//! folder ([`output`]).

pub mod infer;
pub mod output;
pub mod pipeline;
pub mod pose_fit;
pub mod source;
