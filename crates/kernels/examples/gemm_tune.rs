//! Sweep the GEMM cache blocking on one model shape.
//! `cargo run --release -p recon-kernels --example gemm_tune -- K N [f32|bf16|f16]`
//! (`GEMM_TUNE_MC=168,336 GEMM_TUNE_KC=256,512` replace the swept values; `GEMM_TUNE_M` the rows.)
use recon_kernels::gemm::{gemm_blocked, Blocking, PackedMatrix, WeightFormat};
use recon_kernels::isa::Isa;
use recon_kernels::vecmath::Activation;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let k: usize = args.get(1).and_then(|v| v.parse().ok()).unwrap_or(1024);
    let n: usize = args.get(2).and_then(|v| v.parse().ok()).unwrap_or(3072);
    let fmt = match args.get(3).map(|s| s.as_str()) {
        Some("bf16") => WeightFormat::Bf16,
        Some("f16") => WeightFormat::F16,
        _ => WeightFormat::F32,
    };
    let list = |var: &str, default: &[usize]| -> Vec<usize> {
        std::env::var(var).ok().map(|v| v.split(',').filter_map(|x| x.trim().parse().ok()).collect()).unwrap_or_else(|| default.to_vec())
    };
    let m = list("GEMM_TUNE_M", &[2 * 4098])[0];
    let a: Vec<f32> = (0..m * k).map(|i| ((i * 7919) % 1000) as f32 * 1e-3 - 0.5).collect();
    let w: Vec<f32> = (0..n * k).map(|i| ((i * 104729) % 1000) as f32 * 1e-3 - 0.5).collect();
    let b = PackedMatrix::from_linear_weight(&w, n, k, fmt).unwrap();
    let mut c = vec![0f32; m * n];
    let isa = Isa::best();
    for &mc in &list("GEMM_TUNE_MC", &[14 * 12, 14 * 24, 14 * 48]) {
        for &kc in &list("GEMM_TUNE_KC", &[128, 256, 384, 512, 1024]) {
            let blk = Blocking { mc, kc };
            let mut dt = f64::INFINITY;
            for _ in 0..3 {
                let t = Instant::now();
                gemm_blocked(isa, &a, m, k, &b, None, Activation::None, &mut c, n, blk).unwrap();
                dt = dt.min(t.elapsed().as_secs_f64());
            }
            let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
            println!(
                "{} K {k} N {n} mc {mc:4} kc {kc:4}: {:6.1} GFLOP/s  load {}",
                fmt.name(),
                2.0 * (m * n * k) as f64 / dt / 1e9,
                load.split_whitespace().next().unwrap_or("")
            );
        }
    }
}
