//! `recon synth`: occluded tabletop RGB-D scenes with exact ground truth.
//!
//! objects (procedural meshes, parts) → scene (placement, cameras, appearance) →
//! render (ray casting) → sensor model (`recon_core::sensor`) → BOP writer.
//!
//! A dataset is a pure function of its options: scene `i` is generated from a seed
//! derived from (`seed`, `i`) alone and each view's sensor noise from (`seed`, `i`, view),
//! so the bytes do not depend on the thread count or scheduling. Output goes to a staging
//! folder renamed into place at the end, with `recon-synth.json` written last.

// Clippy lints allowed crate-wide, for the reasons given in recon-core's lib.rs.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord, clippy::too_many_arguments, clippy::type_complexity)]
#![warn(missing_docs)]

pub(crate) mod bop_writer;
pub mod objects;
pub(crate) mod scene;

pub use recon_core::render::{render, Camera, Instance, Light, Material, Pattern, RenderMesh, RenderOptions, Rendered};
pub use scene::{Scene, SceneConfig};

use bop_writer::{
    camera_entry, gt_entry, gt_info_entry, mkdir, model_info, model_ply_bytes, write_bytes, write_depth, write_json, write_mask,
    write_normals, write_rgb, DEPTH_SCALE_MM,
};
use rayon::prelude::*;
use recon_core::rng::SeededRng;
use recon_core::sensor::SensorModel;
use recon_core::{Error, Result};
use serde::Serialize;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Marker (and summary) file of a finished dataset.
pub const MARKER: &str = "recon-synth.json";
/// The BOP split the scenes are written to.
pub const SPLIT: &str = "test";

#[derive(Clone, Debug)]
/// Settings of a `recon synth` run.
pub struct SynthOptions {
    /// Number of scenes.
    pub scenes: usize,
    /// Camera views per scene.
    pub views: usize,
    /// Seed of the whole dataset (scene `i` derives its own from it).
    pub seed: u64,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Write composite objects as their rigid parts (one model and GT instance each).
    pub parts: bool,
    /// Depth sensor model applied to the rendered depth.
    pub sensor: SensorModel,
}

/// The defaults of `recon synth`'s flags and `recon_rgbd.synth`'s keywords.
impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions { scenes: 10, views: 1, seed: 0, width: 640, height: 480, parts: false, sensor: SensorModel::ideal() }
    }
}

impl SynthOptions {
    /// Checks the ranges (scenes, views, image size, sensor); the error names the CLI flag.
    pub fn validate(&self) -> Result<()> {
        let bad = |field: &str, msg: String| Err(Error::config("recon synth", field, msg));
        if self.scenes == 0 || self.scenes > 1_000_000 {
            return bad("--scenes", format!("expected 1..=1000000, got {}", self.scenes));
        }
        if self.views == 0 || self.views > 1_000 {
            return bad("--views", format!("expected 1..=1000, got {}", self.views));
        }
        if !(16..=8192).contains(&self.width) || !(12..=8192).contains(&self.height) {
            return bad("--width/--height", format!("expected 16..=8192 × 12..=8192 pixels, got {}×{}", self.width, self.height));
        }
        self.sensor.validate("--sensor")
    }
}

/// What a run produced (also stored in `recon-synth.json`).
#[derive(Serialize, Clone, Debug, Default)]
pub struct Summary {
    /// Scenes written.
    pub scenes: usize,
    /// Images written (scenes × views).
    pub images: usize,
    /// GT instances over all images (objects, or parts in parts mode).
    pub instances: usize,
    /// Object models written.
    pub models: usize,
    /// Objects per kind over all scenes.
    pub objects_by_kind: BTreeMap<String, usize>,
    /// Objects per scene: min, mean, max.
    pub objects_per_scene: [f64; 3],
    /// Target occlusion (1 − visib_fract) of every image, in image order.
    pub target_occlusion: Vec<f64>,
    /// Counts of `target_occlusion` in the bins 0–3, 3–20, 20–40, 40–70, >70 %.
    pub target_occlusion_bins: [usize; 5],
    /// Depth pixels beyond the 16-bit range, written as missing.
    pub depth_clipped_px: usize,
}

fn derived_seed(seed: u64, a: u64, b: u64) -> u64 {
    let mut r = SeededRng::new(seed ^ a.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ b.wrapping_mul(0xC2B2_AE3D_27D4_EB4F));
    r.next_u64()
}

fn occlusion_bin(o: f64) -> usize {
    match o {
        o if o < 0.03 => 0,
        o if o < 0.20 => 1,
        o if o < 0.40 => 2,
        o if o <= 0.70 => 3,
        _ => 4,
    }
}

/// The object ids a scene's render units get: 0 for the support, then `first_obj_id..`.
fn unit_ids(n_units: usize, first_obj_id: u32) -> Vec<i64> {
    (0..n_units).map(|i| if i == 0 { 0 } else { (first_obj_id + i as u32 - 1) as i64 }).collect()
}

/// Generate the dataset into `out` (a BOP dataset root: `models/`, `test/<scene>/`,
/// `camera.json`, and [`MARKER`]). `progress` is called once per scene generated and once
/// per scene rendered (2 × scenes calls). An existing `out` is replaced only if it is an
/// earlier `recon synth` output.
///
/// The same run split over workers ([`begin`], [`plan`], [`write_shard`] per range of
/// scenes, [`finish`]) writes the same bytes: this function is that sequence in one process.
pub fn generate(out: &Path, opts: &SynthOptions, progress: &(dyn Fn() + Sync)) -> Result<Summary> {
    let staging = begin(out, opts)?;
    let scenes = generate_scenes(0..opts.scenes, opts, progress)?;
    let first_ids = first_object_ids(&scenes, opts);
    let shard = write_scenes(&staging, 0, &scenes, &first_ids, opts, progress)?;
    finish(&staging, out, opts, &[shard])
}

/// Checks `out` (absent, empty, or an earlier `recon synth` output) and creates an empty
/// staging folder beside it (`<out>.partial`, with `models/` and `test/`) for the scenes.
pub fn begin(out: &Path, opts: &SynthOptions) -> Result<PathBuf> {
    opts.validate()?;
    if out.exists() {
        let empty = std::fs::read_dir(out).map(|mut d| d.next().is_none()).unwrap_or(false);
        if !empty && !out.join(MARKER).exists() {
            return Err(Error::input(
                out.display().to_string(),
                format!("output folder exists and is not a recon synth dataset (no {MARKER}); remove it or choose another --out"),
            ));
        }
    }
    let staging = out.with_extension("partial");
    if staging.exists() {
        std::fs::remove_dir_all(&staging).map_err(|e| Error::io(&staging, e))?;
    }
    mkdir(&staging.join("models"))?;
    mkdir(&staging.join(SPLIT))?;
    Ok(staging)
}

/// Phase 1 over the whole dataset (scene generation, cheap): the first object id of every
/// scene, since ids run on in scene order. A split run computes it once and hands it to
/// every [`write_shard`].
pub fn plan(opts: &SynthOptions) -> Result<Vec<u32>> {
    opts.validate()?;
    let scenes = generate_scenes(0..opts.scenes, opts, &|| {})?;
    Ok(first_object_ids(&scenes, opts))
}

/// Phase 2 for scenes `range` (their generation again, rendering, the sensor, the files
/// under `staging`), as one worker of a split run does it. `first_ids` is [`plan`]'s.
pub fn write_shard(staging: &Path, opts: &SynthOptions, range: std::ops::Range<usize>, first_ids: &[u32]) -> Result<Shard> {
    opts.validate()?;
    if range.end > opts.scenes || first_ids.len() != opts.scenes || range.start > range.end {
        return Err(Error::input(
            "recon synth shard",
            format!("scenes {range:?} of {} with {} first object ids", opts.scenes, first_ids.len()),
        ));
    }
    let scenes = generate_scenes(range.clone(), opts, &|| {})?;
    write_scenes(staging, range.start, &scenes, &first_ids[range], opts, &|| {})
}

/// What one worker's scenes contribute to the dataset summary and `models_info.json`.
/// Serialised, every float is its bit pattern (JSON text parsed back may move a float by
/// one ulp), so a split run's files are bit-identical to a single run's.
#[derive(Serialize, serde::Deserialize, Clone, Debug)]
pub struct Shard {
    /// Index of the shard's first scene.
    pub first_scene: usize,
    /// The shard's scenes, in order.
    pub scenes: Vec<ShardScene>,
}

#[derive(Serialize, serde::Deserialize, Clone, Debug)]
/// What one scene of a shard contributes.
pub struct ShardScene {
    /// `(obj_id, models_info entry)`; serialised with every float as its bit pattern.
    #[serde(with = "exact_floats")]
    pub models_info: Vec<(u32, Value)>,
    /// GT instances over the scene's images.
    pub instances: usize,
    /// Depth pixels beyond the 16-bit range, written as missing.
    pub clipped: usize,
    /// `f64::to_bits` of each view's target occlusion.
    pub target_occlusion_bits: Vec<u64>,
    /// Kind name of every object of the scene.
    pub kinds: Vec<String>,
}

/// Serde for JSON values with each float written as `{"f64_bits": u64}`.
mod exact_floats {
    use serde::{Deserialize, Deserializer, Serialize, Serializer};
    use serde_json::{json, Value};

    fn encode(v: &Value) -> Value {
        match v {
            Value::Number(n) if n.is_f64() => json!({ "f64_bits": n.as_f64().unwrap_or(f64::NAN).to_bits() }),
            Value::Array(a) => Value::Array(a.iter().map(encode).collect()),
            Value::Object(o) => Value::Object(o.iter().map(|(k, v)| (k.clone(), encode(v))).collect()),
            v => v.clone(),
        }
    }

    fn decode(v: Value) -> Value {
        match v {
            Value::Object(o) if o.len() == 1 && o.get("f64_bits").is_some_and(Value::is_u64) => {
                let bits = o["f64_bits"].as_u64().unwrap_or(0);
                serde_json::Number::from_f64(f64::from_bits(bits)).map_or(Value::Null, Value::Number)
            }
            Value::Array(a) => Value::Array(a.into_iter().map(decode).collect()),
            Value::Object(o) => Value::Object(o.into_iter().map(|(k, v)| (k, decode(v))).collect()),
            v => v,
        }
    }

    pub fn serialize<S: Serializer>(v: &[(u32, Value)], s: S) -> Result<S::Ok, S::Error> {
        v.iter().map(|(id, x)| (*id, encode(x))).collect::<Vec<_>>().serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<(u32, Value)>, D::Error> {
        Ok(Vec::<(u32, Value)>::deserialize(d)?.into_iter().map(|(id, x)| (id, decode(x))).collect())
    }
}

/// Merges the shards (any order; every scene exactly once), writes `models_info.json`,
/// `camera.json` and [`MARKER`] last, and moves the staging folder to `out`.
pub fn finish(staging: &Path, out: &Path, opts: &SynthOptions, shards: &[Shard]) -> Result<Summary> {
    let mut scenes: Vec<Option<&ShardScene>> = vec![None; opts.scenes];
    for sh in shards {
        for (k, sc) in sh.scenes.iter().enumerate() {
            match scenes.get_mut(sh.first_scene + k) {
                Some(slot @ None) => *slot = Some(sc),
                _ => {
                    return Err(Error::input("recon synth shards", format!("scene {} is out of range or given twice", sh.first_scene + k)))
                }
            }
        }
    }
    if let Some(i) = scenes.iter().position(Option::is_none) {
        return Err(Error::input("recon synth shards", format!("scene {i} is missing")));
    }
    let mut models_info = serde_json::Map::new();
    let mut summary = Summary { scenes: opts.scenes, images: opts.scenes * opts.views, ..Default::default() };
    let mut counts = Vec::new();
    for r in scenes.into_iter().flatten() {
        for (id, info) in &r.models_info {
            models_info.insert(id.to_string(), info.clone());
        }
        summary.instances += r.instances;
        summary.depth_clipped_px += r.clipped;
        summary.target_occlusion.extend(r.target_occlusion_bits.iter().map(|&b| f64::from_bits(b)));
        counts.push(r.kinds.len() as f64);
        for k in &r.kinds {
            *summary.objects_by_kind.entry(k.clone()).or_default() += 1;
        }
    }
    summary.models = models_info.len();
    for &o in &summary.target_occlusion {
        summary.target_occlusion_bins[occlusion_bin(o)] += 1;
    }
    summary.objects_per_scene = [
        counts.iter().copied().fold(f64::INFINITY, f64::min),
        counts.iter().sum::<f64>() / counts.len() as f64,
        counts.iter().copied().fold(0.0, f64::max),
    ];
    write_json(&staging.join("models").join("models_info.json"), &Value::Object(models_info))?;
    // Nominal camera (per-image intrinsics are in scene_camera.json).
    let (sx, sy) = (opts.width as f64 / 640.0, opts.height as f64 / 480.0);
    write_json(
        &staging.join("camera.json"),
        &json!({"fx": 600.0 * sx, "fy": 600.0 * sy, "cx": (opts.width as f64 - 1.0) / 2.0, "cy": (opts.height as f64 - 1.0) / 2.0, "width": opts.width, "height": opts.height, "depth_scale": DEPTH_SCALE_MM}),
    )?;
    let marker = json!({
        "generator": "recon synth",
        "format": "BOP scenewise; models/ in mm; depth × depth_scale = mm (sensor model applied); extras per scene: scene_meta.json (kind, part, target flag, materials, lights), depth_gt/ (noise-free depth, same scale), normals/ (camera-frame face normals, RGB = (n + 1) / 2 · 255, 0 where no surface)",
        "options": {"scenes": opts.scenes, "views": opts.views, "seed": opts.seed, "width": opts.width, "height": opts.height, "parts": opts.parts},
        "sensor_model": opts.sensor,
        "split": SPLIT,
        "summary": summary,
    });
    write_json(&staging.join(MARKER), &marker)?;
    if out.exists() {
        std::fs::remove_dir_all(out).map_err(|e| Error::io(out, e))?;
    }
    std::fs::rename(staging, out).map_err(|e| Error::io(out, e))?;
    Ok(summary)
}

/// Scenes `range`, each from its own derived seed.
fn generate_scenes(range: std::ops::Range<usize>, opts: &SynthOptions, progress: &(dyn Fn() + Sync)) -> Result<Vec<Scene>> {
    let cfg = SceneConfig { width: opts.width, height: opts.height, views: opts.views, ..Default::default() };
    range
        .into_par_iter()
        .map(|i| {
            let s = Scene::generate(derived_seed(opts.seed, i as u64, 0), &cfg);
            progress();
            s
        })
        .collect()
}

/// The first object id of every scene (ids run on in scene order).
fn first_object_ids(scenes: &[Scene], opts: &SynthOptions) -> Vec<u32> {
    let mut first_ids = Vec::with_capacity(scenes.len());
    let mut next = 1u32;
    for s in scenes {
        first_ids.push(next);
        let n: usize = if opts.parts { s.objects.iter().map(|o| o.object.parts.len()).sum() } else { s.objects.len() };
        next += n as u32;
    }
    first_ids
}

/// Renders, applies the sensor and writes `scenes` (scene `first + k` for the k-th).
fn write_scenes(
    staging: &Path,
    first: usize,
    scenes: &[Scene],
    first_ids: &[u32],
    opts: &SynthOptions,
    progress: &(dyn Fn() + Sync),
) -> Result<Shard> {
    let results: Vec<ShardScene> = scenes
        .par_iter()
        .enumerate()
        .map(|(k, s)| {
            let r = write_scene(staging, first + k, s, first_ids[k], opts).map(|r| ShardScene {
                models_info: r.models_info,
                instances: r.instances,
                clipped: r.clipped,
                target_occlusion_bits: r.target_occlusion.iter().map(|o| o.to_bits()).collect(),
                kinds: s.objects.iter().map(|o| o.object.kind.name().to_string()).collect(),
            });
            progress();
            r
        })
        .collect::<Result<_>>()?;
    Ok(Shard { first_scene: first, scenes: results })
}

struct SceneResult {
    models_info: Vec<(u32, Value)>,
    instances: usize,
    clipped: usize,
    target_occlusion: Vec<f64>,
}

fn write_scene(root: &Path, index: usize, s: &Scene, first_id: u32, opts: &SynthOptions) -> Result<SceneResult> {
    let units = s.units(opts.parts)?;
    let ids = unit_ids(units.len(), first_id);
    let dir = root.join(SPLIT).join(format!("{index:06}"));
    for sub in ["rgb", "depth", "depth_gt", "normals", "mask", "mask_visib"] {
        mkdir(&dir.join(sub))?;
    }
    // Models (object units only; unit 0 is the support).
    let mut models_info = Vec::new();
    for (u, &id) in units.iter().zip(&ids).skip(1) {
        let o = &s.objects[u.object.unwrap_or(0)];
        let (mesh, sym) = match u.part {
            Some(j) => (o.object.parts[j].mesh.clone(), o.object.parts[j].symmetry.clone()),
            None => (o.object.mesh(), o.object.symmetry.clone()),
        };
        write_bytes(&root.join("models").join(format!("obj_{id:06}.ply")), &model_ply_bytes(&mesh, o.material.color)?)?;
        models_info.push((id as u32, model_info(&mesh, &sym)));
    }
    let (w, h) = (opts.width, opts.height);
    let mut cams = serde_json::Map::new();
    let mut gts = serde_json::Map::new();
    let mut infos = serde_json::Map::new();
    let mut images = serde_json::Map::new();
    let mut clipped = 0;
    let mut target_occlusion = Vec::new();
    let is_object: Vec<bool> = units.iter().map(|u| u.object.is_some()).collect();
    let target_units: Vec<usize> = (0..units.len()).filter(|&i| units[i].object == Some(0)).collect();
    for v in 0..s.views.len() {
        let frame = (index * opts.views + v) as i64;
        let r = s.render_view(&units, &ids, v)?;
        // Edge distance as the audit defines it: discontinuities of the GT objects' depth.
        let covs = r.covariates_full(frame, None, Some(&is_object));
        let k = recon_core::sensor::Pinhole { fx: r.k.fx, fy: r.k.fy, cx: r.k.cx, cy: r.k.cy };
        let measured = opts.sensor.apply_frame(&covs, w, h, k, derived_seed(opts.seed, index as u64, 1 + v as u64));
        write_rgb(&dir.join("rgb").join(format!("{v:06}.png")), &r.rgb, w, h)?;
        clipped += write_depth(&dir.join("depth").join(format!("{v:06}.png")), &measured, w, h)?;
        // Extras beside the BOP folders (ignored by BOP tools): noise-free depth and
        // camera-frame face normals.
        write_depth(&dir.join("depth_gt").join(format!("{v:06}.png")), &r.depth, w, h)?;
        write_normals(&dir.join("normals").join(format!("{v:06}.png")), &r.normal_cam, w, h)?;
        let w2c = s.views[v].camera.world_to_cam;
        cams.insert(v.to_string(), camera_entry(&r, &w2c));
        let mut gt = Vec::new();
        let mut info = Vec::new();
        for (g, ui) in (1..units.len()).enumerate() {
            let m2c = w2c.compose(&units[ui].pose);
            gt.push(gt_entry(&m2c, ids[ui] as u32));
            info.push(gt_info_entry(&r, ui, &measured));
            write_mask(&dir.join("mask").join(format!("{v:06}_{g:06}.png")), &r.amodal[ui], w, h)?;
            write_mask(&dir.join("mask_visib").join(format!("{v:06}_{g:06}.png")), &r.visible_mask(ui), w, h)?;
        }
        // The target as a whole (all its parts).
        let all = (0..w * h).filter(|&p| target_units.iter().any(|&t| r.amodal[t][p])).count();
        let vis = r.index.iter().filter(|&&i| i >= 0 && target_units.contains(&(i as usize))).count();
        let occ = if all > 0 { 1.0 - vis as f64 / all as f64 } else { 1.0 };
        target_occlusion.push(occ);
        images.insert(
            v.to_string(),
            json!({"frame_index": frame, "light": s.views[v].light, "target_visib_fract": 1.0 - occ, "target_px_count_all": all}),
        );
        gts.insert(v.to_string(), Value::Array(gt));
        infos.insert(v.to_string(), Value::Array(info));
    }
    write_json(&dir.join("scene_camera.json"), &Value::Object(cams))?;
    write_json(&dir.join("scene_gt.json"), &Value::Object(gts))?;
    write_json(&dir.join("scene_gt_info.json"), &Value::Object(infos))?;
    let instances: Vec<Value> = (1..units.len())
        .enumerate()
        .map(|(g, ui)| {
            let u = &units[ui];
            let oi = u.object.unwrap_or(0);
            let o = &s.objects[oi];
            json!({
                "gt_idx": g,
                "obj_id": ids[ui],
                "object_index": oi,
                "kind": o.object.kind.name(),
                "part": u.part.map(|j| o.object.parts[j].name),
                "part_pose_in_object": u.part.map(|j| { let p = &o.object.parts[j].pose; json!({"R": bop_writer::flat3(&p.rotation), "t_mm": p.translation.map(|x| x * 1000.0)}) }),
                "target": o.target,
                "shell": o.object.shell,
                "dims_m": o.object.dims.iter().map(|(k, v)| (k.to_string(), json!(v))).collect::<serde_json::Map<_, _>>(),
                "material": u.material,
            })
        })
        .collect();
    write_json(
        &dir.join("scene_meta.json"),
        &json!({
            "generator": "recon synth",
            "scene_seed": s.seed,
            "parts": opts.parts,
            "occlusion_goal": s.occlusion_goal,
            "occlusion_trial": s.occlusion_trial,
            "support": {"size_m": [2.0 * scene::SUPPORT_HALF, 2.0 * scene::SUPPORT_HALF, scene::SUPPORT_THICK], "top_z_m": 0.0, "object_covariate": 0, "material": s.support_material},
            "instances": instances,
            "images": images,
        }),
    )?;
    Ok(SceneResult { models_info, instances: (units.len() - 1) * s.views.len(), clipped, target_occlusion })
}
