//! `recon scene`: posed meshes → settled, simulator-ready scene (URDF, MJCF, USD, GLB).
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct SceneArgs {
    /// A scene file (scene.json, version 1), a `recon infer` output folder, or a
    /// BOP scene folder (`<root>/<split>/<scene>`, e.g. from `recon synth`: GT models at GT poses).
    #[arg(long)]
    input: PathBuf,
    /// With a BOP scene folder: the image id (default: the first).
    #[arg(long)]
    view: Option<u32>,
    /// Output folder (replaced only if it is an earlier `recon scene` output).
    #[arg(long)]
    out: PathBuf,
    /// With a `recon infer` folder: the colour image given to `recon infer`
    /// (default: the one its pose.json records); its depth gives the support
    /// plane. Depth/intrinsics are found beside it.
    #[arg(long)]
    frame: Option<PathBuf>,
    /// Depth image for --frame (16-bit PNG), if not found beside it.
    #[arg(long)]
    depth: Option<PathBuf>,
    /// Metres per depth unit for --frame's depth.
    #[arg(long)]
    depth_scale: Option<f64>,
    /// Material table (default: the shipped models/materials.json).
    #[arg(long)]
    materials: Option<PathBuf>,
    #[command(flatten)]
    options: recon::sim::SceneOptions,
    /// Write this many variations of the scene instead (objects re-placed under
    /// spatial predicates, distractors, object variants; `variant_NNNN/` folders
    /// and manifest.json under --out); --seed makes them reproducible.
    #[arg(long)]
    variations: Option<usize>,
    /// Variations spec (JSON: predicates, distractors, object variants); default:
    /// two predicates sampled per variant, no distractors, no object variants.
    #[arg(long, requires = "variations")]
    spec: Option<PathBuf>,
    /// Print the per-object report as JSON instead of a table.
    #[arg(long)]
    json: bool,
}

pub fn run(a: SceneArgs) -> anyhow::Result<bool> {
    use anyhow::Context;
    use recon::dataset::{FrameOptions, RgbdFrame};
    use recon::sim::MaterialTable;
    use recon::sim::SceneFile;
    use recon::sim::{build_scene, write_outputs};

    // A bad spec or asset fails before the scene is read.
    let spec = match (&a.variations, &a.spec) {
        (Some(_), Some(p)) => Some((recon::sim::VariationSpec::load(p)?, p.display().to_string())),
        (Some(_), None) => Some((recon::sim::VariationSpec::default(), "<default spec>".to_string())),
        _ => None,
    };
    let table = match &a.materials {
        Some(p) => MaterialTable::load(p)?,
        None => MaterialTable::builtin(),
    };
    let assets = match spec.as_ref().and_then(|(s, f)| s.distractors.assets.as_ref().map(|a| (a, f))) {
        Some((a, f)) => Some(recon::sim::AssetLibrary::load(a, &table, f)?),
        None => None,
    };
    let opts = a.options.settings()?;
    let plane_opts = a.options.plane_fit();
    let (scene, file) = if a.input.is_dir() && a.input.join("scene_gt.json").is_file() {
        let (scene, check) = recon::sim::scene_from_bop(&a.input, a.view, &table, &plane_opts)?;
        if let Some(c) = check {
            println!(
                "support plane vs the dataset's world plane: normal {:.3}°, distance {:.2} mm",
                c.normal_error_deg,
                c.offset_error_m * 1e3
            );
        }
        (scene, a.input.join("scene_gt.json").display().to_string())
    } else if a.input.is_dir() {
        if !a.input.join(recon::engine::MARKER).is_file() {
            anyhow::bail!(
                "{}: neither a recon infer output (no {}) nor a BOP scene folder (no scene_gt.json)",
                a.input.display(),
                recon::engine::MARKER
            );
        }
        let color = match a.frame.clone().or_else(|| recon::sim::infer_frame(&a.input)) {
            Some(c) => c,
            None => anyhow::bail!(
                "{}: the support plane comes from the frame's depth, and the colour image recorded in its pose.json is not found; pass --frame <the colour image given to recon infer>",
                a.input.display()
            ),
        };
        let fo = FrameOptions { depth: a.depth.clone(), depth_scale_m: a.depth_scale, ..Default::default() };
        let frame = RgbdFrame::open(&color, &fo).with_context(|| format!("--frame {}", color.display()))?;
        let (scene, notes) = recon::sim::scene_from_infer_output(&a.input, &frame, &table, &plane_opts)?;
        for n in notes {
            eprintln!("note: {n}");
        }
        (scene, a.input.join(recon::engine::MARKER).display().to_string())
    } else {
        (SceneFile::load(&a.input)?, a.input.display().to_string())
    };
    if let (Some(count), Some((spec, spec_file))) = (a.variations, spec) {
        let vo = recon::sim::VariationOptions { count, seed: a.options.seed, spec, spec_file, assets };
        let r = recon::sim::run_variations(&scene, &table, &opts, &vo, &file, &a.out)?;
        let m = &r.manifest;
        if a.json {
            println!("{}", serde_json::to_string_pretty(m)?);
        } else {
            for v in &m.variants {
                let preds: Vec<String> =
                    v.predicates.iter().map(|p| format!("{} {}", p.label, if p.judged.holds { "ok" } else { "FAILS" })).collect();
                println!(
                    "variant {:>4}: {} ({} objects, attempt {}) {}",
                    v.index,
                    if v.kept { "kept" } else { "REJECTED" },
                    v.objects.len(),
                    v.attempts,
                    if v.kept { preds.join(", ") } else { v.rejected.clone().unwrap_or_default() }
                );
            }
            println!(
                "kept {} of {} variants; every predicate holds in {:.1} % of them ({} of {} predicates); {:.2} variants/s ({:.1} s)",
                m.kept,
                m.requested,
                m.predicate_pass_rate * 100.0,
                m.predicates_held,
                m.predicates_total,
                m.kept as f64 / r.seconds,
                r.seconds
            );
            println!("wrote {}", a.out.join(recon::sim::VARIATIONS_MANIFEST).display());
        }
        return Ok(m.kept == m.requested);
    }
    let mut sim = build_scene(&scene, &table, &opts, &file)?;
    write_outputs(&mut sim, &a.out)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&sim.summaries())?);
    } else {
        if let Some(f) = &sim.input.support_plane.fit {
            println!(
                "support plane: {} inliers of {} points, rms residual {:.2} mm, median |residual| {:.2} mm (RANSAC threshold {:.1} mm, final band {:.1} mm)",
                f.inliers,
                f.points,
                f.rms_residual_m * 1e3,
                f.median_abs_residual_m * 1e3,
                f.threshold_m * 1e3,
                f.band_m * 1e3
            );
        }
        println!(
            "settled {} objects in {:.2} s simulated ({} steps; depenetration {:.2} s){}",
            sim.objects.len(),
            sim.settle.simulated_s,
            sim.settle.steps,
            sim.settle.depenetration_s,
            if sim.settle.at_rest { "" } else { ": NOT at rest at the time limit" }
        );
        print!("{}", sim.table());
        let t = &sim.timings;
        println!("timings: annotate+collision {:.2} s, settle {:.2} s, export {:.2} s", t.annotate_and_collision_s, t.settle_s, t.export_s);
        println!("wrote {}", a.out.display());
    }
    Ok(true)
}
