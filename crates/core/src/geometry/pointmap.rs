//! From an RGB-D frame and an object mask to the three per-view tensors the
//! pipeline takes (DINO pixel values, normalised point map, mask), following
//! RecGen's `recgen_inference/preprocessing.py` (`preprocess_view`,
//! `crop_to_bounding_box`, `fit_unit_cube_median_quantile`) as called by
//! `inference.generate` (quantile drop 0.05, clamp `[-2, 3]`, erosion on).
//!
//! What RecGen does, step by step (our implementation follows each):
//! 1. **Erode** the mask (5×5 square, 1 iteration; see
//!    [`crate::dataset::masks::erode`]). Depth outside the eroded mask is
//!    zeroed; a pixel is *valid* when its depth is > 0 (NaN fails that test,
//!    so NaN is invalid too).
//! 2. **Back-project** every pixel with the OpenCV pinhole model: integer
//!    pixel indices are pixel centres, `x = (u − cx)·z/fx`,
//!    `y = (v − cy)·z/fy`, `z` = depth in metres (camera frame: x right,
//!    y down, z forward).
//! 3. **Normalise** using only the points under the eroded mask with valid
//!    depth: centre = per-axis median (`nanmedian`; mean of the two middle
//!    values for an even count), norms of the centred points, and
//!    diameter `d = 2·(q(1−p) − q(p))` of those norms with `p = 0.05`
//!    (NumPy's default linear-interpolation quantiles, i.e. the 5–95 %
//!    spread). The map is `x_n = (x − centre)/d + 0.5`: the object's median
//!    lands on `(0.5, 0.5, 0.5)`, so the normalised frame is RecGen's
//!    "unit cube" `[0, 1]³` (not centred at 0). A zero diameter falls back
//!    to `d = 1`. Points that are not valid-and-masked become `(0, 0, 0)`.
//! 4. **Crop** a square around the eroded mask's bounding box
//!    (`[xmin, xmax] × [ymin, ymax]`, inclusive pixel indices): centre
//!    `((xmin+xmax)/2, (ymin+ymax)/2)`, half side
//!    `max(1.2 · max(xmax−xmin, ymax−ymin)/2, 518/3/2)` — the context
//!    factor is 1.2 and the lower bound limits the zoom to 3× at 518 px —
//!    box corners truncated toward zero (Python `int`), pixels outside the
//!    image are zeros.
//! 5. **Resize** to `S×S`: the RGB crop with Lanczos (PIL `LANCZOS`), the
//!    0/255 mask crop with PIL `NEAREST` (then /255), the point-map crop with
//!    `torch.nn.functional.interpolate(mode="nearest")`, whose source index
//!    is `floor(dst·in/out)` (not PIL's pixel-centre rule). The resized point
//!    map is clamped to `[-2, 3]`.
//!
//! Differences we chose: RecGen multiplies the point map by the mask, which
//! would keep NaN for NaN depth (NaN·0 = NaN); we write zeros, which is what
//! that step intends. Statistics are computed in f64 from f64 points (RecGen
//! uses f32), a difference of order 1e-7 relative.

use candle_core::{Device, Tensor};

use crate::dataset::frame::{depth_valid, Intrinsics, RgbdFrame};
use crate::dataset::image::{crop, dino_pixel_values, mask_to_tensor, CropBox};
use crate::dataset::masks::{erode, Erosion};
use crate::{Error, Result};

/// Back-project a metric depth image (row-major `h·w`) into camera-frame
/// points; invalid depth (0, negative or NaN) gives `(0, 0, 0)`.
pub fn backproject(depth_m: &[f32], w: usize, h: usize, k: &Intrinsics) -> Result<Vec<[f64; 3]>> {
    if depth_m.len() != w * h {
        return Err(Error::input("depth", format!("expected {w}×{h} = {} values, got {}", w * h, depth_m.len())));
    }
    let mut out = Vec::with_capacity(w * h);
    for v in 0..h {
        for u in 0..w {
            let z = depth_m[v * w + u];
            if depth_valid(z) {
                let z = z as f64;
                out.push([(u as f64 - k.cx) * z / k.fx, (v as f64 - k.cy) * z / k.fy, z]);
            } else {
                out.push([0.0; 3]);
            }
        }
    }
    Ok(out)
}

/// Project a camera-frame point to pixel coordinates (inverse of
/// `backproject` for `z > 0`).
pub fn project(p: [f64; 3], k: &Intrinsics) -> [f64; 2] {
    [k.fx * p[0] / p[2] + k.cx, k.fy * p[1] / p[2] + k.cy]
}

/// NumPy `quantile(..., method="linear")` of sorted values.
fn quantile_sorted(v: &[f64], q: f64) -> f64 {
    let pos = q * (v.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = (lo + 1).min(v.len() - 1);
    let t = pos - lo as f64;
    v[lo] + (v[hi] - v[lo]) * t
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// RecGen's camera → normalised map `x_n = (x − centre)/diameter + 0.5`
/// (module docs, step 3). `cam2ncam` in RecGen is this map as a 4×4 matrix
/// with `s = 1/diameter`, `t = 0.5 − centre·s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Normaliser {
    /// Per-axis median of the object's points, metres.
    pub centre: [f64; 3],
    /// `2·(q95 − q5)` of the centred point norms, metres.
    pub diameter: f64,
}

/// The normalised frame's origin offset: the centre maps to `(0.5, 0.5, 0.5)`.
pub const NORMALISED_CENTRE: f64 = 0.5;

impl Normaliser {
    /// Fit on the object's points (already restricted to masked, valid ones).
    /// `quantile_drop` is the fraction cut at each end (RecGen inference: 0.05).
    pub fn fit(points: &[[f64; 3]], quantile_drop: f64) -> Result<Self> {
        if points.is_empty() {
            return Err(Error::msg("point normalisation: no valid object points"));
        }
        if !(0.0..0.5).contains(&quantile_drop) {
            return Err(Error::msg(format!("point normalisation: quantile drop {quantile_drop} must be in [0, 0.5)")));
        }
        let centre: [f64; 3] = std::array::from_fn(|a| median(points.iter().map(|p| p[a]).collect()));
        let mut norms: Vec<f64> =
            points.iter().map(|p| ((p[0] - centre[0]).powi(2) + (p[1] - centre[1]).powi(2) + (p[2] - centre[2]).powi(2)).sqrt()).collect();
        norms.sort_by(|a, b| a.total_cmp(b));
        let diameter = 2.0 * (quantile_sorted(&norms, 1.0 - quantile_drop) - quantile_sorted(&norms, quantile_drop));
        let diameter = if diameter == 0.0 { 1.0 } else { diameter };
        Ok(Normaliser { centre, diameter })
    }

    /// RecGen's `s` (normalised units per metre).
    pub fn scale(&self) -> f64 {
        1.0 / self.diameter
    }

    /// Camera-frame point → normalised frame.
    pub fn to_normalised(&self, p: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|a| (p[a] - self.centre[a]) / self.diameter + NORMALISED_CENTRE)
    }

    /// Normalised-frame point → camera frame.
    pub fn to_camera(&self, q: [f64; 3]) -> [f64; 3] {
        std::array::from_fn(|a| (q[a] - NORMALISED_CENTRE) * self.diameter + self.centre[a])
    }

    /// RecGen `cam2ncam` (row-major 4×4).
    pub fn cam2ncam(&self) -> [[f64; 4]; 4] {
        let s = self.scale();
        let mut m = [[0.0; 4]; 4];
        for a in 0..3 {
            m[a][a] = s;
            m[a][3] = NORMALISED_CENTRE - self.centre[a] * s;
        }
        m[3][3] = 1.0;
        m
    }
}

/// Preprocessing settings; defaults are RecGen's `generate` defaults.
#[derive(Debug, Clone, Copy)]
pub struct PrepareOptions {
    /// Mask erosion before everything (`None` = off).
    pub erosion: Option<Erosion>,
    /// Fraction dropped at each end of the norm distribution (0.05).
    pub quantile_drop: f64,
    /// Clamp of the resized normalised point map (`(-2, 3)`).
    pub clamp: Option<(f32, f32)>,
    /// Crop side = `context ×` the bbox's longer side (1.2).
    pub context: f64,
    /// Lower bound of the crop's half side in source pixels (518/3/2).
    pub min_half_side: f64,
    /// Fewest valid object points accepted.
    pub min_points: usize,
}

impl Default for PrepareOptions {
    fn default() -> Self {
        PrepareOptions {
            erosion: Some(Erosion::default()),
            quantile_drop: 0.05,
            clamp: Some((-2.0, 3.0)),
            context: 1.2,
            min_half_side: 518.0 / 3.0 / 2.0,
            min_points: 1,
        }
    }
}

/// RecGen's square crop box around a mask (module docs, step 4); the whole
/// image when the mask is empty.
pub fn object_crop_box(mask: &[bool], w: usize, h: usize, context: f64, min_half_side: f64) -> CropBox {
    let (mut x0, mut y0, mut x1, mut y1) = (usize::MAX, usize::MAX, 0, 0);
    for y in 0..h {
        for x in 0..w {
            if mask[y * w + x] {
                x0 = x0.min(x);
                x1 = x1.max(x);
                y0 = y0.min(y);
                y1 = y1.max(y);
            }
        }
    }
    if x0 == usize::MAX {
        return CropBox { x0: 0, y0: 0, x1: w as i64, y1: h as i64 };
    }
    let (cx, cy) = ((x0 + x1) as f64 / 2.0, (y0 + y1) as f64 / 2.0);
    let half = ((x1 - x0).max(y1 - y0) as f64 / 2.0 * context).max(min_half_side);
    CropBox {
        x0: (cx - half).trunc() as i64,
        y0: (cy - half).trunc() as i64,
        x1: (cx + half).trunc() as i64,
        y1: (cy + half).trunc() as i64,
    }
}

/// `torch.nn.functional.interpolate(mode="nearest")` of an interleaved
/// `h×w×c` array: source index `min(floor(dst · (in/out)), in − 1)` with the
/// ratio in f32, as PyTorch's CPU kernel computes it.
pub fn resize_nearest_torch<T: Copy>(src: &[T], w: usize, h: usize, c: usize, out_w: usize, out_h: usize) -> Result<Vec<T>> {
    if src.len() != w * h * c || w == 0 || h == 0 || out_w == 0 || out_h == 0 {
        return Err(Error::input("array", format!("bad resize {w}×{h}×{c} ({} values) → {out_w}×{out_h}", src.len())));
    }
    let idx = |o: usize, n_in: usize, n_out: usize| -> usize {
        if n_in == n_out {
            o
        } else {
            let s = n_in as f32 / n_out as f32;
            ((o as f32 * s).floor() as usize).min(n_in - 1)
        }
    };
    let cols: Vec<usize> = (0..out_w).map(|x| idx(x, w, out_w)).collect();
    let mut out = Vec::with_capacity(out_w * out_h * c);
    for y in 0..out_h {
        let sy = idx(y, h, out_h);
        for &sx in &cols {
            let b = (sy * w + sx) * c;
            out.extend_from_slice(&src[b..b + c]);
        }
    }
    Ok(out)
}

/// Everything the pipeline needs for one view, plus what maps its
/// predictions back (`normaliser`) and what it was cut from (`crop`).
#[derive(Debug, Clone)]
pub struct PreparedView {
    /// `[1, 3, S, S]` ImageNet-normalised colour of the crop.
    pub pixel_values: Tensor,
    /// `[1, 3, S, S]` normalised XYZ (zeros off the object), clamped.
    pub pointmap: Tensor,
    /// `[1, 1, S, S]` eroded mask of the crop in {0, 1}.
    pub mask: Tensor,
    /// Maps the crop's normalised frame back to the camera frame.
    pub normaliser: Normaliser,
    /// Crop box in frame pixels (may extend past the image).
    pub crop: CropBox,
    /// Eroded mask at frame resolution (row-major).
    pub mask_full: Vec<bool>,
    /// Object points that entered the statistics.
    pub num_points: usize,
    /// The resized colour crop, interleaved RGB `S·S·3` (for previews).
    pub rgb_crop: Vec<u8>,
    /// Side `S` of the square crop, pixels.
    pub size: usize,
}

/// Prepare one object of a frame with RecGen's default settings on the CPU.
/// `mask` is the object's full-resolution mask (row-major, `true` = object).
///
/// This is the single entry point between inputs and the pipeline: its
/// `pixel_values`, `pointmap` and `mask` are the pipeline's per-view
/// tensors, and its `normaliser` maps the predicted pose back to metres
/// ([`crate::geometry::camera_pose::canonical_to_camera`]). With several views, each
/// view is prepared on its own (its own normaliser), exactly as RecGen's
/// `generate_multiview` does, and results are expressed in the **anchor**
/// (first) view's camera frame through the anchor's normaliser.
pub fn prepare_object(frame: &RgbdFrame, mask: &[bool], size: usize) -> Result<PreparedView> {
    prepare_object_with(frame, mask, size, &PrepareOptions::default(), &Device::Cpu)
}

/// The object's masked, valid camera-frame points after erosion (the points
/// that enter the normalisation statistics), with the eroded mask.
pub fn object_points(frame: &RgbdFrame, mask: &[bool], erosion: Option<Erosion>) -> Result<(Vec<[f64; 3]>, Vec<bool>)> {
    let (w, h) = (frame.width, frame.height);
    if mask.len() != w * h {
        return Err(Error::input("mask", format!("mask has {} pixels, the frame {w}×{h}", mask.len())));
    }
    let eroded = match erosion {
        Some(e) => erode(mask, w, h, e),
        None => mask.to_vec(),
    };
    let pts = masked_points(&frame.depth_m, w, h, &frame.intrinsics, &eroded)?;
    Ok((pts, eroded))
}

/// Camera-frame points of the pixels under `mask` that have a valid depth
/// (the back-projection of [`backproject`], restricted to the mask), in
/// row-major pixel order. For callers that hold a depth image but no colour.
pub fn masked_points(depth_m: &[f32], w: usize, h: usize, k: &Intrinsics, mask: &[bool]) -> Result<Vec<[f64; 3]>> {
    if depth_m.len() != w * h || mask.len() != w * h {
        return Err(Error::input(
            "depth/mask",
            format!("expected {w}×{h} = {} values, got depth {} and mask {}", w * h, depth_m.len(), mask.len()),
        ));
    }
    let mut pts = Vec::new();
    for v in 0..h {
        for u in 0..w {
            let i = v * w + u;
            let z = depth_m[i];
            if mask[i] && depth_valid(z) {
                let z = z as f64;
                pts.push([(u as f64 - k.cx) * z / k.fx, (v as f64 - k.cy) * z / k.fy, z]);
            }
        }
    }
    Ok(pts)
}

/// [`prepare_object`] with explicit options and device.
pub fn prepare_object_with(frame: &RgbdFrame, mask: &[bool], size: usize, opts: &PrepareOptions, dev: &Device) -> Result<PreparedView> {
    let (w, h) = (frame.width, frame.height);
    if size == 0 {
        return Err(Error::msg("prepare_object: size must be positive"));
    }
    let (pts, eroded) = object_points(frame, mask, opts.erosion)?;
    if pts.len() < opts.min_points.max(1) {
        return Err(Error::input(
            frame.rgb_path.display().to_string(),
            format!("object has {} valid depth points under its eroded mask (need {})", pts.len(), opts.min_points.max(1)),
        ));
    }
    let normaliser = Normaliser::fit(&pts, opts.quantile_drop)?;

    // Full-resolution normalised point map, zeros off the object.
    let pm_cam = backproject(&frame.depth_m, w, h, &frame.intrinsics)?;
    let mut pm = vec![0f32; w * h * 3];
    for i in 0..w * h {
        if eroded[i] && depth_valid(frame.depth_m[i]) {
            let q = normaliser.to_normalised(pm_cam[i]);
            pm[3 * i..3 * i + 3].copy_from_slice(&[q[0] as f32, q[1] as f32, q[2] as f32]);
        }
    }

    let cbox = object_crop_box(&eroded, w, h, opts.context, opts.min_half_side);
    let (rgb_c, cw, ch) = crop(&frame.rgb, w, h, 3, cbox)?;
    let mask_u8: Vec<u8> = eroded.iter().map(|&m| if m { 255 } else { 0 }).collect();
    let (mask_c, _, _) = crop(&mask_u8, w, h, 1, cbox)?;
    let (pm_c, _, _) = crop(&pm, w, h, 3, cbox)?;

    let rgb_crop = crate::dataset::image::resize_lanczos_u8(&rgb_c, cw, ch, 3, size, size)?;
    let pixel_values = dino_pixel_values(&rgb_crop, size, size, size, dev)?;
    let mask_t = mask_to_tensor(&mask_c, cw, ch, size, dev)?;
    let mut pm_r = resize_nearest_torch(&pm_c, cw, ch, 3, size, size)?;
    if let Some((lo, hi)) = opts.clamp {
        for v in pm_r.iter_mut() {
            *v = v.clamp(lo, hi);
        }
    }
    let n = size * size;
    let mut chw = vec![0f32; 3 * n];
    for (i, p) in pm_r.chunks_exact(3).enumerate() {
        for c in 0..3 {
            chw[c * n + i] = p[c];
        }
    }
    let pointmap = Tensor::from_vec(chw, (1, 3, size, size), dev)?;
    Ok(PreparedView {
        pixel_values,
        pointmap,
        mask: mask_t,
        normaliser,
        crop: cbox,
        mask_full: eroded,
        num_points: pts.len(),
        rgb_crop,
        size,
    })
}

/// One object ready for the pipeline.
#[derive(Debug, Clone)]
pub struct PreparedObject {
    /// The object's mask.
    pub object: crate::dataset::masks::ObjectMask,
    /// Its prepared view.
    pub view: PreparedView,
}

/// Validate every object of a frame ([`crate::dataset::masks::validate_objects`],
/// with the erosion of `opts`) and prepare the ones that pass. Objects that
/// fail either step are returned as skips; the others are unaffected.
pub fn prepare_frame_objects(
    frame: &RgbdFrame,
    objects: Vec<crate::dataset::masks::ObjectMask>,
    size: usize,
    min_valid_depth_pixels: usize,
    opts: &PrepareOptions,
    dev: &Device,
) -> (Vec<PreparedObject>, Vec<crate::dataset::masks::MaskSkip>) {
    use crate::dataset::masks::{validate_objects, MaskOptions, MaskSkip, SkipReason};
    let mopts = MaskOptions { erosion: opts.erosion, min_valid_depth_pixels };
    let (valid, mut skips) = validate_objects(frame, objects, &mopts);
    let mut out = Vec::new();
    for v in valid {
        match prepare_object_with(frame, &v.mask.to_bools(), size, opts, dev) {
            Ok(view) => out.push(PreparedObject { object: v.mask, view }),
            Err(e) => skips.push(MaskSkip { label: v.mask.label.clone(), reason: SkipReason::Preprocessing(e.to_string()) }),
        }
    }
    (out, skips)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn frame(w: usize, h: usize, k: Intrinsics, depth: impl Fn(usize, usize) -> f32) -> RgbdFrame {
        let mut d = vec![0f32; w * h];
        let mut rgb = vec![0u8; w * h * 3];
        for y in 0..h {
            for x in 0..w {
                d[y * w + x] = depth(x, y);
                rgb[(y * w + x) * 3] = (x * 4) as u8;
            }
        }
        RgbdFrame {
            width: w,
            height: h,
            rgb,
            depth_m: d,
            intrinsics: k,
            rgb_path: PathBuf::from("test.png"),
            depth_path: PathBuf::new(),
            intrinsics_source: "test".into(),
            depth_scale_m: 0.001,
        }
    }

    #[test]
    fn backprojection_uses_pixel_centres() {
        let k = Intrinsics { fx: 2.0, fy: 4.0, cx: 1.0, cy: 0.5 };
        let p = backproject(&[2.0, 0.0, f32::NAN, 4.0], 2, 2, &k).unwrap();
        // (u, v) = (0, 0), z = 2: x = (0 − 1)·2/2 = −1, y = (0 − 0.5)·2/4 = −0.25.
        assert_eq!(p[0], [-1.0, -0.25, 2.0]);
        assert_eq!(p[1], [0.0; 3]);
        assert_eq!(p[2], [0.0; 3]); // NaN depth is invalid
        assert_eq!(p[3], [0.0, 0.5, 4.0]);
        let uv = project(p[3], &k);
        assert_eq!(uv, [1.0, 1.0]);
    }

    #[test]
    fn quantiles_and_medians_like_numpy() {
        // np.quantile([1, 2, 3, 4], [0.05, 0.95]) = [1.15, 3.85]; np.median = 2.5.
        let v = [1.0, 2.0, 3.0, 4.0];
        assert!((quantile_sorted(&v, 0.05) - 1.15).abs() < 1e-12);
        assert!((quantile_sorted(&v, 0.95) - 3.85).abs() < 1e-12);
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), 2.5);
        assert_eq!(median(vec![5.0, 1.0, 3.0]), 3.0);
    }

    #[test]
    fn normaliser_statistics_and_inverse() {
        // Points on the x axis at 1..=5: median (3, 0, 0), norms 2,1,0,1,2 → sorted 0,1,1,2,2;
        // q05 = 0.2 (pos 0.2), q95 = 2 (pos 3.8 between 2 and 2) → d = 2·1.8 = 3.6.
        let pts: Vec<[f64; 3]> = (1..=5).map(|i| [i as f64, 0.0, 0.0]).collect();
        let n = Normaliser::fit(&pts, 0.05).unwrap();
        assert_eq!(n.centre, [3.0, 0.0, 0.0]);
        assert!((n.diameter - 3.6).abs() < 1e-12);
        assert_eq!(n.to_normalised([3.0, 0.0, 0.0]), [0.5, 0.5, 0.5]);
        let p = [1.25, -0.5, 2.0];
        let back = n.to_camera(n.to_normalised(p));
        for a in 0..3 {
            assert!((back[a] - p[a]).abs() < 1e-12);
        }
        // cam2ncam agrees with to_normalised.
        let m = n.cam2ncam();
        let q = n.to_normalised(p);
        for a in 0..3 {
            let v = m[a][0] * p[0] + m[a][1] * p[1] + m[a][2] * p[2] + m[a][3];
            assert!((v - q[a]).abs() < 1e-12);
        }
        // Degenerate cloud: d falls back to 1.
        assert_eq!(Normaliser::fit(&[[1.0, 2.0, 3.0]; 4], 0.05).unwrap().diameter, 1.0);
        assert!(Normaliser::fit(&[], 0.05).is_err());
    }

    #[test]
    fn crop_box_like_recgen() {
        // Mask x 100..=159, y 50..=89 in 640×480: centre (129.5, 69.5), half = max(60·0.6... )
        let (w, h) = (640, 480);
        let mut m = vec![false; w * h];
        for y in 50..90 {
            for x in 100..160 {
                m[y * w + x] = true;
            }
        }
        // Longer side 59 → half 29.5·1.2 = 35.4 < 86.33 → half = 86.33.
        let b = object_crop_box(&m, w, h, 1.2, 518.0 / 6.0);
        let half = 518.0 / 6.0;
        assert_eq!(
            b,
            CropBox {
                x0: (129.5f64 - half) as i64,
                y0: (69.5f64 - half).trunc() as i64,
                x1: (129.5f64 + half) as i64,
                y1: (69.5f64 + half) as i64
            }
        );
        assert_eq!((b.x0, b.y0, b.x1, b.y1), (43, -16, 215, 155)); // −16.83 truncates toward zero
                                                                   // A big object: the context factor rules.
        let mut m = vec![false; w * h];
        for y in 0..300 {
            for x in 200..401 {
                m[y * w + x] = true;
            }
        }
        let b = object_crop_box(&m, w, h, 1.2, 518.0 / 6.0);
        assert_eq!((b.x0, b.y0, b.x1, b.y1), (120, -29, 479, 328)); // half 179.4 around (300, 149.5)
        assert_eq!(object_crop_box(&[false; 6], 3, 2, 1.2, 1.0), CropBox { x0: 0, y0: 0, x1: 3, y1: 2 });
    }

    #[test]
    fn torch_nearest_differs_from_pil() {
        // 4 → 3: torch picks floor(i·4/3) = 0, 1, 2; PIL picks centres floor((i+0.5)·4/3) = 0, 2, 3.
        let src = [10, 11, 12, 13];
        assert_eq!(resize_nearest_torch(&src, 4, 1, 1, 3, 1).unwrap(), vec![10, 11, 12]);
        assert_eq!(crate::dataset::image::resize_nearest(&src, 4, 1, 1, 3, 1).unwrap(), vec![10, 12, 13]);
        // Upsampling 2 → 4 duplicates.
        assert_eq!(resize_nearest_torch(&[1, 2], 2, 1, 1, 4, 1).unwrap(), vec![1, 1, 2, 2]);
    }

    #[test]
    fn prepared_view_tensors_and_invariants() {
        // A fronto-parallel plate at 1 m with a hole, seen by a 64×48 camera.
        let k = Intrinsics { fx: 60.0, fy: 60.0, cx: 31.5, cy: 23.5 };
        let f = frame(64, 48, k, |x, y| {
            if x == 30 && y == 20 {
                f32::NAN
            } else if x == 31 && y == 20 {
                0.0
            } else {
                1.0
            }
        });
        let mut m = vec![false; 64 * 48];
        for y in 10..40 {
            for x in 16..50 {
                m[y * 64 + x] = true;
            }
        }
        let opts = PrepareOptions { min_half_side: 4.0, ..Default::default() };
        let v = prepare_object_with(&f, &m, 28, &opts, &Device::Cpu).unwrap();
        assert_eq!(v.pixel_values.dims(), &[1, 3, 28, 28]);
        assert_eq!(v.pointmap.dims(), &[1, 3, 28, 28]);
        assert_eq!(v.mask.dims(), &[1, 1, 28, 28]);
        // Eroded mask 30×26 = 780 pixels, two without depth.
        assert_eq!(v.num_points, 30 * 26 - 2);
        assert!((v.normaliser.centre[2] - 1.0).abs() < 1e-9);
        // Crop: eroded bbox x 18..=47, y 12..=37; centre (32.5, 24.5), half 29·0.6 = 17.4.
        assert_eq!(v.crop, CropBox { x0: 15, y0: 7, x1: 49, y1: 41 });
        // z of object pixels is 0.5, elsewhere 0 (the mask uses PIL's nearest
        // rule and the point map torch's, as upstream, so edges may disagree).
        let pm = v.pointmap.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let mk = v.mask.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let n = 28 * 28;
        let mut on = 0;
        for i in 0..n {
            let z = pm[2 * n + i];
            assert!(z == 0.0 || (z - 0.5).abs() < 1e-6, "{z}");
            assert!(mk[i] == 0.0 || mk[i] == 1.0);
            if mk[i] == 1.0 && z != 0.0 {
                on += 1;
            }
        }
        assert!(on > 400, "{on}");
        // x of the normalised map increases left to right on the object row.
        let row = 14 * 28;
        assert!(pm[row + 18] > pm[row + 10]);
        // Empty mask → error, not a panic.
        assert!(prepare_object(&f, &vec![false; 64 * 48], 28).is_err());
        assert!(prepare_object(&f, &[true; 3], 28).is_err());
    }
}
