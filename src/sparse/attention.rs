//! Variable-length full attention over sparse tensors: every batch item's
//! rows attend only to each other (TRELLIS sparse `full` attention, which
//! upstream runs as block-diagonal varlen attention).

use crate::model::common::attention;
use crate::Result;
use candle_core::Tensor;
use std::ops::Range;

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
        let per = |t: &Tensor, r: &Range<usize>| -> candle_core::Result<Tensor> { t.narrow(0, r.start, r.len())?.transpose(0, 1)?.unsqueeze(0) };
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
    fn items_do_not_attend_across_batches() -> Result<()> {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (7, 2, 4), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (7, 2, 4), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (7, 2, 4), &dev)?;
        let r = vec![0..3, 3..7];
        let all = varlen_attention(&q, &k, &v, &r, &r)?;
        // Item 1 alone must give the same rows.
        let r1 = vec![0..4];
        let one = varlen_attention(&q.narrow(0, 3, 4)?, &k.narrow(0, 3, 4)?, &v.narrow(0, 3, 4)?, &r1, &r1)?;
        let d = crate::conformance::max_abs_diff(&all.narrow(0, 3, 4)?, &one)?;
        assert!(d < 1e-6);
        Ok(())
    }
}
