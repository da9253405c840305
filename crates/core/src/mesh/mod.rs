//! Triangle meshes: [`Mesh`] (f32, indexed, as the mesh decoder produces and
//! the exporters write), [`TriMesh`] (f64, for measurement), post-processing,
//! and the primitive meshes that tests, synthetic scenes and baselines share.

pub mod atlas;
mod indexed;
pub(crate) mod isosurface;
pub mod post;
pub mod primitives;
pub mod trimesh;
pub use self::atlas::{uv_atlas, AtlasOptions, Texture, TexturedMesh, UvMesh};
pub use self::indexed::*;
pub use self::isosurface::{marching_tetrahedra, ScalarGrid};
pub use self::post::{
    decimate, drop_floaters, face_components, keep_largest_component, mesh_quality, remove_small_components, remove_unreferenced_vertices,
    taubin_smooth, to_u8, transfer_colors, vertex_colors_u8, MeshQuality,
};
pub use self::primitives::{
    bowl_mesh, box_between, box_corners, box_mesh, cuboid, cup_mesh, cylinder_mesh, flat_grid, sphere_mesh, tetrahedron, torus_mesh,
};
pub use self::trimesh::TriMesh;
