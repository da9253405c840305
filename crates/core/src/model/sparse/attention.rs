//! Variable-length full attention over sparse tensors: every batch item's
//! rows attend only to each other (TRELLIS sparse `full` attention, which
//! upstream runs as block-diagonal varlen attention).

use crate::model::nn::common::attention;
use crate::model::nn::fast::{self, AttnLayout, AttnSegment, Compute};
use crate::Result;
use candle_core::Tensor;
use std::ops::Range;

/// [`varlen_attention`] with the fused flash-attention kernel when `compute`
/// is fast (inference only), the plain candle path otherwise.
pub fn varlen_attention_with(
    q: &Tensor,
    k: &Tensor,
    v: &Tensor,
    q_ranges: &[Range<usize>],
    kv_ranges: &[Range<usize>],
    compute: Compute,
) -> Result<Tensor> {
    let Some((precision, isa)) = compute.fast_parts() else {
        return varlen_attention(q, k, v, q_ranges, kv_ranges);
    };
    if q_ranges.len() != kv_ranges.len() {
        return Err(crate::Error::msg("varlen attention: q and kv have different batch sizes"));
    }
    let (nq, h, d) = q.dims3()?;
    let (nk, hk, dk) = k.dims3()?;
    if v.dims() != [nk, hk, dk] || hk != h || dk != d {
        return Err(crate::Error::msg(format!("varlen attention: q {:?}, k {:?}, v {:?} disagree", q.dims(), k.dims(), v.dims())));
    }
    if q_ranges.iter().any(|r| r.end > nq) || kv_ranges.iter().any(|r| r.end > nk) {
        return Err(crate::Error::msg("varlen attention: a range exceeds the rows"));
    }
    let segs: Vec<AttnSegment> = q_ranges.iter().zip(kv_ranges).map(|(a, b)| AttnSegment { q: a.clone(), kv: b.clone() }).collect();
    let lay = AttnLayout::new(h * d, 0);
    let o = fast::with_f32(q, |qs| {
        fast::with_f32(k, |ks| {
            fast::with_f32(v, |vs| fast::attention_rows(isa, precision, h, d, (qs, lay), (ks, lay), (vs, lay), nq, &segs))
        })
    })?;
    // Rows outside every range are zero, as in the plain path's output.
    Ok(Tensor::from_vec(o, (nq, h, d), q.device())?)
}

/// `q` `[Nq, H, D]`, `k`/`v` `[Nk, H, D]`; `q_ranges[b]` and `kv_ranges[b]`
/// are item b's rows. Returns `[Nq, H, D]`; items with no queries are skipped,
/// items with no keys give zeros.
pub fn varlen_attention(q: &Tensor, k: &Tensor, v: &Tensor, q_ranges: &[Range<usize>], kv_ranges: &[Range<usize>]) -> Result<Tensor> {
    if q_ranges.len() != kv_ranges.len() {
        return Err(crate::Error::msg("varlen attention: q and kv have different batch sizes"));
    }
    let mut outs = Vec::with_capacity(q_ranges.len());
    for (qr, kr) in q_ranges.iter().zip(kv_ranges) {
        if qr.is_empty() {
            continue;
        }
        if kr.is_empty() {
            outs.push(q.narrow(0, qr.start, qr.len())?.zeros_like()?);
            continue;
        }
        // [L, H, D] → [1, H, L, D]
        let per =
            |t: &Tensor, r: &Range<usize>| -> candle_core::Result<Tensor> { t.narrow(0, r.start, r.len())?.transpose(0, 1)?.unsqueeze(0) };
        let o = attention(&per(q, qr)?, &per(k, kr)?, &per(v, kr)?)?;
        outs.push(o.squeeze(0)?.transpose(0, 1)?);
    }
    if outs.is_empty() {
        return Ok(q.zeros_like()?);
    }
    Ok(Tensor::cat(&outs, 0)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn fast_path_matches_plain() -> Result<()> {
        use crate::model::nn::fast::Precision;
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (45, 3, 16), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (50, 3, 16), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (50, 3, 16), &dev)?;
        let (qr, kr) = (vec![0..20, 20..20, 20..45], vec![0..31, 31..40, 40..40]);
        let plain = varlen_attention(&q, &k, &v, &qr, &kr)?;
        for (p, tol) in [(Precision::F32, 1e-5), (Precision::Bf16, 3e-2)] {
            let fast = varlen_attention_with(&q, &k, &v, &qr, &kr, Compute::fast(p))?;
            let d = crate::util::max_abs_diff(&plain, &fast)?;
            assert!(d < tol, "{p}: diff {d}");
        }
        Ok(())
    }

    #[test]
    fn items_do_not_attend_across_batches() -> Result<()> {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (7, 2, 4), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (7, 2, 4), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (7, 2, 4), &dev)?;
        let r = vec![0..3, 3..7];
        let all = varlen_attention(&q, &k, &v, &r, &r)?;
        // Item 1 alone must give the same rows.
        let r1: Vec<_> = std::iter::once(0..4).collect();
        let one = varlen_attention(&q.narrow(0, 3, 4)?, &k.narrow(0, 3, 4)?, &v.narrow(0, 3, 4)?, &r1, &r1)?;
        let d = crate::util::max_abs_diff(&all.narrow(0, 3, 4)?, &one)?;
        assert!(d < 1e-6);
        Ok(())
    }
}
