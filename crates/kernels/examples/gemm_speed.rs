//! GEMM GFLOP/s on the model's linear shapes, per ISA and weight format,
//! against the measured FMA / vdpbf16ps peak.
//! `cargo run --release -p recon-kernels --example gemm_speed [M] [--portable]`
//! (`--portable` times the portable kernels too).
use recon_kernels::gemm::{gemm, PackedMatrix, WeightFormat};
use recon_kernels::isa::Isa;
use recon_kernels::peak::{measure_peak_gflops, PeakKind};
use recon_kernels::vecmath::Activation;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let m: usize = args.iter().find_map(|v| v.parse().ok()).unwrap_or(2 * 4098);
    let portable = args.iter().any(|a| a == "--portable");
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("threads {} load {}", rayon::current_num_threads(), load.trim());
    for isa in Isa::all_supported() {
        let f = measure_peak_gflops(isa, PeakKind::F32, 2_000_000, 3).unwrap();
        let b = measure_peak_gflops(isa, PeakKind::Bf16, 2_000_000, 3);
        println!("peak {}: f32 {f:.0} GFLOP/s, bf16 {:?}", isa.name(), b.map(|v| v.round()));
    }
    for &(k, n) in &[(1024usize, 3072usize), (1024, 4096), (4096, 1024), (1024, 1024)] {
        let a: Vec<f32> = (0..m * k).map(|i| ((i * 7919) % 1000) as f32 * 1e-3 - 0.5).collect();
        let w: Vec<f32> = (0..n * k).map(|i| ((i * 104729) % 1000) as f32 * 1e-3 - 0.5).collect();
        let mut c = vec![0f32; m * n];
        for isa in Isa::all_supported() {
            if isa == Isa::Portable && !portable {
                continue;
            }
            for fmt in [WeightFormat::F32, WeightFormat::Bf16, WeightFormat::F16] {
                let b = PackedMatrix::from_linear_weight(&w, n, k, fmt).unwrap();
                gemm(isa, &a, m, k, &b, None, Activation::None, &mut c, n).unwrap();
                let mut dt = f64::INFINITY;
                for _ in 0..3 {
                    let t = Instant::now();
                    gemm(isa, &a, m, k, &b, None, Activation::None, &mut c, n).unwrap();
                    dt = dt.min(t.elapsed().as_secs_f64());
                }
                let gf = 2.0 * (m * n * k) as f64 / dt / 1e9;
                println!("M {m} K {k:4} N {n:4} {:<10} {:<4}: {dt:.3} s {gf:6.1} GFLOP/s", isa.name(), fmt.name());
            }
        }
    }
}
