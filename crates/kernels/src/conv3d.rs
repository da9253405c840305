//! Dense 3D convolution on NCDHW `f32` volumes (stride 1, cubic kernel,
//! symmetric zero padding), plus the small volume ops the sparse-structure
//! decoder needs around it (channel LayerNorm, 3D pixel shuffle).
//!
//! The convolution is im2col + GEMM, but the im2col matrix is only ever built
//! for a bounded chunk of output rows (a run of `(d, h)` lines), so peak extra
//! memory is `threads × COL_BUDGET` floats whatever the grid size. Chunks run in
//! parallel on rayon, each with a single-threaded GEMM (the `gemm` crate).
//!
//! Weights use the PyTorch `Conv3d` layout `[Cout, Cin, k, k, k]`, which read
//! row-major is already the `[Cout, Cin·k³]` GEMM left operand, so no packing
//! step is needed at load time.

use crate::buf::SendPtr;
use crate::gemm::{WeightFormat, MR};
use crate::isa::Isa;
use rayon::prelude::*;

mod winograd;

/// Upper bound on the floats of one im2col chunk (per worker thread): 4 MiB.
const COL_BUDGET: usize = 1 << 20;
/// Aim for at least this many output positions per GEMM when the budget allows,
/// so the weight matrix is streamed through the cache as few times as possible.
const MIN_COLS: usize = 128;

/// Shape of a stride-1 3D convolution on an NCDHW volume.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Conv3dShape {
    /// Batch size (N).
    pub batch: usize,
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Input depth, height, width.
    pub d: usize,
    /// Input height.
    pub h: usize,
    /// Input width.
    pub w: usize,
    /// Cubic kernel size.
    pub k: usize,
    /// Zero padding on every side.
    pub pad: usize,
}

impl Conv3dShape {
    /// Output spatial size `(Do, Ho, Wo)`; `None` when the kernel does not fit.
    pub fn out_dims(&self) -> Option<(usize, usize, usize)> {
        let f = |n: usize| (n + 2 * self.pad + 1).checked_sub(self.k).filter(|&o| o > 0);
        Some((f(self.d)?, f(self.h)?, f(self.w)?))
    }
    /// Elements of the NCDHW input.
    pub fn input_len(&self) -> usize {
        self.batch * self.cin * self.d * self.h * self.w
    }
    /// Elements of the `[cout, cin, k, k, k]` weight.
    pub fn weight_len(&self) -> usize {
        self.cout * self.cin * self.k * self.k * self.k
    }
    /// Elements of the NCDHW output (0 when the output would be empty).
    pub fn output_len(&self) -> usize {
        let (od, oh, ow) = self.out_dims().unwrap_or((0, 0, 0));
        self.batch * self.cout * od * oh * ow
    }
    fn check(&self, x: &[f32], weight: &[f32], bias: Option<&[f32]>, out: &[f32]) -> Result<(), String> {
        if self.k == 0 || self.cin == 0 || self.cout == 0 {
            return Err(format!("conv3d: degenerate shape {self:?}"));
        }
        if self.out_dims().is_none() {
            return Err(format!("conv3d: kernel {} with padding {} does not fit input {:?}", self.k, self.pad, (self.d, self.h, self.w)));
        }
        let lens = [
            ("input", x.len(), self.input_len()),
            ("weight", weight.len(), self.weight_len()),
            ("output", out.len(), self.output_len()),
            ("bias", bias.map_or(self.cout, |b| b.len()), self.cout),
        ];
        for (what, got, want) in lens {
            if got != want {
                return Err(format!("conv3d: {what} has {got} values, shape {self:?} needs {want}"));
            }
        }
        Ok(())
    }
}

/// Channel counts from which the 3×3×3 / pad-1 convolution switches to
/// Winograd F(2³, 3³): it needs 3.4× fewer multiplies, but its per-tap GEMMs
/// are `Cout × Cin`, too small to run well for narrow layers.
const WINOGRAD_MIN_CHANNELS: usize = 64;

/// `out = conv3d(x, weight) + bias`, or `out += conv3d(x, weight) + bias` when
/// `accumulate` (used to fuse a residual add). Returns an error, without
/// touching `out`, when the slice lengths do not match `s`.
///
/// Wide 3×3×3 pad-1 layers run [`conv3d_winograd`], everything else
/// [`conv3d_im2col`].
pub fn conv3d(x: &[f32], s: &Conv3dShape, weight: &[f32], bias: Option<&[f32]>, out: &mut [f32], accumulate: bool) -> Result<(), String> {
    conv3d_with(x, s, weight, bias, out, accumulate, WeightFormat::F32, Isa::best())
}

/// [`conv3d`] with the Winograd layers' weight `format` and kernels `isa`
/// (see [`conv3d_winograd`]); the im2col layers compute in f32 whatever the format.
#[allow(clippy::too_many_arguments)]
pub fn conv3d_with(
    x: &[f32],
    s: &Conv3dShape,
    weight: &[f32],
    bias: Option<&[f32]>,
    out: &mut [f32],
    accumulate: bool,
    format: WeightFormat,
    isa: Isa,
) -> Result<(), String> {
    if s.k == 3 && s.pad == 1 && s.cin >= WINOGRAD_MIN_CHANNELS && s.cout >= WINOGRAD_MIN_CHANNELS {
        conv3d_winograd(x, s, weight, bias, out, accumulate, format, isa)
    } else {
        conv3d_im2col(x, s, weight, bias, out, accumulate)
    }
}

/// im2col + GEMM over bounded chunks of output rows; any `k`/`pad`. Same contract as [`conv3d`].
pub fn conv3d_im2col(
    x: &[f32],
    s: &Conv3dShape,
    weight: &[f32],
    bias: Option<&[f32]>,
    out: &mut [f32],
    accumulate: bool,
) -> Result<(), String> {
    s.check(x, weight, bias, out)?;
    let (od, oh, ow) = s.out_dims().expect("checked");
    let kk = s.cin * s.k * s.k * s.k;
    let plane_out = od * oh * ow;
    let rows = od * oh;
    // Rows per chunk: as many as the im2col budget allows, at least one, and
    // small enough that every thread gets a few chunks to balance the load.
    let budget_rows = (COL_BUDGET / (kk * ow)).max(1);
    let want_rows = MIN_COLS.div_ceil(ow);
    let threads = rayon::current_num_threads().max(1);
    let balance_rows = (rows * s.batch).div_ceil(4 * threads).max(1);
    let chunk_rows = budget_rows.min(balance_rows.max(want_rows)).max(1);
    let n_chunks = rows.div_ceil(chunk_rows);

    let out_ptr = SendPtr(out.as_mut_ptr());
    (0..s.batch * n_chunks).into_par_iter().for_each_init(
        || vec![0f32; kk * chunk_rows * ow],
        |col, job| {
            let b = job / n_chunks;
            let r0 = (job % n_chunks) * chunk_rows;
            let r1 = (r0 + chunk_rows).min(rows);
            let ncols = (r1 - r0) * ow;
            let xb = &x[b * s.cin * s.d * s.h * s.w..][..s.cin * s.d * s.h * s.w];
            im2col_rows(xb, s, (oh, ow), r0, r1, &mut col[..kk * ncols]);
            // SAFETY: this job owns output columns [r0*ow, r1*ow) of batch b
            // for every output channel; no other job writes them.
            unsafe {
                let dst = out_ptr.get().add(b * s.cout * plane_out + r0 * ow);
                let rs = plane_out as isize;
                match (bias, accumulate) {
                    (Some(bv), acc) => {
                        for (co, &bc) in bv.iter().enumerate() {
                            let row = std::slice::from_raw_parts_mut(dst.add(co * plane_out), ncols);
                            if acc {
                                row.iter_mut().for_each(|v| *v += bc);
                            } else {
                                row.fill(bc);
                            }
                        }
                    }
                    (None, false) => {
                        for co in 0..s.cout {
                            std::slice::from_raw_parts_mut(dst.add(co * plane_out), ncols).fill(0.0);
                        }
                    }
                    (None, true) => {}
                }
                gemm::gemm(
                    s.cout,
                    ncols,
                    kk,
                    dst,
                    1,
                    rs,
                    true,
                    weight.as_ptr(),
                    1,
                    kk as isize,
                    col.as_ptr(),
                    1,
                    ncols as isize,
                    1.0,
                    1.0,
                    false,
                    false,
                    false,
                    gemm::Parallelism::None,
                );
            }
        },
    );
    Ok(())
}

/// Fill `col` (`[Cin·k³, (r1-r0)·Wo]`, row-major) with the input patches of
/// output rows `r0..r1` (row `r` = output line `(r / Ho, r % Ho)`).
fn im2col_rows(xb: &[f32], s: &Conv3dShape, (oh, ow): (usize, usize), r0: usize, r1: usize, col: &mut [f32]) {
    let ncols = (r1 - r0) * ow;
    let (k, pad) = (s.k, s.pad);
    let plane = s.d * s.h * s.w;
    for ci in 0..s.cin {
        let xc = &xb[ci * plane..][..plane];
        for kd in 0..k {
            for kh in 0..k {
                for kw in 0..k {
                    let kidx = ((ci * k + kd) * k + kh) * k + kw;
                    let dst_row = &mut col[kidx * ncols..][..ncols];
                    // Valid output columns: 0 <= ow_ + kw - pad < W.
                    let lo = pad.saturating_sub(kw).min(ow);
                    let hi = (s.w + pad).saturating_sub(kw).min(ow).max(lo);
                    for r in r0..r1 {
                        let seg = &mut dst_row[(r - r0) * ow..][..ow];
                        let (odd, ohh) = (r / oh, r % oh);
                        let id = (odd + kd) as isize - pad as isize;
                        let ih = (ohh + kh) as isize - pad as isize;
                        if id < 0 || id >= s.d as isize || ih < 0 || ih >= s.h as isize || lo == hi {
                            seg.fill(0.0);
                            continue;
                        }
                        let src = &xc[(id as usize * s.h + ih as usize) * s.w..][..s.w];
                        seg[..lo].fill(0.0);
                        seg[lo..hi].copy_from_slice(&src[lo + kw - pad..hi + kw - pad]);
                        seg[hi..].fill(0.0);
                    }
                }
            }
        }
    }
}

/// Floats of the transformed input + output buffers of one Winograd tile
/// chunk (64 MiB): narrow layers get more tiles per GEMM, wide ones fewer.
const WINO_BUDGET: usize = 16 << 20;

/// 3×3×3, pad-1 convolution by Winograd F(2³, 3³) (the `winograd` module docs):
/// 3.4× fewer multiplies than direct, as 64 `[tiles, Cin] × [Cin, Cout]`
/// GEMMs on recon's packed GEMM. `format` is the storage of the transformed
/// weights (bf16: they and the transformed activations are rounded to bf16,
/// products accumulated in f32), `isa` the kernels. Same contract as
/// [`conv3d`], restricted to `k = 3, pad = 1`.
#[allow(clippy::too_many_arguments)]
pub fn conv3d_winograd(
    x: &[f32],
    s: &Conv3dShape,
    weight: &[f32],
    bias: Option<&[f32]>,
    out: &mut [f32],
    accumulate: bool,
    format: WeightFormat,
    isa: Isa,
) -> Result<(), String> {
    s.check(x, weight, bias, out)?;
    if s.k != 3 || s.pad != 1 {
        return Err(format!("conv3d_winograd: only k=3, pad=1 (got k={}, pad={})", s.k, s.pad));
    }
    // Whole register tiles of the GEMM (MR rows) per chunk.
    let tiles_per_chunk = (WINO_BUDGET / (64 * (s.cin + s.cout).max(1))).clamp(32, 4096) / MR * MR;
    winograd::winograd(x, s, weight, bias, out, accumulate, format, isa, tiles_per_chunk, None)
}

/// Straightforward direct convolution, the reference the fast path is tested
/// against. Same contract as [`conv3d`] with `accumulate = false`.
pub fn conv3d_reference(x: &[f32], s: &Conv3dShape, weight: &[f32], bias: Option<&[f32]>, out: &mut [f32]) -> Result<(), String> {
    s.check(x, weight, bias, out)?;
    let (od, oh, ow) = s.out_dims().expect("checked");
    let k = s.k;
    for b in 0..s.batch {
        for co in 0..s.cout {
            for z in 0..od {
                for y in 0..oh {
                    for xx in 0..ow {
                        let mut acc = bias.map_or(0.0, |bv| bv[co] as f64);
                        for ci in 0..s.cin {
                            for kd in 0..k {
                                for kh in 0..k {
                                    for kw in 0..k {
                                        let id = (z + kd) as isize - s.pad as isize;
                                        let ih = (y + kh) as isize - s.pad as isize;
                                        let iw = (xx + kw) as isize - s.pad as isize;
                                        if id < 0 || ih < 0 || iw < 0 || id >= s.d as isize || ih >= s.h as isize || iw >= s.w as isize {
                                            continue;
                                        }
                                        let xi = (((b * s.cin + ci) * s.d + id as usize) * s.h + ih as usize) * s.w + iw as usize;
                                        let wi = (((co * s.cin + ci) * k + kd) * k + kh) * k + kw;
                                        acc += x[xi] as f64 * weight[wi] as f64;
                                    }
                                }
                            }
                        }
                        out[(((b * s.cout + co) * od + z) * oh + y) * ow + xx] = acc as f32;
                    }
                }
            }
        }
    }
    Ok(())
}

/// LayerNorm over the channel dim of `x` = `[B, C, N]` (N = flattened spatial
/// positions), with affine `gamma`/`beta` of length C, optionally followed by
/// SiLU. Statistics are two-pass in f32 per position, as `ChannelLayerNorm32`.
pub fn channel_layer_norm(
    x: &[f32],
    (batch, c, n): (usize, usize, usize),
    gamma: &[f32],
    beta: &[f32],
    eps: f32,
    silu: bool,
    out: &mut [f32],
) -> Result<(), String> {
    if x.len() != batch * c * n || out.len() != x.len() || gamma.len() != c || beta.len() != c {
        return Err(format!(
            "channel_layer_norm: lengths x {} out {} gamma {} beta {} do not fit [B={batch}, C={c}, N={n}]",
            x.len(),
            out.len(),
            gamma.len(),
            beta.len()
        ));
    }
    // Positions are processed in blocks so the per-channel loops run over
    // contiguous memory and vectorise.
    const BLK: usize = 256;
    let nblk = n.div_ceil(BLK);
    let out_ptr = SendPtr(out.as_mut_ptr());
    (0..batch * nblk).into_par_iter().for_each_init(
        || (vec![0f32; BLK], vec![0f32; BLK]),
        |(mean, rstd), job| {
            let b = job / nblk;
            let p0 = (job % nblk) * BLK;
            let len = BLK.min(n - p0);
            let (mean, rstd) = (&mut mean[..len], &mut rstd[..len]);
            let xb = &x[b * c * n..][..c * n];
            mean.fill(0.0);
            for ci in 0..c {
                let row = &xb[ci * n + p0..][..len];
                mean.iter_mut().zip(row).for_each(|(m, v)| *m += v);
            }
            mean.iter_mut().for_each(|m| *m /= c as f32);
            rstd.fill(0.0);
            for ci in 0..c {
                let row = &xb[ci * n + p0..][..len];
                rstd.iter_mut().zip(row.iter().zip(mean.iter())).for_each(|(s, (v, m))| *s += (v - m) * (v - m));
            }
            rstd.iter_mut().for_each(|s| *s = 1.0 / (*s / c as f32 + eps).sqrt());
            for ci in 0..c {
                let row = &xb[ci * n + p0..][..len];
                // SAFETY: this job owns positions [p0, p0+len) of batch b.
                let dst = unsafe { std::slice::from_raw_parts_mut(out_ptr.get().add(b * c * n + ci * n + p0), len) };
                let (g, be) = (gamma[ci], beta[ci]);
                for i in 0..len {
                    let y = (row[i] - mean[i]) * rstd[i] * g + be;
                    dst[i] = if silu { y / (1.0 + (-y).exp()) } else { y };
                }
            }
        },
    );
    Ok(())
}

/// 3D pixel shuffle with scale 2, as TRELLIS `pixel_shuffle_3d`: input
/// `[B, C·8, D, H, W]` → output `[B, C, 2D, 2H, 2W]`, where input channel
/// `c·8 + (a·4 + b·2 + e)` lands at offset `(a, b, e)` of voxel `(d, h, w)`.
pub fn pixel_shuffle_3d(x: &[f32], (batch, c8, d, h, w): (usize, usize, usize, usize, usize), out: &mut [f32]) -> Result<(), String> {
    if c8 % 8 != 0 || x.len() != batch * c8 * d * h * w || out.len() != x.len() {
        return Err(format!("pixel_shuffle_3d: {} channels / {} values do not fit [B={batch}, C={c8}, {d}, {h}, {w}]", c8, x.len()));
    }
    let c = c8 / 8;
    let (h2, w2) = (2 * h, 2 * w);
    // One output plane (fixed b, c, z) per job.
    out.par_chunks_mut(h2 * w2).enumerate().for_each(|(pi, plane)| {
        let z = pi % (2 * d);
        let bc = pi / (2 * d);
        let (b, co) = (bc / c, bc % c);
        let (dz, a) = (z / 2, z % 2);
        for y in 0..h2 {
            let (hy, bb) = (y / 2, y % 2);
            let dst = &mut plane[y * w2..][..w2];
            for e in 0..2 {
                let ch = co * 8 + a * 4 + bb * 2 + e;
                let src = &x[(((b * c8 + ch) * d + dz) * h + hy) * w..][..w];
                for (xx, v) in src.iter().enumerate() {
                    dst[2 * xx + e] = *v;
                }
            }
        }
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Small deterministic generator (xorshift) so tests need no extra crate.
    fn rand_vec(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect()
    }

    fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
    }

    fn check_shape(s: Conv3dShape, with_bias: bool, seed: u64) {
        let x = rand_vec(s.input_len(), seed);
        let wt = rand_vec(s.weight_len(), seed + 1);
        let bias = rand_vec(s.cout, seed + 2);
        let bias = with_bias.then_some(&bias[..]);
        let mut got = vec![f32::NAN; s.output_len()];
        let mut want = vec![0.0; s.output_len()];
        conv3d(&x, &s, &wt, bias, &mut got, false).unwrap();
        conv3d_reference(&x, &s, &wt, bias, &mut want).unwrap();
        let scale = (s.cin * s.k * s.k * s.k) as f32;
        let d = max_diff(&got, &want);
        assert!(d <= 1e-5 * scale.sqrt().max(1.0) * 4.0, "{s:?}: max diff {d}");
    }

    #[test]
    fn conv3d_matches_reference_on_awkward_shapes() {
        let shapes = [
            (1, 3, 5, 4, 4, 4, 3, 1),
            (2, 7, 3, 5, 6, 7, 3, 1),
            (2, 1, 1, 3, 3, 3, 3, 1),
            (1, 13, 9, 6, 2, 5, 3, 1),
            (2, 5, 4, 4, 5, 3, 1, 0),
            (1, 4, 6, 5, 5, 6, 3, 0),
            (1, 3, 2, 4, 3, 5, 2, 1),
            (1, 6, 5, 3, 4, 5, 5, 2),
        ];
        for (i, &(batch, cin, cout, d, h, w, k, pad)) in shapes.iter().enumerate() {
            let s = Conv3dShape { batch, cin, cout, d, h, w, k, pad };
            check_shape(s, i % 3 != 2, 100 + i as u64);
        }
    }

    /// Relative L2 error of `got` against `want`.
    fn rel_l2(got: &[f32], want: &[f32]) -> f64 {
        let num: f64 = got.iter().zip(want).map(|(a, b)| ((a - b) as f64).powi(2)).sum();
        let den: f64 = want.iter().map(|b| (*b as f64).powi(2)).sum();
        (num / den.max(1e-30)).sqrt()
    }

    #[test]
    fn winograd_matches_reference() {
        // (batch, cin, cout, d, h, w): odd sizes exercise the cropped edge tiles,
        // channel counts off multiples of 16 / 32 the partial vectors and panels.
        let cases = [(1, 3, 2, 4, 4, 4), (2, 5, 7, 3, 5, 6), (1, 70, 66, 5, 3, 7), (1, 4, 3, 1, 2, 1), (2, 20, 35, 3, 4, 5)];
        for (i, &(batch, cin, cout, d, h, w)) in cases.iter().enumerate() {
            let s = Conv3dShape { batch, cin, cout, d, h, w, k: 3, pad: 1 };
            let x = rand_vec(s.input_len(), 300 + i as u64);
            let wt = rand_vec(s.weight_len(), 400 + i as u64);
            let bias = rand_vec(cout, 500 + i as u64);
            let bias = (i % 2 == 0).then_some(&bias[..]);
            let mut want = vec![0.0; s.output_len()];
            conv3d_reference(&x, &s, &wt, bias, &mut want).unwrap();
            let base = rand_vec(s.output_len(), 600);
            let want_acc: Vec<f32> = base.iter().zip(&want).map(|(a, b)| a + b).collect();
            for isa in Isa::all_supported() {
                for format in [WeightFormat::F32, WeightFormat::Bf16, WeightFormat::F16] {
                    let mut got = vec![f32::NAN; s.output_len()];
                    conv3d_winograd(&x, &s, &wt, bias, &mut got, false, format, isa).unwrap();
                    let mut acc = base.clone();
                    conv3d_winograd(&x, &s, &wt, bias, &mut acc, true, format, isa).unwrap();
                    let diff = max_diff(&got, &want);
                    let tag = format!("case {i} {isa:?} {format:?}");
                    match format {
                        WeightFormat::F32 => {
                            assert!(diff < 1e-5 * (cin as f32 * 27.0).sqrt() * 4.0, "{tag}: {diff}");
                            assert!(max_diff(&acc, &want_acc) < 1e-3, "{tag}: accumulate");
                        }
                        // Transformed weights (and, for bf16, activations) rounded:
                        // the budget is 1 % relative L2; bf16 must really round.
                        _ => {
                            let rel = rel_l2(&got, &want);
                            let lo = if format == WeightFormat::Bf16 { 1e-5 } else { 0.0 };
                            assert!(rel < 1e-2 && rel > lo, "{tag}: relative error {rel}");
                            assert!(rel_l2(&acc, &want_acc) < 1e-2, "{tag}: accumulate");
                        }
                    }
                }
            }
        }
        // Several tile chunks (the last one partial) and k slices (the last one
        // partial), batch 2, no bias.
        let s = Conv3dShape { batch: 2, cin: 70, cout: 5, d: 5, h: 6, w: 7, k: 3, pad: 1 };
        let x = rand_vec(s.input_len(), 700);
        let wt = rand_vec(s.weight_len(), 701);
        let mut want = vec![0.0; s.output_len()];
        conv3d_reference(&x, &s, &wt, None, &mut want).unwrap();
        for isa in Isa::all_supported() {
            for format in [WeightFormat::F32, WeightFormat::Bf16] {
                for (chunk, kc) in [(7, Some(16)), (15, Some(32)), (1000, None)] {
                    let mut got = vec![f32::NAN; s.output_len()];
                    winograd::winograd(&x, &s, &wt, None, &mut got, false, format, isa, chunk, kc).unwrap();
                    let tag = format!("{isa:?} {format:?} chunk {chunk} kc {kc:?}");
                    match format {
                        WeightFormat::F32 => assert!(max_diff(&got, &want) < 1e-4, "{tag}"),
                        _ => assert!(rel_l2(&got, &want) < 1e-2, "{tag}"),
                    }
                }
            }
        }
        // Through the dispatcher at a width that selects Winograd.
        let s = Conv3dShape { batch: 1, cin: 64, cout: 64, d: 6, h: 14, w: 13, k: 3, pad: 1 };
        check_shape(s, true, 77);
    }

    #[test]
    fn conv3d_many_chunks_and_large_k() {
        // Cin·27 large enough that the im2col budget forces one-row chunks.
        let s = Conv3dShape { batch: 1, cin: 1500, cout: 3, d: 3, h: 4, w: 27, k: 3, pad: 1 };
        check_shape(s, true, 7);
    }

    #[test]
    fn conv3d_accumulate_adds_to_output() {
        let s = Conv3dShape { batch: 2, cin: 3, cout: 4, d: 3, h: 4, w: 5, k: 3, pad: 1 };
        let x = rand_vec(s.input_len(), 1);
        let wt = rand_vec(s.weight_len(), 2);
        let bias = rand_vec(4, 3);
        let base = rand_vec(s.output_len(), 4);
        let mut conv = vec![0.0; s.output_len()];
        conv3d(&x, &s, &wt, Some(&bias), &mut conv, false).unwrap();
        let mut acc = base.clone();
        conv3d(&x, &s, &wt, Some(&bias), &mut acc, true).unwrap();
        let want: Vec<f32> = base.iter().zip(&conv).map(|(a, b)| a + b).collect();
        assert!(max_diff(&acc, &want) < 1e-6);
    }

    #[test]
    fn conv3d_rejects_bad_lengths() {
        let s = Conv3dShape { batch: 1, cin: 2, cout: 2, d: 2, h: 2, w: 2, k: 3, pad: 1 };
        let mut out = vec![0.0; s.output_len()];
        assert!(conv3d(&[0.0; 3], &s, &vec![0.0; s.weight_len()], None, &mut out, false).is_err());
        let s2 = Conv3dShape { k: 5, pad: 0, ..s };
        assert!(conv3d(&[0.0; 16], &s2, &vec![0.0; s2.weight_len()], None, &mut [], false).is_err());
    }

    #[test]
    fn channel_layer_norm_matches_naive() {
        let (b, c, n) = (2, 5, 300);
        let x = rand_vec(b * c * n, 9);
        let g = rand_vec(c, 10);
        let be = rand_vec(c, 11);
        for silu in [false, true] {
            let mut out = vec![0.0; x.len()];
            channel_layer_norm(&x, (b, c, n), &g, &be, 1e-5, silu, &mut out).unwrap();
            for bi in 0..b {
                for p in 0..n {
                    let v: Vec<f64> = (0..c).map(|ci| x[(bi * c + ci) * n + p] as f64).collect();
                    let m = v.iter().sum::<f64>() / c as f64;
                    let var = v.iter().map(|a| (a - m) * (a - m)).sum::<f64>() / c as f64;
                    for ci in 0..c {
                        let mut y = (v[ci] - m) / (var + 1e-5).sqrt() * g[ci] as f64 + be[ci] as f64;
                        if silu {
                            y /= 1.0 + (-y).exp();
                        }
                        let got = out[(bi * c + ci) * n + p] as f64;
                        assert!((got - y).abs() < 1e-5, "silu {silu}: {got} vs {y}");
                    }
                }
            }
        }
    }

    #[test]
    fn pixel_shuffle_places_channels() {
        let (b, c, d, h, w) = (2, 3, 2, 3, 4);
        let x: Vec<f32> = (0..b * c * 8 * d * h * w).map(|i| i as f32).collect();
        let mut out = vec![0.0; x.len()];
        pixel_shuffle_3d(&x, (b, c * 8, d, h, w), &mut out).unwrap();
        for bi in 0..b {
            for co in 0..c {
                for z in 0..2 * d {
                    for y in 0..2 * h {
                        for xx in 0..2 * w {
                            let ch = co * 8 + (z % 2) * 4 + (y % 2) * 2 + xx % 2;
                            let src = (((bi * c * 8 + ch) * d + z / 2) * h + y / 2) * w + xx / 2;
                            let dst = (((bi * c + co) * 2 * d + z) * 2 * h + y) * 2 * w + xx;
                            assert_eq!(out[dst], x[src]);
                        }
                    }
                }
            }
        }
    }
}
