//! One forward of the full-size RecGen sparse-structure flow model
//! (models/recgen-large.json: 1024 channels, 24 blocks, 16 heads) on the CPU
//! in f32, batch 2 (conditional + unconditional, as under guidance), 4096
//! voxel tokens + 2 pose tokens, 1369 condition tokens. Random weights with a
//! small std keep activations finite. Reports wall time and peak RSS (VmHWM).
//!
//! Run: `cargo bench --bench ss_flow` (env `BENCH_ITERS`, default 1;
//! `BENCH_BLOCKS=n` runs n blocks instead of 24;
//! `BENCH_DTYPE=f32|bf16|f16` builds the model on the fast kernels in that
//! precision, unset = the plain candle path measured below).
//!
//! About 10.5 TFLOP per forward (≈ 436 GFLOP per block: linears 270, self-
//! attention 138, cross-attention 46). Measured on the shared 2-core dev box
//! (2026-11-22, load ≈ 8): 670 s, peak RSS 2.71 GB (weights 2.09 GB). Op
//! micro-timings there: Linear 8196×1024→4096 46 GFLOP/s; chunked self-
//! attention over 4098 tokens 10.8 s per call (13 GFLOP/s), of which
//! `softmax_last_dim` ≈ 4 s; tanh-GELU on [2, 4098, 4096] 1.3 s. Softmax,
//! GELU and the K=64 batched matmuls of attention are the candle hot spots.

use std::path::Path;
use std::time::Instant;

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;
use recon::model::RecGenConfig;
use recon::model::SparseStructureFlowModel;
use recon::rng::SeededRng;

/// Deterministic uniform weights (std 0.02; norm scales 1 ± small). Nothing
/// is "contained", so the position embedding is computed.
struct RandomWeights;

impl SimpleBackend for RandomWeights {
    fn get(&self, s: Shape, name: &str, _h: candle_nn::Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let seed = name.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x100_0000_01b3));
        let mut x = seed | 1;
        let a = 0.02f32 * 3f32.sqrt();
        let is_scale = name.ends_with("gamma") || name.ends_with("norm2.weight");
        let v: Vec<f32> = (0..s.elem_count())
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                let u = (x >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0;
                if is_scale {
                    1.0 + 0.1 * u
                } else {
                    a * u
                }
            })
            .collect();
        Tensor::from_vec(v, s, dev)?.to_dtype(dtype)
    }
    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("random weights: no shape for `{name}`")
    }
    fn contains_tensor(&self, _name: &str) -> bool {
        false
    }
}

fn vm_hwm_kib() -> Option<u64> {
    recon::util::peak_rss_mib().map(|m| (m * 1024.0) as u64)
}

fn main() -> recon::Result<()> {
    let dev = Device::Cpu;
    let cfg_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/recgen-large.json");
    let mut cfg = RecGenConfig::load(&cfg_path)?.ss_flow_config()?;
    // `BENCH_BLOCKS` runs fewer blocks (for profiling); the time scales per block.
    if let Some(n) = std::env::var("BENCH_BLOCKS").ok().and_then(|v| v.parse().ok()) {
        cfg.num_blocks = n;
    }
    let t0 = Instant::now();
    let vb = VarBuilder::from_backend(Box::new(RandomWeights), DType::F32, dev.clone());
    let compute = match std::env::var("BENCH_DTYPE") {
        Ok(v) => recon::model::Compute::fast(v.parse().map_err(recon::Error::msg)?),
        Err(_) => recon::model::Compute::Plain,
    };
    println!("compute: {}", compute.describe());
    let model = SparseStructureFlowModel::new(&cfg, vb, compute)?;
    recon::util::release_cached_buffers();
    let build_s = t0.elapsed().as_secs_f64();
    let hwm_weights = vm_hwm_kib().unwrap_or(0);

    let b = 2;
    let mut rng = SeededRng::new(0);
    let state = model.initial_state(&mut rng, b, &dev)?;
    let cond = rng.randn(&[b, 1369, cfg.cond_channels], &dev)?;
    let t = Tensor::new(&[750f32, 750.0], &dev)?;
    println!(
        "ss_flow bench: C={} blocks={} heads={} tokens={}+{} cond={} batch={} threads={}",
        cfg.model_channels,
        cfg.num_blocks,
        cfg.heads(),
        cfg.num_tokens(),
        cfg.num_pose_tokens,
        1369,
        b,
        rayon::current_num_threads()
    );
    println!("weights built in {build_s:.1} s, VmHWM after build {:.2} GB", hwm_weights as f64 / 1048576.0);

    let iters: usize = std::env::var("BENCH_ITERS").ok().and_then(|v| v.parse().ok()).unwrap_or(1).max(1);
    for i in 0..iters {
        let t1 = Instant::now();
        let (v, vp) = model.forward(&state[0], Some(&state[1]), &t, &cond)?;
        let secs = t1.elapsed().as_secs_f64();
        let vp = vp.expect("pose velocity");
        let finite = v.flatten_all()?.to_vec1::<f32>()?.iter().chain(vp.flatten_all()?.to_vec1::<f32>()?.iter()).all(|x| x.is_finite());
        println!(
            "forward {i}: {secs:.2} s  v {:?} pose {:?} finite={finite}  peak RSS (VmHWM) {:.2} GB",
            v.dims(),
            vp.dims(),
            vm_hwm_kib().unwrap_or(0) as f64 / 1048576.0
        );
    }
    println!("upstream PyTorch reference (CPU, brief): 47.1 s, 3.1 GB");
    Ok(())
}
