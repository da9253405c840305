//! Matrix multiply `C = A·B (+ bias, activation)` with `B` packed once.
//!
//! `A` (`[M, K]`, activations) is f32 and packed per call into `MR`-row
//! tiles; `B` (`[K, N]`, weights) is packed at load time into `NR`-column
//! panels in its storage format ([`WeightFormat`]): f32, bf16 (k in pairs,
//! the layout `vdpbf16ps` reads) or f16. Results are always f32.
//!
//! Blocking follows the usual GotoBLAS/BLIS structure: a task owns `MC`
//! rows of `C` and a range of panels; for each `KC` slice of `K` it packs
//! its `A` rows once, then takes the panels a block of `NC` at a time (kept
//! in L2) and passes each `A` tile (in L1) over every panel of the block,
//! so `C` is walked along its rows. Each element of `C` is computed by
//! exactly one task with a fixed summation order (k in order, split only at
//! multiples of `KC`), so results do not depend on the thread count, `MC`
//! or `NC`.
//!
//! Kernels, chosen by [`Isa`] at run time:
//! - f32 weights: AVX-512 FMA `14×32` tile; AVX2 FMA covers the same tile
//!   in sub-tiles of up to `6×16` (its 16 registers hold no more); portable;
//! - bf16 weights: `vdpbf16ps` on bf16 pairs of A and B (A rounded to bf16,
//!   f32 accumulation) with AVX512-BF16; otherwise B is widened to f32 in
//!   registers and A rounded to bf16 first, so every ISA computes the same
//!   products;
//! - f16 weights: widened with `vcvtph2ps` (AVX-512, F16C) / in software; A stays f32.

use crate::buf::{AlignedBuf, SendPtr};
use crate::isa::{Isa, Simd};
use crate::vecmath::{self, Activation};
use rayon::prelude::*;

/// Rows of the register tile.
pub const MR: usize = 14;
/// B panels per block of [`Blocking::for_caches`] (`nc`): 4 panels of `kc`
/// k values are 128–256 KiB at the default `kc`, so the two threads of a
/// core (the 2-core Xeon's vCPUs share one) keep theirs in L2 together.
/// Measured there at M 2184 (stage 2's tokens) and K, N 1024–4096 against
/// the old order (each panel past every A tile, `nc` 0): AVX-512 f32 10–20 %,
/// bf16 widened about 5 %, AVX2 f32 a few percent faster by CPU time.
pub const PANELS_PER_BLOCK: usize = 4;
/// Columns of the register tile (two 16-lane vectors).
pub const NR: usize = 32;
/// Cache blocking of [`gemm()`]: rows of `C` per task (`mc`, rounded up to a
/// multiple of `MR`) and k values per slice (`kc`, even).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Blocking {
    /// Rows of `A` per block (a multiple of `MR`).
    pub mc: usize,
    /// k values per slice (even).
    pub kc: usize,
    /// B panels per block (0: the old order, each panel swept past every A
    /// tile of the row block). Each A tile (in L1) meets every panel of a
    /// block (in L2) in turn, and `C` is walked along its rows.
    pub nc: usize,
}

impl Blocking {
    /// Blocking for this CPU's caches ([`cache_sizes`]).
    pub fn for_format(format: WeightFormat) -> Self {
        Self::for_caches(format, cache_sizes())
    }

    /// Blocking for the kernels of `isa` on this CPU's caches ([`Self::for_isa_caches`]).
    pub fn for_isa(isa: Isa, format: WeightFormat) -> Self {
        Self::for_isa_caches(isa, format, cache_sizes())
    }

    /// [`Self::for_caches`], except that AVX2 takes f32 k slices twice as
    /// long: its kernel reads a panel in two 16-column halves, each with the
    /// A tile again, so the panel leaves L1 at any `kc`, and longer slices
    /// halve the passes over `C` (measured a few percent faster).
    pub fn for_isa_caches(isa: Isa, format: WeightFormat, caches: (usize, usize)) -> Self {
        let b = Self::for_caches(format, caches);
        match (isa.simd(), format) {
            (Simd::Avx2, WeightFormat::F32) => Blocking { kc: (2 * b.kc).min(1024), ..b },
            _ => b,
        }
    }

    /// Blocking for an L1d / L2 of `(l1, l2)` bytes: `KC` so that a `KC×NR`
    /// micro-panel of B would fill L1 (the rule tuned on Zen 4: 32 KiB gives
    /// kc 256 in f32, 512 in bf16/f16; `KC` also fixes where the k sums are
    /// split, so it is kept to keep every result's bits), `MC` rows of that
    /// `KC` a third of L2 at B's element size (1 MiB gives 336 rows), so the
    /// larger caches of other cores (e.g. 48 KiB / 2 MiB) get proportionally
    /// larger blocks, and [`PANELS_PER_BLOCK`] panels per block.
    pub fn for_caches(format: WeightFormat, (l1, l2): (usize, usize)) -> Self {
        let bytes = format.bytes_per_element();
        let kc = (l1 / (NR * bytes)).clamp(64, 1024) & !1;
        let tiles = (l2 / 3 / (kc * bytes) / MR).clamp(4, 64);
        Blocking { mc: MR * tiles, kc, nc: PANELS_PER_BLOCK }
    }
}

/// L1 data and L2 cache sizes (bytes) of cpu0 from Linux sysfs, read once;
/// Zen 4's 32 KiB / 1 MiB where unavailable.
pub fn cache_sizes() -> (usize, usize) {
    static SIZES: std::sync::OnceLock<(usize, usize)> = std::sync::OnceLock::new();
    *SIZES.get_or_init(|| {
        let (mut l1, mut l2) = (32 << 10, 1 << 20);
        for i in 0..8 {
            let dir = format!("/sys/devices/system/cpu/cpu0/cache/index{i}");
            let read = |f: &str| std::fs::read_to_string(format!("{dir}/{f}")).ok().map(|s| s.trim().to_string());
            let (Some(level), Some(kind), Some(size)) = (read("level"), read("type"), read("size")) else { continue };
            let Some(bytes) = parse_cache_size(&size) else { continue };
            match (level.as_str(), kind.as_str()) {
                ("1", "Data") => l1 = bytes,
                ("2", "Unified") => l2 = bytes,
                _ => {}
            }
        }
        (l1, l2)
    })
}

/// sysfs cache sizes: `32K`, `1024K`, `2M`, or bytes.
fn parse_cache_size(s: &str) -> Option<usize> {
    let (num, mult) = match s.as_bytes().last()? {
        b'K' => (&s[..s.len() - 1], 1 << 10),
        b'M' => (&s[..s.len() - 1], 1 << 20),
        _ => (s, 1),
    };
    num.parse::<usize>().ok().filter(|&n| n > 0).map(|n| n * mult)
}

/// Storage format of a packed `B` operand.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum WeightFormat {
    /// 32-bit floats.
    F32,
    /// bfloat16 (8-bit exponent, 7-bit mantissa).
    Bf16,
    /// IEEE half precision.
    F16,
}

impl WeightFormat {
    /// Lower-case name (`"f32"`, `"bf16"`, `"f16"`).
    pub fn name(self) -> &'static str {
        match self {
            WeightFormat::F32 => "f32",
            WeightFormat::Bf16 => "bf16",
            WeightFormat::F16 => "f16",
        }
    }
    /// Bytes per stored element.
    pub fn bytes_per_element(self) -> usize {
        match self {
            WeightFormat::F32 => 4,
            _ => 2,
        }
    }
    /// K rounded up to the format's step (bf16 packs k in pairs).
    pub fn k_padded(self, k: usize) -> usize {
        match self {
            WeightFormat::Bf16 => k.div_ceil(2) * 2,
            _ => k,
        }
    }
}

/// Round to the nearest bf16 (ties to even), as `vcvtneps2bf16`; NaN stays NaN.
#[inline(always)]
pub fn f32_to_bf16(x: f32) -> u16 {
    let b = x.to_bits();
    let r = (b.wrapping_add(0x7fff + ((b >> 16) & 1)) >> 16) as u16;
    if x.is_nan() {
        0x7fc0
    } else {
        r
    }
}
#[inline(always)]
/// Widens bf16 bits to f32 (exact).
pub fn bf16_to_f32(b: u16) -> f32 {
    f32::from_bits((b as u32) << 16)
}
/// `x` rounded to bf16 precision, as f32.
#[inline(always)]
pub fn round_bf16(x: f32) -> f32 {
    bf16_to_f32(f32_to_bf16(x))
}

/// [`round_bf16`] on f32 bits, without branches (so loops of it vectorise).
#[inline(always)]
fn round_bf16_bits(b: u32) -> u32 {
    let r = b.wrapping_add(0x7fff + ((b >> 16) & 1)) & 0xffff_0000;
    let nan = (b & 0x7fff_ffff) > 0x7f80_0000;
    if nan {
        0x7fc0_0000
    } else {
        r
    }
}
/// Whether the AVX-512 conversions below may run (a CPU check std caches).
#[inline]
fn avx512_bw() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512bw")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}
/// Whether the AVX2 conversions below may run (a CPU check std caches).
#[inline]
fn avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Floats converted per pass of [`bf16_pairs_down_column`] (its stack buffer).
const PAIRS_CHUNK: usize = 128;

/// `out[k] = bf16(x[2k]·scale) | bf16(x[2k+1]·scale) << 16`, rounded as
/// [`f32_to_bf16`] (a zero high half past an odd end); 16 floats at a time
/// with AVX-512 or AVX2 where the CPU has it, bit for bit the same.
pub(crate) fn bf16_pairs_of_row(x: &[f32], scale: f32, out: &mut [u32]) {
    let out = &mut out[..x.len().div_ceil(2)];
    #[allow(unused_mut)]
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if avx512_bw() {
        // SAFETY: AVX-512 F/BW checked; `out` holds x.len()/2 words.
        done = unsafe { x86::bf16_pairs_of_row(x, scale, out) };
    } else if avx2() {
        // SAFETY: AVX2 checked; as above.
        done = unsafe { avx2::bf16_pairs_of_row(x, scale, out) };
    }
    for k in done / 2..out.len() {
        let lo = f32_to_bf16(x[2 * k] * scale) as u32;
        let hi = if 2 * k + 1 < x.len() { f32_to_bf16(x[2 * k + 1] * scale) as u32 } else { 0 };
        out[k] = lo | (hi << 16);
    }
}

/// Row `x` (times `scale`) as bf16 pairs down column `col` of a word matrix
/// with `stride` words per row: `dst[k·stride + col]` = pair `k` of
/// [`bf16_pairs_of_row`]. The layout of packed A tiles (`stride` = MR) and
/// of attention's Qᵀ panels (`stride` = NR).
pub(crate) fn bf16_pairs_down_column(x: &[f32], scale: f32, dst: &mut [u32], stride: usize, col: usize) {
    let mut words = [0u32; PAIRS_CHUNK / 2];
    for (c, part) in x.chunks(PAIRS_CHUNK).enumerate() {
        let w = &mut words[..part.len().div_ceil(2)];
        bf16_pairs_of_row(part, scale, w);
        for (k, &v) in w.iter().enumerate() {
            dst[(c * PAIRS_CHUNK / 2 + k) * stride + col] = v;
        }
    }
}

#[inline(always)]
/// Rounds an f32 to f16 bits (round to nearest even).
pub fn f32_to_f16(x: f32) -> u16 {
    half::f16::from_f32(x).to_bits()
}
#[inline(always)]
/// Widens f16 bits to f32 (exact).
pub fn f16_to_f32(b: u16) -> f32 {
    half::f16::from_bits(b).to_f32()
}

#[derive(Clone, Debug)]
enum Store {
    F32(AlignedBuf<f32>),
    U16(AlignedBuf<u16>),
}

/// A `[K, N]` right operand packed into `NR`-column panels (zero padded to a
/// whole panel and, for bf16, to even `K`). Panel `p` holds columns
/// `p·NR .. p·NR+NR`; inside it, element `(k, j)` is at `k·NR + j` (f32, f16)
/// or `(k/2)·2NR + 2j + k%2` (bf16 pairs).
#[derive(Clone, Debug)]
pub struct PackedMatrix {
    k: usize,
    n: usize,
    format: WeightFormat,
    store: Store,
}

impl PackedMatrix {
    /// Pack `B[k][n] = get(k, n)`.
    pub fn pack_with(k: usize, n: usize, format: WeightFormat, get: impl Fn(usize, usize) -> f32 + Sync) -> Self {
        let kp = format.k_padded(k);
        let panels = n.div_ceil(NR);
        let stride = kp * NR;
        let fill = |p: usize, panel: &mut dyn FnMut(usize, f32)| {
            for kk in 0..k {
                for j in 0..NR.min(n - p * NR) {
                    let idx = match format {
                        WeightFormat::Bf16 => (kk / 2) * 2 * NR + 2 * j + kk % 2,
                        _ => kk * NR + j,
                    };
                    panel(idx, get(kk, p * NR + j));
                }
            }
        };
        let store = match format {
            WeightFormat::F32 => {
                let mut buf = AlignedBuf::<f32>::zeroed_long_lived(panels * stride);
                buf.par_chunks_mut(stride.max(1)).enumerate().for_each(|(p, dst)| fill(p, &mut |i, v| dst[i] = v));
                Store::F32(buf)
            }
            WeightFormat::Bf16 | WeightFormat::F16 => {
                let conv = if format == WeightFormat::Bf16 { f32_to_bf16 } else { f32_to_f16 };
                let mut buf = AlignedBuf::<u16>::zeroed_long_lived(panels * stride);
                buf.par_chunks_mut(stride.max(1)).enumerate().for_each(|(p, dst)| fill(p, &mut |i, v| dst[i] = conv(v)));
                Store::U16(buf)
            }
        };
        Self { k, n, format, store }
    }

    /// Pack `count` matrices of one `[K, N]` shape together, for operands
    /// whose values are cheapest to produce all at once (the 64 Winograd taps
    /// of a convolution weight). `fill(k, p, row)` writes row `k` of panel
    /// `p` of every matrix: `B_i[k][p·NR + j]` at `row[i·NR + j]` (`row` is
    /// zeroed before each call; columns at or past `N` are discarded).
    pub fn pack_many(count: usize, k: usize, n: usize, format: WeightFormat, fill: impl Fn(usize, usize, &mut [f32]) + Sync) -> Vec<Self> {
        let kp = format.k_padded(k);
        let panels = n.div_ceil(NR);
        let stride = kp * NR;
        let len = panels * stride;
        let mut f32s: Vec<AlignedBuf<f32>> = Vec::new();
        let mut u16s: Vec<AlignedBuf<u16>> = Vec::new();
        // Destination addresses as integers so the panel jobs can share them.
        let addrs: Vec<usize> = match format {
            WeightFormat::F32 => {
                f32s = (0..count).map(|_| AlignedBuf::zeroed(len)).collect();
                f32s.iter_mut().map(|b| b.as_mut_ptr() as usize).collect()
            }
            _ => {
                u16s = (0..count).map(|_| AlignedBuf::zeroed(len)).collect();
                u16s.iter_mut().map(|b| b.as_mut_ptr() as usize).collect()
            }
        };
        (0..panels).into_par_iter().for_each_init(
            || (vec![0f32; count * NR], vec![0f32; count * NR]),
            |(r0, r1), p| {
                let cols = NR.min(n - p * NR);
                let row = |kk: usize, r: &mut Vec<f32>| {
                    r.fill(0.0);
                    if kk < k {
                        fill(kk, p, r);
                        r.chunks_exact_mut(NR).for_each(|c| c[cols..].fill(0.0));
                    }
                };
                let base = p * stride;
                match format {
                    WeightFormat::F32 => {
                        for kk in 0..k {
                            row(kk, r0);
                            for (i, &a) in addrs.iter().enumerate() {
                                // SAFETY: panel p of each buffer (len elements) is written by this job only.
                                let dst = unsafe { std::slice::from_raw_parts_mut((a as *mut f32).add(base + kk * NR), NR) };
                                dst.copy_from_slice(&r0[i * NR..][..NR]);
                            }
                        }
                    }
                    WeightFormat::Bf16 => {
                        for k2 in 0..kp / 2 {
                            row(2 * k2, r0);
                            row(2 * k2 + 1, r1);
                            for (i, &a) in addrs.iter().enumerate() {
                                // SAFETY: as above.
                                let dst = unsafe { std::slice::from_raw_parts_mut((a as *mut u16).add(base + k2 * 2 * NR), 2 * NR) };
                                let (lo, hi) = (&r0[i * NR..][..NR], &r1[i * NR..][..NR]);
                                for j in 0..NR {
                                    dst[2 * j] = f32_to_bf16(lo[j]);
                                    dst[2 * j + 1] = f32_to_bf16(hi[j]);
                                }
                            }
                        }
                    }
                    WeightFormat::F16 => {
                        for kk in 0..k {
                            row(kk, r0);
                            for (i, &a) in addrs.iter().enumerate() {
                                // SAFETY: as above.
                                let dst = unsafe { std::slice::from_raw_parts_mut((a as *mut u16).add(base + kk * NR), NR) };
                                for (d, &v) in dst.iter_mut().zip(&r0[i * NR..][..NR]) {
                                    *d = f32_to_f16(v);
                                }
                            }
                        }
                    }
                }
            },
        );
        let stores: Vec<Store> = match format {
            WeightFormat::F32 => f32s.into_iter().map(Store::F32).collect(),
            _ => u16s.into_iter().map(Store::U16).collect(),
        };
        stores.into_iter().map(|store| Self { k, n, format, store }).collect()
    }

    /// Pack a PyTorch `Linear` weight `W` (`[N, K]` row-major, `y = x·Wᵀ`).
    pub fn from_linear_weight(w: &[f32], n: usize, k: usize, format: WeightFormat) -> Result<Self, String> {
        if w.len() != n * k {
            return Err(format!("linear weight has {} values, expected {n}×{k}", w.len()));
        }
        Ok(Self::pack_with(k, n, format, |kk, nn| w[nn * k + kk]))
    }

    /// Pack a row-major `[K, N]` matrix.
    pub fn from_kn(b: &[f32], k: usize, n: usize, format: WeightFormat) -> Result<Self, String> {
        if b.len() != n * k {
            return Err(format!("matrix has {} values, expected {k}×{n}", b.len()));
        }
        Ok(Self::pack_with(k, n, format, |kk, nn| b[kk * n + nn]))
    }

    /// Rows of the packed matrix (the GEMM's k).
    pub fn k(&self) -> usize {
        self.k
    }
    /// Columns of the packed matrix (the GEMM's n).
    pub fn n(&self) -> usize {
        self.n
    }
    /// Storage format of the packed values.
    pub fn format(&self) -> WeightFormat {
        self.format
    }
    /// Bytes held by the packed values.
    pub fn bytes(&self) -> usize {
        match &self.store {
            Store::F32(b) => b.len() * 4,
            Store::U16(b) => b.len() * 2,
        }
    }

    /// The stored value of `B[k][n]` (after rounding to the format).
    pub fn get(&self, k: usize, n: usize) -> f32 {
        let (p, j) = (n / NR, n % NR);
        let base = p * self.format.k_padded(self.k) * NR;
        match (&self.store, self.format) {
            (Store::F32(b), _) => b[base + k * NR + j],
            (Store::U16(b), WeightFormat::Bf16) => bf16_to_f32(b[base + (k / 2) * 2 * NR + 2 * j + k % 2]),
            (Store::U16(b), _) => f16_to_f32(b[base + k * NR + j]),
        }
    }

    /// Pointer to panel `p` at k offset `k0` (`k0` even for bf16).
    pub(crate) fn panel_ptr(&self, p: usize, k0: usize) -> *const u8 {
        let off = p * self.format.k_padded(self.k) * NR + k0 * NR;
        match &self.store {
            Store::F32(b) => b[off..].as_ptr() as *const u8,
            Store::U16(b) => b[off..].as_ptr() as *const u8,
        }
    }
}

/// How a kernel wants its `A` tile.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum AFormat {
    /// f32 `[k][MR]`.
    F32,
    /// f32 `[k][MR]` with values rounded to bf16 (k padded to even).
    F32Bf16,
    /// bf16 pairs `[k/2][MR]` as u32 (low half = even k).
    Bf16Pairs,
}

pub(crate) fn a_format(isa: Isa, format: WeightFormat) -> AFormat {
    match format {
        WeightFormat::F32 | WeightFormat::F16 => AFormat::F32,
        WeightFormat::Bf16 if isa == Isa::Avx512Bf16 => AFormat::Bf16Pairs,
        WeightFormat::Bf16 => AFormat::F32Bf16,
    }
}

/// u32 words of one packed `A` tile of `kc` k values.
pub(crate) fn a_tile_words(afmt: AFormat, kc: usize) -> usize {
    a_tile_words_mr(afmt, kc, MR)
}

/// [`a_tile_words`] for a tile of `mr` rows.
pub(crate) fn a_tile_words_mr(afmt: AFormat, kc: usize, mr: usize) -> usize {
    match afmt {
        AFormat::F32 => kc * mr,
        AFormat::F32Bf16 => kc.div_ceil(2) * 2 * mr,
        AFormat::Bf16Pairs => kc.div_ceil(2) * mr,
    }
}

/// Rows of the `A` tiles [`gemm()`] packs for the kernels of `isa` on B in
/// `format`: `MR`, except 12 for AVX2 on f32 and bf16, whose row groups of
/// up to six split 12 rows evenly and `MR` only as 5, 5, 4 (a 4-row group
/// has too few independent FMA chains). The f16 kernel runs faster in 5-row
/// groups (its conversions need the registers), so it keeps `MR`, as do
/// attention and Winograd for every ISA.
pub(crate) fn gemm_tile_rows(isa: Isa, format: WeightFormat) -> usize {
    match (isa.simd(), format) {
        (Simd::Avx2, WeightFormat::F32 | WeightFormat::Bf16) => 12,
        _ => MR,
    }
}

/// Pack an `A` tile given by k: `col(k)` returns the `rows` values of
/// column k (contiguous over i), e.g. Vᵀ from row-major V.
#[inline]
pub(crate) fn pack_a_tile_cols<'a>(afmt: AFormat, dst: &mut [u32], rows: usize, kc: usize, col: impl Fn(usize) -> &'a [f32]) {
    let words = a_tile_words(afmt, kc);
    let dst = &mut dst[..words];
    if rows < MR || kc % 2 == 1 {
        dst.fill(0);
    }
    match afmt {
        AFormat::F32 => {
            for k in 0..kc {
                for (d, &v) in dst[k * MR..k * MR + rows].iter_mut().zip(&col(k)[..rows]) {
                    *d = v.to_bits();
                }
            }
        }
        AFormat::F32Bf16 => {
            for k in 0..kc {
                for (d, &v) in dst[k * MR..k * MR + rows].iter_mut().zip(&col(k)[..rows]) {
                    *d = round_bf16(v).to_bits();
                }
            }
        }
        AFormat::Bf16Pairs => {
            #[cfg(target_arch = "x86_64")]
            if avx512_bw() {
                // SAFETY: AVX-512 F/BW checked; `dst` holds the tile's kc/2 rows of MR words.
                unsafe { x86::pack_pairs_cols(dst, rows, kc, col) };
                return;
            }
            for k2 in 0..kc / 2 {
                let (lo, hi) = (&col(2 * k2)[..rows], &col(2 * k2 + 1)[..rows]);
                for i in 0..rows {
                    dst[k2 * MR + i] = f32_to_bf16(lo[i]) as u32 | ((f32_to_bf16(hi[i]) as u32) << 16);
                }
            }
            if kc % 2 == 1 {
                let lo = &col(kc - 1)[..rows];
                for i in 0..rows {
                    dst[(kc / 2) * MR + i] = f32_to_bf16(lo[i]) as u32;
                }
            }
        }
    }
}

/// Pack an `A` tile from row-major f32 rows (`a[i·lda + k]`), the hot case.
#[inline]
pub(crate) fn pack_a_rows(afmt: AFormat, dst: &mut [u32], a: &[f32], lda: usize, rows: usize, kc: usize) {
    pack_a_rows_mr(afmt, dst, a, lda, rows, kc, MR)
}

/// [`pack_a_rows`] into a tile of `mr ≥ rows` rows.
#[inline]
pub(crate) fn pack_a_rows_mr(afmt: AFormat, dst: &mut [u32], a: &[f32], lda: usize, rows: usize, kc: usize, mr: usize) {
    match afmt {
        AFormat::F32 => {
            if rows < mr {
                dst[..kc * mr].fill(0);
            }
            for i in 0..rows {
                let src = &a[i * lda..i * lda + kc];
                for (k, &v) in src.iter().enumerate() {
                    dst[k * mr + i] = v.to_bits();
                }
            }
        }
        AFormat::F32Bf16 => {
            let kp = kc.div_ceil(2) * 2;
            if rows < mr || kp != kc {
                dst[..kp * mr].fill(0);
            }
            for i in 0..rows {
                for (k, &v) in a[i * lda..i * lda + kc].iter().enumerate() {
                    dst[k * mr + i] = v.to_bits();
                }
            }
            // Rounded in a separate contiguous pass, which vectorises (the
            // transposing copy above cannot).
            for w in dst[..kp * mr].iter_mut() {
                *w = round_bf16_bits(*w);
            }
        }
        AFormat::Bf16Pairs => {
            if rows < mr {
                dst[..kc.div_ceil(2) * mr].fill(0);
            }
            for i in 0..rows {
                bf16_pairs_down_column(&a[i * lda..i * lda + kc], 1.0, dst, mr, i);
            }
        }
    }
}

/// One register tile: `C[rows, cols] (+)= A_tile · B_panel` over `kc` k values
/// (`kc` even for bf16 formats). `load`: add to the existing `C` values.
///
/// # Safety
/// `a` holds a packed tile of `kc` values in the format `a_format(isa, format)`,
/// `b` a panel slice of `kc` values, `c` is valid for `rows` rows of stride
/// `ldc` and `cols` columns, `rows ≤ MR`, `cols ≤ NR`, and `isa` is supported.
#[allow(clippy::too_many_arguments)]
#[inline]
pub(crate) unsafe fn microkernel(
    isa: Isa,
    format: WeightFormat,
    kc: usize,
    a: *const u32,
    b: *const u8,
    c: *mut f32,
    ldc: usize,
    rows: usize,
    cols: usize,
    load: bool,
) {
    #[cfg(target_arch = "x86_64")]
    match isa.simd() {
        Simd::Avx512 => {}
        Simd::Avx2 => return avx2::tile::<MR>(format, kc, a, b, c, ldc, rows, cols, load),
        Simd::Scalar => return portable_kernel(format, kc, a as *const f32, b, c, ldc, rows, cols, load),
    }
    #[cfg(target_arch = "x86_64")]
    {
        // A short tile (the last rows of M, or a head dim that is not a
        // multiple of MR) runs a kernel that computes only those rows: the
        // full one would spend MR rows of FMAs on it. Each row's sum is the
        // same either way.
        macro_rules! rows {
            ($r:expr) => {
                match (format, isa) {
                    (WeightFormat::F32, _) => x86::kern_f32::<$r>(kc, a as *const f32, b as *const f32, c, ldc, rows, cols, load),
                    (WeightFormat::F16, _) => x86::kern_f16::<$r>(kc, a as *const f32, b as *const u16, c, ldc, rows, cols, load),
                    (WeightFormat::Bf16, Isa::Avx512Bf16) => x86::kern_bf16_dp::<$r>(kc / 2, a, b as *const u16, c, ldc, rows, cols, load),
                    (WeightFormat::Bf16, _) => {
                        x86::kern_bf16_widen::<$r>(kc / 2, a as *const f32, b as *const u16, c, ldc, rows, cols, load)
                    }
                }
            };
        }
        match rows {
            0..=4 => rows!(4),
            5..=8 => rows!(8),
            _ => rows!(MR),
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = isa;
        portable_kernel(format, kc, a as *const f32, b, c, ldc, rows, cols, load)
    }
}

/// [`microkernel`] on a tile of [`gemm_tile_rows`] rows (`rows` of them).
///
/// # Safety
/// As [`microkernel`], with `a` packed in tiles of `gemm_tile_rows(isa, format)` rows.
#[allow(clippy::too_many_arguments)]
#[inline]
unsafe fn microkernel_gemm(
    isa: Isa,
    format: WeightFormat,
    kc: usize,
    a: *const u32,
    b: *const u8,
    c: *mut f32,
    ldc: usize,
    rows: usize,
    cols: usize,
    load: bool,
) {
    #[cfg(target_arch = "x86_64")]
    if gemm_tile_rows(isa, format) == 12 {
        return avx2::tile::<12>(format, kc, a, b, c, ldc, rows, cols, load);
    }
    debug_assert_eq!(gemm_tile_rows(isa, format), MR);
    microkernel(isa, format, kc, a, b, c, ldc, rows, cols, load)
}

#[allow(clippy::too_many_arguments)]
unsafe fn portable_kernel(
    format: WeightFormat,
    kc: usize,
    a: *const f32,
    b: *const u8,
    c: *mut f32,
    ldc: usize,
    rows: usize,
    cols: usize,
    load: bool,
) {
    let mut acc = [[0f32; NR]; MR];
    let mut brow = [0f32; NR];
    for k in 0..kc {
        match format {
            WeightFormat::F32 => {
                let src = std::slice::from_raw_parts((b as *const f32).add(k * NR), NR);
                brow.copy_from_slice(src);
            }
            WeightFormat::F16 => {
                let src = std::slice::from_raw_parts((b as *const u16).add(k * NR), NR);
                for j in 0..NR {
                    brow[j] = f16_to_f32(src[j]);
                }
            }
            WeightFormat::Bf16 => {
                let src = std::slice::from_raw_parts((b as *const u16).add((k / 2) * 2 * NR), 2 * NR);
                for j in 0..NR {
                    brow[j] = bf16_to_f32(src[2 * j + k % 2]);
                }
            }
        }
        let arow = std::slice::from_raw_parts(a.add(k * MR), MR);
        for i in 0..MR {
            let ai = arow[i];
            for j in 0..NR {
                acc[i][j] += ai * brow[j];
            }
        }
    }
    for i in 0..rows {
        let dst = std::slice::from_raw_parts_mut(c.add(i * ldc), cols);
        for j in 0..cols {
            dst[j] = if load { dst[j] + acc[i][j] } else { acc[i][j] };
        }
    }
}

/// `C[m, n] = act(A[m, :] · B + bias)` for row-major `A` (`lda ≥ K`) and `C`
/// (`ldc ≥ N`). Runs on the rayon pool; the result does not depend on the
/// number of threads.
#[allow(clippy::too_many_arguments)]
pub fn gemm(
    isa: Isa,
    a: &[f32],
    m: usize,
    lda: usize,
    b: &PackedMatrix,
    bias: Option<&[f32]>,
    act: Activation,
    c: &mut [f32],
    ldc: usize,
) -> Result<(), String> {
    gemm_blocked(isa, a, m, lda, b, bias, act, c, ldc, Blocking::for_isa(isa, b.format))
}

/// [`gemm()`] with explicit cache blocking (for tuning).
#[allow(clippy::too_many_arguments)]
pub fn gemm_blocked(
    isa: Isa,
    a: &[f32],
    m: usize,
    lda: usize,
    b: &PackedMatrix,
    bias: Option<&[f32]>,
    act: Activation,
    c: &mut [f32],
    ldc: usize,
    blocking: Blocking,
) -> Result<(), String> {
    gemm_impl(isa, a, m, lda, b, bias, act, c, ldc, blocking, true)
}

/// [`gemm()`] on the calling thread only, for callers that already run
/// many small products in parallel (the same bits as [`gemm()`]).
#[allow(clippy::too_many_arguments)]
pub fn gemm_on_this_thread(
    isa: Isa,
    a: &[f32],
    m: usize,
    lda: usize,
    b: &PackedMatrix,
    bias: Option<&[f32]>,
    act: Activation,
    c: &mut [f32],
    ldc: usize,
) -> Result<(), String> {
    gemm_impl(isa, a, m, lda, b, bias, act, c, ldc, Blocking::for_isa(isa, b.format), false)
}

#[allow(clippy::too_many_arguments)]
fn gemm_impl(
    isa: Isa,
    a: &[f32],
    m: usize,
    lda: usize,
    b: &PackedMatrix,
    bias: Option<&[f32]>,
    act: Activation,
    c: &mut [f32],
    ldc: usize,
    blocking: Blocking,
    parallel: bool,
) -> Result<(), String> {
    let (k, n) = (b.k, b.n);
    let mr = gemm_tile_rows(isa, b.format);
    let mc = blocking.mc.div_ceil(mr).max(1) * mr;
    let kc_blk = (blocking.kc.div_ceil(2) * 2).max(2);
    if !isa.supported() {
        return Err(format!("gemm: instruction set {} is not supported by this CPU", isa.name()));
    }
    if m == 0 || n == 0 {
        return Ok(());
    }
    if lda < k || a.len() < (m - 1) * lda + k {
        return Err(format!("gemm: A has {} values, {m} rows of stride {lda} and {k} columns need {}", a.len(), (m - 1) * lda + k));
    }
    if ldc < n || c.len() < (m - 1) * ldc + n {
        return Err(format!("gemm: C has {} values, {m} rows of stride {ldc} and {n} columns need {}", c.len(), (m - 1) * ldc + n));
    }
    if let Some(bv) = bias {
        if bv.len() != n {
            return Err(format!("gemm: bias has {} values, expected {n}", bv.len()));
        }
    }
    let afmt = a_format(isa, b.format);
    let kc_max = kc_blk.min(b.format.k_padded(k).max(1));
    let panels = n.div_ceil(NR);
    // Row blocks of at most mc rows, their tiles shared out evenly (a short
    // last block would leave a thread idle at the end).
    let all_tiles = m.div_ceil(mr);
    let mblocks = all_tiles.div_ceil(mc / mr);
    // Enough tasks to balance the pool; split N only when M gives too few.
    let threads = if parallel { rayon::current_num_threads().max(1) } else { 1 };
    let ngroups = if parallel { (4 * threads).div_ceil(mblocks).clamp(1, panels) } else { 1 };
    let cptr = SendPtr(c.as_mut_ptr());
    let new_abuf = || AlignedBuf::<u32>::zeroed(all_tiles.div_ceil(mblocks) * a_tile_words_mr(afmt, kc_max, mr));
    let run = |abuf: &mut AlignedBuf<u32>, task: usize| {
        let (mb, ng) = (task / ngroups, task % ngroups);
        let m0 = mb * all_tiles / mblocks * mr;
        let rows = ((mb + 1) * all_tiles / mblocks * mr).min(m) - m0;
        let tiles = rows.div_ceil(mr);
        let (p0, p1) = (ng * panels / ngroups, (ng + 1) * panels / ngroups);
        if k == 0 {
            for i in 0..rows {
                // SAFETY: rows m0..m0+rows and columns of panels p0..p1 belong to this task.
                let row = unsafe {
                    let c0 = (p0 * NR).min(n);
                    let c1 = (p1 * NR).min(n);
                    std::slice::from_raw_parts_mut(cptr.get().add((m0 + i) * ldc + c0), c1 - c0)
                };
                row.fill(0.0);
                vecmath::bias_act(isa, row, bias.map(|bv| &bv[(p0 * NR).min(n)..]), act);
            }
            return;
        }
        let mut k0 = 0;
        while k0 < k {
            let kc = kc_max.min(k - k0);
            let kc_step = b.format.k_padded(kc);
            let tw = a_tile_words_mr(afmt, kc, mr);
            for t in 0..tiles {
                let r0 = t * mr;
                let tr = mr.min(rows - r0);
                pack_a_rows_mr(afmt, &mut abuf[t * tw..(t + 1) * tw], &a[(m0 + r0) * lda + k0..], lda, tr, kc, mr);
            }
            let last = k0 + kc >= k;
            let call = |t: usize, p: usize| {
                let r0 = t * mr;
                let tr = mr.min(rows - r0);
                let cols = NR.min(n - p * NR);
                // SAFETY: the tile lies inside this task's rows and panel range; the
                // packed operands hold kc_step values (zero padded).
                unsafe {
                    let cp = cptr.get().add((m0 + r0) * ldc + p * NR);
                    microkernel_gemm(isa, b.format, kc_step, abuf.as_ptr().add(t * tw), b.panel_ptr(p, k0), cp, ldc, tr, cols, k0 > 0);
                    if last && (bias.is_some() || act != Activation::None) {
                        for i in 0..tr {
                            let row = std::slice::from_raw_parts_mut(cp.add(i * ldc), cols);
                            vecmath::bias_act(isa, row, bias.map(|bv| &bv[p * NR..p * NR + cols]), act);
                        }
                    }
                }
            };
            if blocking.nc == 0 {
                for p in p0..p1 {
                    for t in 0..tiles {
                        call(t, p);
                    }
                }
            } else {
                // A tile stays in L1 while a block of `nc` B panels
                // (kept in L2) streams past it; C is walked along rows.
                let mut q0 = p0;
                while q0 < p1 {
                    let q1 = (q0 + blocking.nc).min(p1);
                    for t in 0..tiles {
                        for p in q0..q1 {
                            call(t, p);
                        }
                    }
                    q0 = q1;
                }
            }
            k0 += kc;
        }
    };
    if parallel {
        (0..mblocks * ngroups).into_par_iter().for_each_init(new_abuf, run);
    } else {
        let mut abuf = new_abuf();
        for task in 0..mblocks * ngroups {
            run(&mut abuf, task);
        }
    }
    Ok(())
}

/// Straightforward triple loop in f64 on the values as the kernels see them
/// (B as stored; A rounded to bf16 for bf16 weights), for tests.
pub fn gemm_reference(a: &[f32], m: usize, lda: usize, b: &PackedMatrix, bias: Option<&[f32]>, act: Activation) -> Vec<f32> {
    let (k, n) = (b.k, b.n);
    let mut out = vec![0f32; m * n];
    for i in 0..m {
        for j in 0..n {
            let mut s = 0f64;
            for kk in 0..k {
                let av = a[i * lda + kk];
                let av = if b.format == WeightFormat::Bf16 { round_bf16(av) } else { av };
                s += av as f64 * b.get(kk, j) as f64;
            }
            out[i * n + j] = s as f32;
        }
        vecmath::bias_act(Isa::Portable, &mut out[i * n..(i + 1) * n], bias, act);
    }
    out
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod x86 {
    use super::{MR, NR};
    use std::arch::x86_64::*;

    /// bf16 bits (round to nearest even, NaN → 0x7fc0, as [`super::f32_to_bf16`])
    /// in the low half of each lane.
    #[inline(always)]
    pub(crate) unsafe fn bf16_bits(v: __m512) -> __m512i {
        let b = _mm512_castps_si512(v);
        let lsb = _mm512_and_si512(_mm512_srli_epi32::<16>(b), _mm512_set1_epi32(1));
        let r = _mm512_srli_epi32::<16>(_mm512_add_epi32(_mm512_add_epi32(b, _mm512_set1_epi32(0x7fff)), lsb));
        _mm512_mask_mov_epi32(r, _mm512_cmp_ps_mask::<_CMP_UNORD_Q>(v, v), _mm512_set1_epi32(0x7fc0))
    }

    /// Words `bf16(lo) | bf16(hi) << 16`, lane by lane.
    #[inline(always)]
    pub(crate) unsafe fn bf16_pairs(lo: __m512, hi: __m512) -> __m512i {
        _mm512_or_si512(bf16_bits(lo), _mm512_slli_epi32::<16>(bf16_bits(hi)))
    }

    /// The whole 16-float blocks of [`super::bf16_pairs_of_row`]; returns
    /// the floats done.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub unsafe fn bf16_pairs_of_row(x: &[f32], scale: f32, out: &mut [u32]) -> usize {
        let s = _mm512_set1_ps(scale);
        let n = x.len() / 16 * 16;
        for i in (0..n).step_by(16) {
            let v = _mm512_mul_ps(_mm512_loadu_ps(x.as_ptr().add(i)), s);
            _mm256_storeu_si256(out.as_mut_ptr().add(i / 2) as *mut __m256i, _mm512_cvtepi32_epi16(bf16_bits(v)));
        }
        n
    }

    /// The bf16-pairs branch of [`super::pack_a_tile_cols`]: key pairs of
    /// two columns of `rows ≤ MR` values into one row of MR words.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub unsafe fn pack_pairs_cols<'a>(dst: &mut [u32], rows: usize, kc: usize, col: impl Fn(usize) -> &'a [f32]) {
        let m = crate::vecmath::x86::tail_mask(rows);
        for k2 in 0..kc.div_ceil(2) {
            let lo = _mm512_maskz_loadu_ps(m, col(2 * k2)[..rows].as_ptr());
            // An odd last key pairs with zero.
            let hi = if 2 * k2 + 1 < kc { _mm512_maskz_loadu_ps(m, col(2 * k2 + 1)[..rows].as_ptr()) } else { _mm512_setzero_ps() };
            _mm512_mask_storeu_epi32(dst.as_mut_ptr().add(k2 * MR) as *mut i32, m, bf16_pairs(lo, hi));
        }
    }

    #[inline(always)]
    fn mask(cols: usize) -> (__mmask16, __mmask16) {
        let m0 = crate::vecmath::x86::tail_mask(cols.min(16));
        let m1 = crate::vecmath::x86::tail_mask(cols.saturating_sub(16));
        (m0, if cols <= 16 { 0 } else { m1 })
    }

    #[inline(always)]
    unsafe fn store<const R: usize>(acc: &[[__m512; 2]; R], c: *mut f32, ldc: usize, rows: usize, cols: usize, load: bool) {
        if cols == NR {
            for i in 0..R {
                if i < rows {
                    let p = c.add(i * ldc);
                    let (mut v0, mut v1) = (acc[i][0], acc[i][1]);
                    if load {
                        v0 = _mm512_add_ps(v0, _mm512_loadu_ps(p));
                        v1 = _mm512_add_ps(v1, _mm512_loadu_ps(p.add(16)));
                    }
                    _mm512_storeu_ps(p, v0);
                    _mm512_storeu_ps(p.add(16), v1);
                }
            }
        } else {
            let (m0, m1) = mask(cols);
            for i in 0..R {
                if i < rows {
                    let p = c.add(i * ldc);
                    let (mut v0, mut v1) = (acc[i][0], acc[i][1]);
                    if load {
                        v0 = _mm512_add_ps(v0, _mm512_maskz_loadu_ps(m0, p));
                        v1 = _mm512_add_ps(v1, _mm512_maskz_loadu_ps(m1, p.add(16)));
                    }
                    _mm512_mask_storeu_ps(p, m0, v0);
                    _mm512_mask_storeu_ps(p.add(16), m1, v1);
                }
            }
        }
    }

    #[target_feature(enable = "avx512f,avx512bw,fma")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn kern_f32<const R: usize>(
        kc: usize,
        a: *const f32,
        b: *const f32,
        c: *mut f32,
        ldc: usize,
        rows: usize,
        cols: usize,
        load: bool,
    ) {
        let mut acc = [[_mm512_setzero_ps(); 2]; R];
        let (mut a, mut b) = (a, b);
        for _ in 0..kc {
            let b0 = _mm512_load_ps(b);
            let b1 = _mm512_load_ps(b.add(16));
            for i in 0..R {
                let ai = _mm512_set1_ps(*a.add(i));
                acc[i][0] = _mm512_fmadd_ps(ai, b0, acc[i][0]);
                acc[i][1] = _mm512_fmadd_ps(ai, b1, acc[i][1]);
            }
            a = a.add(MR);
            b = b.add(NR);
        }
        store(&acc, c, ldc, rows, cols, load);
    }

    #[target_feature(enable = "avx512f,avx512bw,fma")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn kern_f16<const R: usize>(
        kc: usize,
        a: *const f32,
        b: *const u16,
        c: *mut f32,
        ldc: usize,
        rows: usize,
        cols: usize,
        load: bool,
    ) {
        let mut acc = [[_mm512_setzero_ps(); 2]; R];
        let (mut a, mut b) = (a, b);
        for _ in 0..kc {
            let b0 = _mm512_cvtph_ps(_mm256_load_si256(b as *const __m256i));
            let b1 = _mm512_cvtph_ps(_mm256_load_si256(b.add(16) as *const __m256i));
            for i in 0..R {
                let ai = _mm512_set1_ps(*a.add(i));
                acc[i][0] = _mm512_fmadd_ps(ai, b0, acc[i][0]);
                acc[i][1] = _mm512_fmadd_ps(ai, b1, acc[i][1]);
            }
            a = a.add(MR);
            b = b.add(NR);
        }
        store(&acc, c, ldc, rows, cols, load);
    }

    /// bf16 pairs widened in registers: for each k pair, the low halves are
    /// the even k, the high halves the odd k.
    #[target_feature(enable = "avx512f,avx512bw,fma")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn kern_bf16_widen<const R: usize>(
        kc2: usize,
        a: *const f32,
        b: *const u16,
        c: *mut f32,
        ldc: usize,
        rows: usize,
        cols: usize,
        load: bool,
    ) {
        let mut acc = [[_mm512_setzero_ps(); 2]; R];
        let hi_mask = _mm512_set1_epi32(0xffff_0000u32 as i32);
        let (mut a, mut b) = (a, b);
        for _ in 0..kc2 {
            let r0 = _mm512_load_si512(b as *const __m512i);
            let r1 = _mm512_load_si512(b.add(32) as *const __m512i);
            let e0 = _mm512_castsi512_ps(_mm512_slli_epi32::<16>(r0));
            let e1 = _mm512_castsi512_ps(_mm512_slli_epi32::<16>(r1));
            let o0 = _mm512_castsi512_ps(_mm512_and_si512(r0, hi_mask));
            let o1 = _mm512_castsi512_ps(_mm512_and_si512(r1, hi_mask));
            for i in 0..R {
                let ae = _mm512_set1_ps(*a.add(i));
                let ao = _mm512_set1_ps(*a.add(MR + i));
                acc[i][0] = _mm512_fmadd_ps(ao, o0, _mm512_fmadd_ps(ae, e0, acc[i][0]));
                acc[i][1] = _mm512_fmadd_ps(ao, o1, _mm512_fmadd_ps(ae, e1, acc[i][1]));
            }
            a = a.add(2 * MR);
            b = b.add(2 * NR);
        }
        store(&acc, c, ldc, rows, cols, load);
    }

    #[target_feature(enable = "avx512f,avx512bw,avx512bf16,fma")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn kern_bf16_dp<const R: usize>(
        kc2: usize,
        a: *const u32,
        b: *const u16,
        c: *mut f32,
        ldc: usize,
        rows: usize,
        cols: usize,
        load: bool,
    ) {
        let mut acc = [[_mm512_setzero_ps(); 2]; R];
        let (mut a, mut b) = (a, b);
        for _ in 0..kc2 {
            let b0: __m512bh = std::mem::transmute(_mm512_load_si512(b as *const __m512i));
            let b1: __m512bh = std::mem::transmute(_mm512_load_si512(b.add(32) as *const __m512i));
            for i in 0..R {
                let ai: __m512bh = std::mem::transmute(_mm512_set1_epi32(*a.add(i) as i32));
                acc[i][0] = _mm512_dpbf16_ps(acc[i][0], ai, b0);
                acc[i][1] = _mm512_dpbf16_ps(acc[i][1], ai, b1);
            }
            a = a.add(MR);
            b = b.add(2 * NR);
        }
        store(&acc, c, ldc, rows, cols, load);
    }
}

/// AVX2 + FMA kernels over the same packed B panels. The 16 ymm registers
/// hold at most `6×16` of a tile (12 accumulators, two B vectors, one
/// broadcast), so a tile runs as sub-tiles: each 16-column half of the
/// panel in turn, in row groups of at most [`RMAX`] rows sized evenly
/// (`MR` rows: 5, 5, 4, faster than 6, 6, 2; [`super::gemm()`] packs 12-row
/// A tiles for f32 and bf16, see [`super::gemm_tile_rows`]). Every row's
/// sum runs in k order, as in the AVX-512 kernels.
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2 {
    use super::{WeightFormat, NR};
    use crate::vecmath::avx2::lane_mask;
    use std::arch::x86_64::*;

    /// Columns of a sub-tile: two 8-lane vectors.
    const NH: usize = 16;
    /// Rows of the largest sub-tile.
    pub(crate) const RMAX: usize = 6;

    /// bf16 bits (round to nearest even, NaN → 0x7fc0, as [`super::f32_to_bf16`])
    /// in the low half of each lane.
    #[inline(always)]
    pub(crate) unsafe fn bf16_bits(v: __m256) -> __m256i {
        let b = _mm256_castps_si256(v);
        let lsb = _mm256_and_si256(_mm256_srli_epi32::<16>(b), _mm256_set1_epi32(1));
        let r = _mm256_srli_epi32::<16>(_mm256_add_epi32(_mm256_add_epi32(b, _mm256_set1_epi32(0x7fff)), lsb));
        let nan = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_UNORD_Q>(v, v));
        _mm256_blendv_epi8(r, _mm256_set1_epi32(0x7fc0), nan)
    }

    /// Words `bf16(lo) | bf16(hi) << 16`, lane by lane.
    #[inline(always)]
    pub(crate) unsafe fn bf16_pairs(lo: __m256, hi: __m256) -> __m256i {
        _mm256_or_si256(bf16_bits(lo), _mm256_slli_epi32::<16>(bf16_bits(hi)))
    }

    /// The whole 16-float blocks of [`super::bf16_pairs_of_row`]; returns
    /// the floats done.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn bf16_pairs_of_row(x: &[f32], scale: f32, out: &mut [u32]) -> usize {
        let s = _mm256_set1_ps(scale);
        let n = x.len() / 16 * 16;
        for i in (0..n).step_by(16) {
            let v0 = bf16_bits(_mm256_mul_ps(_mm256_loadu_ps(x.as_ptr().add(i)), s));
            let v1 = bf16_bits(_mm256_mul_ps(_mm256_loadu_ps(x.as_ptr().add(i + 8)), s));
            // packus interleaves the 128-bit halves: put them back in order.
            let w = _mm256_permute4x64_epi64::<0b11_01_10_00>(_mm256_packus_epi32(v0, v1));
            _mm256_storeu_si256(out.as_mut_ptr().add(i / 2) as *mut __m256i, w);
        }
        n
    }

    /// Ask for the sub-tile's rows of `C` (a row apart in a large matrix,
    /// so out of cache and not prefetched by the hardware) before the k loop,
    /// so the final `C += acc` does not wait for them.
    #[inline(always)]
    unsafe fn prefetch_c<const R: usize>(c: *mut f32, ldc: usize) {
        for i in 0..R {
            _mm_prefetch::<_MM_HINT_T0>(c.wrapping_add(i * ldc) as *const i8);
        }
    }

    /// `C[R rows, cols ≤ 16] (+)= acc`.
    #[inline(always)]
    unsafe fn store<const R: usize>(acc: &[[__m256; 2]; R], c: *mut f32, ldc: usize, cols: usize, load: bool) {
        if cols == NH {
            for i in 0..R {
                let p = c.add(i * ldc);
                let (mut v0, mut v1) = (acc[i][0], acc[i][1]);
                if load {
                    v0 = _mm256_add_ps(v0, _mm256_loadu_ps(p));
                    v1 = _mm256_add_ps(v1, _mm256_loadu_ps(p.add(8)));
                }
                _mm256_storeu_ps(p, v0);
                _mm256_storeu_ps(p.add(8), v1);
            }
        } else {
            let m = [lane_mask(cols), lane_mask(cols.saturating_sub(8))];
            for i in 0..R {
                for h in 0..2 {
                    let p = c.add(i * ldc + 8 * h);
                    let mut v = acc[i][h];
                    if load {
                        v = _mm256_add_ps(v, _mm256_maskload_ps(p, m[h]));
                    }
                    _mm256_maskstore_ps(p, m[h], v);
                }
            }
        }
    }

    /// The k loop of a sub-tile: [`prefetch_c`], then `step(k)` for `k` in
    /// `0..n`, four at a time (the 5- and 6-row kernels issue close to four
    /// instructions per cycle, so the loop counter's share of the front end
    /// matters).
    #[inline(always)]
    unsafe fn k_loop<const R: usize>(n: usize, c: *mut f32, ldc: usize, mut step: impl FnMut(usize)) {
        prefetch_c::<R>(c, ldc);
        let mut k = 0;
        while k + 4 <= n {
            step(k);
            step(k + 1);
            step(k + 2);
            step(k + 3);
            k += 4;
        }
        while k < n {
            step(k);
            k += 1;
        }
    }

    /// `acc[i] += a[i] · (b0, b1)` for the sub-tile's rows.
    #[inline(always)]
    unsafe fn fma_rows<const R: usize>(acc: &mut [[__m256; 2]; R], a: *const f32, b0: __m256, b1: __m256) {
        for i in 0..R {
            let ai = _mm256_set1_ps(*a.add(i));
            acc[i][0] = _mm256_fmadd_ps(ai, b0, acc[i][0]);
            acc[i][1] = _mm256_fmadd_ps(ai, b1, acc[i][1]);
        }
    }

    /// f32 B: `a` at the sub-tile's first row of an A tile of `S` rows
    /// (stride `S` per k), `b` at its first column (stride `NR` per k).
    #[target_feature(enable = "avx2,fma")]
    unsafe fn kern_f32<const R: usize, const S: usize>(
        kc: usize,
        a: *const f32,
        b: *const f32,
        c: *mut f32,
        ldc: usize,
        cols: usize,
        load: bool,
    ) {
        let mut acc = [[_mm256_setzero_ps(); 2]; R];
        k_loop::<R>(kc, c, ldc, |k| {
            let b = b.add(k * NR);
            fma_rows(&mut acc, a.add(k * S), _mm256_load_ps(b), _mm256_load_ps(b.add(8)));
        });
        store(&acc, c, ldc, cols, load);
    }

    /// f16 B, widened by F16C.
    #[target_feature(enable = "avx2,fma,f16c")]
    unsafe fn kern_f16<const R: usize, const S: usize>(
        kc: usize,
        a: *const f32,
        b: *const u16,
        c: *mut f32,
        ldc: usize,
        cols: usize,
        load: bool,
    ) {
        let mut acc = [[_mm256_setzero_ps(); 2]; R];
        k_loop::<R>(kc, c, ldc, |k| {
            let b = b.add(k * NR);
            let b0 = _mm256_cvtph_ps(_mm_load_si128(b as *const __m128i));
            let b1 = _mm256_cvtph_ps(_mm_load_si128(b.add(8) as *const __m128i));
            fma_rows(&mut acc, a.add(k * S), b0, b1);
        });
        store(&acc, c, ldc, cols, load);
    }

    /// `p`, as a value the compiler cannot tell equal to `p`: loads through
    /// it are not merged with earlier loads through `p`, so their values need
    /// not stay in registers meanwhile (no instruction is emitted).
    #[inline(always)]
    #[allow(clippy::pointers_in_nomem_asm_block)] // the template reads no memory: it only hides the value
    fn reload<T>(mut p: *const T) -> *const T {
        // SAFETY: an empty template; the pointer is passed through unchanged.
        unsafe { std::arch::asm!("/* {0} */", inout(reg) p, options(pure, nomem, nostack, preserves_flags)) };
        p
    }

    /// bf16 pairs of B widened in registers (`b` at the sub-tile's first
    /// word, `NR` words per k pair): the even k of every row, then the odd k
    /// (B reloaded, so six rows still fit the registers).
    #[target_feature(enable = "avx2,fma")]
    unsafe fn kern_bf16<const R: usize, const S: usize>(
        kc2: usize,
        a: *const f32,
        b: *const u32,
        c: *mut f32,
        ldc: usize,
        cols: usize,
        load: bool,
    ) {
        let mut acc = [[_mm256_setzero_ps(); 2]; R];
        let hi_mask = _mm256_set1_epi32(0xffff_0000u32 as i32);
        k_loop::<R>(kc2, c, ldc, |k2| {
            let (a, b) = (a.add(2 * k2 * S), b.add(k2 * NR) as *const __m256i);
            let e0 = _mm256_castsi256_ps(_mm256_slli_epi32::<16>(_mm256_load_si256(b)));
            let e1 = _mm256_castsi256_ps(_mm256_slli_epi32::<16>(_mm256_load_si256(b.add(1))));
            fma_rows(&mut acc, a, e0, e1);
            // Six rows leave no register for the raw pairs: read them again.
            let b = if R == RMAX { reload(b) } else { b };
            let o0 = _mm256_castsi256_ps(_mm256_and_si256(_mm256_load_si256(b), hi_mask));
            let o1 = _mm256_castsi256_ps(_mm256_and_si256(_mm256_load_si256(b.add(1)), hi_mask));
            fma_rows(&mut acc, a.add(S), o0, o1);
        });
        store(&acc, c, ldc, cols, load);
    }

    /// Row groups of a tile of `rows` rows: `(first row, rows)`, at
    /// most [`RMAX`] rows each, as even as possible.
    #[inline(always)]
    pub(crate) fn row_groups(rows: usize) -> impl Iterator<Item = (usize, usize)> {
        let g = rows.div_ceil(RMAX);
        let (base, extra) = (rows / g.max(1), rows % g.max(1));
        (0..g).map(move |i| (i * base + i.min(extra), base + usize::from(i < extra)))
    }

    /// One register tile, as [`super::microkernel`] (same contract) but
    /// with A in tiles of `S` rows, for an `Isa` whose
    /// [`crate::isa::Simd`] is AVX2.
    #[target_feature(enable = "avx2,fma,f16c")]
    pub(crate) unsafe fn tile<const S: usize>(
        format: WeightFormat,
        kc: usize,
        a: *const u32,
        b: *const u8,
        c: *mut f32,
        ldc: usize,
        rows: usize,
        cols: usize,
        load: bool,
    ) {
        for h in 0..cols.div_ceil(NH) {
            let nc = NH.min(cols - h * NH);
            for (r0, nr) in row_groups(rows) {
                let a = (a as *const f32).add(r0);
                let c = c.add(r0 * ldc + h * NH);
                macro_rules! rows {
                    ($r:literal) => {
                        match format {
                            WeightFormat::F32 => kern_f32::<$r, S>(kc, a, (b as *const f32).add(h * NH), c, ldc, nc, load),
                            WeightFormat::F16 => kern_f16::<$r, S>(kc, a, (b as *const u16).add(h * NH), c, ldc, nc, load),
                            WeightFormat::Bf16 => kern_bf16::<$r, S>(kc / 2, a, (b as *const u32).add(h * NH), c, ldc, nc, load),
                        }
                    };
                }
                match nr {
                    1 => rows!(1),
                    2 => rows!(2),
                    3 => rows!(3),
                    4 => rows!(4),
                    5 => rows!(5),
                    _ => rows!(6),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::test_rng::Lcg;

    fn check(isa: Isa, format: WeightFormat, m: usize, k: usize, n: usize, lda: usize, act: Activation, seed: u64) {
        let mut r = Lcg(seed);
        let a = r.vec((m.max(1) - 1) * lda + k, 1.0);
        let w = r.vec(n * k, 1.0);
        let bias = r.vec(n, 1.0);
        let b = PackedMatrix::from_linear_weight(&w, n, k, format).unwrap();
        let ldc = n + 3;
        let mut c = vec![f32::NAN; (m.max(1) - 1) * ldc + n];
        gemm(isa, &a, m, lda, &b, Some(&bias), act, &mut c, ldc).unwrap();
        let want = gemm_reference(&a, m, lda, &b, Some(&bias), act);
        // f32 sums of k products of magnitude ≤ 1: error grows like √k·ulp.
        let tol = 1e-5 * (k as f32).sqrt().max(1.0) * 4.0;
        for i in 0..m {
            for j in 0..n {
                let (g, e) = (c[i * ldc + j], want[i * n + j]);
                assert!((g - e).abs() <= tol * e.abs().max(1.0), "{isa:?} {format:?} m{m} k{k} n{n}: C[{i}][{j}] = {g}, want {e}");
            }
        }
    }

    #[test]
    fn every_isa_and_format_matches_reference_on_awkward_shapes() {
        let shapes = [
            (1, 1, 1),
            (1, 7, 1),
            (3, 1, 5),
            (14, 32, 32),
            (15, 33, 33),
            (29, 64, 65),
            (13, 257, 31),
            (337, 70, 40),
            (2, 1030, 70),
            (50, 3, 97),
        ];
        for isa in Isa::all_supported() {
            for format in [WeightFormat::F32, WeightFormat::Bf16, WeightFormat::F16] {
                for (s, &(m, k, n)) in shapes.iter().enumerate() {
                    let act = [Activation::None, Activation::GeluTanh, Activation::GeluErf][s % 3];
                    check(isa, format, m, k, n, k + (s % 2) * 5, act, s as u64 + 1);
                }
            }
        }
    }

    /// Every tile height (each AVX2 row grouping) and the panel widths
    /// around the 8- and 16-column vector boundaries.
    #[test]
    fn every_tile_height_and_panel_width_matches_reference() {
        for isa in Isa::all_supported() {
            for format in [WeightFormat::F32, WeightFormat::Bf16, WeightFormat::F16] {
                for m in 1..=2 * MR {
                    for n in [1, 7, 8, 9, 15, 16, 17, 24, 25, 31, NR + 16] {
                        check(isa, format, m, 37, n, 40, Activation::None, (m * 100 + n) as u64);
                    }
                }
            }
        }
    }

    #[test]
    fn k_slices_beyond_kc_and_zero_k() {
        for isa in Isa::all_supported() {
            // K spans several KC slices (256 f32 / 512 bf16), odd K for the bf16 pairs.
            check(isa, WeightFormat::F32, 20, 600, 40, 600, Activation::None, 9);
            check(isa, WeightFormat::Bf16, 20, 1101, 40, 1101, Activation::None, 10);
            // K = 0: C = act(bias).
            let b = PackedMatrix::from_linear_weight(&[], 5, 0, WeightFormat::F32).unwrap();
            let mut c = vec![7f32; 2 * 5];
            gemm(isa, &[], 2, 0, &b, Some(&[1.0, -1.0, 0.0, 2.0, 3.0]), Activation::None, &mut c, 5).unwrap();
            assert_eq!(c, vec![1.0, -1.0, 0.0, 2.0, 3.0, 1.0, -1.0, 0.0, 2.0, 3.0]);
        }
    }

    #[test]
    fn result_does_not_depend_on_thread_count() {
        let mut r = Lcg(3);
        let (m, k, n) = (700, 300, 200);
        let a = r.vec(m * k, 1.0);
        let w = r.vec(n * k, 1.0);
        for isa in Isa::all_supported() {
            let b = PackedMatrix::from_linear_weight(&w, n, k, WeightFormat::Bf16).unwrap();
            let run = |t: usize| {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(t).build().unwrap();
                let mut c = vec![0f32; m * n];
                pool.install(|| gemm(isa, &a, m, k, &b, None, Activation::None, &mut c, n).unwrap());
                c
            };
            assert_eq!(run(1), run(3), "{isa:?}");
        }
    }

    #[test]
    fn blocking_follows_the_caches() {
        // Zen 4 (the tuned values), and a core with 48 KiB L1d / 2 MiB L2.
        assert_eq!(Blocking::for_caches(WeightFormat::F32, (32 << 10, 1 << 20)), Blocking { mc: 336, kc: 256, nc: 4 });
        assert_eq!(Blocking::for_caches(WeightFormat::Bf16, (32 << 10, 1 << 20)), Blocking { mc: 336, kc: 512, nc: 4 });
        assert_eq!(Blocking::for_caches(WeightFormat::F16, (32 << 10, 1 << 20)), Blocking { mc: 336, kc: 512, nc: 4 });
        assert_eq!(Blocking::for_caches(WeightFormat::F32, (48 << 10, 2 << 20)), Blocking { mc: 448, kc: 384, nc: 4 });
        // AVX2: f32 k slices twice as long; everything else as the caches say.
        let zen4 = (32 << 10, 1 << 20);
        assert_eq!(Blocking::for_isa_caches(Isa::Avx2, WeightFormat::F32, zen4), Blocking { mc: 336, kc: 512, nc: 4 });
        assert_eq!(Blocking::for_isa_caches(Isa::Avx2, WeightFormat::Bf16, zen4), Blocking { mc: 336, kc: 512, nc: 4 });
        assert_eq!(Blocking::for_isa_caches(Isa::Avx512, WeightFormat::F32, zen4), Blocking { mc: 336, kc: 256, nc: 4 });
        assert_eq!((parse_cache_size("32K"), parse_cache_size("2M"), parse_cache_size("x")), (Some(32 << 10), Some(2 << 20), None));
        let (l1, l2) = cache_sizes();
        assert!(l1 >= 4 << 10 && l2 > l1);
    }

    #[test]
    fn bad_shapes_are_errors() {
        let b = PackedMatrix::from_linear_weight(&[0.0; 6], 2, 3, WeightFormat::F32).unwrap();
        let mut c = vec![0f32; 4];
        assert!(gemm(Isa::Portable, &[0.0; 5], 2, 3, &b, None, Activation::None, &mut c, 2).is_err());
        assert!(gemm(Isa::Portable, &[0.0; 6], 2, 3, &b, Some(&[0.0]), Activation::None, &mut c, 2).is_err());
        assert!(gemm(Isa::Portable, &[0.0; 6], 2, 3, &b, None, Activation::None, &mut c[..3], 2).is_err());
        assert!(PackedMatrix::from_linear_weight(&[0.0; 5], 2, 3, WeightFormat::F32).is_err());
    }

    #[test]
    fn packed_values_round_as_the_format() {
        let w = [1.0f32 + 1.0 / 256.0 + 1.0 / 512.0, -3.0e-3];
        let b = PackedMatrix::from_linear_weight(&w, 2, 1, WeightFormat::Bf16).unwrap();
        assert_eq!(b.get(0, 0), round_bf16(w[0]));
        assert_eq!(b.get(0, 1), round_bf16(w[1]));
        assert_ne!(b.get(0, 0), w[0]);
        let h = PackedMatrix::from_linear_weight(&w, 2, 1, WeightFormat::F16).unwrap();
        assert_eq!(h.get(0, 0), w[0]); // exact in f16 (11-bit mantissa)
        assert_eq!(b.bytes(), 2 * NR * 2);
    }

    /// The vectorised bf16-pair conversions and packs give the scalar
    /// rounding bit for bit: ties, carries into the exponent, infinities,
    /// NaN, denormals, odd lengths and short tiles.
    #[test]
    fn bf16_pair_packs_match_scalar_rounding() {
        let mut r = Lcg(5);
        let n = 20000;
        let mut vals = r.vec(n, 4.0);
        let specials = [
            f32::from_bits(0x3f80_8000), // tie, even: stays
            f32::from_bits(0x3f81_8000), // tie, odd: rounds up
            f32::from_bits(0x3f7f_ffff), // carries into the exponent
            f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
            f32::from_bits(1),
            -f32::from_bits(0x007f_ffff),
            0.0,
            -0.0,
        ];
        for (i, v) in specials.iter().enumerate() {
            for j in (i * 37..n).step_by(997) {
                vals[j] = *v;
            }
        }
        let want_pair = |x: &[f32], k: usize, scale: f32| -> u32 {
            let lo = f32_to_bf16(x[2 * k] * scale) as u32;
            let hi = if 2 * k + 1 < x.len() { f32_to_bf16(x[2 * k + 1] * scale) as u32 } else { 0 };
            lo | (hi << 16)
        };
        for len in [0usize, 1, 2, 15, 16, 17, 31, 33, 64, 1001] {
            for scale in [1.0f32, 0.125, 3.7] {
                let x = &vals[len..2 * len];
                let mut got = vec![u32::MAX; len.div_ceil(2)];
                bf16_pairs_of_row(x, scale, &mut got);
                for (k, &g) in got.iter().enumerate() {
                    assert_eq!(g, want_pair(x, k, scale), "len {len} scale {scale} word {k}");
                }
                // The AVX2 blocks, which this function uses only on CPUs without AVX-512.
                #[cfg(target_arch = "x86_64")]
                if Isa::Avx2.supported() {
                    let mut got = vec![u32::MAX; len.div_ceil(2)];
                    // SAFETY: AVX2 checked.
                    let done = unsafe { avx2::bf16_pairs_of_row(x, scale, &mut got) };
                    assert_eq!(done, len / 16 * 16);
                    for (k, &g) in got[..done / 2].iter().enumerate() {
                        assert_eq!(g, want_pair(x, k, scale), "AVX2: len {len} scale {scale} word {k}");
                    }
                }
            }
        }
        for rows in [1usize, 5, MR] {
            for kc in [1usize, 2, 7, 32, 33, 600, 1025] {
                let lda = kc + 3;
                let a = &vals[..rows * lda];
                let mut got = vec![7u32; a_tile_words(AFormat::Bf16Pairs, kc)];
                pack_a_rows(AFormat::Bf16Pairs, &mut got, a, lda, rows, kc);
                let mut cols = vec![7u32; got.len()];
                pack_a_tile_cols(AFormat::Bf16Pairs, &mut cols, rows, kc, |k| &vals[k * MR..k * MR + MR]);
                // The f32 tiles of bf16-rounded values (tiles of MR and of 12 rows).
                for mr in [MR, 12] {
                    let mut f = vec![7u32; a_tile_words_mr(AFormat::F32Bf16, kc, mr)];
                    pack_a_rows_mr(AFormat::F32Bf16, &mut f, a, lda, rows.min(mr), kc, mr);
                    for k in 0..kc.div_ceil(2) * 2 {
                        for i in 0..mr {
                            let want = if i < rows.min(mr) && k < kc { round_bf16(a[i * lda + k]).to_bits() } else { 0 };
                            assert_eq!(f[k * mr + i], want, "rows {rows} kc {kc} mr {mr}: F32Bf16 ({k}, {i})");
                        }
                    }
                }
                for k2 in 0..kc.div_ceil(2) {
                    for i in 0..MR {
                        let (w, wc) = if i < rows {
                            let row = &a[i * lda..i * lda + kc];
                            let lo = f32_to_bf16(vals[2 * k2 * MR + i]) as u32;
                            let hi = if 2 * k2 + 1 < kc { f32_to_bf16(vals[(2 * k2 + 1) * MR + i]) as u32 } else { 0 };
                            (want_pair(row, k2, 1.0), lo | (hi << 16))
                        } else {
                            (0, 0)
                        };
                        assert_eq!(got[k2 * MR + i], w, "rows {rows} kc {kc}: pack_a_rows word ({k2}, {i})");
                        assert_eq!(cols[k2 * MR + i], wc, "rows {rows} kc {kc}: pack_a_tile_cols word ({k2}, {i})");
                    }
                }
            }
        }
    }

    /// `pack_many` gives, bit for bit, the matrices `pack_with` packs one at a time.
    #[test]
    fn pack_many_matches_pack_with() {
        for format in [WeightFormat::F32, WeightFormat::Bf16, WeightFormat::F16] {
            for (k, n) in [(1, 1), (5, 33), (16, 64), (7, 70)] {
                let mut r = Lcg(k as u64 * 131 + n as u64);
                let vals: Vec<Vec<f32>> = (0..3).map(|_| r.vec(k * n, 2.0)).collect();
                let many = PackedMatrix::pack_many(3, k, n, format, |kk, p, row| {
                    for (i, v) in vals.iter().enumerate() {
                        for j in 0..NR.min(n - p * NR) {
                            row[i * NR + j] = v[kk * n + p * NR + j];
                        }
                    }
                });
                for (i, v) in vals.iter().enumerate() {
                    let one = PackedMatrix::from_kn(v, k, n, format).unwrap();
                    assert_eq!((many[i].k(), many[i].n(), many[i].bytes()), (k, n, one.bytes()));
                    for kk in 0..format.k_padded(k) {
                        for j in 0..n.div_ceil(NR) * NR {
                            let (p, jj) = (j / NR, j % NR);
                            let idx = p * format.k_padded(k) * NR
                                + match format {
                                    WeightFormat::Bf16 => (kk / 2) * 2 * NR + 2 * jj + kk % 2,
                                    _ => kk * NR + jj,
                                };
                            let bits = |m: &PackedMatrix| match &m.store {
                                Store::F32(b) => b[idx].to_bits(),
                                Store::U16(b) => b[idx] as u32,
                            };
                            assert_eq!(bits(&many[i]), bits(&one), "{format:?} k{k} n{n} matrix {i} at ({kk}, {j})");
                        }
                    }
                }
            }
        }
    }
}
