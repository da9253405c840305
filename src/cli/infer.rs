//! `recon infer`: RGB-D frame + masks → posed meshes, Gaussians and poses.
use std::path::PathBuf;

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
    /// Instance ids to reconstruct (default: all present).
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
    /// Architecture file.
    #[arg(long, default_value = "models/recgen-tiny.json")]
    config: PathBuf,
    /// Weights directory (`<module>.safetensors` per module). Without it the model
    /// runs with RANDOM weights (plumbing only; results are not meaningful).
    #[arg(long)]
    weights: Option<PathBuf>,
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Sampler steps for both stages (default: the config's).
    #[arg(long)]
    steps: Option<usize>,
    /// Classifier-free guidance strength for both stages (default: the config's).
    #[arg(long)]
    cfg: Option<f64>,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Output directory (default: `<image stem>_recon` beside the input).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

pub fn run(a: InferArgs) -> anyhow::Result<bool> {
    use anyhow::Context;
    use recon::infer::{write_outputs, Engine, InferOptions};
    use recon::inputs::frame::{FrameOptions, Intrinsics, RgbdFrame};
    use recon::inputs::masks::{load_binary_masks, InstanceMap};
    if let Some(n) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("--threads")?;
    }
    let mut fo = FrameOptions { depth: a.depth.clone(), depth_scale: a.depth_scale, ..Default::default() };
    if let Some(k) = &a.intrinsics {
        let nums: Vec<f64> = k.split(',').filter_map(|v| v.trim().parse().ok()).collect();
        if nums.len() == 4 && k.split(',').count() == 4 {
            fo.intrinsics = Some(Intrinsics::new(nums[0], nums[1], nums[2], nums[3])?);
        } else {
            fo.intrinsics_file = Some(PathBuf::from(k));
        }
    }
    let frame = RgbdFrame::open(&a.rgbd, &fo)?;
    // One file is an instance-id map (a binary 0/255 mask is the one-object case);
    // several files are binary masks, one object each.
    let (objects, mut skipped) = if a.masks.len() == 1 {
        InstanceMap::open(&a.masks[0])?.objects(a.objects.as_deref())
    } else {
        if a.objects.is_some() {
            anyhow::bail!("--objects selects ids of an instance-id map; with several binary mask files, list only the masks you want");
        }
        load_binary_masks(&a.masks)
    };
    let random = a.weights.is_none();
    let engine = match &a.weights {
        Some(dir) => Engine::load(&a.config, dir)?,
        None => Engine::random(&a.config, a.seed)?,
    };
    if random {
        eprintln!(
            "NOTE: no --weights given: running {} with RANDOM weights (seed {}). The plumbing is real; the shapes and poses are not meaningful.",
            a.config.display(),
            a.seed
        );
    }
    let mut opts = InferOptions::default();
    opts.run.seed = a.seed;
    opts.run.ss_steps = a.steps;
    opts.run.slat_steps = a.steps;
    opts.run.ss_cfg_strength = a.cfg;
    opts.run.slat_cfg_strength = a.cfg;
    let result = engine.reconstruct(&frame, objects, &opts)?;
    skipped.extend(result.skipped.iter().cloned());
    let out = match a.out {
        Some(o) => o,
        None => {
            let stem = a.rgbd.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_else(|| "frame".into());
            a.rgbd.with_file_name(format!("{stem}_recon"))
        }
    };
    let written = write_outputs(&result, &out)?;
    if a.json {
        let objs: Vec<serde_json::Value> = result
            .objects
            .iter()
            .zip(&written)
            .map(|(o, w)| {
                serde_json::json!({
                    "object": o.label, "id": o.id,
                    "rotation": o.pose_camera.rotation, "translation_m": o.pose_camera.translation, "scale_m": o.pose_camera.scale,
                    "occupied_voxels": o.occupied_voxels,
                    "faces": o.mesh_camera.as_ref().map(|m| m.faces.len()),
                    "gaussians": o.gaussians_camera.as_ref().map(|g| g.len()),
                    "timings_s": o.timings, "files": w,
                })
            })
            .collect();
        let skips: Vec<serde_json::Value> =
            skipped.iter().map(|s| serde_json::json!({"object": s.label, "reason": s.reason.to_string()})).collect();
        let summary = serde_json::json!({
            "out": out, "random_weights": random, "config": a.config,
            "preprocess_s": result.preprocess_seconds, "objects": objs, "skipped": skips,
        });
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        println!("{:<14} {:>9} {:>9} {:>9} {:>8} {:>8} {:>9} {:>8}", "object", "x_m", "y_m", "z_m", "scale_m", "voxels", "faces", "time_s");
        for o in &result.objects {
            let t = o.pose_camera.translation;
            println!(
                "{:<14} {:>9.4} {:>9.4} {:>9.4} {:>8.4} {:>8} {:>9} {:>8.2}",
                o.label,
                t[0],
                t[1],
                t[2],
                o.pose_camera.scale,
                o.occupied_voxels,
                o.mesh_camera.as_ref().map(|m| m.faces.len()).unwrap_or(0),
                o.timings.total
            );
        }
        for s in &skipped {
            println!("{s}");
        }
        if let Some(o) = result.objects.first() {
            let t = &o.timings;
            println!(
                "stage seconds ({}): encoder {:.2}, ss sampling {:.2}, ss decoder {:.2}, slat sampling {:.2}, mesh {:.2}, gaussians {:.2}; preprocessing (all objects) {:.2}",
                o.label, t.image_encoder, t.ss_sampling, t.ss_decoder, t.slat_sampling, t.mesh_decoder, t.gaussian_decoder, result.preprocess_seconds
            );
        }
        println!("wrote {}{}", out.display(), if random { " (RANDOM weights)" } else { "" });
    }
    Ok(!result.objects.is_empty())
}
