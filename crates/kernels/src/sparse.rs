//! Submanifold sparse 3D convolution on voxel coordinates (spconv `SubMConv3d`).
//!
//! Data layout:
//! - coordinates are `[batch, x, y, z]` (`i32`), one per feature row;
//! - features are row-major `[N, C]` `f32`;
//! - weights use spconv's stored layout `[C_out, kx, ky, kz, C_in]`
//!   (row-major, `C_in` fastest), with a separate bias `[C_out]`.
//!
//! Orientation (cross-correlation, like `torch.nn.Conv3d`): for kernel size
//! `k` and `r = k / 2`, the weight slice at kernel index `(i, j, l)` multiplies
//! the input at `(x + i - r, y + j - r, z + l - r)` to produce the output at
//! `(x, y, z)`. Offset index `o = (i·k + j)·k + l`, matching the weight layout.
//!
//! "Submanifold" means output sites equal input sites, and only active
//! neighbours contribute (missing ones count as zero).
//!
//! The conv is gather → GEMM → scatter per output chunk. Chunks are fixed-size
//! and each output row is accumulated in a fixed order (offset 0, 1, …, then
//! bias), so results are bitwise identical whatever the thread count.

use crate::gemm::{self as kgemm, PackedMatrix, WeightFormat, NR};
use crate::isa::Isa;
use crate::vecmath::Activation;
use rayon::prelude::*;
use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

/// A small multiplicative hasher for packed voxel keys (std's SipHash is
/// needlessly slow for millions of integer lookups).
#[derive(Default)]
pub struct VoxelHasher(u64);

impl Hasher for VoxelHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(5) ^ b as u64).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
        }
    }
    fn write_u64(&mut self, v: u64) {
        // splitmix64 finaliser: good avalanche for structured keys.
        let mut z = v.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        self.0 = z ^ (z >> 31);
    }
}

/// Pack `(batch, x, y, z)` into one u64 (16 bits each, two's complement
/// truncated; coordinates must lie in `-32768..32768`).
#[inline]
fn pack(c: [i32; 4]) -> u64 {
    ((c[0] as u16 as u64) << 48) | ((c[1] as u16 as u64) << 32) | ((c[2] as u16 as u64) << 16) | (c[3] as u16 as u64)
}

/// Coordinate hash: `(batch, x, y, z)` → row index.
pub struct CoordHash {
    map: HashMap<u64, u32, BuildHasherDefault<VoxelHasher>>,
}

impl CoordHash {
    /// Build from coordinates; a duplicated coordinate keeps its first row.
    pub fn new(coords: &[[i32; 4]]) -> Self {
        let mut map = HashMap::with_capacity_and_hasher(coords.len(), Default::default());
        for (i, &c) in coords.iter().enumerate() {
            map.entry(pack(c)).or_insert(i as u32);
        }
        CoordHash { map }
    }

    /// Row of `c`, if active. Coordinates outside the packable range are never active.
    #[inline]
    pub fn get(&self, c: [i32; 4]) -> Option<u32> {
        if c.iter().any(|&v| !(-32768..32768).contains(&v)) {
            return None;
        }
        self.map.get(&pack(c)).copied()
    }

    /// Number of active coordinates.
    pub fn len(&self) -> usize {
        self.map.len()
    }

    /// Whether no coordinate is active.
    pub fn is_empty(&self) -> bool {
        self.map.is_empty()
    }
}

/// Neighbour map of a submanifold conv: for each kernel offset, the
/// `(out_row, in_row)` pairs, sorted by `out_row`.
#[derive(Debug, Clone)]
pub struct NeighbourMap {
    /// Cubic kernel size `k`.
    pub kernel_size: usize,
    /// Number of active rows (input and output).
    pub num_rows: usize,
    /// `pairs[o]` for offset index `o = (i·k + j)·k + l`.
    pub pairs: Vec<Vec<(u32, u32)>>,
}

impl NeighbourMap {
    /// Build the map for odd `kernel_size` over `coords` (outputs = inputs).
    pub fn submanifold(coords: &[[i32; 4]], kernel_size: usize) -> Result<Self, String> {
        if kernel_size.is_multiple_of(2) || kernel_size == 0 {
            return Err(format!("submanifold conv needs an odd kernel size, got {kernel_size}"));
        }
        if coords.len() > u32::MAX as usize {
            return Err("too many voxels for a u32 row index".into());
        }
        let k = kernel_size as i32;
        let r = k / 2;
        let kv = kernel_size.pow(3);
        let hash = CoordHash::new(coords);
        let pairs: Vec<Vec<(u32, u32)>> = (0..kv)
            .into_par_iter()
            .map(|o| {
                let (i, j, l) = ((o as i32) / (k * k), (o as i32 / k) % k, o as i32 % k);
                let (dx, dy, dz) = (i - r, j - r, l - r);
                let mut v = Vec::new();
                for (row, c) in coords.iter().enumerate() {
                    if let Some(src) = hash.get([c[0], c[1] + dx, c[2] + dy, c[3] + dz]) {
                        v.push((row as u32, src));
                    }
                }
                v
            })
            .collect();
        Ok(NeighbourMap { kernel_size, num_rows: coords.len(), pairs })
    }

    /// Number of kernel offsets (`k³`).
    pub fn kernel_volume(&self) -> usize {
        self.pairs.len()
    }
}

/// Output rows per parallel work item. Fixed (not derived from the thread
/// count) so the accumulation order never depends on scheduling.
const CHUNK_ROWS: usize = 256;

/// Submanifold sparse conv: `out[N, c_out] = Σ_o gather_o(x) · W_oᵀ + bias`.
///
/// `feats` is `[N, c_in]`, `weight` is `[c_out, k, k, k, c_in]`, `bias` is
/// `[c_out]` or empty. Returns `[N, c_out]`.
pub fn submanifold_conv3d(
    feats: &[f32],
    c_in: usize,
    map: &NeighbourMap,
    weight: &[f32],
    bias: Option<&[f32]>,
    c_out: usize,
) -> Result<Vec<f32>, String> {
    let kv = map.kernel_volume();
    if weight.len() != c_out * kv * c_in {
        return Err(format!("sparse conv: weight has {} values, expected {c_out}×{kv}×{c_in}", weight.len()));
    }
    conv_by_chunks(feats, c_in, c_out, map, bias, CHUNK_ROWS, |o, gathered, m, prod| {
        // W_o as a [c_in, c_out] matrix read in place from [c_out, kv, c_in]:
        // element (ci, co) sits at co·kv·c_in + o·c_in + ci.
        unsafe {
            gemm::gemm(
                m,
                c_out,
                c_in,
                prod.as_mut_ptr(),
                1,
                c_out as isize,
                false,
                gathered.as_ptr(),
                1,
                c_in as isize,
                weight.as_ptr().add(o * c_in),
                (kv * c_in) as isize,
                1,
                0f32,
                1f32,
                false,
                false,
                false,
                gemm::Parallelism::None,
            );
        }
        Ok(())
    })
}

/// The chunk driver of both kernels: output rows in tasks of `chunk_rows`;
/// per task and kernel offset `o`, the offset's `m` input rows are gathered
/// (`[m, c_in]`), `product(o, gathered, m, prod)` writes their `[m, c_out]`
/// contributions into the zeroed `prod`, and those are added into their
/// output rows, offsets in order; then the bias. Checks `feats` and `bias`.
fn conv_by_chunks(
    feats: &[f32],
    c_in: usize,
    c_out: usize,
    map: &NeighbourMap,
    bias: Option<&[f32]>,
    chunk_rows: usize,
    product: impl Fn(usize, &[f32], usize, &mut [f32]) -> Result<(), String> + Sync,
) -> Result<Vec<f32>, String> {
    let n = map.num_rows;
    if feats.len() != n * c_in {
        return Err(format!("sparse conv: feats has {} values, expected {n}×{c_in}", feats.len()));
    }
    if let Some(b) = bias {
        if b.len() != c_out {
            return Err(format!("sparse conv: bias has {} values, expected {c_out}", b.len()));
        }
    }
    let mut out = vec![0f32; n * c_out];
    if n == 0 {
        return Ok(out);
    }
    out.par_chunks_mut(chunk_rows * c_out).enumerate().try_for_each_init(
        || (Vec::new(), Vec::new()),
        |(gathered, prod): &mut (Vec<f32>, Vec<f32>), (ci, out_chunk)| -> Result<(), String> {
            let row0 = ci * chunk_rows;
            let rows = out_chunk.len() / c_out;
            for (o, pairs) in map.pairs.iter().enumerate() {
                // Pairs are sorted by out_row: find this chunk's slice.
                let lo = pairs.partition_point(|p| (p.0 as usize) < row0);
                let hi = pairs.partition_point(|p| (p.0 as usize) < row0 + rows);
                let sel = &pairs[lo..hi];
                if sel.is_empty() {
                    continue;
                }
                gathered.clear();
                for &(_, src) in sel {
                    gathered.extend_from_slice(&feats[src as usize * c_in..][..c_in]);
                }
                prod.clear();
                prod.resize(sel.len() * c_out, 0f32);
                product(o, gathered, sel.len(), prod)?;
                for (src, &(dst, _)) in prod.chunks_exact(c_out).zip(sel) {
                    let row = &mut out_chunk[(dst as usize - row0) * c_out..][..c_out];
                    for (a, &b) in row.iter_mut().zip(src) {
                        *a += b;
                    }
                }
            }
            if let Some(b) = bias {
                for row in out_chunk.chunks_exact_mut(c_out) {
                    for (a, &bb) in row.iter_mut().zip(b) {
                        *a += bb;
                    }
                }
            }
            Ok(())
        },
    )?;
    Ok(out)
}

/// A submanifold conv weight packed once for recon's GEMM kernels: one
/// `[C_in, C_out]` right operand per kernel offset, in the layer's format
/// (bf16 runs the dot-product kernels where the CPU has them).
#[derive(Clone, Debug)]
pub struct PackedSparseWeight {
    taps: Vec<PackedMatrix>,
    c_in: usize,
    c_out: usize,
}

impl PackedSparseWeight {
    /// Pack a weight in spconv's layout `[c_out, kernel_volume, c_in]`.
    pub fn new(weight: &[f32], c_out: usize, kernel_volume: usize, c_in: usize, format: WeightFormat) -> Result<Self, String> {
        if weight.len() != c_out * kernel_volume * c_in || c_out == 0 || c_in == 0 || kernel_volume == 0 {
            return Err(format!("sparse conv: weight has {} values, expected {c_out}×{kernel_volume}×{c_in}", weight.len()));
        }
        // Row k of panel p of tap i is W[p·NR + j, i, k] for the panel's columns j.
        let taps = PackedMatrix::pack_many(kernel_volume, c_in, c_out, format, |k, p, row| {
            for i in 0..kernel_volume {
                for j in 0..NR.min(c_out - p * NR) {
                    row[i * NR + j] = weight[((p * NR + j) * kernel_volume + i) * c_in + k];
                }
            }
        });
        Ok(Self { taps, c_in, c_out })
    }

    /// Number of kernel offsets.
    pub fn kernel_volume(&self) -> usize {
        self.taps.len()
    }

    /// Input channels.
    pub fn c_in(&self) -> usize {
        self.c_in
    }

    /// Output channels.
    pub fn c_out(&self) -> usize {
        self.c_out
    }

    /// Storage format of the packed taps.
    pub fn format(&self) -> WeightFormat {
        self.taps[0].format()
    }

    /// Bytes held by the packed taps.
    pub fn bytes(&self) -> usize {
        self.taps.iter().map(PackedMatrix::bytes).sum()
    }
}

/// Output rows per task of [`submanifold_conv3d_packed`]: enough tasks to
/// balance the pool, at most [`CHUNK_ROWS`] (each tap's weights are streamed
/// once per task, so longer tasks reuse them more).
fn packed_chunk_rows(n: usize) -> usize {
    let threads = rayon::current_num_threads().max(1);
    n.div_ceil(4 * threads).clamp(32, CHUNK_ROWS)
}

/// [`submanifold_conv3d`] on recon's packed GEMM kernels (`isa`, the weight's
/// format). Output rows are split into tasks; per task and kernel offset, the
/// offset's input rows are gathered, multiplied by the tap on the task's
/// thread, and added into their output rows; then the bias. Each output row
/// sums its offsets in offset order and the GEMM's rows do not depend on how
/// they are grouped, so the result does not depend on the thread count (which
/// sets the task size).
pub fn submanifold_conv3d_packed(
    isa: Isa,
    feats: &[f32],
    map: &NeighbourMap,
    weight: &PackedSparseWeight,
    bias: Option<&[f32]>,
) -> Result<Vec<f32>, String> {
    let (c_in, c_out) = (weight.c_in, weight.c_out);
    if weight.kernel_volume() != map.kernel_volume() {
        return Err(format!("sparse conv: weight has {} offsets, the neighbour map {}", weight.kernel_volume(), map.kernel_volume()));
    }
    if !isa.supported() {
        return Err(format!("sparse conv: instruction set {} is not supported by this CPU", isa.name()));
    }
    conv_by_chunks(feats, c_in, c_out, map, bias, packed_chunk_rows(map.num_rows), |o, gathered, m, prod| {
        kgemm::gemm_on_this_thread(isa, gathered, m, c_in, &weight.taps[o], None, Activation::None, prod, c_out)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::test_rng::Lcg;

    /// Naive dense conv3d with zero padding (k/2), cross-correlation,
    /// torch weight layout [c_out, c_in, k, k, k]. x is [c_in, s, s, s].
    fn dense_conv3d(x: &[f32], c_in: usize, s: usize, w: &[f32], b: &[f32], c_out: usize, k: usize) -> Vec<f32> {
        let r = (k / 2) as isize;
        let mut out = vec![0f32; c_out * s * s * s];
        for co in 0..c_out {
            for xx in 0..s {
                for yy in 0..s {
                    for zz in 0..s {
                        let mut acc = b[co] as f64;
                        for ci in 0..c_in {
                            for i in 0..k {
                                for j in 0..k {
                                    for l in 0..k {
                                        let (px, py, pz) =
                                            (xx as isize + i as isize - r, yy as isize + j as isize - r, zz as isize + l as isize - r);
                                        if px < 0 || py < 0 || pz < 0 || px >= s as isize || py >= s as isize || pz >= s as isize {
                                            continue;
                                        }
                                        let xv = x[((ci * s + px as usize) * s + py as usize) * s + pz as usize];
                                        let wv = w[(((co * c_in + ci) * k + i) * k + j) * k + l];
                                        acc += xv as f64 * wv as f64;
                                    }
                                }
                            }
                        }
                        out[((co * s + xx) * s + yy) * s + zz] = acc as f32;
                    }
                }
            }
        }
        out
    }

    /// Torch layout [c_out, c_in, k, k, k] → spconv layout [c_out, k, k, k, c_in].
    fn to_spconv(w: &[f32], c_in: usize, c_out: usize, k: usize) -> Vec<f32> {
        let kv = k * k * k;
        let mut o = vec![0f32; w.len()];
        for co in 0..c_out {
            for ci in 0..c_in {
                for t in 0..kv {
                    o[(co * kv + t) * c_in + ci] = w[(co * c_in + ci) * kv + t];
                }
            }
        }
        o
    }

    /// Compare sparse conv with the dense reference at the active sites of
    /// `occupancy` (per batch item), inputs zero elsewhere.
    fn check_against_dense(s: usize, c_in: usize, c_out: usize, k: usize, occupancy: &[Vec<bool>], seed: u64) {
        let mut rng = Lcg(seed);
        let kv = k * k * k;
        let w: Vec<f32> = (0..c_out * c_in * kv).map(|_| rng.next()).collect();
        let b: Vec<f32> = (0..c_out).map(|_| rng.next()).collect();
        let ws = to_spconv(&w, c_in, c_out, k);
        let mut coords = Vec::new();
        let mut feats = Vec::new();
        let mut dense_in = Vec::new();
        for (bi, occ) in occupancy.iter().enumerate() {
            let mut x = vec![0f32; c_in * s * s * s];
            for v in 0..s * s * s {
                if occ[v] {
                    let (xx, yy, zz) = (v / (s * s), (v / s) % s, v % s);
                    coords.push([bi as i32, xx as i32, yy as i32, zz as i32]);
                    for ci in 0..c_in {
                        let f = rng.next();
                        x[ci * s * s * s + v] = f;
                        feats.push(f);
                    }
                }
            }
            dense_in.push(x);
        }
        let map = NeighbourMap::submanifold(&coords, k).unwrap();
        let got = submanifold_conv3d(&feats, c_in, &map, &ws, Some(&b), c_out).unwrap();
        let mut max = 0f32;
        for (bi, x) in dense_in.iter().enumerate() {
            let want = dense_conv3d(x, c_in, s, &w, &b, c_out, k);
            for (row, c) in coords.iter().enumerate() {
                if c[0] as usize != bi {
                    continue;
                }
                let v = (c[1] as usize * s + c[2] as usize) * s + c[3] as usize;
                for co in 0..c_out {
                    max = max.max((got[row * c_out + co] - want[co * s * s * s + v]).abs());
                }
            }
        }
        assert!(max < 1e-4, "max abs diff {max}");
        // The packed kernels, every ISA this CPU runs, f32 weights: the same sums.
        for isa in Isa::ALL.into_iter().filter(|i| i.supported()) {
            let packed = PackedSparseWeight::new(&ws, c_out, kv, c_in, WeightFormat::F32).unwrap();
            let fast = submanifold_conv3d_packed(isa, &feats, &map, &packed, Some(&b)).unwrap();
            let d = fast.iter().zip(&got).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
            assert!(d < 1e-4, "{}: packed kernel differs from the reference by {d}", isa.name());
        }
    }

    #[test]
    fn full_grid_matches_dense_conv() {
        let s = 5;
        let occ = vec![vec![true; s * s * s]; 2];
        check_against_dense(s, 3, 5, 3, &occ, 1);
    }

    #[test]
    fn random_sparse_patterns_match_dense_conv() {
        let s = 7;
        let mut rng = Lcg(42);
        for (seed, density) in [(2u64, 0.15f32), (3, 0.5), (4, 0.9)] {
            let occ: Vec<Vec<bool>> = (0..2).map(|_| (0..s * s * s).map(|_| (rng.next() + 1.0) / 2.0 < density).collect()).collect();
            check_against_dense(s, 7, 5, 3, &occ, seed);
        }
    }

    #[test]
    fn kernel_size_one_is_per_voxel_linear() {
        let s = 4;
        let mut rng = Lcg(9);
        let occ: Vec<Vec<bool>> = (0..2).map(|_| (0..s * s * s).map(|_| rng.next() > 0.0).collect()).collect();
        check_against_dense(s, 5, 3, 1, &occ, 5);
    }

    /// Sites of a side-`s` grid in two batch items, each kept where the next draw exceeds `keep_above`.
    fn random_sites(s: i32, rng: &mut Lcg, keep_above: f32) -> Vec<[i32; 4]> {
        let mut coords = Vec::new();
        for b in 0..2 {
            for v in 0..s * s * s {
                if rng.next() > keep_above {
                    coords.push([b, v / (s * s), (v / s) % s, v % s]);
                }
            }
        }
        coords
    }

    #[test]
    fn many_rows_span_chunks_and_are_thread_count_independent() {
        // > CHUNK_ROWS rows so several chunks run in parallel.
        let mut rng = Lcg(7);
        let coords = random_sites(12, &mut rng, -0.2);
        let (c_in, c_out) = (9, 11);
        let feats: Vec<f32> = (0..coords.len() * c_in).map(|_| rng.next()).collect();
        let w: Vec<f32> = (0..c_out * 27 * c_in).map(|_| rng.next()).collect();
        let map = NeighbourMap::submanifold(&coords, 3).unwrap();
        let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let three = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let a = one.install(|| submanifold_conv3d(&feats, c_in, &map, &w, None, c_out).unwrap());
        let b = three.install(|| submanifold_conv3d(&feats, c_in, &map, &w, None, c_out).unwrap());
        assert_eq!(a, b);
        // Spot-check one row against a direct sum.
        let hash = CoordHash::new(&coords);
        let row = coords.len() / 2;
        let c = coords[row];
        for co in 0..c_out {
            let mut acc = 0f64;
            for o in 0..27 {
                let (i, j, l) = (o / 9, (o / 3) % 3, o % 3);
                if let Some(src) = hash.get([c[0], c[1] + i as i32 - 1, c[2] + j as i32 - 1, c[3] + l as i32 - 1]) {
                    for ci in 0..c_in {
                        acc += feats[src as usize * c_in + ci] as f64 * w[(co * 27 + o) * c_in + ci] as f64;
                    }
                }
            }
            assert!((acc as f32 - a[row * c_out + co]).abs() < 1e-4);
        }
    }

    #[test]
    fn packed_kernel_is_thread_count_independent_and_bf16_close() {
        // Rows enough for several tasks, whose size differs between 1 and 3 threads.
        let mut rng = Lcg(11);
        let coords = random_sites(10, &mut rng, -0.6);
        let (c_in, c_out) = (13, 40);
        let feats: Vec<f32> = (0..coords.len() * c_in).map(|_| rng.next()).collect();
        let w: Vec<f32> = (0..c_out * 27 * c_in).map(|_| rng.next()).collect();
        let bias: Vec<f32> = (0..c_out).map(|_| rng.next()).collect();
        let map = NeighbourMap::submanifold(&coords, 3).unwrap();
        let reference = submanifold_conv3d(&feats, c_in, &map, &w, Some(&bias), c_out).unwrap();
        let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let three = rayon::ThreadPoolBuilder::new().num_threads(3).build().unwrap();
        let n = coords.len();
        assert!(one.install(|| packed_chunk_rows(n)) > three.install(|| packed_chunk_rows(n)), "{n} rows");
        let scale = reference.iter().fold(0f32, |m, v| m.max(v.abs()));
        for isa in Isa::ALL.into_iter().filter(|i| i.supported()) {
            for (format, tol) in [(WeightFormat::F32, 1e-5), (WeightFormat::Bf16, 2e-2), (WeightFormat::F16, 2e-2)] {
                let packed = PackedSparseWeight::new(&w, c_out, 27, c_in, format).unwrap();
                assert_eq!(packed.format(), format);
                let a = one.install(|| submanifold_conv3d_packed(isa, &feats, &map, &packed, Some(&bias)).unwrap());
                let b = three.install(|| submanifold_conv3d_packed(isa, &feats, &map, &packed, Some(&bias)).unwrap());
                assert!(a == b, "{} {}: 1 and 3 threads differ", isa.name(), format.name());
                let d = a.iter().zip(&reference).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
                assert!(d <= tol * scale, "{} {}: max diff {d} against the reference (scale {scale})", isa.name(), format.name());
            }
        }
        // A weight or bias of the wrong size is refused, naming what was expected.
        assert!(PackedSparseWeight::new(&w[1..], c_out, 27, c_in, WeightFormat::F32).unwrap_err().contains("expected"));
        let packed = PackedSparseWeight::new(&w, c_out, 27, c_in, WeightFormat::F32).unwrap();
        assert!(submanifold_conv3d_packed(Isa::Portable, &feats, &map, &packed, Some(&bias[1..])).is_err());
        assert!(submanifold_conv3d_packed(Isa::Portable, &feats[1..], &map, &packed, None).is_err());
    }

    #[test]
    fn rejects_bad_shapes() {
        let coords = vec![[0, 0, 0, 0]];
        assert!(NeighbourMap::submanifold(&coords, 2).is_err());
        let map = NeighbourMap::submanifold(&coords, 3).unwrap();
        assert!(submanifold_conv3d(&[1.0, 2.0], 3, &map, &[0.0; 27 * 3], None, 1).is_err());
    }
}
