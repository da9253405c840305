//! Sparse down/up-sampling (TRELLIS `SparseDownsample` / `SparseUpsample`).
//!
//! Downsample by `f`: coarse coords `(b, x/f, y/f, z/f)`, deduplicated and
//! sorted like `torch.unique` on a monotone key (batch-major, then x, y, z
//! lexicographic); features are `sum(children) / (count + 1)`: upstream
//! calls `scatter_reduce(zeros, …, reduce="mean")` with the default
//! `include_self=True`, so the zero initial value takes part in the mean.
//! We reproduce that (the released weights were trained with it). The cache
//! lets the paired upsample (nearest) restore exactly the fine rows/order.

use super::tensor::SparseTensor;
use crate::{Error, Result};
use candle_core::{DType, Tensor};

/// What a downsample remembers for its paired upsample.
#[derive(Debug, Clone)]
pub struct DownsampleCache {
    /// Downsampling factor f.
    pub factor: i32,
    /// Coordinates of the fine (input) tensor, in its row order.
    pub fine_coords: Vec<[i32; 4]>,
    /// Batch size of the fine tensor.
    pub fine_batch_size: usize,
    /// Coarse row of every fine row.
    pub inverse: Vec<u32>,
}

/// Pool onto `coords // factor` (floor division) with upstream's
/// include-self mean: `sum / (count + 1)`.
pub fn sparse_downsample(x: &SparseTensor, factor: usize) -> Result<(SparseTensor, DownsampleCache)> {
    crate::util::profile::timed(crate::util::profile::Kind::SparseIndex, || 0, || downsample(x, factor))
}

fn downsample(x: &SparseTensor, factor: usize) -> Result<(SparseTensor, DownsampleCache)> {
    if factor == 0 {
        return Err(Error::msg("sparse downsample: factor must be ≥ 1"));
    }
    let f = factor as i32;
    let coarse: Vec<[i32; 4]> = x.coords.iter().map(|c| [c[0], c[1].div_euclid(f), c[2].div_euclid(f), c[3].div_euclid(f)]).collect();
    let mut unique = coarse.clone();
    unique.sort_unstable();
    unique.dedup();
    // [i32; 4] orders lexicographically: batch first, then x, y, z.
    let inverse: Vec<u32> = coarse
        .iter()
        .map(|c| unique.binary_search(c).map(|i| i as u32))
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| Error::msg("sparse downsample: internal lookup failed"))?;
    let dev = x.feats.device();
    let n = unique.len();
    let c = x.feats.dim(1)?;
    // Start at 1: the zero "self" value counts (see module doc).
    let mut counts = vec![1f32; n];
    for &i in &inverse {
        counts[i as usize] += 1.0;
    }
    let idx = Tensor::from_vec(inverse.clone(), inverse.len(), dev)?;
    let sums = Tensor::zeros((n, c), x.feats.dtype(), dev)?.index_add(&idx, &x.feats, 0)?;
    let counts = Tensor::from_vec(counts, (n, 1), dev)?.to_dtype(x.feats.dtype())?;
    let feats = sums.broadcast_div(&counts)?;
    let out = SparseTensor::new(unique, feats, x.batch_size)?;
    Ok((out, DownsampleCache { factor: f, fine_coords: x.coords.clone(), fine_batch_size: x.batch_size, inverse }))
}

/// Nearest upsample back to the rows recorded by the matching downsample.
pub fn sparse_upsample(x: &SparseTensor, cache: &DownsampleCache) -> Result<SparseTensor> {
    crate::util::profile::timed(crate::util::profile::Kind::SparseIndex, || 0, || upsample(x, cache))
}

fn upsample(x: &SparseTensor, cache: &DownsampleCache) -> Result<SparseTensor> {
    if cache.inverse.iter().any(|&i| i as usize >= x.len()) {
        return Err(Error::msg("sparse upsample: cache does not belong to this tensor"));
    }
    let idx = Tensor::from_vec(cache.inverse.clone(), cache.inverse.len(), x.feats.device())?;
    let feats = x.feats.index_select(&idx, 0)?;
    SparseTensor::new(cache.fine_coords.clone(), feats, cache.fine_batch_size)
}

/// Coordinates `[N, 3]` (x, y, z) as f32, e.g. for position embeddings.
pub fn xyz_tensor(x: &SparseTensor) -> Result<Tensor> {
    let v: Vec<f32> = x.coords.iter().flat_map(|c| [c[1] as f32, c[2] as f32, c[3] as f32]).collect();
    Ok(Tensor::from_vec(v, (x.len(), 3), x.feats.device())?.to_dtype(DType::F32)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn downsample_pools_and_orders_like_torch_unique() -> Result<()> {
        let coords = vec![[0, 3, 0, 0], [0, 0, 1, 1], [0, 1, 0, 0], [1, 0, 0, 5], [1, 0, 0, 4]];
        let feats = Tensor::new(&[[1f32, 10.], [2., 20.], [4., 40.], [8., 80.], [16., 160.]], &Device::Cpu)?;
        let x = SparseTensor::new(coords.clone(), feats, 2)?;
        let (y, cache) = sparse_downsample(&x, 2)?;
        assert_eq!(y.coords, vec![[0, 0, 0, 0], [0, 1, 0, 0], [1, 0, 0, 2]]);
        // sum / (count + 1), as upstream's include-self scatter mean.
        assert_eq!(y.feats.to_vec2::<f32>()?, vec![vec![2., 20.], vec![0.5, 5.], vec![8., 80.]]);
        let z = sparse_upsample(&y, &cache)?;
        assert_eq!(z.coords, coords);
        assert_eq!(z.feats.to_vec2::<f32>()?, vec![vec![0.5, 5.], vec![2., 20.], vec![2., 20.], vec![8., 80.], vec![8., 80.]]);
        Ok(())
    }
}
