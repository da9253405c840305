//! Fused multi-head softmax attention (flash-attention style): tiled, with an
//! online softmax, so no full score matrix is ever stored. Memory beyond the
//! output is a few packed key/value panels per thread.
//!
//! Inputs are read in place from row-major buffers: element `(row, head, e)`
//! of q, k, v and the output sits at `data[row·stride + offset + head·d + e]`,
//! so q/k/v can be slices of one fused `to_qkv` projection. Work is given as
//! [`Segment`]s (a range of query rows attending to a range of key rows):
//! one per batch item for dense attention, one per item for varlen, one per
//! window for swin attention.
//!
//! Per (segment, head, chunk of queries) a task packs K (as GEMM `A` tiles of
//! `MR` keys) and Vᵀ (tiles of `MR` channels), then for each 32-query panel
//! and each block of `BC` keys computes `Sᵀ = K·Qᵀ` with the GEMM
//! microkernel, updates the running column max / sum, exponentiates in place
//! and accumulates `Oᵀ += Vᵀ·P`. With [`AttnPrecision::Bf16`], Q, K, V and P
//! are rounded to bf16 and products accumulate in f32 (`vdpbf16ps` where
//! available); softmax statistics stay in f32.

use crate::buf::{AlignedBuf, SendPtr};
use crate::gemm::{self, a_format, a_tile_words, microkernel, pack_a_rows, pack_a_tile_cols, AFormat, WeightFormat, MR, NR};
use crate::isa::{Isa, Simd};
use rayon::prelude::*;
use std::ops::Range;

/// Keys per block (a multiple of `MR` and even).
const BC: usize = MR * 8;
/// Queries per task (a multiple of `NR`).
const QCHUNK: usize = NR * 4;

/// Arithmetic of the two products.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum AttnPrecision {
    /// Both products in f32.
    F32,
    /// Q, K, V and P rounded to bf16, products accumulated in f32.
    Bf16,
}

impl AttnPrecision {
    fn format(self) -> WeightFormat {
        match self {
            AttnPrecision::F32 => WeightFormat::F32,
            AttnPrecision::Bf16 => WeightFormat::Bf16,
        }
    }
}

/// Where heads live in a row-major buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeadLayout {
    /// Elements between consecutive rows.
    pub stride: usize,
    /// Element offset of head 0 within a row.
    pub offset: usize,
}

impl HeadLayout {
    /// A layout with `stride` elements between rows and head 0 at element `offset`.
    pub fn new(stride: usize, offset: usize) -> Self {
        Self { stride, offset }
    }
    #[inline(always)]
    fn at(&self, row: usize, head: usize, d: usize) -> usize {
        row * self.stride + self.offset + head * d
    }
}

/// Query rows `q` attend to key/value rows `kv`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Segment {
    /// Query rows of the segment.
    pub q: Range<usize>,
    /// Key/value rows the queries attend to.
    pub kv: Range<usize>,
}

/// Shapes and layouts of one attention call.
#[derive(Debug, Clone, Copy)]
pub struct AttnSpec {
    /// Number of heads.
    pub heads: usize,
    /// Elements per head (`d`).
    pub head_dim: usize,
    /// Multiplies the scores (usually `1/√d`).
    pub scale: f32,
    /// Layout of the queries.
    pub q: HeadLayout,
    /// Layout of the keys.
    pub k: HeadLayout,
    /// Layout of the values.
    pub v: HeadLayout,
    /// Layout of the output.
    pub out: HeadLayout,
    /// Arithmetic of the two products.
    pub precision: AttnPrecision,
}

fn rows_needed(l: &HeadLayout, rows: usize, heads: usize, d: usize) -> usize {
    if rows == 0 {
        0
    } else {
        l.at(rows - 1, heads - 1, d) + d
    }
}

/// `out[q rows] = softmax(scale·Q·Kᵀ)·V` per head and segment. Rows of `out`
/// outside every segment are left untouched; a segment with no keys writes
/// zeros. Segments must not share query rows.
pub fn flash_attention(
    isa: Isa,
    spec: &AttnSpec,
    q: &[f32],
    k: &[f32],
    v: &[f32],
    segments: &[Segment],
    out: &mut [f32],
) -> Result<(), String> {
    let (h, d) = (spec.heads, spec.head_dim);
    if !isa.supported() {
        return Err(format!("attention: instruction set {} is not supported by this CPU", isa.name()));
    }
    if h == 0 || d == 0 {
        return Err("attention: heads and head_dim must be positive".into());
    }
    if spec.out.stride < h * d && segments.iter().any(|s| s.q.len() > 1) {
        return Err("attention: output rows overlap (stride < heads·head_dim)".into());
    }
    let qmax = segments.iter().map(|s| s.q.end).max().unwrap_or(0);
    let kmax = segments.iter().map(|s| s.kv.end).max().unwrap_or(0);
    for (name, buf, l, rows) in [("q", q, &spec.q, qmax), ("k", k, &spec.k, kmax), ("v", v, &spec.v, kmax)] {
        if buf.len() < rows_needed(l, rows, h, d) {
            return Err(format!("attention: {name} has {} values, {rows} rows need {}", buf.len(), rows_needed(l, rows, h, d)));
        }
    }
    if out.len() < rows_needed(&spec.out, qmax, h, d) {
        return Err(format!("attention: output has {} values, {qmax} rows need {}", out.len(), rows_needed(&spec.out, qmax, h, d)));
    }
    let mut sorted: Vec<&Range<usize>> = segments.iter().map(|s| &s.q).filter(|r| !r.is_empty()).collect();
    sorted.sort_by_key(|r| r.start);
    if sorted.windows(2).any(|w| w[1].start < w[0].end) {
        return Err("attention: segments share query rows".into());
    }

    // Heads are done a group at a time: K and Vᵀ of the group's heads are
    // packed once (phase 1), shared by all its query chunks (phase 2). A
    // group holds enough (segment, head) packs to keep every thread busy,
    // and no more: packing all heads at once would hold a copy of K and V
    // as large as the inputs (67 MB in f32 for a full-size guided step).
    let fmt = spec.precision.format();
    let afmt = a_format(isa, fmt);
    let kw = a_tile_words(afmt, d);
    let etiles = d.div_ceil(MR);
    let vw = a_tile_words(afmt, BC);
    let pack_words = |lk: usize| lk.div_ceil(MR) * kw + lk.div_ceil(BC) * etiles * vw;
    let live = segments.iter().filter(|s| !s.q.is_empty()).count().max(1);
    let group = (4 * rayon::current_num_threads()).div_ceil(live).clamp(1, h);
    let optr = SendPtr(out.as_mut_ptr());
    let mut packs = AlignedBuf::<u32>::zeroed(0);
    for h0 in (0..h).step_by(group) {
        let heads = h0..(h0 + group).min(h);
        let mut offsets = Vec::with_capacity(segments.len() * heads.len());
        let mut total = 0usize;
        for s in segments {
            for _ in heads.clone() {
                offsets.push(total);
                total += pack_words(s.kv.len());
            }
        }
        packs.ensure(total);
        {
            let mut parts: Vec<&mut [u32]> = Vec::with_capacity(offsets.len());
            let mut rest: &mut [u32] = &mut packs;
            for s in segments {
                for _ in heads.clone() {
                    let (a, b) = rest.split_at_mut(pack_words(s.kv.len()));
                    parts.push(a);
                    rest = b;
                }
            }
            parts.into_par_iter().enumerate().for_each(|(i, dst)| {
                let (s, hh) = (&segments[i / heads.len()], h0 + i % heads.len());
                pack_kv(afmt, spec, k, v, s.kv.clone(), hh, dst);
            });
        }

        let mut tasks = Vec::new();
        for (si, s) in segments.iter().enumerate() {
            for c in 0..s.q.len().div_ceil(QCHUNK) {
                for hh in heads.clone() {
                    tasks.push((si, hh, c));
                }
            }
        }
        let packs = &packs;
        tasks.into_par_iter().for_each_init(Scratch::default, |scr, (si, hh, c)| {
            let s = &segments[si];
            let q0 = s.q.start + c * QCHUNK;
            let q1 = (q0 + QCHUNK).min(s.q.end);
            let off = offsets[si * heads.len() + hh - h0];
            let pack = &packs[off..off + pack_words(s.kv.len())];
            // SAFETY: this task is the only writer of rows q0..q1, head hh (segments
            // do not share query rows; heads are disjoint column ranges).
            unsafe { attend(isa, spec, q, pack, q0..q1, s.kv.len(), hh, optr, scr) };
        });
    }
    Ok(())
}

/// K tiles then Vᵀ tiles of one (segment, head) into `dst`.
fn pack_kv(afmt: AFormat, spec: &AttnSpec, k: &[f32], v: &[f32], kr: Range<usize>, hh: usize, dst: &mut [u32]) {
    let d = spec.head_dim;
    let lk = kr.len();
    let kw = a_tile_words(afmt, d);
    let ktiles = lk.div_ceil(MR);
    let (kdst, vdst) = dst.split_at_mut(ktiles * kw);
    // Key rows lie a whole token apart (several KB): the hardware does not
    // prefetch them, so each tile asks for the rows of the next but one.
    let fetch_rows = |buf: &[f32], lay: &HeadLayout, rows: Range<usize>| {
        for r in rows.start.min(lk)..rows.end.min(lk) {
            prefetch(&buf[lay.at(kr.start + r, hh, d)..][..d]);
        }
    };
    fetch_rows(k, &spec.k, 0..2 * MR);
    for t in 0..ktiles {
        fetch_rows(k, &spec.k, (t + 2) * MR..(t + 3) * MR);
        let rows = MR.min(lk - t * MR);
        let first = spec.k.at(kr.start + t * MR, hh, d);
        // Rows of K for these keys, stride spec.k.stride.
        pack_a_rows(afmt, &mut kdst[t * kw..(t + 1) * kw], &k[first..], spec.k.stride, rows, d);
    }
    let etiles = d.div_ceil(MR);
    let vw = a_tile_words(afmt, BC);
    fetch_rows(v, &spec.v, 0..BC);
    for bi in 0..lk.div_ceil(BC) {
        let nk = BC.min(lk - bi * BC);
        let kb = kr.start + bi * BC;
        fetch_rows(v, &spec.v, (bi + 1) * BC..(bi + 2) * BC);
        for et in 0..etiles {
            let rows = MR.min(d - et * MR);
            let at = (bi * etiles + et) * vw;
            pack_a_tile_cols(afmt, &mut vdst[at..at + vw], rows, nk, |j| {
                let o = spec.v.at(kb + j, hh, d) + et * MR;
                &v[o..o + rows]
            });
        }
    }
}

#[derive(Default)]
struct Scratch {
    qpanel: Option<AlignedBuf<u32>>,
    s: Option<AlignedBuf<f32>>,
    p: Option<AlignedBuf<u32>>,
    o: Option<AlignedBuf<f32>>,
}

fn buf<T: Copy>(slot: &mut Option<AlignedBuf<T>>, len: usize) -> &mut AlignedBuf<T> {
    match slot {
        Some(b) if b.len() >= len => {}
        _ => *slot = Some(AlignedBuf::zeroed(len)),
    }
    slot.as_mut().unwrap()
}

/// # Safety
/// `out` must be valid for the rows and head written, with no other writer;
/// `pack` is this (segment, head)'s output of [`pack_kv`].
#[allow(clippy::too_many_arguments)]
unsafe fn attend(
    isa: Isa,
    spec: &AttnSpec,
    q: &[f32],
    pack: &[u32],
    qr: Range<usize>,
    lk: usize,
    hh: usize,
    out: SendPtr<f32>,
    scr: &mut Scratch,
) {
    let d = spec.head_dim;
    let fmt = spec.precision.format();
    let afmt = a_format(isa, fmt);
    let out_row = |row: usize| -> &mut [f32] { std::slice::from_raw_parts_mut(out.get().add(spec.out.at(row, hh, d)), d) };
    if lk == 0 {
        for r in qr {
            out_row(r).fill(0.0);
        }
        return;
    }
    let dp = fmt.k_padded(d);
    let kw = a_tile_words(afmt, d);
    let ktiles = lk.div_ceil(MR);
    let (kpack, vpack) = pack.split_at(ktiles * kw);
    let blocks = lk.div_ceil(BC);
    let etiles = d.div_ceil(MR);
    let vw = a_tile_words(afmt, BC);
    let qpanel = buf(&mut scr.qpanel, dp * NR);
    let sbuf = buf(&mut scr.s, BC * NR);
    let pbuf = buf(&mut scr.p, BC * NR);
    let obuf = buf(&mut scr.o, etiles * MR * NR);
    let mut m = [0f32; NR];
    let mut l = [0f32; NR];
    let mut alpha = [0f32; NR];

    let q_rows = |p: usize| p.min(qr.end)..(p + NR).min(qr.end);
    for r in q_rows(qr.start) {
        prefetch(&q[spec.q.at(r, hh, d)..][..d]);
    }
    let mut p0 = qr.start;
    while p0 < qr.end {
        let nq = NR.min(qr.end - p0);
        // The next panel's query rows (a token apart) arrive while this one computes.
        for r in q_rows(p0 + NR) {
            prefetch(&q[spec.q.at(r, hh, d)..][..d]);
        }
        // Qᵀ panel (B operand over d), pre-scaled.
        pack_q_panel(fmt, qpanel, d, nq, |j| &q[spec.q.at(p0 + j, hh, d)..][..d], spec.scale);
        obuf.fill(0.0);
        m.fill(-1e30);
        l.fill(0.0);
        for bi in 0..blocks {
            let nk = BC.min(lk - bi * BC);
            // Sᵀ[key][query] = K·Qᵀ.
            for t in 0..nk.div_ceil(MR) {
                let tile = bi * (BC / MR) + t;
                let rows = MR.min(nk - t * MR);
                microkernel(
                    isa,
                    fmt,
                    dp,
                    kpack.as_ptr().add(tile * kw),
                    qpanel.as_ptr() as *const u8,
                    sbuf.as_mut_ptr().add(t * MR * NR),
                    NR,
                    rows,
                    NR,
                    false,
                );
            }
            // Oᵀ += Vᵀ·P below, P (= Sᵀ after exp) as the B operand [key][query]:
            // f32 in place, or bf16 pairs written by the softmax pass itself.
            let nkp = fmt.k_padded(nk);
            let bptr: *const u8 = match fmt {
                WeightFormat::Bf16 => {
                    let pw = &mut pbuf[..nkp.div_ceil(2) * NR];
                    softmax_block_pairs(isa, &mut sbuf[..nk * NR], nk, &mut m, &mut l, &mut alpha, pw);
                    pw.as_ptr() as *const u8
                }
                _ => {
                    softmax_block(isa, &mut sbuf[..nk * NR], nk, &mut m, &mut l, &mut alpha);
                    sbuf.as_ptr() as *const u8
                }
            };
            // Rescale the running output by exp(m_old − m_new) per query
            // (nothing to do once the running maxima stop changing).
            if alpha.iter().any(|&a| a != 1.0) {
                scale_columns(isa, obuf, &alpha);
            }
            for et in 0..etiles {
                let rows = MR.min(d - et * MR);
                microkernel(
                    isa,
                    fmt,
                    nkp,
                    vpack.as_ptr().add((bi * etiles + et) * vw),
                    bptr,
                    obuf.as_mut_ptr().add(et * MR * NR),
                    NR,
                    rows,
                    NR,
                    true,
                );
            }
        }
        for j in 0..nq {
            let inv = 1.0 / l[j];
            for (e, o) in out_row(p0 + j).iter_mut().enumerate() {
                *o = obuf[e * NR + j] * inv;
            }
        }
        p0 += nq;
    }
}

/// Ask for the cache lines of `x` (a hint: no effect on results).
#[inline(always)]
fn prefetch(x: &[f32]) {
    #[cfg(target_arch = "x86_64")]
    for c in (0..x.len()).step_by(16) {
        // SAFETY: a prefetch never faults; the address is inside `x`.
        unsafe { std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(x.as_ptr().add(c) as *const i8) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}

/// Pack `nq ≤ NR` query rows times `scale` as a B panel over `d`: f32
/// `[e][j]` or bf16 pairs `[e/2][j][2]`; missing queries and the odd-d pad are zero.
fn pack_q_panel<'a>(fmt: WeightFormat, dst: &mut [u32], d: usize, nq: usize, row: impl Fn(usize) -> &'a [f32], scale: f32) {
    match fmt {
        WeightFormat::Bf16 => {
            // As u32 words: word (e/2, j) = bf16(q[j][e]) | bf16(q[j][e+1]) << 16.
            let words = d.div_ceil(2) * NR;
            dst[..words].fill(0);
            for j in 0..nq {
                gemm::bf16_pairs_down_column(&row(j)[..d], scale, dst, NR, j);
            }
        }
        _ => {
            if nq < NR {
                dst[..d * NR].fill(0);
            }
            for j in 0..nq {
                for (e, &x) in row(j).iter().enumerate() {
                    dst[e * NR + j] = (x * scale).to_bits();
                }
            }
        }
    }
}

/// Online-softmax update for one key block: `s` is `Sᵀ` `[nk][NR]`. Updates
/// the running max `m` and sum `l`, sets `alpha = exp(m_old − m_new)`, and
/// replaces `s` by `exp(s − m_new)`.
fn softmax_block(isa: Isa, s: &mut [f32], nk: usize, m: &mut [f32; NR], l: &mut [f32; NR], alpha: &mut [f32; NR]) {
    #[cfg(target_arch = "x86_64")]
    match isa.simd() {
        // SAFETY (both): the ISA is supported (checked by the caller) and s holds nk rows of NR.
        Simd::Avx512 => return unsafe { x86::softmax_block(s, nk, m, l, alpha) },
        Simd::Avx2 => return unsafe { avx2::softmax_block(s, nk, m, l, alpha) },
        Simd::Scalar => {}
    }
    let _ = isa;
    let mut mn = *m;
    for j in 0..nk {
        for c in 0..NR {
            mn[c] = mn[c].max(s[j * NR + c]);
        }
    }
    for c in 0..NR {
        alpha[c] = crate::vecmath::exp_approx(m[c] - mn[c]);
        l[c] *= alpha[c];
    }
    for j in 0..nk {
        for c in 0..NR {
            let p = crate::vecmath::exp_approx(s[j * NR + c] - mn[c]);
            s[j * NR + c] = p;
            l[c] += p;
        }
    }
    *m = mn;
}

/// [`softmax_block`] followed by [`to_bf16_pairs`] into `dst`, in one pass
/// over the scores on AVX-512 and AVX2 (the exponentials go straight to bf16
/// pairs instead of through `s`); same values either way.
fn softmax_block_pairs(isa: Isa, s: &mut [f32], nk: usize, m: &mut [f32; NR], l: &mut [f32; NR], alpha: &mut [f32; NR], dst: &mut [u32]) {
    // SAFETY (all vector paths): the ISA is supported (checked by the
    // caller); s holds nk rows of NR and dst ceil(nk/2)·NR words.
    #[cfg(target_arch = "x86_64")]
    match isa.simd() {
        Simd::Avx512 if isa == Isa::Avx512Bf16 => return unsafe { x86::softmax_block_pairs_bf16(s, nk, m, l, alpha, dst) },
        Simd::Avx512 => return unsafe { x86::softmax_block_pairs(s, nk, m, l, alpha, dst) },
        Simd::Avx2 => return unsafe { avx2::softmax_block_pairs(s, nk, m, l, alpha, dst) },
        Simd::Scalar => {}
    }
    softmax_block(isa, s, nk, m, l, alpha);
    to_bf16_pairs(s, nk, dst);
}

/// `o[r][c] *= alpha[c]` for every row of `NR` columns.
fn scale_columns(isa: Isa, o: &mut [f32], alpha: &[f32; NR]) {
    #[cfg(target_arch = "x86_64")]
    match isa.simd() {
        // SAFETY (both): the ISA is supported (checked by the caller).
        Simd::Avx512 => return unsafe { x86::scale_columns(o, alpha) },
        Simd::Avx2 => return unsafe { avx2::scale_columns(o, alpha) },
        Simd::Scalar => {}
    }
    let _ = isa;
    for row in o.chunks_exact_mut(NR) {
        for (v, &a) in row.iter_mut().zip(alpha) {
            *v *= a;
        }
    }
}

/// `Sᵀ` rows `[nk][NR]` f32 → bf16 pairs over keys: word `(j/2, c)` =
/// `bf16(s[j][c]) | bf16(s[j+1][c]) << 16` (round to nearest even; an odd last
/// key is paired with zero).
fn to_bf16_pairs(s: &[f32], nk: usize, dst: &mut [u32]) {
    for j2 in 0..nk.div_ceil(2) {
        for c in 0..NR {
            let lo = gemm::f32_to_bf16(s[2 * j2 * NR + c]) as u32;
            let hi = if 2 * j2 + 1 < nk { gemm::f32_to_bf16(s[(2 * j2 + 1) * NR + c]) as u32 } else { 0 };
            dst[j2 * NR + c] = lo | (hi << 16);
        }
    }
}

/// Plain reference: materialises each score row in f64 (Q, K, V, P rounded to
/// bf16 for [`AttnPrecision::Bf16`] as the kernel sees them), for tests.
pub fn attention_reference(spec: &AttnSpec, q: &[f32], k: &[f32], v: &[f32], segments: &[Segment], out: &mut [f32]) {
    let (h, d) = (spec.heads, spec.head_dim);
    let r = |x: f32| if spec.precision == AttnPrecision::Bf16 { gemm::round_bf16(x) } else { x };
    for s in segments {
        for qi in s.q.clone() {
            for hh in 0..h {
                let o = spec.out.at(qi, hh, d);
                if s.kv.is_empty() {
                    out[o..o + d].fill(0.0);
                    continue;
                }
                let qv: Vec<f64> = (0..d).map(|e| r(q[spec.q.at(qi, hh, d) + e] * spec.scale) as f64).collect();
                let scores: Vec<f64> = s.kv.clone().map(|ki| (0..d).map(|e| qv[e] * r(k[spec.k.at(ki, hh, d) + e]) as f64).sum()).collect();
                let mx = scores.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
                let p: Vec<f64> = scores.iter().map(|x| (x - mx).exp()).collect();
                let sum: f64 = p.iter().sum();
                for e in 0..d {
                    let acc: f64 = s.kv.clone().zip(&p).map(|(ki, &pj)| r(pj as f32) as f64 * r(v[spec.v.at(ki, hh, d) + e]) as f64).sum();
                    out[o + e] = (acc / sum) as f32;
                }
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::NR;
    use crate::gemm::x86::bf16_pairs;
    use crate::vecmath::x86::exp512;
    use std::arch::x86_64::*;

    /// The block's new running maxima `mn` (also stored into `m`) and
    /// `alpha = exp(m_old − mn)` (stored), and the running sums rescaled by
    /// it, to which the caller adds the block's exponentials.
    #[inline(always)]
    unsafe fn block_start(
        sp: *const f32,
        nk: usize,
        m: &mut [f32; NR],
        l: &[f32; NR],
        alpha: &mut [f32; NR],
    ) -> ([__m512; 2], [__m512; 2]) {
        let mo = [_mm512_loadu_ps(m.as_ptr()), _mm512_loadu_ps(m.as_ptr().add(16))];
        let mut mn = mo;
        for j in 0..nk {
            for h in 0..2 {
                mn[h] = _mm512_max_ps(mn[h], _mm512_loadu_ps(sp.add(j * NR + 16 * h)));
            }
        }
        let mut acc = [_mm512_setzero_ps(); 2];
        for h in 0..2 {
            let a = exp512(_mm512_sub_ps(mo[h], mn[h]));
            _mm512_storeu_ps(alpha.as_mut_ptr().add(16 * h), a);
            acc[h] = _mm512_mul_ps(_mm512_loadu_ps(l.as_ptr().add(16 * h)), a);
            _mm512_storeu_ps(m.as_mut_ptr().add(16 * h), mn[h]);
        }
        (mn, acc)
    }

    #[target_feature(enable = "avx512f,avx512bw,fma")]
    pub unsafe fn softmax_block(s: &mut [f32], nk: usize, m: &mut [f32; NR], l: &mut [f32; NR], alpha: &mut [f32; NR]) {
        let sp = s.as_mut_ptr();
        let (mn, mut acc) = block_start(sp, nk, m, l, alpha);
        for j in 0..nk {
            for h in 0..2 {
                let p = exp512(_mm512_sub_ps(_mm512_loadu_ps(sp.add(j * NR + 16 * h)), mn[h]));
                _mm512_storeu_ps(sp.add(j * NR + 16 * h), p);
                acc[h] = _mm512_add_ps(acc[h], p);
            }
        }
        for h in 0..2 {
            _mm512_storeu_ps(l.as_mut_ptr().add(16 * h), acc[h]);
        }
    }

    /// [`super::softmax_block`] with the exponentials of each key pair
    /// written straight to bf16 pairs by `pairs(even key, odd key)`.
    #[inline(always)]
    unsafe fn softmax_pairs_with(
        s: &[f32],
        nk: usize,
        m: &mut [f32; NR],
        l: &mut [f32; NR],
        alpha: &mut [f32; NR],
        dst: &mut [u32],
        pairs: impl Fn(__m512, __m512) -> __m512i,
    ) {
        let sp = s.as_ptr();
        let dp = dst.as_mut_ptr() as *mut i32;
        let (mn, mut acc) = block_start(sp, nk, m, l, alpha);
        for j2 in 0..nk.div_ceil(2) {
            let j = 2 * j2;
            for h in 0..2 {
                // Summed in key order, as softmax_block does.
                let pe = exp512(_mm512_sub_ps(_mm512_loadu_ps(sp.add(j * NR + 16 * h)), mn[h]));
                acc[h] = _mm512_add_ps(acc[h], pe);
                let po = if j + 1 < nk {
                    let po = exp512(_mm512_sub_ps(_mm512_loadu_ps(sp.add((j + 1) * NR + 16 * h)), mn[h]));
                    acc[h] = _mm512_add_ps(acc[h], po);
                    po
                } else {
                    _mm512_setzero_ps()
                };
                _mm512_storeu_si512(dp.add(j2 * NR + 16 * h) as *mut __m512i, pairs(pe, po));
            }
        }
        for h in 0..2 {
            _mm512_storeu_ps(l.as_mut_ptr().add(16 * h), acc[h]);
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,fma")]
    pub unsafe fn softmax_block_pairs(s: &[f32], nk: usize, m: &mut [f32; NR], l: &mut [f32; NR], alpha: &mut [f32; NR], dst: &mut [u32]) {
        softmax_pairs_with(s, nk, m, l, alpha, dst, |pe, po| bf16_pairs(pe, po));
    }

    /// [`softmax_block_pairs`] rounding with `vcvtne2ps2bf16` (one instruction
    /// for two vectors, then one word shuffle into pairs). The same bits for
    /// every finite score: the exponentials are never subnormal (the exponent
    /// is clamped at −87.3, above the smallest normal), where the instruction
    /// would flush; only a NaN keeps its own payload instead of 0x7fc0.
    #[target_feature(enable = "avx512f,avx512bw,avx512bf16,fma")]
    pub unsafe fn softmax_block_pairs_bf16(
        s: &[f32],
        nk: usize,
        m: &mut [f32; NR],
        l: &mut [f32; NR],
        alpha: &mut [f32; NR],
        dst: &mut [u32],
    ) {
        // Words 0..16 of the conversion are the even key's, 16..32 the odd key's.
        let idx = _mm512_set_epi16(
            31, 15, 30, 14, 29, 13, 28, 12, 27, 11, 26, 10, 25, 9, 24, 8, 23, 7, 22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0,
        );
        softmax_pairs_with(s, nk, m, l, alpha, dst, |pe, po| {
            _mm512_permutexvar_epi16(idx, std::mem::transmute::<__m512bh, __m512i>(_mm512_cvtne2ps_pbh(po, pe)))
        });
    }

    #[target_feature(enable = "avx512f,avx512bw,fma")]
    pub unsafe fn scale_columns(o: &mut [f32], alpha: &[f32; NR]) {
        let a0 = _mm512_loadu_ps(alpha.as_ptr());
        let a1 = _mm512_loadu_ps(alpha.as_ptr().add(16));
        for row in o.chunks_exact_mut(NR) {
            let p = row.as_mut_ptr();
            _mm512_storeu_ps(p, _mm512_mul_ps(_mm512_loadu_ps(p), a0));
            _mm512_storeu_ps(p.add(16), _mm512_mul_ps(_mm512_loadu_ps(p.add(16)), a1));
        }
    }
}

/// The AVX2 versions of the `x86` module: the same operations in the same
/// order, on four 8-lane vectors per row of `NR` queries.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::NR;
    use crate::gemm::avx2::bf16_pairs;
    use crate::vecmath::avx2::exp256;
    use std::arch::x86_64::*;

    /// Vectors per row of `NR` queries.
    const V: usize = NR / 8;

    /// As `x86::block_start`.
    #[inline(always)]
    unsafe fn block_start(
        sp: *const f32,
        nk: usize,
        m: &mut [f32; NR],
        l: &[f32; NR],
        alpha: &mut [f32; NR],
    ) -> ([__m256; V], [__m256; V]) {
        let mo: [__m256; V] = std::array::from_fn(|h| _mm256_loadu_ps(m.as_ptr().add(8 * h)));
        let mut mn = mo;
        for j in 0..nk {
            for h in 0..V {
                mn[h] = _mm256_max_ps(mn[h], _mm256_loadu_ps(sp.add(j * NR + 8 * h)));
            }
        }
        let mut acc = [_mm256_setzero_ps(); V];
        for h in 0..V {
            let a = exp256(_mm256_sub_ps(mo[h], mn[h]));
            _mm256_storeu_ps(alpha.as_mut_ptr().add(8 * h), a);
            acc[h] = _mm256_mul_ps(_mm256_loadu_ps(l.as_ptr().add(8 * h)), a);
            _mm256_storeu_ps(m.as_mut_ptr().add(8 * h), mn[h]);
        }
        (mn, acc)
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn softmax_block(s: &mut [f32], nk: usize, m: &mut [f32; NR], l: &mut [f32; NR], alpha: &mut [f32; NR]) {
        let sp = s.as_mut_ptr();
        let (mn, mut acc) = block_start(sp, nk, m, l, alpha);
        for j in 0..nk {
            for h in 0..V {
                let p = exp256(_mm256_sub_ps(_mm256_loadu_ps(sp.add(j * NR + 8 * h)), mn[h]));
                _mm256_storeu_ps(sp.add(j * NR + 8 * h), p);
                acc[h] = _mm256_add_ps(acc[h], p);
            }
        }
        for h in 0..V {
            _mm256_storeu_ps(l.as_mut_ptr().add(8 * h), acc[h]);
        }
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn softmax_block_pairs(s: &[f32], nk: usize, m: &mut [f32; NR], l: &mut [f32; NR], alpha: &mut [f32; NR], dst: &mut [u32]) {
        let sp = s.as_ptr();
        let dp = dst.as_mut_ptr();
        let (mn, mut acc) = block_start(sp, nk, m, l, alpha);
        for j2 in 0..nk.div_ceil(2) {
            let j = 2 * j2;
            for h in 0..V {
                // Summed in key order, as softmax_block does.
                let pe = exp256(_mm256_sub_ps(_mm256_loadu_ps(sp.add(j * NR + 8 * h)), mn[h]));
                acc[h] = _mm256_add_ps(acc[h], pe);
                let po = if j + 1 < nk {
                    let po = exp256(_mm256_sub_ps(_mm256_loadu_ps(sp.add((j + 1) * NR + 8 * h)), mn[h]));
                    acc[h] = _mm256_add_ps(acc[h], po);
                    po
                } else {
                    _mm256_setzero_ps()
                };
                _mm256_storeu_si256(dp.add(j2 * NR + 8 * h) as *mut __m256i, bf16_pairs(pe, po));
            }
        }
        for h in 0..V {
            _mm256_storeu_ps(l.as_mut_ptr().add(8 * h), acc[h]);
        }
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn scale_columns(o: &mut [f32], alpha: &[f32; NR]) {
        let a: [__m256; V] = std::array::from_fn(|h| _mm256_loadu_ps(alpha.as_ptr().add(8 * h)));
        for row in o.chunks_exact_mut(NR) {
            let p = row.as_mut_ptr();
            for h in 0..V {
                _mm256_storeu_ps(p.add(8 * h), _mm256_mul_ps(_mm256_loadu_ps(p.add(8 * h)), a[h]));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::test_rng::Lcg;

    /// Fused qkv layout (`[L, 3, H, d]`) for self-attention, or separate q and kv buffers.
    fn run_case(isa: Isa, precision: AttnPrecision, h: usize, d: usize, segs: &[Segment], fused: bool, seed: u64) {
        let mut r = Lcg(seed);
        let nq = segs.iter().map(|s| s.q.end).max().unwrap_or(0);
        let nk = segs.iter().map(|s| s.kv.end).max().unwrap_or(0);
        let c = h * d;
        // Scores of a few units so the softmax is neither flat nor one-hot.
        let (q, k, v, ql, kl, vl);
        if fused {
            let n = nq.max(nk);
            let qkv = r.vec(n * 3 * c, 2.0);
            q = qkv.clone();
            k = qkv.clone();
            v = qkv;
            ql = HeadLayout::new(3 * c, 0);
            kl = HeadLayout::new(3 * c, c);
            vl = HeadLayout::new(3 * c, 2 * c);
        } else {
            q = r.vec(nq * c, 2.0);
            let kv = r.vec(nk * 2 * c + 5, 2.0);
            k = kv.clone();
            v = kv;
            ql = HeadLayout::new(c, 0);
            kl = HeadLayout::new(2 * c, 0);
            vl = HeadLayout::new(2 * c, c);
        }
        let spec = AttnSpec {
            heads: h,
            head_dim: d,
            scale: 1.0 / (d as f32).sqrt(),
            q: ql,
            k: kl,
            v: vl,
            out: HeadLayout::new(c + 1, 1),
            precision,
        };
        let mut got = vec![f32::NAN; nq * (c + 1)];
        let mut want = got.clone();
        flash_attention(isa, &spec, &q, &k, &v, segs, &mut got).unwrap();
        attention_reference(&spec, &q, &k, &v, segs, &mut want);
        // bf16: P is rounded after the running max differs from the final one,
        // so allow bf16-level relative error on top of f32 rounding.
        let tol = if precision == AttnPrecision::Bf16 { 2e-2 } else { 2e-5 };
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            if w.is_nan() {
                assert!(g.is_nan(), "{isa:?}: untouched element {i} was written");
                continue;
            }
            assert!((g - w).abs() <= tol * w.abs().max(0.5), "{isa:?} {precision:?} h{h} d{d}: out[{i}] = {g}, want {w}");
        }
    }

    #[test]
    fn matches_reference_on_awkward_lengths_every_isa() {
        let cases: Vec<(usize, usize, Vec<Segment>, bool)> = vec![
            (1, 1, vec![Segment { q: 0..1, kv: 0..1 }], true),
            (2, 8, vec![Segment { q: 0..37, kv: 0..53 }], false),
            (3, 64, vec![Segment { q: 0..33, kv: 0..33 }, Segment { q: 33..40, kv: 33..40 }], true),
            (2, 17, vec![Segment { q: 0..300, kv: 0..250 }], false),
            // Keys spanning several blocks, odd count, queries spanning chunks.
            (1, 64, vec![Segment { q: 0..270, kv: 0..(2 * BC + 15) }], true),
            // Empty kv gives zeros; uncovered rows 5..9 stay untouched.
            (2, 4, vec![Segment { q: 0..5, kv: 0..0 }, Segment { q: 9..12, kv: 2..3 }], false),
            // More heads than one group holds (heads are packed a group at a time).
            (37, 8, vec![Segment { q: 0..40, kv: 0..70 }], false),
            (9, 16, vec![Segment { q: 0..20, kv: 0..20 }, Segment { q: 20..45, kv: 20..61 }], true),
        ];
        for isa in Isa::all_supported() {
            for precision in [AttnPrecision::F32, AttnPrecision::Bf16] {
                for (i, (h, d, segs, fused)) in cases.iter().enumerate() {
                    run_case(isa, precision, *h, *d, segs, *fused, i as u64 + 7);
                }
            }
        }
    }

    #[test]
    fn fused_softmax_pairs_equal_softmax_then_pairs() {
        let mut r = Lcg(11);
        for isa in Isa::all_supported() {
            for nk in [1, 2, 13, BC - 1, BC] {
                let s0 = r.vec(nk * NR, 8.0);
                let (m0, l0): (Vec<f32>, Vec<f32>) = (r.vec(NR, 4.0), r.vec(NR, 1.0).iter().map(|v| v.abs() + 0.5).collect());
                let init = |v: &[f32]| -> [f32; NR] { v.try_into().unwrap() };
                let (mut m1, mut l1, mut a1) = (init(&m0), init(&l0), [0f32; NR]);
                let mut s1 = s0.clone();
                let mut want = vec![0u32; nk.div_ceil(2) * NR];
                softmax_block(isa, &mut s1, nk, &mut m1, &mut l1, &mut a1);
                to_bf16_pairs(&s1, nk, &mut want);
                let (mut m2, mut l2, mut a2) = (init(&m0), init(&l0), [0f32; NR]);
                let mut got = vec![u32::MAX; want.len()];
                softmax_block_pairs(isa, &mut s0.clone(), nk, &mut m2, &mut l2, &mut a2, &mut got);
                assert_eq!((m1, l1, a1), (m2, l2, a2), "{isa:?} nk {nk}: running statistics differ");
                assert_eq!(want, got, "{isa:?} nk {nk}: bf16 pairs differ");
            }
        }
    }

    #[test]
    fn thread_count_does_not_change_results() {
        let mut r = Lcg(5);
        let (h, d, n) = (4, 64, 600);
        let qkv = r.vec(n * 3 * h * d, 2.0);
        let spec = AttnSpec {
            heads: h,
            head_dim: d,
            scale: 0.125,
            q: HeadLayout::new(3 * h * d, 0),
            k: HeadLayout::new(3 * h * d, h * d),
            v: HeadLayout::new(3 * h * d, 2 * h * d),
            out: HeadLayout::new(h * d, 0),
            precision: AttnPrecision::Bf16,
        };
        let segs = [Segment { q: 0..n, kv: 0..n }];
        for isa in Isa::all_supported() {
            let run = |t: usize| {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
                let mut o = vec![0f32; n * h * d];
                pool.install(|| flash_attention(isa, &spec, &qkv, &qkv, &qkv, &segs, &mut o).unwrap());
                o
            };
            assert_eq!(run(1), run(3));
        }
    }

    #[test]
    fn bad_inputs_are_errors() {
        let spec = AttnSpec {
            heads: 2,
            head_dim: 4,
            scale: 0.5,
            q: HeadLayout::new(8, 0),
            k: HeadLayout::new(8, 0),
            v: HeadLayout::new(8, 0),
            out: HeadLayout::new(8, 0),
            precision: AttnPrecision::F32,
        };
        let x = vec![0f32; 16];
        let mut o = vec![0f32; 16];
        let seg = |q: Range<usize>, kv: Range<usize>| Segment { q, kv };
        assert!(flash_attention(Isa::Portable, &spec, &x, &x, &x, &[seg(0..3, 0..2)], &mut o).is_err());
        assert!(flash_attention(Isa::Portable, &spec, &x, &x, &x, &[seg(0..2, 0..2), seg(1..2, 0..1)], &mut o).is_err());
        assert!(flash_attention(Isa::Portable, &spec, &x, &x, &x, &[seg(0..2, 0..2)], &mut o[..15]).is_err());
        assert!(flash_attention(Isa::Portable, &spec, &x, &x, &x, &[seg(0..2, 0..2)], &mut o).is_ok());
    }
}
