//! The other commands as functions: `load_frame` (the frame discovery of `recon infer`),
//! `scene` (`recon scene`), `synth` (`recon synth`, also split into shards for
//! `recon_rgbd.ray.synth`), `eval` (`recon eval`), `audit_depth` (`recon audit depth`) and
//! `dataset_frames` (the frames of a BOP or YCB-Video dataset, for `recon_rgbd.ray`). Each calls
//! the library functions its command calls and returns the report as a dict.

use crate::convert::{frame_options, from_python, rows, to_python};
use crate::errors::{config, input, ConfigError, IntoPy};
use numpy::{PyArray1, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use recon::dataset::{FrameOptions, RgbdFrame};
use recon::sensor::SensorModel;
use recon::synth::SynthOptions;
use std::path::PathBuf;

/// A frame as `recon infer --rgbd` finds it: colour, metric depth and intrinsics.
#[pyfunction]
#[pyo3(signature = (path, *, depth=None, intrinsics=None, depth_scale=None))]
pub fn load_frame<'py>(
    py: Python<'py>,
    path: PathBuf,
    depth: Option<PathBuf>,
    intrinsics: Option<&Bound<'py, PyAny>>,
    depth_scale: Option<f64>,
) -> PyResult<Bound<'py, PyDict>> {
    let fo = frame_options(depth, intrinsics, depth_scale)?;
    let f = py.detach(|| RgbdFrame::open(&path, &fo)).py()?;
    let d = PyDict::new(py);
    let (w, h) = (f.width, f.height);
    d.set_item("rgb", PyArray1::from_vec(py, f.rgb).reshape([h, w, 3])?)?;
    d.set_item("depth", PyArray1::from_vec(py, f.depth_m).reshape([h, w])?)?;
    let k = f.intrinsics;
    d.set_item("K", rows(py, vec![[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])?)?;
    d.set_item("rgb_path", f.rgb_path)?;
    d.set_item("depth_path", f.depth_path)?;
    d.set_item("intrinsics_source", f.intrinsics_source)?;
    d.set_item("depth_scale", f.depth_scale_m)?;
    Ok(d)
}

/// Masks as `recon infer --masks` reads them: one instance-id PNG (`objects` selects ids)
/// or several binary mask files. Returns `{"label", "id", "mask"}` (H×W bool) per object,
/// and the skipped ones with their reasons.
#[pyfunction]
#[pyo3(signature = (paths, objects=None))]
pub fn load_masks<'py>(py: Python<'py>, paths: &Bound<'py, PyAny>, objects: Option<Vec<u32>>) -> PyResult<Bound<'py, PyDict>> {
    let paths: Vec<PathBuf> = match paths.extract::<PathBuf>() {
        Ok(p) => vec![p],
        Err(_) => paths.extract()?,
    };
    let (masks, skipped) = py.detach(|| recon::dataset::load_masks(&paths, objects.as_deref())).py()?;
    let list = pyo3::types::PyList::empty(py);
    for m in masks {
        let d = PyDict::new(py);
        d.set_item("label", &m.label)?;
        d.set_item("id", m.id)?;
        d.set_item("mask", PyArray1::from_vec(py, m.to_bools()).reshape([m.height, m.width])?)?;
        list.append(d)?;
    }
    let out = PyDict::new(py);
    out.set_item("objects", list)?;
    let sk: Vec<(String, String)> = skipped.iter().map(|s| (s.label.clone(), s.reason.to_string())).collect();
    out.set_item("skipped", sk)?;
    Ok(out)
}

fn sensor(path: Option<PathBuf>) -> PyResult<SensorModel> {
    match path {
        Some(p) => SensorModel::load(&p).py(),
        None => Ok(SensorModel::ideal()),
    }
}

/// `recon synth`'s options from keyword arguments (`scenes`, `views`, `seed`, `sensor`,
/// `width`, `height`, `parts`, the CLI's flags); absent ones take the library's defaults
/// ([`SynthOptions::default`], the CLI's too).
fn synth_options(options: Option<&Bound<'_, PyDict>>) -> PyResult<SynthOptions> {
    const NAMES: &str = "scenes, views, seed, sensor, width, height, parts";
    let mut o = SynthOptions::default();
    for (k, v) in options.into_iter().flat_map(|d| d.iter()) {
        let k: String = k.extract()?;
        let typed = |e: PyErr| config(&k, e);
        match k.as_str() {
            "scenes" => o.scenes = v.extract().map_err(typed)?,
            "views" => o.views = v.extract().map_err(typed)?,
            "seed" => o.seed = v.extract().map_err(typed)?,
            "width" => o.width = v.extract().map_err(typed)?,
            "height" => o.height = v.extract().map_err(typed)?,
            "parts" => o.parts = v.extract().map_err(typed)?,
            "sensor" => o.sensor = sensor(v.extract().map_err(typed)?)?,
            _ => return Err(config(&k, format!("unknown option; the options are {NAMES}"))),
        }
    }
    o.validate().py()?;
    Ok(o)
}

/// `recon synth`: a BOP-format dataset; returns the summary.
#[pyfunction]
#[pyo3(signature = (out, **options))]
pub fn synth<'py>(py: Python<'py>, out: PathBuf, options: Option<&Bound<'_, PyDict>>) -> PyResult<Bound<'py, PyAny>> {
    let opts = synth_options(options)?;
    let summary = py.detach(|| recon::synth::generate(&out, &opts, &|| {})).py()?;
    to_python(py, &summary)
}

/// Split synth, step 1: checks `out` and makes the staging folder (returned).
#[pyfunction]
#[pyo3(signature = (out, **options))]
pub fn synth_begin(py: Python<'_>, out: PathBuf, options: Option<&Bound<'_, PyDict>>) -> PyResult<PathBuf> {
    let opts = synth_options(options)?;
    py.detach(|| recon::synth::begin(&out, &opts)).py()
}

/// Split synth, step 2: the first object id of every scene.
#[pyfunction]
#[pyo3(signature = (**options))]
pub fn synth_plan(py: Python<'_>, options: Option<&Bound<'_, PyDict>>) -> PyResult<Vec<u32>> {
    let opts = synth_options(options)?;
    py.detach(|| recon::synth::plan(&opts)).py()
}

/// Split synth, step 3 (one worker): scenes `start..end` into the staging folder; returns
/// the shard record for [`synth_finish`].
#[pyfunction]
#[pyo3(signature = (staging, start, end, first_ids, **options))]
pub fn synth_shard<'py>(
    py: Python<'py>,
    staging: PathBuf,
    start: usize,
    end: usize,
    first_ids: Vec<u32>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    let opts = synth_options(options)?;
    let shard = py.detach(|| recon::synth::write_shard(&staging, &opts, start..end, &first_ids)).py()?;
    to_python(py, &shard)
}

/// Split synth, step 4: merges the shard records and moves the dataset into place.
#[pyfunction]
#[pyo3(signature = (staging, out, shards, **options))]
pub fn synth_finish<'py>(
    py: Python<'py>,
    staging: PathBuf,
    out: PathBuf,
    shards: Vec<Bound<'py, PyAny>>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    let opts = synth_options(options)?;
    let shards: Vec<recon::synth::Shard> =
        shards.iter().map(|s| serde_json::from_value(from_python(s)?).map_err(|e| input("synth shard", e))).collect::<PyResult<_>>()?;
    let summary = py.detach(|| recon::synth::finish(&staging, &out, &opts, &shards)).py()?;
    to_python(py, &summary)
}

/// Removes a folder when dropped (the in-memory objects' meshes, once the scene is built).
struct TempDir(PathBuf);

impl TempDir {
    fn new() -> Self {
        static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
        TempDir(std::env::temp_dir().join(format!("recon-scene-{}-{t}-{n}", std::process::id())))
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// The frame of in-memory objects: a colour image path (depth and intrinsics found beside
/// it as `recon infer` finds them) or a mapping with `rgb`, `depth`, `K` (and `depth_scale`
/// for uint16 depth), such as `load_frame`'s dict.
fn scene_frame(frame: &Bound<'_, PyAny>, depth: Option<PathBuf>, depth_scale: Option<f64>) -> PyResult<RgbdFrame> {
    if let Ok(p) = frame.extract::<PathBuf>() {
        let fo = FrameOptions { depth, depth_scale_m: depth_scale, ..Default::default() };
        return frame.py().detach(|| RgbdFrame::open(&p, &fo)).py();
    }
    let Ok(d) = frame.cast::<PyDict>() else {
        return Err(input("frame", "expected a colour image path or a dict with rgb, depth and K (as load_frame returns)"));
    };
    let get = |k: &str| -> PyResult<Bound<'_, PyAny>> {
        d.get_item(k)?.ok_or_else(|| input("frame", format!("missing key `{k}` (rgb, depth, K[, depth_scale])")))
    };
    let dep = get("depth")?;
    // load_frame's dict holds depth in metres already; its `depth_scale` records the file's.
    let is_u16 = dep.getattr("dtype").and_then(|t| t.str()).map(|t| t == "uint16").unwrap_or(false);
    let scale = match (is_u16, depth_scale) {
        (true, Some(s)) => Some(s),
        (true, None) => d.get_item("depth_scale")?.map(|x| x.extract()).transpose()?,
        (false, Some(_)) => return Err(config("depth_scale", "applies to uint16 depth; float depth is already in metres")),
        (false, None) => None,
    };
    let name: String = match d.get_item("depth_path")? {
        Some(p) => p.str()?.to_string(),
        None => "<frame arrays>".to_string(),
    };
    let mut f = crate::engine::frame_from_arrays(&get("rgb")?, &dep, &get("K")?, scale, &name)?;
    if let Some(p) = d.get_item("rgb_path")? {
        f.rgb_path = p.extract()?;
    }
    Ok(f)
}

/// In-memory objects for a scene: `(label, mesh)` of those with a mesh, notes on the
/// others, and their frame.
type InMemory = (Vec<(String, recon::mesh::Mesh)>, Vec<String>, RgbdFrame);

/// The variations spec: a file, a dict (the file's JSON, passed through as text), or the default.
fn variation_spec(spec: Option<&Bound<'_, PyAny>>) -> PyResult<(recon::sim::VariationSpec, String)> {
    use recon::sim::VariationSpec;
    let Some(s) = spec else { return Ok((VariationSpec::default(), "<default spec>".to_string())) };
    if let Ok(p) = s.extract::<PathBuf>() {
        return Ok((VariationSpec::load(&p).py()?, p.display().to_string()));
    }
    if s.cast::<PyDict>().is_err() {
        return Err(config("spec", "expected a spec file path or a dict of the spec's JSON"));
    }
    let text = serde_json::to_string(&from_python(s)?).map_err(|e| input("spec", e))?;
    Ok((VariationSpec::parse(&text, "<spec dict>").py()?, "<spec dict>".to_string()))
}

/// `recon scene`: a settled, simulator-ready scene from `Engine.reconstruct`'s objects and
/// their frame, a `recon infer` output folder, a scene file or a BOP scene folder. Returns
/// the written files and per-object physics; with `variations=N`, N re-arranged scenes
/// (`recon scene --variations`) and their manifest.
#[pyfunction]
#[pyo3(signature = (objects, frame=None, out=None, *, view=None, depth=None, depth_scale=None, materials=None,
    variations=None, spec=None, **options))]
#[allow(clippy::too_many_arguments)]
pub fn scene<'py>(
    py: Python<'py>,
    objects: &Bound<'py, PyAny>,
    frame: Option<&Bound<'py, PyAny>>,
    out: Option<PathBuf>,
    view: Option<u32>,
    depth: Option<PathBuf>,
    depth_scale: Option<f64>,
    materials: Option<PathBuf>,
    variations: Option<usize>,
    spec: Option<&Bound<'py, PyAny>>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    use recon::sim::{build_scene, MaterialTable, SceneFile, SceneOptions};
    let out = out.ok_or_else(|| config("out", "the output folder is required"))?;
    // The options' names, defaults and checks are the library's (`recon scene`'s flags with `_`).
    let options = match options {
        Some(d) => from_python(d.as_any())?,
        None => serde_json::Value::Object(Default::default()),
    };
    let options = SceneOptions::from_json(options).map_err(|e| ConfigError::new_err(e.keyword_message()))?;
    let opts = options.settings().map_err(|e| ConfigError::new_err(e.keyword_message()))?;
    let seed = options.seed;
    // A bad spec fails before the scene is read, as in the CLI.
    let spec = match (variations, spec) {
        (Some(_), s) => Some(variation_spec(s)?),
        (None, Some(_)) => return Err(config("spec", "applies with variations=N")),
        (None, None) => None,
    };
    let table = match &materials {
        Some(p) => MaterialTable::load(p).py()?,
        None => MaterialTable::builtin(),
    };
    let plane_opts = options.plane_fit();

    // In-memory objects: their meshes (or a note for those without one) and their frame.
    let memory: Option<InMemory> = match objects.extract::<PathBuf>() {
        Ok(_) => None,
        Err(_) => {
            let mut meshes = Vec::new();
            let mut notes = Vec::new();
            for (i, o) in objects.try_iter().map_err(|_| input("objects", "expected a list of recon_rgbd.Object or a path"))?.enumerate() {
                let o = o?;
                let o =
                    o.cast::<crate::engine::Object>().map_err(|_| input("objects", format!("item {i}: expected a recon_rgbd.Object")))?;
                match o.get().mesh_for_scene(py)? {
                    Some(m) => meshes.push(m),
                    None => notes.push(format!("{}: no mesh was decoded; left out", o.get().label())),
                }
            }
            let f = frame.ok_or_else(|| input("frame", "in-memory objects need their frame: a colour image path or load_frame's dict"))?;
            Some((meshes, notes, scene_frame(f, depth.clone(), depth_scale)?))
        }
    };
    let frame_path: Option<PathBuf> = match (&memory, frame) {
        (None, Some(f)) => {
            Some(f.extract().map_err(|_| input("frame", "with a folder or file of objects, frame is the colour image path"))?)
        }
        _ => None,
    };
    let input_path: Option<PathBuf> = objects.extract().ok();
    let result = py.detach(|| -> recon::Result<serde_json::Value> {
        let tmp = TempDir::new();
        let mut notes = Vec::new();
        let mut plane_check = None;
        let (scene, file) = match (&memory, &input_path) {
            (Some((meshes, n, f)), _) => {
                notes.extend(n.iter().cloned());
                (recon::sim::scene_from_meshes(meshes, &tmp.0, f, &table, &plane_opts)?, "objects".to_string())
            }
            (None, Some(input)) if input.is_dir() && input.join("scene_gt.json").is_file() => {
                let (scene, check) = recon::sim::scene_from_bop(input, view, &table, &plane_opts)?;
                plane_check = check;
                (scene, input.join("scene_gt.json").display().to_string())
            }
            (None, Some(input)) if input.is_dir() => {
                let marker = input.join(recon::engine::MARKER);
                if !marker.is_file() {
                    return Err(recon::Error::input(
                        input.display().to_string(),
                        format!("neither a recon infer output (no {}) nor a BOP scene folder (no scene_gt.json)", recon::engine::MARKER),
                    ));
                }
                let color = frame_path.clone().or_else(|| recon::sim::infer_frame(input)).ok_or_else(|| {
                    recon::Error::input(input.display().to_string(), "the colour image recorded in its pose.json is not found; pass frame=")
                })?;
                let f = RgbdFrame::open(&color, &FrameOptions { depth: depth.clone(), depth_scale_m: depth_scale, ..Default::default() })?;
                let (scene, n) = recon::sim::scene_from_infer_output(input, &f, &table, &plane_opts)?;
                notes = n;
                (scene, marker.display().to_string())
            }
            (None, Some(input)) => (SceneFile::load(input)?, input.display().to_string()),
            (None, None) => unreachable!("objects is a path when not in memory"),
        };
        if let (Some(count), Some((spec, spec_file))) = (variations, spec) {
            let vo = recon::sim::VariationOptions::new(count, seed, spec, spec_file);
            let r = recon::sim::run_variations(&scene, &table, &opts, &vo, &file, &out)?;
            return Ok(serde_json::json!({
                "out": out, "manifest_file": recon::sim::VARIATIONS_MANIFEST, "manifest": r.manifest, "seconds": r.seconds, "notes": notes,
            }));
        }
        let mut sim = build_scene(&scene, &table, &opts, &file)?;
        if memory.is_some() {
            // The meshes were read from a temporary folder removed below; the records name
            // the objects instead of files that will not exist.
            for (i, (s, o)) in sim.input.objects.iter_mut().zip(sim.objects.iter_mut()).enumerate() {
                let p = PathBuf::from(format!("<in memory: objects[{i}] {}>", s.name));
                s.mesh = p.clone();
                o.spec.mesh = p.clone();
                o.mesh_file = p;
            }
        }
        let written = recon::sim::write_outputs(&mut sim, &out)?;
        Ok(serde_json::json!({
            "out": out, "files": written, "objects": sim.summaries(), "notes": notes,
            "support_plane": sim.input.support_plane.fit, "plane_check": plane_check,
            "settle": {"at_rest": sim.settle.at_rest, "simulated_s": sim.settle.simulated_s, "steps": sim.settle.steps,
                "depenetration_s": sim.settle.depenetration_s},
            "timings": sim.timings,
        }))
    });
    to_python(py, &result.py()?)
}

/// Removes an eval staging folder left by a failed run (after success it has been renamed).
struct Staging(Option<PathBuf>);

impl Drop for Staging {
    fn drop(&mut self) {
        if let Some(p) = self.0.as_ref().filter(|p| p.exists()) {
            let _ = std::fs::remove_dir_all(p);
        }
    }
}

/// `recon eval`: scores `predictions` (a file), or runs `method` ("observed", or "recgen")
/// over the dataset first. With "recgen" the model is `engine`, or loaded from `weights`,
/// `config`, `dtype` and `seed` as `recon eval --method recgen` loads it; the per-frame
/// flags are `recon infer`'s. Returns the report.
#[pyfunction]
#[pyo3(signature = (dataset, *, predictions=None, method=None, engine=None, out=None, shape="hull",
    f1_tau=recon::eval::EvalOptions::default().f1_tau_rel, scenes=None, occlusion=None,
    surface_samples=recon::eval::EvalOptions::default().n_samples, surface_seed=recon::eval::EvalOptions::default().seed, all_frames=false, two_view=false, views=None, weights=None, config=None,
    dtype=None, threads=None, **options))]
#[allow(clippy::too_many_arguments)]
pub fn eval<'py>(
    py: Python<'py>,
    dataset: PathBuf,
    predictions: Option<PathBuf>,
    method: Option<&str>,
    engine: Option<&Bound<'py, crate::engine::Engine>>,
    out: Option<PathBuf>,
    shape: &str,
    f1_tau: f64,
    scenes: Option<Vec<String>>,
    occlusion: Option<[f64; 2]>,
    surface_samples: usize,
    surface_seed: u64,
    all_frames: bool,
    two_view: bool,
    views: Option<usize>,
    weights: Option<PathBuf>,
    config: Option<PathBuf>,
    dtype: Option<&str>,
    threads: Option<usize>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<Bound<'py, PyAny>> {
    use crate::errors::config as config_err;
    use recon::engine::{begin_output, finish_output};
    use recon::eval::{evaluate, observe_dataset, read_predictions, EvalOptions, ObservedOptions, Shape};
    if !(f1_tau > 0.0 && f1_tau <= 1.0) {
        return Err(config_err("f1_tau", format!("{f1_tau} must be a fraction of the diameter in (0, 1]")));
    }
    if surface_samples == 0 {
        return Err(config_err("surface_samples", "must be positive"));
    }
    if let Some([lo, hi]) = occlusion {
        if !((0.0..100.0).contains(&lo) && hi > lo && hi <= 100.0) {
            return Err(config_err("occlusion", format!("({lo}, {hi}): expected (LO, HI) in percent, 0 ≤ LO < HI ≤ 100")));
        }
    }
    let shape = match shape {
        "hull" => Shape::Hull,
        "box" => Shape::Box,
        s => return Err(config_err("shape", format!("`{s}`: expected hull or box"))),
    };
    match method {
        None | Some("observed") | Some("recgen") => {}
        Some(m) => return Err(config_err("method", format!("`{m}`: expected observed or recgen"))),
    }
    if method.is_none() && predictions.is_none() {
        return Err(config_err("predictions", "give predictions=FILE or method=\"observed\"|\"recgen\""));
    }
    if method.is_some() && predictions.is_some() {
        return Err(config_err("predictions", "give predictions= or method=, not both"));
    }
    if two_view && method != Some("recgen") {
        return Err(config_err("two_view", "applies to method=\"recgen\" only"));
    }
    if views.is_some() && method != Some("recgen") {
        return Err(config_err("views", "applies to method=\"recgen\" only"));
    }
    if views.is_some() && two_view {
        return Err(config_err("views", "give views= or two_view=, not both"));
    }
    if let Some(n) = views.filter(|&n| n == 0 || n > recon::engine::MAX_SECOND_VIEWS + 1) {
        return Err(config_err("views", format!("{n}: expected 1 to {}", recon::engine::MAX_SECOND_VIEWS + 1)));
    }
    let views = views.unwrap_or(if two_view { 2 } else { 1 });
    let model_given = weights.is_some() || config.is_some() || dtype.is_some() || threads.is_some();
    let (o, io) = crate::engine::infer_options(options)?;
    let engine = match (method, engine) {
        (Some("recgen"), Some(_)) if model_given => {
            return Err(config_err("engine", "give engine= or weights/config/dtype/threads, not both"));
        }
        (Some("recgen"), Some(e)) => Some(e.get().shared()),
        // As `recon eval --method recgen`: the model loaded with the run's seed (which also
        // seeds weights="random").
        (Some("recgen"), None) => {
            let e = crate::engine::Engine::new(py, weights, config, dtype.unwrap_or("auto"), threads, o.seed)?;
            Some(e.shared())
        }
        _ if model_given => return Err(config_err("weights", "weights/config/dtype/threads apply to method=\"recgen\" only")),
        _ => None,
    };
    // The index file's record of the run, as before the options were one struct.
    let model = serde_json::json!({
        "samples": o.samples, "select": o.select, "pose_fit": o.pose_fit, "shape_fit": o.shape_fit, "seed": o.seed,
        "max_faces": o.max_faces, "steps": o.steps, "cfg": o.cfg, "min_component_area": o.min_component_area,
    });
    let method = method.map(str::to_string);
    let report = py.detach(move || -> recon::Result<serde_json::Value> {
        let mut ds = recon::dataset::load_dataset(&dataset)?;
        if let Some(s) = &scenes {
            ds.retain_scenes(s)?;
        }
        let opts = EvalOptions {
            n_samples: surface_samples,
            seed: surface_seed,
            f1_tau_rel: f1_tau,
            all_frames: all_frames || method.is_some(),
            occlusion,
            ..Default::default()
        };
        let staging = Staging(out.as_ref().map(|o| begin_output(o)).transpose()?);
        let (report, index) = match (method.as_deref(), &predictions) {
            (Some(m), _) => {
                let dir =
                    staging.0.clone().ok_or_else(|| recon::Error::input("out", format!("method={m} writes its predictions; give out=")))?;
                let outp = out.clone().unwrap_or_default();
                let (pf, index) = if m == "observed" {
                    let run = observe_dataset(&ds, &ObservedOptions { shape, ..Default::default() })?;
                    (run.write(&dir)?, serde_json::json!({"kind": "recon eval --method observed", "shape": shape, "skipped": run.skipped}))
                } else {
                    let (engine, pool) = engine.clone().ok_or_else(|| recon::Error::msg("no engine"))?;
                    let go = || recon::eval::recgen_dataset_views(&ds, &engine, &io, views, occlusion, &|_, _| {});
                    let run = match pool {
                        Some(p) => p.install(go)?,
                        None => go()?,
                    };
                    let idx = serde_json::json!({"kind": "recon eval --method recgen", "model": model, "two_view": two_view, "views": views,
                        "skipped": run.skipped, "seconds_model": run.seconds_model,
                        "poses": run.predictions.iter().map(|p| p.pose_record()).collect::<Vec<_>>()});
                    (run.write(&dir)?, idx)
                };
                // Score what was written, as the CLI does, so re-scoring reproduces it.
                let mut report = evaluate(&ds, &read_predictions(&pf)?, &pf, &opts)?;
                report.predictions = outp.join("predictions.json").display().to_string();
                (report, index)
            }
            (None, Some(p)) => {
                let mut preds = read_predictions(p)?;
                if scenes.is_some() {
                    preds.predictions.retain(|q| ds.frames.iter().any(|f| f.scene == q.scene));
                }
                (evaluate(&ds, &preds, p, &opts)?, serde_json::json!({"kind": "recon eval --predictions"}))
            }
            (None, None) => unreachable!("checked above"),
        };
        if let (Some(o), Some(dir)) = (&out, &staging.0) {
            report.write_files(dir)?;
            finish_output(dir, o, &index)?;
        }
        // to_value keeps every f64 as it is (parsing report.json's text back could move a
        // float by one ulp).
        serde_json::to_value(&report).map_err(|e| recon::Error::msg(e.to_string()))
    });
    to_python(py, &report.py()?)
}

/// `recon audit depth`: measured vs simulated depth of a dataset; returns the report
/// (and writes the CLI's files when `out` is given).
#[pyfunction]
#[pyo3(signature = (dataset, *, sensor=None, out=None, max_pixels=recon::audit::DepthOptions::default().max_pixels_per_frame, frames=None,
    alpha=recon::audit::SearchOptions::default().alpha, max_findings=recon::audit::SearchOptions::default().max_findings,
    robust=recon::audit::SearchOptions::default().robust, interactions=recon::audit::SearchOptions::default().interactions,
    max_folds=recon::audit::SearchOptions::default().max_folds, seed=recon::audit::SearchOptions::default().seed))]
#[allow(clippy::too_many_arguments)]
pub fn audit_depth<'py>(
    py: Python<'py>,
    dataset: PathBuf,
    sensor: Option<PathBuf>,
    out: Option<PathBuf>,
    max_pixels: usize,
    frames: Option<usize>,
    alpha: f64,
    max_findings: usize,
    robust: bool,
    interactions: bool,
    max_folds: usize,
    seed: u64,
) -> PyResult<Bound<'py, PyAny>> {
    use recon::audit::{collect, residual_table, DepthOptions, SearchOptions};
    let opts = SearchOptions { alpha, max_findings, robust, interactions, max_folds, seed, ..Default::default() };
    opts.validate().map_err(|e| ConfigError::new_err(e.keyword_message()))?;
    if max_pixels == 0 {
        return Err(config("max_pixels", "must be ≥ 1"));
    }
    let model = self::sensor(sensor)?;
    let report = py.detach(|| -> recon::Result<serde_json::Value> {
        let dopts = DepthOptions { max_pixels_per_frame: max_pixels, seed, max_frames: frames };
        let col = collect(&dataset, &model, &dopts)?;
        let mut table = residual_table(&model, &col.pixels, &dataset.display().to_string());
        table.unit_names = table
            .unit_names
            .iter()
            .map(|s| s.parse::<usize>().ok().and_then(|i| col.frame_names.get(i).cloned()).unwrap_or_else(|| s.clone()))
            .collect();
        let mut audit = recon::audit::audit_depth(&table, &opts, &model)?;
        if let Some(o) = &out {
            recon::audit::write_outputs(&mut audit, o, None)?;
        }
        serde_json::to_value(&audit.report).map_err(|e| recon::Error::msg(e.to_string()))
    });
    to_python(py, &report.py()?)
}

/// The frames of a BOP dataset (root or split) or a YCB-Video folder, each with what
/// `recon infer` is given for it: `frame` (`<scene>/<NNNNNN>`, also the output folder
/// below `out`), `rgb`, and `masks` (BOP: every GT instance's `mask_visib` file; YCB-Video:
/// the `-label.png` instance map). Depth and intrinsics are found beside `rgb`.
#[pyfunction]
pub fn dataset_frames<'py>(py: Python<'py>, source: PathBuf) -> PyResult<Bound<'py, PyAny>> {
    let frames = py.detach(|| -> recon::Result<Vec<serde_json::Value>> {
        let ds = recon::dataset::load_dataset(&source)?;
        Ok(ds
            .frames
            .iter()
            .map(|f| {
                let masks: Vec<PathBuf> = match ds.layout {
                    recon::dataset::Layout::Ycbv => vec![ds.root.join(&f.scene).join(format!("{:06}-label.png", f.frame))],
                    recon::dataset::Layout::Bop => (0..f.gt.len())
                        .map(|g| ds.root.join(&f.scene).join("mask_visib").join(format!("{:06}_{g:06}.png", f.frame)))
                        .collect(),
                };
                serde_json::json!({
                    "frame": format!("{}/{:06}", f.scene, f.frame),
                    "rgb": ds.rgb_path(f), "masks": masks,
                })
            })
            .collect())
    });
    to_python(py, &frames.py()?)
}

/// Keep large freed buffers in the process heap for reuse (glibc's thresholds), for
/// every library of the process. recon's own large buffers are already reused by
/// size (the extension's allocator, as in the `recon` CLI), so this is only for other
/// libraries' allocations; it raises peak memory a little. Process-wide, so opt-in.
/// Returns whether it took effect (`False` off glibc).
#[pyfunction]
pub fn keep_freed_memory() -> bool {
    recon::util::keep_freed_memory()
}
