//! A side-by-side picture of a reconstruction: the input colour image on the
//! left; on the right the posed meshes ray-cast from the input camera
//! (shaded, one colour per object) over the dimmed input.

use crate::dataset::frame::{Intrinsics, RgbdFrame};
use crate::math::Similarity;
use crate::mesh::Mesh;
use crate::render::raycast::{render, Camera, Instance, Material, RenderMesh, RenderOptions};
use crate::Result;

const PALETTE: [[f32; 3]; 6] =
    [[0.95, 0.55, 0.2], [0.3, 0.7, 0.95], [0.5, 0.9, 0.4], [0.95, 0.4, 0.6], [0.85, 0.85, 0.3], [0.6, 0.5, 0.95]];

/// `2W × H` RGB bytes of the preview of `meshes` (camera frame, metres) over `frame`.
pub fn preview_rgb(frame: &RgbdFrame, meshes: &[&Mesh]) -> Result<(Vec<u8>, usize, usize)> {
    let (w, h) = (frame.width, frame.height);
    let rms: Vec<RenderMesh> = meshes
        .iter()
        .enumerate()
        .filter(|(_, m)| !m.faces.is_empty())
        .map(|(i, m)| RenderMesh::from_mesh(m, &format!("object {i}")))
        .collect::<Result<_>>()?;
    let instances: Vec<Instance> = rms
        .iter()
        .enumerate()
        .map(|(i, m)| {
            let c = PALETTE[i % PALETTE.len()];
            Instance {
                material: Material { color: c, color2: c, ..Material::default() },
                ..Instance::new(m, Similarity::identity(), i as i64)
            }
        })
        .collect();
    let r = render(&instances, &Camera::new(w, h, frame.intrinsics), &RenderOptions::default())?;
    let mut out = vec![0u8; 2 * w * h * 3];
    for y in 0..h {
        for x in 0..w {
            let p = y * w + x;
            let src = &frame.rgb[p * 3..p * 3 + 3];
            let left = (y * 2 * w + x) * 3;
            out[left..left + 3].copy_from_slice(src);
            let right = (y * 2 * w + w + x) * 3;
            if r.index[p] >= 0 {
                out[right..right + 3].copy_from_slice(&r.rgb[p * 3..p * 3 + 3]);
            } else {
                for k in 0..3 {
                    out[right + k] = (src[k] as f32 * 0.35) as u8;
                }
            }
        }
    }
    Ok((out, 2 * w, h))
}

/// Writes the preview as a PNG.
pub fn save_preview(frame: &RgbdFrame, meshes: &[&Mesh], path: &std::path::Path) -> Result<()> {
    let (rgb, w, h) = preview_rgb(frame, meshes)?;
    save_png(rgb, w, h, path)
}

/// The mesh colour of [`overlay_rgb`] (RecGen's `overlay.png`).
pub const OVERLAY_COLOR: [u8; 3] = [116, 92, 180];

/// The mesh's opacity over the input in [`overlay_rgb`].
pub const OVERLAY_OPACITY: f32 = 0.6;

/// `W × H` RGB bytes of RecGen's `overlay.png`: the input image (`rgb`, interleaved,
/// row-major) with `mesh` (camera frame, metres) ray-cast from the input camera `k` and
/// blended over it at [`OVERLAY_OPACITY`], in [`OVERLAY_COLOR`] shaded by how squarely the
/// hit face faces the optical axis (`0.25 + 0.75·|n_z|`). Without a mesh (or faces) the
/// input comes back unchanged.
pub fn overlay_rgb(rgb: &[u8], w: usize, h: usize, k: Intrinsics, mesh: Option<&Mesh>) -> Result<Vec<u8>> {
    if rgb.len() != w * h * 3 || w == 0 || h == 0 {
        return Err(crate::Error::input("overlay", format!("image of {} bytes is not {w}×{h} RGB", rgb.len())));
    }
    let mut out = rgb.to_vec();
    // Faces with a non-finite vertex are left out rather than failing the picture.
    let Some(m) = mesh else { return Ok(out) };
    let finite = |i: u32| m.vertices.get(i as usize).is_some_and(|v| v.iter().all(|x| x.is_finite()));
    let faces: Vec<[u32; 3]> = m.faces.iter().copied().filter(|f| f.iter().all(|&i| finite(i))).collect();
    if faces.is_empty() {
        return Ok(out);
    }
    let vertices: Vec<[f64; 3]> = m.vertices.iter().map(|v| v.map(|x| if x.is_finite() { x as f64 } else { 0.0 })).collect();
    let rm = RenderMesh::new(&vertices, &faces, "overlay mesh")?;
    let r = render(&[Instance::new(&rm, Similarity::identity(), 0)], &Camera::new(w, h, k), &RenderOptions::default())?;
    for p in (0..w * h).filter(|&p| r.index[p] >= 0) {
        let shade = (0.25 + 0.75 * r.normal_cam[p][2].abs()).clamp(0.0, 1.0);
        for c in 0..3 {
            // The shaded colour in whole steps, then the blend, as 8-bit images round down.
            let paint = (OVERLAY_COLOR[c] as f32 * shade).floor();
            let v = rgb[3 * p + c] as f32 * (1.0 - OVERLAY_OPACITY) + paint * OVERLAY_OPACITY;
            out[3 * p + c] = v.clamp(0.0, 255.0) as u8;
        }
    }
    Ok(out)
}

/// Writes [`overlay_rgb`] as a PNG.
pub fn save_overlay(rgb: &[u8], w: usize, h: usize, k: Intrinsics, mesh: Option<&Mesh>, path: &std::path::Path) -> Result<()> {
    save_png(overlay_rgb(rgb, w, h, k, mesh)?, w, h, path)
}

fn save_png(rgb: Vec<u8>, w: usize, h: usize, path: &std::path::Path) -> Result<()> {
    let img = image::RgbImage::from_raw(w as u32, h as u32, rgb).ok_or_else(|| crate::Error::msg("png: buffer size"))?;
    img.save(path).map_err(|e| crate::Error::input(path.display().to_string(), format!("cannot write PNG: {e}")))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::frame::Intrinsics;

    /// A box in front of the camera covers the image centre on the right half
    /// only; the left half is the input unchanged.
    #[test]
    fn preview_draws_meshes_from_the_input_camera() -> Result<()> {
        let (w, h) = (64usize, 48usize);
        let frame = RgbdFrame {
            width: w,
            height: h,
            rgb: vec![200u8; w * h * 3],
            depth_m: vec![0.0; w * h],
            intrinsics: Intrinsics::new(60.0, 60.0, 32.0, 24.0)?,
            rgb_path: Default::default(),
            depth_path: Default::default(),
            intrinsics_source: "explicit".into(),
            depth_scale_m: 1.0,
        };
        let s = 0.05f32;
        let mesh = crate::mesh::primitives::box_between([-s, -s, 0.5 - s], [s, s, 0.5 + s]);
        let (rgb, pw, ph) = preview_rgb(&frame, &[&mesh])?;
        assert_eq!((pw, ph), (2 * w, h));
        let px = |x: usize, y: usize| &rgb[(y * pw + x) * 3..(y * pw + x) * 3 + 3];
        assert_eq!(px(w / 2, h / 2), &[200, 200, 200]);
        assert_ne!(px(w + w / 2, h / 2), &[70, 70, 70], "the box must be drawn at the centre");
        assert_eq!(px(w + 1, 1), &[70, 70, 70], "background is the dimmed input");
        Ok(())
    }

    /// The overlay is the input where the mesh is not, and the blend of the input with the
    /// shaded mesh colour where it is: a box face-on at the centre gets |n_z| = 1.
    #[test]
    fn overlay_blends_the_mesh_over_the_input() -> Result<()> {
        let (w, h) = (64usize, 48usize);
        let rgb: Vec<u8> = (0..w * h * 3).map(|i| (i % 251) as u8).collect();
        let k = Intrinsics::new(60.0, 60.0, 32.0, 24.0)?;
        let s = 0.05f32;
        let mesh = crate::mesh::primitives::box_between([-s, -s, 0.5 - s], [s, s, 0.5 + s]);
        let o = overlay_rgb(&rgb, w, h, k, Some(&mesh))?;
        let at = |img: &[u8], x: usize, y: usize| [0, 1, 2].map(|c| img[(y * w + x) * 3 + c]);
        assert_eq!(at(&o, 1, 1), at(&rgb, 1, 1), "off the mesh: the input");
        let (c, i) = (at(&o, w / 2, h / 2), at(&rgb, w / 2, h / 2));
        for ch in 0..3 {
            let want = (i[ch] as f32 * 0.4 + OVERLAY_COLOR[ch] as f32 * 0.6) as u8;
            assert!(c[ch].abs_diff(want) <= 1, "channel {ch}: {} vs {want}", c[ch]);
        }
        assert_eq!(overlay_rgb(&rgb, w, h, k, None)?, rgb);
        assert!(overlay_rgb(&rgb[1..], w, h, k, Some(&mesh)).is_err());
        Ok(())
    }
}
