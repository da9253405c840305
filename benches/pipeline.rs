//! Whole-pipeline timing on random weights (labelled RANDOM in the output).
//!
//! `cargo bench --bench pipeline -- [CONFIG] [--stage1] [--ss-steps N]
//! [--slat-steps N] [--seed N] [--views 1|2]`
//! (default CONFIG models/recgen-tiny.json). Inputs are synthetic: a smooth
//! image, a disc mask and a sphere-cap pointmap at the DINO input size.
//! Prints the per-stage seconds, sizes and peak RSS.

use candle_core::{Device, Tensor};
use recon::pipeline::{ObjectInputs, Pipeline, RunOptions, Stages, ViewInput};
use std::path::PathBuf;
use std::time::Instant;

fn view(s: usize, shift: f32) -> ViewInput {
    let c = s as f32 * (0.5 + shift);
    let r = s as f32 * 0.35;
    let mut px = vec![0f32; 3 * s * s];
    let mut pm = vec![0f32; 3 * s * s];
    let mut mk = vec![0f32; s * s];
    for y in 0..s {
        for x in 0..s {
            let (u, v) = (x as f32 / s as f32, y as f32 / s as f32);
            for ch in 0..3 {
                px[(ch * s + y) * s + x] = ((3.0 * u + 2.0 * v + ch as f32).sin() * 0.4 + 0.5 - 0.45) / 0.225;
            }
            let (dx, dy) = ((x as f32 + 0.5 - c) / r, (y as f32 + 0.5 - s as f32 * 0.5) / r);
            let d2 = dx * dx + dy * dy;
            if d2 <= 1.0 {
                mk[y * s + x] = 1.0;
                let p = [dx * 0.5, dy * 0.5, 1.5 - 0.5 * (1.0 - d2).sqrt()];
                for ch in 0..3 {
                    pm[(ch * s + y) * s + x] = p[ch];
                }
            }
        }
    }
    let t = |v: Vec<f32>, c: usize| Tensor::from_vec(v, (1, c, s, s), &Device::Cpu).unwrap();
    ViewInput { pixels: t(px, 3), pointmap: t(pm, 3), mask: t(mk, 1) }
}

fn peak_rss_gb() -> f64 {
    recon::bench::peak_rss_mib().map(|m| m / 1024.0).unwrap_or(0.0)
}

fn main() -> recon::Result<()> {
    let mut args = std::env::args().skip(1).filter(|a| a != "--bench");
    let mut config = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/models/recgen-tiny.json"));
    let mut opts = RunOptions { seed: 0, ..Default::default() };
    let mut views = 1;
    while let Some(a) = args.next() {
        let mut num = |name: &str| -> usize {
            args.next().and_then(|v| v.parse().ok()).unwrap_or_else(|| panic!("{name} needs a number"))
        };
        match a.as_str() {
            "--stage1" => opts.stage1_only = true,
            "--ss-steps" => opts.ss_steps = Some(num("--ss-steps")),
            "--slat-steps" => opts.slat_steps = Some(num("--slat-steps")),
            "--seed" => opts.seed = num("--seed") as u64,
            "--views" => views = num("--views"),
            other => config = PathBuf::from(other),
        }
    }
    let stages = if opts.stage1_only { Stages::SparseStructure } else { Stages::All };
    let t = Instant::now();
    let p = Pipeline::random_stages(&config, 0, stages)?;
    println!("{}: RANDOM weights built in {:.2} s", p.config.name, t.elapsed().as_secs_f64());
    let s = p.image_size();
    let inputs = ObjectInputs { views: (0..views).map(|i| view(s, 0.05 * i as f32)).collect() };
    let out = p.run(&inputs, &opts)?;
    let m = &out.metadata;
    println!(
        "views {} | SS sampler {} steps cfg {} | SLat sampler {:?}",
        m.num_views,
        m.ss_sampler.steps,
        m.ss_sampler.cfg_strength,
        m.slat_sampler.as_ref().map(|s| (s.steps, s.cfg_strength))
    );
    println!(
        "occupied {} voxels of {}³ | mesh {:?} faces | gaussians {:?}",
        out.coords.len(),
        out.ss_resolution,
        out.mesh.as_ref().map(|m| m.faces.len()),
        out.gaussians.as_ref().map(|g| g.len())
    );
    let tm = &out.timings;
    for (name, v) in [
        ("image_encoder", tm.image_encoder),
        ("ss_condition", tm.ss_condition),
        ("ss_sampling", tm.ss_sampling),
        ("ss_decoder", tm.ss_decoder),
        ("pose", tm.pose),
        ("slat_condition", tm.slat_condition),
        ("slat_sampling", tm.slat_sampling),
        ("mesh_decoder", tm.mesh_decoder),
        ("gaussian_decoder", tm.gaussian_decoder),
        ("total", tm.total),
    ] {
        println!("  {name:<17} {v:9.3} s");
    }
    println!("peak RSS (VmHWM) {:.2} GB", peak_rss_gb());
    Ok(())
}
