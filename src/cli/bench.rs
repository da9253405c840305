//! `recon bench`: kernel throughput against the measured peak, per-module
//! forward time and peak memory at full size (random weights), precision
//! errors, an end-to-end object, the shape fit, `recon synth` throughput and
//! training steps; tables on stdout, JSON with `--json`. The one benchmark
//! system of the project (there is no `cargo bench`).
use std::path::{Path, PathBuf};

use anyhow::Context;
use recon::model::{Compute, ModuleKey, Precision};
use recon::tools::bench::{self, BenchReport};
use recon::tools::upstream;

#[derive(clap::Args)]
pub struct BenchArgs {
    /// Architecture file (full size: models/recgen-large.json).
    #[arg(long, default_value = "models/recgen-large.json")]
    config: PathBuf,
    /// Sections to run: kernels, modules, guided, stage1, stage2, precision, occupancy, e2e, shape_fit, synth, train (comma separated).
    #[arg(long, value_delimiter = ',', default_value = "kernels,modules")]
    sections: Vec<String>,
    /// Precisions of the fast kernels for modules / e2e / comparisons.
    #[arg(long, value_delimiter = ',', default_value = "f32,bf16")]
    dtype: Vec<Precision>,
    /// Modules for `modules` and `precision` (image_cond_model, ss_flow, ss_decoder, slat_flow, slat_dec_mesh, slat_dec_gs).
    #[arg(long, value_delimiter = ',')]
    modules: Option<Vec<String>>,
    /// Also run the plain candle path in the module section (slow at full size).
    #[arg(long)]
    plain: bool,
    /// Sampler steps per stage of the end-to-end object (default: the architecture
    /// file's, i.e. the paper's 25 + 25 with its CFG for recgen-large).
    #[arg(long)]
    steps: Option<usize>,
    /// Run stage 2 of the end-to-end object on the random model's sampled
    /// (noise) occupancy instead of the realistic object voxel set.
    #[arg(long)]
    sampled_occupancy: bool,
    /// Stage-1 sampler steps of the occupancy comparison.
    #[arg(long, default_value_t = 2)]
    occupancy_steps: usize,
    /// Repetitions of each kernel timing (best of).
    #[arg(long, default_value_t = 2)]
    reps: usize,
    /// Fewer kernel shapes.
    #[arg(long)]
    quick: bool,
    /// Scenes of the `synth` section's dataset (one 640×480 view each, stereo sensor).
    #[arg(long, default_value_t = 50)]
    synth_scenes: usize,
    /// Architecture of the `train` section (it needs an `ss_encoder`).
    #[arg(long, default_value = "models/recgen-nano.json")]
    train_config: PathBuf,
    /// Batch size of the `train` section's steps.
    #[arg(long, default_value_t = 8)]
    train_batch: usize,
    /// Timed steps per objective of the `train` section (after one warm-up step).
    #[arg(long, default_value_t = 3)]
    train_steps: usize,
    /// Write the report as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Upstream timing report from the same machine (`benches/upstream/harness.py --json`):
    /// print recon/upstream ratios for the module rows of this run.
    #[arg(long)]
    compare: Option<PathBuf>,
    /// Folder written by `benches/upstream/harness.py --save`: load its released-layout
    /// full-size checkpoints and measure recon's outputs against upstream's (per --dtype).
    #[arg(long)]
    released: Option<PathBuf>,
}

fn opt(v: Option<f64>, f: impl Fn(f64) -> String) -> String {
    v.map(f).unwrap_or_else(|| "-".into())
}

/// The sections `--sections` accepts, in the order they run.
const SECTIONS: [&str; 11] =
    ["kernels", "modules", "guided", "stage1", "stage2", "precision", "occupancy", "e2e", "shape_fit", "synth", "train"];

pub fn run(a: BenchArgs) -> anyhow::Result<bool> {
    if let Some(n) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("--threads")?;
    }
    if let Some(s) = a.sections.iter().find(|s| !SECTIONS.contains(&s.as_str())) {
        anyhow::bail!("--sections: unknown section `{s}` (known: {})", SECTIONS.join(", "));
    }
    let modules = selected_modules(&a)?;
    let has = |s: &str| a.sections.iter().any(|x| x == s);
    let mut report = BenchReport { machine: Some(bench::MachineInfo::detect()), ..Default::default() };
    print_machine(&mut report, a.compare.is_none());
    if has("kernels") {
        kernels(&a, &mut report)?;
    }
    if has("modules") {
        module_rows(&a, &modules, &mut report)?;
    }
    if has("guided") {
        guided(&a, &modules, &mut report)?;
    }
    if has("stage1") {
        stage1(&a, &mut report)?;
    }
    if has("stage2") {
        stage2(&a, &mut report)?;
    }
    if has("precision") {
        precision(&a, &modules, &mut report)?;
    }
    if has("occupancy") {
        occupancy(&a, &mut report)?;
    }
    if has("e2e") {
        end_to_end(&a, &mut report)?;
    }
    if let Some(dir) = &a.released {
        released(&a, dir, &mut report)?;
    }
    let arch = recon::model::RecGenConfig::load(&a.config)?;
    if has("shape_fit") {
        shape_fit(&a, &arch, &mut report)?;
    }
    if has("synth") {
        synth(&a, &mut report)?;
    }
    if has("train") {
        train(&a, &mut report)?;
    }
    if let Some(path) = &a.compare {
        compare(path, &mut report)?;
    } else if arch.name == "recgen-large" {
        print_ratios(&report);
    } else {
        println!("\n(ratios against the upstream figures are printed for models/recgen-large.json only; this is {})", arch.name);
        print_notes(&report);
    }
    if let Some(path) = &a.json {
        write_json(path, &report)?;
    }
    Ok(true)
}

/// `--modules` checked against the known modules, in their order (default: all).
fn selected_modules(a: &BenchArgs) -> anyhow::Result<Vec<ModuleKey>> {
    Ok(match &a.modules {
        Some(m) => {
            let known = || bench::MODULES.map(ModuleKey::name).join(", ");
            let asked = m.iter().map(|k| match k.parse::<ModuleKey>() {
                Ok(key) if bench::MODULES.contains(&key) => Ok(key),
                _ => Err(anyhow::anyhow!("--modules: unknown module `{k}` (known: {})", known())),
            });
            let asked = asked.collect::<anyhow::Result<Vec<_>>>()?;
            bench::MODULES.into_iter().filter(|k| asked.contains(k)).collect()
        }
        None => bench::MODULES.to_vec(),
    })
}

/// The machine line, and the notes every report carries.
fn print_machine(report: &mut BenchReport, upstream_figures: bool) {
    let m = report.machine.as_ref().expect("detected before");
    println!(
        "machine: {} | {} threads | ISAs {:?} (using {}; bf16 on {}) | allocator: {} | load {}",
        m.cpu,
        m.threads,
        m.supported_isas,
        m.best_isa,
        m.bf16_isa,
        m.allocator,
        opt(m.load_average, |v| format!("{v:.2}"))
    );
    if upstream_figures {
        report.notes.push(
            "upstream figures (issue 8) were measured on a 2-core Intel Xeon with AVX-512, AVX512-BF16 and AMX-BF16; \
             ratios against them compare different machines unless this report comes from that machine type \
             (benches/upstream/harness.py + --compare measures upstream on this machine)"
                .into(),
        );
    }
    report.notes.push("AMX is not implemented (no AMX unit on the development machine; untested tile code is not shipped)".into());
}

/// Instruction-set peaks, GEMM and attention throughput.
fn kernels(a: &BenchArgs, report: &mut BenchReport) -> anyhow::Result<()> {
    eprintln!("measuring instruction-set peaks…");
    report.peaks = bench::measure_peaks();
    println!("\n{:<12} {:<9} {:>10} {:>6}", "isa", "kind", "GFLOP/s", "load");
    for p in &report.peaks {
        println!("{:<12} {:<9} {:>10.1} {:>6}", p.isa, p.kind, p.gflops, opt(p.load_average, |v| format!("{v:.1}")));
    }
    eprintln!("GEMM…");
    report.gemm = bench::bench_gemm(&report.peaks, a.reps, a.quick)?;
    println!(
        "\n{:<22} {:>5} {:>5} {:>5} {:<11} {:<5} {:>8} {:>9} {:>7} {:>6} {:>6}",
        "GEMM", "M", "K", "N", "isa", "w", "s", "GFLOP/s", "peak", "peak%", "load"
    );
    for r in &report.gemm {
        println!(
            "{:<22} {:>5} {:>5} {:>5} {:<11} {:<5} {:>8.3} {:>9.1} {:>7} {:>6} {:>6}",
            r.what,
            r.m,
            r.k,
            r.n,
            r.isa,
            r.format,
            r.seconds,
            r.gflops,
            opt(r.peak_gflops, |p| format!("{p:.1}")),
            opt(r.efficiency, |e| format!("{:.0}", e * 100.0)),
            opt(r.load_average, |v| format!("{v:.1}"))
        );
    }
    eprintln!("attention…");
    report.attention = bench::bench_attention(&report.peaks, a.reps)?;
    println!(
        "\n{:<16} {:>3} {:>3} {:>5} {:>5} {:<5} {:<11} {:>8} {:>9} {:>7} {:>6} {:>6}",
        "attention", "B", "H", "Lq", "Lk", "prec", "isa", "s", "GFLOP/s", "peak", "peak%", "load"
    );
    for r in &report.attention {
        println!(
            "{:<16} {:>3} {:>3} {:>5} {:>5} {:<5} {:<11} {:>8.3} {:>9.1} {:>7} {:>6} {:>6}",
            r.what,
            r.batch,
            r.heads,
            r.lq,
            r.lk,
            r.precision,
            r.isa,
            r.seconds,
            r.gflops,
            opt(r.peak_gflops, |p| format!("{p:.1}")),
            opt(r.efficiency, |e| format!("{:.0}", e * 100.0)),
            opt(r.load_average, |v| format!("{v:.1}"))
        );
    }
    Ok(())
}

/// Per-module build and forward time and peak memory.
fn module_rows(a: &BenchArgs, modules: &[ModuleKey], report: &mut BenchReport) -> anyhow::Result<()> {
    let mut computes: Vec<Compute> = a.dtype.iter().map(|&p| Compute::fast(p)).collect();
    if a.plain {
        computes.push(Compute::Plain);
    }
    println!("\n{:<17} {:<28} {:>8} {:>9} {:>9} {:>6}  input", "module", "compute", "build s", "forward s", "peak MiB", "load");
    report.modules = bench::bench_modules(&a.config, modules, &computes, |r| {
        println!(
            "{:<17} {:<28} {:>8.2} {:>9.2} {:>9} {:>6}  {}",
            r.module,
            r.precision,
            r.build_seconds,
            r.forward_seconds,
            opt(r.peak_rss_mib, |v| format!("{v:.0}")),
            opt(r.load_average, |v| format!("{v:.1}")),
            r.input
        );
    })?;
    Ok(())
}

/// A guided sampler step of the flows (ss_flow, slat_flow), in full and on
/// the run's prepared conditions (keys and values once per run, the
/// constant-context shortcut for the all-zero neg_cond).
fn guided(a: &BenchArgs, modules: &[ModuleKey], report: &mut BenchReport) -> anyhow::Result<()> {
    let computes: Vec<Compute> = a.dtype.iter().map(|&p| Compute::fast(p)).collect();
    println!(
        "\n{:<10} {:<28} {:>8} {:>9} {:>8} {:>8} {:>10} {:>5} {:>10} {:>6}  input",
        "guided", "compute", "full s", "prepare s", "step s", "speed-up", "rel cond", "bits", "rel uncond", "load"
    );
    report.guided = bench::bench_guided(&a.config, modules, &computes, a.reps, true, |r| {
        println!(
            "{:<10} {:<28} {:>8.2} {:>9.2} {:>8.2} {:>7.3}× {:>10.1e} {:>5} {:>10.1e} {:>6}  {}",
            r.module,
            r.precision,
            r.full_seconds,
            r.prepare_seconds,
            r.step_seconds,
            r.full_seconds / r.step_seconds,
            r.max_rel_cond,
            if r.cond_same_bits { "same" } else { "diff" },
            r.max_rel_uncond,
            opt(r.load_average, |v| format!("{v:.1}")),
            r.input
        );
    })?;
    report.notes.push(
        "guided: one step of cond + zero neg_cond; full = everything computed in the step; step = on conditions prepared once per run \
         (prepare s, once per run); rel = max|a−b| / max|b| of the velocities against the full step, bits: whether the \
         conditional half has the full step's bits; slat_flow runs on the object voxel set of the stage2 section"
            .into(),
    );
    Ok(())
}

/// One full-size guided SLat-flow step on the realistic voxel set: FLOPs,
/// GFLOP/s against the peak, and where the time goes.
fn stage2(a: &BenchArgs, report: &mut BenchReport) -> anyhow::Result<()> {
    report.stage2 = flow_step(a, ModuleKey::SlatFlow)?;
    report.notes.push(
        "stage2: one guided SLat-flow step (cond + zero neg_cond, conditions prepared once, shortcuts on) on the object voxel set \
         (a recon synth bottle's surface voxels); GFLOP = GEMM + attention + sparse conv operations counted from each call's shapes; \
         peak = the GEMM precision's peak measured around the step; blocks = the transformer blocks alone; gemm/attn/conv/idx \
         (neighbour maps, down/upsampling)/norm = exclusive kernel time, glue = the rest; io = the sparse io blocks, inclusive"
            .into(),
    );
    Ok(())
}

/// One profiled guided SS-flow step, as `stage2` profiles the SLat flow.
fn stage1(a: &BenchArgs, report: &mut BenchReport) -> anyhow::Result<()> {
    report.stage1 = flow_step(a, ModuleKey::SsFlow)?;
    report.notes.push(
        "stage1: one guided SS-flow step (batch 2: cond + zero neg_cond, conditions prepared once, shortcuts on) on the module \
         bench's inputs; voxels = latent cells, tokens = patches + pose tokens; columns as in stage2"
            .into(),
    );
    Ok(())
}

/// The profiled guided step of one flow per precision of `--dtype`.
fn flow_step(a: &BenchArgs, key: ModuleKey) -> anyhow::Result<Vec<bench::Stage2Row>> {
    let computes: Vec<Compute> = a.dtype.iter().map(|&p| Compute::fast(p)).collect();
    let title = match key {
        ModuleKey::SsFlow => "stage1 (guided SS step)",
        _ => "stage2 (guided SLat step)",
    };
    println!(
        "\n{:<28} {:>6} {:>6} {:>7} {:>7} {:>8} {:>7} {:>6} {:>10} {:>6} {:>5} {:>5} {:>5} {:>5} {:>5} {:>5} {:>5} {:>6}",
        title,
        "voxels",
        "tokens",
        "step s",
        "GFLOP",
        "GFLOP/s",
        "peak",
        "peak%",
        "blocks G/s",
        "peak%",
        "gemm%",
        "attn%",
        "conv%",
        "idx%",
        "norm%",
        "glue%",
        "io%",
        "load"
    );
    let rows = bench::bench_flow_step(&a.config, key, &computes, a.reps, |r| {
        let pct = |s: f64| format!("{:.1}", 100.0 * s / r.step_seconds);
        let p = &r.profile;
        println!(
            "{:<28} {:>6} {:>6} {:>7.2} {:>7.0} {:>8.1} {:>7} {:>6} {:>10.1} {:>6} {:>5} {:>5} {:>5} {:>5} {:>5} {:>5} {:>5} {:>6}",
            r.precision,
            r.voxels,
            r.tokens,
            r.step_seconds,
            r.flops / 1e9,
            r.gflops,
            opt(r.peak_gflops, |v| format!("{v:.1}")),
            opt(r.efficiency, |e| format!("{:.0}", e * 100.0)),
            r.transformer_gflops,
            opt(r.transformer_efficiency, |e| format!("{:.0}", e * 100.0)),
            pct(p.gemm.seconds),
            pct(p.attention.seconds),
            pct(p.sparse_conv.seconds),
            pct(p.sparse_index.seconds),
            pct(p.norm.seconds),
            pct(r.glue_seconds),
            pct(r.io_blocks_seconds),
            opt(r.load_average, |v| format!("{v:.1}"))
        );
    })?;
    Ok(rows)
}

/// Each module's output error in bf16 / f16 against fast f32.
fn precision(a: &BenchArgs, modules: &[ModuleKey], report: &mut BenchReport) -> anyhow::Result<()> {
    println!("\n{:<17} {:<6} {:<9} {:>10} {:>10}", "module", "dtype", "vs", "max rel", "mean rel");
    let cmp_modules: Vec<ModuleKey> = modules.iter().copied().filter(|m| *m != ModuleKey::SsDecoder).collect();
    report.precision = bench::compare_precisions(&a.config, &cmp_modules, &a.dtype, |r| {
        println!("{:<17} {:<6} {:<9} {:>10.2e} {:>10.2e}", r.module, r.precision, r.reference, r.max_rel, r.mean_rel);
    })?;
    report.notes.push(
        "precision errors: max_rel = max|a−b| / max|b|, mean_rel = mean|a−b| / mean|b|, b = fast f32 output on the same input and weights"
            .into(),
    );
    Ok(())
}

/// Occupied voxels that flip between f32 and each lower precision.
fn occupancy(a: &BenchArgs, report: &mut BenchReport) -> anyhow::Result<()> {
    println!(
        "\n{:<6} {:>5} {:>8} {:>9} {:>9} {:>8} {:>10} {:>10} {:>10}",
        "dtype", "steps", "grid", "occ f32", "occupied", "flipped", "of grid", "of occ", "pose Δ"
    );
    for &p in a.dtype.iter().filter(|p| **p != Precision::F32) {
        let r = bench::compare_occupancy(&a.config, p, a.occupancy_steps, 0)?;
        println!(
            "{:<6} {:>5} {:>8} {:>9} {:>9} {:>8} {:>10.2e} {:>10.2e} {:>10.2e}",
            r.precision,
            r.steps,
            r.grid_voxels,
            r.occupied_f32,
            r.occupied,
            r.flipped,
            r.flip_fraction_of_grid,
            r.flip_fraction_of_occupied,
            r.pose_token_max_abs_diff
        );
        report.occupancy.push(r);
    }
    Ok(())
}

/// One object end to end per precision, with seconds and peak memory per stage.
fn end_to_end(a: &BenchArgs, report: &mut BenchReport) -> anyhow::Result<()> {
    println!("\nend to end (random weights, synthetic view, modules built per stage and freed):");
    for &p in &a.dtype {
        let r = bench::bench_end_to_end(&a.config, Compute::fast(p), a.steps, 0, !a.sampled_occupancy)?;
        let t = &r.timings;
        println!(
            "  {} | steps {}/{} | {} occupancy: {} voxels, {} stage-2 tokens | {:?} faces ({:?} after post-processing), {:?} gaussians | total {:.1} s + post {:.1} s (loading {:.1}) | peak RSS {} MiB | load {}",
            r.precision,
            r.ss_steps,
            r.slat_steps,
            r.occupancy,
            r.occupied_voxels,
            r.slat_tokens,
            r.faces,
            r.faces_after_postprocess,
            r.gaussians,
            t.total,
            r.postprocess_seconds,
            t.loading,
            opt(r.peak_rss_mib, |v| format!("{v:.0}")),
            opt(r.load_average, |v| format!("{v:.1}"))
        );
        println!(
            "    seconds per stage: DINOv2 {:.1}, stage-1 sampling {:.1}, SS decoder {:.1}, stage-2 sampling {:.1}, mesh decoder {:.1}, FlexiCubes {:.1}, Gaussian decoder {:.1}, post-processing {:.1}",
            t.image_encoder,
            t.ss_condition + t.ss_sampling,
            t.ss_decoder + t.pose,
            t.slat_condition + t.slat_sampling,
            t.mesh_decoder,
            t.flexicubes,
            t.gaussian_decoder,
            r.postprocess_seconds
        );
        if let Some(m) = &r.memory {
            let f = |v: Option<f64>| opt(v, |x| format!("{x:.0}"));
            println!(
                "    peak RSS MiB per stage: encoder {}, ss flow {}, ss dec {}, slat flow {}, mesh {}, gs {}",
                f(m.image_encoder),
                f(m.ss_flow),
                f(m.ss_decoder),
                f(m.slat_flow),
                f(m.mesh_decoder),
                f(m.gaussian_decoder)
            );
        }
        report.end_to_end.push(r);
    }
    Ok(())
}

/// `--released`: released-layout checkpoints against upstream's outputs.
fn released(a: &BenchArgs, dir: &Path, report: &mut BenchReport) -> anyhow::Result<()> {
    println!("\nreleased-layout checkpoints in {} against upstream's outputs on the same inputs:", dir.display());
    println!("{:<11} {:<28} {:<24} {:>9} {:>10} {:>10}", "module", "recon", "vs", "forward s", "max rel", "mean rel");
    let computes: Vec<Compute> = a.dtype.iter().map(|&p| Compute::fast(p)).collect();
    report.released = upstream::check_released(dir, &computes).with_context(|| format!("--released {}", dir.display()))?;
    for r in &report.released {
        println!(
            "{:<11} {:<28} {:<24} {:>9.2} {:>10.2e} {:>10.2e}",
            r.module, r.compute, r.reference, r.forward_seconds, r.max_rel, r.mean_rel
        );
    }
    Ok(())
}

/// The shape fit per object, and its share of stage-1 sampling.
fn shape_fit(a: &BenchArgs, arch: &recon::model::RecGenConfig, report: &mut BenchReport) -> anyhow::Result<()> {
    println!("\nshape fit per object (observe + fit in pose; nano decodes 32³, full size 64³):");
    println!(
        "{:>4} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9} {:>10} {:>8} {:>6}",
        "r", "points", "model", "shell", "carved", "filled", "fit s", "surface s", "faces", "load"
    );
    report.shape_fit = bench::bench_shape_fit(&[32, 64], a.reps.max(3))?;
    for r in &report.shape_fit {
        println!(
            "{:>4} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9.3} {:>10.3} {:>8} {:>6}",
            r.resolution,
            r.observed_points,
            r.model_voxels,
            r.shell_voxels,
            r.carved,
            r.filled,
            r.seconds,
            r.surface_seconds,
            r.surface_faces,
            opt(r.load_average, |v| format!("{v:.1}"))
        );
    }
    // Against stage-1 sampling: the config's steps × one guided SS-flow forward.
    let steps = arch.samplers.sparse_structure.steps;
    let full = report.shape_fit.iter().find(|r| r.resolution == 64);
    for m in report.modules.iter().filter(|m| m.module == ModuleKey::SsFlow.name()) {
        if let Some(f) = full {
            let stage1 = steps as f64 * m.forward_seconds;
            let added = f.seconds + f.surface_seconds;
            println!(
                "  64³ fit + surface {:.3} s = {:.3} % of stage-1 sampling ({} steps × {:.2} s guided step, {})",
                added,
                100.0 * added / stage1,
                steps,
                m.forward_seconds,
                m.precision
            );
        }
    }
    Ok(())
}

/// `recon synth` throughput and the renderer alone.
fn synth(a: &BenchArgs, report: &mut BenchReport) -> anyhow::Result<()> {
    let dir = std::env::temp_dir().join(format!("recon-bench-synth-{}", std::process::id()));
    eprintln!("synth: {} scenes…", a.synth_scenes);
    let r = bench::bench_synth(&dir, a.synth_scenes, 5)?;
    let b = r.target_occlusion_bins;
    println!(
        "\nsynth: {} scenes × 1 view, {}×{}, stereo sensor, {} threads: {:.2} s ({:.3} s/scene), {} GT instances, {} models | peak RSS {} MiB | load {}",
        r.scenes,
        r.width,
        r.height,
        r.threads,
        r.seconds,
        r.seconds / r.scenes.max(1) as f64,
        r.instances,
        r.models,
        opt(r.peak_rss_mib, |v| format!("{v:.0}")),
        opt(r.load_average, |v| format!("{v:.1}"))
    );
    println!("  target occlusion: 0-3% {} | 3-20% {} | 20-40% {} | 40-70% {} | >70% {}", b[0], b[1], b[2], b[3], b[4]);
    println!(
        "  render: {:.3} s per {}×{} view ({} units), {:.2} Mpixel/s",
        r.render_seconds,
        r.width,
        r.height,
        r.render_units,
        (r.width * r.height) as f64 / r.render_seconds / 1e6
    );
    report.synth = Some(r);
    Ok(())
}

/// Parameters per module and seconds per training step on toy data.
fn train(a: &BenchArgs, report: &mut BenchReport) -> anyhow::Result<()> {
    let cfg = &a.train_config;
    println!("\ntraining of {} (batch {}, {} timed steps after one warm-up):", cfg.display(), a.train_batch, a.train_steps);
    println!("{:<18} {:>12} {:>10}", "module", "parameters", "MB (f32)");
    report.train_params = bench::train_params(cfg).with_context(|| format!("--train-config {}", cfg.display()))?;
    for r in &report.train_params {
        let name = if r.shipped { r.module.clone() } else { format!("{} (train)", r.module) };
        println!("{name:<18} {:>12} {:>10.2}", r.parameters, r.parameters as f64 * 4.0 / 1e6);
    }
    let shipped: usize = report.train_params.iter().filter(|r| r.shipped).map(|r| r.parameters).sum();
    println!("{:<18} {shipped:>12} {:>10.2}", "shipped total", shipped as f64 * 4.0 / 1e6);
    println!(
        "{:<18} {:>10} {:>10} {:>10} {:>10} {:>9} {:>6}",
        "objective", "forward s", "backward s", "update s", "step s", "peak MiB", "load"
    );
    report.train = bench::bench_train(cfg, a.train_batch, a.train_steps, |r| {
        println!(
            "{:<18} {:>10.3} {:>10.3} {:>10.3} {:>10.3} {:>9} {:>6}",
            r.objective,
            r.forward_seconds,
            r.backward_seconds,
            r.update_seconds,
            r.forward_seconds + r.backward_seconds + r.update_seconds,
            opt(r.peak_rss_mib, |v| format!("{v:.0}")),
            opt(r.load_average, |v| format!("{v:.1}"))
        );
    })?;
    Ok(())
}

/// `--compare`: this run's module rows against an upstream report.
fn compare(path: &Path, report: &mut BenchReport) -> anyhow::Result<()> {
    let up = upstream::UpstreamReport::read(path).with_context(|| format!("--compare {}", path.display()))?;
    let here = report.machine.as_ref().map(|m| (m.cpu.clone(), m.threads));
    if here.as_ref() != Some(&(up.machine.cpu.clone(), up.machine.threads)) {
        println!(
            "\nwarning: {} was taken on `{}` with {} threads; this run: {:?} — ratios compare different set-ups",
            path.display(),
            up.machine.cpu,
            up.machine.threads,
            here
        );
    }
    let ours: Vec<upstream::TimingRow> = report.modules.iter().map(Into::into).collect();
    report.compare = upstream::compare(&ours, &up);
    if report.compare.is_empty() {
        println!("\n--compare: no module row of this run has an upstream row (run `--sections modules`)");
    } else {
        println!("\nrecon vs upstream PyTorch ({}; speed-up = upstream s / recon s):", path.display());
        println!(
            "{:<11} {:<22} {:>9} {:>11} {:>9} {:>10} {:>12}",
            "module", "precision", "recon s", "upstream s", "speed-up", "recon MiB", "upstream MiB"
        );
        for c in &report.compare {
            let mib = |v: Option<f64>| opt(v, |x| format!("{x:.0}"));
            println!(
                "{:<11} {:<22} {:>9.2} {:>11.2} {:>8.2}× {:>10} {:>12}",
                c.module,
                c.precision,
                c.recon_seconds,
                c.upstream_seconds,
                c.speedup,
                mib(c.recon_peak_mib),
                mib(c.upstream_peak_mib)
            );
        }
    }
    print_notes(report);
    Ok(())
}

fn print_notes(report: &BenchReport) {
    for n in &report.notes {
        println!("note: {n}");
    }
}

/// The report as JSON, written beside and renamed into place.
fn write_json(path: &Path, report: &BenchReport) -> anyhow::Result<()> {
    let text = serde_json::to_string_pretty(report)?;
    let tmp = path.with_extension("json.partial");
    std::fs::write(&tmp, text).with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, path).with_context(|| format!("writing {}", path.display()))?;
    println!("\nwrote {}", path.display());
    Ok(())
}

/// Ratios against the upstream table of issue 8 (throughput: recon/upstream;
/// time: upstream seconds / recon seconds; > 1 means recon is faster).
fn print_ratios(r: &BenchReport) {
    let mut lines = Vec::new();
    let gemm = |fmt: &str| r.gemm.iter().find(|g| g.what == "4096³" && g.format == fmt).map(|g| g.gflops);
    if let Some(g) = gemm("f32") {
        lines.push(format!(
            "GEMM 4096³ f32: {g:.0} GFLOP/s = {:.2}× upstream MKL ({}), {:.2}× stock candle there ({})",
            g / bench::upstream::GEMM_4096_F32_GFLOPS,
            bench::upstream::GEMM_4096_F32_GFLOPS,
            g / bench::upstream::CANDLE_4096_F32_GFLOPS,
            bench::upstream::CANDLE_4096_F32_GFLOPS
        ));
    }
    if let Some(g) = gemm("bf16") {
        lines.push(format!(
            "GEMM 4096³ bf16: {g:.0} GFLOP/s = {:.2}× upstream oneDNN AMX ({}), {:.2}× stock candle there ({})",
            g / bench::upstream::GEMM_4096_BF16_GFLOPS,
            bench::upstream::GEMM_4096_BF16_GFLOPS,
            g / bench::upstream::CANDLE_4096_BF16_GFLOPS,
            bench::upstream::CANDLE_4096_BF16_GFLOPS
        ));
    }
    if let Some(c) = r.gemm.iter().find(|g| g.isa == "candle") {
        if let Some(g) = gemm("f32") {
            lines.push(format!("GEMM 4096³ f32 here: recon {g:.0} vs stock candle {:.0} GFLOP/s ({:.2}×)", c.gflops, g / c.gflops));
        }
    }
    let module =
        |key: ModuleKey, prec: &str| r.modules.iter().find(|m| m.module == key.name() && m.precision.starts_with(&format!("fast {prec}")));
    for (key, prec, up_s, up_gb) in [
        (ModuleKey::SsFlow, "f32", bench::upstream::SS_FLOW_F32_S, bench::upstream::SS_FLOW_F32_GB),
        (ModuleKey::SsFlow, "bf16", bench::upstream::SS_FLOW_BF16_S, bench::upstream::SS_FLOW_BF16_GB),
        (ModuleKey::SsDecoder, "f32", bench::upstream::SS_DECODER_F32_S, bench::upstream::SS_DECODER_F32_GB),
    ] {
        if let Some(m) = module(key, prec) {
            lines.push(format!(
                "{key} {prec}: {:.1} s → upstream/recon = {:.2} (upstream {up_s} s); peak {} GB (upstream {up_gb} GB)",
                m.forward_seconds,
                up_s / m.forward_seconds,
                opt(m.peak_rss_mib, |v| format!("{:.2}", v / 1024.0))
            ));
        }
    }
    if !lines.is_empty() {
        println!("\nratios vs issue 8's upstream figures (different machine: see notes):");
        for l in lines {
            println!("  {l}");
        }
    }
    print_notes(r);
}
