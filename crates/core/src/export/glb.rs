//! Binary glTF 2.0 (GLB) writer: a mesh (POSITION, NORMAL, optional COLOR_0,
//! u32 indices, one primitive, one node), a textured mesh (TEXCOORD_0 and an
//! embedded PNG as the material's `baseColorTexture`), or a scene of named
//! meshes and coloured point clouds.

use super::axes::{write_file, Axes};
use crate::mesh::{Mesh, TexturedMesh};
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
/// Settings of the GLB writer.
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

/// Binary buffer, buffer views and accessors of a GLB under construction.
#[derive(Default)]
struct Builder {
    bin: Vec<u8>,
    views: Vec<serde_json::Value>,
    accessors: Vec<serde_json::Value>,
}

impl Builder {
    fn push_view(&mut self, bytes: &[u8], target: u32) -> usize {
        // Every view starts 4-byte aligned (all components are 4 bytes).
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        self.views.push(json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len(), "target": target}));
        self.bin.extend_from_slice(bytes);
        self.views.len() - 1
    }

    /// A buffer view without a target (an image).
    fn push_raw_view(&mut self, bytes: &[u8]) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        self.views.push(json!({"buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len()}));
        self.bin.extend_from_slice(bytes);
        self.views.len() - 1
    }

    /// A float VEC2 accessor.
    fn vec2(&mut self, rows: &[[f32; 2]]) -> usize {
        let v = self.push_view(&f32_bytes(rows), ARRAY_BUFFER);
        self.accessors.push(json!({"bufferView": v, "componentType": FLOAT, "count": rows.len(), "type": "VEC2"}));
        self.accessors.len() - 1
    }

    /// A float VEC3 accessor; `bounds` adds min/max (required for POSITION).
    fn vec3(&mut self, rows: &[[f32; 3]], bounds: bool) -> usize {
        let v = self.push_view(&f32_bytes(rows), ARRAY_BUFFER);
        let mut acc = json!({"bufferView": v, "componentType": FLOAT, "count": rows.len(), "type": "VEC3"});
        if bounds {
            let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
            for p in rows {
                for k in 0..3 {
                    lo[k] = lo[k].min(p[k]);
                    hi[k] = hi[k].max(p[k]);
                }
            }
            acc["min"] = json!(lo);
            acc["max"] = json!(hi);
        }
        self.accessors.push(acc);
        self.accessors.len() - 1
    }

    /// A triangle primitive for `mesh` (material 0).
    fn mesh_primitive(&mut self, mesh: &Mesh, opts: &GlbOptions) -> Result<serde_json::Value> {
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
        let pos = self.vec3(&positions, true);
        let nrm = self.vec3(&normals, false);
        let mut attributes = json!({"POSITION": pos, "NORMAL": nrm});
        if let Some(c) = &colors {
            attributes["COLOR_0"] = json!(self.vec3(c, false));
        }
        let idx: Vec<u8> = mesh.faces.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
        let v = self.push_view(&idx, ELEMENT_ARRAY_BUFFER);
        self.accessors.push(json!({"bufferView": v, "componentType": UNSIGNED_INT, "count": mesh.faces.len() * 3, "type": "SCALAR"}));
        let indices = self.accessors.len() - 1;
        Ok(json!({"attributes": attributes, "indices": indices, "mode": 4, "material": 0}))
    }

    /// The GLB file image of `meshes` (each `{"primitives": [...], "name"?: ...}`), one node each.
    fn finish(self, meshes: Vec<serde_json::Value>, node_names: Vec<Option<String>>) -> Result<Vec<u8>> {
        self.finish_with(meshes, node_names, vec![material([1.0; 4])])
    }

    /// [`Builder::finish`] with the document's materials (primitives refer to them by index).
    fn finish_with(
        self,
        meshes: Vec<serde_json::Value>,
        node_names: Vec<Option<String>>,
        materials: Vec<serde_json::Value>,
    ) -> Result<Vec<u8>> {
        self.finish_doc(meshes, node_names, materials, serde_json::Map::new())
    }

    /// [`Builder::finish_with`] plus top-level `extra` entries (images, textures, samplers).
    fn finish_doc(
        mut self,
        meshes: Vec<serde_json::Value>,
        node_names: Vec<Option<String>>,
        materials: Vec<serde_json::Value>,
        extra: serde_json::Map<String, serde_json::Value>,
    ) -> Result<Vec<u8>> {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let nodes: Vec<serde_json::Value> = node_names
            .iter()
            .enumerate()
            .map(|(i, n)| match n {
                Some(n) => json!({"mesh": i, "name": n}),
                None => json!({"mesh": i}),
            })
            .collect();
        let mut doc = json!({
            "asset": {"version": "2.0", "generator": "recon"},
            "scene": 0,
            "scenes": [{"nodes": (0..nodes.len()).collect::<Vec<_>>()}],
            "nodes": nodes,
            "meshes": meshes,
            "materials": materials,
            "accessors": self.accessors,
            "bufferViews": self.views,
            "buffers": [{"byteLength": self.bin.len()}],
        });
        for (k, v) in extra {
            doc[k] = v;
        }
        let mut json_bytes = serde_json::to_vec(&doc).map_err(|e| Error::msg(format!("glb: {e}")))?;
        while !json_bytes.len().is_multiple_of(4) {
            json_bytes.push(b' ');
        }
        let total = 12 + 8 + json_bytes.len() + 8 + self.bin.len();
        let total32 = u32::try_from(total).map_err(|_| Error::msg("glb: file over 4 GiB"))?;
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(&GLB_MAGIC.to_le_bytes());
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&total32.to_le_bytes());
        out.extend_from_slice(&(json_bytes.len() as u32).to_le_bytes());
        out.extend_from_slice(&CHUNK_JSON.to_le_bytes());
        out.extend_from_slice(&json_bytes);
        out.extend_from_slice(&(self.bin.len() as u32).to_le_bytes());
        out.extend_from_slice(&CHUNK_BIN.to_le_bytes());
        out.extend_from_slice(&self.bin);
        Ok(out)
    }
}

/// Serialise `mesh` as a GLB file image.
pub fn glb_bytes(mesh: &Mesh, opts: &GlbOptions) -> Result<Vec<u8>> {
    let mut b = Builder::default();
    let prim = b.mesh_primitive(mesh, opts)?;
    b.finish(vec![json!({"primitives": [prim]})], vec![None])
}

/// Serialise a textured mesh as a GLB file image: POSITION, NORMAL,
/// TEXCOORD_0 (glTF's UV convention, v down, as [`crate::mesh::atlas`] lays
/// it out), u32 indices, and the texture embedded as a PNG, the material's
/// `baseColorTexture` (no COLOR_0: glTF would multiply the two).
pub fn textured_glb_bytes(tm: &TexturedMesh, axes: Axes) -> Result<Vec<u8>> {
    let mesh = &tm.atlas.mesh;
    mesh.validate()?;
    if mesh.vertices.is_empty() || mesh.faces.is_empty() {
        return Err(Error::msg("glb: mesh is empty"));
    }
    if tm.atlas.uv.len() != mesh.vertices.len() || tm.atlas.normals.len() != mesh.vertices.len() {
        return Err(Error::msg(format!(
            "glb: {} UVs and {} normals for {} vertices",
            tm.atlas.uv.len(),
            tm.atlas.normals.len(),
            mesh.vertices.len()
        )));
    }
    let mut b = Builder::default();
    let positions: Vec<[f32; 3]> = mesh.vertices.iter().map(|&v| axes.apply(v)).collect();
    let normals: Vec<[f32; 3]> = tm.atlas.normals.iter().map(|&n| axes.apply(n)).collect();
    let pos = b.vec3(&positions, true);
    let nrm = b.vec3(&normals, false);
    let uv = b.vec2(&tm.atlas.uv);
    let idx: Vec<u8> = mesh.faces.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
    let v = b.push_view(&idx, ELEMENT_ARRAY_BUFFER);
    b.accessors.push(json!({"bufferView": v, "componentType": UNSIGNED_INT, "count": mesh.faces.len() * 3, "type": "SCALAR"}));
    let indices = b.accessors.len() - 1;
    let prim = json!({"attributes": {"POSITION": pos, "NORMAL": nrm, "TEXCOORD_0": uv}, "indices": indices, "mode": 4, "material": 0});
    let png = super::texture::png_bytes(&tm.texture)?;
    let image_view = b.push_raw_view(&png);
    let mut extra = serde_json::Map::new();
    extra.insert("images".into(), json!([{"bufferView": image_view, "mimeType": "image/png"}]));
    // Linear filtering, trilinear minification, clamped: the gutter is dilated for mip-mapping.
    extra.insert("samplers".into(), json!([{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}]));
    extra.insert("textures".into(), json!([{"sampler": 0, "source": 0}]));
    let mat = json!({"pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "baseColorTexture": {"index": 0, "texCoord": 0},
                     "metallicFactor": 0.0, "roughnessFactor": 1.0}});
    b.finish_doc(vec![json!({"primitives": [prim]})], vec![None], vec![mat], extra)
}

/// Write a textured mesh to a `.glb` file ([`textured_glb_bytes`]).
pub fn save_textured_glb(tm: &TexturedMesh, path: &Path, axes: Axes) -> Result<()> {
    write_file(path, &textured_glb_bytes(tm, axes)?)
}

/// Write `mesh` to a `.glb` file.
pub fn save_glb(mesh: &Mesh, path: &Path, opts: &GlbOptions) -> Result<()> {
    write_file(path, &glb_bytes(mesh, opts)?)
}

/// A coloured point cloud for a scene file.
pub struct PointCloud<'a> {
    /// Node name.
    pub name: &'a str,
    /// Positions.
    pub points: &'a [[f32; 3]],
    /// Per-point sRGB colour.
    pub colors: &'a [[u8; 3]],
}

/// Several named meshes (one node each) and coloured point clouds (glTF
/// `POINTS` primitives, one node each) in one GLB, all in the same frame.
pub fn scene_glb_bytes(meshes: &[(&str, &Mesh)], clouds: &[PointCloud], opts: &GlbOptions) -> Result<Vec<u8>> {
    let mut b = Builder::default();
    let (mut out, mut names) = (Vec::new(), Vec::new());
    for (name, m) in meshes {
        let prim = b.mesh_primitive(m, opts)?;
        out.push(json!({"name": name, "primitives": [prim]}));
        names.push(Some(name.to_string()));
    }
    for c in clouds.iter().filter(|c| !c.points.is_empty()) {
        if c.colors.len() != c.points.len() {
            return Err(Error::msg(format!("glb: point cloud `{}` has {} colours for {} points", c.name, c.colors.len(), c.points.len())));
        }
        let pos: Vec<[f32; 3]> = c.points.iter().map(|&p| opts.axes.apply(p)).collect();
        let col: Vec<[f32; 3]> = c.colors.iter().map(|c| c.map(srgb_to_linear)).collect();
        let pa = b.vec3(&pos, true);
        let ca = b.vec3(&col, false);
        out.push(json!({"name": c.name, "primitives": [{"attributes": {"POSITION": pa, "COLOR_0": ca}, "mode": 0, "material": 0}]}));
        names.push(Some(c.name.to_string()));
    }
    if out.is_empty() {
        return Err(Error::msg("glb: empty scene"));
    }
    b.finish(out, names)
}

/// A matte glTF material of a linear base colour (alpha below 1 is blended).
fn material(rgba: [f32; 4]) -> serde_json::Value {
    let mut m = json!({"pbrMetallicRoughness": {"baseColorFactor": rgba, "metallicFactor": 0.0, "roughnessFactor": 1.0}});
    if rgba[3] < 1.0 {
        m["alphaMode"] = json!("BLEND");
    }
    m
}

/// Named meshes, one node each, each with its own material of a linear
/// base colour (white where `None`), all in the same frame.
pub fn colored_meshes_glb_bytes(meshes: &[(&str, &Mesh, Option<[f32; 4]>)], opts: &GlbOptions) -> Result<Vec<u8>> {
    if meshes.is_empty() {
        return Err(Error::msg("glb: empty scene"));
    }
    let mut b = Builder::default();
    let (mut out, mut names, mut materials) = (Vec::new(), Vec::new(), Vec::new());
    for (k, (name, m, rgba)) in meshes.iter().enumerate() {
        let mut prim = b.mesh_primitive(m, opts)?;
        prim["material"] = json!(k);
        out.push(json!({"name": name, "primitives": [prim]}));
        names.push(Some(name.to_string()));
        let mut mat = material(rgba.unwrap_or([1.0; 4]));
        mat["name"] = json!(name);
        materials.push(mat);
    }
    b.finish_with(out, names, materials)
}

/// glTF vertex colours are linear.
fn srgb_to_linear(c: u8) -> f32 {
    let x = c as f32 / 255.0;
    if x <= 0.04045 {
        x / 12.92
    } else {
        ((x + 0.055) / 1.055).powf(2.4)
    }
}

fn f32_bytes<const K: usize>(rows: &[[f32; K]]) -> Vec<u8> {
    rows.iter().flatten().flat_map(|x| x.to_le_bytes()).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::tetrahedron;

    fn u32_at(b: &[u8], o: usize) -> u32 {
        u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
    }

    #[test]
    fn the_asset_reader_reads_what_recon_writes() {
        let t = tetrahedron();
        let b = glb_bytes(&t, &GlbOptions { axes: Axes::ZUp, vertex_colors: false }).unwrap();
        let m = crate::dataset::parse_glb(&b, "t.glb").unwrap();
        assert_eq!(m.faces, t.faces);
        for (a, b) in m.vertices.iter().zip(&t.vertices) {
            assert!((0..3).all(|k| (a[k] - b[k] as f64).abs() < 1e-7));
        }
        // The coloured scene: one node and one material per mesh.
        let b = colored_meshes_glb_bytes(&[("a", &t, Some([0.5, 0.25, 0.0, 1.0])), ("b", &t, None)], &GlbOptions::default()).unwrap();
        let jlen = u32_at(&b, 12) as usize;
        let doc: serde_json::Value = serde_json::from_slice(&b[20..20 + jlen]).unwrap();
        assert_eq!(doc["materials"][0]["pbrMetallicRoughness"]["baseColorFactor"], json!([0.5, 0.25, 0.0, 1.0]));
        assert_eq!(doc["meshes"][1]["primitives"][0]["material"], 1);
        assert_eq!(doc["nodes"][0]["name"], "a");
        assert_eq!(crate::dataset::parse_glb(&b, "s.glb").unwrap().faces.len(), 2 * t.faces.len());
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
    fn textured_glb_has_uvs_and_an_embedded_png() {
        let mut m = crate::mesh::primitives::box_mesh(0.1, 0.1, 0.1);
        m.vertex_attrs = Some(vec![[0.2, 0.4, 0.6, 0.5, 0.5, 1.0]; m.vertices.len()]);
        let atlas = crate::mesh::uv_atlas(&m, &crate::mesh::AtlasOptions::for_size(64)).unwrap();
        let tex = crate::mesh::Texture { width: 64, height: 64, rgb: vec![200; 64 * 64 * 3] };
        let tm = TexturedMesh { atlas, texture: tex };
        let b = textured_glb_bytes(&tm, Axes::YUp).unwrap();
        assert_eq!(u32_at(&b, 8) as usize, b.len());
        let jlen = u32_at(&b, 12) as usize;
        let doc: serde_json::Value = serde_json::from_slice(&b[20..20 + jlen]).unwrap();
        let bin = &b[20 + jlen + 8..];
        let prim = &doc["meshes"][0]["primitives"][0];
        let nv = tm.atlas.mesh.vertices.len();
        for a in ["POSITION", "NORMAL", "TEXCOORD_0"] {
            assert_eq!(doc["accessors"][prim["attributes"][a].as_u64().unwrap() as usize]["count"], nv, "{a}");
        }
        assert!(prim["attributes"].get("COLOR_0").is_none());
        assert_eq!(doc["accessors"][prim["attributes"]["TEXCOORD_0"].as_u64().unwrap() as usize]["type"], "VEC2");
        assert_eq!(doc["accessors"][prim["indices"].as_u64().unwrap() as usize]["count"], 3 * m.faces.len());
        let mat = &doc["materials"][prim["material"].as_u64().unwrap() as usize];
        let tex = &doc["textures"][mat["pbrMetallicRoughness"]["baseColorTexture"]["index"].as_u64().unwrap() as usize];
        let img = &doc["images"][tex["source"].as_u64().unwrap() as usize];
        assert_eq!(img["mimeType"], "image/png");
        let view = &doc["bufferViews"][img["bufferView"].as_u64().unwrap() as usize];
        let (off, len) = (view["byteOffset"].as_u64().unwrap() as usize, view["byteLength"].as_u64().unwrap() as usize);
        let png = image::load_from_memory(&bin[off..off + len]).unwrap().to_rgb8();
        assert_eq!(png.into_raw(), tm.texture.rgb);
        // The asset reader reads its geometry back.
        assert_eq!(crate::dataset::parse_glb(&b, "t.glb").unwrap().faces.len(), m.faces.len());
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

    #[test]
    fn scene_with_meshes_and_points() {
        let mut a = tetrahedron();
        a.vertex_attrs = Some(vec![[1.0, 0.0, 0.0, 0.5, 0.5, 1.0]; 4]);
        let mut b2 = tetrahedron();
        b2.vertices.iter_mut().for_each(|v| v[0] += 2.0);
        let pts = [[0.0f32, 0.0, 1.0], [0.5, 0.5, 1.5], [1.0, -1.0, 2.0]];
        let cols = [[255u8, 0, 0], [0, 255, 0], [10, 20, 30]];
        let cloud = PointCloud { name: "observed", points: &pts, colors: &cols };
        let opts = GlbOptions { axes: Axes::ZUp, vertex_colors: true };
        let b = scene_glb_bytes(&[("a", &a), ("b", &b2)], &[cloud], &opts).unwrap();
        assert_eq!(u32_at(&b, 0), GLB_MAGIC);
        assert_eq!(u32_at(&b, 8) as usize, b.len());
        let jlen = u32_at(&b, 12) as usize;
        let doc: serde_json::Value = serde_json::from_slice(&b[20..20 + jlen]).unwrap();
        assert_eq!(doc["nodes"].as_array().unwrap().len(), 3);
        assert_eq!(doc["scenes"][0]["nodes"], json!([0, 1, 2]));
        assert_eq!(doc["nodes"][2]["name"], "observed");
        let p = &doc["meshes"][2]["primitives"][0];
        assert_eq!(p["mode"], 0);
        let pos = &doc["accessors"][p["attributes"]["POSITION"].as_u64().unwrap() as usize];
        assert_eq!(pos["count"], 3);
        assert_eq!(pos["max"], json!([1.0, 0.5, 2.0]));
        // Second mesh's positions are its own (shifted) vertices.
        let p1 = &doc["meshes"][1]["primitives"][0];
        let pos1 = &doc["accessors"][p1["attributes"]["POSITION"].as_u64().unwrap() as usize];
        assert_eq!(pos1["min"][0], 2.0);
        // Single-mesh writer unchanged in structure.
        let one = glb_bytes(&a, &opts).unwrap();
        let jl = u32_at(&one, 12) as usize;
        let d1: serde_json::Value = serde_json::from_slice(&one[20..20 + jl]).unwrap();
        assert_eq!(d1["nodes"], json!([{"mesh": 0}]));
        let bad = PointCloud { name: "x", points: &pts, colors: &cols[..1] };
        assert!(scene_glb_bytes(&[], &[bad], &opts).is_err());
        assert!(scene_glb_bytes(&[], &[], &opts).is_err());
    }
}
