//! CPU Gaussian splatting: the EWA rasteriser of 3D Gaussian Splatting (Kerbl et al.
//! 2023) for SH degree 0, which is what the SLat Gaussian decoder produces. It renders
//! the predicted Gaussians into a view, for the post-hoc colour calibration
//! (`engine::posthoc_color`) and for colour comparisons in novel views.
//!
//! Per Gaussian: the camera-frame covariance `W·Σ·Wᵀ` is projected with the Jacobian of
//! the pinhole map at the centre (the view direction clamped to 1.3× the image's extent,
//! as 3DGS does), dilated by 0.3 px² (its low-pass filter), and cut off at 3σ. Pixels
//! composite front to back in depth order: `α = min(0.99, o·exp(−½ dᵀ Σ₂⁻¹ d))`,
//! contributions under 1/255 are skipped, and a pixel stops once its transmittance would
//! fall under 1e-4 (that last splat is not added), as the CUDA rasteriser does. Colours
//! are `max(0, C0·dc + 0.5)` (not clamped above, like 3DGS).
//!
//! Pixel centres are at integer coordinates (the convention of [`super::raycast`]), so
//! the centre of pixel `(u, v)` is the ray through `((u − cx)/fx, (v − cy)/fy, 1)`.
//! Tiles of 16×16 pixels run in parallel; each pixel is a pure function of the inputs
//! (depth ties broken by index), so the image does not depend on the thread count.

use super::raycast::Camera;
use crate::gaussians::Gaussians;
use crate::math::quat_to_matrix;
use crate::{Error, Result};
use rayon::prelude::*;

/// Side of the square pixel tiles that are composited independently.
const TILE: usize = 16;
/// Largest image side accepted (pixels): bounds the buffers before any work.
pub const MAX_SPLAT_SIDE: usize = 8192;

/// What a splat render produces; images are row-major `width × height`.
#[derive(Debug, Clone, PartialEq)]
pub struct SplatImage {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Composited colour (the background included where the splats leave it visible).
    pub color: Vec<[f32; 3]>,
    /// Accumulated opacity `1 − T` (what 3DGS renders with every colour set to 1 on black).
    pub alpha: Vec<f32>,
}

/// Background and clipping of a splat render.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SplatOptions {
    /// Colour behind the splats.
    pub background: [f32; 3],
    /// Splats whose centre is nearer than this (camera z, in the scene's units) are dropped.
    pub near: f64,
}

impl Default for SplatOptions {
    fn default() -> Self {
        SplatOptions { background: [0.0; 3], near: 0.01 }
    }
}

/// One Gaussian projected into the image.
#[derive(Clone, Copy)]
struct Splat {
    /// Centre, pixels.
    u: f64,
    v: f64,
    /// Inverse 2D covariance (a, b, c) of `[[a, b], [b, c]]`.
    conic: [f64; 3],
    opacity: f64,
    rgb: [f64; 3],
    depth: f64,
    /// Inclusive pixel rectangle (x0, y0, x1, y1) the 3σ ellipse can touch.
    rect: (usize, usize, usize, usize),
}

/// Projects one Gaussian (world frame) into `cam`; `None` when it is behind the near
/// plane, degenerate, or off the image.
fn project(g: &Gaussians, i: usize, cam: &Camera, near: f64) -> Option<Splat> {
    let w2c = &cam.world_to_cam;
    let p = g.positions[i].map(f64::from);
    let pc = w2c.apply(&p);
    let z = pc[2];
    if !(z > near) {
        return None;
    }
    let k = &cam.k;
    let (w, h) = (cam.width as f64, cam.height as f64);
    // 3DGS clamps the direction the Jacobian is taken at to 1.3× the field of view.
    let lim_x = 1.3 * k.cx.max(w - k.cx) / k.fx;
    let lim_y = 1.3 * k.cy.max(h - k.cy) / k.fy;
    let tx = (pc[0] / z).clamp(-lim_x, lim_x) * z;
    let ty = (pc[1] / z).clamp(-lim_y, lim_y) * z;
    let jac = [[k.fx / z, 0.0, -k.fx * tx / (z * z)], [0.0, k.fy / z, -k.fy * ty / (z * z)]];
    // Σ = R·diag(s²)·Rᵀ in the object's axes, then into the camera: W = s_w·R_w.
    let r = quat_to_matrix(g.rotations[i]).map(|row| row.map(f64::from));
    let s = g.scales[i].map(f64::from);
    let sw = w2c.scale;
    // M = W·R·diag(s): Σ_cam = M·Mᵀ.
    let m: [[f64; 3]; 3] =
        std::array::from_fn(|a| std::array::from_fn(|b| sw * (0..3).map(|c| w2c.rotation[a][c] * r[c][b]).sum::<f64>() * s[b]));
    // T = J·M (2×3); Σ₂ = T·Tᵀ.
    let t: [[f64; 3]; 2] = std::array::from_fn(|a| std::array::from_fn(|b| (0..3).map(|c| jac[a][c] * m[c][b]).sum()));
    let dot = |x: &[f64; 3], y: &[f64; 3]| x[0] * y[0] + x[1] * y[1] + x[2] * y[2];
    let (a, b, c) = (dot(&t[0], &t[0]) + 0.3, dot(&t[0], &t[1]), dot(&t[1], &t[1]) + 0.3);
    let det = a * c - b * b;
    if !(det > 0.0) {
        return None;
    }
    let conic = [c / det, -b / det, a / det];
    let mid = 0.5 * (a + c);
    let lambda = mid + (mid * mid - det).max(0.1).sqrt();
    let radius = (3.0 * lambda.sqrt()).ceil();
    let u = k.fx * pc[0] / z + k.cx;
    let v = k.fy * pc[1] / z + k.cy;
    if !(u.is_finite() && v.is_finite() && radius.is_finite()) {
        return None;
    }
    let (x0, x1) = ((u - radius).max(0.0), (u + radius).min(w - 1.0));
    let (y0, y1) = ((v - radius).max(0.0), (v + radius).min(h - 1.0));
    if x0 > x1 || y0 > y1 {
        return None;
    }
    let rgb = g.rgb(i).map(f64::from);
    let opacity = f64::from(g.opacities[i]);
    Some(Splat {
        u,
        v,
        conic,
        opacity,
        rgb,
        depth: z,
        rect: (x0.ceil() as usize, y0.ceil() as usize, x1.floor() as usize, y1.floor() as usize),
    })
}

/// Renders `g` (world frame) into `cam`. Errors: Gaussians whose fields differ in
/// length, or an image side of 0 or above [`MAX_SPLAT_SIDE`].
pub fn render_gaussians(g: &Gaussians, cam: &Camera, opts: &SplatOptions) -> Result<SplatImage> {
    g.validate()?;
    let (w, h) = (cam.width, cam.height);
    if w == 0 || h == 0 || w > MAX_SPLAT_SIDE || h > MAX_SPLAT_SIDE {
        return Err(Error::msg(format!("splat render: image {w}×{h} must be 1..={MAX_SPLAT_SIDE} pixels a side")));
    }
    let mut splats: Vec<(usize, Splat)> =
        (0..g.len()).into_par_iter().filter_map(|i| project(g, i, cam, opts.near).map(|s| (i, s))).collect();
    splats.sort_by(|(i, a), (j, b)| a.depth.total_cmp(&b.depth).then(i.cmp(j)));
    let (tx, ty) = (w.div_ceil(TILE), h.div_ceil(TILE));
    let mut lists: Vec<Vec<u32>> = vec![Vec::new(); tx * ty];
    for (k, (_, s)) in splats.iter().enumerate() {
        let (x0, y0, x1, y1) = s.rect;
        for ty_ in y0 / TILE..=y1 / TILE {
            for tx_ in x0 / TILE..=x1 / TILE {
                lists[ty_ * tx + tx_].push(k as u32);
            }
        }
    }
    let bg = opts.background.map(f64::from);
    let tiles: Vec<Vec<([f32; 3], f32)>> = lists
        .par_iter()
        .enumerate()
        .map(|(t, list)| {
            let (ox, oy) = ((t % tx) * TILE, (t / tx) * TILE);
            let (tw, th) = (TILE.min(w - ox), TILE.min(h - oy));
            let mut out = Vec::with_capacity(tw * th);
            for py in oy..oy + th {
                for px in ox..ox + tw {
                    let (mut trans, mut col) = (1.0f64, [0.0f64; 3]);
                    for &k in list {
                        let s = &splats[k as usize].1;
                        let (dx, dy) = (s.u - px as f64, s.v - py as f64);
                        let power = -0.5 * (s.conic[0] * dx * dx + s.conic[2] * dy * dy) - s.conic[1] * dx * dy;
                        if power > 0.0 {
                            continue;
                        }
                        let alpha = (s.opacity * power.exp()).min(0.99);
                        if alpha < 1.0 / 255.0 {
                            continue;
                        }
                        let next = trans * (1.0 - alpha);
                        if next < 1e-4 {
                            break;
                        }
                        for c in 0..3 {
                            col[c] += s.rgb[c] * alpha * trans;
                        }
                        trans = next;
                    }
                    out.push(([0, 1, 2].map(|c| (col[c] + trans * bg[c]) as f32), (1.0 - trans) as f32));
                }
            }
            out
        })
        .collect();
    let mut color = vec![[0.0f32; 3]; w * h];
    let mut alpha = vec![0.0f32; w * h];
    for (t, px) in tiles.into_iter().enumerate() {
        let (ox, oy) = ((t % tx) * TILE, (t / tx) * TILE);
        let tw = TILE.min(w - ox);
        for (k, (c, a)) in px.into_iter().enumerate() {
            let (x, y) = (ox + k % tw, oy + k / tw);
            color[y * w + x] = c;
            alpha[y * w + x] = a;
        }
    }
    Ok(SplatImage { width: w, height: h, color, alpha })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::frame::Intrinsics;
    use crate::gaussians::SH_C0;

    fn one(pos: [f32; 3], sigma: f32, opacity: f32, rgb: [f32; 3]) -> Gaussians {
        Gaussians {
            positions: vec![pos],
            scales: vec![[sigma; 3]],
            rotations: vec![[1.0, 0.0, 0.0, 0.0]],
            opacities: vec![opacity],
            dc: vec![rgb.map(|c| (c - 0.5) / SH_C0)],
        }
    }

    fn cam(w: usize, h: usize) -> Camera {
        Camera::new(w, h, Intrinsics { fx: 100.0, fy: 100.0, cx: (w as f64 - 1.0) / 2.0, cy: (h as f64 - 1.0) / 2.0 })
    }

    #[test]
    fn an_isotropic_splat_has_the_analytic_footprint() {
        // σ = 0.01 at z = 1 with f = 100: 1 px, plus the 0.3 px² dilation.
        let g = one([0.0, 0.0, 1.0], 0.01, 0.8, [0.2, 0.6, 1.0]);
        let img = render_gaussians(&g, &cam(33, 33), &SplatOptions::default()).unwrap();
        let var = 1.0 + 0.3;
        for (dx, dy) in [(0i32, 0i32), (1, 0), (0, 2), (1, 1)] {
            let (x, y) = ((16 + dx) as usize, (16 + dy) as usize);
            let want = (0.8 * (-0.5 * f64::from(dx * dx + dy * dy) / var).exp()).min(0.99);
            let a = img.alpha[y * 33 + x] as f64;
            assert!((a - want).abs() < 1e-6, "({dx},{dy}): alpha {a} vs {want}");
            assert!((img.color[y * 33 + x][1] as f64 - 0.6 * want).abs() < 1e-6);
        }
        // Beyond 3σ nothing.
        assert_eq!(img.alpha[16 * 33 + 16 + 6], 0.0);
    }

    #[test]
    fn nearer_splats_cover_farther_ones_whatever_their_order() {
        let mut g = one([0.0, 0.0, 2.0], 0.05, 0.99, [1.0, 0.0, 0.0]);
        g.extend(&one([0.0, 0.0, 1.0], 0.05, 0.99, [0.0, 0.0, 1.0]));
        let img = render_gaussians(&g, &cam(21, 21), &SplatOptions { background: [0.0, 1.0, 0.0], near: 0.01 }).unwrap();
        let c = img.color[10 * 21 + 10];
        assert!(c[2] > 0.98 && c[0] < 0.02 && c[1] < 1e-3, "{c:?}");
        // Behind the camera: dropped; the background shows.
        let back = one([0.0, 0.0, -1.0], 0.05, 0.99, [1.0, 0.0, 0.0]);
        let img = render_gaussians(&back, &cam(8, 8), &SplatOptions { background: [0.0, 1.0, 0.0], near: 0.01 }).unwrap();
        assert!(img.alpha.iter().all(|&a| a == 0.0) && img.color.iter().all(|c| *c == [0.0, 1.0, 0.0]));
    }

    #[test]
    fn the_image_does_not_depend_on_the_thread_count() {
        let mut rng = crate::rng::SeededRng::new(5);
        let n = 3000;
        let g = Gaussians {
            positions: (0..n).map(|_| [rng.uniform() as f32 - 0.5, rng.uniform() as f32 - 0.5, 1.5 + rng.uniform() as f32]).collect(),
            scales: (0..n).map(|_| [0.01 + 0.02 * rng.uniform() as f32, 0.01, 0.03]).collect(),
            rotations: (0..n).map(|_| [rng.uniform() as f32, rng.uniform() as f32 - 0.5, 0.3, -0.2]).collect(),
            opacities: (0..n).map(|_| rng.uniform() as f32).collect(),
            dc: (0..n).map(|_| [rng.uniform() as f32, -(rng.uniform() as f32), 0.5]).collect(),
        };
        let c = cam(70, 50);
        let run = |t| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(t)
                .build()
                .unwrap()
                .install(|| render_gaussians(&g, &c, &SplatOptions::default()).unwrap())
        };
        let (a, b) = (run(1), run(3));
        assert!(a.alpha.iter().filter(|&&x| x > 0.5).count() > 500);
        assert_eq!(a, b);
    }

    #[test]
    fn bad_inputs_are_refused() {
        let mut g = one([0.0, 0.0, 1.0], 0.01, 0.5, [0.5; 3]);
        assert!(render_gaussians(&g, &cam(0, 4), &SplatOptions::default()).is_err());
        g.opacities.clear();
        assert!(render_gaussians(&g, &cam(4, 4), &SplatOptions::default()).is_err());
    }
}
