//! Post-hoc colour calibration (RecGen's `posthoc_color`): the predicted Gaussians are
//! rendered into the input view, a colour transform from their colours to the photo's is
//! fitted on the overlap of the object's (eroded) mask and the render, and, when the fit
//! passes the quality gates, applied to the Gaussians' DC colours and to the mesh colours
//! the model made.
//!
//! Fitters and gates follow upstream's `recgen_modules/utils/posthoc_color.py`: pixels
//! where the render is near black are ignored, at least 200 pixels and a render/mask IoU
//! of 0.25 are required, the fit is refined once on the 80 % of pixels it explains best,
//! gamma is kept within [0.5, 2], scales within [0.3, 3], offsets within ±0.5, and a
//! transform is kept only if it lowers the L1 error on the fit pixels by at least 3 %.
//! The gamma fit is a bounded Brent minimisation on [0.2, 4] (what scipy's
//! `minimize_scalar(method='bounded')` runs), the affine fit per-channel least squares.
//!
//! The view: as upstream, a virtual camera at the input camera's centre is turned to look
//! at the object (so the object sits at the image centre) with a focal length that makes
//! the object's canonical half-extent of 0.55 fill 70 % of a 384² image; the photo is
//! warped into it by the homography `Kv·Rl·K⁻¹` (bilinear) and the mask by nearest
//! neighbour. Unlike upstream, the warp and the render use one pixel convention (centres
//! at integers); upstream's warp and CUDA rasteriser differ by half a pixel.

use crate::dataset::frame::Intrinsics;
use crate::gaussians::{Gaussians, SH_C0};
use crate::math::Similarity;
use crate::mesh::Mesh;
use crate::render::{render_gaussians, Camera, SplatOptions};
use crate::Result;
use serde::{Deserialize, Serialize};

pub use super::options::PosthocColor;

/// Pixels whose rendered luminance is at most this are ignored (near-black render).
const DARK_T: f64 = 0.05;
/// Fewest fit pixels (and fewest overlap pixels) a fit needs.
const MIN_PX: usize = 200;
/// Smallest render/mask IoU: below it the overlap pixels are not in correspondence.
const MIN_IOU: f64 = 0.25;
/// The refit keeps the pixels up to this quantile of the first fit's residual.
const TRIM_Q: f64 = 0.8;
const GAMMA_LO: f64 = 0.5;
const GAMMA_HI: f64 = 2.0;
const SCALE_LO: f64 = 0.3;
const SCALE_HI: f64 = 3.0;
const OFF_LIM: f64 = 0.5;
/// A transform must lower the fit pixels' L1 error by this fraction.
const MIN_REL_GAIN: f64 = 0.03;
/// Side of the virtual view (pixels) and the fraction of it the object fills.
const VIEW_SIDE: usize = 384;
const VIEW_FILL: f64 = 0.7;
/// Half-extent of the canonical object cube the virtual view frames.
const CANONICAL_HALF_EXTENT: f64 = 0.55;

/// A fitted colour transform, as upstream records it (`{"type": "gamma", "gamma": …}`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum ColorTransform {
    /// `c' = c^gamma` on every channel (one gamma, fitted on luminance: hue preserving).
    Gamma {
        /// The exponent.
        gamma: f64,
    },
    /// `c' = scale·c + off` per channel.
    Affine {
        /// Per-channel gain.
        scale: [f64; 3],
        /// Per-channel offset.
        off: [f64; 3],
    },
    /// The gamma, then the affine map.
    GammaAffine {
        /// The exponent.
        gamma: f64,
        /// Per-channel gain.
        scale: [f64; 3],
        /// Per-channel offset.
        off: [f64; 3],
    },
}

impl ColorTransform {
    /// The corrected colour of `c` (inputs and outputs clamped to [0, 1]).
    pub fn apply(&self, c: [f64; 3]) -> [f64; 3] {
        let mut c = c.map(|x| x.clamp(0.0, 1.0));
        if let ColorTransform::Gamma { gamma } | ColorTransform::GammaAffine { gamma, .. } = *self {
            c = c.map(|x| x.clamp(1e-6, 1.0).powf(gamma));
        }
        if let ColorTransform::Affine { scale, off } | ColorTransform::GammaAffine { scale, off, .. } = *self {
            c = std::array::from_fn(|k| c[k] * scale[k] + off[k]);
        }
        c.map(|x| x.clamp(0.0, 1.0))
    }

    /// The transform applied to every colour.
    pub fn apply_all(&self, c: &[[f64; 3]]) -> Vec<[f64; 3]> {
        c.iter().map(|&x| self.apply(x)).collect()
    }
}

/// What the calibration saw, as upstream records it (`stats` of `posthoc_color.json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CalibrationStats {
    /// Pixels of the virtual view in both the mask and the render (alpha > 0.5).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub overlap_px: Option<usize>,
    /// Overlap over union of mask and render.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub iou: Option<f64>,
    /// Why no transform was applied (absent when one was).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub reason: Option<String>,
    /// Mean absolute colour error on the overlap before the transform.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub l1_before: Option<f64>,
    /// The same after.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub l1_after: Option<f64>,
}

/// One object's calibration, as written to `posthoc_color.json`: upstream's `variant`,
/// `transform` (`null` when gated out) and `stats`, plus what recon applied it to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PosthocColorRecord {
    /// The fitter asked for.
    pub variant: PosthocColor,
    /// The transform applied, or `None` (identity) when the fit was gated out.
    pub transform: Option<ColorTransform>,
    /// Overlap, IoU, the reason for identity, and the fit's L1 before and after.
    pub stats: CalibrationStats,
    /// Which outputs were recoloured: `gaussians`, and `mesh` when its colours came from
    /// the model (a mesh coloured from the measured points is left as it is).
    pub applied_to: Vec<String>,
}

fn lum(c: &[f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

fn clip01(c: &[f64; 3]) -> [f64; 3] {
    c.map(|x| x.clamp(0.0, 1.0))
}

/// Colours clipped to [0, 1], the pixels whose source is near black dropped; `None`
/// with fewer than [`MIN_PX`] left.
fn prep(src: &[[f64; 3]], tgt: &[[f64; 3]]) -> Option<(Vec<[f64; 3]>, Vec<[f64; 3]>)> {
    let (s, t): (Vec<[f64; 3]>, Vec<[f64; 3]>) =
        src.iter().zip(tgt).map(|(s, t)| (clip01(s), clip01(t))).filter(|(s, _)| lum(s) > DARK_T).unzip();
    (s.len() >= MIN_PX).then_some((s, t))
}

/// numpy's default (linear) quantile of unsorted values.
fn quantile(values: &[f64], q: f64) -> f64 {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let h = (v.len() - 1) as f64 * q;
    let lo = h.floor() as usize;
    let hi = (lo + 1).min(v.len() - 1);
    v[lo] + (h - lo as f64) * (v[hi] - v[lo])
}

/// The pixels whose first-fit residual is within the [`TRIM_Q`] quantile (all of them
/// when that leaves fewer than [`MIN_PX`]).
fn trim(src: &[[f64; 3]], tgt: &[[f64; 3]], pred: &[[f64; 3]]) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    let resid: Vec<f64> = pred.iter().zip(tgt).map(|(p, t)| (0..3).map(|k| (p[k] - t[k]).abs()).sum::<f64>() / 3.0).collect();
    let q = quantile(&resid, TRIM_Q);
    let keep: Vec<usize> = (0..resid.len()).filter(|&i| resid[i] <= q).collect();
    if keep.len() >= MIN_PX {
        (keep.iter().map(|&i| src[i]).collect(), keep.iter().map(|&i| tgt[i]).collect())
    } else {
        (src.to_vec(), tgt.to_vec())
    }
}

fn mean_abs(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (0..3).map(|k| (x[k] - y[k]).abs()).sum::<f64>()).sum::<f64>() / (3 * a.len()) as f64
}

/// Whether `tr` lowers the L1 error on the fit pixels by at least [`MIN_REL_GAIN`].
fn gate(src: &[[f64; 3]], tgt: &[[f64; 3]], tr: &ColorTransform) -> bool {
    mean_abs(&tr.apply_all(src), tgt) <= mean_abs(src, tgt) * (1.0 - MIN_REL_GAIN)
}

/// Minimum of `f` on `[a, b]` by Brent's method (golden section with parabolic steps),
/// to an absolute tolerance `xatol` (scipy's `fminbound`, which `minimize_scalar`'s
/// bounded method runs; its defaults 1e-5 and 500 evaluations).
fn fminbound(f: impl Fn(f64) -> f64, mut a: f64, mut b: f64, xatol: f64, maxfun: usize) -> f64 {
    let golden = 0.5 * (3.0 - 5f64.sqrt());
    let sqrt_eps = 2.2e-16f64.sqrt();
    let mut fulc = a + golden * (b - a);
    let (mut nfc, mut xf) = (fulc, fulc);
    let (mut rat, mut e) = (0.0f64, 0.0f64);
    let mut fx = f(xf);
    let mut num = 1;
    let (mut ffulc, mut fnfc) = (fx, fx);
    let mut xm = 0.5 * (a + b);
    let mut tol1 = sqrt_eps * xf.abs() + xatol / 3.0;
    let mut tol2 = 2.0 * tol1;
    let sign = |x: f64| {
        if x > 0.0 {
            1.0
        } else if x < 0.0 {
            -1.0
        } else {
            0.0
        }
    };
    while (xf - xm).abs() > tol2 - 0.5 * (b - a) {
        let mut golden_step = true;
        if e.abs() > tol1 {
            golden_step = false;
            let mut r = (xf - nfc) * (fx - ffulc);
            let mut q = (xf - fulc) * (fx - fnfc);
            let mut p = (xf - fulc) * q - (xf - nfc) * r;
            q = 2.0 * (q - r);
            if q > 0.0 {
                p = -p;
            }
            q = q.abs();
            r = e;
            e = rat;
            if p.abs() < (0.5 * q * r).abs() && p > q * (a - xf) && p < q * (b - xf) {
                rat = p / q;
                let x = xf + rat;
                if (x - a) < tol2 || (b - x) < tol2 {
                    let si = sign(xm - xf) + if xm == xf { 1.0 } else { 0.0 };
                    rat = tol1 * si;
                }
            } else {
                golden_step = true;
            }
        }
        if golden_step {
            e = if xf >= xm { a - xf } else { b - xf };
            rat = golden * e;
        }
        let si = sign(rat) + if rat == 0.0 { 1.0 } else { 0.0 };
        let x = xf + si * rat.abs().max(tol1);
        let fu = f(x);
        num += 1;
        if fu <= fx {
            if x >= xf {
                a = xf;
            } else {
                b = xf;
            }
            (fulc, ffulc) = (nfc, fnfc);
            (nfc, fnfc) = (xf, fx);
            (xf, fx) = (x, fu);
        } else {
            if x < xf {
                a = x;
            } else {
                b = x;
            }
            if fu <= fnfc || nfc == xf {
                (fulc, ffulc) = (nfc, fnfc);
                (nfc, fnfc) = (x, fu);
            } else if fu <= ffulc || fulc == xf || fulc == nfc {
                (fulc, ffulc) = (x, fu);
            }
        }
        xm = 0.5 * (a + b);
        tol1 = sqrt_eps * xf.abs() + xatol / 3.0;
        tol2 = 2.0 * tol1;
        if num >= maxfun {
            break;
        }
    }
    xf
}

/// The exponent `g` in [0.2, 4] minimising `mean((a^g − b)²)`.
fn fit_exponent(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    fminbound(|g| a.iter().zip(b).map(|(x, y)| (x.powf(g) - y).powi(2)).sum::<f64>() / n, 0.2, 4.0, 1e-5, 500)
}

/// One luminance gamma for all channels (hue preserving); `None` when there are too few
/// pixels, the gamma leaves [0.5, 2], or it does not pass the gain gate.
/// `src`: the render's colours; `tgt`: the photo's, at the same pixels, in [0, 1].
pub fn fit_gamma(src: &[[f64; 3]], tgt: &[[f64; 3]]) -> Option<ColorTransform> {
    let (s, t) = prep(src, tgt)?;
    let ls: Vec<f64> = s.iter().map(|c| lum(c).clamp(1e-6, 1.0)).collect();
    let lt: Vec<f64> = t.iter().map(lum).collect();
    let g0 = fit_exponent(&ls, &lt);
    let pred: Vec<[f64; 3]> = s.iter().map(|c| c.map(|x| x.clamp(1e-6, 1.0).powf(g0))).collect();
    let (s2, t2) = trim(&s, &t, &pred);
    let ls2: Vec<f64> = s2.iter().map(|c| lum(c).clamp(1e-6, 1.0)).collect();
    let lt2: Vec<f64> = t2.iter().map(lum).collect();
    let g = fit_exponent(&ls2, &lt2);
    if !(GAMMA_LO..=GAMMA_HI).contains(&g) {
        return None;
    }
    let tr = ColorTransform::Gamma { gamma: g };
    gate(&s, &t, &tr).then_some(tr)
}

/// Least squares `b ≈ scale·a + off` for each channel, clamped to the allowed ranges.
fn solve_affine(a: &[[f64; 3]], b: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let n = a.len() as f64;
    let mut scale = [1.0; 3];
    let mut off = [0.0; 3];
    for k in 0..3 {
        let (sx, sy) = (a.iter().map(|c| c[k]).sum::<f64>(), b.iter().map(|c| c[k]).sum::<f64>());
        let sxx: f64 = a.iter().map(|c| c[k] * c[k]).sum();
        let sxy: f64 = a.iter().zip(b).map(|(x, y)| x[k] * y[k]).sum();
        let det = n * sxx - sx * sx;
        // A constant channel: lstsq's minimum-norm solution along (x, 1).
        (scale[k], off[k]) = if det.abs() > 1e-12 * n * sxx.max(1e-300) {
            ((n * sxy - sx * sy) / det, (sxx * sy - sx * sxy) / det)
        } else {
            let x = sx / n;
            let m = sy / n / (x * x + 1.0);
            (m * x, m)
        };
    }
    (scale.map(|s| s.clamp(SCALE_LO, SCALE_HI)), off.map(|o| o.clamp(-OFF_LIM, OFF_LIM)))
}

/// A per-channel affine map `c' = scale·c + off`; `None` when there are too few pixels
/// or it does not pass the gain gate.
pub fn fit_affine(src: &[[f64; 3]], tgt: &[[f64; 3]]) -> Option<ColorTransform> {
    let (s, t) = prep(src, tgt)?;
    let (scale, off) = solve_affine(&s, &t);
    let pred: Vec<[f64; 3]> = s.iter().map(|c| std::array::from_fn(|k| (c[k] * scale[k] + off[k]).clamp(0.0, 1.0))).collect();
    let (s2, t2) = trim(&s, &t, &pred);
    let (scale, off) = solve_affine(&s2, &t2);
    let tr = ColorTransform::Affine { scale, off };
    gate(&s, &t, &tr).then_some(tr)
}

/// The luminance gamma, then a per-channel affine map fitted on top of it; either part
/// may be identity, `None` when both are gated out.
pub fn fit_gamma_affine(src: &[[f64; 3]], tgt: &[[f64; 3]]) -> Option<ColorTransform> {
    let g = fit_gamma(src, tgt);
    let base: Vec<[f64; 3]> = match &g {
        Some(tr) => tr.apply_all(src),
        None => src.iter().map(clip01).collect(),
    };
    let a = fit_affine(&base, tgt);
    if g.is_none() && a.is_none() {
        return None;
    }
    let gamma = match g {
        Some(ColorTransform::Gamma { gamma }) => gamma,
        _ => 1.0,
    };
    let (scale, off) = match a {
        Some(ColorTransform::Affine { scale, off }) => (scale, off),
        _ => ([1.0; 3], [0.0; 3]),
    };
    Some(ColorTransform::GammaAffine { gamma, scale, off })
}

/// The fitter of `variant` (`None` for [`PosthocColor::None`]).
pub fn fit(variant: PosthocColor, src: &[[f64; 3]], tgt: &[[f64; 3]]) -> Option<ColorTransform> {
    match variant {
        PosthocColor::None => None,
        PosthocColor::Gamma => fit_gamma(src, tgt),
        PosthocColor::Affine => fit_affine(src, tgt),
        PosthocColor::GammaAffine => fit_gamma_affine(src, tgt),
    }
}

/// The photo, its mask and the render in the virtual view, and the pixels they share.
pub struct CalibrationView {
    /// Side of the square view, pixels.
    pub side: usize,
    /// The photo warped into the view, RGB in [0, 1] (0 outside the photo).
    pub photo: Vec<[f64; 3]>,
    /// The mask warped into the view.
    pub mask: Vec<bool>,
    /// The Gaussians' render (black background).
    pub render: Vec<[f64; 3]>,
    /// The render's accumulated opacity.
    pub alpha: Vec<f32>,
}

impl CalibrationView {
    /// Pixels covered by the render (alpha > 0.5) and in the mask.
    pub fn overlap(&self) -> Vec<usize> {
        (0..self.mask.len()).filter(|&i| self.mask[i] && self.alpha[i] > 0.5).collect()
    }
}

/// The anchor photo, an object's eroded mask (frame resolution, row-major) and its
/// camera.
pub struct PhotoView<'a> {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Interleaved RGB bytes.
    pub rgb: &'a [u8],
    /// The object's mask.
    pub mask: &'a [bool],
    /// The camera.
    pub intrinsics: Intrinsics,
}

/// Renders `gaussians_camera` (camera frame, metres) and warps the photo and mask into
/// the virtual view that frames the object placed by `object_to_camera` (its canonical
/// cube → camera). `None` when the object's centre is not in front of the camera.
pub fn calibration_view(gaussians_camera: &Gaussians, object_to_camera: &Similarity, photo: &PhotoView) -> Result<Option<CalibrationView>> {
    let t = object_to_camera.translation;
    let dist = (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt();
    if !(dist > 0.0 && t[2] > 0.0) {
        return Ok(None);
    }
    let z = t.map(|x| x / dist);
    // Rotation taking the direction to the object onto the optical axis (Rodrigues
    // form of upstream's `_lookat_camera`).
    let v = [z[1], -z[0], 0.0];
    let w = z[2];
    let vx = [[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]];
    let vx2 = crate::math::matmul(&vx, &vx);
    let rl: [[f64; 3]; 3] =
        std::array::from_fn(|i| std::array::from_fn(|j| if i == j { 1.0 } else { 0.0 } + vx[i][j] + vx2[i][j] / (1.0 + w)));
    // Distance in canonical units over the framed half-extent.
    let zc = dist / object_to_camera.scale;
    let s = VIEW_SIDE as f64;
    let f = (VIEW_FILL / 2.0) / (CANONICAL_HALF_EXTENT / zc) * s;
    let kv = Intrinsics { fx: f, fy: f, cx: s / 2.0, cy: s / 2.0 };
    let cam = Camera { width: VIEW_SIDE, height: VIEW_SIDE, k: kv, world_to_cam: Similarity::rigid(rl, [0.0; 3]) };
    let img = render_gaussians(gaussians_camera, &cam, &SplatOptions::default())?;
    // Virtual pixel → photo pixel: K·Rlᵀ·Kv⁻¹.
    let k = photo.intrinsics;
    let (pw, ph) = (photo.width, photo.height);
    let mut photo_v = vec![[0.0; 3]; VIEW_SIDE * VIEW_SIDE];
    let mut mask_v = vec![false; VIEW_SIDE * VIEW_SIDE];
    for y in 0..VIEW_SIDE {
        for x in 0..VIEW_SIDE {
            let ray = [(x as f64 - kv.cx) / kv.fx, (y as f64 - kv.cy) / kv.fy, 1.0];
            let d: [f64; 3] = std::array::from_fn(|i| (0..3).map(|j| rl[j][i] * ray[j]).sum());
            if !(d[2] > 0.0) {
                continue;
            }
            let (sx, sy) = (k.fx * d[0] / d[2] + k.cx, k.fy * d[1] / d[2] + k.cy);
            let i = y * VIEW_SIDE + x;
            let (nx, ny) = (sx.round(), sy.round());
            if nx >= 0.0 && ny >= 0.0 && (nx as usize) < pw && (ny as usize) < ph {
                mask_v[i] = photo.mask[ny as usize * pw + nx as usize];
            }
            // Bilinear, pixels outside the photo black (cv2's constant border), rounded
            // to bytes as the warped uint8 photo is.
            let (x0, y0) = (sx.floor(), sy.floor());
            let (fx, fy) = (sx - x0, sy - y0);
            let mut acc = [0.0; 3];
            for (dy, wy) in [(0.0, 1.0 - fy), (1.0, fy)] {
                for (dx, wx) in [(0.0, 1.0 - fx), (1.0, fx)] {
                    let (px, py) = (x0 + dx, y0 + dy);
                    if px >= 0.0 && py >= 0.0 && (px as usize) < pw && (py as usize) < ph && wx * wy > 0.0 {
                        let o = 3 * (py as usize * pw + px as usize);
                        for c in 0..3 {
                            acc[c] += wx * wy * photo.rgb[o + c] as f64;
                        }
                    }
                }
            }
            photo_v[i] = acc.map(|a| a.round().clamp(0.0, 255.0) / 255.0);
        }
    }
    let render = img.color.iter().map(|c| c.map(f64::from)).collect();
    Ok(Some(CalibrationView { side: VIEW_SIDE, photo: photo_v, mask: mask_v, render, alpha: img.alpha }))
}

/// Fits `variant` for one object: the transform (`None` = identity) and the statistics
/// upstream records. Does not change the object.
pub fn calibrate(
    gaussians_camera: Option<&Gaussians>,
    object_to_camera: &Similarity,
    photo: &PhotoView,
    variant: PosthocColor,
) -> Result<(Option<ColorTransform>, CalibrationStats)> {
    let identity = |stats: CalibrationStats, reason: &str| Ok((None, CalibrationStats { reason: Some(reason.to_string()), ..stats }));
    let Some(g) = gaussians_camera.filter(|g| !g.is_empty()) else {
        return identity(CalibrationStats::default(), "no gaussian output");
    };
    let Some(view) = calibration_view(g, object_to_camera, photo)? else {
        return identity(CalibrationStats::default(), "object not in front of the camera");
    };
    let ov = view.overlap();
    let union = (0..view.mask.len()).filter(|&i| view.mask[i] || view.alpha[i] > 0.5).count();
    let stats = CalibrationStats {
        overlap_px: Some(ov.len()),
        iou: Some(if union > 0 { ov.len() as f64 / union as f64 } else { 0.0 }),
        ..Default::default()
    };
    if ov.len() < MIN_PX {
        return identity(stats, "insufficient overlap");
    }
    if stats.iou.unwrap_or(0.0) < MIN_IOU {
        return identity(stats, "poor render/mask alignment");
    }
    let src: Vec<[f64; 3]> = ov.iter().map(|&i| view.render[i]).collect();
    let tgt: Vec<[f64; 3]> = ov.iter().map(|&i| view.photo[i]).collect();
    let Some(tr) = fit(variant, &src, &tgt) else {
        return identity(stats, "fit gated (no reliable improvement)");
    };
    let before: Vec<[f64; 3]> = src.iter().map(clip01).collect();
    let stats = CalibrationStats { l1_before: Some(mean_abs(&before, &tgt)), l1_after: Some(mean_abs(&tr.apply_all(&src), &tgt)), ..stats };
    Ok((Some(tr), stats))
}

/// Writes `posthoc_color.json` (compact, as upstream's `json.dump`) into `dir`.
pub fn write_posthoc_color(record: &PosthocColorRecord, dir: &std::path::Path) -> Result<std::path::PathBuf> {
    let path = dir.join("posthoc_color.json");
    let text = serde_json::to_string(record).map_err(|e| crate::Error::msg(e.to_string()))?;
    std::fs::write(&path, text).map_err(|e| crate::Error::io(&path, e))?;
    Ok(path)
}

/// Applies `tr` to the Gaussians' DC colours (through their clamped RGB, as upstream's
/// `apply_to_gaussian`).
pub fn apply_to_gaussians(g: &mut Gaussians, tr: &ColorTransform) {
    for dc in g.dc.iter_mut() {
        let rgb = dc.map(|d| f64::from(SH_C0 * d + 0.5).clamp(0.0, 1.0));
        let new = tr.apply(rgb);
        *dc = new.map(|c| ((c - 0.5) / f64::from(SH_C0)) as f32);
    }
}

/// Applies `tr` to the mesh's vertex colours (the first three attribute channels).
pub fn apply_to_mesh(m: &mut Mesh, tr: &ColorTransform) {
    if let Some(attrs) = m.vertex_attrs.as_mut() {
        for a in attrs.iter_mut() {
            let new = tr.apply([a[0], a[1], a[2]].map(f64::from));
            (a[0], a[1], a[2]) = (new[0] as f32, new[1] as f32, new[2] as f32);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pixels(n: usize, seed: u64) -> Vec<[f64; 3]> {
        let mut rng = crate::rng::SeededRng::new(seed);
        (0..n).map(|_| [0.1 + 0.8 * rng.uniform(), 0.1 + 0.8 * rng.uniform(), 0.1 + 0.8 * rng.uniform()]).collect()
    }

    #[test]
    fn brent_finds_a_bounded_minimum() {
        let x = fminbound(|x| (x - 1.37).powi(2) + 0.1, 0.2, 4.0, 1e-5, 500);
        assert!((x - 1.37).abs() < 1e-4, "{x}");
        // At a bound.
        let x = fminbound(|x| x, 0.2, 4.0, 1e-5, 500);
        assert!((x - 0.2).abs() < 1e-4, "{x}");
    }

    #[test]
    fn a_known_gamma_and_affine_map_are_recovered() {
        let src = pixels(2000, 1);
        // The gamma is fitted on luminance: exact for grey pixels.
        let grey: Vec<[f64; 3]> = src.iter().map(|c| [c[0]; 3]).collect();
        let tgt: Vec<[f64; 3]> = grey.iter().map(|c| c.map(|x| x.powf(1.6))).collect();
        match fit_gamma(&grey, &tgt) {
            Some(ColorTransform::Gamma { gamma }) => assert!((gamma - 1.6).abs() < 1e-3, "{gamma}"),
            other => panic!("{other:?}"),
        }
        let (scale, off) = ([0.8, 1.1, 0.6], [0.05, -0.02, 0.1]);
        let tgt: Vec<[f64; 3]> = src.iter().map(|c| std::array::from_fn(|k| c[k] * scale[k] + off[k])).collect();
        match fit_affine(&src, &tgt) {
            Some(ColorTransform::Affine { scale: s, off: o }) => {
                for k in 0..3 {
                    assert!((s[k] - scale[k]).abs() < 1e-9 && (o[k] - off[k]).abs() < 1e-9, "{s:?} {o:?}");
                }
            }
            other => panic!("{other:?}"),
        }
        // The photo is the render plus zero-mean noise: no transform lowers the error by
        // 3 %, so every fitter gates out.
        let mut rng = crate::rng::SeededRng::new(9);
        let noisy: Vec<[f64; 3]> = src.iter().map(|c| c.map(|x| x + 0.05 * rng.normal())).collect();
        assert_eq!(fit_gamma(&src, &noisy), None);
        assert_eq!(fit_affine(&src, &noisy), None);
        assert_eq!(fit_gamma_affine(&src, &noisy), None);
        // Too few pixels.
        assert_eq!(fit_gamma(&src[..150], &tgt[..150]), None);
    }

    #[test]
    fn the_record_serialises_as_upstream_writes_it() {
        let r = PosthocColorRecord {
            variant: PosthocColor::GammaAffine,
            transform: Some(ColorTransform::GammaAffine { gamma: 1.2, scale: [1.0; 3], off: [0.0; 3] }),
            stats: CalibrationStats { overlap_px: Some(900), iou: Some(0.8), reason: None, l1_before: Some(0.2), l1_after: Some(0.1) },
            applied_to: vec!["gaussians".into()],
        };
        let v = serde_json::to_value(&r).unwrap();
        assert_eq!(v["variant"], "gamma_affine");
        assert_eq!(v["transform"]["type"], "gamma_affine");
        assert_eq!(v["transform"]["gamma"], 1.2);
        assert_eq!(v["stats"]["overlap_px"], 900);
        assert!(v["stats"].get("reason").is_none());
        let back: PosthocColorRecord = serde_json::from_value(v).unwrap();
        assert_eq!(back, r);
    }
}
