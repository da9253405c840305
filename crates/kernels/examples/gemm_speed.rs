//! GEMM GFLOP/s on the model's linear shapes (or square ones), per ISA and
//! weight format, against the measured FMA / vdpbf16ps peak.
//! `cargo run --release -p recon-kernels --example gemm_speed -- [M] [--portable]
//! [--isa avx2,avx512] [--formats f32,bf16] [--square 1024,2048] [--threads T] [--reps R] [--peak-reps R]`
//! (`--portable` times the portable kernels too; `--square` times M = K = N;
//! more repetitions find a quiet moment on a shared machine). `cpu`: the
//! rate over the process's CPU time per thread, which time other programs
//! take from the cores does not lower.
use recon_kernels::gemm::{gemm, PackedMatrix, WeightFormat};
use recon_kernels::isa::Isa;
use recon_kernels::peak::{measure_peak_gflops, PeakKind};
use recon_kernels::vecmath::Activation;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let value = |flag: &str| args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1)).cloned();
    let list = |flag: &str| value(flag).map(|v| v.split(',').map(str::to_string).collect::<Vec<_>>());
    let m: usize = args.first().and_then(|v| v.parse().ok()).unwrap_or(2 * 4098);
    let portable = args.iter().any(|a| a == "--portable");
    let reps: usize = value("--reps").and_then(|v| v.parse().ok()).unwrap_or(3);
    let peak_reps: usize = value("--peak-reps").and_then(|v| v.parse().ok()).unwrap_or(3);
    if let Some(t) = value("--threads").and_then(|v| v.parse().ok()) {
        rayon::ThreadPoolBuilder::new().num_threads(t).build_global().unwrap();
    }
    let isas: Vec<Isa> = match list("--isa") {
        Some(names) => names.iter().map(|n| Isa::parse(n).unwrap_or_else(|| panic!("unknown ISA {n}"))).filter(|i| i.supported()).collect(),
        None => Isa::all_supported().into_iter().filter(|&i| i != Isa::Portable || portable).collect(),
    };
    let formats: Vec<WeightFormat> = list("--formats")
        .unwrap_or_else(|| vec!["f32".into(), "bf16".into(), "f16".into()])
        .iter()
        .map(|f| [WeightFormat::F32, WeightFormat::Bf16, WeightFormat::F16].into_iter().find(|w| w.name() == f).expect("format"))
        .collect();
    let shapes: Vec<(usize, usize, usize)> = match list("--square") {
        Some(s) => s.iter().map(|v| v.parse().expect("size")).map(|s| (s, s, s)).collect(),
        None => [(1024, 3072), (1024, 4096), (4096, 1024), (1024, 1024)].iter().map(|&(k, n)| (m, k, n)).collect(),
    };
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("threads {} load {}", rayon::current_num_threads(), load.trim());
    let mut peaks = Vec::new();
    for &isa in &isas {
        let f = measure_peak_gflops(isa, PeakKind::F32, 2_000_000, peak_reps).unwrap();
        let b = measure_peak_gflops(isa, PeakKind::Bf16, 2_000_000, peak_reps);
        println!("peak {}: f32 {f:.0} GFLOP/s, bf16 {:?}", isa.name(), b.map(|v| v.round()));
        peaks.push((isa, f, b));
    }
    for &(m, k, n) in &shapes {
        let a: Vec<f32> = (0..m * k).map(|i| ((i * 7919) % 1000) as f32 * 1e-3 - 0.5).collect();
        let w: Vec<f32> = (0..n * k).map(|i| ((i * 104729) % 1000) as f32 * 1e-3 - 0.5).collect();
        let mut c = vec![0f32; m * n];
        for &(isa, f32_peak, bf16_peak) in &peaks {
            for &fmt in &formats {
                let b = PackedMatrix::from_linear_weight(&w, n, k, fmt).unwrap();
                gemm(isa, &a, m, k, &b, None, Activation::None, &mut c, n).unwrap();
                let mut dt = f64::INFINITY;
                let c0 = cpu_seconds();
                for _ in 0..reps {
                    let t = Instant::now();
                    gemm(isa, &a, m, k, &b, None, Activation::None, &mut c, n).unwrap();
                    dt = dt.min(t.elapsed().as_secs_f64());
                }
                let cpu = (cpu_seconds() - c0) / reps as f64 / rayon::current_num_threads() as f64;
                let gf = 2.0 * (m * n * k) as f64 / dt / 1e9;
                let cpu_gf = 2.0 * (m * n * k) as f64 / cpu / 1e9;
                let peak = if fmt == WeightFormat::Bf16 && isa == Isa::Avx512Bf16 { bf16_peak.unwrap_or(f32_peak) } else { f32_peak };
                println!(
                    "M {m} K {k:4} N {n:4} {:<10} {:<4}: {dt:.3} s {gf:6.1} GFLOP/s {:5.1} % of peak; cpu {cpu_gf:6.1} GFLOP/s {:5.1} %",
                    isa.name(),
                    fmt.name(),
                    100.0 * gf / peak,
                    100.0 * cpu_gf / peak
                );
            }
        }
    }
}

/// User + system CPU seconds of this process (from /proc/self/stat, 100 Hz ticks; 0 elsewhere).
fn cpu_seconds() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = s.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}
