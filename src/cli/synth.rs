//! `recon synth`: a BOP-format dataset of occluded tabletop RGB-D scenes with exact GT.
use recon::synth::SynthOptions;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct SynthArgs {
    /// Output dataset folder (a BOP dataset root: models/, test/<scene>/, camera.json).
    #[arg(long)]
    out: PathBuf,
    /// Number of scenes.
    #[arg(long, default_value_t = SynthOptions::default().scenes)]
    scenes: usize,
    /// Camera views per scene (view 0 is the one whose target occlusion is aimed).
    #[arg(long, default_value_t = SynthOptions::default().views)]
    views: usize,
    #[arg(long, default_value_t = SynthOptions::default().seed)]
    seed: u64,
    /// Depth sensor model JSON (see models/sensors/); default: ideal depth.
    #[arg(long)]
    sensor: Option<PathBuf>,
    #[arg(long, default_value_t = SynthOptions::default().width)]
    width: usize,
    #[arg(long, default_value_t = SynthOptions::default().height)]
    height: usize,
    /// Write composite objects (mug, bottle) as their rigid parts, one model and GT
    /// instance per part.
    #[arg(long)]
    parts: bool,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: SynthArgs) -> anyhow::Result<bool> {
    use anyhow::Context;
    use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
    use recon::sensor::SensorModel;
    use recon::synth::generate;
    use std::io::IsTerminal;
    if let Some(n) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("--threads")?;
    }
    let sensor = match &a.sensor {
        Some(p) => SensorModel::load(p).with_context(|| format!("--sensor {}", p.display()))?,
        None => SensorModel::ideal(),
    };
    let opts = SynthOptions { scenes: a.scenes, views: a.views, seed: a.seed, width: a.width, height: a.height, parts: a.parts, sensor };
    let bar = ProgressBar::with_draw_target(
        Some(2 * a.scenes as u64),
        if std::io::stderr().is_terminal() { ProgressDrawTarget::stderr() } else { ProgressDrawTarget::hidden() },
    );
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:40}] {pos}/{len} scene steps (generate + render) {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let t0 = std::time::Instant::now();
    let summary = generate(&a.out, &opts, &|| bar.inc(1)).with_context(|| format!("recon synth --out {}", a.out.display()))?;
    bar.finish_and_clear();
    let secs = t0.elapsed().as_secs_f64();
    if a.json {
        println!("{}", serde_json::to_string_pretty(&serde_json::json!({"out": a.out, "seconds": secs, "summary": summary}))?);
    } else {
        let b = summary.target_occlusion_bins;
        println!(
            "wrote {}: {} scenes, {} images, {} GT instances, {} models in {:.1} s",
            a.out.display(),
            summary.scenes,
            summary.images,
            summary.instances,
            summary.models,
            secs
        );
        println!(
            "objects per scene: min {} mean {:.1} max {}",
            summary.objects_per_scene[0], summary.objects_per_scene[1], summary.objects_per_scene[2]
        );
        let kinds: Vec<String> = summary.objects_by_kind.iter().map(|(k, n)| format!("{k} {n}")).collect();
        println!("objects by kind: {}", kinds.join(", "));
        println!("target occlusion (images): 0-3% {} | 3-20% {} | 20-40% {} | 40-70% {} | >70% {}", b[0], b[1], b[2], b[3], b[4]);
        if summary.depth_clipped_px > 0 {
            println!("note: {} depth pixels beyond 6.55 m were written as missing", summary.depth_clipped_px);
        }
    }
    Ok(true)
}
