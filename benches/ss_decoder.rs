//! Full-size sparse-structure decoder benchmark (release channels [512,128,32],
//! latent 8×16³ → logits 64³, batch 1, random weights).
//! `cargo bench --bench ss_decoder` prints seconds per forward and peak RSS.

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;
use recon::model::{occupied_coords, SparseStructureDecoder, SparseStructureDecoderConfig};
use std::time::Instant;

/// Hands out deterministic random tensors of whatever shape is asked for, so
/// the benchmark needs no checkpoint and holds each weight only once.
struct RandomWeights;

fn xorshift_fill(n: usize, seed: u64, scale: f32, offset: f32) -> Vec<f32> {
    let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            offset + scale * (((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0)
        })
        .collect()
}

impl SimpleBackend for RandomWeights {
    fn get(&self, s: Shape, name: &str, _h: candle_nn::Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let seed = name.bytes().fold(1469598103934665603u64, |h, b| (h ^ b as u64).wrapping_mul(1099511628211));
        let dims = s.dims();
        let is_norm = name.contains("norm") || name.starts_with("out_layer.0");
        let (scale, offset) = if is_norm && name.ends_with("weight") {
            (0.1, 1.0)
        } else if dims.len() == 5 {
            // Uniform with variance 1/fan_in keeps activations O(1) through the net.
            ((3.0 / (dims[1] * dims[2] * dims[3] * dims[4]) as f32).sqrt(), 0.0)
        } else {
            (0.05, 0.0)
        };
        Tensor::from_vec(xorshift_fill(s.elem_count(), seed, scale, offset), s, dev)?.to_dtype(dtype)
    }
    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("random weights need a shape for `{name}`")
    }
    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

fn vm_hwm_mib() -> Option<f64> {
    recon::util::peak_rss_mib()
}

fn main() -> recon::Result<()> {
    let iters: usize = std::env::var("SS_DEC_BENCH_ITERS").ok().and_then(|v| v.parse().ok()).unwrap_or(3);
    let cfg = SparseStructureDecoderConfig::release();
    let vb = VarBuilder::from_backend(Box::new(RandomWeights), DType::F32, Device::Cpu);
    let t0 = Instant::now();
    let dec = SparseStructureDecoder::new(&cfg, vb, recon::model::Compute::Plain)?;
    println!(
        "ss_decoder bench: channels {:?}, {} rayon threads; weights built in {:.2} s",
        cfg.channels,
        rayon::current_num_threads(),
        t0.elapsed().as_secs_f64()
    );
    let x = Tensor::from_vec(xorshift_fill(8 * 16 * 16 * 16, 42, 1.0, 0.0), (1, 8, 16, 16, 16), &Device::Cpu)?;
    let mut times = Vec::new();
    let mut cpus = Vec::new();
    let mut occupied = 0;
    for i in 0..iters.max(1) {
        let (t, c0) = (Instant::now(), cpu_seconds());
        let logits = dec.forward(&x)?;
        let dt = t.elapsed().as_secs_f64();
        let cpu = cpu_seconds() - c0;
        occupied = occupied_coords(&logits)?.len();
        println!("forward {i}: {dt:.3} s wall, {cpu:.2} CPU-s  logits {:?}", logits.dims());
        times.push(dt);
        cpus.push(cpu);
    }
    let best = times.iter().cloned().fold(f64::INFINITY, f64::min);
    let mean = times.iter().sum::<f64>() / times.len() as f64;
    let cpu_mean = cpus.iter().sum::<f64>() / cpus.len() as f64;
    println!(
        "seconds per forward: best {best:.3}  mean {mean:.3}  ({} runs); CPU-seconds per forward {cpu_mean:.2}; occupied voxels {occupied}",
        times.len()
    );
    // On a shared machine wall time overstates the cost; CPU-s / threads is the
    // wall time this would take with the cores to itself.
    match vm_hwm_mib() {
        Some(m) => println!("peak RSS (VmHWM): {m:.0} MiB"),
        None => println!("peak RSS: unavailable (/proc/self/status not readable)"),
    }
    Ok(())
}

/// User + system CPU seconds of this process (from /proc/self/stat, 100 Hz ticks).
fn cpu_seconds() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = s.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}
