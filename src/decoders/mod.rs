//! decoders
pub mod flexicubes;
pub mod gaussian;
pub mod mesh;
pub mod mesh_post;
pub mod slat_mesh;
pub mod trunk;

pub use mesh::Mesh;
