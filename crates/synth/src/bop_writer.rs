//! BOP-format output (scenewise layout, thodan/bop_toolkit `docs/bop_datasets_format.md`):
//! models in mm with `models_info.json`; per scene `scene_camera.json`, `scene_gt.json`,
//! `scene_gt_info.json`, `rgb/`, `depth/` (16-bit, `depth_scale` mm per unit), `mask/`
//! (amodal silhouettes) and `mask_visib/`, named `{im_id:06}_{gt_idx:06}.png`.
//! recon's own per-instance facts (kind, part, target flag, materials, lights) go in an
//! extra `scene_meta.json` beside them, which BOP tools ignore.

use crate::objects::Symmetry;
use image::codecs::png::PngEncoder;
use image::{ExtendedColorType, ImageEncoder};
use recon_core::export::ply::{mesh_ply_bytes, PlyOptions};
use recon_core::export::Axes;
use recon_core::math::Similarity;
use recon_core::mesh::trimesh::diameter;
use recon_core::mesh::Mesh;
use recon_core::render::Rendered;
use recon_core::{Error, Result};
use serde_json::{json, Value};
use std::path::Path;

/// Millimetres per stored depth unit: 0.1 mm keeps sensor noise resolvable and still
/// covers 6.5 m in 16 bits.
pub const DEPTH_SCALE_MM: f64 = 0.1;

pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
}

pub fn write_json(path: &Path, v: &Value) -> Result<()> {
    let s = serde_json::to_string_pretty(v).map_err(|e| Error::msg(e.to_string()))?;
    write_bytes(path, s.as_bytes())
}

pub fn mkdir(path: &Path) -> Result<()> {
    std::fs::create_dir_all(path).map_err(|e| Error::io(path, e))
}

fn png(path: &Path, data: &[u8], w: usize, h: usize, ty: ExtendedColorType) -> Result<()> {
    let mut buf = Vec::new();
    PngEncoder::new(&mut buf)
        .write_image(data, w as u32, h as u32, ty)
        .map_err(|e| Error::msg(format!("{}: PNG encoding failed: {e}", path.display())))?;
    write_bytes(path, &buf)
}

pub fn write_rgb(path: &Path, rgb: &[u8], w: usize, h: usize) -> Result<()> {
    png(path, rgb, w, h, ExtendedColorType::Rgb8)
}

pub fn write_mask(path: &Path, mask: &[bool], w: usize, h: usize) -> Result<()> {
    let px: Vec<u8> = mask.iter().map(|&m| if m { 255 } else { 0 }).collect();
    png(path, &px, w, h, ExtendedColorType::L8)
}

/// Unit normals → RGB `(n + 1) / 2 · 255`; pixels without a surface (zero normal) are black.
pub fn write_normals(path: &Path, normals: &[[f32; 3]], w: usize, h: usize) -> Result<()> {
    let px: Vec<u8> = normals
        .iter()
        .flat_map(|n| if n == &[0.0; 3] { [0; 3] } else { n.map(|x| ((x + 1.0) * 127.5).round().clamp(0.0, 255.0) as u8) })
        .collect();
    png(path, &px, w, h, ExtendedColorType::Rgb8)
}

/// Metric depth (metres, 0 = missing) → 16-bit PNG in units of [`DEPTH_SCALE_MM`].
/// Returns how many pixels were beyond the 16-bit range (stored as missing).
pub fn write_depth(path: &Path, depth_m: &[f32], w: usize, h: usize) -> Result<usize> {
    let mut clipped = 0;
    let mut bytes = Vec::with_capacity(2 * depth_m.len());
    for &z in depth_m {
        let v = (z as f64 * 1000.0 / DEPTH_SCALE_MM).round();
        let v = if z > 0.0 && v <= 65535.0 {
            v as u16
        } else {
            if z > 0.0 {
                clipped += 1;
            }
            0
        };
        // The encoder takes native-endian samples and writes PNG's big-endian.
        bytes.extend_from_slice(&v.to_ne_bytes());
    }
    png(path, &bytes, w, h, ExtendedColorType::L16)?;
    Ok(clipped)
}

/// Row-major 3×3 as a flat list.
pub fn flat3(r: &[[f64; 3]; 3]) -> Vec<f64> {
    r.iter().flatten().copied().collect()
}

/// `[x, y, w, h]` of the set pixels, or `[-1, -1, -1, -1]` when none (bop_toolkit's value).
pub fn bbox(mask: &[bool], w: usize) -> [i64; 4] {
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for (i, _) in mask.iter().enumerate().filter(|(_, &m)| m) {
        let (x, y) = (i % w, i / w);
        x0 = x0.min(x);
        y0 = y0.min(y);
        x1 = x1.max(x);
        y1 = y1.max(y);
    }
    if x0 == usize::MAX {
        [-1, -1, -1, -1]
    } else {
        [x0 as i64, y0 as i64, (x1 - x0 + 1) as i64, (y1 - y0 + 1) as i64]
    }
}

/// A `scene_gt.json` entry: model → camera pose in mm.
pub fn gt_entry(m2c: &Similarity, obj_id: u32) -> Value {
    json!({
        "cam_R_m2c": flat3(&m2c.rotation),
        "cam_t_m2c": m2c.translation.iter().map(|x| x * 1000.0).collect::<Vec<_>>(),
        "obj_id": obj_id,
    })
}

/// A `scene_camera.json` entry.
pub fn camera_entry(r: &Rendered, w2c: &Similarity) -> Value {
    let k = r.k;
    json!({
        "cam_K": [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0],
        "depth_scale": DEPTH_SCALE_MM,
        "cam_R_w2c": flat3(&w2c.rotation),
        "cam_t_w2c": w2c.translation.iter().map(|x| x * 1000.0).collect::<Vec<_>>(),
    })
}

/// A `scene_gt_info.json` entry for instance `i` of the render; `measured` is the
/// sensor's depth (0 = missing) for `px_count_valid`.
pub fn gt_info_entry(r: &Rendered, i: usize, measured: &[f32]) -> Value {
    let amodal = &r.amodal[i];
    let visible = r.visible_mask(i);
    let all = amodal.iter().filter(|&&m| m).count();
    let valid = amodal.iter().zip(measured).filter(|(&m, &z)| m && z > 0.0).count();
    let visib = visible.iter().filter(|&&m| m).count();
    json!({
        "bbox_obj": bbox(amodal, r.width),
        "bbox_visib": bbox(&visible, r.width),
        "px_count_all": all,
        "px_count_valid": valid,
        "px_count_visib": visib,
        "visib_fract": if all > 0 { visib as f64 / all as f64 } else { 0.0 },
    })
}

/// The model file (mm, binary PLY with vertex normals and the base colour).
pub fn model_ply_bytes(mesh_m: &Mesh, color: [f32; 3]) -> Result<Vec<u8>> {
    let mm = Mesh {
        vertices: mesh_m.vertices.iter().map(|v| v.map(|x| x * 1000.0)).collect(),
        faces: mesh_m.faces.clone(),
        vertex_attrs: Some(vec![[color[0], color[1], color[2], 0.0, 0.0, 0.0]; mesh_m.vertices.len()]),
    };
    mesh_ply_bytes(&mm, &PlyOptions { axes: Axes::ZUp, normals: true, vertex_colors: true })
}

/// A `models_info.json` entry (mm): diameter (exact, over the vertices), bounding box and
/// symmetries (`symmetries_discrete` as row-major 4×4 with translation in mm).
pub fn model_info(mesh_m: &Mesh, sym: &Symmetry) -> Value {
    let pts: Vec<[f64; 3]> = mesh_m.vertices.iter().map(|v| v.map(|x| x as f64 * 1000.0)).collect();
    let (d, _) = diameter(&pts);
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in &pts {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    let mut v = json!({
        "diameter": d,
        "min_x": lo[0], "min_y": lo[1], "min_z": lo[2],
        "size_x": hi[0] - lo[0], "size_y": hi[1] - lo[1], "size_z": hi[2] - lo[2],
    });
    if !sym.continuous_axes.is_empty() {
        v["symmetries_continuous"] = sym.continuous_axes.iter().map(|a| json!({"axis": a, "offset": [0.0, 0.0, 0.0]})).collect();
    }
    if !sym.discrete.is_empty() {
        v["symmetries_discrete"] = sym
            .discrete
            .iter()
            .map(|r| {
                json!([r[0][0], r[0][1], r[0][2], 0.0, r[1][0], r[1][1], r[1][2], 0.0, r[2][0], r[2][1], r[2][2], 0.0, 0.0, 0.0, 0.0, 1.0])
            })
            .collect();
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bbox_and_depth_encoding() {
        let mut m = vec![false; 20];
        m[6] = true;
        m[13] = true;
        assert_eq!(bbox(&m, 5), [1, 1, 3, 2]);
        assert_eq!(bbox(&[false; 4], 2), [-1, -1, -1, -1]);
        let dir = recon_testkit::tmp("synth-depth");
        let p = dir.join("d.png");
        let clipped = write_depth(&p, &[0.0, 1.23456, 7.0, 0.00004], 2, 2).unwrap();
        assert_eq!(clipped, 1);
        let img = image::open(&p).unwrap().into_luma16();
        assert_eq!(img.as_raw(), &vec![0u16, 12346, 0, 0]);
        std::fs::remove_dir_all(&dir).ok();
    }
}
