//! Wavefront OBJ writer (vertex colours as the common `v x y z r g b` extension).

use super::axes::{write_file, Axes};
use crate::mesh::Mesh;
use crate::Result;
use std::fmt::Write as _;
use std::path::Path;

/// The mesh as OBJ text, optionally with vertex colours and normals.
pub fn mesh_obj_string(mesh: &Mesh, axes: Axes, vertex_colors: bool, normals: bool) -> Result<String> {
    mesh.validate()?;
    let colors = if vertex_colors { mesh.vertex_colors() } else { None };
    let mut s = String::from("# recon\n");
    for (i, v) in mesh.vertices.iter().enumerate() {
        let p = axes.apply(*v);
        let _ = match &colors {
            Some(c) => {
                let c = c[i].map(|x| x.clamp(0.0, 1.0));
                writeln!(s, "v {} {} {} {} {} {}", p[0], p[1], p[2], c[0], c[1], c[2])
            }
            None => writeln!(s, "v {} {} {}", p[0], p[1], p[2]),
        };
    }
    if normals {
        for n in mesh.vertex_normals() {
            let n = axes.apply(n);
            let _ = writeln!(s, "vn {} {} {}", n[0], n[1], n[2]);
        }
    }
    for f in &mesh.faces {
        let [a, b, c] = f.map(|i| i + 1);
        let _ = if normals { writeln!(s, "f {a}//{a} {b}//{b} {c}//{c}") } else { writeln!(s, "f {a} {b} {c}") };
    }
    Ok(s)
}

/// Writes the mesh as an OBJ file (with normals).
pub fn save_obj(mesh: &Mesh, path: &Path, axes: Axes, vertex_colors: bool) -> Result<()> {
    write_file(path, mesh_obj_string(mesh, axes, vertex_colors, true)?.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::tetrahedron;

    #[test]
    fn obj_is_one_based_and_parses_back() {
        let s = mesh_obj_string(&tetrahedron(), Axes::ZUp, true, false).unwrap();
        let v: Vec<Vec<f32>> =
            s.lines().filter(|l| l.starts_with("v ")).map(|l| l[2..].split(' ').map(|x| x.parse().unwrap()).collect()).collect();
        assert_eq!(v, tetrahedron().vertices.iter().map(|p| p.to_vec()).collect::<Vec<_>>());
        let f: Vec<Vec<u32>> =
            s.lines().filter(|l| l.starts_with("f ")).map(|l| l[2..].split(' ').map(|x| x.parse().unwrap()).collect()).collect();
        assert_eq!(f[0], vec![1, 3, 2]);
        assert_eq!(f.len(), 4);
    }
}
