//! A request's inputs: the multipart parts as stored in the job folder ([`Manifest`]),
//! and the frame(s), masks and options read back from them ([`load`]) with the library
//! functions `recon infer` uses, so that the server refuses what the CLI refuses, with
//! the CLI's message, and computes what the CLI computes.

use crate::error::{input_status, ApiError};
use recon_core::dataset::frame::{intrinsics_from_bytes, load_rgb, CameraFormat};
use recon_core::dataset::masks::load_binary_mask;
use recon_core::dataset::{FrameOptions, RgbdFrame};
use recon_core::dataset::{InstanceMap, MaskSkip, ObjectMask, SkipReason};
use recon_core::engine::{InferOptions, RigidTransform, MAX_SECOND_VIEWS};
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

/// The last view number a request takes: the anchor is view 1, and at most
/// [`MAX_SECOND_VIEWS`] (16) views besides it, as `recon infer --view` takes them.
pub const MAX_VIEW: usize = 1 + MAX_SECOND_VIEWS;

/// The parts of a view besides the anchor, by kind: view N's are `rgbN`, `depthN`,
/// `masksN`, `intrinsicsN` and `T_c1_cN` (view 2's are [`PARTS`]' `rgb2` … `T_c1_c2`);
/// any of them given makes all five required. What each holds (`{N}`: the view's number).
pub const VIEW_PART_KINDS: [(&str, &str); 5] = [
    ("rgb", "colour image"),
    ("depth", "depth"),
    ("masks", "masks, matched to masks by instance id (or by order for binary masks)"),
    ("intrinsics", "intrinsics"),
    ("T_c1_c", "camera {N} → camera 1 rigid transform, 4×4 row-major (JSON rows, 16 numbers, or {\"T_c1_c{N}\": rows})"),
];

/// The five parts of view `k` (2 …= [`MAX_VIEW`]), in [`VIEW_PART_KINDS`]' order.
pub fn view_parts(k: usize) -> [String; 5] {
    VIEW_PART_KINDS.map(|(kind, _)| format!("{kind}{k}"))
}

/// A part name of a view besides the anchor: its kind (index into [`VIEW_PART_KINDS`])
/// and its view number, 2 or more (`usize::MAX` when too long to read; beyond
/// [`MAX_VIEW`] it is refused by [`check_part_name`]). `rgb`, `rgb1`, `rgb02` are not.
pub fn view_part(name: &str) -> Option<(usize, usize)> {
    VIEW_PART_KINDS.iter().enumerate().find_map(|(i, (kind, _))| {
        let digits = name.strip_prefix(kind)?;
        if digits.is_empty() || digits.starts_with('0') || !digits.bytes().all(|b| b.is_ascii_digit()) {
            return None;
        }
        let k = digits.parse::<usize>().unwrap_or(usize::MAX);
        (k >= 2).then_some((i, k))
    })
}

/// What a part holds, for messages: [`PARTS`]' text, or `view N: …` for views 3 and on.
pub fn part_description(name: &str) -> Option<String> {
    if let Some(p) = PARTS.iter().find(|p| p.0 == name) {
        return Some(p.2.to_string());
    }
    let (kind, k) = view_part(name).filter(|(_, k)| *k <= MAX_VIEW)?;
    Some(format!("view {k}: {}", VIEW_PART_KINDS[kind].1.replace("{N}", &k.to_string())))
}

/// Every part a request may carry, as [`PARTS`] lists them (name, required, what it
/// holds), then views 3 to [`MAX_VIEW`]'s: the OpenAPI document's list.
pub fn all_parts() -> Vec<(String, bool, String)> {
    let mut v: Vec<(String, bool, String)> = PARTS.iter().map(|(n, r, w)| (n.to_string(), *r, w.to_string())).collect();
    for k in 3..=MAX_VIEW {
        v.extend(view_parts(k).into_iter().map(|n| {
            let what = part_description(&n).unwrap_or_default();
            (n, false, what)
        }));
    }
    v
}

/// Refuses a part name the request cannot carry: a `400` naming it, with the names
/// there are (the `…N` forms, not every view's), or the view limit for `rgb18` and on.
pub fn check_part_name(name: &str) -> Result<(), ApiError> {
    if PARTS.iter().any(|p| p.0 == name) {
        return Ok(());
    }
    match view_part(name) {
        Some((_, k)) if k <= MAX_VIEW => Ok(()),
        Some(_) => Err(ApiError::bad(
            name,
            "name",
            format!(
                "part `{name}`: views besides the anchor are numbered 2 to {MAX_VIEW}; a request takes at most \
                 {MAX_SECOND_VIEWS} views besides the anchor"
            ),
        )),
        None => {
            let names: Vec<&str> = PARTS.iter().map(|p| p.0).filter(|n| view_part(n).is_none()).collect();
            let kinds: Vec<String> = VIEW_PART_KINDS.iter().map(|(k, _)| format!("{k}N")).collect();
            Err(ApiError::bad(
                name,
                "name",
                format!(
                    "unknown part `{name}`; the parts are {}, and for each view N = 2 to {MAX_VIEW} besides the anchor {}",
                    names.join(", "),
                    kinds.join(", ")
                ),
            ))
        }
    }
}

/// Largest small part (intrinsics, options, objects, T_c1_c2, and views 3 and on's), bytes.
pub const MAX_SMALL_PART_BYTES: u64 = 1 << 20;

/// Whether `name` is a small part (held in memory, parsed as text).
pub fn is_small_part(name: &str) -> bool {
    matches!(name, "intrinsics" | "options" | "objects") || matches!(view_part(name), Some((3 | 4, k)) if k <= MAX_VIEW)
}

/// Whether `name` may be given more than once (binary masks).
pub fn is_repeatable(name: &str) -> bool {
    name == "masks" || matches!(view_part(name), Some((2, k)) if k <= MAX_VIEW)
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
    /// Objects left out before the engine (ids asked for that are absent, …), the other
    /// views' relabelled `view N …` as the CLI does.
    pub skipped: Vec<MaskSkip>,
    /// The views besides the anchor, view 2 first.
    pub views: Vec<OtherView>,
    /// The options, checked.
    pub options: InferOptions,
}

/// A view besides the anchor, read from its parts (`rgbN`, …, `T_c1_cN`).
pub struct OtherView {
    /// Its number N: 2, 3, …
    pub number: usize,
    /// Its frame.
    pub frame: RgbdFrame,
    /// Its masks (paired with view 1's by the engine).
    pub objects: Vec<ObjectMask>,
    /// Camera N → camera 1.
    pub t_c1_ci: RigidTransform,
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
        let what = part_description(name).unwrap_or_default();
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

/// Reads one view (`suffix` "" for the anchor, else its number) of the stored parts.
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

/// A view's `T_c1_cN` part, checked as the CLI's `--rel-pose` and `--view`'s `T_c1_ci`
/// are (16 finite numbers, last row 0 0 0 1, an orthonormal rotation with determinant 1):
/// JSON rows or numbers, `{"T_c1_cN": rows}`, or 16 numbers as text.
fn load_rel_pose(dir: &Path, m: &Manifest, name: &str) -> Result<RigidTransform, ApiError> {
    let p = required(dir, m, name)?;
    let raw = std::fs::read(&p.path).map_err(|e| ApiError::unavailable(format!("reading the stored {name}: {e}")))?;
    let text = String::from_utf8_lossy(&raw);
    let t = text.trim();
    let nums: Vec<f64> = if t.starts_with('{') || t.starts_with('[') {
        let v: serde_json::Value =
            serde_json::from_str(t).map_err(|e| ApiError::bad(name, "json", format!("{name}: invalid JSON: {e}")))?;
        let v = v.get(name).cloned().unwrap_or(v);
        fn walk(v: &serde_json::Value, out: &mut Vec<f64>) -> bool {
            match v {
                serde_json::Value::Array(a) => a.iter().all(|x| walk(x, out)),
                serde_json::Value::Number(n) => n.as_f64().map(|x| out.push(x)).is_some(),
                _ => false,
            }
        }
        let mut nums = Vec::new();
        if !walk(&v, &mut nums) {
            // The message `recon infer --rel-pose FILE` gives.
            let e = recon_core::Error::config(name, name, "must hold only numbers (4×4 rows or 16 numbers)");
            return Err(ApiError::new(input_status(&e), e.to_string()).at(name, name));
        }
        nums
    } else {
        t.split(|c: char| c == ',' || c.is_whitespace())
            .filter(|s| !s.is_empty())
            .map(str::parse)
            .collect::<Result<_, _>>()
            .map_err(|_| ApiError::bad(name, name, format!("{name}: `{t}` is not 16 numbers (4×4 row-major)")))?
    };
    recon_core::geometry::rel_pose_from_numbers(&nums, name, name)
        .map_err(|e| ApiError::new(input_status(&e), e.to_string()).at(name, name))
}

/// The number of views besides the anchor a request gives, checked: numbered 2, 3, …
/// without a gap, each with all five of its parts.
fn count_views(m: &Manifest) -> Result<usize, ApiError> {
    let Some(last) = m.parts.keys().filter_map(|n| view_part(n)).map(|(_, k)| k).max() else { return Ok(0) };
    for k in 2..=last {
        let names = view_parts(k);
        let given: Vec<&str> = names.iter().map(String::as_str).filter(|p| m.parts.contains_key(*p)).collect();
        let list = format!("{} and {}", names[..4].join(", "), names[4]);
        if given.is_empty() {
            let missing = &names[0];
            return Err(ApiError::bad(
                missing,
                missing,
                format!(
                    "missing part `{missing}`: view {last} is given, and the views besides the anchor are numbered from 2 \
                     without a gap; view {k} needs {list}"
                ),
            ));
        }
        if let Some(missing) = names.iter().find(|p| !given.contains(&p.as_str())) {
            let what = if k == 2 { "a second view".to_string() } else { format!("view {k}") };
            return Err(ApiError::bad(
                missing,
                missing,
                format!("missing part `{missing}`: {what} needs {list} (given: {})", given.join(", ")),
            ));
        }
    }
    Ok(last - 1)
}

/// Reads and checks everything a job runs on from its folder `dir`. `max_views` is the
/// loaded model's (a second view needs 2; more views than it takes run as fused pairs).
/// Called when the request arrives (nothing is queued that fails here) and again by the
/// worker.
pub fn load(dir: &Path, m: &Manifest, max_views: usize) -> Result<Loaded, ApiError> {
    for (name, req, what) in PARTS {
        if *req && !m.parts.contains_key(*name) {
            return Err(ApiError::bad(name, name, format!("missing part `{name}` ({what})")));
        }
    }
    for name in m.parts.keys() {
        check_part_name(name)?;
    }
    let options = InferOptions::from_json(m.options.clone()).map_err(|e| option_error(&e))?;
    let frame = load_frame(dir, m, "")?;
    let (objects, mut skipped) = load_view_masks(dir, m, "masks", &frame)?;
    // `recon infer`'s rule: more objects that pass the mask checks than max_objects is refused.
    let settings = options.settings().map_err(|e| option_error(&e))?;
    recon_core::engine::check_object_count(&frame, &objects, &settings, "masks")
        .map_err(|e| ApiError::new(crate::error::input_status(&e), e.to_string()).at("masks", "max_objects"))?;
    let others = count_views(m)?;
    if others > 0 && max_views < 2 {
        return Err(ApiError::bad(
            "rgb2",
            "rgb2",
            format!("this model takes {max_views} view(s); a second view needs a two-view (num_pose_tokens 2) model"),
        ));
    }
    let mut views = Vec::with_capacity(others);
    for k in 2..2 + others {
        let [_, _, masks, _, pose] = view_parts(k);
        let frame_k = load_frame(dir, m, &k.to_string())?;
        let (objects_k, skipped_k) = load_view_masks(dir, m, &masks, &frame_k)?;
        let t_c1_ci = load_rel_pose(dir, m, &pose)?;
        // The engine pairs the views' objects; a count mismatch of binary masks is the request's fault.
        recon_core::engine::match_view(&objects, objects_k.clone(), k).map_err(|e| {
            let msg = match e {
                recon_core::Error::Input { msg, .. } => msg,
                e => e.to_string(),
            };
            ApiError::bad(&masks, &masks, format!("{masks}: {msg}"))
        })?;
        // As `recon infer`: another view's masks that are not there are listed, and cost that view only.
        skipped.extend(skipped_k.into_iter().map(|mut s| {
            s.label = format!("view {k} {}", s.label);
            s
        }));
        views.push(OtherView { number: k, frame: frame_k, objects: objects_k, t_c1_ci });
    }
    Ok(Loaded { frame, objects, skipped, views, options })
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
    fn view_parts_are_named_by_number_up_to_the_limit() {
        assert_eq!(view_part("rgb3"), Some((0, 3)));
        assert_eq!(view_part("masks2"), Some((2, 2)));
        assert_eq!(view_part("T_c1_c17"), Some((4, 17)));
        for n in ["rgb", "rgb1", "rgb0", "rgb03", "rgbx", "rgb3a", "depth_scale2", "T_c1_c", "options2"] {
            assert_eq!(view_part(n), None, "{n}");
        }
        assert!(check_part_name("intrinsics17").is_ok() && check_part_name("T_c1_c2").is_ok() && check_part_name("objects").is_ok());
        for n in ["depth18", "rgb99999999999999999999999"] {
            let e = check_part_name(n).unwrap_err();
            assert_eq!((e.status.as_u16(), e.part.as_deref(), e.field.as_deref()), (400, Some(n), Some("name")));
            assert!(e.message.contains("numbered 2 to 17") && e.message.contains("at most 16 views besides the anchor"), "{e}");
        }
        let e = check_part_name("colour").unwrap_err();
        assert!(e.message.starts_with("unknown part `colour`; the parts are rgb, depth, masks, intrinsics, options, objects,"), "{e}");
        assert!(e.message.contains("rgbN, depthN, masksN, intrinsicsN, T_c1_cN") && !e.message.contains("rgb5"), "{e}");
        assert!(check_part_name("rgb1").is_err());
        assert!(is_small_part("intrinsics5") && is_small_part("T_c1_c9") && is_small_part("T_c1_c2") && is_small_part("options"));
        assert!(!is_small_part("rgb5") && !is_small_part("masks3") && !is_small_part("T_c1_c18"));
        assert!(is_repeatable("masks") && is_repeatable("masks2") && is_repeatable("masks17"));
        assert!(!is_repeatable("masks18") && !is_repeatable("rgb3"));
        // The OpenAPI list: the table, then views 3 to 17.
        let all = all_parts();
        assert_eq!(all.len(), PARTS.len() + 15 * 5);
        let t3 = all.iter().find(|p| p.0 == "T_c1_c3").unwrap();
        assert!(!t3.1 && t3.2.starts_with("view 3: camera 3 → camera 1") && t3.2.contains(r#"{"T_c1_c3": rows}"#), "{t3:?}");
        assert_eq!(part_description("rgb2").as_deref(), Some("second view: colour image"));
        assert_eq!(part_description("rgb18"), None);
    }

    #[test]
    fn views_are_numbered_without_a_gap_and_given_whole() {
        let stored = StoredPart { file: "x".into(), filename: None, bytes: 1 };
        let with = |views: &[usize], without: &[&str]| {
            let mut m = Manifest::default();
            for &k in views {
                for n in view_parts(k) {
                    if !without.contains(&n.as_str()) {
                        m.parts.insert(n, vec![stored.clone()]);
                    }
                }
            }
            count_views(&m)
        };
        assert_eq!(with(&[], &[]).unwrap(), 0);
        assert_eq!(with(&[2, 3, 4], &[]).unwrap(), 3);
        let e = with(&[2, 4], &[]).unwrap_err();
        assert_eq!((e.part.as_deref(), e.field.as_deref()), (Some("rgb3"), Some("rgb3")));
        assert!(
            e.message.contains("view 4 is given") && e.message.contains("view 3 needs rgb3, depth3, masks3, intrinsics3 and T_c1_c3"),
            "{e}"
        );
        let e = with(&[3], &[]).unwrap_err();
        assert_eq!(e.part.as_deref(), Some("rgb2"));
        let e = with(&[2, 3], &["masks3"]).unwrap_err();
        assert_eq!((e.part.as_deref(), e.field.as_deref()), (Some("masks3"), Some("masks3")));
        assert!(
            e.message.contains("view 3 needs rgb3, depth3, masks3, intrinsics3 and T_c1_c3 (given: rgb3, depth3, intrinsics3, T_c1_c3)"),
            "{e}"
        );
        // View 2 keeps its message.
        let e = with(&[2], &["depth2"]).unwrap_err();
        assert!(e.message.starts_with("missing part `depth2`: a second view needs rgb2, depth2, masks2, intrinsics2 and T_c1_c2"), "{e}");
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
