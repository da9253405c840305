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
        let t = Instant::now();
        conv3d(&x, &s, &w, Some(&b), &mut out, false).unwrap();
        let dt = t.elapsed().as_secs_f64();
        let gflop = 2.0 * (cin * 27 * cout * r * r * r) as f64 * 1e-9;
        println!("cin {cin:4} cout {cout:4} grid {r:2}^3: {dt:.3} s  {:.1} GFLOP/s", gflop / dt);
    }
}
