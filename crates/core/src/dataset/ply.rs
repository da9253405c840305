//! Minimal PLY reader for evaluation models: ASCII and binary (little- or big-endian);
//! reads vertex `x y z` (any numeric type) and face `vertex_indices`/`vertex_index` lists
//! (polygons fan-triangulated); every other property and element is skipped.

use crate::mesh::trimesh::TriMesh;
use crate::{Error, Result};
use std::path::Path;

#[derive(Clone, Copy, Debug, PartialEq)]
enum Ty {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Ty {
    fn parse(s: &str) -> Option<Ty> {
        Some(match s {
            "char" | "int8" => Ty::I8,
            "uchar" | "uint8" => Ty::U8,
            "short" | "int16" => Ty::I16,
            "ushort" | "uint16" => Ty::U16,
            "int" | "int32" => Ty::I32,
            "uint" | "uint32" => Ty::U32,
            "float" | "float32" => Ty::F32,
            "double" | "float64" => Ty::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Ty::I8 | Ty::U8 => 1,
            Ty::I16 | Ty::U16 => 2,
            Ty::I32 | Ty::U32 | Ty::F32 => 4,
            Ty::F64 => 8,
        }
    }
    fn read(self, b: &[u8], le: bool) -> f64 {
        macro_rules! rd {
            ($t:ty, $n:expr) => {{
                let a: [u8; $n] = b[..$n].try_into().unwrap_or([0; $n]);
                if le {
                    <$t>::from_le_bytes(a) as f64
                } else {
                    <$t>::from_be_bytes(a) as f64
                }
            }};
        }
        match self {
            Ty::I8 => b[0] as i8 as f64,
            Ty::U8 => b[0] as f64,
            Ty::I16 => rd!(i16, 2),
            Ty::U16 => rd!(u16, 2),
            Ty::I32 => rd!(i32, 4),
            Ty::U32 => rd!(u32, 4),
            Ty::F32 => rd!(f32, 4),
            Ty::F64 => rd!(f64, 8),
        }
    }
}

#[derive(Debug)]
struct Prop {
    name: String,
    /// `Some(count type)` for list properties.
    list: Option<Ty>,
    ty: Ty,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Prop>,
}

#[derive(PartialEq)]
enum Format {
    Ascii,
    Binary { le: bool },
}

/// Reads a PLY mesh (ASCII or binary; polygons split into triangles).
pub fn read_ply(path: &Path) -> Result<TriMesh> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    parse_ply(&bytes, &path.display().to_string())
}

/// Parses PLY bytes; `file` names the source in errors.
pub fn parse_ply(bytes: &[u8], file: &str) -> Result<TriMesh> {
    Ok(parse_ply_with_colors(bytes, file)?.0)
}

/// Reads a PLY mesh and its per-vertex colours (`red`, `green`, `blue`,
/// scaled to [0, 1] for `uchar`), `None` when the file has none.
pub fn read_ply_with_colors(path: &Path) -> Result<(TriMesh, Option<Vec<[f32; 3]>>)> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    parse_ply_with_colors(&bytes, &path.display().to_string())
}

/// [`parse_ply`] plus the per-vertex colours.
pub fn parse_ply_with_colors(bytes: &[u8], file: &str) -> Result<(TriMesh, Option<Vec<[f32; 3]>>)> {
    let err = |m: String| Error::input(file, m);
    // Header ends at the first "end_header" line.
    let marker = b"end_header";
    let pos = bytes.windows(marker.len()).position(|w| w == marker).ok_or_else(|| err("PLY header has no `end_header`".into()))?;
    let mut body = pos + marker.len();
    while body < bytes.len() && bytes[body] != b'\n' {
        body += 1;
    }
    body += 1;
    let header = std::str::from_utf8(&bytes[..pos]).map_err(|_| err("PLY header is not UTF-8".into()))?;
    let mut lines = header.lines().map(str::trim);
    if lines.next() != Some("ply") {
        return Err(err("not a PLY file (first line is not `ply`)".into()));
    }
    let mut format = None;
    let mut elems: Vec<Element> = Vec::new();
    for line in lines {
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.as_slice() {
            ["format", f, _] => {
                format = Some(match *f {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::Binary { le: true },
                    "binary_big_endian" => Format::Binary { le: false },
                    other => return Err(err(format!("unsupported PLY format `{other}`"))),
                })
            }
            ["element", name, n] => {
                let count = n.parse().map_err(|_| err(format!("element `{name}`: bad count `{n}`")))?;
                elems.push(Element { name: name.to_string(), count, props: vec![] });
            }
            ["property", "list", ct, it, name] => {
                let e = elems.last_mut().ok_or_else(|| err("property before any element".into()))?;
                let (c, i) = (Ty::parse(ct), Ty::parse(it));
                match (c, i) {
                    (Some(c), Some(i)) => e.props.push(Prop { name: name.to_string(), list: Some(c), ty: i }),
                    _ => return Err(err(format!("property `{name}`: unknown list types `{ct} {it}`"))),
                }
            }
            ["property", ty, name] => {
                let e = elems.last_mut().ok_or_else(|| err("property before any element".into()))?;
                let ty = Ty::parse(ty).ok_or_else(|| err(format!("property `{name}`: unknown type `{ty}`")))?;
                e.props.push(Prop { name: name.to_string(), list: None, ty });
            }
            _ => {} // comment, obj_info, blank
        }
    }
    let format = format.ok_or_else(|| err("PLY header has no `format` line".into()))?;
    let data = &bytes[body.min(bytes.len())..];
    let mut mesh = TriMesh::default();
    let mut reader: Box<dyn ValueReader + '_> = match format {
        Format::Ascii => Box::new(AsciiReader {
            toks: std::str::from_utf8(data).map_err(|_| err("ASCII PLY body is not UTF-8".into()))?.split_ascii_whitespace(),
        }),
        Format::Binary { le } => Box::new(BinReader { data, pos: 0, le }),
    };
    // Bound every element count by the data before reading a row: each value
    // takes at least one byte (ASCII: a digit; binary: its type's size), so a
    // header claiming more rows than the file can hold is refused up front
    // instead of looping or growing the mesh towards the claim.
    let mut min_bytes: u128 = 0;
    for e in &elems {
        let row: u128 = match format {
            Format::Ascii => e.props.len() as u128,
            Format::Binary { .. } => e.props.iter().map(|p| p.list.unwrap_or(p.ty).size() as u128).sum(),
        };
        let need = row.saturating_mul(e.count as u128);
        let room = (data.len() as u128).saturating_sub(min_bytes);
        if need > room {
            let limit = room.checked_div(row).unwrap_or(0);
            return Err(Error::too_large(
                file,
                format!("element `{}` count", e.name),
                e.count as u128,
                limit,
                "rows",
                format!("{} data bytes left hold at most {limit} rows of {row} bytes", room),
            ));
        }
        min_bytes += need;
    }
    let n_vertices = elems.iter().find(|e| e.name == "vertex").map_or(0, |e| e.count);
    let mut colors: Vec<[f32; 3]> = Vec::new();
    for e in &elems {
        let is_vertex = e.name == "vertex";
        let is_face = e.name == "face";
        let xyz: Vec<Option<usize>> =
            ["x", "y", "z"].iter().map(|n| e.props.iter().position(|p| p.name == *n && p.list.is_none())).collect();
        if is_vertex && xyz.iter().any(Option::is_none) {
            return Err(err("element `vertex` lacks one of the properties x, y, z".into()));
        }
        let rgb: Vec<Option<usize>> =
            ["red", "green", "blue"].iter().map(|n| e.props.iter().position(|p| p.name == *n && p.list.is_none())).collect();
        let has_rgb = is_vertex && rgb.iter().all(Option::is_some);
        // uchar colours are 0..255; float colours are taken as 0..1.
        let rgb_scale = if has_rgb && e.props[rgb[0].unwrap_or(0)].ty == Ty::U8 { 1.0 / 255.0 } else { 1.0 };
        let rows = if e.props.is_empty() { 0 } else { e.count };
        for row in 0..rows {
            let mut v = [0.0; 3];
            let mut c = [0f32; 3];
            for (pi, p) in e.props.iter().enumerate() {
                let ctx = || format!("element `{}` row {row} property `{}`", e.name, p.name);
                match p.list {
                    None => {
                        let x = reader.next(p.ty).ok_or_else(|| err(format!("{}: unexpected end of data", ctx())))?;
                        if is_vertex {
                            for k in 0..3 {
                                if xyz[k] == Some(pi) {
                                    v[k] = x;
                                }
                                if has_rgb && rgb[k] == Some(pi) {
                                    c[k] = (x * rgb_scale) as f32;
                                }
                            }
                        }
                    }
                    Some(ct) => {
                        let n = reader.next(ct).ok_or_else(|| err(format!("{}: unexpected end of data", ctx())))?;
                        if !(0.0..=1e6).contains(&n) {
                            return Err(err(format!("{}: bad list length {n}", ctx())));
                        }
                        let mut idx = Vec::with_capacity(n as usize);
                        for _ in 0..n as usize {
                            idx.push(reader.next(p.ty).ok_or_else(|| err(format!("{}: unexpected end of data", ctx())))?);
                        }
                        if is_face && (p.name == "vertex_indices" || p.name == "vertex_index") {
                            for k in 1..idx.len().saturating_sub(1) {
                                let tri = [idx[0], idx[k], idx[k + 1]];
                                let mut f = [0u32; 3];
                                for (j, &i) in tri.iter().enumerate() {
                                    if i < 0.0 || i.fract() != 0.0 || i as usize >= n_vertices {
                                        return Err(err(format!("{}: vertex index {i} out of range", ctx())));
                                    }
                                    f[j] = i as u32;
                                }
                                mesh.faces.push(f);
                            }
                        }
                    }
                }
            }
            if is_vertex {
                mesh.vertices.push(v);
                if has_rgb {
                    colors.push(c);
                }
            }
        }
    }
    if mesh.vertices.is_empty() {
        return Err(err("PLY has no vertices".into()));
    }
    let colors = (colors.len() == mesh.vertices.len()).then_some(colors);
    Ok((mesh, colors))
}

trait ValueReader {
    fn next(&mut self, ty: Ty) -> Option<f64>;
}

struct AsciiReader<'a> {
    toks: std::str::SplitAsciiWhitespace<'a>,
}

impl ValueReader for AsciiReader<'_> {
    fn next(&mut self, _ty: Ty) -> Option<f64> {
        self.toks.next()?.parse().ok()
    }
}

struct BinReader<'a> {
    data: &'a [u8],
    pos: usize,
    le: bool,
}

impl ValueReader for BinReader<'_> {
    fn next(&mut self, ty: Ty) -> Option<f64> {
        let end = self.pos + ty.size();
        let b = self.data.get(self.pos..end)?;
        self.pos = end;
        Some(ty.read(b, self.le))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ascii_and_binary_agree() {
        let ascii = "ply\nformat ascii 1.0\ncomment x\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 255\n1 0 0 0\n1 1 0 0\n0 1 0.5 9\n4 0 1 2 3\n";
        let a = parse_ply(ascii.as_bytes(), "a.ply").unwrap();
        assert_eq!(a.faces, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(a.vertices[3], [0.0, 1.0, 0.5]);

        let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty double z\nproperty float nx\nelement face 2\nproperty list uchar uint vertex_indices\nproperty uchar flags\nend_header\n".to_vec();
        for v in &a.vertices {
            for c in v {
                b.extend_from_slice(&c.to_le_bytes());
            }
            b.extend_from_slice(&1.5f32.to_le_bytes());
        }
        for f in &a.faces {
            b.push(3);
            for i in f {
                b.extend_from_slice(&i.to_le_bytes());
            }
            b.push(7);
        }
        let m = parse_ply(&b, "b.ply").unwrap();
        assert_eq!(m.vertices, a.vertices);
        assert_eq!(m.faces, a.faces);
        // Truncated data and bad indices are reported with the file name.
        let e = parse_ply(&b[..b.len() - 3], "b.ply").unwrap_err().to_string();
        assert!(e.contains("b.ply") && e.contains("face"), "{e}");
        let bad = ascii.replace("4 0 1 2 3", "3 0 1 9");
        assert!(parse_ply(bad.as_bytes(), "c.ply").unwrap_err().to_string().contains("out of range"));
    }

    #[test]
    fn vertex_colours_are_read_when_complete() {
        let ply = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 255 0 0\n1 0 0 0 255 0\n0 1 0 0 0 51\n3 0 1 2\n";
        let (m, c) = parse_ply_with_colors(ply.as_bytes(), "c.ply").unwrap();
        assert_eq!(m.faces, vec![[0, 1, 2]]);
        assert_eq!(c.unwrap(), vec![[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.2]]);
        // Only `red`: no colours.
        let red_only = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n0 0 0 1\n1 0 0 2\n0 1 0 3\n";
        assert!(parse_ply_with_colors(red_only.as_bytes(), "r.ply").unwrap().1.is_none());
    }
}
