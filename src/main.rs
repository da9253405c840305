use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "recon", version, about = "RGB-D frames + masks → simulation-ready posed 3D objects")]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run conformance fixture directories (config.json + data.safetensors) and report max abs error per output.
    Conformance {
        /// Fixture directories.
        #[arg(required = true)]
        dirs: Vec<std::path::PathBuf>,
    },
    /// Reconstruct every masked object of an RGB-D frame: posed mesh, Gaussians and pose per object.
    Infer(InferArgs),
    /// Checkpoints: download, verify, random-initialise.
    Weights {
        #[command(subcommand)]
        cmd: WeightsCmd,
    },
}

#[derive(clap::Args)]
struct InferArgs {
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

fn infer(a: InferArgs) -> anyhow::Result<bool> {
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

#[derive(Subcommand)]
enum WeightsCmd {
    /// Download a manifest's files (Hugging Face files into the standard HF cache).
    Fetch {
        /// Manifest name (recgen, trellis-image-large, dinov2-vitl14-reg) or path; default: all.
        #[arg(long)]
        manifest: Option<String>,
        /// Cache directory (default: $HF_HOME/hub or ~/.cache/huggingface/hub).
        #[arg(long)]
        cache: Option<PathBuf>,
        /// Also download files marked optional.
        #[arg(long)]
        with_optional: bool,
    },
    /// Check a directory (or HF cache) against a manifest: files present, tensor names and shapes.
    Verify {
        dir: PathBuf,
        /// Manifest name or path; default: all.
        #[arg(long)]
        manifest: Option<String>,
    },
    /// Write random-initialised weights (labelled recon.random_init=true) for a module config.
    Init {
        /// Module config JSON ({"name": ClassName, "args": {...}}), e.g. models/dinov2_tiny.json.
        #[arg(long)]
        config: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Print the tensor names and shapes a module config expects (JSON).
    Expected {
        #[arg(long)]
        config: PathBuf,
    },
}

fn manifests(name: &Option<String>) -> anyhow::Result<Vec<recon::weights::manifest::Manifest>> {
    use recon::weights::manifest::Manifest;
    Ok(match name {
        Some(n) => vec![Manifest::load(n)?],
        None => Manifest::all()?,
    })
}

fn weights(cmd: WeightsCmd) -> anyhow::Result<bool> {
    use recon::weights::{fetch, init, registry, verify};
    match cmd {
        WeightsCmd::Fetch { manifest, cache, with_optional } => {
            for m in manifests(&manifest)? {
                let paths = fetch::fetch(&m, cache.as_deref(), with_optional)?;
                for p in paths {
                    println!("{}", p.display());
                }
            }
            Ok(true)
        }
        WeightsCmd::Verify { dir, manifest } => {
            if !dir.is_dir() {
                anyhow::bail!("{}: not a directory", dir.display());
            }
            let mut ok = true;
            for m in manifests(&manifest)? {
                let rows = verify::verify_dir(&m, &dir)?;
                verify::print_table(&m, &dir, &rows, &mut std::io::stdout());
                ok &= rows.iter().all(|r| r.ok);
            }
            Ok(ok)
        }
        WeightsCmd::Init { config, out, seed } => {
            let p = init::write_random_init(&config, &out, seed)?;
            println!("wrote {} (RANDOM weights, recon.random_init=true, seed {seed})", p.display());
            Ok(true)
        }
        WeightsCmd::Expected { config } => {
            let cfg = registry::ModuleConfig::read(&config)?;
            let specs = registry::expected_tensors(&cfg, &config.display().to_string())?;
            println!("{}", serde_json::to_string(&specs)?);
            Ok(true)
        }
    }
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let ok = match cli.cmd {
        Cmd::Conformance { dirs } => recon::conformance::run_dirs(&dirs, &mut std::io::stdout())?,
        Cmd::Weights { cmd } => weights(cmd)?,
        Cmd::Infer(a) => infer(a)?,
    };
    if !ok {
        std::process::exit(1);
    }
    Ok(())
}
