//! export: the asset formats, mesh (GLB, PLY, OBJ) and Gaussian-splat (3DGS
//! PLY) writers. The simulator formats of a settled scene (URDF, MJCF, USD)
//! live with the scene in `crate::sim`.

mod axes;
pub mod glb;
pub mod obj;
pub mod ply;
pub mod splat;

pub use axes::Axes;
pub use glb::{glb_bytes, save_glb, GlbOptions};
