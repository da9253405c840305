//! The benchmarks of `recon bench`: kernel throughput against the measured
//! peak of each instruction set, per-module forward time and peak memory at
//! full size on random weights, an end-to-end object, the bf16/f16-versus-f32
//! error of each stage, the shape fit, `recon synth` throughput and the cost
//! of a training step. Results are plain rows (serialisable to JSON); the CLI
//! prints them as tables.
//!
//! Timings on a shared machine are noisy: every row records the 1-minute
//! load average at the time it was taken.

use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device, Tensor};
use serde::Serialize;

use crate::engine::pipeline::{ObjectInputs, Pipeline, RunOptions, Stages, ViewInput, Weights};
use crate::model::config::{ModuleKey, RecGenConfig};
use crate::model::nn::fast::{Compute, Precision};
use crate::model::sparse::SparseTensor;
use crate::rng::SeededRng;
use crate::tools::upstream::rel_errors;
use crate::util::memory::{peak_rss_mib, reset_peak_rss};
use crate::weights::registry;
use crate::Result;
use recon_kernels::attention::{flash_attention, AttnPrecision, AttnSpec, HeadLayout, Segment};
use recon_kernels::gemm::{gemm, PackedMatrix, WeightFormat};
use recon_kernels::isa::Isa;
use recon_kernels::peak::{measure_peak_gflops, PeakKind};
use recon_kernels::vecmath::Activation;

/// 1-minute load average (Linux), recorded with every measurement.
pub fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg").ok()?.split_whitespace().next()?.parse().ok()
}

/// The machine a report was taken on.
#[derive(Debug, Clone, Serialize)]
pub struct MachineInfo {
    pub cpu: String,
    pub threads: usize,
    pub best_isa: &'static str,
    /// Where bf16 weights run: `avx512bf16` (`vdpbf16ps`) only where it beats f32 FMA.
    pub bf16_isa: &'static str,
    pub supported_isas: Vec<&'static str>,
    pub load_average: Option<f64>,
    /// `buffer cache` when large buffers are reused by size
    /// (`util::LargeBufferCache`, the CLI's allocator), `heap reuse` when
    /// glibc keeps freed memory (`util::keep_freed_memory`), else `system`.
    pub allocator: &'static str,
}

impl MachineInfo {
    pub fn detect() -> Self {
        let cpu = std::fs::read_to_string("/proc/cpuinfo")
            .ok()
            .and_then(|s| s.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split(':').nth(1)).map(|v| v.trim().to_string()))
            .unwrap_or_else(|| "unknown".into());
        Self {
            cpu,
            threads: rayon::current_num_threads(),
            best_isa: Isa::best().name(),
            bf16_isa: recon_kernels::peak::bf16_isa().name(),
            supported_isas: Isa::all_supported().into_iter().map(|i| i.name()).collect(),
            load_average: load_average(),
            allocator: if crate::util::buffer_cache_active() {
                "buffer cache"
            } else if crate::util::freed_memory_kept() {
                "heap reuse"
            } else {
                "system"
            },
        }
    }
}

/// Measured multiply-accumulate peak of one instruction set.
#[derive(Debug, Clone, Serialize)]
pub struct PeakRow {
    pub isa: &'static str,
    pub kind: &'static str,
    pub gflops: f64,
    pub load_average: Option<f64>,
}

/// Every supported instruction set's f32 FMA peak, and the bf16 dot-product peak where available.
pub fn measure_peaks() -> Vec<PeakRow> {
    let mut rows = Vec::new();
    for isa in Isa::all_supported() {
        for (kind, name) in [(PeakKind::F32, "f32 fma"), (PeakKind::Bf16, "bf16 dot")] {
            let iters = if isa == Isa::Portable { 200_000 } else { 4_000_000 };
            if let Some(g) = measure_peak_gflops(isa, kind, iters, 3) {
                rows.push(PeakRow { isa: isa.name(), kind: name, gflops: g, load_average: load_average() });
            }
        }
    }
    rows
}

/// The peak a GEMM in `format` on `isa` is measured against: the bf16 dot
/// product for bf16 weights on AVX512-BF16, else the f32 FMA of that ISA.
pub fn reference_peak(peaks: &[PeakRow], isa: Isa, format: WeightFormat) -> Option<f64> {
    let kind = if format == WeightFormat::Bf16 && isa == Isa::Avx512Bf16 { "bf16 dot" } else { "f32 fma" };
    peaks.iter().find(|p| p.isa == isa.name() && p.kind == kind).map(|p| p.gflops)
}

/// The reference peak re-measured right before and after `f` (mean of the
/// two), so efficiency is judged against what the shared machine gave at
/// that moment rather than at the start of the run.
fn with_adjacent_peak<R>(isa: Isa, format: WeightFormat, f: impl FnOnce() -> R) -> (R, Option<f64>) {
    let kind = if format == WeightFormat::Bf16 && isa == Isa::Avx512Bf16 { PeakKind::Bf16 } else { PeakKind::F32 };
    let iters = if isa == Isa::Portable { 100_000 } else { 2_000_000 };
    let before = measure_peak_gflops(isa, kind, iters, 2);
    let r = f();
    let after = measure_peak_gflops(isa, kind, iters, 2);
    (r, before.zip(after).map(|(a, b)| 0.5 * (a + b)))
}

#[derive(Debug, Clone, Serialize)]
pub struct GemmRow {
    pub what: String,
    pub m: usize,
    pub k: usize,
    pub n: usize,
    pub isa: &'static str,
    pub format: &'static str,
    pub seconds: f64,
    pub gflops: f64,
    /// Fraction of the peak of the instruction set measured around this row.
    pub efficiency: Option<f64>,
    /// That peak (GFLOP/s).
    pub peak_gflops: Option<f64>,
    pub load_average: Option<f64>,
}

fn best_of<F: FnMut()>(reps: usize, mut f: F) -> f64 {
    f();
    (0..reps.max(1))
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

fn lcg_vec(n: usize, seed: u64) -> Vec<f32> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) - 0.5
        })
        .collect()
}

/// The model's linear shapes at the SS-flow guided step (M = 2 × 4098 tokens),
/// plus the 4096³ reference, for each format on the best ISA (and the
/// portable path on one shape), and stock candle's f32 matmul at 4096³.
pub fn bench_gemm(peaks: &[PeakRow], reps: usize, quick: bool) -> Result<Vec<GemmRow>> {
    let isa = Isa::best();
    let m = 2 * 4098;
    let mut shapes: Vec<(&str, usize, usize, usize)> = vec![
        ("qkv 1024→3072", m, 1024, 3072),
        ("to_out/q 1024→1024", m, 1024, 1024),
        ("mlp.0 1024→4096", m, 1024, 4096),
        ("mlp.2 4096→1024", m, 4096, 1024),
        ("4096³", 4096, 4096, 4096),
    ];
    if quick {
        shapes.retain(|s| s.0.starts_with("qkv") || s.0.starts_with("mlp.2"));
    }
    let mut rows = Vec::new();
    for &(what, m, k, n) in &shapes {
        let a = lcg_vec(m * k, 1);
        let w = lcg_vec(n * k, 2);
        let mut c = vec![0f32; m * n];
        for format in [WeightFormat::F32, WeightFormat::Bf16, WeightFormat::F16] {
            let b = PackedMatrix::from_linear_weight(&w, n, k, format).map_err(crate::Error::msg)?;
            let mut isas = vec![isa];
            if what.starts_with("qkv") && isa != Isa::Portable && !quick {
                isas.push(Isa::Portable);
            }
            for run_isa in isas {
                let (s, peak) = with_adjacent_peak(run_isa, format, || {
                    best_of(if run_isa == Isa::Portable { 0 } else { reps }, || {
                        gemm(run_isa, &a, m, k, &b, None, Activation::None, &mut c, n).expect("gemm");
                    })
                });
                let gflops = 2.0 * (m * n * k) as f64 / s / 1e9;
                let peak = peak.or_else(|| reference_peak(peaks, run_isa, format));
                let efficiency = peak.map(|p| gflops / p);
                rows.push(GemmRow {
                    what: what.into(),
                    m,
                    k,
                    n,
                    isa: run_isa.name(),
                    format: format.name(),
                    seconds: s,
                    gflops,
                    efficiency,
                    peak_gflops: peak,
                    load_average: load_average(),
                });
            }
        }
    }
    if !quick {
        // Stock candle (gemm crate) for the comparison row.
        let (m, k, n) = (4096, 4096, 4096);
        let a = Tensor::from_vec(lcg_vec(m * k, 1), (m, k), &Device::Cpu)?;
        let b = Tensor::from_vec(lcg_vec(k * n, 2), (k, n), &Device::Cpu)?;
        let (s, peak) = with_adjacent_peak(isa, WeightFormat::F32, || {
            best_of(reps, || {
                a.matmul(&b).expect("candle matmul");
            })
        });
        let gflops = 2.0 * (m * n * k) as f64 / s / 1e9;
        let peak = peak.or_else(|| reference_peak(peaks, isa, WeightFormat::F32));
        let efficiency = peak.map(|p| gflops / p);
        rows.push(GemmRow {
            what: "4096³ stock candle".into(),
            m,
            k,
            n,
            isa: "candle",
            format: "f32",
            seconds: s,
            gflops,
            efficiency,
            peak_gflops: peak,
            load_average: load_average(),
        });
    }
    Ok(rows)
}

#[derive(Debug, Clone, Serialize)]
pub struct AttentionRow {
    pub what: String,
    pub batch: usize,
    pub heads: usize,
    pub lq: usize,
    pub lk: usize,
    pub precision: &'static str,
    pub isa: &'static str,
    pub seconds: f64,
    pub gflops: f64,
    pub efficiency: Option<f64>,
    pub peak_gflops: Option<f64>,
    pub load_average: Option<f64>,
}

/// Fused attention at the SS-flow shapes: self-attention over 4098 tokens and
/// cross-attention to 1374 condition tokens, batch 2, 16 heads of 64.
pub fn bench_attention(peaks: &[PeakRow], reps: usize) -> Result<Vec<AttentionRow>> {
    let isa = Isa::best();
    let (b, h, d) = (2usize, 16usize, 64usize);
    let c = h * d;
    let mut rows = Vec::new();
    for &(what, lq, lk) in &[("self 4098", 4098usize, 4098usize), ("cross 4098×1374", 4098, 1374)] {
        let q = lcg_vec(b * lq * c, 3);
        let kv = lcg_vec(b * lk * 2 * c, 4);
        let segs: Vec<Segment> = (0..b).map(|i| Segment { q: i * lq..(i + 1) * lq, kv: i * lk..(i + 1) * lk }).collect();
        let mut out = vec![0f32; b * lq * c];
        for precision in [AttnPrecision::F32, AttnPrecision::Bf16] {
            let spec = AttnSpec {
                heads: h,
                head_dim: d,
                scale: 0.125,
                q: HeadLayout::new(c, 0),
                k: HeadLayout::new(2 * c, 0),
                v: HeadLayout::new(2 * c, c),
                out: HeadLayout::new(c, 0),
                precision,
            };
            let format = if precision == AttnPrecision::Bf16 { WeightFormat::Bf16 } else { WeightFormat::F32 };
            let (s, peak) = with_adjacent_peak(isa, format, || {
                best_of(reps, || flash_attention(isa, &spec, &q, &kv, &kv, &segs, &mut out).expect("attention"))
            });
            let gflops = 4.0 * (b * h * lq * lk * d) as f64 / s / 1e9;
            let peak = peak.or_else(|| reference_peak(peaks, isa, format));
            let efficiency = peak.map(|p| gflops / p);
            let pname = if precision == AttnPrecision::Bf16 { "bf16" } else { "f32" };
            rows.push(AttentionRow {
                what: what.into(),
                batch: b,
                heads: h,
                lq,
                lk,
                precision: pname,
                isa: isa.name(),
                seconds: s,
                gflops,
                efficiency,
                peak_gflops: peak,
                load_average: load_average(),
            });
        }
    }
    Ok(rows)
}

/// One module at full size: build (random weights, packed) and one forward.
#[derive(Debug, Clone, Serialize)]
pub struct ModuleRow {
    pub module: String,
    pub input: String,
    pub precision: String,
    pub build_seconds: f64,
    pub forward_seconds: f64,
    /// VmHWM over build + forward, the high-water mark reset before the build.
    pub peak_rss_mib: Option<f64>,
    pub packed_weights_mib: Option<f64>,
    pub load_average: Option<f64>,
}

impl From<&ModuleRow> for crate::tools::upstream::TimingRow {
    fn from(m: &ModuleRow) -> Self {
        Self {
            module: m.module.clone(),
            precision: m.precision.clone(),
            forward_seconds: m.forward_seconds,
            peak_rss_mib: m.peak_rss_mib,
            load_average: m.load_average,
        }
    }
}

/// A voxel shell of radius `r` (thickness 2) centred in a `res`³ grid, batch index `b`.
pub fn shell_coords(res: i32, r: f64, b: i32) -> Vec<[i32; 4]> {
    let c = res as f64 / 2.0;
    let mut out = Vec::new();
    for x in 0..res {
        for y in 0..res {
            for z in 0..res {
                let d = ((x as f64 + 0.5 - c).powi(2) + (y as f64 + 0.5 - c).powi(2) + (z as f64 + 0.5 - c).powi(2)).sqrt();
                if (d - r).abs() < 1.0 {
                    out.push([b, x, y, z]);
                }
            }
        }
    }
    out
}

/// The realistic stage-2 voxel set: the surface voxels of a `recon synth`
/// object (a bottle, fixed seed) at `res`³, as the SS decoder's occupancy of
/// a real object looks (TRELLIS voxelises mesh surfaces). The mesh is centred
/// and scaled so its longest side spans 95 % of the grid, and every triangle
/// is sampled on a barycentric lattice finer than half a voxel. Sorted
/// `(x, y, z)`, as the pipeline's argwhere order; deterministic.
pub fn object_voxels(res: usize) -> Vec<[i32; 3]> {
    use crate::synth::objects::{Kind, Object};
    let mesh = Object::random(Kind::Bottle, &mut SeededRng::new(7)).mesh();
    let (lo, hi) = crate::mesh::primitives::bounds(&mesh);
    let extent = (0..3).map(|i| hi[i] - lo[i]).fold(0.0, f64::max).max(f64::MIN_POSITIVE);
    let scale = 0.95 * res as f64 / extent;
    let to_grid = |v: &[f32; 3]| -> [f64; 3] { std::array::from_fn(|i| (v[i] as f64 - 0.5 * (lo[i] + hi[i])) * scale + 0.5 * res as f64) };
    let mut out = Vec::new();
    for f in &mesh.faces {
        let [a, b, c] = f.map(|i| to_grid(&mesh.vertices[i as usize]));
        let edge = |p: &[f64; 3], q: &[f64; 3]| (0..3).map(|i| (p[i] - q[i]).powi(2)).sum::<f64>().sqrt();
        let n = (2.0 * edge(&a, &b).max(edge(&b, &c)).max(edge(&c, &a))).ceil().max(1.0) as usize;
        for i in 0..=n {
            for j in 0..=n - i {
                let (u, v) = (i as f64 / n as f64, j as f64 / n as f64);
                let p: [i32; 3] = std::array::from_fn(|k| (a[k] + u * (b[k] - a[k]) + v * (c[k] - a[k])).floor() as i32);
                if p.iter().all(|&x| (0..res as i32).contains(&x)) {
                    out.push(p);
                }
            }
        }
    }
    out.sort_unstable();
    out.dedup();
    out
}

/// Distinct cells of `voxels` at `1/factor` resolution: the SLat flow's
/// transformer tokens per item (its io stages downsample by `patch_size`).
pub fn coarse_tokens(voxels: &[[i32; 3]], factor: usize) -> usize {
    let f = factor.max(1) as i32;
    let mut c: Vec<[i32; 3]> = voxels.iter().map(|v| v.map(|x| x.div_euclid(f))).collect();
    c.sort_unstable();
    c.dedup();
    c.len()
}

/// A synthetic view at DINO size `s`: smooth image, disc mask, sphere-cap pointmap.
pub fn synthetic_view(s: usize, shift: f32) -> ViewInput {
    disc_view(s, shift, |u, v, ch| ((3.0 * u + 2.0 * v + ch as f32).sin() * 0.4 + 0.5 - 0.45) / 0.225)
}

/// A view of side `s` whose normalised pixel (u, v, channel) is `colour(u, v, ch)`,
/// with a disc mask (radius 0.35·s, centre moved by `shift`·s along x) and, inside
/// it, the pointmap of a sphere of radius 0.5 centred 1.5 in front of the camera
/// (zeros outside).
pub fn disc_view(s: usize, shift: f32, colour: impl Fn(f32, f32, usize) -> f32) -> ViewInput {
    let c = s as f32 * (0.5 + shift);
    let r = s as f32 * 0.35;
    let mut px = vec![0f32; 3 * s * s];
    let mut pm = vec![0f32; 3 * s * s];
    let mut mk = vec![0f32; s * s];
    for y in 0..s {
        for x in 0..s {
            let (u, v) = (x as f32 / s as f32, y as f32 / s as f32);
            for ch in 0..3 {
                px[(ch * s + y) * s + x] = colour(u, v, ch);
            }
            let (dx, dy) = ((x as f32 + 0.5 - c) / r, (y as f32 + 0.5 - s as f32 * 0.5) / r);
            let d2 = dx * dx + dy * dy;
            if d2 <= 1.0 {
                mk[y * s + x] = 1.0;
                let p = [dx * 0.5, dy * 0.5, 1.5 - 0.5 * (1.0 - d2).sqrt()];
                for ch in 0..3 {
                    pm[(ch * s + y) * s + x] = p[ch];
                }
            }
        }
    }
    let t = |v: Vec<f32>, c: usize| Tensor::from_vec(v, (1, c, s, s), &Device::Cpu).expect("view tensor");
    ViewInput { pixels: t(px, 3), pointmap: t(pm, 3), mask: t(mk, 1) }
}

/// Which full-size modules [`bench_modules`] runs.
pub const MODULES: [ModuleKey; 6] = ModuleKey::ALL;

/// Deterministic inputs of one module's forward, as upstream's shapes: DINOv2
/// one 518² view; SS flow batch 2 (a guided step) with 4096 + 2 pose tokens
/// and 1374 condition tokens; SS decoder one latent; SLat flow batch 2 on a
/// 64³ voxel shell (~14k voxels) with 1371 condition tokens; decoders on the
/// same shell.
pub struct ModuleInputs {
    pub pixels: Tensor,
    pub ss_state: Vec<Tensor>,
    pub ss_t: Tensor,
    pub ss_cond: Tensor,
    pub ss_latent: Tensor,
    pub slat_x: SparseTensor,
    pub slat_t: Tensor,
    pub slat_cond: Tensor,
    pub slat: SparseTensor,
}

impl ModuleInputs {
    pub fn new(arch: &RecGenConfig) -> Result<Self> {
        let dev = Device::Cpu;
        let mut rng = SeededRng::new(11);
        let dino = &arch.args.image_cond_model;
        let ss = arch.ss_flow_config();
        let s = dino.img_size;
        let pixels = rng.randn(&[1, 3, s, s], &dev)?;
        let r = ss.resolution;
        let pc = ss.pose_channels().unwrap_or(10);
        let mut ss_state = vec![rng.randn(&[2, ss.in_channels, r, r, r], &dev)?];
        if ss.pose_channels().is_some() {
            ss_state.push(rng.randn(&[2, ss.num_pose_tokens, pc], &dev)?);
        }
        let ss_cond = (rng.randn(&[2, 1374, ss.cond_channels], &dev)? * 0.5)?;
        let ss_latent = rng.randn(&[1, ss.in_channels, r, r, r], &dev)?;
        let slat_cfg = &arch.args.slat_flow;
        let res = slat_cfg.resolution as i32;
        let one = shell_coords(res, res as f64 * 0.375, 0);
        let n = one.len();
        let two: Vec<[i32; 4]> = one.iter().copied().chain(one.iter().map(|c| [1, c[1], c[2], c[3]])).collect();
        let f = rng.randn(&[n, slat_cfg.in_channels], &dev)?;
        let slat_x = SparseTensor::new(two, Tensor::cat(&[&f, &f], 0)?, 2)?;
        let slat_cond = (rng.randn(&[2, 1371, slat_cfg.cond_channels], &dev)? * 0.5)?;
        let slat = SparseTensor::new(one, rng.randn(&[n, slat_cfg.out_channels], &dev)?, 1)?;
        Ok(Self {
            pixels,
            ss_state,
            ss_t: Tensor::new(&[750f32, 750.0], &dev)?,
            ss_cond,
            ss_latent,
            slat_x,
            slat_t: Tensor::new(&[750f32, 750.0], &dev)?,
            slat_cond,
            slat,
        })
    }

    fn describe(&self, key: ModuleKey) -> String {
        match key {
            ModuleKey::ImageCondModel => format!("1 view {:?}", self.pixels.dims()),
            ModuleKey::SsFlow => format!(
                "batch 2 (guided step), {} + pose tokens, cond {:?}",
                self.ss_state[0].elem_count() / self.ss_state[0].dims()[0] / self.ss_state[0].dims()[1],
                self.ss_cond.dims()
            ),
            ModuleKey::SsDecoder => format!("latent {:?}", self.ss_latent.dims()),
            ModuleKey::SlatFlow => format!("batch 2 (guided step), {} voxels each, cond {:?}", self.slat.len(), self.slat_cond.dims()),
            _ => format!("{} voxels", self.slat.len()),
        }
    }
}

/// Build module `key` of `arch` with random weights for `compute`.
fn build_and_run(arch: &RecGenConfig, key: ModuleKey, compute: Compute, inputs: &ModuleInputs) -> Result<(f64, f64, Vec<Tensor>)> {
    let cfg = arch.module_args(key)?;
    let label = format!("{}: {key}", arch.name);
    let seed = registry::module_seed(0, key.name());
    let t = Instant::now();
    let vb = registry::random_var_builder(&cfg, seed)?;
    macro_rules! build {
        ($f:path) => {{
            let m = $f(&cfg, vb, &label, compute)?;
            // As the engine's load: the build's temporaries do not recur.
            crate::util::release_cached_buffers();
            m
        }};
    }
    let (build_s, fwd_s, out) = match key {
        ModuleKey::ImageCondModel => {
            let m = build!(registry::build_dinov2);
            let b = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let o = m.recgen_cond(&inputs.pixels)?;
            (b, t.elapsed().as_secs_f64(), vec![o])
        }
        ModuleKey::SsFlow => {
            let m = build!(registry::build_ss_flow);
            let b = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let (v, vp) = m.forward(&inputs.ss_state[0], inputs.ss_state.get(1), &inputs.ss_t, &inputs.ss_cond)?;
            (b, t.elapsed().as_secs_f64(), std::iter::once(v).chain(vp).collect())
        }
        ModuleKey::SsDecoder => {
            let m = build!(registry::build_ss_decoder);
            let b = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let o = m.forward(&inputs.ss_latent)?;
            (b, t.elapsed().as_secs_f64(), vec![o])
        }
        ModuleKey::SlatFlow => {
            let m = build!(registry::build_slat_flow);
            let b = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let o = m.forward(&inputs.slat_x, &inputs.slat_t, &inputs.slat_cond)?;
            (b, t.elapsed().as_secs_f64(), vec![o.feats])
        }
        ModuleKey::SlatDecMesh => {
            let m = build!(registry::build_mesh_decoder);
            let b = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let o = m.forward_feats_fused(&inputs.slat)?;
            (b, t.elapsed().as_secs_f64(), vec![o.feats])
        }
        ModuleKey::SlatDecGs => {
            let m = build!(registry::build_gaussian_decoder);
            let b = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let o = m.forward_feats(&inputs.slat, &mut |_, _| {})?;
            (b, t.elapsed().as_secs_f64(), vec![o])
        }
        other => return Err(crate::Error::msg(format!("bench: `{other}` is a training-only module"))),
    };
    Ok((build_s, fwd_s, out))
}

/// Build and run each of `modules` once per compute; peak RSS per row.
pub fn bench_modules(
    arch_path: &Path,
    modules: &[ModuleKey],
    computes: &[Compute],
    mut on_row: impl FnMut(&ModuleRow),
) -> Result<Vec<ModuleRow>> {
    let arch = RecGenConfig::load(arch_path)?;
    let inputs = ModuleInputs::new(&arch)?;
    let mut rows = Vec::new();
    for &key in modules {
        for &compute in computes {
            reset_peak_rss();
            let base = peak_rss_mib();
            let (build_seconds, forward_seconds, out) = build_and_run(&arch, key, compute, &inputs)?;
            for o in &out {
                let finite = o.flatten_all()?.to_dtype(DType::F32)?.to_vec1::<f32>()?.iter().all(|v| v.is_finite());
                if !finite {
                    return Err(crate::Error::msg(format!("bench: {key} produced non-finite values ({})", compute.describe())));
                }
            }
            let row = ModuleRow {
                module: key.to_string(),
                input: inputs.describe(key),
                precision: compute.describe(),
                build_seconds,
                forward_seconds,
                peak_rss_mib: peak_rss_mib(),
                packed_weights_mib: None,
                load_average: load_average(),
            };
            let _ = base;
            on_row(&row);
            rows.push(row);
        }
    }
    Ok(rows)
}

/// One guided sampler step of a flow at full size (cond + all-zero
/// `neg_cond`, as the pipeline samples), computed in full and on the run's
/// prepared condition.
#[derive(Debug, Clone, Serialize)]
pub struct GuidedRow {
    pub module: String,
    pub input: String,
    pub precision: String,
    /// A guided step computing everything: the condition's keys and values
    /// inside the step, the unconditional cross-attention in full (best of reps).
    pub full_seconds: f64,
    /// Preparing the run's cond and neg_cond, once per sampling run (best of reps).
    pub prepare_seconds: f64,
    /// A guided step on the prepared conditions, with the constant-context
    /// shortcut for the all-zero neg_cond (best of reps).
    pub step_seconds: f64,
    /// The step's velocities against the full step's: max |a−b| / max |b|, cond half.
    pub max_rel_cond: f64,
    /// The same for the unconditional half (the shortcut's float rounding).
    pub max_rel_uncond: f64,
    /// Whether the conditional half has the full step's bits in every repetition.
    pub cond_same_bits: bool,
    pub load_average: Option<f64>,
}

fn same_bits(a: &Tensor, b: &Tensor) -> Result<bool> {
    let bits = |t: &Tensor| -> Result<Vec<u32>> {
        Ok(t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?.iter().map(|v| v.to_bits()).collect())
    };
    Ok(a.dims() == b.dims() && bits(a)? == bits(b)?)
}

/// The SLat-flow input of a guided step on [`object_voxels`] at the flow's
/// resolution: coordinates (batch 0) and seeded noise features.
pub fn object_slat_state(arch: &RecGenConfig) -> Result<(Vec<[i32; 4]>, Tensor)> {
    let cfg = &arch.args.slat_flow;
    let coords: Vec<[i32; 4]> = object_voxels(cfg.resolution).into_iter().map(|[x, y, z]| [0, x, y, z]).collect();
    let feats = SeededRng::new(12).randn(&[coords.len(), cfg.in_channels], &Device::Cpu)?;
    Ok((coords, feats))
}

/// For `ss_flow` and `slat_flow` among `modules`: a guided step computed in
/// full and on the prepared conditions, alternately `reps` times each (best
/// of), on the inputs of [`bench_modules`] (the condition's first item, a
/// zero `neg_cond`); with `object`, the SLat flow runs on [`object_voxels`]
/// instead of the module bench's sphere shell.
pub fn bench_guided(
    arch_path: &Path,
    modules: &[ModuleKey],
    computes: &[Compute],
    reps: usize,
    object: bool,
    mut on_row: impl FnMut(&GuidedRow),
) -> Result<Vec<GuidedRow>> {
    use crate::model::sampler::VelocityModel;
    use crate::model::stage2::slat_flow::SlatVelocity;
    let arch = RecGenConfig::load(arch_path)?;
    let inputs = ModuleInputs::new(&arch)?;
    let mut rows = Vec::new();
    for &key in modules.iter().filter(|k| matches!(k, ModuleKey::SsFlow | ModuleKey::SlatFlow)) {
        for &compute in computes.iter().filter(|c| c.is_fast()) {
            let cfg = arch.module_args(key)?;
            let label = format!("{}: {key}", arch.name);
            let vb = registry::random_var_builder(&cfg, registry::module_seed(0, key.name()))?;
            // One guided step at t = 0.75: (prepare s, step s, velocities).
            let time_step = |m: &dyn VelocityModel, state: &[Tensor], cond: &Tensor, neg: &Tensor, prepared: bool| {
                let t = Instant::now();
                let run = if prepared { m.prepare(cond, Some(neg))? } else { None };
                let prep = t.elapsed().as_secs_f64();
                let t = Instant::now();
                let (c, u) = run.as_deref().unwrap_or(m).velocity_cfg(state, 750.0, cond, neg)?;
                Ok::<_, crate::Error>((prep, t.elapsed().as_secs_f64(), c.into_iter().chain(u).collect::<Vec<_>>()))
            };
            let (mut full_s, mut prep_s, mut step_s) = (f64::INFINITY, f64::INFINITY, f64::INFINITY);
            let mut errs = (0f64, 0f64);
            let mut cond_same_bits = true;
            let mut record = |full: (f64, f64, Vec<Tensor>), short: (f64, f64, Vec<Tensor>)| -> Result<()> {
                full_s = full_s.min(full.1);
                prep_s = prep_s.min(short.0);
                step_s = step_s.min(short.1);
                let half = full.2.len() / 2;
                for (i, (a, b)) in short.2.iter().zip(&full.2).enumerate() {
                    let e = rel_errors(a, b)?.0;
                    if i < half {
                        errs.0 = errs.0.max(e);
                        cond_same_bits &= same_bits(a, b)?;
                    } else {
                        errs.1 = errs.1.max(e);
                    }
                }
                Ok(())
            };
            let input = match key {
                ModuleKey::SsFlow => {
                    let mut m = registry::build_ss_flow(&cfg, vb, &label, compute)?;
                    crate::util::release_cached_buffers();
                    let state: Vec<Tensor> = inputs.ss_state.iter().map(|s| s.narrow(0, 0, 1)).collect::<candle_core::Result<_>>()?;
                    let cond = inputs.ss_cond.narrow(0, 0, 1)?;
                    let neg = cond.zeros_like()?;
                    for _ in 0..reps.max(1) {
                        m.set_shortcuts(false);
                        let full = time_step(&m, &state, &cond, &neg, false)?;
                        m.set_shortcuts(true);
                        record(full, time_step(&m, &state, &cond, &neg, true)?)?;
                    }
                    format!(
                        "{} + pose tokens, cond {:?} and zeros",
                        inputs.ss_state[0].elem_count() / inputs.ss_state[0].dims()[0] / inputs.ss_state[0].dims()[1],
                        cond.dims()
                    )
                }
                _ => {
                    let mut m = registry::build_slat_flow(&cfg, vb, &label, compute)?;
                    crate::util::release_cached_buffers();
                    let (coords, state) = if object {
                        let (c, f) = object_slat_state(&arch)?;
                        (c, [f])
                    } else {
                        (inputs.slat.coords.clone(), [inputs.slat_x.feats.narrow(0, 0, inputs.slat.len())?])
                    };
                    let coords = &coords;
                    let cond = inputs.slat_cond.narrow(0, 0, 1)?;
                    let neg = cond.zeros_like()?;
                    for _ in 0..reps.max(1) {
                        m.set_shortcuts(false);
                        let full = time_step(&SlatVelocity { model: &m, coords }, &state, &cond, &neg, false)?;
                        m.set_shortcuts(true);
                        record(full, time_step(&SlatVelocity { model: &m, coords }, &state, &cond, &neg, true)?)?;
                    }
                    let what = if object { "object surface voxels" } else { "shell voxels" };
                    let tokens =
                        coarse_tokens(&coords.iter().map(|c| [c[1], c[2], c[3]]).collect::<Vec<_>>(), arch.args.slat_flow.patch_size);
                    format!("{} {what} ({tokens} tokens), cond {:?} and zeros", coords.len(), cond.dims())
                }
            };
            let row = GuidedRow {
                module: key.to_string(),
                input,
                precision: compute.describe(),
                full_seconds: full_s,
                prepare_seconds: prep_s,
                step_seconds: step_s,
                max_rel_cond: errs.0,
                max_rel_uncond: errs.1,
                cond_same_bits,
                load_average: load_average(),
            };
            on_row(&row);
            rows.push(row);
        }
    }
    Ok(rows)
}

/// One guided SLat-flow step at full size on the realistic voxel set
/// ([`object_voxels`]), as the sampler runs it (conditions prepared once,
/// shortcuts on), with the kernels' time and FLOPs
/// ([`crate::util::profile`]).
#[derive(Debug, Clone, Serialize)]
pub struct Stage2Row {
    /// The flow profiled: `slat_flow` (section `stage2`) or `ss_flow` (section `stage1`).
    pub module: String,
    pub precision: String,
    /// Occupied voxels at the flow's resolution (the SS flow: its latent grid's cells).
    pub voxels: usize,
    /// Transformer tokens per item.
    pub tokens: usize,
    /// The step (best of the repetitions; profile of that one).
    pub step_seconds: f64,
    /// FLOPs of the step's GEMMs, attention and sparse convolutions,
    /// counted from the operand shapes of each call.
    pub flops: f64,
    /// `flops / step_seconds / 1e9`.
    pub gflops: f64,
    /// The peak of the step's GEMM precision on its ISA (bf16 dot product on
    /// AVX512-BF16, else f32 FMA), measured right before and after the step.
    pub peak_gflops: Option<f64>,
    pub efficiency: Option<f64>,
    /// The transformer blocks alone: seconds, GFLOP/s and share of the peak.
    pub transformer_seconds: f64,
    pub transformer_gflops: f64,
    pub transformer_efficiency: Option<f64>,
    /// The sparse io blocks (input and output ResBlocks), seconds.
    pub io_blocks_seconds: f64,
    /// Exclusive seconds per kind; glue = the step less all of them.
    pub profile: crate::util::profile::Profile,
    pub glue_seconds: f64,
    pub load_average: Option<f64>,
}

/// [`Stage2Row`] of the SLat flow on [`object_slat_state`] for each fast compute.
pub fn bench_stage2(arch_path: &Path, computes: &[Compute], reps: usize, on_row: impl FnMut(&Stage2Row)) -> Result<Vec<Stage2Row>> {
    bench_flow_step(arch_path, ModuleKey::SlatFlow, computes, reps, on_row)
}

/// [`Stage2Row`] of one flow (`ss_flow`: the module bench's first item;
/// `slat_flow`: [`object_slat_state`]) for each fast compute: `reps`
/// profiled guided steps (best of) after preparing the conditions once.
pub fn bench_flow_step(
    arch_path: &Path,
    key: ModuleKey,
    computes: &[Compute],
    reps: usize,
    mut on_row: impl FnMut(&Stage2Row),
) -> Result<Vec<Stage2Row>> {
    use crate::model::sampler::VelocityModel;
    use crate::model::stage2::slat_flow::SlatVelocity;
    use crate::util::profile;
    let arch = RecGenConfig::load(arch_path)?;
    let cfg = arch.module_args(key)?;
    let (state, cond, voxels, tokens, coords) = match key {
        ModuleKey::SlatFlow => {
            let (coords, feats) = object_slat_state(&arch)?;
            let voxels: Vec<[i32; 3]> = coords.iter().map(|c| [c[1], c[2], c[3]]).collect();
            let tokens = coarse_tokens(&voxels, arch.args.slat_flow.patch_size);
            let cond = (SeededRng::new(13).randn(&[1, 1371, arch.args.slat_flow.cond_channels], &Device::Cpu)? * 0.5)?;
            (vec![feats], cond, coords.len(), tokens, coords)
        }
        ModuleKey::SsFlow => {
            let inputs = ModuleInputs::new(&arch)?;
            let state: Vec<Tensor> = inputs.ss_state.iter().map(|s| s.narrow(0, 0, 1)).collect::<candle_core::Result<_>>()?;
            let cells = state[0].elem_count() / state[0].dims()[1];
            let pose_tokens = state.get(1).map_or(0, |p| if p.rank() == 3 { p.dims()[1] } else { 1 });
            (state, inputs.ss_cond.narrow(0, 0, 1)?, cells, arch.args.ss_flow.num_tokens() + pose_tokens, Vec::new())
        }
        _ => return Err(crate::Error::msg(format!("bench: {key} is not a flow"))),
    };
    let neg = cond.zeros_like()?;
    let mut rows = Vec::new();
    for &compute in computes.iter().filter(|c| c.is_fast()) {
        let Some((precision, isa)) = compute.fast_parts() else { continue };
        let vb = registry::random_var_builder(&cfg, registry::module_seed(0, key.name()))?;
        let (ss, slat) = match key {
            ModuleKey::SsFlow => (Some(registry::build_ss_flow(&cfg, vb, &format!("{}: {key}", arch.name), compute)?), None),
            _ => (None, Some(registry::build_slat_flow(&cfg, vb, &format!("{}: {key}", arch.name), compute)?)),
        };
        crate::util::release_cached_buffers();
        let sv = slat.as_ref().map(|m| SlatVelocity { model: m, coords: &coords });
        let v: &dyn VelocityModel = match (&ss, &sv) {
            (Some(m), _) => m,
            (_, Some(v)) => v,
            _ => unreachable!("one of the two flows was built"),
        };
        let run = v.prepare(&cond, Some(&neg))?;
        let model: &dyn VelocityModel = run.as_deref().unwrap_or(v);
        let (best, peak) = with_adjacent_peak(isa, precision.weight_format(), || -> Result<(f64, profile::Profile)> {
            let mut best = (f64::INFINITY, profile::Profile::default());
            for _ in 0..reps.max(1) {
                profile::reset();
                profile::set_enabled(true);
                let t = Instant::now();
                let r = model.velocity_cfg(&state, 750.0, &cond, &neg);
                let s = t.elapsed().as_secs_f64();
                profile::set_enabled(false);
                r?;
                if s < best.0 {
                    best = (s, profile::snapshot());
                }
            }
            profile::reset();
            Ok(best)
        });
        let (step_seconds, p) = best?;
        let flops = p.flops();
        let gflops = flops / step_seconds / 1e9;
        let transformer_gflops = p.transformer_flops / p.transformer_seconds.max(f64::MIN_POSITIVE) / 1e9;
        let row = Stage2Row {
            module: key.name().into(),
            precision: compute.describe(),
            voxels,
            tokens,
            step_seconds,
            flops,
            gflops,
            peak_gflops: peak,
            efficiency: peak.map(|pk| gflops / pk),
            transformer_seconds: p.transformer_seconds,
            transformer_gflops,
            transformer_efficiency: peak.map(|pk| transformer_gflops / pk),
            io_blocks_seconds: p.io_blocks_seconds,
            glue_seconds: (step_seconds - p.kernel_seconds()).max(0.0),
            profile: p,
            load_average: load_average(),
        };
        on_row(&row);
        rows.push(row);
    }
    Ok(rows)
}

/// Error of one stage's output in a precision against the f32 fast path
/// (same weights, same input): `max_rel = max|a−b| / max|b|`,
/// `mean_rel = mean|a−b| / mean|b|`.
#[derive(Debug, Clone, Serialize)]
pub struct PrecisionRow {
    pub module: String,
    pub precision: String,
    pub reference: String,
    pub max_rel: f64,
    pub mean_rel: f64,
    /// SS decoder only: fraction of voxels whose occupancy (logit > 0) differs.
    pub occupancy_flip_fraction: Option<f64>,
    pub occupied_reference: Option<usize>,
}

/// Each module's output in `precisions` against fast f32, full size.
pub fn compare_precisions(
    arch_path: &Path,
    modules: &[ModuleKey],
    precisions: &[Precision],
    mut on_row: impl FnMut(&PrecisionRow),
) -> Result<Vec<PrecisionRow>> {
    let arch = RecGenConfig::load(arch_path)?;
    let inputs = ModuleInputs::new(&arch)?;
    let mut rows = Vec::new();
    for &key in modules {
        let (_, _, reference) = build_and_run(&arch, key, Compute::fast(Precision::F32), &inputs)?;
        for &p in precisions {
            if p == Precision::F32 {
                continue;
            }
            let (_, _, out) = build_and_run(&arch, key, Compute::fast(p), &inputs)?;
            let (max_rel, mean_rel) = rel_errors(&out[0], &reference[0])?;
            let (flips, occ) = if key == ModuleKey::SsDecoder {
                let a = out[0].flatten_all()?.to_vec1::<f32>()?;
                let b = reference[0].flatten_all()?.to_vec1::<f32>()?;
                let flips = a.iter().zip(&b).filter(|(x, y)| (**x > 0.0) != (**y > 0.0)).count();
                (Some(flips as f64 / a.len() as f64), Some(b.iter().filter(|v| **v > 0.0).count()))
            } else {
                (None, None)
            };
            let row = PrecisionRow {
                module: key.to_string(),
                precision: p.name().into(),
                reference: "fast f32".into(),
                max_rel,
                mean_rel,
                occupancy_flip_fraction: flips,
                occupied_reference: occ,
            };
            on_row(&row);
            rows.push(row);
        }
    }
    Ok(rows)
}

/// Effect of a precision on stage 1's result: occupancy and pose from the
/// whole stage-1 chain (encoder, `steps` sampler steps, decoder) against f32.
#[derive(Debug, Clone, Serialize)]
pub struct OccupancyRow {
    pub precision: String,
    pub steps: usize,
    pub grid_voxels: usize,
    pub occupied_f32: usize,
    pub occupied: usize,
    /// Voxels occupied in exactly one of the two runs.
    pub flipped: usize,
    /// `flipped / grid_voxels`.
    pub flip_fraction_of_grid: f64,
    /// `flipped / occupied_f32`.
    pub flip_fraction_of_occupied: f64,
    /// Max |Δ| of the sampled (normalised) pose tokens.
    pub pose_token_max_abs_diff: f64,
}

/// Stage 1 end to end in f32 and in `precision` (same seed and inputs).
pub fn compare_occupancy(arch_path: &Path, precision: Precision, steps: usize, seed: u64) -> Result<OccupancyRow> {
    let run = |p: Precision| -> Result<crate::engine::pipeline::ObjectReconstruction> {
        let opts = crate::engine::pipeline::LoadOptions { compute: Compute::fast(p), per_stage: true };
        let pl = Pipeline::load(arch_path, Weights::Random(seed), Stages::SparseStructure, &opts)?;
        let inputs = ObjectInputs { views: vec![synthetic_view(pl.image_size(), 0.0)] };
        pl.run(&inputs, &RunOptions { seed, ss_steps: Some(steps), stage1_only: true, ..Default::default() })
    };
    let a = run(Precision::F32)?;
    let b = run(precision)?;
    let sa: std::collections::HashSet<[i32; 3]> = a.coords.iter().copied().collect();
    let sb: std::collections::HashSet<[i32; 3]> = b.coords.iter().copied().collect();
    let flipped = sa.symmetric_difference(&sb).count();
    let grid = a.ss_resolution.pow(3);
    let pose =
        a.pose.tokens_10d.iter().flatten().zip(b.pose.tokens_10d.iter().flatten()).map(|(x, y)| (x - y).abs() as f64).fold(0.0, f64::max);
    Ok(OccupancyRow {
        precision: precision.name().into(),
        steps,
        grid_voxels: grid,
        occupied_f32: sa.len(),
        occupied: sb.len(),
        flipped,
        flip_fraction_of_grid: flipped as f64 / grid as f64,
        flip_fraction_of_occupied: flipped as f64 / sa.len().max(1) as f64,
        pose_token_max_abs_diff: pose,
    })
}

/// One object end to end.
#[derive(Debug, Clone, Serialize)]
pub struct EndToEndRow {
    pub precision: String,
    pub per_stage: bool,
    pub ss_steps: usize,
    pub slat_steps: usize,
    /// What stage 2 ran on: `object` ([`object_voxels`]) or `sampled` (the
    /// random model's stage-1 occupancy, noise).
    pub occupancy: String,
    pub occupied_voxels: usize,
    /// Stage-2 transformer tokens per item (voxels at 1/patch_size resolution).
    pub slat_tokens: usize,
    pub faces: Option<usize>,
    pub gaussians: Option<usize>,
    pub timings: crate::engine::pipeline::StageTimings,
    /// `recon infer`'s mesh post-processing of the decoded mesh (floater
    /// removal, decimation to the default face budget), seconds.
    pub postprocess_seconds: f64,
    pub faces_after_postprocess: Option<usize>,
    pub memory: Option<crate::engine::pipeline::StageMemory>,
    /// Peak RSS of the whole run (MiB): the largest stage's.
    pub peak_rss_mib: Option<f64>,
    pub load_average: Option<f64>,
}

/// An object end to end on random weights (synthetic single view), every
/// module built for its stage and freed after it; `steps` `None`: the
/// architecture file's sampler settings (the paper's 25 + 25 steps and CFG
/// for recgen-large). With `object`, stage 2 runs on [`object_voxels`] at
/// the SS decoder's resolution (through the pipeline's occupancy hook, in
/// place of the random model's noise occupancy).
pub fn bench_end_to_end(arch_path: &Path, compute: Compute, steps: Option<usize>, seed: u64, object: bool) -> Result<EndToEndRow> {
    let opts = crate::engine::pipeline::LoadOptions { compute, per_stage: true };
    let p = Pipeline::load(arch_path, Weights::Random(seed), Stages::All, &opts)?;
    let inputs = ObjectInputs { views: vec![synthetic_view(p.image_size(), 0.0)] };
    let run = RunOptions { seed, ss_steps: steps, slat_steps: steps, measure_memory: true, ..Default::default() };
    let mut to_object = |_: &crate::engine::pipeline::PredictedPose, _: &[[i32; 3]], res: usize| Ok(object_voxels(res));
    let fit: Option<&mut crate::engine::pipeline::OccupancyFit<'_>> = if object { Some(&mut to_object) } else { None };
    let out = p.run_guided(&inputs, &run, &|_| {}, fit)?;
    let patch = RecGenConfig::load(arch_path)?.args.slat_flow.patch_size;
    let t = Instant::now();
    let post = out.mesh.as_ref().map(|m| {
        let m = crate::mesh::post::drop_floaters(m.clone(), 0.02);
        let n = crate::engine::DEFAULT_MAX_FACES;
        if m.faces.len() > n {
            crate::mesh::post::decimate(&m, n)
        } else {
            m
        }
    });
    let postprocess_seconds = t.elapsed().as_secs_f64();
    Ok(EndToEndRow {
        postprocess_seconds,
        faces_after_postprocess: post.map(|m| m.faces.len()),
        // The pipeline resets the high-water mark per stage: the run's peak is the largest stage's.
        peak_rss_mib: out
            .memory
            .as_ref()
            .map(|m| {
                [m.image_encoder, m.ss_flow, m.ss_decoder, m.slat_flow, m.mesh_decoder, m.gaussian_decoder]
                    .into_iter()
                    .flatten()
                    .fold(0f64, f64::max)
            })
            .or_else(peak_rss_mib),
        precision: compute.describe(),
        per_stage: true,
        ss_steps: out.metadata.ss_sampler.steps,
        slat_steps: out.metadata.slat_sampler.as_ref().map(|s| s.steps).unwrap_or(0),
        occupancy: if object { "object" } else { "sampled" }.into(),
        occupied_voxels: out.coords.len(),
        slat_tokens: coarse_tokens(&out.coords, patch),
        faces: out.mesh.as_ref().map(|m| m.faces.len()),
        gaussians: out.gaussians.as_ref().map(|g| g.len()),
        timings: out.timings,
        memory: out.memory,
        load_average: load_average(),
    })
}

/// The shape fit ([`crate::engine::fit_in_pose`]) at one occupancy resolution.
#[derive(Debug, Clone, Serialize)]
pub struct ShapeFitRow {
    pub resolution: usize,
    pub observed_points: usize,
    pub model_voxels: usize,
    pub shell_voxels: usize,
    pub carved: usize,
    pub filled: usize,
    /// Best of the repetitions.
    pub seconds: f64,
    /// The fitted mesh (`--mesh-from fitted`): closed surface of the fitted
    /// solid plus its smoothing, best of the repetitions, and its faces.
    pub surface_seconds: f64,
    pub surface_faces: usize,
    pub load_average: Option<f64>,
}

/// What the shape fit adds per object, at each stage-1 occupancy resolution
/// (recgen-nano decodes 32³, the full-size model 64³): a box 0.2 m long on a
/// table, 0.8 m from a 640×480 camera, rendered, and an over-full ball as the
/// model's occupancy (what the nano model tends to give).
pub fn bench_shape_fit(resolutions: &[usize], reps: usize) -> Result<Vec<ShapeFitRow>> {
    use crate::dataset::Intrinsics;
    use crate::engine::{fit_in_pose, DepthView, Grid, ShapeFitOptions, ViewPoints};
    use crate::geometry::Plane;
    use crate::math::Similarity;
    use crate::mesh::cuboid;
    use crate::render::{render, Camera, Instance, RenderMesh, RenderOptions};

    let (w, h) = (640, 480);
    let k = Intrinsics { fx: 600.0, fy: 600.0, cx: 320.0, cy: 240.0 };
    // Camera y points down; the table is the plane y = 0.05 m, the box stands on it.
    let half = [0.5, 0.3, 0.2];
    let (c, s) = (0.3f64.cos(), 0.3f64.sin());
    let pose = Similarity { rotation: [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], translation: [0.0, 0.05 - 0.3 * 0.2, 0.8], scale: 0.2 };
    let obj = RenderMesh::from_trimesh(&cuboid(half), "box")?;
    let table = RenderMesh::from_trimesh(&cuboid([1.0, 0.01, 1.0]), "table")?;
    let table_pose = Similarity { translation: [0.0, 0.06, 0.8], ..Similarity::identity() };
    let out =
        render(&[Instance::new(&obj, pose, 1), Instance::new(&table, table_pose, 2)], &Camera::new(w, h, k), &RenderOptions::default())?;
    let points: Vec<[f64; 3]> = (0..w * h)
        .filter(|&i| out.index[i] == 0 && out.depth[i] > 0.0)
        .map(|i| {
            let z = out.depth[i] as f64;
            [((i % w) as f64 - k.cx) / k.fx * z, ((i / w) as f64 - k.cy) / k.fy * z, z]
        })
        .collect();
    let view = ViewPoints { points, to_anchor: Similarity::identity(), depth: DepthView::new(&out.depth, w, h, k) };
    let support = Some(Plane { normal: [0.0, -1.0, 0.0], offset: 0.05 });
    let opts = ShapeFitOptions::default();
    let mut rows = Vec::new();
    for &r in resolutions {
        let cells: Vec<[i32; 3]> = (0..r * r * r)
            .map(|i| [(i / (r * r)) as i32, (i / r % r) as i32, (i % r) as i32])
            .filter(|c| c.iter().map(|&v| ((v as f64 + 0.5) / r as f64 - 0.5).powi(2)).sum::<f64>() < 0.45 * 0.45)
            .collect();
        let model = Grid::from_coords(&cells, r);
        let mut best = f64::INFINITY;
        let mut last = None;
        for _ in 0..reps.max(1) {
            let t = Instant::now();
            let fitted = fit_in_pose(model.clone(), pose, [1.0; 3], std::slice::from_ref(&view), &[support], &opts);
            best = best.min(t.elapsed().as_secs_f64());
            last = Some(fitted);
        }
        let (_, shell, report) = last.expect("at least one repetition");
        let (mut surface_seconds, mut surface_faces) = (f64::INFINITY, 0);
        for _ in 0..reps.max(1) {
            let t = Instant::now();
            let m = crate::mesh::taubin_smooth(&shell.smooth_surface(2), 30);
            surface_seconds = surface_seconds.min(t.elapsed().as_secs_f64());
            surface_faces = m.faces.len();
        }
        rows.push(ShapeFitRow {
            resolution: r,
            observed_points: view.points.len(),
            model_voxels: model.count(),
            shell_voxels: shell.count(),
            carved: report.carved,
            filled: report.filled,
            seconds: best,
            surface_seconds,
            surface_faces,
            load_average: load_average(),
        });
    }
    Ok(rows)
}

/// `recon synth` throughput: one dataset of `scenes` one-view 640×480 scenes with
/// the stereo sensor model, then the bare renderer on one scene's view.
#[derive(Debug, Clone, Serialize)]
pub struct SynthRow {
    pub scenes: usize,
    pub width: usize,
    pub height: usize,
    pub threads: usize,
    /// The whole dataset (generation, rendering, sensor model, files).
    pub seconds: f64,
    pub instances: usize,
    pub models: usize,
    /// Target occlusion histogram: 0–3 %, 3–20 %, 20–40 %, 40–70 %, > 70 %.
    pub target_occlusion_bins: [usize; 5],
    /// One view of one scene rendered again, mean of the repetitions.
    pub render_seconds: f64,
    pub render_units: usize,
    pub peak_rss_mib: Option<f64>,
    pub load_average: Option<f64>,
}

/// Generate a `scenes`-scene dataset under `dir` (removed afterwards) and time
/// the renderer alone on scene 7's first view `reps` times.
pub fn bench_synth(dir: &Path, scenes: usize, reps: usize) -> Result<SynthRow> {
    use crate::sensor::SensorModel;
    use crate::synth::{generate, Scene, SceneConfig, SynthOptions};
    let (width, height) = (640, 480);
    reset_peak_rss();
    let opts = SynthOptions { scenes, views: 1, seed: 1, width, height, parts: false, sensor: SensorModel::stereo_default() };
    let t = Instant::now();
    let s = generate(dir, &opts, &|| {})?;
    let seconds = t.elapsed().as_secs_f64();
    std::fs::remove_dir_all(dir).ok();
    let scene = Scene::generate(7, &SceneConfig::default())?;
    let units = scene.units(false)?;
    let ids: Vec<i64> = (0..units.len() as i64).collect();
    let t = Instant::now();
    for _ in 0..reps.max(1) {
        scene.render_view(&units, &ids, 0)?;
    }
    Ok(SynthRow {
        scenes,
        width,
        height,
        threads: rayon::current_num_threads(),
        seconds,
        instances: s.instances,
        models: s.models,
        target_occlusion_bins: s.target_occlusion_bins,
        render_seconds: t.elapsed().as_secs_f64() / reps.max(1) as f64,
        render_units: units.len(),
        peak_rss_mib: peak_rss_mib(),
        load_average: load_average(),
    })
}

/// Parameters of one module of an architecture (`ss_encoder` is trained only).
#[derive(Debug, Clone, Serialize)]
pub struct ParamRow {
    pub module: String,
    pub parameters: usize,
    pub shipped: bool,
}

/// Seconds per training step of one objective on toy data (mean over the
/// timed steps after one warm-up step).
#[derive(Debug, Clone, Serialize)]
pub struct TrainStepRow {
    pub objective: String,
    pub batch: usize,
    pub steps: usize,
    /// Toy data and the forward pass.
    pub forward_seconds: f64,
    pub backward_seconds: f64,
    /// Gradient clipping and the AdamW update.
    pub update_seconds: f64,
    pub peak_rss_mib: Option<f64>,
    pub load_average: Option<f64>,
}

/// The parameters of every module of the architecture at `arch_path`.
pub fn train_params(arch_path: &Path) -> Result<Vec<ParamRow>> {
    let arch = RecGenConfig::load(arch_path)?;
    let mut keys: Vec<(ModuleKey, bool)> = arch.modules().into_iter().map(|(k, _)| (k, true)).collect();
    if arch.ss_encoder.is_some() {
        keys.push((ModuleKey::SsEncoder, false));
    }
    keys.into_iter()
        .map(|(key, shipped)| {
            let args = arch.module_args(key)?;
            let parameters = registry::expected_tensors(&args, key.name())?.iter().map(|s| s.shape.iter().product::<usize>()).sum();
            Ok(ParamRow { module: key.to_string(), parameters, shipped })
        })
        .collect()
}

/// One warm-up step, then `steps` timed ones: (data + forward, backward, update) seconds per step.
fn time_train_steps(obj: &dyn crate::train::Objective, batch: usize, steps: usize) -> Result<(f64, f64, f64)> {
    use crate::train::{clip_grad_norm, AdamW};
    let vars: Vec<_> =
        obj.trainable().iter().flat_map(|m| m.vars.iter().map(move |(n, v)| (format!("{}/{n}", m.key), v.clone()))).collect();
    let mut opt = AdamW::new(&vars, candle_nn::ParamsAdamW { lr: 1e-4, weight_decay: 0.0, ..Default::default() })?;
    let mut rng = SeededRng::new(1);
    let (mut f, mut b, mut u) = (0.0, 0.0, 0.0);
    for i in 0..=steps {
        let t = Instant::now();
        let l = obj.loss(&mut rng, batch)?;
        let tf = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mut g = l.total.backward()?;
        let tb = t.elapsed().as_secs_f64();
        let t = Instant::now();
        clip_grad_norm(&mut g, &vars, Some(1.0))?;
        opt.step(&g)?;
        let tu = t.elapsed().as_secs_f64();
        if i > 0 {
            f += tf;
            b += tb;
            u += tu;
        }
    }
    let n = steps.max(1) as f64;
    Ok((f / n, b / n, u / n))
}

/// Seconds per training step of the SS VAE and of the SS flow (one and two
/// views) of the architecture at `arch_path` on toy data.
pub fn bench_train(arch_path: &Path, batch: usize, steps: usize, mut each: impl FnMut(&TrainStepRow)) -> Result<Vec<TrainStepRow>> {
    use crate::geometry::{Fill, PoseStats};
    use crate::model::ReconLoss;
    use crate::train::{pose_stats_json, scan, FlowMatching, FlowObjective, ModuleParams, ToyConfig, ToySource, VaeObjective};
    let arch = RecGenConfig::load(arch_path)?;
    let src = ToySource::new(ToyConfig { models: 8, samples: 16, width: 320, height: 240, seed: 1, occluders: true, second_view: true })?;
    let enc_cfg = arch.ss_encoder.clone().ok_or_else(|| crate::Error::msg("the architecture needs an ss_encoder section"))?;
    let mut rows = Vec::new();
    let mut row = |objective: String, (f, b, u): (f64, f64, f64)| {
        let r = TrainStepRow {
            objective,
            batch,
            steps,
            forward_seconds: f,
            backward_seconds: b,
            update_seconds: u,
            peak_rss_mib: peak_rss_mib(),
            load_average: load_average(),
        };
        each(&r);
        rows.push(r);
    };

    reset_peak_rss();
    let enc = ModuleParams::init(ModuleKey::SsEncoder, &enc_cfg, 1)?;
    let dec = ModuleParams::init(ModuleKey::SsDecoder, &arch.ss_decoder, 2)?;
    let f = enc.args.ss_encoder("ss_encoder")?.downsample_factor();
    let res = arch.ss_flow_config().resolution * f;
    let vae = VaeObjective::new(&src, enc, dec, res, Fill::Solid, ReconLoss::Dice, 1e-3)?;
    row(format!("ss-vae ({res}³)"), time_train_steps(&vae, batch, steps)?);
    drop(vae);

    reset_peak_rss();
    let enc_p = ModuleParams::init(ModuleKey::SsEncoder, &enc_cfg, 1)?;
    let encoder = registry::build_ss_encoder(&enc_p.args, enc_p.var_builder(), "ss_encoder", Compute::Plain)?;
    let sc = scan(&src)?;
    let stats = PoseStats::from_json(&pose_stats_json(&sc.poses, arch.pose.nine_d_layout, "toy")?, "toy")?;
    let dino = ModuleParams::init(ModuleKey::ImageCondModel, &arch.image_cond_model, 3)?;
    let flow = ModuleParams::init(ModuleKey::SsFlow, &arch.ss_flow, 4)?;
    let mut obj = FlowObjective::new(&src, sc, stats, dino, flow, &encoder, Fill::Solid, FlowMatching::default())?;
    for (label, p) in [("1 view", 0.0), ("2 views", 1.0)] {
        obj.p_two_view = p;
        row(format!("ss-flow ({label})"), time_train_steps(&obj, batch, steps)?);
    }
    Ok(rows)
}

/// The upstream PyTorch figures of issue 8 (Intel Xeon, 2 cores, AVX-512 +
/// AMX), for ratios: GEMM GFLOP/s, and seconds / peak GB per module.
pub mod upstream {
    pub const GEMM_4096_F32_GFLOPS: f64 = 320.0;
    pub const GEMM_4096_BF16_GFLOPS: f64 = 1774.0;
    pub const CANDLE_4096_F32_GFLOPS: f64 = 201.0;
    pub const CANDLE_4096_BF16_GFLOPS: f64 = 162.0;
    pub const SS_FLOW_F32_S: f64 = 47.1;
    pub const SS_FLOW_F32_GB: f64 = 3.1;
    pub const SS_FLOW_BF16_S: f64 = 17.0;
    pub const SS_FLOW_BF16_GB: f64 = 3.2;
    pub const SS_DECODER_F32_S: f64 = 3.8;
    pub const SS_DECODER_F32_GB: f64 = 1.0;
}

/// Everything one `recon bench` invocation measured.
#[derive(Debug, Clone, Serialize, Default)]
pub struct BenchReport {
    pub machine: Option<MachineInfo>,
    pub peaks: Vec<PeakRow>,
    pub gemm: Vec<GemmRow>,
    pub attention: Vec<AttentionRow>,
    pub modules: Vec<ModuleRow>,
    pub guided: Vec<GuidedRow>,
    /// The SS flow's profiled guided step (section `stage1`).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub stage1: Vec<Stage2Row>,
    pub stage2: Vec<Stage2Row>,
    pub precision: Vec<PrecisionRow>,
    pub occupancy: Vec<OccupancyRow>,
    pub end_to_end: Vec<EndToEndRow>,
    pub shape_fit: Vec<ShapeFitRow>,
    pub synth: Option<SynthRow>,
    pub train_params: Vec<ParamRow>,
    pub train: Vec<TrainStepRow>,
    /// recon against an upstream report from the same machine (`--compare`).
    pub compare: Vec<crate::tools::upstream::CompareRow>,
    /// recon on released-layout checkpoints against upstream's outputs (`--released`).
    pub released: Vec<crate::tools::upstream::ReleasedRow>,
    pub notes: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// After freeing a large buffer, the reset mark no longer includes it.
    #[test]
    fn reset_peak_rss_forgets_freed_memory() {
        let Some(_) = peak_rss_mib() else { return };
        let v: Vec<Vec<u8>> = (0..64).map(|i| vec![i as u8 | 1; 4 << 20]).collect(); // 256 MiB in 4 MiB blocks
        let with = peak_rss_mib().unwrap();
        drop(v);
        reset_peak_rss();
        let after = peak_rss_mib().unwrap();
        assert!(after < with - 128.0, "peak {with:.0} MiB before, {after:.0} MiB after the reset");
    }

    #[test]
    fn shell_and_view_shapes() {
        let s = shell_coords(16, 6.0, 1);
        assert!(!s.is_empty() && s.iter().all(|c| c[0] == 1 && c[1..].iter().all(|&v| (0..16).contains(&v))));
        let v = synthetic_view(28, 0.0);
        assert_eq!(v.pixels.dims(), &[1, 3, 28, 28]);
        assert!(v.mask.sum_all().unwrap().to_scalar::<f32>().unwrap() > 0.0);
    }

    /// The realistic voxel set: a few thousand surface voxels at 64³, about a
    /// quarter of them as 32³ tokens, in argwhere order, the same every time.
    #[test]
    fn object_voxels_are_a_realistic_surface() {
        let v = object_voxels(64);
        assert!((2000..12000).contains(&v.len()), "{} voxels", v.len());
        assert!(v.windows(2).all(|w| w[0] < w[1]) && v.iter().flatten().all(|&c| (0..64).contains(&c)));
        let tokens = coarse_tokens(&v, 2);
        assert!(tokens * 3 < v.len() && tokens * 6 > v.len(), "{tokens} tokens for {} voxels", v.len());
        // Longest side spans 95 % of the grid.
        let span = (0..3).map(|i| v.iter().map(|c| c[i]).max().unwrap() - v.iter().map(|c| c[i]).min().unwrap()).max().unwrap();
        assert!((58..=62).contains(&span), "span {span}");
        assert_eq!(object_voxels(64), v);
        assert!(object_voxels(16).len() < v.len() / 8);
    }

    #[test]
    fn relative_errors_and_reference_peak() {
        let a = Tensor::new(&[1.0f32, 2.0, -3.0], &Device::Cpu).unwrap();
        let b = Tensor::new(&[1.0f32, 2.5, -3.0], &Device::Cpu).unwrap();
        let (mx, mean) = rel_errors(&a, &b).unwrap();
        assert!((mx - 0.5 / 3.0).abs() < 1e-9 && (mean - 0.5 / 6.5).abs() < 1e-9);
        let peaks = vec![
            PeakRow { isa: "avx512bf16", kind: "f32 fma", gflops: 100.0, load_average: None },
            PeakRow { isa: "avx512bf16", kind: "bf16 dot", gflops: 200.0, load_average: None },
        ];
        assert_eq!(reference_peak(&peaks, Isa::Avx512Bf16, WeightFormat::Bf16), Some(200.0));
        assert_eq!(reference_peak(&peaks, Isa::Avx512Bf16, WeightFormat::F16), Some(100.0));
        assert_eq!(reference_peak(&peaks, Isa::Avx512, WeightFormat::F32), None);
    }

    /// The synth section makes and removes its dataset; the train section counts
    /// every module's parameters and times both objectives (micro architecture).
    #[test]
    fn synth_and_train_sections_run() {
        let dir = recon_testkit::tmp("bench-synth").join("out");
        let r = bench_synth(&dir, 1, 1).unwrap();
        assert!(r.instances > 0 && r.render_units > 0 && r.render_seconds > 0.0, "{r:?}");
        assert!(!dir.exists());

        let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
        let nano = train_params(&repo.join("models/recgen-nano.json")).unwrap();
        assert!(nano.iter().any(|p| p.module == "ss_encoder" && !p.shipped && p.parameters > 0));
        assert!(nano.iter().filter(|p| p.shipped).count() >= 5 && nano.iter().all(|p| p.parameters > 0));

        let work = recon_testkit::tmp("bench-train");
        let v: serde_json::Value = crate::util::read_json(&repo.join("models/recgen-nano.json")).unwrap();
        let micro = work.join("recgen-micro.json");
        std::fs::write(&micro, serde_json::to_string(&crate::train::micro_architecture(&v)).unwrap()).unwrap();
        for f in ["stereo_pose_stats.example.json", "slat_pose_stats.example.json"] {
            std::fs::copy(repo.join("models").join(f), work.join(f)).unwrap();
        }
        let mut seen = 0;
        let rows = bench_train(&micro, 1, 1, |_| seen += 1).unwrap();
        assert_eq!((rows.len(), seen), (3, 3));
        assert!(rows.iter().all(|r| r.forward_seconds > 0.0 && r.backward_seconds > 0.0 && r.update_seconds > 0.0));
    }

    /// The stage2 section profiles a guided step of the tiny SLat flow on the
    /// object voxel set, and the end-to-end object runs stage 2 on that set.
    #[test]
    fn stage2_section_and_object_occupancy_run_tiny() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/recgen-tiny.json");
        let rows = bench_stage2(&path, &[Compute::fast(Precision::F32)], 1, |_| {}).unwrap();
        let r = &rows[0];
        let p = &r.profile;
        assert_eq!(r.voxels, object_voxels(32).len());
        assert!(r.tokens > 0 && r.tokens < r.voxels && r.step_seconds > 0.0, "{r:?}");
        assert!(p.gemm.flops > 0.0 && p.attention.flops > 0.0 && p.sparse_conv.flops > 0.0 && p.sparse_index.calls > 0, "{p:?}");
        assert!(p.transformer_flops > 0.0 && p.io_blocks_flops > 0.0 && r.flops >= p.transformer_flops + p.io_blocks_flops, "{p:?}");
        assert!(r.gflops > 0.0 && r.io_blocks_seconds < r.step_seconds && r.transformer_seconds < r.step_seconds, "{r:?}");
        assert!(!crate::util::profile::enabled());

        let e = bench_end_to_end(&path, Compute::fast(Precision::F32), Some(1), 0, true).unwrap();
        let want = object_voxels(32); // the tiny SS decoder's grid
        assert_eq!((e.occupancy.as_str(), e.occupied_voxels), ("object", want.len()));
        assert_eq!(e.slat_tokens, coarse_tokens(&want, 2));
    }

    /// The module bench runs every module of the tiny architecture on both paths.
    #[test]
    fn module_bench_runs_tiny_modules() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/recgen-tiny.json");
        let rows = bench_modules(
            &path,
            &[ModuleKey::ImageCondModel, ModuleKey::SsFlow, ModuleKey::SlatDecGs],
            &[Compute::fast(Precision::Bf16)],
            |_| {},
        )
        .unwrap();
        assert_eq!(rows.len(), 3);
        assert!(rows.iter().all(|r| r.forward_seconds > 0.0));
        let cmp = compare_precisions(&path, &[ModuleKey::SsFlow], &[Precision::Bf16], |_| {}).unwrap();
        assert_eq!(cmp.len(), 1);
        assert!(cmp[0].max_rel > 0.0 && cmp[0].max_rel < 0.5, "bf16 vs f32 {}", cmp[0].max_rel);
        let occ = compare_occupancy(&path, Precision::Bf16, 2, 0).unwrap();
        assert!(occ.occupied_f32 > 0 && (0.0..=1.0).contains(&occ.flip_fraction_of_grid));
    }
}
