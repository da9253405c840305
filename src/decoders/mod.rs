//! decoders
pub mod flexicubes;
pub mod mesh;
pub mod mesh_post;

pub use mesh::Mesh;
