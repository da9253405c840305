//! Binary little-endian PLY mesh writer (optional normals and RGB colours).

use super::axes::{write_file, Axes};
use crate::mesh::post::to_u8;
use crate::mesh::Mesh;
use crate::Result;
use std::path::Path;

#[derive(Debug, Clone, Copy)]
/// Settings of the mesh PLY writer.
pub struct PlyOptions {
    /// Output axes.
    pub axes: Axes,
    /// Write per-vertex normals.
    pub normals: bool,
    /// Write `red green blue` (uchar) from the vertex attributes when present.
    pub vertex_colors: bool,
}

impl Default for PlyOptions {
    fn default() -> Self {
        PlyOptions { axes: Axes::ZUp, normals: false, vertex_colors: true }
    }
}

/// The mesh as binary little-endian PLY bytes.
pub fn mesh_ply_bytes(mesh: &Mesh, opts: &PlyOptions) -> Result<Vec<u8>> {
    mesh.validate()?;
    let colors = if opts.vertex_colors { mesh.vertex_colors() } else { None };
    let normals = opts.normals.then(|| mesh.vertex_normals());
    let mut h = String::from("ply\nformat binary_little_endian 1.0\ncomment recon\n");
    h += &format!("element vertex {}\nproperty float x\nproperty float y\nproperty float z\n", mesh.vertices.len());
    if normals.is_some() {
        h += "property float nx\nproperty float ny\nproperty float nz\n";
    }
    if colors.is_some() {
        h += "property uchar red\nproperty uchar green\nproperty uchar blue\n";
    }
    h += &format!("element face {}\nproperty list uchar int vertex_indices\nend_header\n", mesh.faces.len());
    let mut out = h.into_bytes();
    for (i, v) in mesh.vertices.iter().enumerate() {
        for x in opts.axes.apply(*v) {
            out.extend_from_slice(&x.to_le_bytes());
        }
        if let Some(n) = &normals {
            for x in opts.axes.apply(n[i]) {
                out.extend_from_slice(&x.to_le_bytes());
            }
        }
        if let Some(c) = &colors {
            out.extend(c[i].map(to_u8));
        }
    }
    for f in &mesh.faces {
        out.push(3);
        for &i in f {
            out.extend_from_slice(&(i as i32).to_le_bytes());
        }
    }
    Ok(out)
}

/// Writes the mesh as a binary PLY file.
pub fn save_mesh_ply(mesh: &Mesh, path: &Path, opts: &PlyOptions) -> Result<()> {
    write_file(path, &mesh_ply_bytes(mesh, opts)?)
}

/// Split a PLY image into its header lines and binary body.
pub fn split_header(b: &[u8]) -> Option<(Vec<String>, &[u8])> {
    let end = b.windows(11).position(|w| w == b"end_header\n")? + 11;
    let head = std::str::from_utf8(&b[..end]).ok()?;
    Some((head.lines().map(|l| l.to_string()).collect(), &b[end..]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::tetrahedron;

    #[test]
    fn header_and_body_sizes() {
        let mut mesh = tetrahedron();
        mesh.vertex_attrs = Some(vec![[1.0, 0.5, 0.0, 0.0, 0.0, 0.0]; 4]);
        let b = mesh_ply_bytes(&mesh, &PlyOptions { normals: true, ..Default::default() }).unwrap();
        let (head, body) = split_header(&b).unwrap();
        assert_eq!(head[0], "ply");
        assert_eq!(head[1], "format binary_little_endian 1.0");
        assert!(head.contains(&"element vertex 4".to_string()));
        assert!(head.contains(&"element face 4".to_string()));
        let props: Vec<&str> = head.iter().filter(|l| l.starts_with("property")).map(|l| l.as_str()).collect();
        assert_eq!(props.len(), 10);
        assert_eq!(props[3], "property float nx");
        assert_eq!(props[6], "property uchar red");
        assert_eq!(head.last().unwrap(), "end_header");
        let vsize = 6 * 4 + 3;
        assert_eq!(body.len(), 4 * vsize + 4 * 13);
        // First vertex colour bytes, then first face record.
        assert_eq!(&body[24..27], &[255, 128, 0]);
        let f0 = &body[4 * vsize..4 * vsize + 13];
        assert_eq!(f0[0], 3);
        assert_eq!(i32::from_le_bytes(f0[5..9].try_into().unwrap()), 2);
    }

    #[test]
    fn plain_mesh_has_no_colour_properties() {
        let b = mesh_ply_bytes(&tetrahedron(), &PlyOptions::default()).unwrap();
        let (head, body) = split_header(&b).unwrap();
        assert!(!head.iter().any(|l| l.contains("red")));
        assert_eq!(body.len(), 4 * 12 + 4 * 13);
    }
}
