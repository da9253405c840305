//! Small shared helpers: JSON files with errors that name them (`json`),
//! resource bounds for hostile inputs (`limits`), peak memory (`memory`), the
//! large-buffer allocator (`buffer_cache`), temporary folders for tests (`testing`),
//! and the statistics several layers use.

pub(crate) mod buffer_cache;
pub mod json;
pub mod limits;
pub mod memory;
pub mod profile;
// Always built (hidden): a cargo feature for it made the test build and the Python wheel
// compile recon-core, and all that depends on it, twice in CI.
#[doc(hidden)]
pub mod testing;

pub use self::buffer_cache::{buffer_cache_active, cached_buffer_bytes, release_cached_buffers, LargeBufferCache};
pub use self::memory::{freed_memory_kept, keep_freed_memory, peak_rss_mib, reset_peak_rss};
pub use json::{from_value, read_json};
pub use limits::{
    check_image_dims, checked_product, memory_budget_bytes, open_image, MAX_DEFLATE_RATIO, MAX_IMAGE_ALLOC, MAX_IMAGE_PIXELS,
    MAX_IMAGE_SIDE, MAX_MAT_INFLATED,
};

use crate::{Error, Result};
use candle_core::{DType, Tensor};

/// Mean of the values after dropping the largest `trim` fraction
/// (`floor(n·trim)` values). NaN for an empty input.
pub fn trimmed_mean(d: &[f64], trim: f64) -> f64 {
    let n = d.len();
    if n == 0 {
        return f64::NAN;
    }
    let drop = ((n as f64 * trim.clamp(0.0, 1.0)).floor() as usize).min(n - 1);
    let keep = n - drop;
    let mut v = d.to_vec();
    if drop > 0 {
        v.select_nth_unstable_by(keep - 1, |a, b| a.total_cmp(b));
    }
    v[..keep].iter().sum::<f64>() / keep as f64
}

/// Max absolute difference; shapes must agree (error names both shapes).
pub fn max_abs_diff(got: &Tensor, want: &Tensor) -> Result<f64> {
    if got.dims() != want.dims() {
        return Err(Error::msg(format!("shape mismatch: got {:?}, expected {:?}", got.dims(), want.dims())));
    }
    let d = (got.to_dtype(DType::F64)? - want.to_dtype(DType::F64)?)?.abs()?;
    let m = d.flatten_all()?.max(0)?.to_scalar::<f64>()?;
    Ok(m)
}
