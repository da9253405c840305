//! RGB-D frames: colour + metric depth + pinhole intrinsics, found beside the
//! colour image by dataset conventions or given explicitly.
//!
//! **Depth units.** [`RgbdFrame::depth_m`] is in metres. A pixel is *invalid*
//! when its value is `0.0` or not finite (NaN); the loaders write `0.0` for
//! "no reading" (PNG value 0). Every consumer (masks, point maps) treats both
//! the same way. The stored PNG value `v` becomes `v · depth_scale` metres,
//! with `depth_scale` (metres per unit) taken, in order of precedence, from
//! [`FrameOptions::depth_scale_m`], the intrinsics file (BOP `depth_scale` is
//! *millimetres* per unit, YCB-Video `factor_depth` is units per metre, our
//! `depth_scale_m` is metres per unit), or else 0.001 (millimetres), which is
//! what RecGen's `normalize_depth` assumes for integer depth.
//!
//! **Layouts found automatically** from the colour path (first match wins):
//!
//! | colour | depth | intrinsics |
//! |---|---|---|
//! | `NNNNNN-color.png` (YCB-Video, PoseCNN demo) | `NNNNNN-depth.png` | `NNNNNN-meta.mat` (`intrinsic_matrix`, `factor_depth`), `NNNNNN-meta.json`, `meta.yml` / `meta.json` in the folder |
//! | `<scene>/rgb/NNNNNN.png` (BOP) | `<scene>/depth/NNNNNN.png` | `<scene>/scene_camera.json`, entry `"<int id>"`: `cam_K`, `depth_scale` (mm per unit) |
//! | `rgb.png` (LINEMOD/BOP single camera) | `depth.png` | `camera.json`: `cam_K` or `fx,fy,cx,cy`, `depth_scale` (mm per unit) |
//! | `frame.png` (generic) | `frame.depth.png` | `frame.json`, else `camera.json` in the folder |
//!
//! Intrinsics JSON may hold `fx, fy, cx, cy`, a row-major `cam_K` (9 numbers)
//! or `K`/`intrinsic_matrix` (9 numbers or 3×3 rows), optionally under an
//! `intrinsics` key. `meta.yml` is read for `INTRINSICS: [fx,0,cx,0,fy,cy,0,0,1]`
//! (the PoseCNN demo format) or `fx:`/`fy:`/`cx:`/`cy:` lines.

use std::path::{Path, PathBuf};

use crate::dataset::matv5::MatFile;
use crate::{Error, Result};

/// OpenCV pinhole intrinsics in pixels: a point `(x, y, z)` projects to
/// `u = fx·x/z + cx`, `v = fy·y/z + cy`, integer `(u, v)` being pixel centres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

impl Intrinsics {
    /// Checked intrinsics (finite, `fx`, `fy` > 0).
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64) -> Result<Self> {
        let k = Intrinsics { fx, fy, cx, cy };
        k.validate("intrinsics")?;
        Ok(k)
    }

    fn validate(&self, file: &str) -> Result<()> {
        let ok = [self.fx, self.fy, self.cx, self.cy].iter().all(|v| v.is_finite()) && self.fx > 0.0 && self.fy > 0.0;
        if ok {
            Ok(())
        } else {
            Err(Error::input(file, format!("bad intrinsics {self:?}: need finite values and fx, fy > 0")))
        }
    }

    /// From a row-major 3×3 K (`[fx,0,cx, 0,fy,cy, 0,0,1]`).
    pub fn from_k_row_major(k: &[f64], file: &str) -> Result<Self> {
        if k.len() != 9 {
            return Err(Error::input(file, format!("camera matrix needs 9 numbers, got {}", k.len())));
        }
        let i = Intrinsics { fx: k[0], fy: k[4], cx: k[2], cy: k[5] };
        i.validate(file)?;
        Ok(i)
    }
}

/// Explicit choices that override the automatic search.
#[derive(Debug, Clone, Default)]
pub struct FrameOptions {
    /// Depth image path (16-bit PNG).
    pub depth: Option<PathBuf>,
    /// Intrinsics given directly.
    pub intrinsics: Option<Intrinsics>,
    /// Intrinsics JSON file (formats in the module docs).
    pub intrinsics_file: Option<PathBuf>,
    /// Metres per depth unit (e.g. 0.001 for millimetres, 1e-4 for YCB-Video).
    pub depth_scale_m: Option<f64>,
}

/// One RGB-D frame in memory.
#[derive(Debug, Clone)]
pub struct RgbdFrame {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Interleaved 8-bit RGB, row-major, `height·width·3`.
    pub rgb: Vec<u8>,
    /// Depth in metres, row-major `height·width`; `0.0` or non-finite = invalid.
    pub depth_m: Vec<f32>,
    /// Pinhole intrinsics of the colour and depth images (registered).
    pub intrinsics: Intrinsics,
    /// The colour image file.
    pub rgb_path: PathBuf,
    /// The depth image file.
    pub depth_path: PathBuf,
    /// Where the intrinsics came from (a path, or "explicit").
    pub intrinsics_source: String,
    /// Metres per stored depth unit that was applied.
    pub depth_scale_m: f64,
}

/// Whether a metric depth value is a usable reading.
#[inline]
pub fn depth_valid(z: f32) -> bool {
    z.is_finite() && z > 0.0
}

/// Intrinsics plus the depth scale (metres per unit) the same file states.
#[derive(Debug, Clone, Copy)]
struct CameraInfo {
    k: Intrinsics,
    depth_scale_m: Option<f64>,
}

#[derive(Debug, Clone)]
enum IntrSource {
    Json(PathBuf),
    BopScene(PathBuf, u64),
    Mat(PathBuf),
    Yaml(PathBuf),
}

impl IntrSource {
    fn path(&self) -> &Path {
        match self {
            IntrSource::Json(p) | IntrSource::BopScene(p, _) | IntrSource::Mat(p) | IntrSource::Yaml(p) => p,
        }
    }

    fn describe(&self) -> String {
        match self {
            IntrSource::BopScene(p, id) => format!("{} (entry \"{id}\")", p.display()),
            s => s.path().display().to_string(),
        }
    }

    fn load(&self) -> Result<CameraInfo> {
        let file = self.path().display().to_string();
        match self {
            IntrSource::Json(p) => {
                let v: serde_json::Value = crate::util::json::read_json(p)?;
                camera_from_json(&v, &file)
            }
            IntrSource::BopScene(p, id) => {
                let v: serde_json::Value = crate::util::json::read_json(p)?;
                let e = v.get(id.to_string()).ok_or_else(|| Error::input(&file, format!("no entry \"{id}\" in scene_camera.json")))?;
                camera_from_json(e, &file)
            }
            IntrSource::Mat(p) => camera_from_mat(&MatFile::open(p)?, &file),
            IntrSource::Yaml(p) => {
                let text = std::fs::read_to_string(p).map_err(|e| Error::io(p, e))?;
                camera_from_yaml(&text, &file)
            }
        }
    }
}

fn num(v: &serde_json::Value) -> Option<f64> {
    v.as_f64()
}

fn flat_numbers(v: &serde_json::Value) -> Option<Vec<f64>> {
    let a = v.as_array()?;
    let mut out = Vec::new();
    for x in a {
        match x {
            serde_json::Value::Array(_) => out.extend(flat_numbers(x)?),
            _ => out.push(num(x)?),
        }
    }
    Some(out)
}

/// Intrinsics from a YCB-Video `meta.mat` (`intrinsic_matrix`, `factor_depth`).
fn camera_from_mat(m: &MatFile, file: &str) -> Result<CameraInfo> {
    let k = m.require("intrinsic_matrix", file)?;
    let rows = k
        .rows()
        .filter(|r| r.len() == 3 && r.iter().all(|row| row.len() == 3))
        .ok_or_else(|| Error::input(file, format!("intrinsic_matrix has dims {:?}, expected 3×3", k.dims)))?;
    let flat: Vec<f64> = rows.concat();
    let intr = Intrinsics::from_k_row_major(&flat, file)?;
    let scale = match m.get("factor_depth") {
        Some(f) if f.len() == 1 && f.data[0] > 0.0 => Some(1.0 / f.data[0]),
        Some(f) => return Err(Error::input(file, format!("factor_depth must be one positive number, got {:?}", f.data))),
        None => None,
    };
    Ok(CameraInfo { k: intr, depth_scale_m: scale })
}

/// The camera file formats [`intrinsics_from_bytes`] reads.
#[derive(Clone, Copy, Debug)]
pub enum CameraFormat {
    /// JSON (BOP `scene_camera.json` entry or a plain K).
    Json,
    /// YAML (ROS `camera_info`).
    Yaml,
    /// MATLAB v5 `.mat` (YCB-Video `meta.mat`).
    Mat,
}

/// Intrinsics and depth scale (metres per unit) from a camera file's bytes,
/// as `RgbdFrame::open` reads them (the fuzz targets' entry point).
pub fn intrinsics_from_bytes(bytes: &[u8], format: CameraFormat, file: &str) -> Result<(Intrinsics, Option<f64>)> {
    let c = match format {
        CameraFormat::Json => {
            let v: serde_json::Value = serde_json::from_slice(bytes).map_err(|e| Error::Json { path: file.into(), source: e })?;
            camera_from_json(&v, file)?
        }
        CameraFormat::Yaml => camera_from_yaml(&String::from_utf8_lossy(bytes), file)?,
        CameraFormat::Mat => camera_from_mat(&MatFile::parse(bytes, file)?, file)?,
    };
    Ok((c.k, c.depth_scale_m))
}

/// Intrinsics from a JSON object (formats in the module docs).
fn camera_from_json(v: &serde_json::Value, file: &str) -> Result<CameraInfo> {
    let v = v.get("intrinsics").filter(|x| x.is_object()).unwrap_or(v);
    let k = if let (Some(fx), Some(fy), Some(cx), Some(cy)) =
        (v.get("fx").and_then(num), v.get("fy").and_then(num), v.get("cx").and_then(num), v.get("cy").and_then(num))
    {
        let k = Intrinsics { fx, fy, cx, cy };
        k.validate(file)?;
        k
    } else if let Some(m) = ["cam_K", "K", "intrinsic_matrix", "camera_matrix"].iter().find_map(|key| v.get(*key)) {
        let flat = flat_numbers(m).ok_or_else(|| Error::input(file, "camera matrix must be a list of numbers"))?;
        Intrinsics::from_k_row_major(&flat, file)?
    } else {
        return Err(Error::input(file, "no intrinsics: expected fx/fy/cx/cy, cam_K, K or intrinsic_matrix"));
    };
    let scale = if let Some(s) = v.get("depth_scale_m") {
        Some(num(s).filter(|s| *s > 0.0).ok_or_else(|| Error::input(file, "depth_scale_m must be a positive number"))?)
    } else if let Some(s) = v.get("depth_scale") {
        // BOP convention: millimetres per stored unit.
        Some(num(s).filter(|s| *s > 0.0).ok_or_else(|| Error::input(file, "depth_scale must be a positive number"))? / 1000.0)
    } else {
        None
    };
    Ok(CameraInfo { k, depth_scale_m: scale })
}

/// Intrinsics from the small YAML files RGB-D demos ship (no YAML library:
/// only the two forms in the module docs are understood).
fn camera_from_yaml(text: &str, file: &str) -> Result<CameraInfo> {
    if let Some(i) = text.find("INTRINSICS:") {
        let rest = &text[i + "INTRINSICS:".len()..];
        // The `]` that closes the list: searched after the `[` (fuzzing found `] … [`).
        let a = rest.find('[');
        let b = a.and_then(|a| rest[a..].find(']').map(|b| a + b));
        if let (Some(a), Some(b)) = (a, b) {
            let vals: std::result::Result<Vec<f64>, _> =
                rest[a + 1..b].split(',').map(|s| s.trim()).filter(|s| !s.is_empty()).map(|s| s.parse::<f64>()).collect();
            let vals = vals.map_err(|e| Error::input(file, format!("INTRINSICS: {e}")))?;
            return Ok(CameraInfo { k: Intrinsics::from_k_row_major(&vals, file)?, depth_scale_m: None });
        }
    }
    let get = |key: &str| -> Option<f64> {
        text.lines().find_map(|l| {
            let l = l.trim();
            let rest = l.strip_prefix(key)?.trim_start().strip_prefix(':')?;
            rest.trim().parse().ok()
        })
    };
    match (get("fx"), get("fy"), get("cx"), get("cy")) {
        (Some(fx), Some(fy), Some(cx), Some(cy)) => {
            let k = Intrinsics { fx, fy, cx, cy };
            k.validate(file)?;
            Ok(CameraInfo { k, depth_scale_m: get("depth_scale_m") })
        }
        _ => Err(Error::input(file, "no intrinsics: expected `INTRINSICS: [9 numbers]` or fx/fy/cx/cy lines")),
    }
}

/// One layout convention that matched the colour file's name.
struct Candidate {
    convention: &'static str,
    depth: PathBuf,
    intrinsics: Vec<IntrSource>,
}

fn candidates(rgb: &Path) -> Vec<Candidate> {
    let dir = rgb.parent().map(Path::to_path_buf).unwrap_or_default();
    let stem = rgb.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    let mut out = Vec::new();
    if let Some(prefix) = stem.strip_suffix("-color") {
        out.push(Candidate {
            convention: "YCB-Video (NNNNNN-color.png)",
            depth: dir.join(format!("{prefix}-depth.png")),
            intrinsics: vec![
                IntrSource::Mat(dir.join(format!("{prefix}-meta.mat"))),
                IntrSource::Json(dir.join(format!("{prefix}-meta.json"))),
                IntrSource::Yaml(dir.join("meta.yml")),
                IntrSource::Yaml(dir.join("meta.yaml")),
                IntrSource::Json(dir.join("meta.json")),
            ],
        });
    }
    if dir.file_name().and_then(|s| s.to_str()) == Some("rgb") {
        if let Some(scene) = dir.parent() {
            let mut intr = Vec::new();
            if let Ok(id) = stem.parse::<u64>() {
                intr.push(IntrSource::BopScene(scene.join("scene_camera.json"), id));
            }
            intr.push(IntrSource::Json(scene.join("camera.json")));
            out.push(Candidate {
                convention: "BOP (rgb/NNNNNN.png)",
                depth: scene.join("depth").join(format!("{stem}.png")),
                intrinsics: intr,
            });
        }
    }
    if stem == "rgb" {
        out.push(Candidate {
            convention: "LINEMOD single camera (rgb.png)",
            depth: dir.join("depth.png"),
            intrinsics: vec![IntrSource::Json(dir.join("camera.json"))],
        });
    }
    out.push(Candidate {
        convention: "generic (frame.png)",
        depth: dir.join(format!("{stem}.depth.png")),
        intrinsics: vec![IntrSource::Json(dir.join(format!("{stem}.json"))), IntrSource::Json(dir.join("camera.json"))],
    });
    out
}

/// Decode a colour image to interleaved RGB8.
pub fn load_rgb(path: &Path) -> Result<(Vec<u8>, usize, usize)> {
    let img = crate::util::open_image(path, "colour image")?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    Ok((img.to_rgb8().into_raw(), w, h))
}

/// Read a 16-bit single-channel depth PNG as raw units.
pub fn load_depth_u16(path: &Path) -> Result<(Vec<u16>, usize, usize)> {
    let file = path.display().to_string();
    let img = crate::util::open_image(path, "depth image")?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    match img {
        image::DynamicImage::ImageLuma16(b) => Ok((b.into_raw(), w, h)),
        other => Err(Error::input(&file, format!("depth must be a 16-bit single-channel PNG (uint16 units), found {:?}", other.color()))),
    }
}

impl RgbdFrame {
    /// Load the colour image and find its depth and intrinsics (module docs).
    pub fn open(rgb_path: &Path, opts: &FrameOptions) -> Result<Self> {
        let (rgb, width, height) = load_rgb(rgb_path)?;
        let cands = candidates(rgb_path);

        // Depth: explicit path, else the first convention whose file exists.
        let (depth_path, intr_sources): (PathBuf, Vec<IntrSource>) = match &opts.depth {
            Some(p) => {
                if !p.is_file() {
                    return Err(Error::input(p.display().to_string(), "depth file given explicitly does not exist"));
                }
                (p.clone(), cands.into_iter().flat_map(|c| c.intrinsics).collect())
            }
            None => match cands.iter().position(|c| c.depth.is_file()) {
                Some(i) => {
                    let mut c = cands;
                    let chosen = c.swap_remove(i);
                    (chosen.depth, chosen.intrinsics)
                }
                None => {
                    let looked: Vec<String> = cands.iter().map(|c| format!("  {} [{}]", c.depth.display(), c.convention)).collect();
                    return Err(Error::input(
                        rgb_path.display().to_string(),
                        format!("no depth image found; looked for:\n{}\n(give one explicitly with a depth path)", looked.join("\n")),
                    ));
                }
            },
        };

        // Intrinsics: explicit values, explicit file, else the first sidecar that exists.
        let (info, intrinsics_source) = if let Some(k) = opts.intrinsics {
            k.validate("explicit intrinsics")?;
            (CameraInfo { k, depth_scale_m: None }, "explicit".to_string())
        } else if let Some(p) = &opts.intrinsics_file {
            let src = if p.extension().and_then(|e| e.to_str()) == Some("mat") {
                IntrSource::Mat(p.clone())
            } else if matches!(p.extension().and_then(|e| e.to_str()), Some("yml" | "yaml")) {
                IntrSource::Yaml(p.clone())
            } else {
                IntrSource::Json(p.clone())
            };
            (src.load()?, p.display().to_string())
        } else {
            match intr_sources.iter().find(|s| s.path().is_file()) {
                Some(s) => (s.load()?, s.describe()),
                None => {
                    let looked: Vec<String> = intr_sources.iter().map(|s| format!("  {}", s.describe())).collect();
                    return Err(Error::input(
                        rgb_path.display().to_string(),
                        format!(
                            "no camera intrinsics found; looked for:\n{}\n(give fx, fy, cx, cy or an intrinsics file explicitly)",
                            looked.join("\n")
                        ),
                    ));
                }
            }
        };

        let depth_scale = opts.depth_scale_m.or(info.depth_scale_m).unwrap_or(0.001);
        if !(depth_scale.is_finite() && depth_scale > 0.0) {
            return Err(Error::input("depth_scale", format!("must be positive metres per unit, got {depth_scale}")));
        }
        let (raw, dw, dh) = load_depth_u16(&depth_path)?;
        if (dw, dh) != (width, height) {
            return Err(Error::input(
                depth_path.display().to_string(),
                format!(
                    "depth is {dw}×{dh} but the colour image {} is {width}×{height}; depth must be registered to colour",
                    rgb_path.display()
                ),
            ));
        }
        let depth_m = raw.iter().map(|&v| (v as f64 * depth_scale) as f32).collect();
        Ok(RgbdFrame {
            width,
            height,
            rgb,
            depth_m,
            intrinsics: info.k,
            rgb_path: rgb_path.to_path_buf(),
            depth_path,
            intrinsics_source,
            depth_scale_m: depth_scale,
        })
    }

    /// A frame from buffers already in memory (the Python bindings' arrays):
    /// interleaved RGB8 and metric depth, both row-major `height·width`. `name`
    /// stands in for the file paths in reports and error messages.
    pub fn from_buffers(width: usize, height: usize, rgb: Vec<u8>, depth_m: Vec<f32>, intrinsics: Intrinsics, name: &str) -> Result<Self> {
        if width == 0 || height == 0 {
            return Err(Error::input(name, format!("empty frame ({width}×{height})")));
        }
        if rgb.len() != width * height * 3 {
            return Err(Error::input(name, format!("rgb has {} values, expected {height}×{width}×3", rgb.len())));
        }
        if depth_m.len() != width * height {
            return Err(Error::input(
                name,
                format!("depth has {} values, expected {height}×{width} (registered to colour)", depth_m.len()),
            ));
        }
        intrinsics.validate(name)?;
        Ok(RgbdFrame {
            width,
            height,
            rgb,
            depth_m,
            intrinsics,
            rgb_path: PathBuf::from(name),
            depth_path: PathBuf::from(name),
            intrinsics_source: "explicit".to_string(),
            depth_scale_m: 1.0,
        })
    }

    /// Depth at pixel `(u, v)` in metres (`0.0`/NaN = invalid).
    pub fn depth_at(&self, u: usize, v: usize) -> f32 {
        self.depth_m[v * self.width + u]
    }

    /// Median of the valid depth values (metres), `None` if there are none.
    pub fn median_valid_depth(&self) -> Option<f32> {
        let mut v: Vec<f32> = self.depth_m.iter().copied().filter(|&z| depth_valid(z)).collect();
        if v.is_empty() {
            return None;
        }
        let mid = v.len() / 2;
        let (_, m, _) = v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
        Some(*m)
    }

    /// Fraction of pixels with a valid depth reading.
    pub fn valid_fraction(&self) -> f64 {
        self.depth_m.iter().filter(|&&z| depth_valid(z)).count() as f64 / self.depth_m.len().max(1) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write_rgb(p: &Path, w: u32, h: u32) {
        let img = image::RgbImage::from_fn(w, h, |x, y| image::Rgb([x as u8, y as u8, 7]));
        img.save(p).unwrap();
    }

    fn write_depth(p: &Path, w: u32, h: u32, v: u16) {
        let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, _| image::Luma([if x == 0 { 0 } else { v }]));
        img.save(p).unwrap();
    }

    #[test]
    fn generic_layout_with_json() {
        let d = crate::util::testing::tmp("frame-generic");
        write_rgb(&d.join("shot.png"), 8, 6);
        write_depth(&d.join("shot.depth.png"), 8, 6, 1500);
        std::fs::write(d.join("shot.json"), r#"{"fx": 500, "fy": 501, "cx": 3.5, "cy": 2.5}"#).unwrap();
        let f = RgbdFrame::open(&d.join("shot.png"), &FrameOptions::default()).unwrap();
        assert_eq!((f.width, f.height), (8, 6));
        assert_eq!(f.intrinsics, Intrinsics { fx: 500.0, fy: 501.0, cx: 3.5, cy: 2.5 });
        assert_eq!(f.depth_scale_m, 0.001); // default: millimetres
        assert!((f.depth_at(3, 2) - 1.5).abs() < 1e-6);
        assert_eq!(f.depth_at(0, 2), 0.0);
        assert_eq!(&f.rgb[(2 * 8 + 3) * 3..(2 * 8 + 3) * 3 + 3], &[3, 2, 7]);
        // Explicit scale overrides the default.
        let f = RgbdFrame::open(&d.join("shot.png"), &FrameOptions { depth_scale_m: Some(1e-4), ..Default::default() }).unwrap();
        assert!((f.depth_at(3, 2) - 0.15).abs() < 1e-6);
    }

    #[test]
    fn bop_and_linemod_layouts() {
        let d = crate::util::testing::tmp("frame-bop");
        std::fs::create_dir_all(d.join("rgb")).unwrap();
        std::fs::create_dir_all(d.join("depth")).unwrap();
        write_rgb(&d.join("rgb/000007.png"), 4, 4);
        write_depth(&d.join("depth/000007.png"), 4, 4, 1000);
        std::fs::write(d.join("scene_camera.json"), r#"{"7": {"cam_K": [600, 0, 2, 0, 610, 1.5, 0, 0, 1], "depth_scale": 0.1}}"#).unwrap();
        let f = RgbdFrame::open(&d.join("rgb/000007.png"), &FrameOptions::default()).unwrap();
        assert_eq!(f.intrinsics, Intrinsics { fx: 600.0, fy: 610.0, cx: 2.0, cy: 1.5 });
        // 1000 units × 0.1 mm = 0.1 m.
        assert!((f.depth_at(1, 1) - 0.1).abs() < 1e-6);

        let d = crate::util::testing::tmp("frame-lm");
        write_rgb(&d.join("rgb.png"), 4, 4);
        write_depth(&d.join("depth.png"), 4, 4, 900);
        std::fs::write(d.join("camera.json"), r#"{"cam_K": [572.4, 0, 325.2, 0, 573.5, 242.0, 0, 0, 1], "depth_scale": 1.0}"#).unwrap();
        let f = RgbdFrame::open(&d.join("rgb.png"), &FrameOptions::default()).unwrap();
        assert!((f.depth_at(1, 1) - 0.9).abs() < 1e-6);
        assert_eq!(f.intrinsics.cy, 242.0);
    }

    #[test]
    fn ycb_layout_with_mat_and_yaml() {
        let d = crate::util::testing::tmp("frame-ycb");
        write_rgb(&d.join("000001-color.png"), 4, 4);
        write_depth(&d.join("000001-depth.png"), 4, 4, 10000);
        let k = vec![1066.778, 0.0, 0.0, 0.0, 1067.487, 0.0, 312.9869, 241.3109, 1.0];
        let bytes = crate::dataset::matv5::tests::write_mat(
            &[("intrinsic_matrix", vec![3, 3], k), ("factor_depth", vec![1, 1], vec![10000.0])],
            true,
            false,
        );
        std::fs::write(d.join("000001-meta.mat"), bytes).unwrap();
        let f = RgbdFrame::open(&d.join("000001-color.png"), &FrameOptions::default()).unwrap();
        assert_eq!(f.intrinsics, Intrinsics { fx: 1066.778, fy: 1067.487, cx: 312.9869, cy: 241.3109 });
        assert!((f.depth_at(2, 2) - 1.0).abs() < 1e-6);

        // PoseCNN demo: meta.yml in the folder, depth in mm.
        let d = crate::util::testing::tmp("frame-rs");
        write_rgb(&d.join("000000-color.png"), 4, 4);
        write_depth(&d.join("000000-depth.png"), 4, 4, 700);
        std::fs::write(d.join("meta.yml"), "INTRINSICS: [618.0, 0.0, 312.3,\n  0.0, 618.1, 232.3, 0.0, 0.0, 1.0]\n").unwrap();
        let f = RgbdFrame::open(&d.join("000000-color.png"), &FrameOptions::default()).unwrap();
        assert_eq!(f.intrinsics, Intrinsics { fx: 618.0, fy: 618.1, cx: 312.3, cy: 232.3 });
        assert!((f.depth_at(2, 2) - 0.7).abs() < 1e-6);
    }

    #[test]
    fn frames_from_buffers_check_their_sizes() {
        let k = Intrinsics::new(100.0, 100.0, 2.0, 1.5).unwrap();
        let f = RgbdFrame::from_buffers(4, 3, vec![7; 36], vec![1.5; 12], k, "<array>").unwrap();
        assert_eq!((f.width, f.height, f.depth_at(3, 2), f.rgb_path.as_path()), (4, 3, 1.5, Path::new("<array>")));
        let e = RgbdFrame::from_buffers(4, 3, vec![7; 35], vec![1.5; 12], k, "<array>").unwrap_err().to_string();
        assert!(e.contains("<array>") && e.contains("35") && e.contains("3×4×3"), "{e}");
        let e = RgbdFrame::from_buffers(4, 3, vec![7; 36], vec![1.5; 11], k, "<array>").unwrap_err().to_string();
        assert!(e.contains("depth has 11 values"), "{e}");
        let bad = Intrinsics { fx: -1.0, ..k };
        assert!(RgbdFrame::from_buffers(4, 3, vec![7; 36], vec![1.5; 12], bad, "<array>").is_err());
    }

    #[test]
    fn missing_and_bad_files_are_reported() {
        let d = crate::util::testing::tmp("frame-missing");
        write_rgb(&d.join("000001-color.png"), 4, 4);
        let e = RgbdFrame::open(&d.join("000001-color.png"), &FrameOptions::default()).unwrap_err().to_string();
        assert!(e.contains("000001-depth.png") && e.contains("000001-color.depth.png"), "{e}");

        // Depth present, intrinsics missing: every candidate is listed.
        write_depth(&d.join("000001-depth.png"), 4, 4, 1);
        let e = RgbdFrame::open(&d.join("000001-color.png"), &FrameOptions::default()).unwrap_err().to_string();
        assert!(e.contains("000001-meta.mat") && e.contains("meta.yml"), "{e}");
        // Explicit intrinsics fix it.
        let o = FrameOptions { intrinsics: Some(Intrinsics::new(100.0, 100.0, 2.0, 2.0).unwrap()), ..Default::default() };
        assert!(RgbdFrame::open(&d.join("000001-color.png"), &o).is_ok());

        // Wrong size.
        write_depth(&d.join("000001-depth.png"), 5, 4, 1);
        let e = RgbdFrame::open(&d.join("000001-color.png"), &o).unwrap_err().to_string();
        assert!(e.contains("5×4") && e.contains("4×4") && e.contains("000001-depth.png"), "{e}");

        // 8-bit depth.
        image::GrayImage::new(4, 4).save(d.join("000001-depth.png")).unwrap();
        let e = RgbdFrame::open(&d.join("000001-color.png"), &o).unwrap_err().to_string();
        assert!(e.contains("16-bit") && e.contains("000001-depth.png"), "{e}");

        // Explicit depth path that does not exist.
        let o2 = FrameOptions { depth: Some(d.join("nope.png")), ..o.clone() };
        assert!(RgbdFrame::open(&d.join("000001-color.png"), &o2).unwrap_err().to_string().contains("nope.png"));

        // Bad intrinsics JSON.
        std::fs::write(d.join("k.json"), r#"{"fx": -1, "fy": 1, "cx": 0, "cy": 0}"#).unwrap();
        write_depth(&d.join("000001-depth.png"), 4, 4, 1);
        let o3 = FrameOptions { intrinsics_file: Some(d.join("k.json")), ..Default::default() };
        assert!(RgbdFrame::open(&d.join("000001-color.png"), &o3).is_err());
    }
}
