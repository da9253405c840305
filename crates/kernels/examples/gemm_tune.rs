//! Sweep the GEMM cache blocking on one model shape.
//! `cargo run --release -p recon-kernels --example gemm_tune -- K N [f32|bf16|f16]`
//! (`GEMM_TUNE_MC=168,336 GEMM_TUNE_KC=256,512 GEMM_TUNE_NC=0,8` replace the swept values; `GEMM_TUNE_M`
//! the rows; `GEMM_TUNE_ISA=avx2` caps the kernels; `GEMM_TUNE_REPS` the timed runs, best kept.)
//! `cpu`: the rate over the process CPU time per pool thread, which other programs' load does not lower.
use recon_kernels::gemm::{gemm_blocked, Blocking, PackedMatrix, WeightFormat};
use recon_kernels::isa::Isa;
use recon_kernels::vecmath::Activation;
use std::time::Instant;

fn main() {
    if let Ok(t) = std::env::var("GEMM_TUNE_THREADS") {
        rayon::ThreadPoolBuilder::new().num_threads(t.parse().expect("GEMM_TUNE_THREADS")).build_global().unwrap();
    }
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
    let isa = std::env::var("GEMM_TUNE_ISA").ok().and_then(|v| Isa::parse(&v)).unwrap_or_else(Isa::best);
    let reps = list("GEMM_TUNE_REPS", &[3])[0].max(1);
    let threads = rayon::current_num_threads() as f64;
    println!("isa {} M {m} threads {threads}", isa.name());
    // Every configuration once per round, so a change in the machine's load hits all alike.
    let mut cfgs = Vec::new();
    let nc_default = [recon_kernels::gemm::PANELS_PER_BLOCK];
    for &mc in &list("GEMM_TUNE_MC", &[14 * 12, 14 * 24, 14 * 48]) {
        for &kc in &list("GEMM_TUNE_KC", &[128, 256, 384, 512, 1024]) {
            for &nc in &list("GEMM_TUNE_NC", &nc_default) {
                cfgs.push((Blocking { mc, kc, nc }, f64::INFINITY, f64::INFINITY));
            }
        }
    }
    let flop = 2.0 * (m * n * k) as f64;
    for _ in 0..reps {
        for (blk, dt, cpu) in cfgs.iter_mut() {
            let (t, c0) = (Instant::now(), cpu_seconds());
            gemm_blocked(isa, &a, m, k, &b, None, Activation::None, &mut c, n, *blk).unwrap();
            *dt = dt.min(t.elapsed().as_secs_f64());
            *cpu = cpu.min((cpu_seconds() - c0) / threads);
        }
    }
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    for (blk, dt, cpu) in &cfgs {
        println!(
            "{} K {k} N {n} mc {:4} kc {:4} nc {:3}: {:6.1} GFLOP/s  cpu {:6.1}",
            fmt.name(),
            blk.mc,
            blk.kc,
            blk.nc,
            flop / dt / 1e9,
            flop / cpu / 1e9,
        );
    }
    println!("load {}", load.trim());
}

/// CPU seconds of this process (`CLOCK_PROCESS_CPUTIME_ID`: exact, not in ticks).
fn cpu_seconds() -> f64 {
    #[repr(C)]
    struct Timespec {
        sec: i64,
        nsec: i64,
    }
    extern "C" {
        fn clock_gettime(clock: i32, ts: *mut Timespec) -> i32;
    }
    const CLOCK_PROCESS_CPUTIME_ID: i32 = 2;
    let mut ts = Timespec { sec: 0, nsec: 0 };
    // SAFETY: a valid out pointer; Linux's clock id 2 is the process CPU clock.
    if unsafe { clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &mut ts) } != 0 {
        return 0.0;
    }
    ts.sec as f64 + ts.nsec as f64 * 1e-9
}
