//! Fused attention GFLOP/s at the SS flow shapes (batch 2, 16 heads, d 64):
//! self-attention over 4098 tokens (fused qkv layout) and cross-attention to
//! 1374 condition tokens.
//! `cargo run --release -p recon-kernels --example attention_speed`
//! (`-- --isa avx512bf16 --prec bf16` to time one combination, `--portable` to
//! time the portable kernels too.)
use recon_kernels::attention::{flash_attention, AttnPrecision, AttnSpec, HeadLayout, Segment};
use recon_kernels::isa::Isa;
use std::time::Instant;

/// Command-line filters: `--portable`, `--isa NAME`, `--prec f32|bf16`.
struct Filters {
    portable: bool,
    isa: Option<String>,
    prec: Option<String>,
}

fn filters() -> Filters {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let value = |flag: &str| args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1)).cloned();
    Filters { portable: args.iter().any(|a| a == "--portable"), isa: value("--isa"), prec: value("--prec") }
}

fn main() {
    let only = filters();
    let (b, h, d) = (2usize, 16usize, 64usize);
    let c = h * d;
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!("threads {} load {}", rayon::current_num_threads(), load.trim());
    for &(lq, lk, name) in &[(4098usize, 4098usize, "self"), (4098, 1374, "cross")] {
        let q: Vec<f32> = (0..b * lq * 3 * c).map(|i| ((i * 7919) % 1000) as f32 * 2e-3 - 1.0).collect();
        let kv: Vec<f32> = (0..b * lk * 2 * c).map(|i| ((i * 104729) % 1000) as f32 * 2e-3 - 1.0).collect();
        let segs: Vec<Segment> = (0..b).map(|i| Segment { q: i * lq..(i + 1) * lq, kv: i * lk..(i + 1) * lk }).collect();
        let mut out = vec![0f32; b * lq * c];
        for isa in Isa::all_supported() {
            if isa == Isa::Portable && !only.portable {
                continue;
            }
            if only.isa.as_deref().is_some_and(|v| v != isa.name()) {
                continue;
            }
            for precision in [AttnPrecision::F32, AttnPrecision::Bf16] {
                if only.prec.as_deref().is_some_and(|v| !v.eq_ignore_ascii_case(&format!("{precision:?}"))) {
                    continue;
                }
                let spec = AttnSpec {
                    heads: h,
                    head_dim: d,
                    scale: 0.125,
                    q: HeadLayout::new(3 * c, 0),
                    k: HeadLayout::new(2 * c, 0),
                    v: HeadLayout::new(2 * c, c),
                    out: HeadLayout::new(c, 0),
                    precision,
                };
                let mut dt = f64::INFINITY;
                for _ in 0..2 {
                    let t = Instant::now();
                    flash_attention(isa, &spec, &q, &kv, &kv, &segs, &mut out).unwrap();
                    dt = dt.min(t.elapsed().as_secs_f64());
                }
                let gf = 4.0 * (b * h * lq * lk * d) as f64 / dt / 1e9;
                println!("{name:<5} Lq {lq} Lk {lk} {:<10} {precision:?}: {dt:.3} s {gf:6.1} GFLOP/s", isa.name());
            }
        }
    }
}
