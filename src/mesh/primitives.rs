//! Primitive meshes that tests, synthetic scenes and baselines share.

use crate::mesh::trimesh::TriMesh;
use crate::mesh::Mesh;
use crate::spatial::P3;

/// A closed, outward-oriented tetrahedron.
pub fn tetrahedron() -> Mesh {
    Mesh {
        vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        faces: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
        vertex_attrs: None,
    }
}

/// A closed box mesh `[-h, h]`, outward-facing triangles.
pub fn box_mesh(h: P3) -> TriMesh {
    let vertices = (0..8).map(|i| [if i & 1 == 1 { h[0] } else { -h[0] }, if i & 2 == 2 { h[1] } else { -h[1] }, if i & 4 == 4 { h[2] } else { -h[2] }]).collect();
    let faces = vec![[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]];
    TriMesh { vertices, faces }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tetrahedron_is_closed() {
        assert!(tetrahedron().topology().is_closed_oriented_manifold());
    }
}
