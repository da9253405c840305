//! Image preprocessing for the DINOv2 conditioning, as TRELLIS/RecGen do it
//! (`preprocess_image`, `encode_image`, RecGen `get_cond` mask/pointmap
//! resizes). Functions take explicit row-major arrays so the pipeline can
//! feed decoded files or in-memory frames alike.
//!
//! Exactness: upstream resizes with PIL `LANCZOS` (Lanczos3, support scaled
//! when downsampling); [`resize_lanczos_pil`] reproduces Pillow's
//! fixed-point algorithm (checked bit-exact against Pillow 13 on random
//! images), and the nearest resizes follow PIL's coordinate arithmetic.

use crate::{Error, Result};
use candle_core::{Device, Tensor};

/// ImageNet normalisation used by DINOv2 (`torchvision.transforms.Normalize`).
pub const DINO_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
/// ImageNet standard deviations used by DINOv2 (with [`DINO_MEAN`]).
pub const DINO_STD: [f32; 3] = [0.229, 0.224, 0.225];
/// Side of the square DINOv2 input (37×37 patches of 14 px).
pub const DINO_SIZE: usize = 518;

/// Normalise `[B, 3, H, W]` values in [0, 1] with the DINOv2 mean/std.
pub fn normalize_01(x: &Tensor) -> Result<Tensor> {
    let dev = x.device();
    let mean = Tensor::from_slice(&DINO_MEAN, (1, 3, 1, 1), dev)?.to_dtype(x.dtype())?;
    let std = Tensor::from_slice(&DINO_STD, (1, 3, 1, 1), dev)?.to_dtype(x.dtype())?;
    Ok(x.broadcast_sub(&mean)?.broadcast_div(&std)?)
}

fn check_len(what: &str, len: usize, w: usize, h: usize, c: usize) -> Result<()> {
    if w == 0 || h == 0 || len != w * h * c {
        return Err(Error::input(what, format!("expected {w}x{h}x{c} = {} values, got {len}", w * h * c)));
    }
    Ok(())
}

/// Lanczos3 resize of an interleaved 8-bit image with 3 (RGB) or 4 (RGBA)
/// channels, computed as Pillow's `ImagingResample` does (see
/// [`resize_lanczos_pil`]). Channels are filtered independently (PIL
/// premultiplies RGBA around this; callers that need that do it).
pub fn resize_lanczos_u8(px: &[u8], w: usize, h: usize, channels: usize, out_w: usize, out_h: usize) -> Result<Vec<u8>> {
    check_len("image", px.len(), w, h, channels)?;
    if out_w == 0 || out_h == 0 {
        return Err(Error::input("image", "resize target must be non-empty"));
    }
    if !(channels == 3 || channels == 4) {
        return Err(Error::input("image", format!("{channels} channels; expected 3 or 4")));
    }
    Ok(resize_lanczos_pil(px, w, h, channels, out_w, out_h))
}

// Pillow's fixed-point precision for 8-bit resampling (32 − 8 − 2 bits).
const PIL_PRECISION_BITS: u32 = 22;

fn pil_lanczos(x: f64) -> f64 {
    let sinc = |x: f64| if x == 0.0 { 1.0 } else { (x * std::f64::consts::PI).sin() / (x * std::f64::consts::PI) };
    if (-3.0..3.0).contains(&x) {
        sinc(x) * sinc(x / 3.0)
    } else {
        0.0
    }
}

/// Pillow's `precompute_coeffs` + `normalize_coeffs_8bpc`: per output pixel
/// the first source index, the tap count and fixed-point weights.
fn pil_coeffs(n_in: usize, n_out: usize) -> (Vec<(usize, usize)>, Vec<i32>, usize) {
    let scale = n_in as f64 / n_out as f64;
    let filterscale = scale.max(1.0);
    let support = 3.0 * filterscale;
    let ksize = support.ceil() as usize * 2 + 1;
    let mut bounds = Vec::with_capacity(n_out);
    let mut kk = vec![0i32; n_out * ksize];
    let mut w = vec![0f64; ksize];
    for xx in 0..n_out {
        let center = (xx as f64 + 0.5) * scale;
        let ss = 1.0 / filterscale;
        let xmin = ((center - support + 0.5) as i64).max(0) as usize; // C (int) truncation
        let xmax = ((center + support + 0.5) as i64).min(n_in as i64) as usize - xmin;
        let mut ww = 0.0;
        for x in 0..xmax {
            w[x] = pil_lanczos((x as f64 + xmin as f64 - center + 0.5) * ss);
            ww += w[x];
        }
        for x in 0..xmax {
            let v = if ww != 0.0 { w[x] / ww } else { w[x] };
            let f = v * (1u64 << PIL_PRECISION_BITS) as f64;
            kk[xx * ksize + x] = if v < 0.0 { (-0.5 + f) as i32 } else { (0.5 + f) as i32 };
        }
        bounds.push((xmin, xmax));
    }
    (bounds, kk, ksize)
}

#[inline]
fn pil_clip8(v: i64) -> u8 {
    if v >= (1i64 << PIL_PRECISION_BITS) << 8 {
        255
    } else if v <= 0 {
        0
    } else {
        (v >> PIL_PRECISION_BITS) as u8
    }
}

/// Pillow's separable Lanczos resampling of 8-bit images, reproduced
/// exactly: weights from `lanczos(x)·` normalised per output pixel over the
/// taps inside the image, support scaled by the downsampling factor,
/// weights rounded to 22-bit fixed point, a horizontal pass (only over the
/// source rows the vertical pass will read) rounded to 8 bits, then a
/// vertical pass. A pass is skipped when its size does not change.
pub fn resize_lanczos_pil(px: &[u8], w: usize, h: usize, c: usize, out_w: usize, out_h: usize) -> Vec<u8> {
    use rayon::prelude::*;
    let half = 1i64 << (PIL_PRECISION_BITS - 1);
    // Horizontal pass over the rows the vertical pass needs.
    let (vb, vk, vks) = pil_coeffs(h, out_h);
    let (y_first, y_last) = if out_h != h { (vb[0].0, vb[out_h - 1].0 + vb[out_h - 1].1) } else { (0, h) };
    let tmp: Vec<u8> = if out_w != w {
        let (hb, hk, hks) = pil_coeffs(w, out_w);
        let mut t = vec![0u8; (y_last - y_first) * out_w * c];
        t.par_chunks_mut(out_w * c).enumerate().for_each(|(r, row)| {
            let src = &px[(r + y_first) * w * c..(r + y_first + 1) * w * c];
            for xx in 0..out_w {
                let (xmin, n) = hb[xx];
                let k = &hk[xx * hks..xx * hks + n];
                for ch in 0..c {
                    let mut ss = half;
                    for (x, &kw) in k.iter().enumerate() {
                        ss += src[(x + xmin) * c + ch] as i64 * kw as i64;
                    }
                    row[xx * c + ch] = pil_clip8(ss);
                }
            }
        });
        t
    } else {
        px[y_first * w * c..y_last * w * c].to_vec()
    };
    if out_h == h {
        return tmp;
    }
    let mut out = vec![0u8; out_w * out_h * c];
    out.par_chunks_mut(out_w * c).enumerate().for_each(|(yy, row)| {
        let (ymin, n) = vb[yy];
        let ymin = ymin - y_first;
        let k = &vk[yy * vks..yy * vks + n];
        for i in 0..out_w * c {
            let mut ss = half;
            for (y, &kw) in k.iter().enumerate() {
                ss += tmp[(y + ymin) * out_w * c + i] as i64 * kw as i64;
            }
            row[i] = pil_clip8(ss);
        }
    });
    out
}

/// Interleaved 8-bit RGB (`h*w*3`) → `[1, 3, h, w]` f32 in [0, 1].
pub fn rgb_u8_to_tensor(rgb: &[u8], w: usize, h: usize, dev: &Device) -> Result<Tensor> {
    check_len("rgb", rgb.len(), w, h, 3)?;
    let mut chw = vec![0f32; 3 * w * h];
    for (i, p) in rgb.chunks_exact(3).enumerate() {
        for c in 0..3 {
            chw[c * w * h + i] = p[c] as f32 / 255.0;
        }
    }
    Ok(Tensor::from_vec(chw, (1, 3, h, w), dev)?)
}

/// `encode_image`: resize to `size`×`size` (Lanczos3), /255, normalise → `[1, 3, size, size]`.
pub fn dino_pixel_values(rgb: &[u8], w: usize, h: usize, size: usize, dev: &Device) -> Result<Tensor> {
    let r = resize_lanczos_u8(rgb, w, h, 3, size, size)?;
    normalize_01(&rgb_u8_to_tensor(&r, size, size, dev)?)
}

/// PIL `NEAREST` resize of an interleaved `h×w×channels` array: output pixel
/// `x` samples source column `floor((x + 0.5)·w/out_w)`, with PIL's
/// arithmetic: its affine sampler starts at `0.5·s` (`s = w/out_w` in f64)
/// and *adds* `s` per pixel, and the accumulated rounding decides exact
/// ties (e.g. 220 → 518, row 388); a direct product differs there.
pub fn resize_nearest<T: Copy>(src: &[T], w: usize, h: usize, channels: usize, out_w: usize, out_h: usize) -> Result<Vec<T>> {
    check_len("array", src.len(), w, h, channels)?;
    let map = |n_in: usize, n_out: usize| -> Vec<usize> {
        let s = n_in as f64 / n_out as f64;
        let mut acc = 0.5 * s;
        (0..n_out)
            .map(|_| {
                let i = (acc as usize).min(n_in - 1);
                acc += s;
                i
            })
            .collect()
    };
    let cols = map(w, out_w);
    let rows = map(h, out_h);
    let mut out = Vec::with_capacity(out_w * out_h * channels);
    for &sy in &rows {
        for &sx in &cols {
            let base = (sy * w + sx) * channels;
            out.extend_from_slice(&src[base..base + channels]);
        }
    }
    Ok(out)
}

/// RecGen mask input: 8-bit mask (`h*w`, 0 or 255) resized NEAREST to
/// `size`² and divided by 255 → `[1, 1, size, size]`.
pub fn mask_to_tensor(mask: &[u8], w: usize, h: usize, size: usize, dev: &Device) -> Result<Tensor> {
    let r = resize_nearest(mask, w, h, 1, size, size)?;
    let v: Vec<f32> = r.iter().map(|&m| m as f32 / 255.0).collect();
    Ok(Tensor::from_vec(v, (1, 1, size, size), dev)?)
}

/// Point map (`h*w*3` XYZ, already normalised by the caller) resized NEAREST
/// to `size`² → `[1, 3, size, size]`.
pub fn pointmap_to_tensor(xyz: &[f32], w: usize, h: usize, size: usize, dev: &Device) -> Result<Tensor> {
    let r = resize_nearest(xyz, w, h, 3, size, size)?;
    let n = size * size;
    let mut chw = vec![0f32; 3 * n];
    for (i, p) in r.chunks_exact(3).enumerate() {
        for c in 0..3 {
            chw[c * n + i] = p[c];
        }
    }
    Ok(Tensor::from_vec(chw, (1, 3, size, size), dev)?)
}

/// A crop rectangle in pixel coordinates, `[x0, x1) × [y0, y1)`; may extend
/// past the image (those pixels are zero, as with PIL `crop`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CropBox {
    /// Left edge (inclusive).
    pub x0: i64,
    /// Top edge (inclusive).
    pub y0: i64,
    /// Right edge (exclusive).
    pub x1: i64,
    /// Bottom edge (exclusive).
    pub y1: i64,
}

/// Python's `round` (half to even), which PIL applies to float crop boxes.
fn round_half_even(v: f64) -> i64 {
    let r = v.round();
    if (v - v.trunc()).abs() == 0.5 && (r as i64) % 2 != 0 {
        (r - v.signum()) as i64
    } else {
        r as i64
    }
}

/// TRELLIS square crop around the object: bbox of `alpha > 0.8·255`, side
/// `int(1.2·max(bw, bh))` (bbox extents are max−min of pixel indices),
/// centred on the bbox centre. `None` when no pixel passes the threshold.
pub fn square_crop_box(alpha: &[u8], w: usize, h: usize) -> Result<Option<CropBox>> {
    check_len("alpha", alpha.len(), w, h, 1)?;
    let thr = 0.8 * 255.0;
    let (mut xmin, mut ymin, mut xmax, mut ymax) = (usize::MAX, usize::MAX, 0usize, 0usize);
    for y in 0..h {
        for x in 0..w {
            if alpha[y * w + x] as f64 > thr {
                xmin = xmin.min(x);
                xmax = xmax.max(x);
                ymin = ymin.min(y);
                ymax = ymax.max(y);
            }
        }
    }
    if xmin == usize::MAX {
        return Ok(None);
    }
    let (cx, cy) = ((xmin + xmax) as f64 / 2.0, (ymin + ymax) as f64 / 2.0);
    let side = ((xmax - xmin).max(ymax - ymin) as f64 * 1.2) as i64;
    let half = (side / 2) as f64;
    Ok(Some(CropBox {
        x0: round_half_even(cx - half),
        y0: round_half_even(cy - half),
        x1: round_half_even(cx + half),
        y1: round_half_even(cy + half),
    }))
}

/// Crop an interleaved image to `b`, filling outside pixels with zeros.
pub fn crop<T: Copy + Default>(px: &[T], w: usize, h: usize, channels: usize, b: CropBox) -> Result<(Vec<T>, usize, usize)> {
    check_len("image", px.len(), w, h, channels)?;
    if b.x1 <= b.x0 || b.y1 <= b.y0 {
        return Err(Error::input("crop", format!("empty crop box {b:?}")));
    }
    let (ow, oh) = ((b.x1 - b.x0) as usize, (b.y1 - b.y0) as usize);
    let mut out = vec![T::default(); ow * oh * channels];
    for oy in 0..oh {
        let sy = b.y0 + oy as i64;
        if sy < 0 || sy >= h as i64 {
            continue;
        }
        for ox in 0..ow {
            let sx = b.x0 + ox as i64;
            if sx < 0 || sx >= w as i64 {
                continue;
            }
            let s = (sy as usize * w + sx as usize) * channels;
            let d = (oy * ow + ox) * channels;
            out[d..d + channels].copy_from_slice(&px[s..s + channels]);
        }
    }
    Ok((out, ow, oh))
}

/// TRELLIS `preprocess_image` for an RGBA image with a meaningful alpha
/// (background removal is out of scope): square crop around the alpha bbox,
/// Lanczos resize to `size`², RGB premultiplied by alpha (black background).
/// Returns interleaved RGB `size*size*3`.
///
/// PIL resizes RGBA in premultiplied form and converts back; we resize the
/// premultiplied image directly, which equals PIL's result up to 8-bit
/// rounding of the un-/re-premultiplication.
pub fn trellis_preprocess_rgba(rgba: &[u8], w: usize, h: usize, size: usize) -> Result<Vec<u8>> {
    check_len("rgba", rgba.len(), w, h, 4)?;
    let alpha: Vec<u8> = rgba.chunks_exact(4).map(|p| p[3]).collect();
    let b = square_crop_box(&alpha, w, h)?.ok_or_else(|| Error::input("rgba", "alpha mask is empty (no pixel above 0.8·255)"))?;
    let (c, cw, ch) = crop(rgba, w, h, 4, b)?;
    let pre: Vec<u8> = c
        .chunks_exact(4)
        .flat_map(|p| {
            let a = p[3] as u32;
            let m = |v: u8| ((v as u32 * a + 127) / 255) as u8;
            [m(p[0]), m(p[1]), m(p[2]), p[3]]
        })
        .collect();
    let r = resize_lanczos_u8(&pre, cw, ch, 4, size, size)?;
    Ok(r.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_matches_pil_convention() {
        // 4 → 2 picks source indices 1 and 3 (centres 0.5·2 = 1, 1.5·2 = 3).
        let src: Vec<u8> = (0..4).collect();
        assert_eq!(resize_nearest(&src, 4, 1, 1, 2, 1).unwrap(), vec![1, 3]);
        // 2 → 4 duplicates.
        assert_eq!(resize_nearest(&[7u8, 9], 2, 1, 1, 4, 1).unwrap(), vec![7, 7, 9, 9]);
        // PIL's accumulated coordinate: 220 → 518 row 388 samples 164
        // (checked against Pillow 13), where 388.5·220/518 is exactly 165.
        let col: Vec<u16> = (0..220).collect();
        assert_eq!(resize_nearest(&col, 1, 220, 1, 1, 518).unwrap()[388], 164);
        assert!(resize_nearest(&[1u8, 2, 3], 2, 1, 1, 4, 1).is_err());
    }

    #[test]
    fn lanczos_is_bit_exact_with_pillow() {
        // Expected bytes from Pillow 13 `Image.resize(..., LANCZOS)` of this 6×4 RGB image.
        let src: Vec<u8> = (0..6 * 4 * 3).map(|i| ((i * 37 + 11) % 256) as u8).collect();
        let down = [
            57, 111, 142, 170, 72, 123, 159, 131, 95, 118, 179, 77, 109, 146, 193, 82, 126, 168, 188, 78, 134, 173, 159, 107, 150, 185,
            108, 109, 155, 84, 115, 135, 143, 86, 84, 144,
        ];
        assert_eq!(resize_lanczos_u8(&src, 6, 4, 3, 4, 3).unwrap(), down);
        let up = resize_lanczos_u8(&src, 6, 4, 3, 9, 7).unwrap();
        // First row, middle and last values of the 9×7 upsample.
        assert_eq!(&up[..12], &[0, 8, 45, 43, 116, 153, 176, 163, 198, 252, 13, 42]);
        assert_eq!(&up[up.len() - 6..], &[72, 131, 156, 0, 12, 39]);
        assert_eq!(up.len(), 9 * 7 * 3);
    }

    #[test]
    fn crop_box_like_trellis() {
        // Object occupying x 10..=29, y 20..=29 of a 64×48 image.
        let (w, h) = (64, 48);
        let mut a = vec![0u8; w * h];
        for y in 20..30 {
            for x in 10..30 {
                a[y * w + x] = 255;
            }
        }
        // bbox (10,20,29,29): centre (19.5, 24.5), side int(19·1.2) = 22, half 11.
        // round(8.5) = 8, round(13.5) = 14, round(30.5) = 30, round(35.5) = 36.
        let b = square_crop_box(&a, w, h).unwrap().unwrap();
        assert_eq!(b, CropBox { x0: 8, y0: 14, x1: 30, y1: 36 });
        let (c, cw, ch) = crop(&a, w, h, 1, b).unwrap();
        assert_eq!((cw, ch), (22, 22));
        assert_eq!(c[(20 - 14) * 22 + (10 - 8)], 255);
        assert_eq!(c[0], 0);
        assert!(square_crop_box(&vec![0u8; w * h], w, h).unwrap().is_none());
        // Boxes past the border are zero-filled.
        let (c, _, _) = crop(&[5u8; 4], 2, 2, 1, CropBox { x0: -1, y0: -1, x1: 1, y1: 1 }).unwrap();
        assert_eq!(c, vec![0, 0, 0, 5]);
    }

    #[test]
    fn pixel_values_constant_image() {
        let dev = Device::Cpu;
        // A constant image stays constant under Lanczos; check the normalisation.
        let rgb = vec![128u8; 20 * 10 * 3];
        let t = dino_pixel_values(&rgb, 20, 10, 28, &dev).unwrap();
        assert_eq!(t.dims(), &[1, 3, 28, 28]);
        let v = t.flatten_from(2).unwrap().to_vec3::<f32>().unwrap();
        for c in 0..3 {
            let want = (128.0 / 255.0 - DINO_MEAN[c]) / DINO_STD[c];
            assert!(v[0][c].iter().all(|x| (x - want).abs() < 1e-5), "channel {c}");
        }
    }

    #[test]
    fn mask_and_pointmap_tensors() {
        let dev = Device::Cpu;
        let m = mask_to_tensor(&[0, 255, 255, 0], 2, 2, 4, &dev).unwrap();
        let v = m.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert_eq!(&v[..4], &[0.0, 0.0, 1.0, 1.0]);
        let pm: Vec<f32> = (0..12).map(|i| i as f32).collect();
        let p = pointmap_to_tensor(&pm, 2, 2, 2, &dev).unwrap();
        // channel 1 (y) of the 4 pixels: 1, 4, 7, 10
        assert_eq!(p.get(0).unwrap().get(1).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap(), vec![1.0, 4.0, 7.0, 10.0]);
    }

    #[test]
    fn preprocess_rgba_black_background() {
        let (w, h) = (40, 30);
        let mut px = vec![0u8; w * h * 4];
        for y in 10..20 {
            for x in 10..30 {
                let i = (y * w + x) * 4;
                px[i..i + 4].copy_from_slice(&[200, 100, 50, 255]);
            }
        }
        let out = trellis_preprocess_rgba(&px, w, h, 56).unwrap();
        assert_eq!(out.len(), 56 * 56 * 3);
        assert_eq!(&out[..3], &[0, 0, 0]); // corner is background
        let c = (28 * 56 + 28) * 3;
        assert!((out[c] as i32 - 200).abs() <= 2 && (out[c + 1] as i32 - 100).abs() <= 2);
    }
}
