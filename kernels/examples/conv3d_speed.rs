//! Times one dense conv3d at the sizes of the full sparse-structure decoder.
//! `cargo run --release -p recon-kernels --example conv3d_speed`
use recon_kernels::conv3d::{conv3d, Conv3dShape};
use std::time::Instant;

fn main() {
    for &(cin, cout, r) in &[(512usize, 512usize, 16usize), (512, 1024, 16), (128, 128, 32), (128, 256, 32), (32, 32, 64)] {
        let s = Conv3dShape { batch: 1, cin, cout, d: r, h: r, w: r, k: 3, pad: 1 };
        let x: Vec<f32> = (0..s.input_len()).map(|i| ((i * 7919) % 1000) as f32 * 1e-3).collect();
        let w: Vec<f32> = (0..s.weight_len()).map(|i| ((i * 104729) % 1000) as f32 * 1e-3 - 0.5).collect();
        let b = vec![0.1f32; cout];
        let mut out = vec![0f32; s.output_len()];
        conv3d(&x, &s, &w, Some(&b), &mut out, false).unwrap();
        // Best of 3 wall times, and CPU seconds (less sensitive to a shared machine).
        let mut dt = f64::INFINITY;
        let c0 = cpu_seconds();
        for _ in 0..3 {
            let t = Instant::now();
            conv3d(&x, &s, &w, Some(&b), &mut out, false).unwrap();
            dt = dt.min(t.elapsed().as_secs_f64());
        }
        let cpu = (cpu_seconds() - c0) / 3.0;
        let gflop = 2.0 * (cin * 27 * cout * r * r * r) as f64 * 1e-9;
        println!("cin {cin:4} cout {cout:4} grid {r:2}^3: {dt:.3} s  {:.1} GFLOP/s  cpu {cpu:.3} s/run", gflop / dt);
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
