//! Binary glTF 2.0 (GLB) mesh writer: POSITION, NORMAL, optional COLOR_0,
//! u32 indices, one primitive, one node.

use super::{write_file, Axes};
use crate::decoders::Mesh;
use crate::{Error, Result};
use serde_json::json;
use std::path::Path;

const GLB_MAGIC: u32 = 0x4654_6C67; // "glTF"
const CHUNK_JSON: u32 = 0x4E4F_534A; // "JSON"
const CHUNK_BIN: u32 = 0x004E_4942; // "BIN\0"
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;

#[derive(Debug, Clone, Copy)]
pub struct GlbOptions {
    /// Output axes (TRELLIS exports y-up).
    pub axes: Axes,
    /// Write COLOR_0 from the mesh's vertex attributes when present.
    pub vertex_colors: bool,
}

impl Default for GlbOptions {
    fn default() -> Self {
        GlbOptions { axes: Axes::YUp, vertex_colors: true }
    }
}

/// Serialise `mesh` as a GLB file image.
pub fn glb_bytes(mesh: &Mesh, opts: &GlbOptions) -> Result<Vec<u8>> {
    mesh.validate()?;
    if mesh.vertices.is_empty() || mesh.faces.is_empty() {
        return Err(Error::msg("glb: mesh is empty"));
    }
    let positions: Vec<[f32; 3]> = mesh.vertices.iter().map(|&v| opts.axes.apply(v)).collect();
    // Unreferenced vertices have no normal; glTF wants unit normals everywhere.
    let normals: Vec<[f32; 3]> = mesh
        .vertex_normals()
        .into_iter()
        .map(|n| if n == [0.0; 3] { [0.0, 0.0, 1.0] } else { n })
        .map(|n| opts.axes.apply(n))
        .collect();
    let colors = if opts.vertex_colors { mesh.vertex_colors() } else { None }
        .map(|c| c.into_iter().map(|c| c.map(|x| x.clamp(0.0, 1.0))).collect::<Vec<_>>());

    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut push_view = |bin: &mut Vec<u8>, bytes: &[u8], target: u32| -> usize {
        // Every view starts 4-byte aligned (all components are 4 bytes).
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len(), "target": target}));
        bin.extend_from_slice(bytes);
        views.len() - 1
    };

    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in &positions {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let n = positions.len();
    let v = push_view(&mut bin, &f32_bytes(&positions), ARRAY_BUFFER);
    accessors.push(json!({"bufferView": v, "componentType": FLOAT, "count": n, "type": "VEC3", "min": lo, "max": hi}));
    let v = push_view(&mut bin, &f32_bytes(&normals), ARRAY_BUFFER);
    accessors.push(json!({"bufferView": v, "componentType": FLOAT, "count": n, "type": "VEC3"}));
    let mut attributes = json!({"POSITION": 0, "NORMAL": 1});
    if let Some(c) = &colors {
        let v = push_view(&mut bin, &f32_bytes(c), ARRAY_BUFFER);
        accessors.push(json!({"bufferView": v, "componentType": FLOAT, "count": n, "type": "VEC3"}));
        attributes["COLOR_0"] = json!(accessors.len() - 1);
    }
    let idx: Vec<u8> = mesh.faces.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
    let v = push_view(&mut bin, &idx, ELEMENT_ARRAY_BUFFER);
    accessors.push(json!({"bufferView": v, "componentType": UNSIGNED_INT, "count": mesh.faces.len() * 3, "type": "SCALAR"}));
    let indices = accessors.len() - 1;
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }

    let doc = json!({
        "asset": {"version": "2.0", "generator": "recon"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": attributes, "indices": indices, "mode": 4, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"byteLength": bin.len()}],
    });
    let mut json_bytes = serde_json::to_vec(&doc).map_err(|e| Error::msg(format!("glb: {e}")))?;
    while !json_bytes.len().is_multiple_of(4) {
        json_bytes.push(b' ');
    }
    let total = 12 + 8 + json_bytes.len() + 8 + bin.len();
    let total32 = u32::try_from(total).map_err(|_| Error::msg("glb: file over 4 GiB"))?;
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(&GLB_MAGIC.to_le_bytes());
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&total32.to_le_bytes());
    out.extend_from_slice(&(json_bytes.len() as u32).to_le_bytes());
    out.extend_from_slice(&CHUNK_JSON.to_le_bytes());
    out.extend_from_slice(&json_bytes);
    out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
    out.extend_from_slice(&CHUNK_BIN.to_le_bytes());
    out.extend_from_slice(&bin);
    Ok(out)
}

/// Write `mesh` to a `.glb` file.
pub fn save_glb(mesh: &Mesh, path: &Path, opts: &GlbOptions) -> Result<()> {
    write_file(path, &glb_bytes(mesh, opts)?)
}

fn f32_bytes<const K: usize>(rows: &[[f32; K]]) -> Vec<u8> {
    rows.iter().flatten().flat_map(|x| x.to_le_bytes()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::tests::tetrahedron;

    fn u32_at(b: &[u8], o: usize) -> u32 {
        u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
    }

    #[test]
    fn glb_layout_round_trips() {
        let mut mesh = tetrahedron();
        mesh.vertex_attrs = Some(vec![[0.1, 0.2, 0.3, 0.5, 0.5, 1.0]; 4]);
        let b = glb_bytes(&mesh, &GlbOptions::default()).unwrap();
        assert_eq!(u32_at(&b, 0), GLB_MAGIC);
        assert_eq!(u32_at(&b, 4), 2);
        assert_eq!(u32_at(&b, 8) as usize, b.len());
        assert_eq!(b.len() % 4, 0);
        let jlen = u32_at(&b, 12) as usize;
        assert_eq!(jlen % 4, 0);
        assert_eq!(u32_at(&b, 16), CHUNK_JSON);
        let doc: serde_json::Value = serde_json::from_slice(&b[20..20 + jlen]).unwrap();
        let bo = 20 + jlen;
        let blen = u32_at(&b, bo) as usize;
        assert_eq!(u32_at(&b, bo + 4), CHUNK_BIN);
        assert_eq!(blen % 4, 0);
        assert_eq!(bo + 8 + blen, b.len());
        assert_eq!(doc["buffers"][0]["byteLength"].as_u64().unwrap() as usize, blen);
        let bin = &b[bo + 8..];

        let prim = &doc["meshes"][0]["primitives"][0];
        let acc = |name: &str| &doc["accessors"][prim["attributes"][name].as_u64().unwrap() as usize];
        assert_eq!(acc("POSITION")["count"], 4);
        assert_eq!(acc("NORMAL")["count"], 4);
        assert_eq!(acc("COLOR_0")["count"], 4);
        let ind = &doc["accessors"][prim["indices"].as_u64().unwrap() as usize];
        assert_eq!(ind["count"], 12);
        assert_eq!(ind["componentType"], UNSIGNED_INT);
        for v in doc["bufferViews"].as_array().unwrap() {
            let off = v["byteOffset"].as_u64().unwrap() as usize;
            assert_eq!(off % 4, 0);
            assert!(off + v["byteLength"].as_u64().unwrap() as usize <= blen);
        }
        // POSITION min/max match the y-up rotated data: (x, y, z) -> (x, z, -y).
        let view = &doc["bufferViews"][acc("POSITION")["bufferView"].as_u64().unwrap() as usize];
        let off = view["byteOffset"].as_u64().unwrap() as usize;
        let first: Vec<f32> = (0..3).map(|k| f32::from_le_bytes(bin[off + 4 * k..off + 4 * k + 4].try_into().unwrap())).collect();
        let v0 = mesh.vertices[0];
        assert_eq!(first, vec![v0[0], v0[2], -v0[1]]);
        let max: Vec<f64> = acc("POSITION")["max"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
        let want_max_y = mesh.vertices.iter().map(|v| v[2]).fold(f32::MIN, f32::max) as f64;
        assert!((max[1] - want_max_y).abs() < 1e-7);
        // Indices survive.
        let iv = &doc["bufferViews"][ind["bufferView"].as_u64().unwrap() as usize];
        let io = iv["byteOffset"].as_u64().unwrap() as usize;
        let idx: Vec<u32> = (0..12).map(|k| u32_at(bin, io + 4 * k)).collect();
        assert_eq!(idx, mesh.faces.iter().flatten().copied().collect::<Vec<_>>());
    }

    #[test]
    fn glb_without_colours_and_empty_mesh() {
        let b = glb_bytes(&tetrahedron(), &GlbOptions { axes: Axes::ZUp, vertex_colors: true }).unwrap();
        let jlen = u32_at(&b, 12) as usize;
        let doc: serde_json::Value = serde_json::from_slice(&b[20..20 + jlen]).unwrap();
        assert!(doc["meshes"][0]["primitives"][0]["attributes"].get("COLOR_0").is_none());
        assert_eq!(doc["accessors"].as_array().unwrap().len(), 3);
        assert!(glb_bytes(&Mesh::default(), &GlbOptions::default()).is_err());
    }
}
