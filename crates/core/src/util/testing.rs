//! Temporary folders for tests: the one helper every test of the workspace
//! uses (recon-core's unit tests here, the other crates' through recon-testkit).

use std::path::PathBuf;

/// The workspace root (models/, data/sample/, tests/fixtures/).
pub fn repo() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
}

/// A fresh, empty folder under the system temp dir, unique to this process
/// and `tag` (what was there from an earlier run is removed first). Tags must
/// differ between the tests of one test binary.
pub fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("recon-test-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Whether two tensors have the same shape and the same f32 bits everywhere.
pub fn same_bits(a: &candle_core::Tensor, b: &candle_core::Tensor) -> crate::Result<bool> {
    let bits = |t: &candle_core::Tensor| -> crate::Result<Vec<u32>> {
        Ok(t.to_dtype(candle_core::DType::F32)?.flatten_all()?.to_vec1::<f32>()?.iter().map(|v| v.to_bits()).collect())
    };
    Ok(a.dims() == b.dims() && bits(a)? == bits(b)?)
}

/// `max|got − want| / max|want|` (the error relative to the output's scale).
pub fn max_rel_diff(got: &candle_core::Tensor, want: &candle_core::Tensor) -> crate::Result<f64> {
    let scale = want.to_dtype(candle_core::DType::F64)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f64>()?;
    Ok(crate::util::max_abs_diff(got, want)? / scale.max(f64::MIN_POSITIVE))
}
