//! Winograd F(2³, 3³) for 3×3×3, pad-1 convolutions (Lavin & Gray 2015).
//!
//! Each 2×2×2 output tile is `Aᵀ [ (G g Gᵀ) ⊙ (Bᵀ d B) ] A` along every
//! axis; summed over input channels, the elementwise product becomes 64
//! independent GEMMs, one per tap `e` of the 4×4×4 transformed tile:
//! `M[e] (tiles × Cout) = V[e] (tiles × Cin) · U[e] (Cin × Cout)`.
//!
//! - `U[e]` (transformed weights) is computed per call straight into recon's
//!   packed GEMM layout ([`PackedMatrix::pack_many`]) in the layer's
//!   [`WeightFormat`]: transformed in f32, rounded once (bf16 / f16).
//! - The input is copied once into a zero-padded channels-last volume, so the
//!   4×4×4 patch of 16 consecutive channels is 64 contiguous 16-lane loads
//!   and `Bᵀ d B` runs on whole vectors. `V[e]` is written directly in the
//!   GEMM kernel's packed `A` layout (rounded to bf16 there for bf16
//!   weights), so the GEMMs pack nothing.
//! - The GEMMs run recon's register-tile kernel ([`microkernel`]: AVX-512
//!   or AVX2 FMA, or `vdpbf16ps` with f32 accumulation), one task per (tap, row
//!   block), so every tap's operands are packed once.
//! - The output transform reads 16 consecutive output channels of `M` and
//!   writes NCDHW (plus bias, optionally accumulating onto `out`).
//!
//! The transforms are written once over a 16-lane vector type: a plain array
//! (portable), two AVX2 registers or an AVX-512 register; all do the same
//! operations in the same order (no fused multiply-adds), so they give
//! identical bits.

use super::Conv3dShape;
use crate::buf::SendPtr;
use crate::gemm::{a_format, a_tile_words, f32_to_bf16, microkernel, AFormat, Blocking, PackedMatrix, WeightFormat, MR, NR};
use crate::isa::{Isa, Simd};
use rayon::prelude::*;

/// Channels per transform vector.
const L: usize = 16;

/// 16 f32 lanes: the arithmetic the transforms need.
trait Lanes: Copy {
    /// # Safety
    /// `p` is valid for 16 reads.
    unsafe fn load(p: *const f32) -> Self;
    fn add(self, o: Self) -> Self;
    fn sub(self, o: Self) -> Self;
    fn half(self) -> Self;
    fn to_array(self) -> [f32; L];
    /// Each lane rounded to bf16 as [`f32_to_bf16`] does.
    fn to_bf16(self) -> [u16; L];
}

#[derive(Clone, Copy)]
struct Plain([f32; L]);

impl Lanes for Plain {
    #[inline(always)]
    unsafe fn load(p: *const f32) -> Self {
        Plain(std::ptr::read_unaligned(p as *const [f32; L]))
    }
    #[inline(always)]
    fn add(self, o: Self) -> Self {
        Plain(std::array::from_fn(|i| self.0[i] + o.0[i]))
    }
    #[inline(always)]
    fn sub(self, o: Self) -> Self {
        Plain(std::array::from_fn(|i| self.0[i] - o.0[i]))
    }
    #[inline(always)]
    fn half(self) -> Self {
        Plain(self.0.map(|v| 0.5 * v))
    }
    #[inline(always)]
    fn to_array(self) -> [f32; L] {
        self.0
    }
    #[inline(always)]
    fn to_bf16(self) -> [u16; L] {
        self.0.map(f32_to_bf16)
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Lanes, L};
    use crate::gemm::avx2::bf16_bits as avx2_bf16_bits;
    use crate::gemm::x86::bf16_bits;
    use std::arch::x86_64::*;

    /// One AVX-512 register; only used inside `avx512f` functions.
    #[derive(Clone, Copy)]
    pub(super) struct Zmm(__m512);

    impl Lanes for Zmm {
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            Zmm(_mm512_loadu_ps(p))
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            // SAFETY (all methods): reached only from `avx512f` functions.
            Zmm(unsafe { _mm512_add_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            Zmm(unsafe { _mm512_sub_ps(self.0, o.0) })
        }
        #[inline(always)]
        fn half(self) -> Self {
            Zmm(unsafe { _mm512_mul_ps(self.0, _mm512_set1_ps(0.5)) })
        }
        #[inline(always)]
        fn to_array(self) -> [f32; L] {
            let mut a = [0f32; L];
            unsafe { _mm512_storeu_ps(a.as_mut_ptr(), self.0) };
            a
        }
        #[inline(always)]
        fn to_bf16(self) -> [u16; L] {
            // Rounded as f32_to_bf16 (nearest even; NaN → 0x7fc0).
            let mut a = [0u16; L];
            unsafe { _mm256_storeu_si256(a.as_mut_ptr() as *mut __m256i, _mm512_cvtepi32_epi16(bf16_bits(self.0))) };
            a
        }
    }

    /// Two AVX2 registers; only used inside `avx2` functions.
    #[derive(Clone, Copy)]
    pub(super) struct Ymm2([__m256; 2]);

    impl Ymm2 {
        #[inline(always)]
        fn zip(self, o: Self, f: impl Fn(__m256, __m256) -> __m256) -> Self {
            Ymm2([f(self.0[0], o.0[0]), f(self.0[1], o.0[1])])
        }
    }

    impl Lanes for Ymm2 {
        #[inline(always)]
        unsafe fn load(p: *const f32) -> Self {
            Ymm2([_mm256_loadu_ps(p), _mm256_loadu_ps(p.add(8))])
        }
        #[inline(always)]
        fn add(self, o: Self) -> Self {
            // SAFETY (all methods): reached only from `avx2` functions.
            self.zip(o, |a, b| unsafe { _mm256_add_ps(a, b) })
        }
        #[inline(always)]
        fn sub(self, o: Self) -> Self {
            self.zip(o, |a, b| unsafe { _mm256_sub_ps(a, b) })
        }
        #[inline(always)]
        fn half(self) -> Self {
            self.zip(self, |a, _| unsafe { _mm256_mul_ps(a, _mm256_set1_ps(0.5)) })
        }
        #[inline(always)]
        fn to_array(self) -> [f32; L] {
            let mut a = [0f32; L];
            unsafe {
                _mm256_storeu_ps(a.as_mut_ptr(), self.0[0]);
                _mm256_storeu_ps(a.as_mut_ptr().add(8), self.0[1]);
            }
            a
        }
        #[inline(always)]
        fn to_bf16(self) -> [u16; L] {
            // Rounded as f32_to_bf16; packus interleaves the 128-bit halves, the permute restores the order.
            let mut a = [0u16; L];
            unsafe {
                let w = _mm256_packus_epi32(avx2_bf16_bits(self.0[0]), avx2_bf16_bits(self.0[1]));
                _mm256_storeu_si256(a.as_mut_ptr() as *mut __m256i, _mm256_permute4x64_epi64::<0b11_01_10_00>(w));
            }
            a
        }
    }
}

/// Bᵀ along one axis.
#[inline(always)]
fn bt<T: Lanes>(d: [T; 4]) -> [T; 4] {
    [d[0].sub(d[2]), d[1].add(d[2]), d[2].sub(d[1]), d[1].sub(d[3])]
}

/// G along one axis.
#[inline(always)]
fn g3<T: Lanes>(g: [T; 3]) -> [T; 4] {
    [g[0], g[0].add(g[1]).add(g[2]).half(), g[0].sub(g[1]).add(g[2]).half(), g[2]]
}

/// Aᵀ along one axis.
#[inline(always)]
fn at<T: Lanes>(m: [T; 4]) -> [T; 2] {
    [m[0].add(m[1]).add(m[2]), m[1].sub(m[2]).sub(m[3])]
}

/// `Bᵀ d B` of a 4×4×4 patch, `p[(z·4 + y)·4 + x]`, in place.
#[inline(always)]
fn input_tile<T: Lanes>(p: &mut [T; 64]) {
    for zy in 0..16 {
        let i = zy * 4;
        let r = bt([p[i], p[i + 1], p[i + 2], p[i + 3]]);
        p[i..i + 4].copy_from_slice(&r);
    }
    for z in 0..4 {
        for x in 0..4 {
            let i = |y: usize| (z * 4 + y) * 4 + x;
            let r = bt([p[i(0)], p[i(1)], p[i(2)], p[i(3)]]);
            for (y, v) in r.into_iter().enumerate() {
                p[i(y)] = v;
            }
        }
    }
    for yx in 0..16 {
        let r = bt([p[yx], p[16 + yx], p[32 + yx], p[48 + yx]]);
        for (z, v) in r.into_iter().enumerate() {
            p[z * 16 + yx] = v;
        }
    }
}

/// `G g Gᵀ` of a 3×3×3 kernel, `g[(z·3 + y)·3 + x]` → `u[(z·4 + y)·4 + x]`.
#[inline(always)]
fn weight_tile<T: Lanes>(g: &[T; 27]) -> [T; 64] {
    let mut t1 = [g[0]; 36]; // [3 z][3 y][4 x]
    for zy in 0..9 {
        let r = g3([g[zy * 3], g[zy * 3 + 1], g[zy * 3 + 2]]);
        t1[zy * 4..zy * 4 + 4].copy_from_slice(&r);
    }
    let mut t2 = [g[0]; 48]; // [3 z][4 y][4 x]
    for z in 0..3 {
        for x in 0..4 {
            let r = g3([t1[(z * 3) * 4 + x], t1[(z * 3 + 1) * 4 + x], t1[(z * 3 + 2) * 4 + x]]);
            for (y, v) in r.into_iter().enumerate() {
                t2[(z * 4 + y) * 4 + x] = v;
            }
        }
    }
    let mut u = [g[0]; 64];
    for yx in 0..16 {
        let r = g3([t2[yx], t2[16 + yx], t2[32 + yx]]);
        for (z, v) in r.into_iter().enumerate() {
            u[z * 16 + yx] = v;
        }
    }
    u
}

/// `Aᵀ m A` of a 4×4×4 tile → the 2×2×2 outputs `[(z·2 + y)·2 + x]`.
#[inline(always)]
fn output_tile<T: Lanes>(q: &[T; 64]) -> [T; 8] {
    let mut r1 = [q[0]; 32]; // [4 z][4 y][2 x]
    for zy in 0..16 {
        let r = at([q[zy * 4], q[zy * 4 + 1], q[zy * 4 + 2], q[zy * 4 + 3]]);
        r1[zy * 2..zy * 2 + 2].copy_from_slice(&r);
    }
    let mut r2 = [q[0]; 16]; // [4 z][2 y][2 x]
    for z in 0..4 {
        for x in 0..2 {
            let i = |y: usize| (z * 4 + y) * 2 + x;
            let r = at([r1[i(0)], r1[i(1)], r1[i(2)], r1[i(3)]]);
            r2[(z * 2) * 2 + x] = r[0];
            r2[(z * 2 + 1) * 2 + x] = r[1];
        }
    }
    let mut r3 = [q[0]; 8];
    for yx in 0..4 {
        let r = at([r2[yx], r2[4 + yx], r2[8 + yx], r2[12 + yx]]);
        r3[yx] = r[0];
        r3[4 + yx] = r[1];
    }
    r3
}

/// Geometry of one call: tile grid, padded channels-last input, strides.
#[derive(Clone, Copy)]
struct Geom {
    cin: usize,
    cout: usize,
    d: usize,
    h: usize,
    w: usize,
    /// Tiles along y and x.
    th: usize,
    tw: usize,
    /// Padded input height and width (`2·tiles + 2`).
    hp: usize,
    wp: usize,
    /// `Cin` rounded up to whole vectors (the channel stride of the padded input).
    cinp: usize,
    /// `Cout` rounded up to whole GEMM panels.
    coutp: usize,
}

impl Geom {
    fn new(s: &Conv3dShape) -> Self {
        let (th, tw) = (s.h.div_ceil(2), s.w.div_ceil(2));
        Geom {
            cin: s.cin,
            cout: s.cout,
            d: s.d,
            h: s.h,
            w: s.w,
            th,
            tw,
            hp: 2 * th + 2,
            wp: 2 * tw + 2,
            cinp: s.cin.next_multiple_of(L),
            coutp: s.cout.next_multiple_of(NR),
        }
    }
    fn tiles(&self) -> usize {
        self.d.div_ceil(2) * self.th * self.tw
    }
    fn padded_len(&self) -> usize {
        (2 * self.d.div_ceil(2) + 2) * self.hp * self.wp * self.cinp
    }
    fn tile(&self, t: usize) -> (usize, usize, usize) {
        (t / (self.th * self.tw), (t / self.tw) % self.th, t % self.tw)
    }
}

/// Layout of `V`: for tap `e`, row tile `rt` (`MR` tiles) and k slice `ks`
/// (`kc` channels), one packed `A` tile of the GEMM kernel (`aw` words).
#[derive(Clone, Copy)]
struct APack {
    afmt: AFormat,
    kc: usize,
    nks: usize,
    nrt: usize,
    aw: usize,
}

impl APack {
    fn offset(&self, e: usize, rt: usize, ks: usize) -> usize {
        ((e * self.nrt + rt) * self.nks + ks) * self.aw
    }
}

/// Every matrix of `U` for `weight` (`[Cout, Cin, 3, 3, 3]`).
fn weight_taps(weight: &[f32], cin: usize, cout: usize, format: WeightFormat, isa: Isa) -> Vec<PackedMatrix> {
    PackedMatrix::pack_many(64, cin, cout, format, |ci, p, row| {
        #[cfg(target_arch = "x86_64")]
        match isa.simd() {
            // SAFETY (both): the caller checked that the CPU runs `isa`.
            Simd::Avx512 => return unsafe { weight_row_avx512(weight, cin, cout, ci, p, row) },
            Simd::Avx2 => return unsafe { weight_row_avx2(weight, cin, cout, ci, p, row) },
            Simd::Scalar => {}
        }
        let _ = isa;
        weight_row::<Plain>(weight, cin, cout, ci, p, row)
    })
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,fma")]
unsafe fn weight_row_avx512(weight: &[f32], cin: usize, cout: usize, ci: usize, p: usize, row: &mut [f32]) {
    weight_row::<x86::Zmm>(weight, cin, cout, ci, p, row)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn weight_row_avx2(weight: &[f32], cin: usize, cout: usize, ci: usize, p: usize, row: &mut [f32]) {
    weight_row::<x86::Ymm2>(weight, cin, cout, ci, p, row)
}

/// Row `ci` of panel `p` of every `U[e]`: `row[e·NR + j] = U[e](ci, co = p·NR + j)`.
#[inline(always)]
fn weight_row<T: Lanes>(weight: &[f32], cin: usize, cout: usize, ci: usize, p: usize, row: &mut [f32]) {
    let cols = NR.min(cout - p * NR);
    let mut g = [[0f32; NR]; 27];
    for j in 0..cols {
        let src = &weight[((p * NR + j) * cin + ci) * 27..][..27];
        for (t, &v) in src.iter().enumerate() {
            g[t][j] = v;
        }
    }
    for half in 0..NR / L {
        // SAFETY: each g[t] holds NR = 2·L values.
        let gl: [T; 27] = std::array::from_fn(|t| unsafe { T::load(g[t].as_ptr().add(half * L)) });
        let u = weight_tile(&gl);
        for (e, ue) in u.iter().enumerate() {
            row[e * NR + half * L..][..L].copy_from_slice(&ue.to_array());
        }
    }
}

/// Copy batch item `xb` (NCDHW, `Cin` channels) into the interior of the
/// zero-bordered channels-last `xp` (`[Dp][Hp][Wp][Cinp]`).
fn pad_channels_last(xb: &[f32], g: &Geom, xp: &mut [f32]) {
    let (d, h, w) = (g.d, g.h, g.w);
    let plane = d * h * w;
    xp.par_chunks_mut(g.hp * g.wp * g.cinp).enumerate().for_each(|(zp, dst)| {
        if zp == 0 || zp > d {
            return;
        }
        let z = zp - 1;
        for y in 0..h {
            let drow = &mut dst[((y + 1) * g.wp + 1) * g.cinp..][..w * g.cinp];
            for ci in 0..g.cin {
                let src = &xb[ci * plane + (z * h + y) * w..][..w];
                for (x, &v) in src.iter().enumerate() {
                    drow[x * g.cinp + ci] = v;
                }
            }
        }
    });
}

/// Store the 16 channels `kk0..kk0+16` of row `i` into a packed `A` tile.
///
/// # Safety
/// `dst` holds a tile of at least `kk0 + 16` k values in `afmt`.
#[inline(always)]
unsafe fn store_a<T: Lanes>(afmt: AFormat, v: T, dst: *mut u32, kk0: usize, i: usize) {
    match afmt {
        AFormat::F32 => {
            for (j, x) in v.to_array().into_iter().enumerate() {
                *dst.add((kk0 + j) * MR + i) = x.to_bits();
            }
        }
        AFormat::F32Bf16 => {
            for (j, b) in v.to_bf16().into_iter().enumerate() {
                *dst.add((kk0 + j) * MR + i) = (b as u32) << 16;
            }
        }
        AFormat::Bf16Pairs => {
            let b = v.to_bf16();
            for j2 in 0..L / 2 {
                *dst.add((kk0 / 2 + j2) * MR + i) = b[2 * j2] as u32 | ((b[2 * j2 + 1] as u32) << 16);
            }
        }
    }
}

/// `V` of row tile `rt` (tiles `t0 + rt·MR ..`, at most `tc` in the chunk).
#[inline(always)]
fn input_job<T: Lanes>(xp: &[f32], g: &Geom, ap: &APack, t0: usize, tc: usize, rt: usize, v: *mut u32) {
    let cinp = g.cinp;
    assert!(xp.len() >= g.padded_len());
    for i in 0..MR.min(tc - rt * MR) {
        let (tz, ty, tx) = g.tile(t0 + rt * MR + i);
        let base = ((2 * tz * g.hp + 2 * ty) * g.wp + 2 * tx) * cinp;
        for c0 in (0..cinp).step_by(L) {
            let mut p = [unsafe { T::load(xp.as_ptr()) }; 64];
            for a in 0..4 {
                for b in 0..4 {
                    let row = base + (a * g.hp + b) * g.wp * cinp + c0;
                    for c in 0..4 {
                        // SAFETY: the patch lies inside the padded volume (asserted length).
                        p[(a * 4 + b) * 4 + c] = unsafe { T::load(xp.as_ptr().add(row + c * cinp)) };
                    }
                }
            }
            input_tile(&mut p);
            let (ks, kk0) = (c0 / ap.kc, c0 % ap.kc);
            for (e, &pe) in p.iter().enumerate() {
                // SAFETY: row tile rt of V belongs to this job; ap.kc is a multiple of L.
                unsafe { store_a(ap.afmt, pe, v.add(ap.offset(e, rt, ks)), kk0, i) };
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,fma")]
unsafe fn input_job_avx512(xp: &[f32], g: &Geom, ap: &APack, t0: usize, tc: usize, rt: usize, v: *mut u32) {
    input_job::<x86::Zmm>(xp, g, ap, t0, tc, rt, v)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn input_job_avx2(xp: &[f32], g: &Geom, ap: &APack, t0: usize, tc: usize, rt: usize, v: *mut u32) {
    input_job::<x86::Ymm2>(xp, g, ap, t0, tc, rt, v)
}

fn input_transform(isa: Isa, xp: &[f32], g: &Geom, ap: &APack, t0: usize, tc: usize, v: &mut [u32]) {
    assert!(v.len() >= ap.offset(64, 0, 0) && tc <= ap.nrt * MR);
    let vp = SendPtr(v.as_mut_ptr());
    (0..tc.div_ceil(MR)).into_par_iter().for_each(|rt| {
        #[cfg(target_arch = "x86_64")]
        match isa.simd() {
            // SAFETY (both): the caller checked that the CPU runs `isa`.
            Simd::Avx512 => return unsafe { input_job_avx512(xp, g, ap, t0, tc, rt, vp.get()) },
            Simd::Avx2 => return unsafe { input_job_avx2(xp, g, ap, t0, tc, rt, vp.get()) },
            Simd::Scalar => {}
        }
        let _ = isa;
        input_job::<Plain>(xp, g, ap, t0, tc, rt, vp.get())
    });
}

/// `M` of the chunk's `tc` tiles, as `[tile][panel][e][NR]`: the output
/// transform then reads each tile's values sequentially, and rows of the GEMM
/// result (tiles, for one tap) are still a fixed stride apart. One task per
/// tap and block of row tiles, sweeping the tap's weight panels.
#[allow(clippy::too_many_arguments)]
fn gemm_taps(isa: Isa, format: WeightFormat, u: &[PackedMatrix], g: &Geom, ap: &APack, v: &[u32], tc: usize, m: &mut [f32]) {
    assert!(v.len() >= ap.offset(64, 0, 0) && m.len() >= tc * 64 * g.coutp && u.len() == 64);
    let panels = g.cout.div_ceil(NR);
    let nrt = tc.div_ceil(MR);
    let rb_tiles = (Blocking::for_isa(isa, format).mc / MR).max(1);
    let nrb = nrt.div_ceil(rb_tiles);
    let ldc = 64 * g.coutp;
    debug_assert!(g.coutp.is_multiple_of(NR));
    let mp = SendPtr(m.as_mut_ptr());
    (0..64 * nrb).into_par_iter().for_each(|task| {
        let (e, rb) = (task / nrb, task % nrb);
        let (rt0, rt1) = (rb * rb_tiles, ((rb + 1) * rb_tiles).min(nrt));
        for ks in 0..ap.nks {
            let k0 = ks * ap.kc;
            let kc = format.k_padded(ap.kc.min(g.cin - k0));
            for p in 0..panels {
                let bp = u[e].panel_ptr(p, k0);
                let cols = NR.min(g.cout - p * NR);
                for rt in rt0..rt1 {
                    let rows = MR.min(tc - rt * MR);
                    // SAFETY: the A tile holds kc values in a_format(isa, format) (zero padded),
                    // the B panel kc values; rows rt of tap e of M belong to this task.
                    unsafe {
                        let c = mp.get().add(rt * MR * ldc + (p * 64 + e) * NR);
                        microkernel(isa, format, kc, v.as_ptr().add(ap.offset(e, rt, ks)), bp, c, ldc, rows, cols, ks > 0);
                    }
                }
            }
        }
    });
}

/// Tiles `t0 + tl`, `tl` in `tl0..tl1`, from `M` into the NCDHW `out`
/// (every output channel).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn output_job<T: Lanes>(
    m: &[f32],
    g: &Geom,
    t0: usize,
    (tl0, tl1): (usize, usize),
    bias: Option<&[f32]>,
    accumulate: bool,
    out: SendPtr<f32>,
) {
    let (d, h, w) = (g.d, g.h, g.w);
    let plane = d * h * w;
    assert!(m.len() >= tl1 * 64 * g.coutp);
    for tl in tl0..tl1 {
        let (tz, ty, tx) = g.tile(t0 + tl);
        for c0 in (0..g.cout).step_by(L) {
            let n = L.min(g.cout - c0);
            let (p, half) = (c0 / NR, c0 % NR);
            let row = |e: usize| tl * 64 * g.coutp + (p * 64 + e) * NR + half;
            // SAFETY: M holds tl1 tiles of 64·Coutp values (asserted).
            let q: [T; 64] = std::array::from_fn(|e| unsafe { T::load(m.as_ptr().add(row(e))) });
            let r = output_tile(&q);
            for (k, rk) in r.iter().enumerate() {
                let (oz, oy, ox) = (2 * tz + k / 4, 2 * ty + (k / 2) % 2, 2 * tx + k % 2);
                if oz >= d || oy >= h || ox >= w {
                    continue;
                }
                let pos = (oz * h + oy) * w + ox;
                let vals = rk.to_array();
                for j in 0..n {
                    // SAFETY: the outputs of these tiles (one batch item) belong to this job.
                    unsafe {
                        let o = out.get().add((c0 + j) * plane + pos);
                        let val = vals[j] + bias.map_or(0.0, |b| b[c0 + j]);
                        *o = if accumulate { *o + val } else { val };
                    }
                }
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,fma")]
unsafe fn output_job_avx512(m: &[f32], g: &Geom, t0: usize, tls: (usize, usize), bias: Option<&[f32]>, acc: bool, out: SendPtr<f32>) {
    output_job::<x86::Zmm>(m, g, t0, tls, bias, acc, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn output_job_avx2(m: &[f32], g: &Geom, t0: usize, tls: (usize, usize), bias: Option<&[f32]>, acc: bool, out: SendPtr<f32>) {
    output_job::<x86::Ymm2>(m, g, t0, tls, bias, acc, out)
}

/// One job per row of tiles along x (cut at the chunk's ends): M is read
/// sequentially, and jobs write disjoint output rows.
#[allow(clippy::too_many_arguments)]
fn output_transform(isa: Isa, m: &[f32], g: &Geom, t0: usize, tc: usize, bias: Option<&[f32]>, accumulate: bool, ob: &mut [f32]) {
    assert!(ob.len() == g.cout * g.d * g.h * g.w && bias.is_none_or(|b| b.len() == g.cout));
    let op = SendPtr(ob.as_mut_ptr());
    let (r0, r1) = (t0 / g.tw, (t0 + tc).div_ceil(g.tw));
    (r0..r1).into_par_iter().for_each(|r| {
        let tls = ((r * g.tw).max(t0) - t0, ((r + 1) * g.tw).min(t0 + tc) - t0);
        #[cfg(target_arch = "x86_64")]
        match isa.simd() {
            // SAFETY (both): the caller checked that the CPU runs `isa`.
            Simd::Avx512 => return unsafe { output_job_avx512(m, g, t0, tls, bias, accumulate, op) },
            Simd::Avx2 => return unsafe { output_job_avx2(m, g, t0, tls, bias, accumulate, op) },
            Simd::Scalar => {}
        }
        let _ = isa;
        output_job::<Plain>(m, g, t0, tls, bias, accumulate, op)
    });
}

/// The convolution (shape already checked, `k = 3`, `pad = 1`): tiles in
/// chunks of `tiles_per_chunk`, U in `format`, kernels of `isa`, k slices of
/// `kc` channels (a multiple of 16; `None`: as the GEMM blocks them).
#[allow(clippy::too_many_arguments)]
pub(super) fn winograd(
    x: &[f32],
    s: &Conv3dShape,
    weight: &[f32],
    bias: Option<&[f32]>,
    out: &mut [f32],
    accumulate: bool,
    format: WeightFormat,
    isa: Isa,
    tiles_per_chunk: usize,
    kc: Option<usize>,
) -> Result<(), String> {
    if !isa.supported() {
        return Err(format!("conv3d: instruction set {} is not supported by this CPU", isa.name()));
    }
    let g = Geom::new(s);
    let ntiles = g.tiles();
    let plane = s.d * s.h * s.w;
    let u = weight_taps(weight, s.cin, s.cout, format, isa);
    let tc_max = tiles_per_chunk.clamp(1, ntiles);
    let afmt = a_format(isa, format);
    // k slices as the GEMM blocks them (B's micro-panel in L1), whole vectors.
    let kc = kc.unwrap_or(Blocking::for_isa(isa, format).kc).max(L) / L * L;
    let ap = APack { afmt, kc, nks: s.cin.div_ceil(kc), nrt: tc_max.div_ceil(MR), aw: a_tile_words(afmt, kc) };
    let mut xp = vec![0f32; g.padded_len()];
    let mut v = vec![0u32; ap.offset(64, 0, 0)];
    let mut m = vec![0f32; tc_max * 64 * g.coutp];
    for b in 0..s.batch {
        pad_channels_last(&x[b * s.cin * plane..][..s.cin * plane], &g, &mut xp);
        let ob = &mut out[b * s.cout * plane..][..s.cout * plane];
        for t0 in (0..ntiles).step_by(tc_max) {
            let tc = tc_max.min(ntiles - t0);
            input_transform(isa, &xp, &g, &ap, t0, tc, &mut v);
            gemm_taps(isa, format, &u, &g, &ap, &v, tc, &mut m);
            output_transform(isa, &m, &g, t0, tc, bias, accumulate, ob);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::Lcg;

    /// The AVX2 and AVX-512 builds of the transforms give the portable ones' bits.
    #[test]
    fn vector_transforms_match_portable_bits() {
        let s = Conv3dShape { batch: 1, cin: 20, cout: 19, d: 3, h: 5, w: 4, k: 3, pad: 1 };
        let mut r = Lcg(5);
        let x = r.vec(s.input_len(), 1.0);
        let wt = r.vec(s.weight_len(), 1.0);
        let bias = r.vec(s.cout, 1.0);
        let base = r.vec(s.output_len(), 1.0);
        let g = Geom::new(&s);
        let ntiles = g.tiles();
        let mut xp = vec![0f32; g.padded_len()];
        pad_channels_last(&x, &g, &mut xp);
        let m: Vec<f32> = (0..ntiles * 64 * g.coutp).map(|i| r.next() + (i % 7) as f32).collect();
        for (format, afmt) in
            [(WeightFormat::F32, AFormat::F32), (WeightFormat::Bf16, AFormat::F32Bf16), (WeightFormat::Bf16, AFormat::Bf16Pairs)]
        {
            let ap = APack { afmt, kc: 16, nks: 2, nrt: ntiles.div_ceil(MR), aw: a_tile_words(afmt, 16) };
            let mut runs = Vec::new();
            let isas = [Isa::Portable, Isa::Avx2, Isa::Avx512].into_iter().filter(|i| i.supported()).collect::<Vec<_>>();
            for &isa in &isas {
                let mut v = vec![0u32; ap.offset(64, 0, 0)];
                input_transform(isa, &xp, &g, &ap, 0, ntiles, &mut v);
                let mut out = base.clone();
                output_transform(isa, &m, &g, 0, ntiles, Some(&bias), true, &mut out);
                let u: Vec<u32> = weight_taps(&wt, 20, 19, format, isa)
                    .iter()
                    .flat_map(|p| (0..20).flat_map(move |ci| (0..19).map(move |co| p.get(ci, co).to_bits())))
                    .collect();
                runs.push((v, out.iter().map(|f| f.to_bits()).collect::<Vec<_>>(), u));
            }
            for (isa, run) in isas.iter().zip(&runs).skip(1) {
                assert!(runs[0] == *run, "{afmt:?}: portable and {isa:?} transforms differ");
            }
        }
    }

    /// The vector bf16 roundings are `f32_to_bf16`, ties and NaN included.
    #[test]
    fn vector_bf16_rounding_matches_scalar() {
        #[target_feature(enable = "avx512f,avx512bw")]
        unsafe fn round512(v: &[f32; L]) -> [u16; L] {
            x86::Zmm::load(v.as_ptr()).to_bf16()
        }
        #[target_feature(enable = "avx2,fma")]
        unsafe fn round256(v: &[f32; L]) -> [u16; L] {
            x86::Ymm2::load(v.as_ptr()).to_bf16()
        }
        let special = [1.0 + 1.0 / 256.0, 1.0 + 3.0 / 256.0, -2.5e-3, f32::NAN, f32::INFINITY, -0.0, 3.4e38, 1e-40];
        let mut r = Lcg(9);
        for round_i in 0..64 {
            // The specials in the low lanes, then in the high ones (AVX2's second register).
            let v: [f32; L] = std::array::from_fn(|j| if j / 8 == round_i { special[j % 8] } else { r.next() * 100.0 });
            let want = v.map(f32_to_bf16);
            if Isa::Avx512.supported() {
                // SAFETY: AVX-512 checked.
                assert_eq!(unsafe { round512(&v) }, want, "AVX-512 {v:?}");
            }
            if Isa::Avx2.supported() {
                // SAFETY: AVX2 checked.
                assert_eq!(unsafe { round256(&v) }, want, "AVX2 {v:?}");
            }
        }
    }
}
