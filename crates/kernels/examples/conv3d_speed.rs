//! Times one dense conv3d at the sizes of the full sparse-structure decoder,
//! with f32 and with bf16 transformed weights (the Winograd layers; the
//! narrow im2col layers compute in f32 either way).
//! `cargo run --release -p recon-kernels --example conv3d_speed [-- --isa avx2]`
//! (`--isa` caps the kernels at that family).
use recon_kernels::conv3d::{conv3d_winograd, conv3d_with, Conv3dShape};
use recon_kernels::gemm::WeightFormat;
use recon_kernels::isa::Isa;
use recon_kernels::peak::bf16_isa;
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let cap = args.iter().position(|a| a == "--isa").and_then(|i| args.get(i + 1)).map(|n| Isa::parse(n).expect("unknown ISA"));
    let capped = |isa: Isa| cap.map_or(isa, |c| c.min(isa));
    println!("2·27·Cin·Cout·voxels / best-of-3 wall time; cpu = CPU seconds per run");
    // `wino`: the narrow layer forced through Winograd (the dispatcher uses im2col there).
    let layers = [
        (512usize, 512usize, 16usize, false),
        (512, 1024, 16, false),
        (128, 128, 32, false),
        (128, 256, 32, false),
        (32, 32, 64, false),
        (32, 32, 64, true),
    ];
    for &(cin, cout, r, wino) in &layers {
        let s = Conv3dShape { batch: 1, cin, cout, d: r, h: r, w: r, k: 3, pad: 1 };
        let x: Vec<f32> = (0..s.input_len()).map(|i| ((i * 7919) % 1000) as f32 * 1e-3).collect();
        let w: Vec<f32> = (0..s.weight_len()).map(|i| ((i * 104729) % 1000) as f32 * 1e-3 - 0.5).collect();
        let b = vec![0.1f32; cout];
        let mut out = vec![0f32; s.output_len()];
        let mut line = format!("cin {cin:4} cout {cout:4} grid {r:2}^3{}:", if wino { " wino" } else { "     " });
        let conv = |out: &mut [f32], format, isa| {
            if wino {
                conv3d_winograd(&x, &s, &w, Some(&b), out, false, format, isa)
            } else {
                conv3d_with(&x, &s, &w, Some(&b), out, false, format, isa)
            }
        };
        for (name, format, isa) in [("f32", WeightFormat::F32, capped(Isa::best())), ("bf16", WeightFormat::Bf16, capped(bf16_isa()))] {
            conv(&mut out, format, isa).unwrap();
            // Best of 3 wall times, and CPU seconds (less sensitive to a shared machine).
            let mut dt = f64::INFINITY;
            let c0 = cpu_seconds();
            for _ in 0..3 {
                let t = Instant::now();
                conv(&mut out, format, isa).unwrap();
                dt = dt.min(t.elapsed().as_secs_f64());
            }
            let cpu = (cpu_seconds() - c0) / 3.0;
            let gflop = 2.0 * (cin * 27 * cout * r * r * r) as f64 * 1e-9;
            line += &format!("  {name} {dt:.3} s {:6.1} GFLOP/s cpu {cpu:.3} s", gflop / dt);
        }
        println!("{line}");
    }
}

/// User + system CPU seconds of this process (from /proc/self/stat, 100 Hz ticks).
fn cpu_seconds() -> f64 {
    let s = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = s.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}
