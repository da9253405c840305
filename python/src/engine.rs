//! `recon_rgbd.Engine` (a loaded model, [`recon::engine::Engine`]) and the objects it returns.
//!
//! The engine is immutable once loaded, so one Python object serves several threads:
//! every call releases the GIL for its whole computation, and with `threads=N` runs in
//! the engine's own rayon pool.

use crate::convert::{from_python, rows, to_python};
use crate::errors::{config, input, weights_to_py, ConfigError, IntoPy, WeightsError};
use clap::ValueEnum;
use numpy::{PyArrayMethods, PyReadonlyArray1, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use recon::dataset::{Intrinsics, MaskSkip, ObjectMask, RgbdFrame};
use recon::engine::{
    Dtype, FrameImage, FrameResult, InferOptions, InferSettings, ModelSource, ObjectResult, RecgenFiles, RecgenPose, SecondView, ViewSpec,
};
use recon::geometry::pose::PoseRepresentation;
use recon::math::Similarity;
use std::path::PathBuf;
use std::sync::Arc;

/// A CLI enum from its flag value (`"cross"`, `"depth-stretch"`, …).
fn parse_enum<T: ValueEnum>(flag: &str, v: &str) -> PyResult<T> {
    T::from_str(v, false).map_err(|_| {
        let names: Vec<String> =
            T::value_variants().iter().filter_map(|x| x.to_possible_value()).map(|p| p.get_name().to_string()).collect();
        config(flag, format!("`{v}`: expected one of {}", names.join(", ")))
    })
}

/// The per-frame options from a call's keyword arguments: the names, defaults and checks
/// are the library's ([`InferOptions`], `recon infer`'s flags with `_`); an unknown keyword
/// is an error listing the valid ones.
pub(crate) fn infer_options(options: Option<&Bound<'_, PyDict>>) -> PyResult<(InferOptions, InferSettings)> {
    let v = match options {
        Some(d) => from_python(d.as_any())?,
        None => serde_json::Value::Object(Default::default()),
    };
    let opts = InferOptions::from_json(v).map_err(|e| ConfigError::new_err(e.keyword_message()))?;
    let settings = opts.settings().map_err(|e| ConfigError::new_err(e.keyword_message()))?;
    Ok((opts, settings))
}

/// `InferOptions::default()` as a dict: the defaults of every per-frame keyword.
#[pyfunction]
pub fn infer_defaults(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    to_python(py, &InferOptions::default())
}

/// Intrinsics from a 3×3 K (any float or int array-like).
fn intrinsics(k: &Bound<'_, PyAny>, what: &str) -> PyResult<Intrinsics> {
    let np = k.py().import("numpy")?;
    let a: PyReadonlyArray2<f64> =
        np.call_method1("asarray", (k, "float64"))?.extract().map_err(|_| input(what, "expected a 3×3 matrix"))?;
    let a = a.as_array();
    if a.shape() != [3, 3] {
        return Err(input(what, format!("expected a 3×3 matrix, got shape {:?}", a.shape())));
    }
    Intrinsics::new(a[[0, 0]], a[[1, 1]], a[[0, 2]], a[[1, 2]]).map_err(|e| input(what, e))
}

/// An array from what people hold images in: numpy arrays (any layout), PIL images and torch
/// CPU tensors (`__array__`), other DLPack producers (`__dlpack__`).
fn as_ndarray<'py>(x: &Bound<'py, PyAny>, what: &str) -> PyResult<Bound<'py, PyAny>> {
    let np = x.py().import("numpy")?;
    let arr = if !x.hasattr("__array__")? && !x.hasattr("__array_interface__")? && x.hasattr("__dlpack__")? {
        np.call_method1("from_dlpack", (x,))
    } else {
        np.call_method1("asarray", (x,))
    };
    arr.map_err(|e| input(what, format!("cannot be read as an array ({e})")))
}

/// `rgb` as H×W×3 uint8 without loss: uint8 as it is, other integers when every value is in
/// 0..=255, floats when every value is in [0, 1] (× 255, rounded: the usual float-image
/// convention). Anything else is refused, naming the argument.
fn rgb_u8<'py>(rgb: &Bound<'py, PyAny>, what: &str) -> PyResult<Bound<'py, PyAny>> {
    let np = rgb.py().import("numpy")?;
    let a = as_ndarray(rgb, what)?;
    let dtype = a.getattr("dtype")?;
    let kind: String = dtype.getattr("kind")?.extract()?;
    let size: usize = a.getattr("size")?.extract()?;
    let range = || -> PyResult<(f64, f64)> {
        if size == 0 {
            return Ok((0.0, 0.0));
        }
        Ok((np.call_method1("min", (&a,))?.extract()?, np.call_method1("max", (&a,))?.extract()?))
    };
    match kind.as_str() {
        "u" if dtype.getattr("itemsize")?.extract::<usize>()? == 1 => Ok(a),
        "u" | "i" => {
            let (lo, hi) = range()?;
            if lo < 0.0 || hi > 255.0 {
                return Err(input(what, format!("{dtype} values {lo}..{hi} do not fit 8-bit colour without loss: expected 0..255")));
            }
            a.call_method1("astype", ("uint8",))
        }
        "f" => {
            let finite: bool = np.call_method1("isfinite", (&a,))?.call_method0("all")?.extract()?;
            if !finite {
                return Err(input(what, format!("{dtype} colour must be finite and in [0, 1] (it holds NaN or infinity)")));
            }
            let (lo, hi) = range()?;
            if lo < 0.0 || hi > 1.0 {
                return Err(input(
                    what,
                    format!("{dtype} colour must be finite and in [0, 1] (got {lo}..{hi}); pass uint8 0..255 for other ranges"),
                ));
            }
            np.call_method1("rint", (a.call_method1("__mul__", (255.0,))?,))?.call_method1("astype", ("uint8",))
        }
        _ => Err(input(what, format!("expected an H×W×3 uint8 array (or float in [0, 1]), got dtype {dtype}"))),
    }
}

/// `depth` as uint16 units or float metres, without loss, with the `depth_scale` still to
/// apply: uint16 (× `depth_scale`, default 0.001) and float16/32/64 metres as they are; other
/// integers only with `depth_scale` (their unit is not known otherwise), scaled here.
fn depth_array<'py>(depth: &Bound<'py, PyAny>, depth_scale: Option<f64>, what: &str) -> PyResult<(Bound<'py, PyAny>, Option<f64>)> {
    let a = as_ndarray(depth, what)?;
    let dtype = a.getattr("dtype")?;
    let kind: String = dtype.getattr("kind")?.extract()?;
    let item: usize = dtype.getattr("itemsize")?.extract()?;
    match (kind.as_str(), item) {
        ("u", 2) | ("f", 4) | ("f", 8) => Ok((a, depth_scale)),
        ("f", 2) => Ok((a.call_method1("astype", ("float32",))?, depth_scale)),
        ("u" | "i", _) => {
            let Some(s) = depth_scale else {
                return Err(input(
                    what,
                    format!("{dtype} depth has no known unit: pass depth_scale (metres per unit), or give uint16 (millimetres by default) or float metres"),
                ));
            };
            if !(s.is_finite() && s > 0.0) {
                return Err(config("depth_scale", format!("must be positive metres per unit, got {s}")));
            }
            let np = depth.py().import("numpy")?;
            let size: usize = a.getattr("size")?.extract()?;
            if size > 0 && np.call_method1("min", (&a,))?.extract::<f64>()? < 0.0 {
                return Err(input(what, "negative depth values"));
            }
            // float64 holds every integer below 2^53 exactly; the scale is applied as for uint16.
            Ok((a.call_method1("astype", ("float64",))?.call_method1("__mul__", (s,))?, None))
        }
        _ => Err(input(what, format!("expected an H×W uint16 (with depth_scale) or float metres array, got dtype {dtype}"))),
    }
}

/// An RGB-D frame from arrays: `rgb` H×W×3 uint8 (or what converts to it without loss,
/// [`rgb_u8`]); `depth` H×W uint16 (× `depth_scale` metres, default 0.001) or float metres
/// ([`depth_array`]). numpy arrays of any layout, PIL images, torch tensors (`__array__`) and
/// DLPack producers are read.
pub(crate) fn frame_from_arrays(
    rgb: &Bound<'_, PyAny>,
    depth: &Bound<'_, PyAny>,
    k: &Bound<'_, PyAny>,
    depth_scale: Option<f64>,
    name: &str,
) -> PyResult<RgbdFrame> {
    let rgb = rgb_u8(rgb, &format!("{name} rgb"))?;
    let rgb: PyReadonlyArray3<u8> = rgb.extract().map_err(|_| input(&format!("{name} rgb"), "expected an H×W×3 uint8 array"))?;
    let [h, w, c] = <[usize; 3]>::try_from(rgb.shape()).map_err(|_| input(name, "rgb must be H×W×3"))?;
    if c != 3 {
        return Err(input(&format!("{name} rgb"), format!("expected H×W×3 uint8, got {h}×{w}×{c}")));
    }
    // One copy into the frame's own buffer (a no-op reinterpretation is not possible: the
    // frame owns its pixels); C-contiguous input is copied as one block. (numpy's `as_slice`
    // also accepts Fortran order, in memory order: ndarray's standard-layout slice does not.)
    let rgb_v: Vec<u8> = match rgb.as_array().as_slice() {
        Some(s) => s.to_vec(),
        None => rgb.as_array().iter().copied().collect(),
    };
    let dname = format!("{name} depth");
    let (depth, depth_scale) = depth_array(depth, depth_scale, &dname)?;
    let depth = &depth;
    let depth_v: Vec<f32> = if let Ok(d) = depth.extract::<PyReadonlyArray2<u16>>() {
        if d.shape() != [h, w] {
            return Err(input(&dname, format!("shape {:?} but rgb is {h}×{w}; depth must be registered to colour", d.shape())));
        }
        let s = depth_scale.unwrap_or(0.001);
        if !(s.is_finite() && s > 0.0) {
            return Err(config("depth_scale", format!("must be positive metres per unit, got {s}")));
        }
        d.as_array().iter().map(|&v| (v as f64 * s) as f32).collect()
    } else if let Ok(d) = depth.extract::<PyReadonlyArray2<f32>>() {
        if d.shape() != [h, w] {
            return Err(input(&dname, format!("shape {:?} but rgb is {h}×{w}; depth must be registered to colour", d.shape())));
        }
        if depth_scale.is_some() {
            return Err(config("depth_scale", "applies to uint16 depth; float depth is already in metres"));
        }
        match d.as_array().as_slice() {
            Some(s) => s.to_vec(),
            None => d.as_array().iter().copied().collect(),
        }
    } else if let Ok(d) = depth.extract::<PyReadonlyArray2<f64>>() {
        if d.shape() != [h, w] {
            return Err(input(&dname, format!("shape {:?} but rgb is {h}×{w}; depth must be registered to colour", d.shape())));
        }
        if depth_scale.is_some() {
            return Err(config("depth_scale", "applies to uint16 depth; float depth is already in metres"));
        }
        d.as_array().iter().map(|&v| v as f32).collect()
    } else {
        return Err(input(&dname, "expected an H×W uint16 (with depth_scale) or float32 metres array"));
    };
    RgbdFrame::from_buffers(w, h, rgb_v, depth_v, intrinsics(k, &format!("{name} K"))?, name).py()
}

/// Masks: an H×W instance-id image (0 = background; ids ascending) or a list of H×W
/// boolean masks (labelled `mask 0`, `mask 1`, … and matched by order across views).
fn masks_from(m: &Bound<'_, PyAny>, what: &str) -> PyResult<(Vec<ObjectMask>, Vec<MaskSkip>)> {
    let np = m.py().import("numpy")?;
    if let Ok(list) = m.cast::<PyList>() {
        let mut out = Vec::new();
        for (i, x) in list.iter().enumerate() {
            let a: PyReadonlyArray2<bool> = np
                .call_method1("asarray", (x, "bool"))?
                .extract()
                .map_err(|_| input(what, format!("mask {i}: expected an H×W boolean array")))?;
            let (h, w) = (a.shape()[0], a.shape()[1]);
            let mask: Vec<bool> = a.as_array().iter().copied().collect();
            out.push(ObjectMask::from_bools(None, format!("mask {i}"), w, h, &mask));
        }
        return Ok((out, Vec::new()));
    }
    let arr = np.call_method1("asarray", (m,))?;
    let kind: String = arr.getattr("dtype")?.getattr("kind")?.extract()?;
    if !matches!(kind.as_str(), "u" | "i") {
        return Err(input(what, format!("expected an H×W integer instance-id image or a list of boolean masks, got dtype kind `{kind}`")));
    }
    let ids: PyReadonlyArray2<i64> =
        np.call_method1("asarray", (arr, "int64"))?.extract().map_err(|_| input(what, "an instance-id image must be H×W"))?;
    let (h, w) = (ids.shape()[0], ids.shape()[1]);
    let mut v = Vec::with_capacity(h * w);
    for &x in ids.as_array().iter() {
        v.push(u32::try_from(x).map_err(|_| input(what, format!("instance id {x} is not in 0..=4294967295")))?);
    }
    let map = recon::dataset::InstanceMap { width: w, height: h, ids: v, path: PathBuf::from(what) };
    Ok(map.objects(None))
}

/// A view besides the anchor from a dict of arrays (`view2=` or an item of `views=`):
/// "rgb", "depth", "K", "masks", the pose `pose_key` (this camera → camera 1, 4×4) and
/// optionally "depth_scale". `name` labels errors (`view2`, `views[1]`).
fn array_view(py: Python<'_>, v: &Bound<'_, PyAny>, name: &str, pose_key: &str) -> PyResult<(RgbdFrame, Vec<ObjectMask>, Similarity)> {
    let keys = format!("rgb, depth, K, masks, {pose_key}[, depth_scale]");
    let v = v.cast::<PyDict>().map_err(|_| input(name, format!("expected a dict with {keys}")))?;
    let get = |k: &str| -> PyResult<Bound<'_, PyAny>> { v.get_item(k)?.ok_or_else(|| input(name, format!("missing key `{k}` ({keys})"))) };
    let ds: Option<f64> = v.get_item("depth_scale")?.map(|x| x.extract()).transpose()?;
    let frame = frame_from_arrays(&get("rgb")?, &get("depth")?, &get("K")?, ds, &format!("<{name} array>"))?;
    let (objects, _) = masks_from(&get("masks")?, &format!("{name} masks"))?;
    let np = py.import("numpy")?;
    let what = format!("{name} {pose_key}");
    let t: PyReadonlyArray2<f64> =
        np.call_method1("asarray", (get(pose_key)?, "float64"))?.extract().map_err(|_| input(&what, "expected a 4×4 matrix"))?;
    if t.shape() != [4, 4] {
        return Err(input(&what, format!("expected a 4×4 matrix, got {:?}", t.shape())));
    }
    let flat: Vec<f64> = t.as_array().iter().copied().collect();
    let rel = recon::geometry::rel_pose_from_numbers(&flat, name, pose_key).py()?;
    Ok((frame, objects, rel))
}

/// JSON-ready view dict values: paths as text (`os.fspath`), arrays as lists.
fn plain<'py>(x: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
    let py = x.py();
    if x.hasattr("__fspath__")? {
        return py.import("os")?.call_method1("fspath", (x,));
    }
    if x.hasattr("tolist")? {
        return x.call_method0("tolist");
    }
    if x.is_instance_of::<PyList>() || x.is_instance_of::<pyo3::types::PyTuple>() {
        let items = x.try_iter()?.map(|i| plain(&i?)).collect::<PyResult<Vec<_>>>()?;
        return Ok(PyList::new(py, items)?.into_any());
    }
    Ok(x.clone())
}

/// The `views=` of `reconstruct_files`: view files (`recon infer --view`) or dicts of
/// the same keys (relative paths from the working folder), checked before any is read.
fn view_specs(views: Option<&Bound<'_, PyAny>>) -> PyResult<Vec<ViewSpec>> {
    let Some(views) = views.filter(|v| !v.is_none()) else { return Ok(Vec::new()) };
    let items: Vec<Bound<'_, PyAny>> = views.try_iter()?.collect::<PyResult<_>>()?;
    recon::engine::check_view_count(items.len()).py()?;
    items
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let label = format!("views[{i}]");
            if let Ok(d) = v.cast::<PyDict>() {
                let clean = PyDict::new(v.py());
                for (k, x) in d.iter() {
                    clean.set_item(k, plain(&x)?)?;
                }
                ViewSpec::from_json(&from_python(clean.as_any())?, std::path::Path::new(""), &label).py()
            } else {
                let p: PathBuf = v.extract().map_err(|_| input(&label, "expected a view file path or a dict (rgb, masks, T_c1_ci, …)"))?;
                ViewSpec::from_file(&p, &label).py()
            }
        })
        .collect()
}

/// Says once per process that the default model answers: a toy next to RecGen's released
/// weights, which a user who passed no `weights=` may not know.
fn warn_default_model(py: Python<'_>) -> PyResult<()> {
    static WARNED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    if WARNED.swap(true, std::sync::atomic::Ordering::Relaxed) {
        return Ok(());
    }
    let category = py.get_type::<crate::errors::DefaultModelWarning>();
    // stacklevel 1: the warning points at the Python line that built the engine.
    PyErr::warn(py, &category, DEFAULT_MODEL_WARNING, 1)
}

/// The text of [`warn_default_model`].
pub(crate) const DEFAULT_MODEL_WARNING: &std::ffi::CStr = c"recon_rgbd: no weights given, so the embedded recgen-nano answers: \
a 27 MB model trained on recon's synthetic scenes that has never seen a real object. For RecGen's released \
weights run `python -m recon_rgbd weights fetch recgen` once, then use Engine(weights=\"recgen\") \
(or Engine.from_pretrained(\"TRI-ML/RecGen\")); Engine(weights=\"random\") is plumbing only. \
This warning is a recon_rgbd.DefaultModelWarning (a UserWarning), given once per process.";

/// A loaded model, reused across objects, frames and threads.
#[pyclass(frozen, module = "recon_rgbd")]
pub struct Engine {
    engine: Arc<recon::engine::Engine>,
    pool: Option<Arc<rayon::ThreadPool>>,
    source: String,
}

impl Engine {
    /// The model and its pool, for library calls that take an engine (`recon eval`).
    pub(crate) fn shared(&self) -> (Arc<recon::engine::Engine>, Option<Arc<rayon::ThreadPool>>) {
        (self.engine.clone(), self.pool.clone())
    }

    /// Run `f` without the GIL, in the engine's pool when it has one.
    fn compute<T: Send>(&self, py: Python<'_>, f: impl FnOnce(&recon::engine::Engine) -> T + Send) -> T {
        let engine = &self.engine;
        let pool = self.pool.clone();
        py.detach(move || match pool {
            Some(p) => p.install(|| f(engine)),
            None => f(engine),
        })
    }
}

/// Calls a Python callable with progress dictionaries (from any thread).
fn progress_fn(cb: Option<Py<PyAny>>) -> impl Fn(recon::engine::Progress) + Sync {
    move |e: recon::engine::Progress| {
        let Some(cb) = cb.as_ref() else { return };
        Python::attach(|py| {
            use recon::engine::Progress as P;
            let d = PyDict::new(py);
            let r: PyResult<()> = (|| {
                match e {
                    P::Object { index, total, label } => {
                        d.set_item("event", "object")?;
                        d.set_item("index", index)?;
                        d.set_item("total", total)?;
                        d.set_item("object", label)?;
                    }
                    P::Sample { index, total, seed } => {
                        d.set_item("event", "sample")?;
                        d.set_item("index", index)?;
                        d.set_item("total", total)?;
                        d.set_item("seed", seed)?;
                    }
                    P::Stage(s) => {
                        d.set_item("event", "stage")?;
                        d.set_item("stage", s.name())?;
                    }
                    P::Decimating => d.set_item("event", "decimating")?,
                    P::Selecting => d.set_item("event", "selecting")?,
                    P::ObjectDone { label, seconds } => {
                        d.set_item("event", "object_done")?;
                        d.set_item("object", label)?;
                        d.set_item("seconds", seconds)?;
                    }
                }
                cb.call1(py, (d,))?;
                Ok(())
            })();
            // A failing callback must not abort the reconstruction; Python reports it.
            if let Err(err) = r {
                err.write_unraisable(py, Some(cb.bind(py)));
            }
        })
    }
}

#[pymethods]
impl Engine {
    #[new]
    #[pyo3(signature = (weights=None, config=None, dtype="auto", threads=None, seed=42))]
    pub(crate) fn new(
        py: Python<'_>,
        weights: Option<PathBuf>,
        config: Option<PathBuf>,
        dtype: &str,
        threads: Option<usize>,
        seed: u64,
    ) -> PyResult<Self> {
        let dtype = parse_enum::<Dtype>("dtype", dtype)?;
        let w = weights.as_ref().map(|p| p.to_string_lossy().into_owned());
        let source = ModelSource::parse(w.as_deref(), config.as_deref(), seed).map_err(weights_to_py)?;
        let pool = match threads {
            Some(0) => return Err(crate::errors::config("threads", "must be at least 1")),
            Some(n) => Some(Arc::new(
                rayon::ThreadPoolBuilder::new().num_threads(n).build().map_err(|e| crate::errors::ReconError::new_err(e.to_string()))?,
            )),
            None => None,
        };
        let load = source.load_options(dtype).map_err(weights_to_py)?;
        let src = source.clone();
        let engine = py
            .detach(|| match &pool {
                Some(p) => p.install(|| recon::engine::Engine::load(&src, &load)),
                None => recon::engine::Engine::load(&src, &load),
            })
            .map_err(weights_to_py)?;
        if source == ModelSource::Default {
            warn_default_model(py)?;
        }
        Ok(Engine { engine: Arc::new(engine), pool, source: format!("{source:?}") })
    }

    /// RecGen's released weights from a Hugging Face repository: `weights="hf:REPO[@REVISION]"`
    /// (`recon infer --weights hf:REPO[@REV]`). Files the Hugging Face cache (HF_HUB_CACHE, else
    /// HF_HOME/hub) lacks are downloaded into it through hf-hub, with a progress bar, unless
    /// HF_HUB_OFFLINE is set; HF_TOKEN for gated repos. `revision`: a commit, branch or tag
    /// (default: the manifest's pinned commit for TRI-ML/RecGen, else `main`). `manifest`: a
    /// manifest file for this repo (what `python -m recon_rgbd weights manifest recgen --pin`
    /// writes for a fine-tune or a mirror) whose SHA-256 pins and tensor lists are checked
    /// instead of the ones recon carries.
    #[classmethod]
    #[pyo3(signature = (repo, revision=None, *, manifest=None, config=None, dtype="auto", threads=None))]
    #[allow(clippy::too_many_arguments)]
    fn from_pretrained(
        _cls: &Bound<'_, pyo3::types::PyType>,
        py: Python<'_>,
        repo: &str,
        revision: Option<&str>,
        manifest: Option<PathBuf>,
        config: Option<PathBuf>,
        dtype: &str,
        threads: Option<usize>,
    ) -> PyResult<Self> {
        let repo = repo.strip_prefix("hf:").unwrap_or(repo);
        let spec = match revision {
            Some(r) => format!("hf:{repo}@{r}"),
            None => format!("hf:{repo}"),
        };
        let weights = match manifest {
            None => spec,
            Some(path) => {
                // The spec is not loaded then, but a bad repo or revision is still refused.
                recon::engine::parse_hf(&spec["hf:".len()..]).map_err(weights_to_py)?;
                let file = path.display().to_string();
                let m = recon::weights::Manifest::load(&file).map_err(weights_to_py)?;
                let bad = |what: String| WeightsError::new_err(format!("from_pretrained: manifest {file}: {what}"));
                if !m.repo.as_deref().is_some_and(|r| r.eq_ignore_ascii_case(repo)) {
                    return Err(bad(format!("is for repo `{}`, not `{repo}`", m.repo.as_deref().unwrap_or("(none)"))));
                }
                if let Some(r) = revision.filter(|r| Some(*r) != m.revision.as_deref()) {
                    return Err(bad(format!(
                        "pins revision `{}`, not `{r}`; pass revision=None, or a manifest pinned at `{r}`",
                        m.revision()
                    )));
                }
                file
            }
        };
        Engine::new(py, Some(PathBuf::from(weights)), config, dtype, threads, 42)
    }

    /// Where this engine's model comes from (`ModelSource`, as `repr` shows it): `Default` is
    /// the embedded recgen-nano.
    #[getter]
    fn model(&self) -> String {
        self.source.clone()
    }

    /// Whether the weights are random (`weights="random"`: plumbing only).
    #[getter]
    fn random_weights(&self) -> bool {
        self.engine.pipeline.weights().is_random()
    }

    fn __repr__(&self) -> String {
        format!("recon_rgbd.Engine({})", self.source)
    }

    #[pyo3(signature = (rgb, depth, K, masks, *, depth_scale=None, view2=None, views=None, progress=None, **options))]
    #[allow(non_snake_case, clippy::too_many_arguments)]
    fn reconstruct(
        &self,
        py: Python<'_>,
        rgb: &Bound<'_, PyAny>,
        depth: &Bound<'_, PyAny>,
        K: &Bound<'_, PyAny>,
        masks: &Bound<'_, PyAny>,
        depth_scale: Option<f64>,
        view2: Option<&Bound<'_, PyDict>>,
        views: Option<&Bound<'_, PyAny>>,
        progress: Option<Py<PyAny>>,
        options: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Vec<Object>> {
        let (_, opts) = infer_options(options)?;
        // The views besides the anchor, counted before any is converted: view2, then views.
        let more: Vec<Bound<'_, PyAny>> = match views.filter(|v| !v.is_none()) {
            Some(v) => v.try_iter()?.collect::<PyResult<_>>()?,
            None => Vec::new(),
        };
        recon::engine::check_view_count(view2.iter().count() + more.len()).py()?;
        let frame = frame_from_arrays(rgb, depth, K, depth_scale, "<array>")?;
        let (objects, _) = masks_from(masks, "masks")?;
        let mut others = Vec::new();
        if let Some(v) = view2 {
            others.push(array_view(py, v.as_any(), "view2", "T_c1_c2")?);
        }
        for (i, v) in more.iter().enumerate() {
            others.push(array_view(py, v, &format!("views[{i}]"), "T_c1_ci")?);
        }
        let report = progress_fn(progress);
        let result = self.compute(py, |e| {
            let sv = others.iter().map(|(f, o, rel)| SecondView { frame: f, objects: o.clone(), t_c1_c2: *rel }).collect();
            e.reconstruct_views(&frame, objects, sv, &opts, &report)
        });
        let result = result.py()?;
        let shared = FrameShared::new(py, &result)?;
        result.objects.into_iter().map(|o| Object::new(py, o, &shared)).collect()
    }

    /// `recon infer` on files: the same discovery, the same calls, the same output folder.
    #[pyo3(signature = (rgbd, masks, out=None, *, depth=None, intrinsics=None, depth_scale=None, objects=None, views=None, progress=None, **options))]
    #[allow(clippy::too_many_arguments)]
    fn reconstruct_files<'py>(
        &self,
        py: Python<'py>,
        rgbd: PathBuf,
        masks: &Bound<'py, PyAny>,
        out: Option<PathBuf>,
        depth: Option<PathBuf>,
        intrinsics: Option<&Bound<'py, PyAny>>,
        depth_scale: Option<f64>,
        objects: Option<Vec<u32>>,
        views: Option<&Bound<'py, PyAny>>,
        progress: Option<Py<PyAny>>,
        options: Option<&Bound<'py, PyDict>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (options, opts) = infer_options(options)?;
        let specs = view_specs(views)?;
        let masks: Vec<PathBuf> = match masks.extract::<PathBuf>() {
            Ok(p) => vec![p],
            Err(_) => masks.extract()?,
        };
        let fo = crate::convert::frame_options(depth, intrinsics, depth_scale)?;
        let out = out.unwrap_or_else(|| {
            let stem = rgbd.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "frame".into());
            rgbd.with_file_name(format!("{stem}_recon"))
        });
        let report = progress_fn(progress);
        let summary = self.compute(py, |e| -> recon::Result<serde_json::Value> {
            let frame = RgbdFrame::open(&rgbd, &fo)?;
            let (objs, mut skipped) = recon::dataset::load_masks(&masks, objects.as_deref())?;
            // As `recon infer --view`: a view's unreadable masks are listed, and cost that view only.
            let mut opened = Vec::with_capacity(specs.len());
            for (i, spec) in specs.iter().enumerate() {
                let v = spec.open(objects.as_deref())?;
                skipped.extend(v.skipped.iter().cloned().map(|mut s| {
                    s.label = format!("view {} {}", i + 2, s.label);
                    s
                }));
                opened.push(v);
            }
            let others = opened.iter().map(|v| SecondView { frame: &v.frame, objects: v.objects.clone(), t_c1_c2: v.t_c1_ci }).collect();
            let result = e.reconstruct_views(&frame, objs, others, &opts, &report)?;
            skipped.extend(result.skipped.iter().cloned());
            let written = recon::engine::write_outputs(&result, &out)?;
            let objs: Vec<serde_json::Value> = result
                .objects
                .iter()
                .zip(&written)
                .map(|(o, w)| {
                    let st = recon::engine::stage_seconds(o);
                    serde_json::json!({
                        "object": o.label, "id": o.id,
                        "rotation": o.pose_camera.rotation, "translation_m": o.pose_camera.translation, "scale_m": o.pose_camera.scale,
                        "score_m": o.selection.score_m, "uncertainty": o.uncertainty,
                        "faces": o.mesh_camera.as_ref().map(|m| m.faces.len()),
                        "stage_seconds": recon::engine::STAGE_COLUMNS.iter().zip(st).map(|(k, v)| (k.to_string(), serde_json::json!(v))).collect::<serde_json::Map<_, _>>(),
                        "files": w,
                    })
                })
                .collect();
            Ok(serde_json::json!({
                "out": out, "seed": options.seed, "preprocess_s": result.preprocess_seconds, "objects": objs,
                "skipped": skipped.iter().map(|s| serde_json::json!({"object": s.label, "reason": s.reason.to_string()})).collect::<Vec<_>>(),
                "notes": result.notes,
            }))
        });
        to_python(py, &summary.py()?)
    }
}

/// Vertices, faces and per-vertex colours of a mesh in the camera frame (metres).
#[pyclass(frozen, module = "recon_rgbd")]
pub struct Mesh {
    /// float32 N×3, camera frame of view 1 (OpenCV: x right, y down, z forward), metres.
    #[pyo3(get)]
    vertices: Py<PyAny>,
    /// int32 M×3 vertex indices.
    #[pyo3(get)]
    faces: Py<PyAny>,
    /// float32 N×6 in [0, 1] (TRELLIS's colour channels: RGB, then a normal-map triple), or None.
    #[pyo3(get)]
    attributes: Py<PyAny>,
}

/// An `N×K` array of `dtype` (any array-like) as rows, or an input error naming `what`.
fn array_rows<T: numpy::Element + Copy, const K: usize>(a: &Bound<'_, PyAny>, dtype: &str, what: &str) -> PyResult<Vec<[T; K]>> {
    let np = a.py().import("numpy")?;
    let bad = || input(what, format!("expected an N×{K} {dtype} array"));
    let arr: PyReadonlyArray2<T> = np.call_method1("ascontiguousarray", (a, dtype))?.extract().map_err(|_| bad())?;
    if arr.shape()[1] != K {
        return Err(bad());
    }
    Ok(arr.as_array().rows().into_iter().map(|r| std::array::from_fn(|k| r[k])).collect())
}

#[pymethods]
impl Mesh {
    /// A mesh from arrays (checked: faces index the vertices): float32 N×3 vertices, int
    /// M×3 faces, optional float32 N×6 attributes. `recon_rgbd.Client` builds its objects' meshes so.
    #[new]
    #[pyo3(signature = (vertices, faces, attributes=None))]
    fn py_new(
        py: Python<'_>,
        vertices: &Bound<'_, PyAny>,
        faces: &Bound<'_, PyAny>,
        attributes: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let vertices = array_rows::<f32, 3>(vertices, "float32", "vertices")?;
        let faces: Vec<[i64; 3]> = array_rows::<i64, 3>(faces, "int64", "faces")?;
        let faces = faces
            .into_iter()
            .map(|f| {
                let ok = f.iter().all(|&i| (0..vertices.len() as i64).contains(&i));
                ok.then(|| f.map(|i| i as u32))
                    .ok_or_else(|| input("faces", format!("face {f:?} indexes past {} vertices", vertices.len())))
            })
            .collect::<PyResult<Vec<_>>>()?;
        let vertex_attrs = attributes.filter(|a| !a.is_none()).map(|a| array_rows::<f32, 6>(a, "float32", "attributes")).transpose()?;
        if vertex_attrs.as_ref().is_some_and(|a| a.len() != vertices.len()) {
            return Err(input("attributes", "needs one row per vertex"));
        }
        Mesh::new(py, recon::mesh::Mesh { vertices, faces, vertex_attrs })
    }

    /// float32 N×3 RGB in [0, 1] (a view of `attributes`), or None.
    #[getter]
    fn colors<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let a = self.attributes.bind(py);
        if a.is_none() {
            return Ok(a.clone());
        }
        let s = py.import("builtins")?.getattr("slice")?;
        a.get_item((s.call1((py.None(),))?, s.call1((0, 3))?))
    }

    fn __repr__(&self, py: Python<'_>) -> PyResult<String> {
        let n: usize = self.vertices.bind(py).len()?;
        let m: usize = self.faces.bind(py).len()?;
        Ok(format!("recon_rgbd.Mesh({n} vertices, {m} faces)"))
    }
}

impl Mesh {
    fn new(py: Python<'_>, m: recon::mesh::Mesh) -> PyResult<Self> {
        let faces: Vec<[i32; 3]> = m.faces.iter().map(|f| f.map(|i| i as i32)).collect();
        Ok(Mesh {
            vertices: rows(py, m.vertices)?.unbind(),
            faces: rows(py, faces)?.unbind(),
            attributes: match m.vertex_attrs {
                Some(a) => rows(py, a)?.unbind(),
                None => py.None(),
            },
        })
    }

    /// Back to recon's mesh (one copy), for the exporters.
    fn to_recon(&self, py: Python<'_>) -> PyResult<recon::mesh::Mesh> {
        let v: PyReadonlyArray2<f32> = self.vertices.bind(py).extract()?;
        let f: PyReadonlyArray2<i32> = self.faces.bind(py).extract()?;
        let vertices: Vec<[f32; 3]> = v.as_array().rows().into_iter().map(|r| [r[0], r[1], r[2]]).collect();
        let faces: Vec<[u32; 3]> = f.as_array().rows().into_iter().map(|r| [r[0] as u32, r[1] as u32, r[2] as u32]).collect();
        let attrs = self.attributes.bind(py);
        let vertex_attrs = if attrs.is_none() {
            None
        } else {
            let a: PyReadonlyArray2<f32> = attrs.extract()?;
            Some(a.as_array().rows().into_iter().map(|r| [r[0], r[1], r[2], r[3], r[4], r[5]]).collect())
        };
        Ok(recon::mesh::Mesh { vertices, faces, vertex_attrs })
    }
}

/// 3D Gaussians in the camera frame (metres).
#[pyclass(frozen, module = "recon_rgbd")]
pub struct Gaussians {
    /// float32 N×3 centres.
    #[pyo3(get)]
    means: Py<PyAny>,
    /// float32 N×3 standard deviations along the local axes (metres).
    #[pyo3(get)]
    scales: Py<PyAny>,
    /// float32 N×4 unit quaternions (w, x, y, z).
    #[pyo3(get)]
    rotations: Py<PyAny>,
    /// float32 N opacities in (0, 1).
    #[pyo3(get)]
    opacities: Py<PyAny>,
    /// float32 N×3 RGB in [0, 1] (0.28209479·dc + 0.5).
    #[pyo3(get)]
    colors: Py<PyAny>,
    /// float32 N×3 SH degree-0 coefficients, as stored in gaussians.ply.
    #[pyo3(get)]
    dc: Py<PyAny>,
}

#[pymethods]
impl Gaussians {
    /// Gaussians from arrays (float32; rows per Gaussian): N×3 means, N×3 scales, N×4
    /// rotations (w, x, y, z), N opacities, N×3 SH degree-0 `dc`. `recon_rgbd.Client` builds its
    /// objects' Gaussians so.
    #[new]
    fn py_new(
        py: Python<'_>,
        means: &Bound<'_, PyAny>,
        scales: &Bound<'_, PyAny>,
        rotations: &Bound<'_, PyAny>,
        opacities: &Bound<'_, PyAny>,
        dc: &Bound<'_, PyAny>,
    ) -> PyResult<Self> {
        let np = py.import("numpy")?;
        let op: PyReadonlyArray1<f32> = np
            .call_method1("ascontiguousarray", (opacities, "float32"))?
            .extract()
            .map_err(|_| input("opacities", "expected an N float32 array"))?;
        let g = recon::gaussians::Gaussians {
            positions: array_rows::<f32, 3>(means, "float32", "means")?,
            scales: array_rows::<f32, 3>(scales, "float32", "scales")?,
            rotations: array_rows::<f32, 4>(rotations, "float32", "rotations")?,
            opacities: op.as_array().to_vec(),
            dc: array_rows::<f32, 3>(dc, "float32", "dc")?,
        };
        g.validate().map_err(|e| input("gaussians", e.to_string()))?;
        Gaussians::new(py, g)
    }

    fn __len__(&self, py: Python<'_>) -> PyResult<usize> {
        self.means.bind(py).len()
    }
}

impl Gaussians {
    fn new(py: Python<'_>, g: recon::gaussians::Gaussians) -> PyResult<Self> {
        let colors: Vec<[f32; 3]> = g.dc.iter().map(|c| c.map(|x| 0.282_094_8 * x + 0.5)).collect();
        Ok(Gaussians {
            means: rows(py, g.positions)?.unbind(),
            scales: rows(py, g.scales)?.unbind(),
            rotations: rows(py, g.rotations)?.unbind(),
            opacities: numpy::PyArray1::from_vec(py, g.opacities).into_any().unbind(),
            colors: rows(py, colors)?.unbind(),
            dc: rows(py, g.dc)?.unbind(),
        })
    }

    fn to_recon(&self, py: Python<'_>) -> PyResult<recon::gaussians::Gaussians> {
        fn take<const K: usize>(a: &Bound<'_, PyAny>) -> PyResult<Vec<[f32; K]>> {
            let a: PyReadonlyArray2<f32> = a.extract()?;
            Ok(a.as_array().rows().into_iter().map(|r| std::array::from_fn(|k| r[k])).collect())
        }
        let op: PyReadonlyArray1<f32> = self.opacities.bind(py).extract()?;
        Ok(recon::gaussians::Gaussians {
            positions: take::<3>(self.means.bind(py))?,
            scales: take::<3>(self.scales.bind(py))?,
            rotations: take::<4>(self.rotations.bind(py))?,
            opacities: op.as_array().to_vec(),
            dc: take::<3>(self.dc.bind(py))?,
        })
    }
}

/// One reconstructed object.
#[pyclass(frozen, module = "recon_rgbd")]
pub struct Object {
    /// Instance id in the mask image, or None for a boolean mask.
    #[pyo3(get)]
    id: Option<u32>,
    /// `id N`, or `mask N` for the N-th boolean mask.
    #[pyo3(get)]
    label: String,
    /// float64 4×4 rigid camera-from-object transform (metres); with `scale`:
    /// `x_camera = R · (scale · x_object) + t`, object frame = the decoder's [-0.5, 0.5]³.
    #[pyo3(get)]
    pose: Py<PyAny>,
    #[pyo3(get)]
    scale: f64,
    /// The selection score (metres): trimmed mean distance of the observed points to the
    /// posed mesh, plus the free-space term with pose_fit="depth".
    #[pyo3(get)]
    score: f64,
    /// Spread of the per-sample poses with samples > 1 (translation_sd_mm, rotation_sd_deg,
    /// scale_sd_rel), else None.
    #[pyo3(get)]
    spread: Py<PyAny>,
    /// Seconds per stage, the columns of `recon infer`'s timing table.
    #[pyo3(get)]
    stage_seconds: Py<PyAny>,
    /// The mesh in the camera frame, or None when the decoder produced none.
    #[pyo3(get)]
    mesh: Option<Py<Mesh>>,
    /// The Gaussians in the camera frame, or None.
    #[pyo3(get)]
    gaussians: Option<Py<Gaussians>>,
    /// Everything pose.json holds except the files (selection, views, candidates, run, notes).
    #[pyo3(get)]
    details: Py<PyAny>,
    /// The mesh in the object frame (RecGen's `raw_mesh`): `mesh` is this mesh placed by the pose.
    #[pyo3(get)]
    raw_mesh: Option<Py<Mesh>>,
    /// The Gaussians in the object frame: `gaussians` are these placed by the pose.
    #[pyo3(get)]
    raw_gaussians: Option<Py<Gaussians>>,
    /// RecGen's `pose_matrix`: float64 4×4, object frame → the anchor view's normalised frame.
    #[pyo3(get)]
    pose_matrix: Py<PyAny>,
    /// RecGen's `pose_quat`: float64 `[tx, ty, tz, qx, qy, qz, qw]` (scipy order) of `pose_matrix`.
    #[pyo3(get)]
    pose_quat: Py<PyAny>,
    /// RecGen's `pose` dict: quaternion (x, y, z, w), translation, scale, rotation_matrix.
    #[pyo3(get)]
    parsed_pose: Py<PyAny>,
    /// RecGen's `cam2ncam`: float64 4×4, anchor camera (metres) → normalised frame.
    #[pyo3(get)]
    cam2ncam: Py<PyAny>,
    /// RecGen's `pose_representation` (the stage-1 pose layout, e.g. `6d_translation_scale`).
    #[pyo3(get)]
    pose_representation: Option<String>,
    /// The anchor view's H×W×3 uint8 image (one array shared by the frame's objects).
    #[pyo3(get)]
    rgb: Py<PyAny>,
    /// The anchor view's float64 3×3 K.
    #[pyo3(get)]
    intrinsics: Py<PyAny>,
    /// The post-hoc colour calibration (`posthoc_color=`): a dict with `variant`,
    /// `transform` (None when gated out), `stats` and `applied_to`, as posthoc_color.json;
    /// None when it was not asked for.
    #[pyo3(get)]
    posthoc_color: Py<PyAny>,
    /// What `save` writes into metadata.json (None for objects built from parts).
    recgen: Option<(RecgenPose, PoseRepresentation)>,
    /// What `save` writes into posthoc_color.json.
    posthoc_record: Option<recon::engine::posthoc_color::PosthocColorRecord>,
    /// The mesh on its UV atlas with the baked texture (`colour="texture"`), what
    /// `to_glb` writes; None with `colour="vertex"` and for objects built from parts.
    textured: Option<recon::mesh::TexturedMesh>,
}

/// What every object of a frame shares: the anchor image (one numpy array), its K, the
/// model's pose representation.
struct FrameShared {
    rgb: Py<PyAny>,
    intrinsics: Py<PyAny>,
    pose_representation: PoseRepresentation,
}

impl FrameShared {
    fn new(py: Python<'_>, r: &FrameResult) -> PyResult<Self> {
        let im = &r.image;
        let rgb = numpy::PyArray1::from_vec(py, im.rgb.clone()).reshape([im.height, im.width, 3])?.into_any().unbind();
        let k = im.intrinsics;
        let intrinsics = rows(py, vec![[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]])?.unbind();
        Ok(FrameShared { rgb, intrinsics, pose_representation: r.pose_representation })
    }
}

/// RecGen's `pose` dict with numpy values.
fn parsed_pose_dict<'py>(py: Python<'py>, p: &recon::engine::ParsedPose) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("quaternion", numpy::PyArray1::from_vec(py, p.quaternion.to_vec()))?;
    d.set_item("translation", numpy::PyArray1::from_vec(py, p.translation.to_vec()))?;
    d.set_item("scale", p.scale)?;
    d.set_item("rotation_matrix", rows(py, p.rotation_matrix.to_vec())?)?;
    Ok(d)
}

impl Object {
    fn new(py: Python<'_>, o: ObjectResult, frame: &FrameShared) -> PyResult<Self> {
        let p = &o.pose_camera;
        let row = |i: usize| -> [f64; 4] {
            let r = p.rotation[i];
            [r[0] as f64, r[1] as f64, r[2] as f64, p.translation[i] as f64]
        };
        let pose = rows(py, vec![row(0), row(1), row(2), [0.0, 0.0, 0.0, 1.0]])?;
        let st = recon::engine::stage_seconds(&o);
        let stage = PyDict::new(py);
        for (k, v) in recon::engine::STAGE_COLUMNS.iter().zip(st) {
            stage.set_item(k, v)?;
        }
        let details = serde_json::json!({
            "selection": o.selection, "views": o.views, "candidates": o.candidates,
            "occupied_voxels": o.occupied_voxels, "faces_decoded": o.faces_decoded,
            "samples": o.samples, "run": o.metadata, "notes": o.notes,
        });
        let rp = o.recgen_pose();
        let representation = serde_json::to_value(frame.pose_representation).ok().and_then(|v| v.as_str().map(str::to_string));
        Ok(Object {
            raw_mesh: o.mesh_object.map(|m| Mesh::new(py, m).and_then(|m| Py::new(py, m))).transpose()?,
            raw_gaussians: o.gaussians_object.map(|g| Gaussians::new(py, g).and_then(|g| Py::new(py, g))).transpose()?,
            pose_matrix: rows(py, rp.pose_matrix.to_vec())?.unbind(),
            pose_quat: numpy::PyArray1::from_vec(py, rp.pose_quat.to_vec()).into_any().unbind(),
            parsed_pose: parsed_pose_dict(py, &rp.pose)?.into_any().unbind(),
            cam2ncam: rows(py, rp.cam2ncam.to_vec())?.unbind(),
            pose_representation: representation,
            rgb: frame.rgb.clone_ref(py),
            intrinsics: frame.intrinsics.clone_ref(py),
            recgen: Some((rp, frame.pose_representation)),
            posthoc_color: to_python(py, &o.posthoc_color)?.unbind(),
            posthoc_record: o.posthoc_color.clone(),
            textured: o.textured.clone(),
            id: o.id,
            label: o.label.clone(),
            pose: pose.unbind(),
            scale: p.scale as f64,
            score: o.selection.score_m,
            spread: to_python(py, &o.uncertainty)?.unbind(),
            stage_seconds: stage.into_any().unbind(),
            details: to_python(py, &details)?.unbind(),
            mesh: o.mesh_camera.map(|m| Mesh::new(py, m).and_then(|m| Py::new(py, m))).transpose()?,
            gaussians: o.gaussians_camera.map(|g| Gaussians::new(py, g).and_then(|g| Py::new(py, g))).transpose()?,
        })
    }

    pub(crate) fn label(&self) -> &str {
        &self.label
    }

    /// `(label, mesh)` for `recon_rgbd.scene`, or None when no mesh was decoded.
    pub(crate) fn mesh_for_scene(&self, py: Python<'_>) -> PyResult<Option<(String, recon::mesh::Mesh)>> {
        self.mesh.as_ref().map(|m| Ok((self.label.clone(), m.get().to_recon(py)?))).transpose()
    }

    fn mesh_or_err(&self, py: Python<'_>) -> PyResult<recon::mesh::Mesh> {
        match &self.mesh {
            Some(m) => m.get().to_recon(py),
            None => Err(input(&self.label, "no mesh was decoded for this object")),
        }
    }
}

#[pymethods]
impl Object {
    /// An object from its parts, as `recon_rgbd.Client` builds the objects of a remote job (the
    /// fields of the same names; `pose` a 4×4 array).
    #[staticmethod]
    #[pyo3(signature = (*, id, label, pose, scale, score, spread, stage_seconds, details, mesh=None, gaussians=None))]
    #[allow(clippy::too_many_arguments)]
    fn _from_parts(
        py: Python<'_>,
        id: Option<u32>,
        label: String,
        pose: &Bound<'_, PyAny>,
        scale: f64,
        score: f64,
        spread: Py<PyAny>,
        stage_seconds: Py<PyAny>,
        details: Py<PyAny>,
        mesh: Option<Py<Mesh>>,
        gaussians: Option<Py<Gaussians>>,
    ) -> PyResult<Self> {
        let p = array_rows::<f64, 4>(pose, "float64", "pose")?;
        if p.len() != 4 {
            return Err(input("pose", "expected a 4×4 array"));
        }
        Ok(Object {
            id,
            label,
            pose: rows(py, p)?.unbind(),
            scale,
            score,
            spread,
            stage_seconds,
            mesh,
            gaussians,
            details,
            // A remote job's answer carries recon's files, not RecGen's fields.
            raw_mesh: None,
            raw_gaussians: None,
            pose_matrix: py.None(),
            pose_quat: py.None(),
            parsed_pose: py.None(),
            cam2ncam: py.None(),
            pose_representation: None,
            rgb: py.None(),
            intrinsics: py.None(),
            recgen: None,
            posthoc_color: py.None(),
            posthoc_record: None,
            textured: None,
        })
    }

    /// Write the mesh as GLB, exactly as `recon infer` writes `<object>/mesh.glb` (textured
    /// with `colour="texture"`; vertex-coloured with `colour="vertex"`, the default).
    fn to_glb(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        if let Some(tm) = &self.textured {
            return py.detach(|| recon::export::save_textured_glb(tm, &path, recon::export::Axes::ZUp)).py();
        }
        let m = self.mesh_or_err(py)?;
        let opts = recon::export::GlbOptions { axes: recon::export::Axes::ZUp, vertex_colors: true };
        py.detach(|| recon::export::save_glb(&m, &path, &opts)).py()
    }

    /// Write the mesh as PLY, exactly as `recon infer` writes `<object>/mesh.ply`.
    fn to_ply(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let m = self.mesh_or_err(py)?;
        let opts = recon::export::PlyOptions { axes: recon::export::Axes::ZUp, normals: true, vertex_colors: true };
        py.detach(|| recon::export::save_mesh_ply(&m, &path, &opts)).py()
    }

    /// Write the Gaussians as a 3DGS splat PLY, as `recon infer` writes `<object>/gaussians.ply`.
    fn gaussians_to_ply(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let g = match &self.gaussians {
            Some(g) => g.get().to_recon(py)?,
            None => return Err(input(&self.label, "no Gaussians were decoded for this object")),
        };
        py.detach(|| recon::export::save_splat_ply(&g, &path, recon::export::Axes::ZUp)).py()
    }

    /// RecGen's `RecGenResult.save(output_dir, save_splat=...)`: into `output_dir` (created
    /// if needed) mesh.obj (object frame) and posed_mesh.obj (camera frame) when there is a
    /// mesh, gaussian.ply and posed_gaussian.ply when there are Gaussians and `save_splat`,
    /// overlay.png and metadata.json (and posthoc_color.json after a colour calibration);
    /// the files `recon infer --recgen-files` writes beside pose.json.
    #[pyo3(signature = (output_dir, *, save_splat=true))]
    fn save(&self, py: Python<'_>, output_dir: PathBuf, save_splat: bool) -> PyResult<()> {
        let Some((pose, pose_representation)) = self.recgen else {
            return Err(input(&self.label, "save needs RecGen's pose fields, which objects of a recon_rgbd.Client answer do not carry"));
        };
        let rgb: PyReadonlyArray3<u8> =
            self.rgb.bind(py).extract().map_err(|_| input(&self.label, "rgb: expected an H×W×3 uint8 array"))?;
        let [height, width, _] = <[usize; 3]>::try_from(rgb.shape()).map_err(|_| input(&self.label, "rgb must be H×W×3"))?;
        let image = FrameImage {
            width,
            height,
            rgb: rgb.as_array().iter().copied().collect(),
            intrinsics: intrinsics(self.intrinsics.bind(py), "intrinsics")?,
        };
        let mesh_object = self.raw_mesh.as_ref().map(|m| m.get().to_recon(py)).transpose()?;
        let mesh_camera = self.mesh.as_ref().map(|m| m.get().to_recon(py)).transpose()?;
        let gaussians_object = self.raw_gaussians.as_ref().map(|g| g.get().to_recon(py)).transpose()?;
        let gaussians_camera = self.gaussians.as_ref().map(|g| g.get().to_recon(py)).transpose()?;
        let files = RecgenFiles {
            mesh_object: mesh_object.as_ref(),
            mesh_camera: mesh_camera.as_ref(),
            gaussians_object: gaussians_object.as_ref(),
            gaussians_camera: gaussians_camera.as_ref(),
            pose,
            pose_representation,
            image: &image,
            posthoc_color: self.posthoc_record.as_ref(),
        };
        py.detach(|| {
            std::fs::create_dir_all(&output_dir).map_err(|e| recon::Error::io(&output_dir, e))?;
            files.write(&output_dir, save_splat).map(|_| ())
        })
        .py()
    }

    /// The mesh as a `trimesh.Trimesh` (vertex colours as RGBA uint8); needs trimesh.
    fn to_trimesh<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let tm = py
            .import("trimesh")
            .map_err(|_| pyo3::exceptions::PyImportError::new_err("Object.to_trimesh needs trimesh (pip install trimesh)"))?;
        let Some(m) = &self.mesh else { return Err(input(&self.label, "no mesh was decoded for this object")) };
        let m = m.get();
        let kw = PyDict::new(py);
        kw.set_item("vertices", m.vertices.bind(py))?;
        kw.set_item("faces", m.faces.bind(py))?;
        kw.set_item("process", false)?;
        let colors = m.colors(py)?;
        if !colors.is_none() {
            let np = py.import("numpy")?;
            let rgb = np
                .call_method1("clip", (colors.call_method1("__mul__", (255.0,))?.call_method0("round")?, 0, 255))?
                .call_method1("astype", ("uint8",))?;
            let n: usize = rgb.len()?;
            let alpha = np.call_method1("full", ((n, 1), 255u8, "uint8"))?;
            kw.set_item("vertex_colors", np.call_method1("hstack", ((rgb, alpha),))?)?;
        }
        tm.getattr("Trimesh")?.call((), Some(&kw))
    }

    fn __repr__(&self) -> String {
        format!("recon_rgbd.Object({}, scale={:.4} m, score={:.4} m)", self.label, self.scale, self.score)
    }
}
