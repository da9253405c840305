//! SLat flow forward benchmark at the released size (model_channels 1024,
//! io_block_channels [128], 16 heads, cond 1024 with 1369 + 2 tokens), random
//! small weights, batch 1, on solid voxel balls of ~5k / ~10k / ~20k voxels at
//! resolution 64 (the transformer runs on the ×2-downsampled tokens).
//!
//! `SLAT_BENCH_BLOCKS` (default 24) sets the number of transformer blocks.
//! With fewer than 24 the bench also runs a 0-block model and extrapolates
//! linearly: t(24) = t(0) + 24 · (t(B) − t(0)) / B.
//! Peak RSS is VmHWM, reset per case via /proc/self/clear_refs.
//!
//! Run: `cargo bench --bench slat_flow` (release).

use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use recon::model::SparseTensor;
use recon::model::{SLatFlowConfig, SLatFlowModel};
use std::collections::HashMap;
use std::time::Instant;

fn config(blocks: usize) -> SLatFlowConfig {
    SLatFlowConfig::from_json(&serde_json::json!({
        "resolution": 64, "in_channels": 8, "out_channels": 8, "model_channels": 1024, "cond_channels": 1024,
        "num_blocks": blocks, "num_heads": 16, "mlp_ratio": 4, "patch_size": 2, "num_io_res_blocks": 2,
        "io_block_channels": [128], "pe_mode": "ape", "qk_rms_norm": true, "use_skip_connection": true
    }))
    .expect("bench config")
}

/// Model with small random weights (norm scales ≈ 1, other weights ~N(0, 0.02²)).
/// The weights are handed over as plain tensors: VarMap variables would make
/// candle keep every intermediate alive for backprop, which is not inference.
fn random_model(cfg: &SLatFlowConfig) -> candle_core::Result<SLatFlowModel> {
    let vm = VarMap::new();
    SLatFlowModel::new(cfg, VarBuilder::from_varmap(&vm, DType::F32, &Device::Cpu), recon::model::Compute::Plain)
        .map_err(candle_core::Error::wrap)?;
    let mut weights = HashMap::new();
    {
        let data = vm.data().lock().expect("varmap lock");
        for (name, var) in data.iter() {
            let r = Tensor::randn(0f32, 0.02, var.shape(), &Device::Cpu)?;
            let is_scale = name.ends_with("norm1.weight") || name.ends_with("norm2.weight") || name.ends_with("gamma");
            weights.insert(name.clone(), if is_scale { (r + 1.0)? } else { r });
        }
    }
    drop(vm);
    SLatFlowModel::new(cfg, VarBuilder::from_tensors(weights, DType::F32, &Device::Cpu), recon::model::Compute::Plain)
        .map_err(candle_core::Error::wrap)
}

/// A solid ball at the grid centre with about `target` voxels.
fn ball(target: usize) -> Vec<[i32; 4]> {
    let mut r = 1.0f64;
    loop {
        let coords: Vec<[i32; 4]> = (0..64i32)
            .flat_map(|x| (0..64i32).flat_map(move |y| (0..64i32).map(move |z| [0, x, y, z])))
            .filter(|c| {
                let d = |v: i32| v as f64 + 0.5 - 32.0;
                d(c[1]).powi(2) + d(c[2]).powi(2) + d(c[3]).powi(2) <= r * r
            })
            .collect();
        if coords.len() >= target {
            return coords;
        }
        r += 0.25;
    }
}

fn vm_hwm_mib() -> f64 {
    recon::util::peak_rss_mib().unwrap_or(f64::NAN)
}

fn reset_hwm() {
    recon::util::reset_peak_rss();
}

fn time_forward(model: &SLatFlowModel, coords: &[[i32; 4]], cond: &Tensor) -> candle_core::Result<(f64, usize, f64)> {
    let feats = Tensor::randn(0f32, 1.0, (coords.len(), 8), &Device::Cpu)?;
    let x = SparseTensor::new(coords.to_vec(), feats, 1).map_err(candle_core::Error::wrap)?;
    let tokens = recon::model::sparse_downsample(&x, 2).map_err(candle_core::Error::wrap)?.0.len();
    let t = Tensor::new(&[500f32], &Device::Cpu)?;
    reset_hwm();
    let start = Instant::now();
    let y = model.forward(&x, &t, cond).map_err(candle_core::Error::wrap)?;
    let secs = start.elapsed().as_secs_f64();
    let finite = y.feats.abs()?.max_keepdim(1)?.max_keepdim(0)?.flatten_all()?.to_vec1::<f32>()?[0];
    assert!(finite.is_finite(), "non-finite output");
    Ok((secs, tokens, vm_hwm_mib()))
}

fn main() -> candle_core::Result<()> {
    let blocks: usize = std::env::var("SLAT_BENCH_BLOCKS").ok().and_then(|v| v.parse().ok()).unwrap_or(24);
    let sizes: Vec<usize> = std::env::var("SLAT_BENCH_SIZES")
        .ok()
        .map(|v| v.split(',').filter_map(|s| s.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![5000, 10000, 20000]);
    println!(
        "SLat flow bench: C=1024, io [128], 16 heads, {blocks} block(s), cond 1371×1024, batch 1, {} rayon threads",
        rayon::current_num_threads()
    );
    let cond = Tensor::randn(0f32, 1.0, (1, 1371, 1024), &Device::Cpu)?;

    let base = if blocks < 24 {
        let m0 = random_model(&config(0))?;
        let mut v = Vec::new();
        for &n in &sizes {
            let c = ball(n);
            let (s, tok, rss) = time_forward(&m0, &c, &cond)?;
            println!("  0 blocks: {:>6} voxels, {:>5} tokens: {:>8.2} s, peak RSS {:>8.0} MiB", c.len(), tok, s, rss);
            v.push(s);
        }
        Some(v)
    } else {
        None
    };

    let model = random_model(&config(blocks))?;
    for (i, &n) in sizes.iter().enumerate() {
        let c = ball(n);
        let (s, tok, rss) = time_forward(&model, &c, &cond)?;
        print!("  {blocks} blocks: {:>6} voxels, {:>5} tokens: {:>8.2} s, peak RSS {:>8.0} MiB", c.len(), tok, s, rss);
        if let Some(b) = &base {
            let per_block = (s - b[i]) / blocks.max(1) as f64;
            // Weights of the missing blocks (23.09 M params each, f32).
            let extra_mib = (24 - blocks) as f64 * 23.09e6 * 4.0 / (1024.0 * 1024.0);
            print!(
                "  → extrapolated 24 blocks: {:.1} s ({:.2} s/block), peak RSS ≈ {:.0} MiB",
                b[i] + 24.0 * per_block,
                per_block,
                rss + extra_mib
            );
        }
        println!();
    }
    Ok(())
}
