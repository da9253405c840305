//! The `observed` baseline end to end on tiny `recon synth` datasets: synthesise, predict,
//! write, re-read, score. Also checks the visibility estimator of YCB-Video against the
//! exact `visib_fract` the synthesiser writes.

mod common;

use common::tmp;
use recon::dataset::load_dataset;
use recon::dataset::{surface_patches, visible_fraction};
use recon::eval::{evaluate, read_predictions, EvalOptions};
use recon::eval::{observe_dataset, observe_dataset_corrected, DatasetCorrection, ObservedOptions};
use recon::math::Similarity;
use recon::sensor::{DepthCorrection, Mechanism, SensorModel};
use recon::synth::{generate, SynthOptions};
use std::path::Path;

fn tiny(sensor: SensorModel) -> SynthOptions {
    SynthOptions { scenes: 2, views: 1, seed: 5, width: 160, height: 120, parts: false, sensor }
}

#[test]
fn observed_baseline_on_two_tiny_synthetic_scenes() {
    let stereo = SensorModel::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("models/sensors/stereo.json")).unwrap();
    for (name, sensor) in [("ideal", SensorModel::ideal()), ("stereo", stereo)] {
        let dir = tmp(name);
        let data = dir.join("data");
        generate(&data, &tiny(sensor), &|| {}).unwrap();
        let ds = load_dataset(&data).unwrap();
        let n_gt: usize = ds.frames.iter().map(|f| f.gt.len()).sum();
        assert!(ds.frames.len() == 2 && n_gt >= 8, "{} frames, {n_gt} instances", ds.frames.len());
        let run = observe_dataset(&ds, &ObservedOptions::default()).unwrap();
        // Every instance is either predicted or skipped with a reason, none twice.
        assert_eq!(run.predictions.len() + run.skipped.len(), n_gt);
        assert!(run.predictions.len() * 2 >= n_gt, "{name}: only {} of {n_gt} predicted: {:?}", run.predictions.len(), run.skipped);
        let pf = run.write(&dir.join("pred")).unwrap();
        let preds = read_predictions(&pf).unwrap();
        assert!(preds.predictions.iter().all(|p| !p.model_frame && p.mesh.as_ref().is_some_and(|m| dir.join("pred").join(m).is_file())));
        let r = evaluate(&ds, &preds, &pf, &EvalOptions { n_samples: 3000, all_frames: true, ..Default::default() }).unwrap();
        eprintln!("{name}:\n{}", r.text_table());
        // Every GT instance scored; misses are exactly the skipped ones.
        assert_eq!((r.overall.n_gt, r.overall.n_missed), (n_gt, run.skipped.len()));
        for o in &r.objects {
            let Some(m) = &o.metrics else { continue };
            assert!(m.add.is_none());
            // A hull of seen points lies on/inside the object: its distance to the GT
            // surface is a fraction of the object's size, never more than its diameter.
            assert!(
                m.add_sb_norm.is_finite() && m.add_sb_norm > 0.0 && m.add_sb_norm < 0.5,
                "{name} {}: ADD-SB/d {}",
                o.model,
                m.add_sb_norm
            );
            assert!(m.cd_norm.is_finite() && m.cd_norm < 0.5, "{name} {}: CD_norm {}", o.model, m.cd_norm);
            assert!(m.dre.is_finite() && m.dre < 1.0 && m.pred_diameter < 1.2 * o.gt_diameter, "{name} {}: DRE {}", o.model, m.dre);
        }
        // Mostly visible objects are where the floor is highest.
        let vis: Vec<f64> = r
            .objects
            .iter()
            .filter(|o| o.visib_fract.is_some_and(|v| v > 0.9))
            .filter_map(|o| o.metrics.as_ref())
            .map(|m| m.add_sb_norm)
            .collect();
        assert!(!vis.is_empty());
        let mean = vis.iter().sum::<f64>() / vis.len() as f64;
        assert!(mean < 0.2, "{name}: mean ADD-SB/d of visible objects {mean}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

/// Mean ADD-SB/d and CD_norm of the observed baseline on `ds` (with a depth correction).
fn baseline_scores(ds: &recon::dataset::Dataset, dir: &Path, correction: Option<&DatasetCorrection>) -> (f64, f64) {
    let run = observe_dataset_corrected(ds, &ObservedOptions::default(), correction).unwrap();
    let pf = run.write(dir).unwrap();
    let r = evaluate(ds, &read_predictions(&pf).unwrap(), &pf, &EvalOptions { n_samples: 2000, all_frames: true, ..Default::default() })
        .unwrap();
    let m: Vec<(f64, f64)> = r.objects.iter().filter_map(|o| o.metrics.as_ref()).map(|m| (m.add_sb_norm, m.cd_norm)).collect();
    assert!(m.len() >= 4, "{} scored", m.len());
    (m.iter().map(|x| x.0).sum::<f64>() / m.len() as f64, m.iter().map(|x| x.1).sum::<f64>() / m.len() as f64)
}

/// A depth scale error planted in the frames pushes the baseline's objects away from the
/// camera; the depth correction that undoes it brings the scores back to those of the
/// clean frames.
#[test]
fn depth_correction_undoes_a_planted_scale_before_the_baseline() {
    let dir = tmp("corr");
    let scale = Mechanism::DepthScale { scale: 0.04 };
    let (clean, planted) = (dir.join("clean"), dir.join("planted"));
    generate(&clean, &tiny(SensorModel::ideal()), &|| {}).unwrap();
    let mut sensor = SensorModel::ideal();
    sensor.mechanisms = vec![scale.clone()];
    generate(&planted, &tiny(sensor), &|| {}).unwrap();
    let (clean, planted) = (load_dataset(&clean).unwrap(), load_dataset(&planted).unwrap());
    let c = DatasetCorrection::new(DepthCorrection::from_fitted(&[scale], "test"), &planted);
    let ideal = baseline_scores(&clean, &dir.join("p0"), None);
    let before = baseline_scores(&planted, &dir.join("p1"), None);
    let after = baseline_scores(&planted, &dir.join("p2"), Some(&c));
    eprintln!("mean ADD-SB/d, CD_norm: clean {ideal:?}, planted {before:?}, corrected {after:?}");
    // The scale moves every point 4 % farther: ADD-SB/d (no alignment) grows; CD_norm is
    // scored after ICP and barely moves.
    let hurt = before.0 - ideal.0;
    assert!(hurt > 0.005, "the planted scale should hurt ADD-SB/d: {before:?} vs {ideal:?}");
    assert!((after.0 - ideal.0).abs() < 0.2 * hurt, "corrected ADD-SB/d {after:?} vs clean {ideal:?}, planted {before:?}");
    assert!((after.1 - ideal.1).abs() < 0.01, "corrected CD_norm {after:?} vs clean {ideal:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn visibility_estimate_agrees_with_synthetic_visib_fract() {
    let dir = tmp("visib");
    let data = dir.join("data");
    let mut opts = tiny(SensorModel::ideal());
    (opts.scenes, opts.width, opts.height) = (4, 320, 240);
    generate(&data, &opts, &|| {}).unwrap();
    let ds = load_dataset(&data).unwrap();
    let mut errs = Vec::new();
    for f in &ds.frames {
        for (gi, g) in f.gt.iter().enumerate() {
            let mask =
                image::open(ds.root.join(&f.scene).join("mask_visib").join(format!("{:06}_{gi:06}.png", f.frame))).unwrap().to_luma8();
            let (w, h) = (mask.width() as usize, mask.height() as usize);
            let m: Vec<bool> = mask.into_raw().into_iter().map(|v| v > 0).collect();
            let s = surface_patches(&ds.models[&g.obj_id].mesh.sample_surface(6000, 1), 10);
            let (Some(est), Some(truth)) = (visible_fraction(&s, &Similarity::rigid(g.r, g.t), &f.k, &m, w, h), g.visib_fract) else {
                continue;
            };
            errs.push((est - truth).abs());
        }
    }
    errs.sort_by(f64::total_cmp);
    let med = errs[errs.len() / 2];
    eprintln!(
        "visibility estimate vs synth visib_fract over {} instances: median |err| {med:.3}, max {:.3}",
        errs.len(),
        errs[errs.len() - 1]
    );
    // Open shells (bowls, mugs) and low resolution keep it approximate; typical error small.
    assert!(errs.len() >= 16 && med < 0.05, "median error {med}");
    let _ = std::fs::remove_dir_all(&dir);
}
