//! Resource bounds checked before allocating what an input's header claims.
//! Every bound here is stated in the README ("Hostile inputs"); a file over
//! one is refused with [`Error::TooLarge`] naming the file, the field and the
//! bound, never an abort.

use crate::{Error, Result};

/// Largest image side read (colour, depth, masks), in pixels.
pub const MAX_IMAGE_SIDE: u32 = 32_768;
/// Largest image read, in pixels (100 MP: 300 MB as RGB8, 1.2 GB as the
/// f32 point map an object's crop is cut from).
pub const MAX_IMAGE_PIXELS: u64 = 100_000_000;
/// Most bytes one image decode may allocate (RGBA16 at [`MAX_IMAGE_PIXELS`]).
pub const MAX_IMAGE_ALLOC: u64 = 8 * MAX_IMAGE_PIXELS;
/// Most bytes a zlib stream inside a MAT v5 file may inflate to (YCB-Video
/// `meta.mat` files are under 1 MB; a 1080p `vertmap` of doubles is 50 MB).
pub const MAX_MAT_INFLATED: u64 = 64 << 20;
/// Deflate cannot expand data by more than this factor (RFC 1951 caps a
/// match at 258 bytes per 2 bits of code), so a compressed zip entry of
/// `n` bytes cannot honestly claim more than `n · MAX_DEFLATE_RATIO`.
pub const MAX_DEFLATE_RATIO: u64 = 1032;

/// Largest user mesh file read (GLB, OBJ or PLY asset), in bytes.
pub const MAX_MESH_FILE_BYTES: u64 = 256 << 20;
/// Most vertices and most triangles one user mesh may hold (a scanned
/// object decimated for simulation has well under a million).
pub const MAX_MESH_VERTICES: u64 = 4_000_000;
/// Most triangles one user mesh may hold (see [`MAX_MESH_VERTICES`]).
pub const MAX_MESH_TRIANGLES: u64 = 8_000_000;
/// Most mesh files one asset folder may hold, and the deepest folder walked.
pub const MAX_ASSET_FILES: usize = 1000;
/// Most folder levels walked in an asset folder, the folder itself counting as one (see [`MAX_ASSET_FILES`]).
pub const MAX_ASSET_DEPTH: usize = 4;
/// Largest physics JSON beside an asset, in bytes.
pub const MAX_ASSET_JSON_BYTES: u64 = 1 << 20;
/// Largest JSON chunk of a GLB file, in bytes.
pub const MAX_GLB_JSON_BYTES: u64 = 64 << 20;
/// Deepest glTF node hierarchy followed.
pub const MAX_GLTF_NODE_DEPTH: usize = 64;

/// The machine's memory in bytes (`MemTotal` of /proc/meminfo), capped by
/// the applied settings' memory limit (`RECON_MEMORY_LIMIT_MB`, for clusters
/// whose jobs get less than the node has). `None` where neither is known.
pub fn memory_budget_bytes() -> Option<u64> {
    let env = crate::settings::current().memory_limit;
    let total = std::fs::read_to_string("/proc/meminfo").ok().and_then(|s| {
        let line = s.lines().find(|l| l.starts_with("MemTotal:"))?;
        line.split_whitespace().nth(1)?.parse::<u64>().ok().map(|kib| kib << 10)
    });
    match (env, total) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

/// Product of `dims` without overflow; `None` when it exceeds u128.
pub fn checked_product(dims: impl IntoIterator<Item = u128>) -> Option<u128> {
    dims.into_iter().try_fold(1u128, |a, d| a.checked_mul(d))
}

/// A file's size, checked against `max` bytes before it is read (`what` names
/// the bound in the error).
pub fn check_file_size(path: &std::path::Path, max: u64, what: &str) -> Result<u64> {
    let len = std::fs::metadata(path).map_err(|e| Error::io(path, e))?.len();
    if len > max {
        return Err(Error::too_large(path.display().to_string(), "file size", len as u128, max as u128, "bytes", what));
    }
    Ok(len)
}

/// The dimensions of an image file, checked against [`MAX_IMAGE_SIDE`] and
/// [`MAX_IMAGE_PIXELS`] from its header alone.
pub fn check_image_dims(file: &str, w: u32, h: u32) -> Result<()> {
    let side = w.max(h);
    if side > MAX_IMAGE_SIDE {
        return Err(Error::too_large(
            file,
            "image width/height",
            side as u128,
            MAX_IMAGE_SIDE as u128,
            "pixels",
            format!("header says {w}×{h}"),
        ));
    }
    let px = w as u64 * h as u64;
    if px > MAX_IMAGE_PIXELS {
        return Err(Error::too_large(file, "image size", px as u128, MAX_IMAGE_PIXELS as u128, "pixels", format!("header says {w}×{h}")));
    }
    Ok(())
}

/// Open an image with its size checked from the header before decoding, and
/// the decoder's own allocation limit set to [`MAX_IMAGE_ALLOC`].
pub fn open_image(path: &std::path::Path, what: &str) -> Result<image::DynamicImage> {
    let file = path.display().to_string();
    let bad = |e: &dyn std::fmt::Display| Error::input(&file, format!("cannot read {what}: {e}"));
    let reader = || -> Result<image::ImageReader<std::io::BufReader<std::fs::File>>> {
        let r = image::ImageReader::open(path).map_err(|e| bad(&e))?;
        r.with_guessed_format().map_err(|e| bad(&e))
    };
    let (w, h) = reader()?.into_dimensions().map_err(|e| bad(&e))?;
    check_image_dims(&file, w, h)?;
    let mut r = reader()?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE);
    limits.max_image_height = Some(MAX_IMAGE_SIDE);
    limits.max_alloc = Some(MAX_IMAGE_ALLOC);
    r.limits(limits);
    r.decode().map_err(|e| bad(&e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn image_dims_are_bounded() {
        assert!(check_image_dims("a.png", 640, 480).is_ok());
        let e = check_image_dims("a.png", 100_000, 100_000).unwrap_err();
        assert!(matches!(&e, Error::TooLarge(b) if b.claimed == 100_000), "{e}");
        let e = check_image_dims("a.png", 20_000, 20_000).unwrap_err();
        assert!(matches!(&e, Error::TooLarge(b) if b.claimed == 400_000_000), "{e}");
    }

    #[test]
    fn products_do_not_overflow() {
        assert_eq!(checked_product([2, 3, 4]), Some(24));
        assert_eq!(checked_product([u64::MAX as u128, u64::MAX as u128, 4]), None);
    }
}
