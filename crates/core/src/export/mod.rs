//! export: the asset formats, mesh (GLB, PLY, OBJ; textured GLB and OBJ + MTL + PNG) and Gaussian-splat (3DGS
//! PLY) writers. The simulator formats of a settled scene (URDF, MJCF, USD)
//! live with the scene in `crate::sim`.

mod axes;
pub mod glb;
pub mod obj;
pub mod ply;
pub(crate) mod splat;
pub mod texture;

pub use self::ply::split_header;
pub use self::ply::{save_mesh_ply, PlyOptions};
pub use self::splat::save_splat_ply;
pub use axes::Axes;
pub use glb::{colored_meshes_glb_bytes, glb_bytes, save_glb, save_textured_glb, textured_glb_bytes, GlbOptions};
