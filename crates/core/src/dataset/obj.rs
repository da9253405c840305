//! Minimal Wavefront OBJ reader for user meshes: `v x y z` (an optional `w`
//! or vertex colour after them is ignored) and `f` statements (`i`, `i/t`,
//! `i//n`, `i/t/n`; negative indices count back from the last vertex),
//! polygons fan-triangulated. Every other statement (normals, texture
//! coordinates, groups, materials, lines) is skipped. Errors name the file,
//! the line and the statement; counts are bounded by
//! [`crate::util::limits`].

use crate::mesh::trimesh::TriMesh;
use crate::util::limits::{MAX_MESH_TRIANGLES, MAX_MESH_VERTICES};
use crate::{Error, Result};

/// Parses OBJ bytes; `file` names the source in errors.
pub fn parse_obj(bytes: &[u8], file: &str) -> Result<TriMesh> {
    let mut mesh = TriMesh::default();
    let mut corners: Vec<u32> = Vec::new();
    for (n, raw) in bytes.split(|b| *b == b'\n').enumerate() {
        let line_no = n + 1;
        let bad = |stmt: &str, msg: String| Error::config(file, format!("line {line_no} (`{stmt}`)"), msg);
        let line = std::str::from_utf8(raw).map_err(|_| bad("?", "expected UTF-8 text".into()))?;
        let line = line.split('#').next().unwrap_or("").trim();
        let mut toks = line.split_ascii_whitespace();
        match toks.next() {
            Some("v") => {
                let mut v = [0.0; 3];
                for (k, x) in v.iter_mut().enumerate() {
                    let t = toks.next().ok_or_else(|| bad("v", format!("expected 3 coordinates, found {k}")))?;
                    *x = t
                        .parse::<f64>()
                        .ok()
                        .filter(|x| x.is_finite())
                        .ok_or_else(|| bad("v", format!("expected a finite number, got `{t}`")))?;
                }
                if mesh.vertices.len() as u64 >= MAX_MESH_VERTICES {
                    return Err(Error::too_large(
                        file,
                        "vertices (`v`)",
                        mesh.vertices.len() as u128 + 1,
                        MAX_MESH_VERTICES as u128,
                        "vertices",
                        format!("line {line_no}"),
                    ));
                }
                mesh.vertices.push(v);
            }
            Some("f") => {
                corners.clear();
                for t in toks {
                    let first = t.split('/').next().unwrap_or("");
                    let i: i64 = first
                        .parse()
                        .map_err(|_| bad("f", format!("expected a vertex index (`i`, `i/t`, `i//n` or `i/t/n`), got `{t}`")))?;
                    let nv = mesh.vertices.len() as i64;
                    // 1-based; negative counts back from the vertices read so far.
                    let k = if i > 0 { i - 1 } else { nv + i };
                    if i == 0 || k < 0 || k >= nv {
                        return Err(bad(
                            "f",
                            format!("vertex index {i} out of range: {nv} vertices defined so far (1..={nv} or -{nv}..=-1)"),
                        ));
                    }
                    corners.push(k as u32);
                }
                if corners.len() < 3 {
                    return Err(bad("f", format!("expected at least 3 vertices in a face, got {}", corners.len())));
                }
                if (mesh.faces.len() + corners.len() - 2) as u64 > MAX_MESH_TRIANGLES {
                    return Err(Error::too_large(
                        file,
                        "triangles (`f`)",
                        (mesh.faces.len() + corners.len() - 2) as u128,
                        MAX_MESH_TRIANGLES as u128,
                        "triangles",
                        format!("line {line_no}"),
                    ));
                }
                for k in 1..corners.len() - 1 {
                    mesh.faces.push([corners[0], corners[k], corners[k + 1]]);
                }
            }
            _ => {}
        }
    }
    if mesh.vertices.is_empty() {
        return Err(Error::config(file, "v", "expected vertices (`v x y z` lines), found none"));
    }
    if mesh.faces.is_empty() {
        return Err(Error::config(file, "f", "expected triangles or polygons (`f` lines), found none"));
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_polygons_and_index_forms() {
        let text = "# a square and a triangle\nv 0 0 0\nv 1 0 0\nv 1 1 0 1.0\nv 0 1 0 0.5 0.5 0.5\nvn 0 0 1\nvt 0 0\n\
                    g quad\nf 1/1/1 2/1/1 3//1 4\nf -4 -3 -1\nusemtl red\nl 1 2\n";
        let m = parse_obj(text.as_bytes(), "a.obj").unwrap();
        assert_eq!(m.vertices.len(), 4);
        assert_eq!(m.faces, vec![[0, 1, 2], [0, 2, 3], [0, 1, 3]]);
        assert_eq!(m.vertices[2], [1.0, 1.0, 0.0]);
    }

    #[test]
    fn bad_files_name_the_line_and_what_was_expected() {
        let e = parse_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "b.obj").unwrap_err().to_string();
        assert!(e.contains("b.obj") && e.contains("line 4 (`f`)") && e.contains("index 4 out of range"), "{e}");
        let e = parse_obj(b"v 0 0\n", "b.obj").unwrap_err().to_string();
        assert!(e.contains("line 1 (`v`)") && e.contains("3 coordinates"), "{e}");
        let e = parse_obj(b"v 0 nan 0\n", "b.obj").unwrap_err().to_string();
        assert!(e.contains("finite number"), "{e}");
        let e = parse_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n", "b.obj").unwrap_err().to_string();
        assert!(e.contains("at least 3"), "{e}");
        let e = parse_obj(b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "b.obj").unwrap_err().to_string();
        assert!(e.contains("`f`") && e.contains("found none"), "{e}");
        let e = parse_obj(b"v 0 0 0\nf 0 1 1\n", "b.obj").unwrap_err().to_string();
        assert!(e.contains("index 0 out of range"), "{e}");
        let e = parse_obj(b"\xff\xfe\n", "b.obj").unwrap_err().to_string();
        assert!(e.contains("UTF-8"), "{e}");
    }
}
