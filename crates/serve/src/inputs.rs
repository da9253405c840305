//! A request's inputs: the multipart parts as stored in the job folder ([`Manifest`]),
//! and the frame(s), masks and options read back from them ([`load`]) with the library
//! functions `recon infer` uses, so that the server refuses what the CLI refuses, with
//! the CLI's message, and computes what the CLI computes.

use crate::error::{input_status, ApiError};
use recon_core::dataset::frame::{intrinsics_from_bytes, load_rgb, CameraFormat};
use recon_core::dataset::masks::load_binary_mask;
use recon_core::dataset::{FrameOptions, RgbdFrame};
use recon_core::dataset::{InstanceMap, MaskSkip, ObjectMask, SkipReason};
use recon_core::engine::{InferOptions, RigidTransform};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The parts `POST /v1/reconstruct` takes: name, whether required, what it holds.
pub const PARTS: &[(&str, bool, &str)] = &[
    ("rgb", true, "colour image, PNG or JPEG"),
    ("depth", true, "depth: 16-bit PNG (units of depth_scale_m, default millimetres) or .npy float32 metres, registered to rgb"),
    ("masks", true, "one instance-id PNG (0 = background), or several binary mask parts (one object each)"),
    ("intrinsics", true, "JSON {fx, fy, cx, cy} or {K: 3×3 or 9 numbers}, optional depth_scale_m; or the text fx,fy,cx,cy"),
    ("options", false, "JSON object of recon infer's per-frame options (names and defaults of docs/options.md)"),
    ("objects", false, "instance ids to reconstruct: 1,2,3 or a JSON array (default: every id present)"),
    ("rgb2", false, "second view: colour image"),
    ("depth2", false, "second view: depth"),
    ("masks2", false, "second view: masks, matched to masks by instance id (or by order for binary masks)"),
    ("intrinsics2", false, "second view: intrinsics"),
    ("T_c1_c2", false, "second view: camera 2 → camera 1 rigid transform, 4×4 row-major (JSON rows, 16 numbers, or {\"T_c1_c2\": rows})"),
];

/// The parts of the second view; any of them given makes all of them required.
pub const SECOND_VIEW_PARTS: [&str; 5] = ["rgb2", "depth2", "masks2", "intrinsics2", "T_c1_c2"];

/// Largest small part (intrinsics, options, objects, T_c1_c2), bytes.
pub const MAX_SMALL_PART_BYTES: u64 = 1 << 20;

/// Whether `name` is a small part (held in memory, parsed as text).
pub fn is_small_part(name: &str) -> bool {
    matches!(name, "intrinsics" | "intrinsics2" | "options" | "objects" | "T_c1_c2")
}

/// Whether `name` may be given more than once (binary masks).
pub fn is_repeatable(name: &str) -> bool {
    matches!(name, "masks" | "masks2")
}

/// One stored part.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct StoredPart {
    /// The file, relative to the job folder (`inputs/rgb`).
    pub file: String,
    /// The client's file name, made safe (letters, digits, `.`, `-`, `_`).
    pub filename: Option<String>,
    /// Its size.
    pub bytes: u64,
}

/// What a request stored: its parts, and the options it runs with (the server's defaults
/// overridden by the request's `options`, complete). Written as `request.json`.
#[derive(Debug, Clone, Serialize, Deserialize, Default)]
pub struct Manifest {
    /// Part name → its stored files (several only for binary masks).
    pub parts: BTreeMap<String, Vec<StoredPart>>,
    /// The per-frame options, every name present.
    pub options: serde_json::Value,
    /// The instance ids asked for (`None`: every id present).
    pub objects: Option<Vec<u32>>,
}

/// A client's file name made safe to store and to show: its last path component, only
/// ASCII letters, digits, `.`, `-` and `_`, not starting with `.`, at most 96 characters.
pub fn safe_filename(name: &str) -> Option<String> {
    let last = name.rsplit(['/', '\\']).next().unwrap_or("");
    let s: String = last.chars().filter(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_')).take(96).collect();
    let s = s.trim_start_matches('.').to_string();
    (!s.is_empty()).then_some(s)
}

/// The request's `options` part merged over the server's `defaults`: an unknown name or
/// a bad value is a 400 naming the option (the message of [`InferOptions::from_json`]).
pub fn merge_options(defaults: &InferOptions, part: Option<&[u8]>) -> Result<serde_json::Value, ApiError> {
    let mut merged = serde_json::to_value(defaults).map_err(|e| ApiError::unavailable(e.to_string()))?;
    if let Some(bytes) = part {
        let v: serde_json::Value =
            serde_json::from_slice(bytes).map_err(|e| ApiError::bad("options", "json", format!("options: invalid JSON: {e}")))?;
        let serde_json::Value::Object(given) = v else {
            return Err(ApiError::bad("options", "json", "options: expected a JSON object of option names"));
        };
        // The request's own names first, so that an unknown one is reported as such.
        InferOptions::from_json(serde_json::Value::Object(given.clone())).map_err(|e| option_error(&e))?;
        if let serde_json::Value::Object(m) = &mut merged {
            m.extend(given);
        }
    }
    let o = InferOptions::from_json(merged.clone()).map_err(|e| option_error(&e))?;
    if o.max_objects > defaults.max_objects {
        return Err(ApiError::bad(
            "options",
            "max_objects",
            format!("options: max_objects: {} is above this server's limit of {} (--max-objects)", o.max_objects, defaults.max_objects),
        ));
    }
    Ok(merged)
}

fn option_error(e: &recon_core::engine::OptionError) -> ApiError {
    ApiError::bad("options", e.option(), format!("options: {}", e.keyword_message()))
}

/// The `objects` part: `1,2,3` or a JSON array of ids.
pub fn parse_objects(bytes: &[u8]) -> Result<Vec<u32>, ApiError> {
    let text = String::from_utf8_lossy(bytes);
    let t = text.trim();
    let bad = || ApiError::bad("objects", "objects", format!("objects: expected instance ids as 1,2,3 or a JSON array, got `{t}`"));
    if t.starts_with('[') {
        serde_json::from_str::<Vec<u32>>(t).map_err(|_| bad())
    } else {
        t.split(',').map(|s| s.trim().parse::<u32>().map_err(|_| bad())).collect()
    }
}

/// What a job runs on, read from its stored parts.
pub struct Loaded {
    /// View 1.
    pub frame: RgbdFrame,
    /// View 1's objects.
    pub objects: Vec<ObjectMask>,
    /// Objects left out before the engine (ids asked for that are absent, …), view 2's
    /// relabelled `view 2 …` as the CLI does.
    pub skipped: Vec<MaskSkip>,
    /// View 2: frame, masks and `T_c1_c2`.
    pub second: Option<(RgbdFrame, Vec<ObjectMask>, RigidTransform)>,
    /// The options, checked.
    pub options: InferOptions,
}

/// A stored part's path and the name it is shown by.
struct Part {
    name: String,
    path: PathBuf,
    filename: Option<String>,
}

fn one<'a>(dir: &Path, m: &'a Manifest, name: &str) -> Option<(Part, &'a StoredPart)> {
    let p = m.parts.get(name)?.first()?;
    Some((Part { name: name.to_string(), path: dir.join(&p.file), filename: p.filename.clone() }, p))
}

fn required(dir: &Path, m: &Manifest, name: &str) -> Result<Part, ApiError> {
    one(dir, m, name).map(|(p, _)| p).ok_or_else(|| {
        let what = PARTS.iter().find(|p| p.0 == name).map_or("", |p| p.2);
        ApiError::bad(name, name, format!("missing part `{name}` ({what})"))
    })
}

/// An engine error about stored input files, as the request sees it: each stored path in
/// the message replaced by its part's name, the part named, and the field (the bound's
/// field, the config field, or `default_field`).
fn from_engine(e: &recon_core::Error, parts: &[&Part], default_field: &str) -> ApiError {
    let orig = e.to_string();
    let path_of = |p: &Part| p.path.display().to_string();
    // The part whose file the message names first is the one at fault (its file leads it).
    let part = parts.iter().filter_map(|p| orig.find(&path_of(p)).map(|i| (i, *p))).min_by_key(|(i, _)| *i).map(|(_, p)| p);
    let mut by_length: Vec<&&Part> = parts.iter().collect();
    by_length.sort_by_key(|p| std::cmp::Reverse(path_of(p).len()));
    let msg = by_length.iter().fold(orig.clone(), |m, p| m.replace(&path_of(p), &p.name));
    let field = match e {
        recon_core::Error::TooLarge(b) => b.field.clone(),
        recon_core::Error::Config { field, .. } => field.clone(),
        recon_core::Error::Json { .. } => "json".to_string(),
        _ => default_field.to_string(),
    };
    let name = part.or(parts.first().copied()).map_or("request", |p| p.name.as_str());
    ApiError::new(input_status(e), msg).at(name, &field)
}

/// The intrinsics part as JSON bytes: JSON as given, or `fx,fy,cx,cy` text (the CLI's
/// `--intrinsics` form) turned into `{"fx":…}`; which field is wrong when one is
/// (for the error's `field`).
fn intrinsics_json(bytes: &[u8], part: &str) -> Result<(Vec<u8>, Option<&'static str>), ApiError> {
    let text = String::from_utf8_lossy(bytes);
    let t = text.trim();
    if !(t.starts_with('{') || t.starts_with('[')) {
        let nums: Vec<f64> = t.split(',').filter_map(|v| v.trim().parse().ok()).collect();
        if nums.len() == 4 && t.split(',').count() == 4 {
            // As the CLI's `--intrinsics fx,fy,cx,cy`.
            if let Err(e) = recon_core::dataset::Intrinsics::new(nums[0], nums[1], nums[2], nums[3]) {
                let bad =
                    ["fx", "fy", "cx", "cy"].into_iter().zip(&nums).find(|(k, v)| !v.is_finite() || (k.starts_with('f') && **v <= 0.0));
                return Err(ApiError::bad(part, bad.map_or("intrinsics", |b| b.0), e.to_string().replacen("intrinsics", part, 1)));
            }
            let v = serde_json::json!({"fx": nums[0], "fy": nums[1], "cx": nums[2], "cy": nums[3]});
            return Ok((v.to_string().into_bytes(), None));
        }
        return Err(ApiError::bad(part, "json", format!("{part}: expected JSON (fx, fy, cx, cy or K) or the text fx,fy,cx,cy")));
    }
    let field = serde_json::from_str::<serde_json::Value>(t).ok().and_then(|v| {
        let v = v.get("intrinsics").filter(|x| x.is_object()).cloned().unwrap_or(v);
        for k in ["fx", "fy", "cx", "cy"] {
            match v.get(k) {
                Some(x) if x.as_f64().is_some_and(|f| f.is_finite() && (!k.starts_with('f') || f > 0.0)) => {}
                Some(_) => return Some(k),
                None => {}
            }
        }
        ["cam_K", "K", "intrinsic_matrix", "camera_matrix"].into_iter().find(|k| v.get(*k).is_some())
    });
    Ok((bytes.to_vec(), field))
}

/// Reads one view (`suffix` "" or "2") of the stored parts.
fn load_frame(dir: &Path, m: &Manifest, suffix: &str) -> Result<RgbdFrame, ApiError> {
    let rgb = required(dir, m, &format!("rgb{suffix}"))?;
    let depth = required(dir, m, &format!("depth{suffix}"))?;
    let intr = required(dir, m, &format!("intrinsics{suffix}"))?;
    let raw = std::fs::read(&intr.path).map_err(|e| ApiError::unavailable(format!("reading the stored {}: {e}", intr.name)))?;
    let (json, bad_field) = intrinsics_json(&raw, &intr.name)?;
    let ipath = intr.path.with_extension("json");
    if ipath != intr.path || json != raw {
        std::fs::write(&ipath, &json).map_err(|e| ApiError::unavailable(format!("storing {}: {e}", intr.name)))?;
    }
    let intr = Part { path: ipath, ..intr };
    let ifield = bad_field.unwrap_or("intrinsics");
    let npy = std::fs::File::open(&depth.path)
        .and_then(|mut f| {
            let mut head = [0u8; 6];
            std::io::Read::read_exact(&mut f, &mut head).map(|_| head == *b"\x93NUMPY")
        })
        .unwrap_or(false);
    let mut frame = if npy {
        let (rgb_px, w, h) = load_rgb(&rgb.path).map_err(|e| from_engine(&e, &[&rgb], "image"))?;
        let (k, _) = intrinsics_from_bytes(&json, CameraFormat::Json, &intr.path.display().to_string())
            .map_err(|e| from_engine(&e, &[&intr], ifield))?;
        let (dw, dh, d) = read_npy_f32(&depth.path, &depth.name)?;
        if (dw, dh) != (w, h) {
            return Err(ApiError::bad(
                &depth.name,
                "shape",
                format!(
                    "{}: depth is {dw}×{dh} but the colour image {} is {w}×{h}; depth must be registered to colour",
                    depth.name, rgb.name
                ),
            ));
        }
        RgbdFrame::from_buffers(w, h, rgb_px, d, k, &rgb.name).map_err(|e| from_engine(&e, &[&rgb, &depth], "size"))?
    } else {
        let fo = FrameOptions { depth: Some(depth.path.clone()), intrinsics_file: Some(intr.path.clone()), ..Default::default() };
        RgbdFrame::open(&rgb.path, &fo).map_err(|e| {
            let field = if e.to_string().contains(&intr.path.display().to_string()) { ifield } else { "image" };
            from_engine(&e, &[&rgb, &depth, &intr], field)
        })?
    };
    // Reports name the client's files, as `recon infer` names its arguments.
    frame.rgb_path = PathBuf::from(rgb.filename.clone().unwrap_or_else(|| rgb.name.clone()));
    frame.depth_path = PathBuf::from(depth.filename.clone().unwrap_or_else(|| depth.name.clone()));
    Ok(frame)
}

/// Reads one view's masks: one part is an instance-id map, several are binary masks.
/// Every mask must be the frame's size. Masks are held as row runs, so a map of many
/// instances costs its pixels; `max_objects` is checked on what passes ([`load`]).
fn load_view_masks(dir: &Path, m: &Manifest, name: &str, frame: &RgbdFrame) -> Result<(Vec<ObjectMask>, Vec<MaskSkip>), ApiError> {
    let stored = m
        .parts
        .get(name)
        .filter(|v| !v.is_empty())
        .ok_or_else(|| required(dir, m, name).err().unwrap_or_else(|| ApiError::bad(name, name, "missing")))?;
    let size_check = |w: usize, h: usize, part: &str| -> Result<(), ApiError> {
        if (w, h) != (frame.width, frame.height) {
            let reason = SkipReason::WrongSize { mask: (w, h), frame: (frame.width, frame.height) };
            return Err(ApiError::bad(part, "size", format!("{part}: {reason}")));
        }
        Ok(())
    };
    if stored.len() == 1 {
        let p = Part { name: name.to_string(), path: dir.join(&stored[0].file), filename: stored[0].filename.clone() };
        let map = InstanceMap::open(&p.path).map_err(|e| from_engine(&e, &[&p], "image"))?;
        size_check(map.width, map.height, name)?;
        Ok(map.objects(m.objects.as_deref()))
    } else {
        if m.objects.is_some() {
            return Err(ApiError::bad(
                "objects",
                "objects",
                "objects: selects ids of an instance-id map; with several binary mask parts, send only the masks you want",
            ));
        }
        let mut out = Vec::new();
        for (k, s) in stored.iter().enumerate() {
            let part = format!("{name}[{k}]");
            let p = Part { name: part.clone(), path: dir.join(&s.file), filename: s.filename.clone() };
            let mask = load_binary_mask(&p.path).map_err(|e| from_engine(&e, &[&p], "image"))?;
            size_check(mask.width, mask.height, &part)?;
            out.push(mask);
        }
        Ok((out, Vec::new()))
    }
}

/// The `T_c1_c2` part, checked as the CLI's `--rel-pose` is (16 finite numbers, last row
/// 0 0 0 1, an orthonormal rotation with determinant 1).
fn load_rel_pose(dir: &Path, m: &Manifest) -> Result<RigidTransform, ApiError> {
    let p = required(dir, m, "T_c1_c2")?;
    let raw = std::fs::read(&p.path).map_err(|e| ApiError::unavailable(format!("reading the stored T_c1_c2: {e}")))?;
    let text = String::from_utf8_lossy(&raw);
    let t = text.trim();
    let value: serde_json::Value = if t.starts_with('{') || t.starts_with('[') {
        let v: serde_json::Value =
            serde_json::from_str(t).map_err(|e| ApiError::bad("T_c1_c2", "json", format!("T_c1_c2: invalid JSON: {e}")))?;
        v.get("T_c1_c2").cloned().unwrap_or(v)
    } else {
        let nums: Result<Vec<f64>, _> =
            t.split(|c: char| c == ',' || c.is_whitespace()).filter(|s| !s.is_empty()).map(str::parse).collect();
        match nums {
            Ok(n) => serde_json::json!(n),
            Err(_) => return Err(ApiError::bad("T_c1_c2", "T_c1_c2", format!("T_c1_c2: `{t}` is not 16 numbers (4×4 row-major)"))),
        }
    };
    let file = p.path.with_extension("json");
    std::fs::write(&file, serde_json::json!({ "T_c1_c2": value }).to_string())
        .map_err(|e| ApiError::unavailable(format!("storing T_c1_c2: {e}")))?;
    let part = Part { path: file.clone(), ..p };
    recon_core::geometry::parse_rel_pose(&file.display().to_string()).map_err(|e| from_engine(&e, &[&part], "T_c1_c2"))
}

/// Reads and checks everything a job runs on from its folder `dir`. `max_views` is the
/// loaded model's (a second view needs 2). Called when the request arrives (nothing is
/// queued that fails here) and again by the worker.
pub fn load(dir: &Path, m: &Manifest, max_views: usize) -> Result<Loaded, ApiError> {
    for (name, req, what) in PARTS {
        if *req && !m.parts.contains_key(*name) {
            return Err(ApiError::bad(name, name, format!("missing part `{name}` ({what})")));
        }
    }
    let options = InferOptions::from_json(m.options.clone()).map_err(|e| option_error(&e))?;
    let frame = load_frame(dir, m, "")?;
    let (objects, skipped) = load_view_masks(dir, m, "masks", &frame)?;
    // `recon infer`'s rule: more objects that pass the mask checks than max_objects is refused.
    let settings = options.settings().map_err(|e| option_error(&e))?;
    recon_core::engine::check_object_count(&frame, &objects, &settings, "masks")
        .map_err(|e| ApiError::new(crate::error::input_status(&e), e.to_string()).at("masks", "max_objects"))?;
    let given: Vec<&str> = SECOND_VIEW_PARTS.iter().copied().filter(|p| m.parts.contains_key(*p)).collect();
    let second = if given.is_empty() {
        None
    } else {
        if let Some(missing) = SECOND_VIEW_PARTS.iter().find(|p| !given.contains(p)) {
            return Err(ApiError::bad(
                missing,
                missing,
                format!(
                    "missing part `{missing}`: a second view needs rgb2, depth2, masks2, intrinsics2 and T_c1_c2 (given: {})",
                    given.join(", ")
                ),
            ));
        }
        if max_views < 2 {
            return Err(ApiError::bad(
                "rgb2",
                "rgb2",
                format!("this model takes {max_views} view(s); a second view needs a two-view (num_pose_tokens 2) model"),
            ));
        }
        let f2 = load_frame(dir, m, "2")?;
        let (o2, _) = load_view_masks(dir, m, "masks2", &f2)?;
        let rel = load_rel_pose(dir, m)?;
        // The engine pairs the views' objects; a count mismatch of binary masks is the request's fault.
        recon_core::engine::match_views(objects.clone(), o2.clone())
            .map_err(|e| ApiError::bad("masks2", "masks2", e.to_string().replace("--masks2", "masks2")))?;
        Some((f2, o2, rel))
    };
    Ok(Loaded { frame, objects, skipped, second, options })
}

/// A `.npy` file of float32 depth in metres, 2-D `(height, width)`, C order; the shape is
/// checked against the image bounds before anything of that size is allocated.
pub fn read_npy_f32(path: &Path, part: &str) -> Result<(usize, usize, Vec<f32>), ApiError> {
    use std::io::Read;
    let bad = |field: &str, msg: String| ApiError::bad(part, field, format!("{part}: {msg}"));
    let mut f = std::fs::File::open(path).map_err(|e| ApiError::unavailable(format!("reading the stored {part}: {e}")))?;
    let len = f.metadata().map(|m| m.len()).unwrap_or(0);
    let mut head = [0u8; 8];
    f.read_exact(&mut head).map_err(|_| bad("npy", "truncated .npy header".into()))?;
    if head[..6] != *b"\x93NUMPY" {
        return Err(bad("npy", "not a .npy file".into()));
    }
    let (header_len, prefix) = match head[6] {
        1 => {
            let mut b = [0u8; 2];
            f.read_exact(&mut b).map_err(|_| bad("npy", "truncated .npy header".into()))?;
            (u16::from_le_bytes(b) as u64, 10)
        }
        2 | 3 => {
            let mut b = [0u8; 4];
            f.read_exact(&mut b).map_err(|_| bad("npy", "truncated .npy header".into()))?;
            (u32::from_le_bytes(b) as u64, 12)
        }
        v => return Err(bad("npy", format!("unsupported .npy version {v}"))),
    };
    if header_len > 65_536 || header_len > len {
        return Err(bad("npy", format!(".npy header of {header_len} bytes is longer than the file or 64 KiB")));
    }
    let mut h = vec![0u8; header_len as usize];
    f.read_exact(&mut h).map_err(|_| bad("npy", "truncated .npy header".into()))?;
    let h = String::from_utf8_lossy(&h);
    let value_of = |key: &str| -> Option<String> {
        let i = h.find(&format!("'{key}'"))? + key.len() + 2;
        let rest = h[i..].trim_start().strip_prefix(':')?.trim_start();
        let end = if rest.starts_with('(') { rest.find(')')? + 1 } else { rest.find([',', '}'])? };
        Some(rest[..end].trim().to_string())
    };
    let descr = value_of("descr").unwrap_or_default();
    if !matches!(descr.trim_matches(['\'', '"']), "<f4" | "=f4" | "f4") {
        return Err(bad("descr", format!(".npy dtype {descr}: depth must be float32 metres ('<f4')")));
    }
    if value_of("fortran_order").as_deref() != Some("False") {
        return Err(bad("fortran_order", ".npy must be in C order (fortran_order False)".into()));
    }
    let shape = value_of("shape").unwrap_or_default();
    let dims: Vec<u64> = shape.trim_matches(['(', ')']).split(',').filter_map(|s| s.trim().parse().ok()).collect();
    let [rows, cols] = dims[..] else {
        return Err(bad("shape", format!(".npy shape {shape}: expected 2-D (height, width)")));
    };
    let (w, hgt) = (u32::try_from(cols).unwrap_or(u32::MAX), u32::try_from(rows).unwrap_or(u32::MAX));
    recon_core::util::check_image_dims(part, w, hgt).map_err(|e| ApiError::new(input_status(&e), e.to_string()).at(part, "shape"))?;
    let n = (rows * cols) as usize;
    let data_len = len.saturating_sub(prefix + header_len);
    if data_len != n as u64 * 4 {
        return Err(bad("shape", format!(".npy shape {shape} needs {} data bytes, the file has {data_len}", n * 4)));
    }
    let mut bytes = vec![0u8; n * 4];
    f.read_exact(&mut bytes).map_err(|_| bad("shape", "truncated .npy data".into()))?;
    let d = bytes.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    Ok((cols as usize, rows as usize, d))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_names_are_made_safe() {
        assert_eq!(safe_filename("../../etc/passwd").as_deref(), Some("passwd"));
        assert_eq!(safe_filename("C:\\x\\cup mask.png").as_deref(), Some("cupmask.png"));
        assert_eq!(safe_filename("..."), None);
        assert_eq!(safe_filename(".hidden").as_deref(), Some("hidden"));
    }

    #[test]
    fn options_merge_over_the_defaults_and_name_unknown_ones() {
        let d = InferOptions { samples: 3, ..Default::default() };
        let v = merge_options(&d, Some(br#"{"seed": 7}"#)).unwrap();
        assert_eq!((v["seed"].as_u64(), v["samples"].as_u64()), (Some(7), Some(3)));
        let e = merge_options(&d, Some(br#"{"sample": 2}"#)).unwrap_err();
        assert_eq!((e.part.as_deref(), e.field.as_deref()), (Some("options"), Some("sample")));
        assert!(e.message.contains("unknown option `sample`"), "{e}");
        let e = merge_options(&d, Some(br#"{"min_component_area": 2}"#)).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("min_component_area"));
        assert!(merge_options(&d, Some(b"[1]")).is_err());
        assert!(merge_options(&d, Some(b"{")).is_err());
        // RecGen's preprocessing knobs are options like the others.
        let v = merge_options(&d, Some(br#"{"clamp_range": [-1, 2], "use_pointmap": false, "mask_erosion_iterations": 0}"#)).unwrap();
        let o = InferOptions::from_json(v).unwrap();
        assert_eq!((o.clamp_range.low, o.clamp_range.high, o.use_pointmap, o.mask_erosion_iterations), (-1.0, 2.0, false, 0));
        let e = merge_options(&d, Some(br#"{"mask_erosion_kernel_size": 0}"#)).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("mask_erosion_kernel_size"));
        let e = merge_options(&d, Some(br#"{"clamp_range": [3, -2]}"#)).unwrap_err();
        assert_eq!(e.field.as_deref(), Some("clamp_range"));
    }

    #[test]
    fn objects_and_intrinsics_text() {
        assert_eq!(parse_objects(b"1, 2,3").unwrap(), vec![1, 2, 3]);
        assert_eq!(parse_objects(b"[4]").unwrap(), vec![4]);
        assert!(parse_objects(b"a").is_err());
        let (j, bad) = intrinsics_json(b"500,500,320,240", "intrinsics").unwrap();
        assert!(bad.is_none());
        assert_eq!(serde_json::from_slice::<serde_json::Value>(&j).unwrap()["fx"], 500.0);
        let e = intrinsics_json(b"-5,500,320,240", "intrinsics").unwrap_err();
        assert_eq!(e.field.as_deref(), Some("fx"));
        let e = intrinsics_json(b"500,NaN,320,240", "intrinsics2").unwrap_err();
        assert_eq!((e.part.as_deref(), e.field.as_deref()), (Some("intrinsics2"), Some("fy")));
        assert!(e.message.starts_with("intrinsics2: bad intrinsics"), "{e}");
        assert_eq!(intrinsics_json(br#"{"fx": 1, "fy": -1, "cx": 0, "cy": 0}"#, "intrinsics").unwrap().1, Some("fy"));
        assert!(intrinsics_json(b"nonsense", "intrinsics").is_err());
    }

    #[test]
    fn npy_depth_is_read_with_its_shape_checked() {
        let d = recon_testkit::tmp("serve-npy");
        let write = |name: &str, descr: &str, shape: &str, data: &[u8]| {
            let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
            while (10 + h.len() + 1) % 64 != 0 {
                h.push(' ');
            }
            h.push('\n');
            let mut b = b"\x93NUMPY\x01\x00".to_vec();
            b.extend((h.len() as u16).to_le_bytes());
            b.extend(h.as_bytes());
            b.extend(data);
            let p = d.join(name);
            std::fs::write(&p, b).unwrap();
            p
        };
        let vals: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let (w, h, v) = read_npy_f32(&write("a.npy", "<f4", "(2, 3)", &vals), "depth").unwrap();
        assert_eq!((w, h, v[5]), (3, 2, 6.0));
        let e = read_npy_f32(&write("b.npy", "<f8", "(2, 3)", &vals), "depth").unwrap_err();
        assert_eq!(e.field.as_deref(), Some("descr"));
        let e = read_npy_f32(&write("c.npy", "<f4", "(100000, 100000)", &vals), "depth").unwrap_err();
        assert_eq!((e.status.as_u16(), e.field.as_deref()), (413, Some("shape")));
        let e = read_npy_f32(&write("d.npy", "<f4", "(3, 3)", &vals), "depth").unwrap_err();
        assert!(e.message.contains("36 data bytes"), "{e}");
        let _ = std::fs::remove_dir_all(&d);
    }
}
