//! Colour error of the predicted Gaussians in novel views of `recon synth` scenes, with
//! each post-hoc colour calibration (issue 36 §5).
//!
//! Per scene: the target object is reconstructed from view 0 (ideal depth, its visible
//! mask) with the shipped default model, once per `--posthoc-color` variant. Its
//! Gaussians are splatted into every view, and compared with the ground-truth render of
//! that view (the same ray caster that made the input, the light kept where it is for
//! view 0 relative to the camera) on the pixels where the target is visible and the
//! splats cover (alpha > 0.5): mean absolute RGB error in [0, 1]. View 0 is the input
//! view, the others are novel.
//!
//!     cargo run --release --example novel_view_color -- --scenes 12 --seed 91000 --views 3
//!
//! Prints a table and writes `--json FILE` when given.
use anyhow::{bail, Context, Result};
use recon::dataset::{ObjectMask, RgbdFrame};
use recon::engine::{Engine, InferOptions, LoadOptions, ModelSource, PosthocColor};
use recon::render::{render_gaussians, Camera, SplatOptions};
use recon::synth::{Scene, SceneConfig};

struct Args {
    scenes: usize,
    seed: u64,
    views: usize,
    variants: Vec<PosthocColor>,
    json: Option<std::path::PathBuf>,
}

fn args() -> Result<Args> {
    let mut a = Args {
        scenes: 12,
        seed: 91000,
        views: 3,
        variants: vec![PosthocColor::None, PosthocColor::Gamma, PosthocColor::Affine, PosthocColor::GammaAffine],
        json: None,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut val = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--scenes" => a.scenes = val()?.parse()?,
            "--seed" => a.seed = val()?.parse()?,
            "--views" => a.views = val()?.parse()?,
            "--variants" => {
                a.variants = val()?
                    .split(',')
                    .map(|v| serde_json::from_value(serde_json::Value::String(v.to_string())).with_context(|| format!("variant {v}")))
                    .collect::<Result<_>>()?
            }
            "--json" => a.json = Some(val()?.into()),
            _ => bail!("unknown flag {flag}; flags: --scenes N --seed S --views V --variants none,gamma,… --json FILE"),
        }
    }
    Ok(a)
}

/// Mean absolute RGB error on the pixels of `visible` the splats cover, and their count.
fn color_l1(pred: &recon::render::SplatImage, gt_rgb: &[u8], visible: &[bool]) -> (f64, usize) {
    let (mut sum, mut n) = (0.0, 0);
    for i in 0..visible.len() {
        if visible[i] && pred.alpha[i] > 0.5 {
            let c = pred.color[i];
            sum += (0..3).map(|k| (f64::from(c[k]).clamp(0.0, 1.0) - f64::from(gt_rgb[3 * i + k]) / 255.0).abs()).sum::<f64>() / 3.0;
            n += 1;
        }
    }
    (if n > 0 { sum / n as f64 } else { f64::NAN }, n)
}

fn main() -> Result<()> {
    let a = args()?;
    let engine = Engine::load(&ModelSource::Default, &LoadOptions::default())?;
    let cfg = SceneConfig { views: 1 + a.views, ..Default::default() };
    // rows: (scene, variant, view, l1, pixels, applied)
    let mut rows: Vec<(u64, PosthocColor, usize, f64, usize, bool)> = Vec::new();
    for s in 0..a.scenes as u64 {
        let seed = a.seed + s;
        let mut scene = Scene::generate(seed, &cfg)?;
        // Novel views lit as view 0 is, relative to the camera: only the viewpoint changes.
        let light = scene.views[0].light;
        for v in scene.views.iter_mut() {
            v.light = light;
        }
        let units = scene.units(false)?;
        let ids: Vec<i64> = (0..units.len() as i64).collect();
        let target = units.iter().position(|u| u.object == Some(0)).context("no target unit")? as i32;
        let renders: Vec<_> = (0..scene.views.len()).map(|v| scene.render_view(&units, &ids, v)).collect::<recon::Result<_>>()?;
        let r0 = &renders[0];
        let visible0: Vec<bool> = r0.index.iter().map(|&i| i == target).collect();
        if visible0.iter().filter(|&&v| v).count() < 400 {
            eprintln!("scene {seed}: target barely visible, skipped");
            continue;
        }
        let cam0 = scene.views[0].camera;
        let frame = RgbdFrame::from_buffers(cam0.width, cam0.height, r0.rgb.clone(), r0.depth.clone(), cam0.k, &format!("synth {seed}"))?;
        let mask = ObjectMask::from_bools(Some(1), "target", cam0.width, cam0.height, &visible0);
        for &variant in &a.variants {
            let settings = InferOptions { posthoc_color: variant, ..Default::default() }.settings()?;
            let res = engine.reconstruct(&frame, vec![mask.clone()], &settings)?;
            let Some(o) = res.objects.first() else {
                eprintln!("scene {seed} {variant}: not reconstructed: {:?}", res.skipped);
                continue;
            };
            let Some(g) = o.gaussians_camera.as_ref() else { continue };
            let applied = o.posthoc_color.as_ref().is_some_and(|r| r.transform.is_some());
            for (v, rv) in renders.iter().enumerate() {
                let cam = scene.views[v].camera;
                // Anchor camera → world → this camera.
                let to_v = cam.world_to_cam.compose(&cam0.world_to_cam.inverse());
                let splat = render_gaussians(g, &Camera { world_to_cam: to_v, ..cam }, &SplatOptions::default())?;
                let visible: Vec<bool> = rv.index.iter().map(|&i| i == target).collect();
                let (l1, n) = color_l1(&splat, &rv.rgb, &visible);
                if n > 0 {
                    rows.push((seed, variant, v, l1, n, applied));
                }
            }
        }
        eprintln!("scene {seed} done");
    }
    println!("| posthoc_color | scenes (applied) | input view L1 | novel views L1 (mean ± sd over scenes) |");
    println!("|---|---|---|---|");
    let mut summary = Vec::new();
    for &variant in &a.variants {
        let mine: Vec<_> = rows.iter().filter(|r| r.1 == variant).collect();
        let scenes: std::collections::BTreeSet<u64> = mine.iter().map(|r| r.0).collect();
        let applied = scenes.iter().filter(|s| mine.iter().any(|r| r.0 == **s && r.5)).count();
        let input: Vec<f64> = mine.iter().filter(|r| r.2 == 0).map(|r| r.3).collect();
        // Per scene: the mean over its novel views.
        let novel: Vec<f64> = scenes
            .iter()
            .filter_map(|s| {
                let v: Vec<f64> = mine.iter().filter(|r| r.0 == *s && r.2 > 0).map(|r| r.3).collect();
                (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
            })
            .collect();
        let mean = |x: &[f64]| x.iter().sum::<f64>() / x.len().max(1) as f64;
        let sd = |x: &[f64]| {
            let m = mean(x);
            (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / (x.len().max(2) - 1) as f64).sqrt()
        };
        println!(
            "| {variant} | {} ({applied}) | {:.4} ± {:.4} | {:.4} ± {:.4} |",
            scenes.len(),
            mean(&input),
            sd(&input),
            mean(&novel),
            sd(&novel)
        );
        summary.push(serde_json::json!({
            "variant": variant, "scenes": scenes.len(), "applied": applied,
            "input_l1_mean": mean(&input), "input_l1_sd": sd(&input),
            "novel_l1_mean": mean(&novel), "novel_l1_sd": sd(&novel),
            "per_scene_novel": novel, "per_scene_input": input,
        }));
    }
    if let Some(p) = &a.json {
        let doc = serde_json::json!({"scenes": a.scenes, "seed": a.seed, "views": a.views, "summary": summary});
        std::fs::write(p, serde_json::to_string_pretty(&doc)?).with_context(|| p.display().to_string())?;
    }
    Ok(())
}
