//! Kernel throughput: measured FMA / bf16 peaks, GEMM on the model's linear
//! shapes (f32, bf16, f16 weights) and fused attention at the SS-flow shapes,
//! with the fraction of peak each reaches. The same code as
//! `recon bench --sections kernels`.
//!
//! Run: `cargo bench --bench kernels` (env `BENCH_REPS`, default 2).

fn main() -> recon::Result<()> {
    let reps = std::env::var("BENCH_REPS").ok().and_then(|v| v.parse().ok()).unwrap_or(2);
    let m = recon::tools::MachineInfo::detect();
    println!("{} | {} threads | best ISA {} | load {:?}", m.cpu, m.threads, m.best_isa, m.load_average);
    let peaks = recon::tools::measure_peaks();
    for p in &peaks {
        println!("peak {:<11} {:<9} {:8.1} GFLOP/s", p.isa, p.kind, p.gflops);
    }
    for r in recon::tools::bench_gemm(&peaks, reps, false)? {
        let eff = r.efficiency.map(|e| format!("{:.0}%", e * 100.0)).unwrap_or_default();
        println!(
            "gemm {:<22} {:<11} {:<5} {:8.3} s {:8.1} GFLOP/s {eff:>5} load {:?}",
            r.what, r.isa, r.format, r.seconds, r.gflops, r.load_average
        );
    }
    for r in recon::tools::bench_attention(&peaks, reps)? {
        let eff = r.efficiency.map(|e| format!("{:.0}%", e * 100.0)).unwrap_or_default();
        println!(
            "attention {:<16} {:<5} {:8.3} s {:8.1} GFLOP/s {eff:>5} load {:?}",
            r.what, r.precision, r.seconds, r.gflops, r.load_average
        );
    }
    Ok(())
}
