//! Conversions between recon's values and Python's: JSON reports to dicts and back
//! (floats exactly: Rust → Python goes through shortest round-trip text and Python's
//! correctly rounded parser, Python → Rust reads the f64 itself), numpy arrays, and the
//! frame-discovery arguments of `recon infer`.

use crate::errors::{input, IntoPy};
use numpy::{PyArray1, PyArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};
use recon::dataset::{FrameOptions, Intrinsics};
use serde_json::Value;
use std::path::PathBuf;

/// A serialisable report as a Python object (dicts, lists, floats, ints, strings).
pub fn to_python<'py, T: serde::Serialize>(py: Python<'py>, v: &T) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(v).map_err(|e| crate::errors::ReconError::new_err(e.to_string()))?;
    py.import("json")?.call_method1("loads", (text,))
}

/// A Python object of JSON types as a JSON value (floats bit-exact).
pub fn from_python(o: &Bound<'_, PyAny>) -> PyResult<Value> {
    if o.is_none() {
        return Ok(Value::Null);
    }
    if o.is_instance_of::<PyBool>() {
        return Ok(Value::Bool(o.extract()?));
    }
    if o.is_instance_of::<PyInt>() {
        if let Ok(v) = o.extract::<i64>() {
            return Ok(Value::from(v));
        }
        return Ok(Value::from(o.extract::<u64>()?));
    }
    if o.is_instance_of::<PyFloat>() {
        let f: f64 = o.extract()?;
        return serde_json::Number::from_f64(f)
            .map(Value::Number)
            .ok_or_else(|| crate::errors::input("value", format!("{f} is not a finite number")));
    }
    if o.is_instance_of::<PyString>() {
        return Ok(Value::String(o.extract()?));
    }
    if let Ok(d) = o.cast::<PyDict>() {
        let mut m = serde_json::Map::new();
        for (k, v) in d.iter() {
            m.insert(k.extract::<String>()?, from_python(&v)?);
        }
        return Ok(Value::Object(m));
    }
    if o.is_instance_of::<PyList>() || o.is_instance_of::<PyTuple>() {
        return o.try_iter()?.map(|x| from_python(&x?)).collect::<PyResult<Vec<_>>>().map(Value::Array);
    }
    Err(crate::errors::input("value", format!("cannot convert a {} to JSON", o.get_type().name()?)))
}

/// `rows × K` numpy array that takes over the vector's buffer (no copy).
pub fn rows<'py, T: numpy::Element, const K: usize>(py: Python<'py>, v: Vec<[T; K]>) -> PyResult<Bound<'py, PyAny>> {
    let n = v.len();
    Ok(PyArray1::from_vec(py, v.into_flattened()).reshape([n, K])?.into_any())
}

/// `--depth`, `--intrinsics` (a 3×3 K, `[fx, fy, cx, cy]`, or a JSON/MAT/YAML file) and
/// `--depth-scale` of `recon infer`.
pub fn frame_options(depth: Option<PathBuf>, intrinsics: Option<&Bound<'_, PyAny>>, depth_scale: Option<f64>) -> PyResult<FrameOptions> {
    let mut fo = FrameOptions { depth, depth_scale_m: depth_scale, ..Default::default() };
    if let Some(k) = intrinsics {
        if let Ok(p) = k.extract::<PathBuf>() {
            fo.intrinsics_file = Some(p);
        } else {
            let np = k.py().import("numpy")?;
            let flat: Vec<f64> =
                np.call_method1("ravel", (np.call_method1("asarray", (k, "float64"))?,))?.call_method0("tolist")?.extract()?;
            fo.intrinsics = Some(match flat.len() {
                4 => Intrinsics::new(flat[0], flat[1], flat[2], flat[3]).py()?,
                9 => Intrinsics::from_k_row_major(&flat, "intrinsics").py()?,
                n => return Err(input("intrinsics", format!("expected a 3×3 K, [fx, fy, cx, cy] or a file; got {n} numbers"))),
            });
        }
    }
    Ok(fo)
}
