//! Wavefront OBJ writer (vertex colours as the common `v x y z r g b` extension),
//! and textured OBJ + MTL (`vt`, `map_Kd`) beside a PNG.

use super::axes::{write_file, Axes};
use crate::mesh::{Mesh, TexturedMesh};
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

/// A textured mesh as OBJ text: `mtllib`, `usemtl`, `v`, `vt` (OBJ's v up:
/// `1 - v` of the atlas's glTF convention), `vn` and `f v/vt/vn`.
pub fn textured_obj_string(tm: &TexturedMesh, axes: Axes, mtl_file: &str, material: &str) -> Result<String> {
    let mesh = &tm.atlas.mesh;
    mesh.validate()?;
    if tm.atlas.uv.len() != mesh.vertices.len() || tm.atlas.normals.len() != mesh.vertices.len() {
        return Err(crate::Error::msg(format!("obj: {} UVs for {} vertices", tm.atlas.uv.len(), mesh.vertices.len())));
    }
    let mut s = format!("# recon\nmtllib {mtl_file}\n");
    for v in &mesh.vertices {
        let p = axes.apply(*v);
        let _ = writeln!(s, "v {} {} {}", p[0], p[1], p[2]);
    }
    for t in &tm.atlas.uv {
        let _ = writeln!(s, "vt {} {}", t[0], 1.0 - t[1]);
    }
    for n in &tm.atlas.normals {
        let n = axes.apply(*n);
        let _ = writeln!(s, "vn {} {} {}", n[0], n[1], n[2]);
    }
    let _ = writeln!(s, "usemtl {material}");
    for f in &mesh.faces {
        let [a, b, c] = f.map(|i| i + 1);
        let _ = writeln!(s, "f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}");
    }
    Ok(s)
}

/// The MTL text of one matte material whose diffuse colour is `texture_file`.
pub fn mtl_string(material: &str, texture_file: &str) -> String {
    format!("# recon\nnewmtl {material}\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd {texture_file}\n")
}

/// Writes `<stem>.obj`, `<stem>.mtl` and `texture_file` (PNG) into `dir`:
/// the textured mesh as [`textured_obj_string`] and [`mtl_string`] write it.
pub fn save_textured_obj(tm: &TexturedMesh, dir: &Path, stem: &str, texture_file: &str, axes: Axes) -> Result<()> {
    let mtl = format!("{stem}.mtl");
    write_file(&dir.join(format!("{stem}.obj")), textured_obj_string(tm, axes, &mtl, stem)?.as_bytes())?;
    write_file(&dir.join(&mtl), mtl_string(stem, texture_file).as_bytes())?;
    super::texture::save_png(&tm.texture, &dir.join(texture_file))
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

    #[test]
    fn textured_obj_refers_to_its_mtl_and_png() {
        let m = crate::mesh::primitives::box_mesh(0.1, 0.1, 0.1);
        let atlas = crate::mesh::uv_atlas(&m, &crate::mesh::AtlasOptions::for_size(64)).unwrap();
        let tm = TexturedMesh { atlas, texture: crate::mesh::Texture { width: 64, height: 64, rgb: vec![7; 64 * 64 * 3] } };
        let dir = std::env::temp_dir().join(format!("recon-obj-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        save_textured_obj(&tm, &dir, "visual", "texture.png", Axes::ZUp).unwrap();
        let obj = std::fs::read_to_string(dir.join("visual.obj")).unwrap();
        assert!(obj.contains("mtllib visual.mtl\n") && obj.contains("usemtl visual\n"));
        assert_eq!(obj.lines().filter(|l| l.starts_with("vt ")).count(), tm.atlas.uv.len());
        let f: Vec<&str> = obj.lines().filter(|l| l.starts_with("f ")).collect();
        assert_eq!(f.len(), m.faces.len());
        for l in &f {
            for c in l[2..].split(' ') {
                let i: Vec<usize> = c.split('/').map(|x| x.parse().unwrap()).collect();
                assert!(i.len() == 3 && i.iter().all(|&k| (1..=tm.atlas.uv.len()).contains(&k)), "{l}");
            }
        }
        let mtl = std::fs::read_to_string(dir.join("visual.mtl")).unwrap();
        assert!(mtl.contains("newmtl visual\n") && mtl.contains("map_Kd texture.png\n"));
        let png = image::open(dir.join("texture.png")).unwrap().to_rgb8();
        assert_eq!(png.into_raw(), tm.texture.rgb);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
