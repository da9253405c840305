//! A view besides the anchor, described by a small JSON file: `recon infer
//! --view FILE` (repeatable), Python's `views=[…]` and the `views` column of
//! `recon_rgbd.ray`'s frame tables.
//!
//! ```json
//! {"rgb": "000005-color.png", "masks": "000005-label.png",
//!  "depth": "000005-depth.png", "intrinsics": [1066.778, 1067.487, 312.987, 241.311],
//!  "depth_scale": 0.0001,
//!  "T_c1_ci": [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}
//! ```
//!
//! - `rgb` (required): the colour image; depth and intrinsics are found beside
//!   it as for `--rgbd` unless given;
//! - `masks` (required): an instance-id PNG, or a list of binary mask files;
//! - `depth`: the depth image; `depth_scale`: metres per depth unit;
//! - `intrinsics`: `[fx, fy, cx, cy]`, a 3×3 K (rows or 9 numbers), the text
//!   `"fx,fy,cx,cy"`, or an intrinsics file;
//! - `T_c1_ci` (required): this camera → the anchor camera
//!   (`x₁ = R·xᵢ + t`, metres), 4×4 rows or 16 numbers, row-major.
//!
//! Relative paths are resolved against the folder of the JSON file (or the
//! base folder the caller gives). Unknown keys are errors, and every error
//! names the view (`--view 3 (v3.json)`) and the field.

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::dataset::frame::{FrameOptions, Intrinsics, RgbdFrame};
use crate::dataset::masks::{load_masks, MaskSkip, ObjectMask};
use crate::geometry::camera_pose::rel_pose_from_numbers;
use crate::math::Similarity;
use crate::{Error, Result};

/// The keys of a view file.
pub const VIEW_KEYS: [&str; 6] = ["rgb", "masks", "depth", "intrinsics", "depth_scale", "T_c1_ci"];

/// Largest view file read: a few paths and numbers.
const MAX_VIEW_FILE_BYTES: u64 = 1 << 20;

/// One view besides the anchor, read from its JSON description (module docs).
#[derive(Debug, Clone)]
pub struct ViewSpec {
    /// What errors name: `--view 3 (path/v3.json)`.
    pub label: String,
    /// The colour image.
    pub rgb: PathBuf,
    /// The masks: one instance-id PNG or several binary masks.
    pub masks: Vec<PathBuf>,
    /// Depth, intrinsics and depth scale, as `--rgbd`'s flags give them.
    pub frame: FrameOptions,
    /// This camera → the anchor camera (rigid, metres).
    pub t_c1_ci: Similarity,
}

/// A view opened: its frame, its masks and the masks that could not be read.
pub struct OpenedView {
    /// The RGB-D frame.
    pub frame: RgbdFrame,
    /// The object masks.
    pub objects: Vec<ObjectMask>,
    /// Masks left out (unreadable or empty), to be listed, not fatal.
    pub skipped: Vec<MaskSkip>,
    /// This camera → the anchor camera.
    pub t_c1_ci: Similarity,
}

impl ViewSpec {
    /// Read a view file; relative paths in it are taken from its folder.
    /// `label` names the view in errors (`--view 3`).
    pub fn from_file(path: &Path, label: &str) -> Result<Self> {
        let label = format!("{label} ({})", path.display());
        let len = std::fs::metadata(path).map_err(|e| Error::input(&label, format!("cannot read the view file: {e}")))?.len();
        if len > MAX_VIEW_FILE_BYTES {
            return Err(Error::too_large(
                &label,
                "view file",
                len as u128,
                MAX_VIEW_FILE_BYTES as u128,
                "bytes",
                "a view file holds a few paths and numbers",
            ));
        }
        let text = std::fs::read_to_string(path).map_err(|e| Error::input(&label, format!("cannot read the view file: {e}")))?;
        let v: Value = serde_json::from_str(&text).map_err(|e| Error::input(&label, format!("not valid JSON: {e}")))?;
        let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        Self::from_json(&v, &base, &label)
    }

    /// A view from its JSON object; relative paths are joined to `base`.
    pub fn from_json(v: &Value, base: &Path, label: &str) -> Result<Self> {
        let bad = |field: &str, msg: String| Error::input(label, format!("`{field}`: {msg}"));
        let m =
            v.as_object().ok_or_else(|| Error::input(label, format!("a view must be a JSON object with keys {}", VIEW_KEYS.join(", "))))?;
        if let Some(k) = m.keys().find(|k| !VIEW_KEYS.contains(&k.as_str())) {
            return Err(bad(k, format!("unknown key; a view has {}", VIEW_KEYS.join(", "))));
        }
        let path = |field: &str, v: &Value| -> Result<PathBuf> {
            let s = v.as_str().filter(|s| !s.is_empty()).ok_or_else(|| bad(field, "expected a file path".to_string()))?;
            Ok(base.join(s))
        };
        let rgb = path("rgb", m.get("rgb").ok_or_else(|| bad("rgb", "missing: the colour image".to_string()))?)?;
        let masks = match m.get("masks") {
            None => return Err(bad("masks", "missing: an instance-id PNG or a list of binary masks".to_string())),
            Some(Value::Array(a)) if !a.is_empty() => a.iter().map(|x| path("masks", x)).collect::<Result<Vec<_>>>()?,
            Some(x) => vec![path("masks", x)?],
        };
        let mut frame = FrameOptions::default();
        if let Some(d) = m.get("depth").filter(|d| !d.is_null()) {
            frame.depth = Some(path("depth", d)?);
        }
        if let Some(s) = m.get("depth_scale").filter(|d| !d.is_null()) {
            let s = s
                .as_f64()
                .filter(|s| s.is_finite() && *s > 0.0)
                .ok_or_else(|| bad("depth_scale", format!("expected positive metres per depth unit, got {s}")))?;
            frame.depth_scale_m = Some(s);
        }
        match m.get("intrinsics") {
            None | Some(Value::Null) => {}
            Some(Value::String(s)) => {
                let nums: Vec<f64> = s.split(',').filter_map(|x| x.trim().parse().ok()).collect();
                if nums.len() == 4 && s.split(',').count() == 4 {
                    frame.intrinsics =
                        Some(Intrinsics::new(nums[0], nums[1], nums[2], nums[3]).map_err(|e| bad("intrinsics", e.to_string()))?);
                } else {
                    frame.intrinsics_file = Some(base.join(s));
                }
            }
            Some(k) => {
                let nums = numbers(k).ok_or_else(|| bad("intrinsics", "expected [fx, fy, cx, cy], a 3×3 K or a file".to_string()))?;
                frame.intrinsics = Some(
                    match nums.len() {
                        4 => Intrinsics::new(nums[0], nums[1], nums[2], nums[3]),
                        9 => Intrinsics::from_k_row_major(&nums, label),
                        n => return Err(bad("intrinsics", format!("expected [fx, fy, cx, cy] or a 3×3 K, got {n} numbers"))),
                    }
                    .map_err(|e| bad("intrinsics", e.to_string()))?,
                );
            }
        }
        let t = m.get("T_c1_ci").ok_or_else(|| bad("T_c1_ci", "missing: this camera → the anchor camera, 4×4".to_string()))?;
        let nums = numbers(t).ok_or_else(|| bad("T_c1_ci", "expected 4×4 rows or 16 numbers".to_string()))?;
        let t_c1_ci = rel_pose_from_numbers(&nums, label, "T_c1_ci")?;
        Ok(ViewSpec { label: label.to_string(), rgb, masks, frame, t_c1_ci })
    }

    /// Read the view's frame and masks (`objects`: the instance ids to keep,
    /// as `--objects`). Errors name the view.
    pub fn open(&self, objects: Option<&[u32]>) -> Result<OpenedView> {
        let frame = RgbdFrame::open(&self.rgb, &self.frame).map_err(|e| Error::input(&self.label, format!("frame: {e}")))?;
        let (objects, skipped) = load_masks(&self.masks, objects).map_err(|e| Error::input(&self.label, format!("`masks`: {e}")))?;
        Ok(OpenedView { frame, objects, skipped, t_c1_ci: self.t_c1_ci })
    }
}

/// Every number of a JSON array, nested or flat (`None` if anything else is in it).
fn numbers(v: &Value) -> Option<Vec<f64>> {
    fn walk(v: &Value, out: &mut Vec<f64>) -> bool {
        match v {
            Value::Array(a) => a.iter().all(|x| walk(x, out)),
            Value::Number(n) => n.as_f64().map(|x| out.push(x)).is_some(),
            _ => false,
        }
    }
    let mut out = Vec::new();
    (v.is_array() && walk(v, &mut out)).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    const ID: [[f64; 4]; 4] = [[1.0, 0.0, 0.0, 0.25], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];

    #[test]
    fn paths_resolve_against_the_base_and_fields_are_checked() {
        let base = Path::new("/data/views");
        let v = ViewSpec::from_json(
            &json!({"rgb": "a.png", "masks": ["m1.png", "/abs/m2.png"], "depth": "d.png", "intrinsics": "500,500,320,240",
                    "depth_scale": 0.001, "T_c1_ci": ID}),
            base,
            "--view 2",
        )
        .unwrap();
        assert_eq!(v.rgb, base.join("a.png"));
        assert_eq!(v.masks, vec![base.join("m1.png"), PathBuf::from("/abs/m2.png")]);
        assert_eq!(v.frame.depth, Some(base.join("d.png")));
        assert_eq!(v.frame.intrinsics, Some(Intrinsics::new(500.0, 500.0, 320.0, 240.0).unwrap()));
        assert_eq!(v.frame.depth_scale_m, Some(0.001));
        assert_eq!(v.t_c1_ci.translation[0], 0.25);
        // A K as rows, T as 16 numbers, an intrinsics file.
        let flat: Vec<f64> = ID.iter().flatten().copied().collect();
        let k = [[600.0, 0.0, 320.0], [0.0, 610.0, 240.0], [0.0, 0.0, 1.0]];
        let v = ViewSpec::from_json(&json!({"rgb": "a.png", "masks": "l.png", "intrinsics": k, "T_c1_ci": flat}), base, "v").unwrap();
        assert_eq!(v.frame.intrinsics.unwrap().fy, 610.0);
        let v =
            ViewSpec::from_json(&json!({"rgb": "a.png", "masks": "l.png", "intrinsics": "cam.json", "T_c1_ci": ID}), base, "v").unwrap();
        assert_eq!(v.frame.intrinsics_file, Some(base.join("cam.json")));

        // Every error names the view and the field.
        let err = |j: Value| ViewSpec::from_json(&j, base, "--view 3").unwrap_err().to_string();
        let e = err(json!({"rgb": "a.png", "masks": "l.png"}));
        assert!(e.contains("--view 3") && e.contains("`T_c1_ci`") && e.contains("missing"), "{e}");
        let e = err(json!({"rgb": "a.png", "masks": "l.png", "T_c1_ci": ID, "T_c1_c2": ID}));
        assert!(e.contains("`T_c1_c2`") && e.contains("unknown key"), "{e}");
        let e = err(json!({"masks": "l.png", "T_c1_ci": ID}));
        assert!(e.contains("`rgb`"), "{e}");
        let e = err(json!({"rgb": "a.png", "masks": "l.png", "T_c1_ci": [1, 2, 3]}));
        assert!(e.contains("--view 3") && e.contains("T_c1_ci needs 16"), "{e}");
        let mut bent = ID;
        bent[0][1] = 0.5;
        let e = err(json!({"rgb": "a.png", "masks": "l.png", "T_c1_ci": bent}));
        assert!(e.contains("T_c1_ci: the 3×3 block is not a rotation"), "{e}");
        let e = err(json!({"rgb": "a.png", "masks": "l.png", "T_c1_ci": ID, "depth_scale": -1}));
        assert!(e.contains("`depth_scale`"), "{e}");
        let e = err(json!({"rgb": "a.png", "masks": "l.png", "T_c1_ci": ID, "intrinsics": [1, 2, 3]}));
        assert!(e.contains("`intrinsics`") && e.contains("3 numbers"), "{e}");
        let e = err(json!(["a.png"]));
        assert!(e.contains("--view 3") && e.contains("JSON object"), "{e}");
    }

    #[test]
    fn a_file_names_itself_in_errors() {
        let dir = crate::util::testing::tmp("view-spec");
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("v2.json");
        std::fs::write(&f, "{not json").unwrap();
        let e = ViewSpec::from_file(&f, "--view 2").unwrap_err().to_string();
        assert!(e.contains("--view 2") && e.contains("v2.json") && e.contains("JSON"), "{e}");
        std::fs::write(&f, json!({"rgb": "c.png", "masks": "l.png", "T_c1_ci": ID}).to_string()).unwrap();
        let v = ViewSpec::from_file(&f, "--view 2").unwrap();
        assert_eq!(v.rgb, dir.join("c.png"));
        // Opening reads the frame: a missing image is named with the view.
        let e = v.open(None).err().unwrap().to_string();
        assert!(e.contains("--view 2") && e.contains("frame"), "{e}");
        let e = ViewSpec::from_file(&dir.join("absent.json"), "--view 4").unwrap_err().to_string();
        assert!(e.contains("--view 4") && e.contains("absent.json"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
