//! Image preprocessing for the DINOv2 conditioning, as TRELLIS/RecGen do it
//! (`preprocess_image`, `encode_image`, RecGen `get_cond` mask/pointmap
//! resizes). Functions take explicit row-major arrays so the pipeline can
//! feed decoded files or in-memory frames alike.
//!
//! Exactness: upstream resizes with PIL `LANCZOS` (Lanczos3, support scaled
//! when downsampling). We use the `image` crate's `Lanczos3`, which follows
//! the same definition, but the two differ in fixed-point details, so resized
//! pixels may differ by a few 8-bit levels; everything after the resize
//! (scaling, normalisation, nearest resizes, crop box) is exact.

use crate::{Error, Result};
use candle_core::{Device, Tensor};

/// ImageNet normalisation used by DINOv2 (`torchvision.transforms.Normalize`).
pub const DINO_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
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

/// Lanczos3 resize of an interleaved 8-bit image with 3 (RGB) or 4 (RGBA) channels.
pub fn resize_lanczos_u8(px: &[u8], w: usize, h: usize, channels: usize, out_w: usize, out_h: usize) -> Result<Vec<u8>> {
    check_len("image", px.len(), w, h, channels)?;
    if out_w == 0 || out_h == 0 {
        return Err(Error::input("image", "resize target must be non-empty"));
    }
    if (w, h) == (out_w, out_h) {
        // PIL returns a copy for a same-size resize.
        return Ok(px.to_vec());
    }
    use image::imageops::{resize, FilterType};
    let bad = || Error::input("image", "buffer does not match its size");
    let out = match channels {
        3 => resize(&image::RgbImage::from_raw(w as u32, h as u32, px.to_vec()).ok_or_else(bad)?, out_w as u32, out_h as u32, FilterType::Lanczos3)
            .into_raw(),
        4 => resize(&image::RgbaImage::from_raw(w as u32, h as u32, px.to_vec()).ok_or_else(bad)?, out_w as u32, out_h as u32, FilterType::Lanczos3)
            .into_raw(),
        c => return Err(Error::input("image", format!("{c} channels; expected 3 or 4"))),
    };
    Ok(out)
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
/// `x` samples source column `floor((x + 0.5)·w/out_w)`.
pub fn resize_nearest<T: Copy>(src: &[T], w: usize, h: usize, channels: usize, out_w: usize, out_h: usize) -> Result<Vec<T>> {
    check_len("array", src.len(), w, h, channels)?;
    let map = |o: usize, n_in: usize, n_out: usize| (((o as f64 + 0.5) * n_in as f64 / n_out as f64) as usize).min(n_in - 1);
    let cols: Vec<usize> = (0..out_w).map(|x| map(x, w, out_w)).collect();
    let mut out = Vec::with_capacity(out_w * out_h * channels);
    for y in 0..out_h {
        let sy = map(y, h, out_h);
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
    pub x0: i64,
    pub y0: i64,
    pub x1: i64,
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
    let b = square_crop_box(&alpha, w, h)?
        .ok_or_else(|| Error::input("rgba", "alpha mask is empty (no pixel above 0.8·255)"))?;
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
        assert!(resize_nearest(&[1u8, 2, 3], 2, 1, 1, 4, 1).is_err());
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
