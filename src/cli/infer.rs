//! `recon infer`: RGB-D frame(s) + masks → posed meshes, Gaussians and poses.
use crate::cli::model_args::ModelArgs;
use std::path::{Path, PathBuf};

#[derive(clap::Args)]
pub struct InferArgs {
    /// Colour image. Depth and intrinsics are found beside it (`X.depth.png` + `X.json`,
    /// `NNNNNN-color.png` + `-depth.png` + `-meta.mat`, BOP `rgb/ depth/ scene_camera.json`,
    /// `rgb.png` + `depth.png` + `camera.json`) unless given explicitly.
    #[arg(long)]
    rgbd: PathBuf,
    /// Instance-id PNG (0 = background), or several binary mask files.
    #[arg(long, num_args = 1.., required = true)]
    masks: Vec<PathBuf>,
    /// Instance ids to reconstruct (default: all present). Applies to both views.
    #[arg(long, value_delimiter = ',')]
    objects: Option<Vec<u32>>,
    /// Depth image (16-bit PNG).
    #[arg(long)]
    depth: Option<PathBuf>,
    /// Intrinsics: `fx,fy,cx,cy` or a JSON file.
    #[arg(long)]
    intrinsics: Option<String>,
    /// Metres per depth unit (e.g. 0.001 for millimetres).
    #[arg(long)]
    depth_scale: Option<f64>,
    /// Second view's colour image (same conventions as --rgbd): two-view conditioning.
    /// Results are reported in the camera frame of --rgbd.
    #[arg(long, requires_all = ["masks2", "rel_pose"])]
    view2: Option<PathBuf>,
    /// Second view's masks (instance-id PNG or binary masks). Objects are matched to
    /// --masks by instance id, or by file order for binary masks.
    #[arg(long, num_args = 1.., requires = "view2")]
    masks2: Vec<PathBuf>,
    /// Second view's depth image.
    #[arg(long, requires = "view2")]
    depth2: Option<PathBuf>,
    /// Second view's intrinsics: `fx,fy,cx,cy` or a JSON file.
    #[arg(long, requires = "view2")]
    intrinsics2: Option<String>,
    /// Second view's metres per depth unit.
    #[arg(long, requires = "view2")]
    depth_scale2: Option<f64>,
    /// Relative camera pose T_c1_c2, camera 2 → camera 1 (x_cam1 = R·x_cam2 + t, metres):
    /// 16 numbers of the 4×4 matrix, row-major, or a JSON file with "T_c1_c2" (4×4 rows).
    #[arg(long, requires = "view2", allow_hyphen_values = true)]
    rel_pose: Option<String>,
    /// A view besides --rgbd's, repeatable: a JSON file {"rgb", "masks", "T_c1_ci" (this
    /// camera → the --rgbd camera, 4×4), optional "depth", "intrinsics", "depth_scale"};
    /// relative paths are taken from the file's folder (docs/infer.md). Views count from 2
    /// (after --view2). More views than the model takes at once run as fused (anchor,
    /// view) pairs: --fusion, --slat-fusion.
    #[arg(long = "view", value_name = "JSON")]
    views: Vec<PathBuf>,
    /// Depth correction written by `recon audit depth` (`depth_correction.json`): the
    /// fitted registration shift, extrinsic rotation, depth scale/offset, radial
    /// distortion and drift are undone on every view's depth before anything else.
    #[arg(long, value_name = "FILE")]
    depth_correction: Option<PathBuf>,
    /// The frame's index in the audited dataset, for a drift correction (default 0).
    #[arg(long, value_name = "N", default_value_t = 0, requires = "depth_correction")]
    depth_correction_frame: i64,
    #[command(flatten)]
    model: ModelArgs,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Output directory (default: `<image stem>_recon` beside the input).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
    /// Also write `preview.png`: the input beside the posed meshes ray-cast from its camera.
    #[arg(long)]
    preview: bool,
    /// Also write RecGen's `save` files per object (`mesh.obj`, `posed_mesh.obj`, `gaussian.ply`,
    /// `posed_gaussian.ply`, `overlay.png`, `metadata.json`), as `recgen_inference` lays them out.
    #[arg(long)]
    recgen_files: bool,
}

fn frame_options(
    depth: &Option<PathBuf>,
    intrinsics: &Option<String>,
    scale: Option<f64>,
    flag: &str,
) -> anyhow::Result<recon::dataset::FrameOptions> {
    use recon::dataset::{FrameOptions, Intrinsics};
    let mut fo = FrameOptions { depth: depth.clone(), depth_scale_m: scale, ..Default::default() };
    if let Some(k) = intrinsics {
        let nums: Vec<f64> = k.split(',').filter_map(|v| v.trim().parse().ok()).collect();
        if nums.len() == 4 && k.split(',').count() == 4 {
            fo.intrinsics = Some(Intrinsics::new(nums[0], nums[1], nums[2], nums[3])?);
        } else if Path::new(k).is_file() {
            fo.intrinsics_file = Some(PathBuf::from(k));
        } else {
            anyhow::bail!("{flag} `{k}`: expected fx,fy,cx,cy or an intrinsics JSON file");
        }
    }
    Ok(fo)
}

use recon::engine::stage_seconds as stage_row;
use recon::engine::STAGE_COLUMNS as STAGES;

/// A terminal progress bar (hidden unless both stdout and stderr are terminals).
struct Bar {
    pb: indicatif::ProgressBar,
    state: std::sync::Mutex<BarState>,
}

#[derive(Default)]
struct BarState {
    label: String,
    object: (usize, usize),
    seed: u64,
    stage: Option<(recon::engine::Stage, std::time::Instant)>,
    what: &'static str,
    done: Vec<String>,
}

impl Bar {
    fn new(units: u64) -> Self {
        use std::io::IsTerminal;
        let pb = if std::io::stdout().is_terminal() && std::io::stderr().is_terminal() {
            let pb = indicatif::ProgressBar::new(units);
            pb.set_style(
                indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:24} {pos}/{len} {msg}")
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            );
            pb.enable_steady_tick(std::time::Duration::from_millis(200));
            pb
        } else {
            indicatif::ProgressBar::hidden()
        };
        Bar { pb, state: Default::default() }
    }

    fn event(&self, e: recon::engine::Progress) {
        use recon::engine::Progress;
        let Ok(mut s) = self.state.lock() else { return };
        let close_stage = |s: &mut BarState| {
            if let Some((st, t0)) = s.stage.take() {
                s.done.push(format!("{} {:.1}s", st.name(), t0.elapsed().as_secs_f64()));
            }
        };
        match e {
            Progress::Object { index, total, label } => {
                s.label = label.to_string();
                s.object = (index + 1, total);
                s.done.clear();
                s.what = "preparing";
            }
            Progress::Sample { index, seed, .. } => {
                close_stage(&mut s);
                s.what = "starting";
                if index > 0 {
                    self.pb.inc(1);
                }
                s.seed = seed;
            }
            Progress::Stage(st) => {
                close_stage(&mut s);
                s.stage = Some((st, std::time::Instant::now()));
                s.what = st.name();
            }
            Progress::Decimating => {
                close_stage(&mut s);
                s.what = "decimating";
            }
            Progress::Selecting => s.what = "scoring poses",
            Progress::ObjectDone { label, seconds } => {
                close_stage(&mut s);
                self.pb.inc(1);
                self.pb.println(format!("{label}: {seconds:.1} s ({})", s.done.join(", ")));
                s.done.clear();
            }
        }
        let seed = if s.what == "preparing" { String::new() } else { format!(" seed {}", s.seed) };
        self.pb.set_message(format!("{} [{}/{}]{seed}: {}", s.label, s.object.0, s.object.1, s.what));
    }
}

/// Exit status of `recon infer` (README "Exit codes"): every object written.
pub const EXIT_ALL: i32 = 0;
/// Some objects were written, others failed or were skipped (listed in the index file).
pub const EXIT_SOME: i32 = 3;
/// No object could be reconstructed (the index file lists why).
pub const EXIT_NONE: i32 = 2;

/// The exit status for `done` objects written and `failed` not.
pub fn exit_code(done: usize, failed: usize) -> i32 {
    match (done, failed) {
        (0, _) => EXIT_NONE,
        (_, 0) => EXIT_ALL,
        _ => EXIT_SOME,
    }
}

/// Runs `recon infer`; returns the exit status ([`exit_code`]); a fatal
/// error (bad input, unwritable output) is an `Err` (exit status 1).
pub fn run(a: InferArgs) -> anyhow::Result<i32> {
    use anyhow::Context;
    use recon::dataset::RgbdFrame;
    use recon::engine::{write_outputs_with, OutputOptions};
    use recon::engine::{Engine, SecondView};
    use recon::geometry::parse_rel_pose;
    if let Some(n) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("--threads")?;
    }
    let opts = a.model.infer_settings()?;
    let correction = a.depth_correction.as_deref().map(recon::sensor::DepthCorrection::load).transpose()?;
    if let Some(c) = &correction {
        eprintln!("depth correction: {} (frame index {})", c.describe(), a.depth_correction_frame);
    }
    let correct = |f: &mut RgbdFrame| {
        if let Some(c) = &correction {
            c.apply_to_frame(f, a.depth_correction_frame);
        }
    };
    let mut frame = RgbdFrame::open(&a.rgbd, &frame_options(&a.depth, &a.intrinsics, a.depth_scale, "--intrinsics")?)?;
    correct(&mut frame);
    let (objects, mut skipped) = recon::dataset::load_masks(&a.masks, a.objects.as_deref())?;
    // View 1's unreadable or unusable masks are objects that failed; another view's only cost that view.
    let failed_masks = skipped.len();
    // The other views: --view2, then every --view, counted before any is read.
    recon::engine::check_view_count(a.view2.iter().count() + a.views.len())?;
    let mut others = Vec::new();
    if let Some(v2) = &a.view2 {
        let mut f2 = RgbdFrame::open(v2, &frame_options(&a.depth2, &a.intrinsics2, a.depth_scale2, "--intrinsics2")?)?;
        correct(&mut f2);
        let (o2, s2) = recon::dataset::load_masks(&a.masks2, a.objects.as_deref())?;
        skipped.extend(s2.into_iter().map(|mut s| {
            s.label = format!("view 2 {}", s.label);
            s
        }));
        let rel = a.rel_pose.as_deref().context("--view2 needs --rel-pose")?;
        others.push((f2, o2, parse_rel_pose(rel)?));
    }
    for path in &a.views {
        let k = others.len() + 2;
        let mut v = recon::engine::ViewSpec::from_file(path, &format!("view {k}"))?.open(a.objects.as_deref())?;
        correct(&mut v.frame);
        skipped.extend(v.skipped.into_iter().map(|mut s| {
            s.label = format!("view {k} {}", s.label);
            s
        }));
        others.push((v.frame, v.objects, v.t_c1_ci));
    }

    // Too many objects is refused before the model is loaded (the engine checks again).
    recon::engine::check_object_count(&frame, &objects, &opts, "--masks")?;
    let source = a.model.source()?;
    a.model.note_default_model();
    let load = a.model.load_options(&source)?;
    let engine = Engine::load(&source, &load)?;
    let config = source.architecture()?;
    let random = engine.pipeline.weights().is_random();
    if random {
        eprintln!(
            "NOTE: running {} with RANDOM weights (seed {}). The plumbing is real; the shapes and poses are not meaningful.",
            config.display(),
            a.model.infer.seed
        );
    }

    if let recon::engine::WeightsSource::Files { manifest_files, notes, .. } = engine.pipeline.weights() {
        if !manifest_files.is_empty() {
            let mut names: Vec<&str> = manifest_files.iter().map(|f| f.manifest.as_str()).collect();
            names.sort_unstable();
            names.dedup();
            let pins = manifest_files.iter().filter(|f| f.sha256.is_some()).count();
            let lists = manifest_files.iter().filter(|f| f.tensors.is_some()).count();
            eprintln!(
                "weights: {} files of {} from the Hugging Face cache; {pins} SHA-256 pins and {lists} tensor lists matched (--json lists them)",
                manifest_files.len(),
                names.join(" + ")
            );
        }
        for n in notes {
            eprintln!("weights: {n}");
        }
    }
    let bar = Bar::new((objects.len() * opts.samples) as u64);
    let progress = |e: recon::engine::Progress<'_>| bar.event(e);
    let other_views = others.iter().map(|(f, o, rel)| SecondView { frame: f, objects: o.clone(), t_c1_c2: *rel }).collect();
    let result = engine.reconstruct_views(&frame, objects, other_views, &opts, &progress);
    bar.pb.finish_and_clear();
    let mut result = result?;
    let failed = failed_masks + result.skipped.len();
    skipped.extend(result.skipped.iter().cloned());
    // The index file lists every object that is not there, mask skips included.
    result.skipped = skipped.clone();
    let out = match a.out {
        Some(o) => o,
        None => {
            let stem = a.rgbd.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "frame".into());
            a.rgbd.with_file_name(format!("{stem}_recon"))
        }
    };
    let written = write_outputs_with(&result, &out, &OutputOptions { recgen_files: a.recgen_files })?;
    if a.preview {
        let meshes: Vec<&recon::mesh::Mesh> = result.objects.iter().filter_map(|o| o.mesh_camera.as_ref()).collect();
        recon::render::save_preview(&frame, &meshes, &out.join("preview.png"))?;
    }
    let totals: Vec<f64> = (0..STAGES.len()).map(|k| result.objects.iter().map(|o| stage_row(o)[k]).sum()).collect();
    if a.json {
        let objs: Vec<serde_json::Value> = result
            .objects
            .iter()
            .zip(&written)
            .map(|(o, w)| {
                serde_json::json!({
                    "object": o.label, "id": o.id,
                    "rotation": o.pose_camera.rotation, "translation_m": o.pose_camera.translation, "scale_m": o.pose_camera.scale,
                    "selection": o.selection, "uncertainty": o.uncertainty, "views": o.views,
                    "occupied_voxels": o.occupied_voxels,
                    "shape_fit": o.shape_fit,
                    "faces_decoded": o.faces_decoded,
                    "faces": o.mesh_camera.as_ref().map(|m| m.faces.len()),
                    "gaussians": o.gaussians_camera.as_ref().map(|g| g.len()),
                    "timings_s": o.timings, "postprocess_s": o.postprocess_seconds, "select_s": o.select_seconds,
                    "stage_seconds": STAGES.iter().zip(stage_row(o)).map(|(k, v)| (k.to_string(), serde_json::json!(v))).collect::<serde_json::Map<_, _>>(),
                    "notes": o.notes, "files": w,
                })
            })
            .collect();
        let skips: Vec<serde_json::Value> =
            skipped.iter().map(|s| serde_json::json!({"object": s.label, "reason": s.reason.to_string()})).collect();
        let summary = serde_json::json!({
            "out": out, "random_weights": random, "config": config, "dtype": load.compute.fast_parts().map_or("f32", |(p, _)| p.name()),
            "views": 1 + others.len(), "samples": opts.samples, "select": opts.select, "pose_fit": a.model.infer.pose_fit, "seed": a.model.infer.seed,
            "preprocess_s": result.preprocess_seconds,
            "stage_totals_s": STAGES.iter().zip(&totals).map(|(k, v)| (k.to_string(), serde_json::json!(v))).collect::<serde_json::Map<_, _>>(),
            "objects": objs, "skipped": skips, "notes": result.notes, "weights": engine.pipeline.weights(),
            "recon_version": recon::VERSION, "model_identity": engine.pipeline.identity(),
        });
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!(
            "{:<14} {:>9} {:>9} {:>9} {:>8} {:>4} {:>6} {:>9} {:>8} {:>8} {:>7} {:>7} {:>8}",
            "object", "x_m", "y_m", "z_m", "scale_m", "view", "seed", "score_mm", "t_sd_mm", "r_sd_deg", "s_sd", "voxels", "faces"
        );
        for o in &result.objects {
            let t = o.pose_camera.translation;
            let u = o.uncertainty.as_ref();
            let opt = |v: Option<f64>, k: usize| v.map_or("-".to_string(), |v| format!("{v:.k$}"));
            println!(
                "{:<14} {:>9.4} {:>9.4} {:>9.4} {:>8.4} {:>4} {:>6} {:>9.2} {:>8} {:>8} {:>7} {:>7} {:>8}",
                o.label,
                t[0],
                t[1],
                t[2],
                o.pose_camera.scale,
                o.selection.view,
                o.selection.seed,
                o.selection.score_m * 1e3,
                opt(u.map(|u| u.translation_sd_mm), 1),
                opt(u.map(|u| u.rotation_sd_deg), 1),
                opt(u.map(|u| u.scale_sd_rel), 3),
                o.occupied_voxels,
                o.mesh_camera.as_ref().map(|m| m.faces.len()).unwrap_or(0),
            );
            for n in &o.notes {
                println!("  note: {n}");
            }
        }
        for s in &skipped {
            println!("{s}");
        }
        for n in &result.notes {
            println!("note: {n}");
        }
        if !result.objects.is_empty() {
            print!("\n{:<14}", "seconds");
            for s in STAGES {
                print!(" {s:>13}");
            }
            println!();
            for o in &result.objects {
                print!("{:<14}", o.label);
                for v in stage_row(o) {
                    print!(" {v:>13.2}");
                }
                println!();
            }
            print!("{:<14}", "all objects");
            for v in &totals {
                print!(" {v:>13.2}");
            }
            println!("\npreprocessing (all objects): {:.2} s", result.preprocess_seconds);
        }
        println!("wrote {}{}", out.display(), if random { " (RANDOM weights)" } else { "" });
    }
    Ok(exit_code(result.objects.len(), failed))
}
