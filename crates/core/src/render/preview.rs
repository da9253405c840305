//! A side-by-side picture of a reconstruction: the input colour image on the
//! left; on the right the posed meshes ray-cast from the input camera
//! (shaded, one colour per object) over the dimmed input.

use crate::dataset::frame::RgbdFrame;
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
    let img = image::RgbImage::from_raw(w as u32, h as u32, rgb).ok_or_else(|| crate::Error::msg("preview: buffer size"))?;
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
}
