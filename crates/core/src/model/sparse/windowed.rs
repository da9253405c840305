//! Swin-style windowed self-attention on sparse tensors (TRELLIS
//! `sparse_windowed_scaled_dot_product_self_attention`).
//!
//! Voxels are shifted by `shift` on every axis, bucketed into cubic windows of
//! side `window`, and each non-empty window (per batch item) is one attention
//! sequence. There is no cyclic roll: the shift only moves window boundaries.
//! Attention is permutation-invariant inside a window, so the order of rows
//! within a window does not matter; we use a stable sort for determinism.

use super::tensor::SparseTensor;
use crate::model::nn::common::{attention, MultiHeadAttention};
use crate::{Error, Result};
use candle_core::Tensor;

/// Which rows form each window: `order` lists row indices window by window,
/// `seq_lens[w]` rows per window (in `order`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct WindowPartition {
    /// Row indices, grouped window by window.
    pub order: Vec<usize>,
    /// Rows per non-empty window, in `order`'s window order.
    pub seq_lens: Vec<usize>,
}

impl WindowPartition {
    /// Partition `coords` (batch, x, y, z) into windows of side `window`, with
    /// every spatial coordinate shifted by `+shift` first.
    pub fn new(coords: &[[i32; 4]], window: usize, shift: usize) -> Result<Self> {
        if window == 0 {
            return Err(Error::msg("windowed attention: window size must be > 0"));
        }
        if coords.is_empty() {
            return Ok(Self { order: vec![], seq_lens: vec![] });
        }
        let (w, s) = (window as i64, shift as i64);
        // Number of windows per axis from the max shifted coordinate over all rows.
        let mut nw = [1i64; 3];
        for c in coords {
            for a in 0..3 {
                let v = c[a + 1] as i64 + s;
                if v < 0 {
                    return Err(Error::msg("windowed attention: negative coordinate"));
                }
                nw[a] = nw[a].max((v + 1 + w - 1) / w);
            }
        }
        let key = |c: &[i32; 4]| -> i64 {
            let wx = (c[1] as i64 + s) / w;
            let wy = (c[2] as i64 + s) / w;
            let wz = (c[3] as i64 + s) / w;
            ((c[0] as i64 * nw[0] + wx) * nw[1] + wy) * nw[2] + wz
        };
        let keys: Vec<i64> = coords.iter().map(key).collect();
        let mut order: Vec<usize> = (0..coords.len()).collect();
        order.sort_by_key(|&i| keys[i]); // stable
        let mut seq_lens = Vec::new();
        let mut i = 0;
        while i < order.len() {
            let k = keys[order[i]];
            let start = i;
            while i < order.len() && keys[order[i]] == k {
                i += 1;
            }
            seq_lens.push(i - start);
        }
        Ok(Self { order, seq_lens })
    }

    /// One window holding each batch item's rows (full attention per item).
    pub fn per_batch(x: &SparseTensor) -> Self {
        let ranges = x.batch_ranges();
        Self { order: (0..x.len()).collect(), seq_lens: ranges.iter().map(|r| r.len()).filter(|&l| l > 0).collect() }
    }

    /// Windows grouped by length, as lists of row-index lists (in `order`).
    fn windows_by_len(&self) -> Vec<(usize, Vec<&[usize]>)> {
        let mut groups: std::collections::BTreeMap<usize, Vec<&[usize]>> = Default::default();
        let mut start = 0;
        for &l in &self.seq_lens {
            groups.entry(l).or_default().push(&self.order[start..start + l]);
            start += l;
        }
        groups.into_iter().collect()
    }
}

/// Softmax attention inside each window. `q`, `k`, `v` are `[N, H, D]` over
/// the rows of a sparse tensor; returns `[N, H, D]` in the same row order.
/// Windows of equal length are batched together (bounded by a score budget).
pub fn windowed_attention(q: &Tensor, k: &Tensor, v: &Tensor, part: &WindowPartition) -> Result<Tensor> {
    let (n, h, d) = q.dims3()?;
    if part.order.len() != n {
        return Err(Error::msg(format!("windowed attention: partition has {} rows, tensor {n}", part.order.len())));
    }
    let dev = q.device();
    let budget = 32usize << 20; // score elements per batched call
    let mut outs = Vec::new();
    let mut placed: Vec<u32> = Vec::with_capacity(n);
    for (len, wins) in part.windows_by_len() {
        let per_call = (budget / (h * len * len).max(1)).max(1);
        for chunk in wins.chunks(per_call) {
            let idx: Vec<u32> = chunk.iter().flat_map(|w| w.iter().map(|&i| i as u32)).collect();
            placed.extend_from_slice(&idx);
            let nw = chunk.len();
            let idx = Tensor::from_vec(idx, nw * len, dev)?;
            let gather =
                |t: &Tensor| -> Result<Tensor> { Ok(t.index_select(&idx, 0)?.reshape((nw, len, h, d))?.transpose(1, 2)?.contiguous()?) };
            let o = attention(&gather(q)?, &gather(k)?, &gather(v)?)?; // [nw, H, L, D]
            outs.push(o.transpose(1, 2)?.reshape((nw * len, h, d))?);
        }
    }
    if outs.is_empty() {
        return Ok(q.zeros_like()?);
    }
    let cat = Tensor::cat(&outs, 0)?;
    // Inverse permutation: row i of the output is at position inv[i] of `cat`.
    let mut inv = vec![0u32; n];
    for (pos, &row) in placed.iter().enumerate() {
        inv[row as usize] = pos as u32;
    }
    let inv = Tensor::from_vec(inv, n, dev)?;
    Ok(cat.index_select(&inv, 0)?)
}

/// TRELLIS `SparseMultiHeadAttention` self-attention on sparse feats `[N, C]`
/// with a given window partition (use [`WindowPartition::per_batch`] for
/// full attention).
pub fn sparse_self_attention(attn: &MultiHeadAttention, feats: &Tensor, part: &WindowPartition) -> Result<Tensor> {
    if attn.is_fast() {
        return sparse_self_attention_fast(attn, feats, part);
    }
    let (q, k, v) = attn.qkv(&feats.unsqueeze(0)?, None)?; // each [1, N, H, D]
    let flat = |t: Tensor| -> Result<Tensor> { Ok(t.squeeze(0)?.contiguous()?) };
    let o = windowed_attention(&flat(q)?, &flat(k)?, &flat(v)?, part)?;
    Ok(attn.out(&o.unsqueeze(0)?)?.squeeze(0)?)
}

/// Fast path: rows gathered into window order so that each window is one
/// contiguous segment of the fused flash-attention kernel, then scattered back.
fn sparse_self_attention_fast(attn: &MultiHeadAttention, feats: &Tensor, part: &WindowPartition) -> Result<Tensor> {
    let n = feats.dim(0)?;
    if part.order.len() != n {
        return Err(Error::msg(format!("windowed attention: partition has {} rows, tensor {n}", part.order.len())));
    }
    if n == 0 {
        return Ok(feats.clone());
    }
    let dev = feats.device();
    let order: Vec<u32> = part.order.iter().map(|&i| i as u32).collect();
    let mut inv = vec![0u32; n];
    for (pos, &row) in part.order.iter().enumerate() {
        inv[row] = pos as u32;
    }
    let xs = feats.index_select(&Tensor::from_vec(order, n, dev)?, 0)?;
    let mut segs = Vec::with_capacity(part.seq_lens.len());
    let mut start = 0;
    for &l in &part.seq_lens {
        segs.push(crate::model::nn::fast::AttnSegment { q: start..start + l, kv: start..start + l });
        start += l;
    }
    let y = attn.forward_rows(&xs, None, &segs)?;
    Ok(y.index_select(&Tensor::from_vec(inv, n, dev)?, 0)?)
}

/// Plain per-window reference (one window at a time), for tests.
#[cfg(test)]
fn windowed_attention_naive(q: &Tensor, k: &Tensor, v: &Tensor, part: &WindowPartition) -> Result<Tensor> {
    use candle_core::D;
    let (n, h, d) = q.dims3()?;
    let mut rows = vec![None; n];
    let mut start = 0;
    for &l in &part.seq_lens {
        let ids = &part.order[start..start + l];
        start += l;
        let idx = Tensor::from_vec(ids.iter().map(|&i| i as u32).collect::<Vec<_>>(), l, q.device())?;
        let g = |t: &Tensor| -> Result<Tensor> { Ok(t.index_select(&idx, 0)?.transpose(0, 1)?.contiguous()?) };
        let (qq, kk, vv) = (g(q)?, g(k)?, g(v)?); // [H, L, D]
        let s = (qq.matmul(&kk.t()?)? / (d as f64).sqrt())?;
        let p = candle_nn::ops::softmax(&s, D::Minus1)?;
        let o = p.matmul(&vv)?.transpose(0, 1)?; // [L, H, D]
        for (j, &i) in ids.iter().enumerate() {
            rows[i] = Some(o.get(j)?);
        }
    }
    let rows: Vec<Tensor> = rows.into_iter().map(|r| r.unwrap()).collect();
    let _ = h;
    Ok(Tensor::stack(&rows, 0)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Tensor, D};

    fn shell(res: i32, batch: i32) -> Vec<[i32; 4]> {
        let mut c = vec![];
        for b in 0..batch {
            for x in 0..res {
                for y in 0..res {
                    for z in 0..res {
                        let r = ((x - 5) * (x - 5) + (y - 6) * (y - 6) + (z - 4) * (z - 4)) as f32;
                        if (r.sqrt() - 4.0 - b as f32).abs() < 0.8 {
                            c.push([b, x, y, z]);
                        }
                    }
                }
            }
        }
        c
    }

    fn max_diff(a: &Tensor, b: &Tensor) -> f32 {
        (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
    }

    #[test]
    fn big_window_equals_full_attention() -> Result<()> {
        let coords = shell(14, 2);
        let n = coords.len();
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (n, 2, 8), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (n, 2, 8), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (n, 2, 8), &dev)?;
        let part = WindowPartition::new(&coords, 64, 0)?;
        assert_eq!(part.seq_lens.len(), 2, "one window per batch item");
        let feats = Tensor::zeros((n, 1), candle_core::DType::F32, &dev)?;
        let st = SparseTensor::new(coords.clone(), feats, 2)?;
        let full = WindowPartition::per_batch(&st);
        let a = windowed_attention(&q, &k, &v, &part)?;
        let b = windowed_attention(&q, &k, &v, &full)?;
        assert!(max_diff(&a, &b) < 1e-6);
        // Full attention over batch item 0 computed directly.
        let n0 = coords.iter().filter(|c| c[0] == 0).count();
        let g = |t: &Tensor| t.narrow(0, 0, n0).unwrap().transpose(0, 1).unwrap().contiguous().unwrap();
        let s = (g(&q).matmul(&g(&k).t()?)? / 8f64.sqrt())?;
        let want = candle_nn::ops::softmax(&s, D::Minus1)?.matmul(&g(&v))?.transpose(0, 1)?;
        assert!(max_diff(&a.narrow(0, 0, n0)?, &want) < 1e-5);
        Ok(())
    }

    /// The fused-kernel path of a layer built with fast kernels gives the
    /// plain path's result (f32), including uneven window sizes.
    #[test]
    fn fast_sparse_attention_matches_plain() -> Result<()> {
        use crate::model::nn::fast::{Compute, Precision};
        use candle_nn::{VarBuilder, VarMap};
        let coords = shell(14, 2);
        let n = coords.len();
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, candle_core::DType::F32, &dev);
        let plain = MultiHeadAttention::new(48, 3, None, true, vb.pp("attn"), Compute::Plain)?;
        let fast = MultiHeadAttention::new(48, 3, None, true, vb.pp("attn"), Compute::fast(Precision::F32))?;
        assert!(fast.is_fast() && !plain.is_fast());
        let feats = Tensor::randn(0f32, 1.0, (n, 48), &dev)?;
        for p in [WindowPartition::new(&coords, 4, 0)?, WindowPartition::new(&coords, 4, 2)?, WindowPartition::new(&coords, 64, 0)?] {
            let a = sparse_self_attention(&plain, &feats, &p)?;
            let b = sparse_self_attention(&fast, &feats, &p)?;
            assert!(max_diff(&a, &b) < 1e-4, "diff {}", max_diff(&a, &b));
        }
        Ok(())
    }

    #[test]
    fn small_windows_match_naive_and_shift_regroups() -> Result<()> {
        let coords = shell(14, 2);
        let n = coords.len();
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (n, 3, 4), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (n, 3, 4), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (n, 3, 4), &dev)?;
        let p0 = WindowPartition::new(&coords, 4, 0)?;
        let p2 = WindowPartition::new(&coords, 4, 2)?;
        assert_ne!(p0, p2);
        assert_eq!(p0.seq_lens.iter().sum::<usize>(), n);
        // Every window lies in one batch item and one 4-cube of shifted coords.
        for (p, s) in [(&p0, 0), (&p2, 2)] {
            let mut start = 0;
            for &l in &p.seq_lens {
                let ids = &p.order[start..start + l];
                start += l;
                let c0 = coords[ids[0]];
                for &i in ids {
                    let c = coords[i];
                    assert_eq!(c[0], c0[0]);
                    for a in 1..4 {
                        assert_eq!((c[a] + s) / 4, (c0[a] + s) / 4);
                    }
                }
            }
        }
        // With shift 2, voxels (x=1) and (x=2) are in different windows; with shift 0 together.
        let two = [[0, 1, 0, 0], [0, 2, 0, 0]];
        assert_eq!(WindowPartition::new(&two, 4, 0)?.seq_lens, vec![2]);
        assert_eq!(WindowPartition::new(&two, 4, 2)?.seq_lens, vec![1, 1]);
        for p in [&p0, &p2] {
            let a = windowed_attention(&q, &k, &v, p)?;
            let b = windowed_attention_naive(&q, &k, &v, p)?;
            assert!(max_diff(&a, &b) < 1e-5);
        }
        let a0 = windowed_attention(&q, &k, &v, &p0)?;
        let a2 = windowed_attention(&q, &k, &v, &p2)?;
        assert!(max_diff(&a0, &a2) > 1e-3, "shift must change the result");
        Ok(())
    }
}
