//! Minimal binary glTF 2.0 (GLB) reader for user meshes: the triangle
//! primitives (mode 4) of every mesh a scene's nodes reach, their FLOAT VEC3
//! `POSITION` and their indices (unsigned byte, short or int; none means
//! consecutive triangles), placed by the node transforms (`matrix`, or
//! `translation`/`rotation`/`scale`). Points and lines are skipped;
//! materials, textures, normals, skins and animations are ignored. Data
//! must sit in the file's BIN chunk (no external or data-URI buffers, no
//! sparse or quantised accessors). Coordinates are glTF's (y up).
//!
//! Every claim of the file (chunk lengths, accessor counts, offsets and
//! strides, node depth) is checked against the data and the bounds of
//! [`crate::util::limits`] before anything of that size is allocated;
//! errors name the file, the glTF field and what was expected.

use crate::mesh::trimesh::TriMesh;
use crate::util::limits::{MAX_GLB_JSON_BYTES, MAX_GLTF_NODE_DEPTH, MAX_MESH_TRIANGLES, MAX_MESH_VERTICES};
use crate::{Error, Result};
use serde_json::Value;

const MAGIC: u32 = 0x4654_6C67; // "glTF"
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;
const FLOAT: u64 = 5126;

type M4 = [[f64; 4]; 4];
const IDENTITY: M4 = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];

fn mul(a: &M4, b: &M4) -> M4 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..4).map(|k| a[i][k] * b[k][j]).sum()))
}

/// An accessor's elements, read in place (checked to lie inside the data).
struct Elements<'a> {
    bin: &'a [u8],
    stride: usize,
    elem: usize,
    count: usize,
}

impl<'a> Elements<'a> {
    fn iter(&self) -> impl Iterator<Item = &'a [u8]> + '_ {
        (0..self.count).map(|i| &self.bin[i * self.stride..i * self.stride + self.elem])
    }
}

struct Doc<'a> {
    file: &'a str,
    json: Value,
    bin: &'a [u8],
}

fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}

/// Parses GLB bytes; `file` names the source in errors.
pub fn parse_glb(bytes: &[u8], file: &str) -> Result<TriMesh> {
    let bad = |field: &str, msg: String| Error::config(file, field, msg);
    if bytes.len() < 20 {
        return Err(bad("header", format!("expected a 12-byte GLB header and a JSON chunk, the file has {} bytes", bytes.len())));
    }
    if u32_at(bytes, 0) != MAGIC {
        return Err(bad("header.magic", "expected `glTF` (a binary glTF file; .gltf text files are not read)".into()));
    }
    let version = u32_at(bytes, 4);
    if version != 2 {
        return Err(bad("header.version", format!("expected glTF 2, got {version}")));
    }
    let total = u32_at(bytes, 8) as usize;
    if total > bytes.len() || total < 20 {
        return Err(bad("header.length", format!("claims {total} bytes, the file has {} (truncated?)", bytes.len())));
    }
    let bytes = &bytes[..total];
    let jlen = u32_at(bytes, 12) as u64;
    if u32_at(bytes, 16) != CHUNK_JSON {
        return Err(bad("chunk 0", "expected the JSON chunk first".into()));
    }
    if jlen > MAX_GLB_JSON_BYTES {
        return Err(Error::too_large(file, "JSON chunk length", jlen as u128, MAX_GLB_JSON_BYTES as u128, "bytes", "GLB JSON chunk"));
    }
    let jend = 20 + jlen as usize;
    if jend > bytes.len() {
        return Err(bad("chunk 0.length", format!("claims {jlen} bytes, {} are left (truncated?)", bytes.len() - 20)));
    }
    let json: Value = serde_json::from_slice(&bytes[20..jend]).map_err(|e| bad("chunk 0", format!("expected glTF JSON: {e}")))?;
    if !json.is_object() {
        return Err(bad("<root>", "expected a JSON object".into()));
    }
    // The BIN chunk, when present, follows (4-byte aligned; GLB writers pad the JSON).
    let mut bin: &[u8] = &[];
    let bstart = jend.next_multiple_of(4);
    if bstart + 8 <= bytes.len() {
        let blen = u32_at(bytes, bstart) as usize;
        if u32_at(bytes, bstart + 4) == CHUNK_BIN {
            let end = (bstart + 8).checked_add(blen).filter(|e| *e <= bytes.len());
            let end = end
                .ok_or_else(|| bad("chunk 1.length", format!("claims {blen} bytes, {} are left (truncated?)", bytes.len() - bstart - 8)))?;
            bin = &bytes[bstart + 8..end];
        }
    }
    let doc = Doc { file, json, bin };
    doc.mesh()
}

impl Doc<'_> {
    fn bad(&self, field: impl Into<String>, msg: impl Into<String>) -> Error {
        Error::config(self.file, field, msg)
    }

    fn array(&self, name: &str) -> &[Value] {
        self.json.get(name).and_then(Value::as_array).map(Vec::as_slice).unwrap_or(&[])
    }

    /// Element `i` of a top-level array, named `name[i]` in errors.
    fn item(&self, name: &str, i: &Value, field: &str) -> Result<(usize, &Value)> {
        let k = i.as_u64().ok_or_else(|| self.bad(field, format!("expected an index into `{name}`, got {i}")))? as usize;
        let arr = self.array(name);
        let v = arr.get(k).ok_or_else(|| self.bad(field, format!("index {k} out of range: `{name}` has {} entries", arr.len())))?;
        Ok((k, v))
    }

    fn uint(&self, v: &Value, key: &str, field: &str, default: Option<u64>) -> Result<u64> {
        match v.get(key) {
            None => default.ok_or_else(|| self.bad(format!("{field}.{key}"), "missing")),
            Some(x) => x.as_u64().ok_or_else(|| self.bad(format!("{field}.{key}"), format!("expected a non-negative integer, got {x}"))),
        }
    }

    fn numbers<const N: usize>(&self, v: &Value, field: &str) -> Result<[f64; N]> {
        let a = v.as_array().filter(|a| a.len() == N);
        let a = a.ok_or_else(|| self.bad(field, format!("expected {N} numbers")))?;
        let mut out = [0.0; N];
        for (o, x) in out.iter_mut().zip(a) {
            *o = x.as_f64().filter(|x| x.is_finite()).ok_or_else(|| self.bad(field, format!("expected {N} finite numbers")))?;
        }
        Ok(out)
    }

    fn local(&self, node: &Value, field: &str) -> Result<M4> {
        if let Some(m) = node.get("matrix") {
            let c = self.numbers::<16>(m, &format!("{field}.matrix"))?;
            // Column-major.
            return Ok(std::array::from_fn(|i| std::array::from_fn(|j| c[j * 4 + i])));
        }
        let t = node.get("translation").map(|v| self.numbers::<3>(v, &format!("{field}.translation"))).transpose()?.unwrap_or([0.0; 3]);
        let q =
            node.get("rotation").map(|v| self.numbers::<4>(v, &format!("{field}.rotation"))).transpose()?.unwrap_or([0.0, 0.0, 0.0, 1.0]);
        let s = node.get("scale").map(|v| self.numbers::<3>(v, &format!("{field}.scale"))).transpose()?.unwrap_or([1.0; 3]);
        let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(n > 1e-6) {
            return Err(self.bad(format!("{field}.rotation"), "expected a unit quaternion (x, y, z, w)"));
        }
        let [x, y, z, w] = q.map(|c| c / n);
        let r = [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
            [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
            [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
        ];
        let mut m = IDENTITY;
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = r[i][j] * s[j];
            }
            m[i][3] = t[i];
        }
        Ok(m)
    }

    /// Accessor `idx`'s elements and component type, after checking that
    /// every element lies inside its buffer view and the BIN chunk.
    fn accessor(&self, idx: &Value, field: &str, want_type: &str, types: &[u64]) -> Result<(Elements<'_>, u64)> {
        let (k, a) = self.item("accessors", idx, field)?;
        let af = format!("accessors[{k}]");
        if a.get("sparse").is_some() {
            return Err(self.bad(format!("{af}.sparse"), "sparse accessors are not read"));
        }
        let ty = a.get("type").and_then(Value::as_str).unwrap_or("");
        if ty != want_type {
            return Err(self.bad(format!("{af}.type"), format!("expected {want_type} for {field}, got `{ty}`")));
        }
        let ct = self.uint(a, "componentType", &af, None)?;
        if !types.contains(&ct) {
            return Err(self.bad(format!("{af}.componentType"), format!("expected one of {types:?} for {field}, got {ct}")));
        }
        if a.get("normalized").and_then(Value::as_bool) == Some(true) {
            return Err(self.bad(format!("{af}.normalized"), "normalized (quantised) accessors are not read"));
        }
        let count = self.uint(a, "count", &af, None)?;
        let bound = if want_type == "SCALAR" { 3 * MAX_MESH_TRIANGLES } else { MAX_MESH_VERTICES };
        if count > bound {
            return Err(Error::too_large(self.file, format!("{af}.count"), count as u128, bound as u128, "elements", field.to_string()));
        }
        let comp = match ct {
            5121 => 1,
            5123 => 2,
            _ => 4,
        };
        let elem = comp * if want_type == "VEC3" { 3 } else { 1 };
        let Some(view_idx) = a.get("bufferView") else {
            return Err(self.bad(format!("{af}.bufferView"), "missing (accessors without data are not read)"));
        };
        let (vk, view) = self.item("bufferViews", view_idx, &format!("{af}.bufferView"))?;
        let vf = format!("bufferViews[{vk}]");
        let (bk, buffer) = self.item("buffers", view.get("buffer").unwrap_or(&Value::Null), &format!("{vf}.buffer"))?;
        if bk != 0 || buffer.get("uri").is_some() {
            return Err(
                self.bad(format!("{vf}.buffer"), "expected buffer 0, the GLB's BIN chunk (external and data-URI buffers are not read)")
            );
        }
        let voff = self.uint(view, "byteOffset", &vf, Some(0))?;
        let vlen = self.uint(view, "byteLength", &vf, None)?;
        let stride = self.uint(view, "byteStride", &vf, Some(elem))?;
        if stride < elem || stride > 252 {
            return Err(self.bad(format!("{vf}.byteStride"), format!("expected {elem}..=252 bytes for {field}, got {stride}")));
        }
        if voff.checked_add(vlen).is_none_or(|e| e > self.bin.len() as u64) {
            return Err(self.bad(
                format!("{vf}.byteLength"),
                format!("bytes {voff}..{} lie outside the BIN chunk ({} bytes)", voff.saturating_add(vlen), self.bin.len()),
            ));
        }
        let aoff = self.uint(a, "byteOffset", &af, Some(0))?;
        let need = if count == 0 { 0 } else { aoff + (count - 1) * stride + elem };
        if need > vlen {
            return Err(self.bad(
                format!("{af}.count"),
                format!("{count} elements of {elem} bytes (stride {stride}, offset {aoff}) need {need} bytes, the view has {vlen}"),
            ));
        }
        let base = (voff + aoff) as usize;
        Ok((Elements { bin: &self.bin[base..], stride: stride as usize, elem: elem as usize, count: count as usize }, ct))
    }

    fn primitive(&self, mk: usize, pk: usize, p: &Value, m: &M4, out: &mut TriMesh) -> Result<()> {
        let pf = format!("meshes[{mk}].primitives[{pk}]");
        if self.uint(p, "mode", &pf, Some(4))? != 4 {
            return Ok(()); // points, lines, strips: not a triangle list
        }
        let pos = p.get("attributes").and_then(|a| a.get("POSITION"));
        let pos = pos.ok_or_else(|| self.bad(format!("{pf}.attributes.POSITION"), "missing"))?;
        let (elems, _) = self.accessor(pos, &format!("{pf}.attributes.POSITION"), "VEC3", &[FLOAT])?;
        let base = out.vertices.len() as u64;
        if base + elems.count as u64 > MAX_MESH_VERTICES {
            return Err(Error::too_large(
                self.file,
                "vertices (all primitives)",
                (base + elems.count as u64) as u128,
                MAX_MESH_VERTICES as u128,
                "vertices",
                pf,
            ));
        }
        for e in elems.iter() {
            let v: [f64; 3] = std::array::from_fn(|k| f32::from_le_bytes([e[4 * k], e[4 * k + 1], e[4 * k + 2], e[4 * k + 3]]) as f64);
            if v.iter().any(|x| !x.is_finite()) {
                return Err(self.bad(format!("{pf}.attributes.POSITION"), format!("expected finite coordinates, got {v:?}")));
            }
            out.vertices.push(std::array::from_fn(|i| (0..3).map(|k| m[i][k] * v[k]).sum::<f64>() + m[i][3]));
        }
        let n = elems.count as u64;
        let idx: Vec<u64> = match p.get("indices") {
            Some(i) => {
                let (ie, ct) = self.accessor(i, &format!("{pf}.indices"), "SCALAR", &[5121, 5123, 5125])?;
                ie.iter()
                    .map(|b| match ct {
                        5121 => b[0] as u64,
                        5123 => u16::from_le_bytes([b[0], b[1]]) as u64,
                        _ => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as u64,
                    })
                    .collect()
            }
            None => (0..n).collect(),
        };
        if !idx.len().is_multiple_of(3) {
            return Err(self.bad(format!("{pf}.indices"), format!("expected a multiple of 3 indices (a triangle list), got {}", idx.len())));
        }
        if let Some(bad) = idx.iter().find(|i| **i >= n) {
            return Err(self.bad(format!("{pf}.indices"), format!("index {bad} out of range: POSITION has {n} vertices")));
        }
        if (out.faces.len() + idx.len() / 3) as u64 > MAX_MESH_TRIANGLES {
            return Err(Error::too_large(
                self.file,
                "triangles (all primitives)",
                (out.faces.len() + idx.len() / 3) as u128,
                MAX_MESH_TRIANGLES as u128,
                "triangles",
                pf,
            ));
        }
        out.faces.extend(idx.chunks_exact(3).map(|t| [0, 1, 2].map(|k| (base + t[k]) as u32)));
        Ok(())
    }

    fn node(&self, k: usize, parent: &M4, depth: usize, path: &mut Vec<usize>, out: &mut TriMesh) -> Result<()> {
        let field = format!("nodes[{k}]");
        if depth > MAX_GLTF_NODE_DEPTH {
            return Err(Error::too_large(self.file, "node depth", depth as u128, MAX_GLTF_NODE_DEPTH as u128, "levels", field));
        }
        if path.contains(&k) {
            return Err(self.bad(&field, "expected a tree of nodes: this node is its own ancestor"));
        }
        let node = &self.array("nodes")[k];
        let m = mul(parent, &self.local(node, &field)?);
        if let Some(mi) = node.get("mesh") {
            let (mk, mesh) = self.item("meshes", mi, &format!("{field}.mesh"))?;
            for (pk, p) in mesh.get("primitives").and_then(Value::as_array).map(Vec::as_slice).unwrap_or(&[]).iter().enumerate() {
                self.primitive(mk, pk, p, &m, out)?;
            }
        }
        path.push(k);
        for (ci, c) in node.get("children").and_then(Value::as_array).map(Vec::as_slice).unwrap_or(&[]).iter().enumerate() {
            let (ck, _) = self.item("nodes", c, &format!("{field}.children[{ci}]"))?;
            self.node(ck, &m, depth + 1, path, out)?;
        }
        path.pop();
        Ok(())
    }

    fn mesh(&self) -> Result<TriMesh> {
        let mut out = TriMesh::default();
        let scenes = self.array("scenes");
        if !scenes.is_empty() {
            let s = self.json.get("scene").cloned().unwrap_or(Value::from(0));
            let (sk, scene) = self.item("scenes", &s, "scene")?;
            for (i, n) in scene.get("nodes").and_then(Value::as_array).map(Vec::as_slice).unwrap_or(&[]).iter().enumerate() {
                let (k, _) = self.item("nodes", n, &format!("scenes[{sk}].nodes[{i}]"))?;
                self.node(k, &IDENTITY, 0, &mut vec![], &mut out)?;
            }
        } else {
            // No scene: every mesh as it is.
            for (mk, mesh) in self.array("meshes").iter().enumerate() {
                for (pk, p) in mesh.get("primitives").and_then(Value::as_array).map(Vec::as_slice).unwrap_or(&[]).iter().enumerate() {
                    self.primitive(mk, pk, p, &IDENTITY, &mut out)?;
                }
            }
        }
        if out.faces.is_empty() {
            return Err(self.bad("meshes", "expected at least one triangle primitive (mode 4) reached from the scene, found none"));
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A GLB of one triangle, its JSON edited by `f`.
    fn glb(f: impl Fn(&mut Value)) -> Vec<u8> {
        let mut bin: Vec<u8> =
            [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]].iter().flatten().flat_map(|x| x.to_le_bytes()).collect();
        bin.extend([0u16, 1, 2, 0].iter().flat_map(|x| x.to_le_bytes()));
        let mut j = serde_json::json!({
            "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"children": [1], "translation": [0, 0, 1]}, {"mesh": 0, "scale": [2, 2, 2]}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"},
                          {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}],
            "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 8}],
            "buffers": [{"byteLength": 44}]});
        f(&mut j);
        let mut js = serde_json::to_vec(&j).unwrap();
        while !js.len().is_multiple_of(4) {
            js.push(b' ');
        }
        let mut out = Vec::new();
        out.extend(MAGIC.to_le_bytes());
        out.extend(2u32.to_le_bytes());
        out.extend(((20 + js.len() + 8 + bin.len()) as u32).to_le_bytes());
        out.extend((js.len() as u32).to_le_bytes());
        out.extend(CHUNK_JSON.to_le_bytes());
        out.extend(js);
        out.extend((bin.len() as u32).to_le_bytes());
        out.extend(CHUNK_BIN.to_le_bytes());
        out.extend(bin);
        out
    }

    #[test]
    fn node_transforms_and_short_indices() {
        let m = parse_glb(&glb(|_| {}), "n.glb").unwrap();
        assert_eq!(m.faces, vec![[0, 1, 2]]);
        assert_eq!(m.vertices, vec![[0.0, 0.0, 1.0], [2.0, 0.0, 1.0], [0.0, 2.0, 1.0]]);
    }

    #[test]
    fn hostile_files_name_the_field() {
        let err = |b: &[u8]| parse_glb(b, "h.glb").unwrap_err().to_string();
        let good = glb(|_| {});
        let e = err(&good[..good.len() - 10]);
        assert!(e.contains("h.glb") && e.contains("header.length") && e.contains("truncated"), "{e}");
        let e = err(b"GLTF\x02\0\0\0");
        assert!(e.contains("header"), "{e}");
        let e = err(&glb(|j| j["accessors"][0]["count"] = 1_000_000_000u64.into()));
        assert!(e.contains("accessors[0].count") && e.contains("limit"), "{e}");
        let e = err(&glb(|j| j["accessors"][0]["count"] = 4.into()));
        assert!(e.contains("accessors[0].count") && e.contains("the view has 36"), "{e}");
        let e = err(&glb(|j| j["bufferViews"][1]["byteOffset"] = 40.into()));
        assert!(e.contains("bufferViews[1].byteLength") && e.contains("outside the BIN chunk"), "{e}");
        let e = err(&glb(|j| j["nodes"][1]["children"] = serde_json::json!([0])));
        assert!(e.contains("nodes[0]") && e.contains("own ancestor"), "{e}");
        let e = err(&glb(|j| j["accessors"][0]["componentType"] = 5123.into()));
        assert!(e.contains("accessors[0].componentType") && e.contains("POSITION"), "{e}");
        let e = err(&glb(|j| j["meshes"][0]["primitives"][0]["indices"] = 7.into()));
        assert!(e.contains("meshes[0].primitives[0].indices") && e.contains("out of range"), "{e}");
        let e = err(&glb(|j| j["buffers"][0]["uri"] = "x.bin".into()));
        assert!(e.contains("bufferViews[0].buffer") && e.contains("external"), "{e}");
        let e = err(&glb(|j| j["meshes"][0]["primitives"][0]["mode"] = 0.into()));
        assert!(e.contains("triangle primitive"), "{e}");
    }

    #[test]
    fn out_of_range_vertex_indices_are_refused() {
        // Index 3 written into the index data: POSITION has 3 vertices.
        let mut b = glb(|_| {});
        let n = b.len();
        b[n - 4] = 3;
        let e = parse_glb(&b, "i.glb").unwrap_err().to_string();
        assert!(e.contains("index 3 out of range"), "{e}");
    }
}
