//! Ground-truth datasets for evaluation: BOP format and the YCB-Video (PoseCNN) layout.
//!
//! Everything is converted to **metres** on load (BOP stores mm). Poses map model to
//! camera: `X_cam = R · X_model + t`.

use crate::dataset::matv5::MatFile;
use crate::dataset::ply::read_ply;
use crate::mesh::trimesh::{diameter, DiameterMethod, TriMesh};
use crate::spatial::P3;
use crate::{Error, Result};
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// An object model in metres.
#[derive(Debug, Clone)]
pub struct Model {
    /// Model name (file stem or YCB-Video folder name).
    pub name: String,
    /// File it was read from.
    pub path: PathBuf,
    /// Mesh, or a point cloud (no faces) for YCB-Video `points.xyz`.
    pub mesh: TriMesh,
    /// Largest distance between two model points, metres.
    pub diameter: f64,
    /// `"models_info.json"` when taken from the dataset, else how it was computed.
    pub diameter_source: String,
}

/// One annotated object instance in a frame.
#[derive(Debug, Clone)]
pub struct GtInstance {
    /// Object (model) id.
    pub obj_id: u32,
    /// Model → camera rotation, row-major.
    pub r: [[f64; 3]; 3],
    /// Metres.
    pub t: P3,
    /// Fraction of the object's projected silhouette that is visible, if the dataset says
    /// (or, with `visib_estimated`, as estimated by [`crate::dataset::visible_fraction`]).
    pub visib_fract: Option<f64>,
    /// `visib_fract` is our estimate, not the dataset's annotation (YCB-Video).
    pub visib_estimated: bool,
    /// Visible 2D box `[x, y, w, h]` in pixels, if known.
    pub bbox_visib: Option<[f64; 4]>,
}

#[derive(Debug, Clone)]
/// One annotated frame of a dataset.
pub struct Frame {
    /// Scene (BOP) or sequence (YCB-Video) folder name.
    pub scene: String,
    /// Frame (image) id within the scene.
    pub frame: u32,
    /// Pinhole intrinsics in pixels.
    pub k: [[f64; 3]; 3],
    /// Metres per raw depth unit: BOP's `depth_scale` (millimetres per unit) / 1000;
    /// YCB-Video: 1 / factor_depth. Metres end to end, as `RgbdFrame::depth_scale_m`.
    pub depth_scale_m: f64,
    /// Annotated object instances, in annotation order.
    pub gt: Vec<GtInstance>,
    /// World → camera (`x_cam = R·x_w + t`, metres) when the dataset gives it
    /// (BOP `cam_R_w2c` / `cam_t_w2c`): relates frames of a scene.
    pub cam_w2c: Option<([[f64; 3]; 3], [f64; 3])>,
}

/// On-disk layout a [`Dataset`] was read from (decides where its images are).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Layout {
    /// `<split>/<scene>/{depth,mask_visib}/…` ([`load_bop`]); `root` is the split folder.
    #[default]
    Bop,
    /// `<root>/<seq>/NNNNNN-{depth,label}.png` ([`load_ycbv`]).
    Ycbv,
}

#[derive(Debug, Clone, Default)]
/// A loaded ground-truth dataset: models (metres) and annotated frames.
pub struct Dataset {
    /// Root folder it was loaded from.
    pub root: PathBuf,
    /// BOP or YCB-Video layout.
    pub layout: Layout,
    /// Object models by id.
    pub models: BTreeMap<u32, Model>,
    /// Annotated frames, in load order.
    pub frames: Vec<Frame>,
}

impl Dataset {
    /// The frame `frame` of scene `scene`.
    pub fn frame(&self, scene: &str, frame: u32) -> Option<&Frame> {
        self.frames.iter().find(|f| f.scene == scene && f.frame == frame)
    }

    /// Keeps only the frames of the named scenes. A name matches a scene folder exactly or,
    /// when both are integers, by value (`48` selects `000048`). Unknown names are an error.
    pub fn retain_scenes(&mut self, names: &[String]) -> Result<()> {
        let same = |a: &str, b: &str| a == b || matches!((a.parse::<u64>(), b.parse::<u64>()), (Ok(x), Ok(y)) if x == y);
        if let Some(bad) = names.iter().find(|n| !self.frames.iter().any(|f| same(&f.scene, n))) {
            let mut have: Vec<&str> = self.frames.iter().map(|f| f.scene.as_str()).collect();
            have.dedup();
            return Err(Error::input(self.root.display().to_string(), format!("no scene `{bad}` (scenes: {})", have.join(", "))));
        }
        self.frames.retain(|f| names.iter().any(|n| same(&f.scene, n)));
        Ok(())
    }

    /// Colour image of a frame (BOP `rgb/NNNNNN.png` or `.jpg`, YCB-Video `NNNNNN-color.png`).
    pub fn rgb_path(&self, f: &Frame) -> PathBuf {
        match self.layout {
            Layout::Bop => {
                let dir = self.root.join(&f.scene).join("rgb");
                let png = dir.join(format!("{:06}.png", f.frame));
                if png.is_file() {
                    png
                } else {
                    dir.join(format!("{:06}.jpg", f.frame))
                }
            }
            Layout::Ycbv => self.root.join(&f.scene).join(format!("{:06}-color.png", f.frame)),
        }
    }

    /// Depth image of a frame (16-bit PNG; raw value × `depth_scale_m` = metres).
    pub fn depth_path(&self, f: &Frame) -> PathBuf {
        match self.layout {
            Layout::Bop => self.root.join(&f.scene).join("depth").join(format!("{:06}.png", f.frame)),
            Layout::Ycbv => self.root.join(&f.scene).join(format!("{:06}-depth.png", f.frame)),
        }
    }

    /// Where the visible mask of GT instance `gt_index` of frame `f` is: a BOP
    /// `mask_visib/NNNNNN_GGGGGG.png` (non-zero = visible), or the YCB-Video label map
    /// (`NNNNNN-label.png`, visible pixels hold the class index = `obj_id`).
    pub fn visible_mask_source(&self, f: &Frame, gt_index: usize) -> MaskSource {
        match self.layout {
            Layout::Bop => {
                MaskSource::Binary(self.root.join(&f.scene).join("mask_visib").join(format!("{:06}_{gt_index:06}.png", f.frame)))
            }
            Layout::Ycbv => MaskSource::Label(self.root.join(&f.scene).join(format!("{:06}-label.png", f.frame)), f.gt[gt_index].obj_id),
        }
    }
}

/// A visible-mask file: a binary mask, or a label map and the value that marks the object.
#[derive(Debug, Clone, PartialEq)]
pub enum MaskSource {
    /// A binary mask PNG (non-zero = object).
    Binary(PathBuf),
    /// A label map PNG and the value marking the object.
    Label(PathBuf, u32),
}

fn read_json(path: &Path) -> Result<Value> {
    let s = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    serde_json::from_str(&s).map_err(|e| Error::Json { path: path.to_path_buf(), source: e })
}

fn field<'a>(v: &'a Value, key: &str, file: &Path, ctx: &str) -> Result<&'a Value> {
    v.get(key).ok_or_else(|| Error::config(file.display().to_string(), format!("{ctx}.{key}"), "missing"))
}

fn nums<const N: usize>(v: &Value, file: &Path, ctx: &str) -> Result<[f64; N]> {
    let bad = || Error::config(file.display().to_string(), ctx, format!("expected an array of {N} finite numbers"));
    let a = v.as_array().ok_or_else(bad)?;
    if a.len() != N {
        return Err(bad());
    }
    let mut o = [0.0; N];
    for (i, x) in a.iter().enumerate() {
        o[i] = x.as_f64().filter(|f| f.is_finite()).ok_or_else(bad)?;
    }
    Ok(o)
}

fn mat3(a: [f64; 9]) -> [[f64; 3]; 3] {
    [[a[0], a[1], a[2]], [a[3], a[4], a[5]], [a[6], a[7], a[8]]]
}

fn frame_map<'a>(v: &'a Value, file: &Path) -> Result<Vec<(u32, &'a Value)>> {
    let obj = v.as_object().ok_or_else(|| Error::config(file.display().to_string(), "<root>", "expected an object keyed by image id"))?;
    obj.iter()
        .map(|(k, v)| {
            k.parse::<u32>().map(|id| (id, v)).map_err(|_| Error::config(file.display().to_string(), k.as_str(), "key is not an image id"))
        })
        .collect()
}

/// Loads a BOP split directory (`<split>/<scene>/scene_{camera,gt,gt_info}.json`) with its
/// models (`models_dir/models_info.json`, `models_dir/obj_XXXXXX.ply`, both in mm). Only
/// models referenced by the GT are loaded. `scene_gt_info.json` is optional.
pub fn load_bop(split_dir: &Path, models_dir: &Path) -> Result<Dataset> {
    let mut scene_dirs: Vec<PathBuf> = std::fs::read_dir(split_dir)
        .map_err(|e| Error::io(split_dir, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("scene_gt.json").is_file())
        .collect();
    scene_dirs.sort();
    if scene_dirs.is_empty() {
        return Err(Error::input(split_dir.display().to_string(), "no scene directories with scene_gt.json"));
    }
    let mut ds = Dataset { root: split_dir.to_path_buf(), ..Default::default() };
    let mut used = BTreeSet::new();
    for sd in &scene_dirs {
        let scene = sd.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
        let cam_path = sd.join("scene_camera.json");
        let gt_path = sd.join("scene_gt.json");
        let info_path = sd.join("scene_gt_info.json");
        let cam = read_json(&cam_path)?;
        let gt = read_json(&gt_path)?;
        let info = if info_path.is_file() { Some(read_json(&info_path)?) } else { None };
        let mut frames = frame_map(&gt, &gt_path)?;
        frames.sort_by_key(|f| f.0);
        for (im, anns) in frames {
            let key = im.to_string();
            let c = cam
                .get(&key)
                .ok_or_else(|| Error::config(cam_path.display().to_string(), key.as_str(), "image in scene_gt.json has no camera"))?;
            let k = mat3(nums::<9>(field(c, "cam_K", &cam_path, &key)?, &cam_path, &format!("{key}.cam_K"))?);
            let depth_scale_mm = match c.get("depth_scale") {
                Some(v) => {
                    v.as_f64().ok_or_else(|| Error::config(cam_path.display().to_string(), format!("{key}.depth_scale"), "not a number"))?
                }
                None => 1.0,
            };
            let cam_w2c = match (c.get("cam_R_w2c"), c.get("cam_t_w2c")) {
                (Some(r), Some(t)) => {
                    let r = mat3(nums::<9>(r, &cam_path, &format!("{key}.cam_R_w2c"))?);
                    let t = nums::<3>(t, &cam_path, &format!("{key}.cam_t_w2c"))?;
                    Some((r, [t[0] / 1000.0, t[1] / 1000.0, t[2] / 1000.0]))
                }
                _ => None,
            };
            let anns = anns.as_array().ok_or_else(|| Error::config(gt_path.display().to_string(), key.as_str(), "expected a list"))?;
            let infos = info.as_ref().and_then(|i| i.get(&key)).and_then(Value::as_array);
            let mut gts = Vec::new();
            for (i, a) in anns.iter().enumerate() {
                let ctx = format!("{key}[{i}]");
                let r = mat3(nums::<9>(field(a, "cam_R_m2c", &gt_path, &ctx)?, &gt_path, &format!("{ctx}.cam_R_m2c"))?);
                let t = nums::<3>(field(a, "cam_t_m2c", &gt_path, &ctx)?, &gt_path, &format!("{ctx}.cam_t_m2c"))?;
                let obj_id = field(a, "obj_id", &gt_path, &ctx)?
                    .as_u64()
                    .and_then(|x| u32::try_from(x).ok())
                    .ok_or_else(|| Error::config(gt_path.display().to_string(), format!("{ctx}.obj_id"), "not a non-negative integer"))?;
                let inf = infos.and_then(|v| v.get(i));
                let visib_fract = match inf.and_then(|x| x.get("visib_fract")) {
                    Some(v) => Some(v.as_f64().filter(|f| (0.0..=1.0).contains(f)).ok_or_else(|| {
                        Error::config(info_path.display().to_string(), format!("{ctx}.visib_fract"), "not a number in [0, 1]")
                    })?),
                    None => None,
                };
                let bbox_visib = match inf.and_then(|x| x.get("bbox_visib")) {
                    Some(v) => Some(nums::<4>(v, &info_path, &format!("{ctx}.bbox_visib"))?),
                    None => None,
                };
                used.insert(obj_id);
                gts.push(GtInstance {
                    obj_id,
                    r,
                    t: [t[0] / 1000.0, t[1] / 1000.0, t[2] / 1000.0],
                    visib_fract,
                    visib_estimated: false,
                    bbox_visib,
                });
            }
            ds.frames.push(Frame { scene: scene.clone(), frame: im, k, depth_scale_m: depth_scale_mm / 1000.0, gt: gts, cam_w2c });
        }
    }
    let info_path = models_dir.join("models_info.json");
    let info = if info_path.is_file() { Some(read_json(&info_path)?) } else { None };
    for id in used {
        let path = models_dir.join(format!("obj_{id:06}.ply"));
        let mut mesh = read_ply(&path)?;
        for v in &mut mesh.vertices {
            *v = [v[0] / 1000.0, v[1] / 1000.0, v[2] / 1000.0];
        }
        let from_info = info.as_ref().and_then(|i| i.get(id.to_string())).and_then(|m| m.get("diameter"));
        let (diameter, diameter_source) = match from_info {
            Some(d) => (
                d.as_f64()
                    .filter(|x| *x > 0.0)
                    .ok_or_else(|| Error::config(info_path.display().to_string(), format!("{id}.diameter"), "not a positive number"))?
                    / 1000.0,
                "models_info.json".to_string(),
            ),
            None => diameter_of(&mesh),
        };
        ds.models.insert(id, Model { name: format!("obj_{id:06}"), path, mesh, diameter, diameter_source });
    }
    Ok(ds)
}

fn diameter_of(mesh: &TriMesh) -> (f64, String) {
    let (d, m) = diameter(&mesh.used_vertices());
    (d, if m == DiameterMethod::Exact { "computed (exact)".into() } else { "computed (approximate)".into() })
}

/// YCB-Video class names by class index (1-based), as in the dataset's classes.txt.
pub const YCBV_CLASSES: [&str; 21] = [
    "002_master_chef_can",
    "003_cracker_box",
    "004_sugar_box",
    "005_tomato_soup_can",
    "006_mustard_bottle",
    "007_tuna_fish_can",
    "008_pudding_box",
    "009_gelatin_box",
    "010_potted_meat_can",
    "011_banana",
    "019_pitcher_base",
    "021_bleach_cleanser",
    "024_bowl",
    "025_mug",
    "035_power_drill",
    "036_wood_block",
    "037_scissors",
    "040_large_marker",
    "051_large_clamp",
    "052_extra_large_clamp",
    "061_foam_brick",
];

/// Reads an ASCII `x y z` per line point file (metres for YCB-Video).
pub fn read_xyz(path: &Path) -> Result<Vec<P3>> {
    let s = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut pts = Vec::new();
    for (i, line) in s.lines().enumerate() {
        let t: Vec<&str> = line.split_whitespace().collect();
        if t.is_empty() {
            continue;
        }
        let p: Vec<f64> = t.iter().take(3).filter_map(|x| x.parse().ok()).filter(|x: &f64| x.is_finite()).collect();
        if p.len() != 3 {
            return Err(Error::input(path.display().to_string(), format!("line {}: expected `x y z`", i + 1)));
        }
        pts.push([p[0], p[1], p[2]]);
    }
    if pts.is_empty() {
        return Err(Error::input(path.display().to_string(), "no points"));
    }
    Ok(pts)
}

/// Loads the YCB-Video layout: `<root>/<seq>/NNNNNN-meta.mat` (poses 3×4×N in metres,
/// `cls_indexes`, `intrinsic_matrix`, `factor_depth`) and models from
/// `<root>/models_points_xyz/<class name>/points.xyz` (metres, point clouds; diameters are
/// computed exactly from them). There is no visibility annotation: `visib_fract` is
/// estimated from the model, the GT pose and the `-label.png` map
/// (`crate::dataset::visibility`, `visib_estimated = true`), and left `None` without a label map.
pub fn load_ycbv(root: &Path) -> Result<Dataset> {
    let mut metas: Vec<(String, u32, PathBuf)> = Vec::new();
    let mut seqs: Vec<PathBuf> =
        std::fs::read_dir(root).map_err(|e| Error::io(root, e))?.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_dir()).collect();
    seqs.sort();
    for sd in seqs {
        let scene = sd.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
        for e in std::fs::read_dir(&sd).map_err(|e| Error::io(&sd, e))?.filter_map(|e| e.ok()) {
            let name = e.file_name().to_string_lossy().to_string();
            if let Some(id) = name.strip_suffix("-meta.mat").and_then(|s| s.parse::<u32>().ok()) {
                metas.push((scene.clone(), id, e.path()));
            }
        }
    }
    metas.sort();
    if metas.is_empty() {
        return Err(Error::input(root.display().to_string(), "no <seq>/NNNNNN-meta.mat files"));
    }
    let mut ds = Dataset { root: root.to_path_buf(), layout: Layout::Ycbv, ..Default::default() };
    let mut used = BTreeSet::new();
    for (scene, id, path) in metas {
        let m = MatFile::open(&path)?.vars;
        let file = path.display().to_string();
        let get = |k: &str| m.get(k).ok_or_else(|| Error::config(file.clone(), k, "missing variable"));
        let km = get("intrinsic_matrix")?;
        if km.dims != [3, 3] {
            return Err(Error::config(file.clone(), "intrinsic_matrix", format!("dims {:?}, expected [3, 3]", km.dims)));
        }
        let mut k = [[0.0; 3]; 3];
        for (i, row) in k.iter_mut().enumerate() {
            for (j, x) in row.iter_mut().enumerate() {
                *x = km.data[i + 3 * j];
            }
        }
        let fd = get("factor_depth")?
            .data
            .first()
            .copied()
            .filter(|x| *x > 0.0)
            .ok_or_else(|| Error::config(file.clone(), "factor_depth", "not a positive number"))?;
        let cls = &get("cls_indexes")?.data;
        let poses = get("poses")?;
        let n = cls.len();
        // A single object is stored as a 3×4 matrix (MATLAB drops trailing singleton dims).
        let dims_ok = poses.dims == [3, 4, n] || (n == 1 && poses.dims == [3, 4]);
        if !dims_ok {
            return Err(Error::config(file.clone(), "poses", format!("dims {:?}, expected [3, 4, {n}] for {n} cls_indexes", poses.dims)));
        }
        let mut gts = Vec::with_capacity(n);
        for (o, &c) in cls.iter().enumerate() {
            if c.fract() != 0.0 || c < 1.0 || c as usize > YCBV_CLASSES.len() {
                return Err(Error::config(file.clone(), format!("cls_indexes[{o}]"), format!("{c} is not a class index 1..=21")));
            }
            let at = |i: usize, j: usize| poses.data[i + 3 * j + 12 * o];
            let r = [[at(0, 0), at(0, 1), at(0, 2)], [at(1, 0), at(1, 1), at(1, 2)], [at(2, 0), at(2, 1), at(2, 2)]];
            let t = [at(0, 3), at(1, 3), at(2, 3)];
            used.insert(c as u32);
            gts.push(GtInstance { obj_id: c as u32, r, t, visib_fract: None, visib_estimated: false, bbox_visib: None });
        }
        ds.frames.push(Frame { scene, frame: id, k, depth_scale_m: 1000.0 / fd / 1000.0, gt: gts, cam_w2c: None });
    }
    for id in used {
        let name = YCBV_CLASSES[id as usize - 1];
        let path = root.join("models_points_xyz").join(name).join("points.xyz");
        let mesh = TriMesh { vertices: read_xyz(&path)?, faces: vec![] };
        let (diameter, diameter_source) = diameter_of(&mesh);
        ds.models.insert(id, Model { name: name.to_string(), path, mesh, diameter, diameter_source });
    }
    estimate_visibility(&mut ds)?;
    Ok(ds)
}

/// Fills `visib_fract` of every GT instance that has a label map (module docs of
/// [`crate::dataset::visibility`]).
fn estimate_visibility(ds: &mut Dataset) -> Result<()> {
    use crate::dataset::masks::InstanceMap;
    use crate::dataset::visibility::{surface_patches, visible_fraction};
    let patches: BTreeMap<u32, _> = ds.models.iter().map(|(id, m)| (*id, surface_patches(&m.mesh.used_vertices(), 10))).collect();
    let mut frames = std::mem::take(&mut ds.frames);
    for f in frames.iter_mut() {
        let Some(MaskSource::Label(path, _)) = (!f.gt.is_empty()).then(|| ds.visible_mask_source(f, 0)) else { continue };
        if !path.is_file() {
            continue;
        }
        let map = InstanceMap::open(&path)?;
        for g in f.gt.iter_mut() {
            let mask: Vec<bool> = map.ids.iter().map(|&v| v == g.obj_id).collect();
            let pose = crate::math::Similarity::rigid(g.r, g.t);
            if let Some(v) = patches.get(&g.obj_id).and_then(|s| visible_fraction(s, &pose, &f.k, &mask, map.width, map.height)) {
                g.visib_fract = Some(v);
                g.visib_estimated = true;
            }
        }
    }
    ds.frames = frames;
    Ok(())
}

/// Loads a dataset, detecting the layout:
/// - `path/models_points_xyz/` exists → YCB-Video ([`load_ycbv`]);
/// - otherwise BOP: `path` is a split directory holding scene folders (or a dataset root
///   whose `test/` is one) and models come from `path/models`, `path/../models` or
///   `path/../models_eval`, the first that has `models_info.json` or `.ply` files.
pub fn load_dataset(path: &Path) -> Result<Dataset> {
    if path.join("models_points_xyz").is_dir() {
        return load_ycbv(path);
    }
    let has_scenes = |p: &Path| {
        std::fs::read_dir(p).map(|rd| rd.filter_map(|e| e.ok()).any(|e| e.path().join("scene_gt.json").is_file())).unwrap_or(false)
    };
    let split = if has_scenes(path) {
        path.to_path_buf()
    } else if has_scenes(&path.join("test")) {
        path.join("test")
    } else {
        return Err(Error::input(
            path.display().to_string(),
            "neither a YCB-Video folder (models_points_xyz/) nor a BOP split (scene folders with scene_gt.json)",
        ));
    };
    let parent = split.parent().map(Path::to_path_buf).unwrap_or_default();
    let candidates = [split.join("models"), parent.join("models"), parent.join("models_eval"), path.join("models")];
    let models = candidates
        .iter()
        .find(|d| {
            d.join("models_info.json").is_file()
                || std::fs::read_dir(d)
                    .map(|rd| rd.filter_map(|e| e.ok()).any(|e| e.path().extension().is_some_and(|x| x == "ply")))
                    .unwrap_or(false)
        })
        .ok_or_else(|| {
            Error::input(path.display().to_string(), "BOP models folder not found (tried models/, ../models/, ../models_eval/)")
        })?;
    load_bop(&split, models)
}

/// Tiny BOP datasets written to disk, for tests (other crates' through recon-testkit).
#[doc(hidden)]
pub mod tests {
    use crate::dataset::bop::*;

    /// Real-data discovery, shared with the integration tests (test support:
    /// it reads `RECON_REALDATA` / `RECON_REQUIRE_REALDATA`, so it lives in tests/).
    #[cfg(test)]
    mod realdata {
        include!(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/common/realdata.rs"));
    }

    /// Writes a tiny BOP dataset (one scene, two frames, two objects) under `dir`, returns
    /// the split dir. Object 1: unit-ish box 40×20×10 mm (binary PLY), object 2: tetra
    /// (ASCII PLY) without a models_info entry.
    pub fn write_bop(dir: &Path) -> PathBuf {
        let models = dir.join("models");
        let scene = dir.join("test").join("000048");
        std::fs::create_dir_all(&models).unwrap();
        std::fs::create_dir_all(&scene).unwrap();
        let bx = crate::mesh::primitives::box_corners([-20.0f32, -10.0, -5.0], [20.0, 10.0, 5.0]);
        let faces = crate::mesh::primitives::BOX_FACES.map(|f| f.map(|i| i as i32));
        let mut b = b"ply\nformat binary_little_endian 1.0\nelement vertex 8\nproperty float x\nproperty float y\nproperty float z\nelement face 12\nproperty list uchar int vertex_indices\nend_header\n".to_vec();
        for v in &bx {
            for c in v {
                b.extend(c.to_le_bytes());
            }
        }
        for f in &faces {
            b.push(3);
            for i in f {
                b.extend(i.to_le_bytes());
            }
        }
        std::fs::write(models.join("obj_000001.ply"), b).unwrap();
        std::fs::write(
            models.join("obj_000002.ply"),
            "ply\nformat ascii 1.0\nelement vertex 4\nproperty double x\nproperty double y\nproperty double z\nelement face 4\nproperty list uchar uint vertex_indices\nend_header\n0 0 0\n30 0 0\n0 40 0\n0 0 120\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n",
        )
        .unwrap();
        std::fs::write(models.join("models_info.json"), r#"{"1": {"diameter": 45.8257569495584, "min_x": -20.0}}"#).unwrap();
        std::fs::write(scene.join("scene_camera.json"), r#"{"1": {"cam_K": [1066.778, 0.0, 312.9869, 0.0, 1067.487, 241.3109, 0.0, 0.0, 1.0], "depth_scale": 0.1}, "2": {"cam_K": [1000, 0, 320, 0, 1000, 240, 0, 0, 1], "depth_scale": 1.0}}"#).unwrap();
        std::fs::write(
            scene.join("scene_gt.json"),
            r#"{"1": [{"cam_R_m2c": [1,0,0, 0,1,0, 0,0,1], "cam_t_m2c": [10.0, -20.0, 700.0], "obj_id": 1},
                     {"cam_R_m2c": [0,-1,0, 1,0,0, 0,0,1], "cam_t_m2c": [-50.0, 0.0, 800.0], "obj_id": 2}],
                "2": [{"cam_R_m2c": [1,0,0, 0,0,-1, 0,1,0], "cam_t_m2c": [0.0, 0.0, 600.0], "obj_id": 1}]}"#,
        )
        .unwrap();
        std::fs::write(
            scene.join("scene_gt_info.json"),
            r#"{"1": [{"bbox_visib": [100, 120, 30, 20], "visib_fract": 1.0}, {"bbox_visib": [10, 12, 3, 2], "visib_fract": 0.75}],
                "2": [{"bbox_visib": [1, 2, 3, 4], "visib_fract": 0.5}]}"#,
        )
        .unwrap();
        dir.join("test")
    }

    #[test]
    fn loads_small_bop_dataset() {
        let dir = crate::util::testing::tmp("bop-load");
        let split = write_bop(&dir);
        let ds = load_dataset(&dir).unwrap();
        assert_eq!(ds.frames.len(), 2);
        let f1 = ds.frame("000048", 1).unwrap();
        assert_eq!(f1.k[0][0], 1066.778);
        assert_eq!(f1.k[1][2], 241.3109);
        assert_eq!(f1.depth_scale_m, 0.1 / 1000.0);
        assert_eq!(f1.gt.len(), 2);
        assert_eq!(f1.gt[0].t, [0.01, -0.02, 0.7]);
        assert_eq!(f1.gt[1].r[0], [0.0, -1.0, 0.0]);
        assert_eq!(f1.gt[1].visib_fract, Some(0.75));
        assert_eq!(f1.gt[0].bbox_visib, Some([100.0, 120.0, 30.0, 20.0]));
        let f2 = ds.frame("000048", 2).unwrap();
        assert_eq!(f2.gt[0].r[2], [0.0, 1.0, 0.0]);
        // Model 1: binary PLY, diameter from models_info (mm → m).
        let m1 = &ds.models[&1];
        assert_eq!((m1.mesh.vertices.len(), m1.mesh.faces.len()), (8, 12));
        assert!((m1.mesh.vertices[7][0] - 0.02).abs() < 1e-9);
        assert_eq!(m1.diameter_source, "models_info.json");
        assert!((m1.diameter - 0.0458257569495584).abs() < 1e-15);
        // Model 2: ASCII PLY, no info entry → computed diameter: |(0,40,0) − (0,0,120)| mm.
        let m2 = &ds.models[&2];
        assert_eq!(m2.diameter_source, "computed (exact)");
        assert!((m2.diameter - (0.04f64.powi(2) + 0.12f64.powi(2)).sqrt()).abs() < 1e-12, "{}", m2.diameter);
        // Same result when pointing at the split directly.
        assert_eq!(load_dataset(&split).unwrap().frames.len(), 2);

        // Errors name the file and the field.
        let gt = split.join("000048").join("scene_gt.json");
        std::fs::write(&gt, r#"{"1": [{"cam_R_m2c": [1,0,0], "cam_t_m2c": [0,0,1], "obj_id": 1}]}"#).unwrap();
        let e = load_dataset(&dir).unwrap_err().to_string();
        assert!(e.contains("scene_gt.json") && e.contains("1[0].cam_R_m2c"), "{e}");
        std::fs::write(&gt, r#"{"1": [{"cam_R_m2c": [1,0,0,0,1,0,0,0,1], "cam_t_m2c": [0,0,1], "obj_id": 9}]}"#).unwrap();
        let e = load_dataset(&dir).unwrap_err().to_string();
        assert!(e.contains("obj_000009.ply"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn loads_ycbv_real_frames() {
        let Some(root) = realdata::realdata_for_test(Some("ycbv_video_oprb"), "the YCB-Video loading test") else {
            return;
        };
        let root = root.as_path();
        let ds = load_dataset(root).unwrap();
        assert_eq!(ds.frames.len(), 15);
        assert_eq!(ds.models.len(), 12);
        for f in &ds.frames {
            // README: fx=1066.778, fy=1067.487, cx=312.9869, cy=241.3109, factor_depth 10000.
            assert_eq!([f.k[0][0], f.k[1][1], f.k[0][2], f.k[1][2], f.k[2][2]], [1066.778, 1067.487, 312.9869, 241.3109, 1.0]);
            assert_eq!(f.depth_scale_m, 0.1 / 1000.0);
            for g in &f.gt {
                // Rotations are orthonormal.
                for i in 0..3 {
                    for j in 0..3 {
                        let d: f64 = (0..3).map(|k| g.r[i][k] * g.r[j][k]).sum();
                        assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-5);
                    }
                }
                assert!(g.t[2] > 0.3 && g.t[2] < 2.0);
            }
        }
        let ids = |s: &str| ds.frame(s, 1).unwrap().gt.iter().map(|g| g.obj_id).collect::<Vec<_>>();
        assert_eq!(ids("0000"), vec![8, 14, 21]);
        assert_eq!(ids("0001"), vec![1, 2, 3, 5]);
        assert_eq!(ids("0002"), vec![5, 7, 9, 10, 16, 18]);
        // Pose of 002_master_chef_can in 0001/000001 (values printed by scipy.io.loadmat).
        let g = &ds.frame("0001", 1).unwrap().gt[0];
        assert!((g.r[0][0] - 0.99646004).abs() < 1e-7 && (g.r[1][2] + 0.83866412).abs() < 1e-7 && (g.r[2][1] - 0.83522303).abs() < 1e-7);
        assert!((g.t[0] + 0.03296732).abs() < 1e-7 && (g.t[1] - 0.13458166).abs() < 1e-7 && (g.t[2] - 0.97498233).abs() < 1e-7);
        assert_eq!(ds.models[&1].name, "002_master_chef_can");
        assert_eq!(ds.models[&1].mesh.vertices.len(), 2620);
        // README check: GT-posed points of unoccluded objects project into their label mask.
        let frame = ds.frame("0001", 1).unwrap();
        let label = image::open(root.join("0001/000001-label.png")).unwrap().to_luma8();
        for g in frame.gt.iter().filter(|g| g.obj_id == 1 || g.obj_id == 3) {
            let pts = &ds.models[&g.obj_id].mesh.vertices;
            let inside = pts
                .iter()
                .filter(|p| {
                    let x: Vec<f64> = (0..3).map(|i| (0..3).map(|j| g.r[i][j] * p[j]).sum::<f64>() + g.t[i]).collect();
                    let u = (frame.k[0][0] * x[0] / x[2] + frame.k[0][2]).round();
                    let v = (frame.k[1][1] * x[1] / x[2] + frame.k[1][2]).round();
                    u >= 0.0 && v >= 0.0 && u < 640.0 && v < 480.0 && label.get_pixel(u as u32, v as u32)[0] as u32 == g.obj_id
                })
                .count();
            let frac = inside as f64 / pts.len() as f64;
            assert!(frac > 0.9, "obj {}: {frac}", g.obj_id);
        }
        // Diameter of the master chef can point cloud (exact; ≈ 0.17 m, BOP lists 172 mm for its mesh).
        let d = ds.models[&1].diameter;
        assert!(d > 0.15 && d < 0.19, "{d}");
    }
}
