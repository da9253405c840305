//! Texture images: the PNG every textured format refers to (or embeds).

use super::axes::write_file;
use crate::mesh::Texture;
use crate::{Error, Result};
use std::path::Path;

/// The texture as PNG bytes (8-bit RGB, sRGB as the formats read base colours).
pub fn png_bytes(t: &Texture) -> Result<Vec<u8>> {
    use image::ImageEncoder;
    if t.rgb.len() != t.width * t.height * 3 || t.width == 0 || t.height == 0 {
        return Err(Error::msg(format!("texture: {} bytes for a {}×{} RGB image", t.rgb.len(), t.width, t.height)));
    }
    let (w, h) = (u32::try_from(t.width), u32::try_from(t.height));
    let (Ok(w), Ok(h)) = (w, h) else { return Err(Error::msg("texture: image over 2³² texels a side")) };
    let mut out = Vec::new();
    image::codecs::png::PngEncoder::new(&mut out)
        .write_image(&t.rgb, w, h, image::ExtendedColorType::Rgb8)
        .map_err(|e| Error::msg(format!("texture: PNG encoding: {e}")))?;
    Ok(out)
}

/// Writes the texture as a PNG file.
pub fn save_png(t: &Texture, path: &Path) -> Result<()> {
    write_file(path, &png_bytes(t)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trips() {
        let t = Texture { width: 3, height: 2, rgb: (0..18).map(|i| (i * 13) as u8).collect() };
        let b = png_bytes(&t).unwrap();
        let back = image::load_from_memory(&b).unwrap().to_rgb8();
        assert_eq!((back.width(), back.height()), (3, 2));
        assert_eq!(back.into_raw(), t.rgb);
        assert!(png_bytes(&Texture { width: 2, height: 2, rgb: vec![0; 3] }).is_err());
    }
}
