//! Full-size structured-latent decoders (released config: 768 channels,
//! 12 heads, swin window 8, resolution 64, 32 Gaussians per voxel) on
//! surface-like shells of ~5k/10k/20k voxels, random weights.
//!
//! `cargo bench --bench slat_decoders` (release). Env:
//! - `SLAT_BENCH_BLOCKS` (default 12): transformer blocks actually run; with
//!   fewer, the 12-block time is extrapolated from the measured per-block time.
//! - `SLAT_BENCH_SIZES` (default `5000,10000,20000`): target voxel counts.
//! - `SLAT_BENCH_MESH` / `SLAT_BENCH_GS` = 0 to skip a decoder.
//!
//! Peak RSS is the process high-water mark (VmHWM), reset before each run
//! through `/proc/self/clear_refs`, so it includes the weights.

use candle_core::{Module, Tensor};
use recon::model::SLatGaussianDecoder;
use recon::model::SparseTensor;
use recon::model::{random_var_builder, SLatMeshDecoder};
use std::time::Instant;

const FULL_BLOCKS: usize = 12;

fn env_usize(k: &str, d: usize) -> usize {
    std::env::var(k).ok().and_then(|v| v.parse().ok()).unwrap_or(d)
}

/// Voxels of a spherical shell (radius `r`, thickness `t`) at resolution 64.
fn shell(r: f64, t: f64) -> Vec<[i32; 4]> {
    let mut v = Vec::new();
    for x in 0..64 {
        for y in 0..64 {
            for z in 0..64 {
                let d = [x, y, z].map(|c| c as f64 + 0.5 - 32.0);
                let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                if (n - r).abs() < t / 2.0 {
                    v.push([0, x, y, z]);
                }
            }
        }
    }
    v
}

/// Shell with about `n` voxels (thickness grows once the radius is maxed).
fn shell_with(n: usize) -> Vec<[i32; 4]> {
    let t = if n > 12_000 { 2.6 } else { 1.8 };
    let (mut lo, mut hi) = (2.0, 30.0);
    for _ in 0..30 {
        let mid = 0.5 * (lo + hi);
        if shell(mid, t).len() < n {
            lo = mid
        } else {
            hi = mid
        }
    }
    shell(hi, t)
}

fn reset_peak() {
    recon::util::reset_peak_rss();
}

fn peak_mib() -> f64 {
    recon::util::peak_rss_mib().unwrap_or(f64::NAN)
}

fn args(blocks: usize, mesh: bool) -> serde_json::Value {
    let rep = if mesh {
        serde_json::json!({"use_color": true})
    } else {
        serde_json::json!({
            "lr": {"_xyz": 1.0, "_features_dc": 1.0, "_opacity": 1.0, "_scaling": 1.0, "_rotation": 0.1},
            "perturb_offset": true, "voxel_size": 1.5, "num_gaussians": 32,
            "2d_filter_kernel_size": 0.1, "3d_filter_kernel_size": 9e-4,
            "scaling_bias": 4e-3, "opacity_bias": 0.1, "scaling_activation": "softplus"
        })
    };
    serde_json::json!({
        "resolution": 64, "model_channels": 768, "latent_channels": 8, "num_blocks": blocks,
        "num_heads": 12, "mlp_ratio": 4, "attn_mode": "swin", "window_size": 8, "pe_mode": "ape",
        "representation_config": rep
    })
}

/// Seconds of the trunk's input layer and of each block (from tap timestamps).
fn trunk_times(trunk: &recon::model::SparseTransformerBase, x: &SparseTensor) -> recon::Result<(Tensor, f64, Vec<f64>)> {
    let t0 = Instant::now();
    let mut stamps = Vec::new();
    let h = trunk.forward_with(x, &mut |_, _| stamps.push(t0.elapsed().as_secs_f64()))?;
    let end = t0.elapsed().as_secs_f64();
    stamps.push(end);
    // stamps[0] = input layer done; stamps[j+1] = block j done.
    let blocks: Vec<f64> = stamps.windows(2).map(|w| w[1] - w[0]).take(trunk.blocks.len()).collect();
    Ok((h, stamps[0], blocks))
}

fn main() -> recon::Result<()> {
    let blocks = env_usize("SLAT_BENCH_BLOCKS", FULL_BLOCKS).max(1);
    let sizes: Vec<usize> = std::env::var("SLAT_BENCH_SIZES")
        .unwrap_or_else(|_| "5000,10000,20000".into())
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    println!(
        "slat_decoders: 768 ch, 12 heads, swin 8, res 64; running {blocks} of {FULL_BLOCKS} blocks; threads {}",
        rayon::current_num_threads()
    );
    for &target in &sizes {
        let coords = shell_with(target);
        let n = coords.len();
        let mut s = 1u64;
        let feats: Vec<f32> = (0..n * 8)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect();
        let x = SparseTensor::new(coords, Tensor::from_vec(feats, (n, 8), &candle_core::Device::Cpu)?, 1)?;

        if env_usize("SLAT_BENCH_GS", 1) == 1 {
            reset_peak();
            let a = args(blocks, false);
            let vb = random_var_builder(1, 0.02, |vb| SLatGaussianDecoder::new(&a, vb, recon::model::Compute::Plain))?;
            let dec = SLatGaussianDecoder::new(&a, vb, recon::model::Compute::Plain)?;
            let t0 = Instant::now();
            let (h, t_in, tb) = trunk_times(&dec.trunk, &x)?;
            let t1 = Instant::now();
            let h = recon::model::layer_norm_plain(&h, 1e-5)?;
            let feats = dec.out_layer_forward(&h)?;
            let reps = dec.to_representation(&x, &feats)?;
            let g = reps[0].to_gaussians()?;
            let t_head = t1.elapsed().as_secs_f64();
            let total = t0.elapsed().as_secs_f64();
            let per_block = tb.iter().sum::<f64>() / tb.len() as f64;
            let full = t_in + per_block * FULL_BLOCKS as f64 + t_head;
            println!(
                "gs   voxels {n:6}: measured {total:7.2} s (input {t_in:.2}, blocks {:.2} s each, head {t_head:.2}) -> 12-block est {full:7.2} s; {} gaussians; peak RSS {:.0} MiB",
                per_block, g.len(), peak_mib()
            );
        }

        if env_usize("SLAT_BENCH_MESH", 1) == 1 {
            reset_peak();
            let a = args(blocks, true);
            let vb = random_var_builder(2, 0.02, |vb| SLatMeshDecoder::new(&a, vb, recon::model::Compute::Plain))?;
            let dec = SLatMeshDecoder::new(&a, vb, recon::model::Compute::Plain)?;
            let t0 = Instant::now();
            let (h, t_in, tb) = trunk_times(&dec.trunk, &x)?;
            let t1 = Instant::now();
            let h = dec.upsample[0].forward(&x.with_feats(h)?)?;
            let t_up0 = t1.elapsed().as_secs_f64();
            let peak_trunk_up0 = peak_mib();
            let n128 = h.len();
            let t2 = Instant::now();
            let ch = dec.extractor.channels();
            let out = dec.upsample[1].forward_then(&h, ch, &|t| Ok(dec.out_layer.forward(&t)?))?;
            drop(h);
            let t_up1 = t2.elapsed().as_secs_f64();
            let peak_up1 = peak_mib();
            let n256 = out.len();
            let t3 = Instant::now();
            let meshes = dec.extractor.extract_sparse(&out)?;
            let t_fc = t3.elapsed().as_secs_f64();
            let total = t0.elapsed().as_secs_f64();
            let per_block = tb.iter().sum::<f64>() / tb.len() as f64;
            let full = total + per_block * (FULL_BLOCKS as f64 - tb.len() as f64);
            println!(
                "mesh voxels {n:6}: measured {total:7.2} s (input {t_in:.2}, blocks {per_block:.2} s each, upsample.0 {t_up0:.2} [{n128} vox], upsample.1+out {t_up1:.2} [{n256} vox], flexicubes {t_fc:.2}) -> 12-block est {full:7.2} s; mesh {} v / {} f; peak RSS {:.0} MiB (through upsample.0 {peak_trunk_up0:.0}, through upsample.1 {peak_up1:.0})",
                meshes[0].vertices.len(), meshes[0].faces.len(), peak_mib()
            );
        }
    }
    Ok(())
}
