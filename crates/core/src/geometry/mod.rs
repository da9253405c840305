//! Geometry: object poses (rotation encodings, normalisation), point maps and
//! their crops, the support plane, and mesh voxelisation.

pub mod camera_pose;
pub mod plane;
pub mod pointmap;
pub mod pose;
pub mod voxelize;
pub use self::camera_pose::{canonical_to_camera, parse_rel_pose, pose_to_camera, pose_to_normalised, rel_pose_from_numbers};
pub use self::plane::{fit_plane, least_squares_plane, world_from_camera, Plane, PlaneFit, PlaneFitOptions};
pub use self::pointmap::project;
pub use self::pointmap::{object_points, prepare_frame_objects, prepare_object, Normaliser, PrepareOptions};
pub use self::pose::{pose_to_similarity, similarity_to_pose, Pose, PoseStats};
pub use self::voxelize::Fill;
