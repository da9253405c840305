//! `recon train ss-vae|ss-flow|slat-ae|slat-flow`: train a model on BOP-format data
//! (what `recon synth` writes). Recipe and outputs: `recon::train`.
use std::path::PathBuf;

use clap::{Args, ValueEnum};

#[derive(Clone, Copy, ValueEnum)]
pub enum StageArg {
    /// Sparse-structure VAE (encoder + decoder) on voxelised object models.
    SsVae,
    /// Image encoder + sparse-structure flow with pose tokens (needs --vae).
    SsFlow,
    /// Structured-latent autoencoder: SLat encoder + mesh and Gaussian decoders, supervised by exact SDF and colours.
    SlatAe,
    /// Structured-latent flow on the frozen slat-ae encoder's latents (needs --stage1 and --slat-ae); writes the complete model folder.
    SlatFlow,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum FillArg {
    Solid,
    Surface,
}

#[derive(Args)]
pub struct TrainArgs {
    stage: StageArg,
    /// Architecture file (with an `ss_encoder` section).
    #[arg(long, default_value = "models/recgen-nano.json")]
    config: PathBuf,
    /// BOP dataset folder: its `train/` (or the folder itself) holds the scenes, `models/` the PLY models.
    #[arg(long)]
    data: PathBuf,
    /// Scenes folder, when not `<data>/train` or `<data>`.
    #[arg(long)]
    split: Option<PathBuf>,
    /// Models folder, when not `<data>/models`.
    #[arg(long)]
    models: Option<PathBuf>,
    /// Output folder (new or empty; with --resume, the run's own folder).
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = 2000)]
    steps: usize,
    #[arg(long, default_value_t = 8)]
    batch: usize,
    #[arg(long, default_value_t = 2e-4)]
    lr: f64,
    #[arg(long, default_value_t = 0.0)]
    weight_decay: f64,
    /// Global gradient-norm clip (0: off).
    #[arg(long, default_value_t = 1.0)]
    grad_clip: f64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Continue from the newest checkpoint in --out, or from the given checkpoint folder.
    #[arg(long, num_args = 0..=1)]
    resume: Option<Option<PathBuf>>,
    #[arg(long, default_value_t = 250)]
    checkpoint_every: usize,
    /// ss-flow: output folder of `recon train ss-vae`.
    #[arg(long)]
    vae: Option<PathBuf>,
    /// Occupancy target: solid (surface + interior) or surface shell.
    #[arg(long, value_enum, default_value = "solid")]
    fill: FillArg,
    /// Skip instances with a smaller visible fraction (scene_gt_info.json).
    #[arg(long, default_value_t = 0.1)]
    min_visib: f64,
    /// ss-flow: probability of a two-view batch (when the data has second views).
    #[arg(long, default_value_t = 0.5)]
    p_two_view: f64,
    /// ss-flow: classifier-free-guidance condition dropout.
    #[arg(long, default_value_t = 0.1)]
    p_uncond: f64,
    /// ss-flow: weight of the pose velocity loss.
    #[arg(long, default_value_t = 0.01)]
    pose_alpha: f64,
    /// slat-ae: crop side in voxels (0: whole objects).
    #[arg(long, default_value_t = 10)]
    crop: usize,
    /// slat-ae: most active voxels per crop.
    #[arg(long, default_value_t = 400)]
    max_voxels: usize,
    /// slat-flow: output folder of `recon train ss-flow`.
    #[arg(long)]
    stage1: Option<PathBuf>,
    /// slat-flow: output folder of `recon train slat-ae`.
    #[arg(long)]
    slat_ae: Option<PathBuf>,
    /// slat-flow: most object models encoded.
    #[arg(long, default_value_t = 1000)]
    max_models: usize,
    /// Warm start: initialise the trained modules from this finished run of the same stage (fresh optimiser; settings may differ).
    #[arg(long)]
    init: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
}

pub fn run(a: TrainArgs) -> anyhow::Result<bool> {
    use anyhow::Context;
    use recon::geometry::Fill;
    use recon::train::TrainingSource;
    use recon::train::{run, Resume, Stage, TrainOptions};
    use recon::train::{BopOptions, BopSource};
    if let Some(n) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("--threads")?;
    }
    let split = a.split.clone().unwrap_or_else(|| if a.data.join("train").is_dir() { a.data.join("train") } else { a.data.clone() });
    let models = a.models.clone().unwrap_or_else(|| a.data.join("models"));
    let stage = match a.stage {
        StageArg::SsVae => Stage::SsVae,
        StageArg::SsFlow => Stage::SsFlow,
        StageArg::SlatAe => Stage::SlatAe,
        StageArg::SlatFlow => Stage::SlatFlow,
    };
    let source = BopSource::open(&split, &models, &BopOptions { min_visib_fract: a.min_visib, second_view: true })
        .with_context(|| format!("reading training data from {}", split.display()))?;
    let mut o = TrainOptions::new(stage, a.config.clone(), a.out.clone());
    o.settings.steps = a.steps;
    o.settings.batch = a.batch;
    o.settings.lr = a.lr;
    o.settings.weight_decay = a.weight_decay;
    o.settings.grad_clip = (a.grad_clip > 0.0).then_some(a.grad_clip);
    o.settings.seed = a.seed;
    o.settings.checkpoint_every = a.checkpoint_every;
    o.fill = match a.fill {
        FillArg::Solid => Fill::Solid,
        FillArg::Surface => Fill::Surface,
    };
    o.flow.p_uncond = a.p_uncond;
    o.flow.pose_alpha = a.pose_alpha;
    o.p_two_view = a.p_two_view;
    o.vae = a.vae.clone();
    o.crop = a.crop;
    o.max_voxels = a.max_voxels;
    o.stage1 = a.stage1.clone();
    o.slat_ae = a.slat_ae.clone();
    o.max_models = a.max_models;
    o.init = a.init.clone();
    o.resume = a.resume.as_ref().map(|p| match p {
        None => Resume::Latest,
        Some(dir) => Resume::Dir(dir.clone()),
    });
    eprintln!("recon train {}: {} → {}", stage.name(), source.describe(), a.out.display());
    let r = run(&source, &o).with_context(|| format!("recon train {}", stage.name()))?;
    for n in &r.notes {
        eprintln!("  {n}");
    }
    let params: usize = r.params.values().sum();
    eprintln!("  parameters: {params} ({:?})", r.params);
    if let Some(s) = &r.summary {
        eprintln!(
            "  steps {}..{}: final loss {:.5}, {:.3} s/step, {:.1} s in all",
            s.first_step,
            s.last_step,
            s.final_loss.unwrap_or(f64::NAN),
            s.mean_step_seconds,
            s.seconds
        );
    }
    if let (Some(b), Some(e)) = (r.eval_before, r.eval_after) {
        eprintln!("  fixed-batch loss: {b:.5} before, {e:.5} after");
    }
    for f in &r.files {
        println!("{}", f.display());
    }
    Ok(true)
}
