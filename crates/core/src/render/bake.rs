//! Texture baking: the colour of every texel of a [`UvMesh`]'s atlas, from the
//! photos of the views that see its surface point, else from the mesh's vertex
//! colours.
//!
//! Per texel (its surface point `p` and the face's normal `n`) and per view:
//! `p` is projected with the view's intrinsics and pose; the view sees it when
//! the view's measured depth at that pixel is within a tolerance of `p`'s depth
//! (nothing in front of it, and the mesh there is where the sensor saw a
//! surface) and the face turns towards the camera (`cos θ ≥ min_cos`). The
//! colour is the mean of the views' bilinear samples weighted by `cos^sharpness`:
//! the most frontal view dominates, and colours blend where two views see the
//! point about equally (no hard seam between views). A texel no view sees
//! takes the interpolated vertex colour (grey without vertex colours). Last,
//! the colours are dilated into every empty texel (the gutter and unused
//! space, nearest chart's colour first) so mip-mapping does not bleed the
//! background into the charts.

use crate::dataset::Intrinsics;
use crate::math::Similarity;
use crate::mesh::atlas::raster_triangle;
use crate::mesh::{Texture, TexturedMesh, UvMesh};
use crate::{Error, Result};
use rayon::prelude::*;

/// One input view: its photo, measured depth, camera and pose.
#[derive(Clone, Copy)]
pub struct BakeView<'a> {
    /// Interleaved RGB, row-major, `width · height · 3` bytes.
    pub rgb: &'a [u8],
    /// Depth along the optical axis, metres, `width · height` (0 or non-finite: none).
    pub depth_m: &'a [f32],
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// The camera's pinhole intrinsics.
    pub intrinsics: Intrinsics,
    /// Mesh frame → this camera's frame (OpenCV axes; metres).
    pub camera_from_mesh: Similarity,
}

/// Settings of [`bake_texture`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BakeOptions {
    /// A view sees a point when its depth differs from the measured depth by at
    /// most `max(depth_tolerance_m, depth_tolerance_rel · depth)`.
    pub depth_tolerance_m: f64,
    /// See `depth_tolerance_m`.
    pub depth_tolerance_rel: f64,
    /// Least cosine between the face normal and the direction to the camera.
    pub min_cos: f64,
    /// Exponent of the cosine weight (higher: the most frontal view alone).
    pub sharpness: i32,
}

impl Default for BakeOptions {
    fn default() -> Self {
        BakeOptions { depth_tolerance_m: 0.015, depth_tolerance_rel: 0.02, min_cos: 0.2, sharpness: 8 }
    }
}

/// Where a bake's texels came from.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct BakeReport {
    /// Texels inside a chart.
    pub texels_surface: usize,
    /// Of those, coloured from at least one view's photo.
    pub texels_from_views: usize,
    /// Of those, coloured from the vertex colours (no view sees them).
    pub texels_from_vertices: usize,
}

fn check_view(i: usize, v: &BakeView) -> Result<()> {
    let what = format!("bake view {i}");
    let n = v.width.checked_mul(v.height).ok_or_else(|| Error::input(&what, "image size overflows"))?;
    if n == 0 {
        return Err(Error::input(&what, format!("image size {}×{}: both must be ≥ 1", v.width, v.height)));
    }
    if v.rgb.len() != 3 * n {
        return Err(Error::input(&what, format!("{} RGB bytes for a {}×{} image (expected {})", v.rgb.len(), v.width, v.height, 3 * n)));
    }
    if v.depth_m.len() != n {
        return Err(Error::input(&what, format!("{} depth values for a {}×{} image", v.depth_m.len(), v.width, v.height)));
    }
    let k = v.intrinsics;
    if !(k.fx > 0.0 && k.fy > 0.0 && k.fx.is_finite() && k.fy.is_finite() && k.cx.is_finite() && k.cy.is_finite()) {
        return Err(Error::input(&what, format!("intrinsics {k:?}: fx, fy must be finite and > 0")));
    }
    if !(v.camera_from_mesh.scale > 0.0 && v.camera_from_mesh.scale.is_finite()) {
        return Err(Error::input(&what, "pose: scale must be finite and > 0"));
    }
    Ok(())
}

/// Bilinear sample of `rgb` at continuous pixel coordinates (pixel centres at `i + 0.5`).
fn bilinear(v: &BakeView, u: f64, w: f64) -> [f64; 3] {
    let (x, y) = ((u - 0.5).clamp(0.0, (v.width - 1) as f64), (w - 0.5).clamp(0.0, (v.height - 1) as f64));
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (x1, y1) = ((x0 + 1).min(v.width - 1), (y0 + 1).min(v.height - 1));
    let (fx, fy) = (x - x0 as f64, y - y0 as f64);
    let px = |xx: usize, yy: usize, c: usize| v.rgb[3 * (yy * v.width + xx) + c] as f64;
    [0, 1, 2].map(|c| {
        let top = px(x0, y0, c) * (1.0 - fx) + px(x1, y0, c) * fx;
        let bot = px(x0, y1, c) * (1.0 - fx) + px(x1, y1, c) * fx;
        top * (1.0 - fy) + bot * fy
    })
}

/// The colour one view gives `p` (mesh frame) with face normal `n`, and its weight.
fn view_sample(v: &BakeView, p: [f64; 3], n: [f64; 3], opts: &BakeOptions) -> Option<([f64; 3], f64)> {
    let q = v.camera_from_mesh.apply(&p);
    if q[2] <= 1e-6 {
        return None;
    }
    let k = v.intrinsics;
    let (u, w) = (k.fx * q[0] / q[2] + k.cx, k.fy * q[1] / q[2] + k.cy);
    if !(u >= 0.0 && w >= 0.0 && u < v.width as f64 && w < v.height as f64) {
        return None;
    }
    let d = v.depth_m[w as usize * v.width + u as usize] as f64;
    if !(d > 0.0 && d.is_finite()) || (q[2] - d).abs() > opts.depth_tolerance_m.max(opts.depth_tolerance_rel * d) {
        return None;
    }
    let r = v.camera_from_mesh.rotation;
    let nc = [0, 1, 2].map(|i| (0..3).map(|j| r[i][j] * n[j]).sum::<f64>());
    let (ln, lq) = ((nc[0] * nc[0] + nc[1] * nc[1] + nc[2] * nc[2]).sqrt(), (q[0] * q[0] + q[1] * q[1] + q[2] * q[2]).sqrt());
    if ln <= 0.0 {
        return None;
    }
    let cos = -(nc[0] * q[0] + nc[1] * q[1] + nc[2] * q[2]) / (ln * lq);
    (cos >= opts.min_cos).then(|| (bilinear(v, u, w), cos.powi(opts.sharpness)))
}

/// Bakes the texture of `atlas` (a `size`² image, the atlas's own size) from
/// `views` and the mesh's vertex colours ([module docs](self)). Errors name the
/// view whose image, depth or camera is malformed. Deterministic for any
/// thread count (every texel is computed on its own).
pub fn bake_texture(atlas: &UvMesh, views: &[BakeView], opts: &BakeOptions) -> Result<(Texture, BakeReport)> {
    for (i, v) in views.iter().enumerate() {
        check_view(i, v)?;
    }
    let n = atlas.options.size as usize;
    let mesh = &atlas.mesh;
    mesh.validate()?;
    if atlas.uv.len() != mesh.vertices.len() {
        return Err(Error::msg(format!("bake: {} UVs for {} vertices", atlas.uv.len(), mesh.vertices.len())));
    }
    // Which face and where in it each texel lies.
    let mut hit: Vec<(u32, [f32; 3])> = vec![(u32::MAX, [0.0; 3]); n * n];
    for f in 0..mesh.faces.len() {
        raster_triangle(atlas.face_texels(f), n, n, |x, y, b| hit[y * n + x] = (f as u32, b.map(|x| x as f32)));
    }
    let normals = mesh.face_normals();
    let colours = mesh.vertex_colors();
    let texel = |&(f, b): &(u32, [f32; 3])| -> Option<([u8; 3], bool)> {
        if f == u32::MAX {
            return None;
        }
        let face = mesh.faces[f as usize];
        let b = b.map(f64::from);
        let p = [0, 1, 2].map(|k| (0..3).map(|c| b[c] * mesh.vertices[face[c] as usize][k] as f64).sum::<f64>());
        let nrm = normals[f as usize].map(f64::from);
        let (mut acc, mut wsum) = ([0.0f64; 3], 0.0f64);
        for v in views {
            if let Some((c, w)) = view_sample(v, p, nrm, opts) {
                for k in 0..3 {
                    acc[k] += w * c[k];
                }
                wsum += w;
            }
        }
        if wsum > 0.0 {
            return Some((acc.map(|x| (x / wsum).round().clamp(0.0, 255.0) as u8), true));
        }
        let c = match &colours {
            Some(cs) => [0, 1, 2].map(|k| (0..3).map(|c| b[c] * cs[face[c] as usize][k] as f64).sum::<f64>()),
            None => [0.5; 3],
        };
        Some((c.map(|x| (x * 255.0).round().clamp(0.0, 255.0) as u8), false))
    };
    let baked: Vec<Option<([u8; 3], bool)>> = hit.par_iter().map(texel).collect();
    let mut report = BakeReport::default();
    for (_, from_view) in baked.iter().flatten() {
        report.texels_surface += 1;
        if *from_view {
            report.texels_from_views += 1;
        } else {
            report.texels_from_vertices += 1;
        }
    }
    let filled: Vec<Option<[u8; 3]>> = baked.into_iter().map(|t| t.map(|(c, _)| c)).collect();
    Ok((Texture { width: n, height: n, rgb: dilate(filled, n) }, report))
}

/// Fills every empty texel with the colour of the nearest filled one
/// (breadth-first over 4-neighbours, in texel order: deterministic); grey when
/// nothing is filled.
fn dilate(mut t: Vec<Option<[u8; 3]>>, n: usize) -> Vec<u8> {
    let mut queue: std::collections::VecDeque<usize> = (0..t.len()).filter(|&i| t[i].is_some()).collect();
    while let Some(i) = queue.pop_front() {
        let (x, y) = (i % n, i / n);
        let c = t[i];
        for (nx, ny) in [(x.wrapping_sub(1), y), (x + 1, y), (x, y.wrapping_sub(1)), (x, y + 1)] {
            if nx < n && ny < n && t[ny * n + nx].is_none() {
                t[ny * n + nx] = c;
                queue.push_back(ny * n + nx);
            }
        }
    }
    t.into_iter().flat_map(|c| c.unwrap_or([128; 3])).collect()
}

/// Lays out `mesh` on an atlas for a `size`² texture and bakes it from `views`
/// ([`crate::mesh::uv_atlas`] then [`bake_texture`]).
pub fn texture_mesh(mesh: &crate::mesh::Mesh, size: u32, views: &[BakeView], opts: &BakeOptions) -> Result<(TexturedMesh, BakeReport)> {
    let atlas = crate::mesh::uv_atlas(mesh, &crate::mesh::AtlasOptions::for_size(size))?;
    let (texture, report) = bake_texture(&atlas, views, opts)?;
    Ok((TexturedMesh { atlas, texture }, report))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{box_between, Mesh};
    use crate::render::{render, Camera, Instance, Light, Material, RenderMesh, RenderOptions};

    /// A cube whose six faces have six colours, seen by recon's ray caster with
    /// flat (ambient-only) light from a corner: three faces visible.
    fn cube_scene() -> (Mesh, Vec<(Mesh, [f32; 3])>, Camera, crate::render::Rendered) {
        let cube = box_between([-0.05; 3], [0.05; 3]);
        let h = 0.05f32;
        // One thin slab per face, just outside it, carrying the face's colour.
        let e = 1e-4f32;
        let slabs: Vec<(Mesh, [f32; 3])> = vec![
            (box_between([h, -h, -h], [h + e, h, h]), [0.9, 0.1, 0.1]),
            (box_between([-h - e, -h, -h], [-h, h, h]), [0.1, 0.9, 0.1]),
            (box_between([-h, h, -h], [h, h + e, h]), [0.1, 0.1, 0.9]),
            (box_between([-h, -h - e, -h], [h, -h, h]), [0.9, 0.9, 0.1]),
            (box_between([-h, -h, h], [h, h, h + e]), [0.1, 0.9, 0.9]),
            (box_between([-h, -h, -h - e], [h, h, -h]), [0.9, 0.1, 0.9]),
        ];
        let k = Intrinsics { fx: 300.0, fy: 300.0, cx: 80.0, cy: 60.0 };
        let mut cam = Camera::new(160, 120, k);
        cam.world_to_cam = Camera::look_at([0.25, 0.2, 0.3], [0.0; 3], [0.0, 0.0, 1.0]);
        let rms: Vec<RenderMesh> = slabs.iter().map(|(m, _)| RenderMesh::from_mesh(m, "slab").unwrap()).collect();
        let inst: Vec<Instance> = rms
            .iter()
            .zip(&slabs)
            .enumerate()
            .map(|(i, (rm, (_, c)))| {
                let mut x = Instance::new(rm, Similarity::identity(), i as i64);
                x.material = Material { color: *c, color2: *c, pattern: crate::render::Pattern::Solid };
                x
            })
            .collect();
        let opts = RenderOptions { light: Light { direction_cam: [0.0, 0.0, -1.0], ambient: 1.0, diffuse: 0.0 }, background: [0, 0, 0] };
        let r = render(&inst, &cam, &opts).unwrap();
        (cube, slabs, cam, r)
    }

    #[test]
    fn cube_faces_get_their_colours() {
        let (mut cube, slabs, cam, r) = cube_scene();
        // Vertex colours (the fallback for hidden faces): mid grey.
        cube.vertex_attrs = Some(vec![[0.5, 0.5, 0.5, 0.5, 0.5, 1.0]; cube.vertices.len()]);
        let view = BakeView {
            rgb: &r.rgb,
            depth_m: &r.depth,
            width: r.width,
            height: r.height,
            intrinsics: cam.k,
            camera_from_mesh: cam.world_to_cam,
        };
        let (tm, rep) = texture_mesh(&cube, 128, &[view], &BakeOptions::default()).unwrap();
        assert!(rep.texels_from_views > 0 && rep.texels_from_vertices > 0, "{rep:?}");
        let eye = cam.eye();
        // Per face of the cube: the texels well inside it must carry the slab's
        // rendered colour when the face looks at the camera, else the vertex grey.
        let a = &tm.atlas;
        let n = a.options.size as usize;
        let normals = a.mesh.face_normals();
        let (mut checked_seen, mut checked_hidden) = (0, 0);
        for f in 0..a.mesh.faces.len() {
            let nrm = normals[f];
            let (slab, col) = slabs
                .iter()
                .max_by(|x, y| {
                    let dx = crate::mesh::primitives::centre_of(&x.0);
                    let dy = crate::mesh::primitives::centre_of(&y.0);
                    let dot = |d: [f64; 3]| (0..3).map(|k| d[k] * nrm[k] as f64).sum::<f64>();
                    dot(dx).total_cmp(&dot(dy))
                })
                .unwrap();
            let _ = slab;
            let c = a.mesh.faces[f].map(|v| a.mesh.vertices[v as usize]);
            let centre = [0, 1, 2].map(|k| (c[0][k] + c[1][k] + c[2][k]) as f64 / 3.0);
            let to_eye = [0, 1, 2].map(|k| eye[k] - centre[k]);
            let facing = (0..3).map(|k| to_eye[k] * nrm[k] as f64).sum::<f64>() > 0.0;
            let want: [u8; 3] = if facing { (*col).map(|x| (x * 255.0).round() as u8) } else { [128; 3] };
            raster_triangle(a.face_texels(f), n, n, |x, y, b| {
                // Away from the face's edges (bilinear samples there mix neighbours).
                if b.iter().all(|&w| w > 0.2) {
                    let got = tm.texture.texel(x, y);
                    assert!(
                        (0..3).all(|k| (got[k] as i32 - want[k] as i32).abs() <= 3),
                        "face {f} texel ({x}, {y}): {got:?}, want {want:?}"
                    );
                    if facing {
                        checked_seen += 1
                    } else {
                        checked_hidden += 1
                    }
                }
            });
        }
        assert!(checked_seen > 100 && checked_hidden > 100, "{checked_seen} seen, {checked_hidden} hidden texels checked");
        // Gutter and unused texels are dilated: no black (the render's background) anywhere.
        assert!(tm.texture.rgb.chunks(3).all(|c| c != [0, 0, 0]));
        // Determinism.
        let (again, _) = texture_mesh(&cube, 128, &[view], &BakeOptions::default()).unwrap();
        assert_eq!(again, tm);
    }

    #[test]
    fn malformed_views_are_named() {
        let cube = box_between([-0.05; 3], [0.05; 3]);
        let rgb = vec![0u8; 10];
        let depth = vec![0f32; 4];
        let k = Intrinsics { fx: 1.0, fy: 1.0, cx: 0.0, cy: 0.0 };
        let v = BakeView { rgb: &rgb, depth_m: &depth, width: 2, height: 2, intrinsics: k, camera_from_mesh: Similarity::identity() };
        let e = texture_mesh(&cube, 64, &[v], &BakeOptions::default()).unwrap_err().to_string();
        assert!(e.contains("bake view 0") && e.contains("RGB bytes"), "{e}");
    }
}
