//! Whole-pipeline timing on random weights (labelled RANDOM in the output).
//!
//! `cargo bench --bench pipeline -- [CONFIG] [--stage1] [--ss-steps N]
//! [--slat-steps N] [--seed N] [--views 1|2] [--dtype f32|bf16|f16] [--per-stage]`
//! (default CONFIG models/recgen-tiny.json). Inputs are synthetic: a smooth
//! image, a disc mask and a sphere-cap pointmap at the DINO input size.
//! Prints the per-stage seconds, sizes and peak RSS.

use recon::engine::{LoadOptions, ObjectInputs, Pipeline, RunOptions, Stages, Weights};
use recon::model::Precision;
use recon::tools::synthetic_view as view;
use std::path::PathBuf;
use std::time::Instant;

fn peak_rss_gb() -> f64 {
    recon::util::peak_rss_mib().map(|m| m / 1024.0).unwrap_or(0.0)
}

fn main() -> recon::Result<()> {
    let mut args = std::env::args().skip(1).filter(|a| a != "--bench");
    let mut config = PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/models/recgen-tiny.json"));
    let mut opts = RunOptions { seed: 0, ..Default::default() };
    let mut views = 1;
    let mut load = LoadOptions::default();
    while let Some(a) = args.next() {
        let mut num = |name: &str| -> usize { args.next().and_then(|v| v.parse().ok()).unwrap_or_else(|| panic!("{name} needs a number")) };
        match a.as_str() {
            "--stage1" => opts.stage1_only = true,
            "--ss-steps" => opts.ss_steps = Some(num("--ss-steps")),
            "--slat-steps" => opts.slat_steps = Some(num("--slat-steps")),
            "--seed" => opts.seed = num("--seed") as u64,
            "--views" => views = num("--views"),
            "--per-stage" => load.per_stage = true,
            "--dtype" => {
                let p: Precision = args.next().unwrap_or_default().parse().unwrap_or_else(|e| panic!("--dtype: {e}"));
                load = LoadOptions { per_stage: load.per_stage, ..LoadOptions::precision(p) };
            }
            other => config = PathBuf::from(other),
        }
    }
    let stages = if opts.stage1_only { Stages::SparseStructure } else { Stages::All };
    let t = Instant::now();
    opts.measure_memory = true;
    let p = Pipeline::load(&config, Weights::Random(0), stages, &load)?;
    println!("{}: RANDOM weights built in {:.2} s ({})", p.config.name, t.elapsed().as_secs_f64(), load.compute.describe());
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
        ("loading", tm.loading),
        ("total", tm.total),
    ] {
        println!("  {name:<17} {v:9.3} s");
    }
    if let Some(m) = &out.memory {
        println!("peak RSS MiB per stage: {m:?}");
    }
    println!("peak RSS (VmHWM) {:.2} GB", peak_rss_gb());
    Ok(())
}
