//! `recon eval`: score predictions (or a built-in baseline) against a BOP-format or
//! YCB-Video dataset; prints the occlusion-binned table, writes report JSON + SVG plot.
use crate::cli::model_args::ModelArgs;
use recon::eval::EvalOptions;
use std::path::PathBuf;

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum Method {
    /// Visible depth points → oriented bounding box (pose) + convex hull (shape).
    Observed,
    /// The model (`--weights DIR`, a trained folder with its architecture file) on every GT
    /// instance's visible mask, as `recon infer` runs it.
    Recgen,
}

#[derive(Clone, Copy, clap::ValueEnum)]
pub enum ShapeArg {
    Hull,
    Box,
}

#[derive(clap::Args)]
pub struct EvalArgs {
    /// Dataset: a BOP split or dataset folder (from `recon synth`, or a real BOP dataset),
    /// or a YCB-Video folder (sequences + models_points_xyz/).
    #[arg(long)]
    dataset: PathBuf,
    /// Predictions JSON (format in the `recon::eval` docs).
    #[arg(long, conflicts_with = "method", required_unless_present = "method")]
    predictions: Option<PathBuf>,
    /// Run a built-in predictor on every frame instead of reading predictions; its
    /// predictions file and meshes are written to --out for re-scoring.
    #[arg(long, value_enum)]
    method: Option<Method>,
    /// Shape output by --method observed.
    #[arg(long, value_enum, default_value = "hull")]
    shape: ShapeArg,
    /// Output folder (report.json, report.txt, plot.svg; with --method also
    /// predictions.json + meshes/). Default with --method: `<dataset name>-<method>-eval`
    /// in the current folder; with --predictions: print only.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the whole report as JSON instead of the table.
    #[arg(long)]
    json: bool,
    /// F1 distance threshold as a fraction of the GT diameter.
    #[arg(long, default_value_t = EvalOptions::default().f1_tau_rel)]
    f1_tau: f64,
    /// Only these scenes (comma-separated; `48` matches `000048`).
    #[arg(long, value_delimiter = ',')]
    scenes: Option<Vec<String>>,
    /// Only GT instances occluded LO–HI percent (`20-70`: 20 ≤ occlusion < 70); with
    /// --method, only those are reconstructed.
    #[arg(long, value_name = "LO-HI", value_parser = parse_occlusion)]
    occlusion: Option<[f64; 2]>,
    /// Surface samples per mesh.
    #[arg(long, default_value_t = EvalOptions::default().n_samples)]
    surface_samples: usize,
    /// Surface-sampling seed.
    #[arg(long, default_value_t = EvalOptions::default().seed)]
    surface_seed: u64,
    /// Score every frame of the dataset, also frames without any prediction (always on
    /// with --method).
    #[arg(long)]
    all_frames: bool,
    /// --method recgen: the model and its settings (the same flags and defaults as
    /// `recon infer`).
    #[command(flatten)]
    model: ModelArgs,
    /// --method recgen: two-view conditioning: each frame with the next frame of its scene
    /// (needs cam_R_w2c/cam_t_w2c), the pose chosen across both views.
    #[arg(long)]
    two_view: bool,
    /// --method recgen: N views: each frame with the next N−1 frames of its scene (fewer
    /// when the scene has fewer; relative poses from cam_R_w2c/cam_t_w2c); 2 is --two-view.
    /// More views than the model takes at once run as fused pairs (--fusion, --slat-fusion).
    #[arg(long, conflicts_with = "two_view", value_parser = clap::value_parser!(u64).range(1..=(recon::engine::MAX_SECOND_VIEWS as u64 + 1)))]
    views: Option<u64>,
    /// Depth correction written by `recon audit depth` (`depth_correction.json`), applied
    /// to every frame's depth before --method runs on it; a drift correction uses the
    /// frame's position in the dataset (the audit's frame index).
    #[arg(long, value_name = "FILE")]
    depth_correction: Option<PathBuf>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
}

/// `LO-HI` in percent, 0 ≤ LO < HI ≤ 100.
fn parse_occlusion(v: &str) -> Result<[f64; 2], String> {
    let bad = || format!("`{v}`: expected LO-HI in percent, 0 ≤ LO < HI ≤ 100 (e.g. 20-70)");
    let (lo, hi) = v.split_once('-').ok_or_else(bad)?;
    let (lo, hi): (f64, f64) = (lo.trim().parse().map_err(|_| bad())?, hi.trim().parse().map_err(|_| bad())?);
    if !((0.0..100.0).contains(&lo) && hi > lo && hi <= 100.0) {
        return Err(bad());
    }
    Ok([lo, hi])
}

/// `<dataset folder name>-<method>-eval` in the current folder.
fn default_out(dataset: &std::path::Path, method: &str) -> PathBuf {
    let name = dataset
        .canonicalize()
        .ok()
        .and_then(|p| p.file_name().map(|s| s.to_string_lossy().into_owned()))
        .unwrap_or_else(|| "dataset".into());
    PathBuf::from(format!("{name}-{method}-eval"))
}

/// Removes a staging folder left by a failed run (after success it has been renamed away).
struct Staging(Option<PathBuf>);

impl Drop for Staging {
    fn drop(&mut self) {
        if let Some(p) = self.0.as_ref().filter(|p| p.exists()) {
            let _ = std::fs::remove_dir_all(p);
        }
    }
}

pub fn run(a: EvalArgs) -> anyhow::Result<bool> {
    use anyhow::{bail, Context};
    use recon::dataset::load_dataset;
    use recon::engine::{begin_output, finish_output};
    use recon::eval::{evaluate, read_predictions};
    use recon::eval::{observe_dataset_corrected, ObservedOptions, Shape};
    if let Some(n) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("--threads")?;
    }
    if !(a.f1_tau > 0.0 && a.f1_tau <= 1.0) {
        bail!("--f1-tau {} must be a fraction of the diameter in (0, 1]", a.f1_tau);
    }
    if a.surface_samples == 0 {
        bail!("--surface-samples must be positive");
    }
    let mut ds = load_dataset(&a.dataset).with_context(|| format!("loading dataset {}", a.dataset.display()))?;
    if a.depth_correction.is_some() && a.method.is_none() {
        bail!("--depth-correction applies to --method observed|recgen (predictions are already made)");
    }
    // Frame indices from the whole dataset, as the audit numbers them, before --scenes.
    let correction = match &a.depth_correction {
        Some(p) => {
            let c = recon::sensor::DepthCorrection::load(p)?;
            eprintln!("depth correction {}: {}", p.display(), c.describe());
            Some(recon::eval::DatasetCorrection::new(c, &ds))
        }
        None => None,
    };
    let correction_json = correction.as_ref().map(|c| serde_json::json!({"file": a.depth_correction, "correction": c.correction}));
    if let Some(s) = &a.scenes {
        ds.retain_scenes(s)?;
    }
    let opts = EvalOptions {
        n_samples: a.surface_samples,
        seed: a.surface_seed,
        f1_tau_rel: a.f1_tau,
        all_frames: a.all_frames || a.method.is_some(),
        occlusion: a.occlusion,
        ..Default::default()
    };
    if a.two_view && !matches!(a.method, Some(Method::Recgen)) {
        bail!("--two-view applies to --method recgen only");
    }
    if a.views.is_some() && !matches!(a.method, Some(Method::Recgen)) {
        bail!("--views applies to --method recgen only");
    }
    let views = a.views.map_or(if a.two_view { 2 } else { 1 }, |n| n as usize);
    let (report, out, staging, index) = match (a.method, &a.predictions) {
        (Some(Method::Observed), _) => {
            let shape = match a.shape {
                ShapeArg::Hull => Shape::Hull,
                ShapeArg::Box => Shape::Box,
            };
            let out = a.out.clone().unwrap_or_else(|| default_out(&a.dataset, "observed"));
            let staging = Staging(Some(begin_output(&out)?));
            let dir = staging.0.clone().unwrap_or_default();
            let t0 = std::time::Instant::now();
            let run = observe_dataset_corrected(&ds, &ObservedOptions { shape, ..Default::default() }, correction.as_ref())?;
            let n_box = run.predictions.iter().filter(|p| p.observed.shape == Shape::Box).count();
            eprintln!(
                "observed baseline: {} predictions ({} as box) on {} frames, {} GT instances skipped, {:.1} s",
                run.predictions.len(),
                n_box,
                ds.frames.len(),
                run.skipped.len(),
                t0.elapsed().as_secs_f64()
            );
            for s in run.skipped.iter().take(10) {
                eprintln!("  skipped scene {} frame {} gt {} (obj {}): {}", s.scene, s.frame, s.gt_index, s.obj_id, s.reason);
            }
            if run.skipped.len() > 10 {
                eprintln!("  … {} more in recon-output.json", run.skipped.len() - 10);
            }
            let pf = run.write(&dir)?;
            let t1 = std::time::Instant::now();
            // Score what was written (JSON-parsed poses), so re-scoring the folder with
            // --predictions reproduces these numbers to the last bit.
            let mut report = evaluate(&ds, &read_predictions(&pf)?, &pf, &opts)?;
            eprintln!("scored {} GT instances in {:.1} s", report.objects.len(), t1.elapsed().as_secs_f64());
            report.predictions = out.join("predictions.json").display().to_string();
            let index = serde_json::json!({ "kind": "recon eval --method observed", "shape": shape, "skipped": run.skipped,
                "depth_correction": correction_json, "recon_version": recon::VERSION });
            (report, Some(out), staging, index)
        }
        (Some(Method::Recgen), _) => {
            let source = a.model.source()?;
            a.model.note_default_model();
            let engine = recon::engine::Engine::load(&source, &a.model.load_options(&source)?)
                .with_context(|| format!("loading the model ({source:?})"))?;
            let io = a.model.infer_settings()?;
            let out = a.out.clone().unwrap_or_else(|| default_out(&a.dataset, "recgen"));
            let staging = Staging(Some(begin_output(&out)?));
            let dir = staging.0.clone().unwrap_or_default();
            let t0 = std::time::Instant::now();
            let run = recon::eval::recgen_dataset_corrected(&ds, &engine, &io, views, a.occlusion, correction.as_ref(), &|done, total| {
                if done % 10 == 0 || done == total {
                    eprintln!("  {done}/{total} frames, {:.0} s", t0.elapsed().as_secs_f64());
                }
            })?;
            eprintln!(
                "recgen: {} predictions on {} frames, {} GT instances skipped, {:.1} s ({:.1} s in the model)",
                run.predictions.len(),
                ds.frames.len(),
                run.skipped.len(),
                t0.elapsed().as_secs_f64(),
                run.seconds_model
            );
            for s in run.skipped.iter().take(10) {
                eprintln!("  skipped scene {} frame {} gt {} (obj {}): {}", s.scene, s.frame, s.gt_index, s.obj_id, s.reason);
            }
            let pf = run.write(&dir)?;
            let mut report = evaluate(&ds, &read_predictions(&pf)?, &pf, &opts)?;
            report.predictions = out.join("predictions.json").display().to_string();
            let index = serde_json::json!({
                "kind": "recon eval --method recgen", "model": a.model, "config": source.architecture()?, "two_view": a.two_view, "views": views, "skipped": run.skipped,
                "seconds_model": run.seconds_model, "depth_correction": correction_json,
                "poses": run.predictions.iter().map(|p| p.pose_record()).collect::<Vec<_>>(),
                "recon_version": recon::VERSION, "model_identity": engine.pipeline.identity(),
            });
            (report, Some(out), staging, index)
        }
        (None, Some(p)) => {
            let mut preds = read_predictions(p)?;
            if a.scenes.is_some() {
                let before = preds.predictions.len();
                preds.predictions.retain(|q| ds.frames.iter().any(|f| f.scene == q.scene));
                if preds.predictions.len() < before {
                    eprintln!("--scenes: {} predictions of other scenes left out", before - preds.predictions.len());
                }
            }
            let staging = Staging(a.out.as_ref().map(|o| begin_output(o)).transpose()?);
            let t1 = std::time::Instant::now();
            let report = evaluate(&ds, &preds, p, &opts)?;
            eprintln!("scored {} GT instances in {:.1} s", report.objects.len(), t1.elapsed().as_secs_f64());
            (report, a.out.clone(), staging, serde_json::json!({ "kind": "recon eval --predictions", "recon_version": recon::VERSION }))
        }
        (None, None) => bail!("give --predictions FILE or --method observed|recgen"),
    };
    if a.json {
        println!("{}", report.to_json()?);
    } else {
        print!("{}", report.text_table());
    }
    if let (Some(out), Some(dir)) = (out, staging.0.as_ref()) {
        report.write_files(dir)?;
        finish_output(dir, &out, &index)?;
        eprintln!("wrote {}", out.display());
    }
    Ok(true)
}
