//! Hidden-mechanism tests of the audit's mechanism inference (issue 33): a `recon synth`
//! dataset is generated through a sensor model with physical mechanisms planted (kind
//! fixed per case, parameters drawn from the case's seed inside a detectable part of the
//! prior); the audit sees only the measured dataset and the audited model without
//! mechanisms (blind) and must name the planted mechanism, not ambiguously, with its
//! free parameters within the tolerances of [`tolerance`]; nulls must name none; two
//! planted together must both be found.
//!
//! `AUDIT_MECH_SEEDS=a..b cargo test --test audit_mechanisms -- --ignored mechanism_sweep --nocapture`
//! runs every kind over the seeds (default 100..110) and prints the rates
//! (`AUDIT_MECH_KINDS=a,b` restricts the kinds). The CI subset is a few kinds on one seed.
mod common;

use common::tmp;
use recon::audit::{
    audit_depth_frames, collect, free_params, infer_mechanisms, residual_table, DepthOptions, MechanismOptions, MechanismReport,
    SearchOptions,
};
use recon::rng::SeededRng;
use recon::sensor::{Mechanism, SensorModel, MECHANISM_NAMES};
use recon::synth::{generate, SynthOptions};
use std::collections::BTreeMap;

const W: usize = 160;
const H: usize = 120;
const SCENES: usize = 4;
const VIEWS: usize = 2;
const PIXELS: usize = 600;

fn audited_model() -> SensorModel {
    SensorModel::stereo_default()
}

/// A planted mechanism of `kind` drawn from `seed`: magnitudes in the detectable part of
/// the prior, random signs.
fn plant(kind: &str, seed: u64) -> Mechanism {
    let mut rng = SeededRng::new(seed ^ 0xA5A5);
    let mut u = || rng.uniform();
    let mut sign = || if u() < 0.5 { -1.0 } else { 1.0 };
    let mut r = SeededRng::new(seed ^ 0x5A5A);
    let mut between = |a: f64, b: f64| a + (b - a) * r.uniform();
    match kind {
        "registration" => {
            let a = std::f64::consts::TAU * between(0.0, 1.0);
            let m = between(1.0, 3.0);
            Mechanism::Registration { du_px: m * a.cos(), dv_px: m * a.sin() }
        }
        "extrinsic_rotation" => Mechanism::ExtrinsicRotation { rx_deg: 0.0, ry_deg: 0.0, rz_deg: sign() * between(1.0, 3.0) },
        "depth_scale" => Mechanism::DepthScale { scale: sign() * between(0.01, 0.04) },
        "depth_offset" => Mechanism::DepthOffset { offset_m: sign() * between(0.004, 0.015) },
        "radial_distortion" => Mechanism::RadialDistortion { k1: sign() * between(0.12, 0.3), k2: 0.0 },
        "drift" => Mechanism::Drift { offset_m_per_frame: sign() * between(0.0005, 0.0015), scale_per_frame: 0.0 },
        "edge_fattening" => Mechanism::EdgeFattening { band_px: [2.0, 3.0, 4.0][(between(0.0, 2.999)) as usize] },
        "mixed_pixels" => Mechanism::MixedPixels { band_px: [1.5, 2.0, 3.0][(between(0.0, 2.999)) as usize] },
        "occlusion_shadow" => Mechanism::OcclusionShadow { baseline_m: sign() * between(0.06, 0.14) },
        "range_noise" => Mechanism::RangeNoise { coefficient: between(0.006, 0.015) },
        "grazing_dropout" => Mechanism::GrazingDropout { onset_deg: between(45.0, 65.0), rate: between(0.6, 1.0) },
        "dark_dropout" => Mechanism::DarkDropout { below: between(0.2, 0.45), rate: between(0.6, 1.0) },
        "material_group" => {
            Mechanism::MaterialGroup { intensity_below: between(0.15, 0.35), bias_m: sign() * between(0.004, 0.01), noise_m: 0.0 }
        }
        other => panic!("unknown kind {other}"),
    }
}

/// Tolerance of each free parameter: |fitted − planted| ≤ abs + rel·|planted|.
fn tolerance(kind: &str, param: &str) -> (f64, f64) {
    match (kind, param) {
        ("registration", _) => (0.3, 0.0),
        ("extrinsic_rotation", _) => (0.3, 0.0),
        ("depth_scale", _) => (0.002, 0.1),
        ("depth_offset", _) => (0.001, 0.0),
        ("radial_distortion", _) => (0.04, 0.15),
        ("drift", "offset_m_per_frame") => (0.0002, 0.0),
        ("drift", _) => (0.0005, 0.0),
        ("edge_fattening", _) | ("mixed_pixels", _) => (1.0, 0.0),
        ("occlusion_shadow", _) => (0.01, 0.3),
        ("range_noise", _) => (0.0, 0.3),
        ("grazing_dropout", "onset_deg") => (8.0, 0.0),
        ("dark_dropout", "below") => (0.08, 0.0),
        (_, "rate") => (0.25, 0.0),
        ("material_group", "intensity_below") => (0.08, 0.0),
        ("material_group", "bias_m") => (0.002, 0.0),
        ("material_group", _) => (0.003, 0.0),
        _ => (0.0, 0.0),
    }
}

/// Generates the dataset through the audited model plus `planted`, runs the inference blind.
fn infer(planted: &[Mechanism], seed: u64, tag: &str) -> MechanismReport {
    let dir = tmp(tag);
    let data = dir.join("data");
    let mut truth = audited_model();
    truth.mechanisms = planted.to_vec();
    let opts = SynthOptions { scenes: SCENES, views: VIEWS, seed, width: W, height: H, parts: false, sensor: truth };
    generate(&data, &opts, &|| {}).unwrap();
    let audited = audited_model();
    let col = collect(&data, &audited, &DepthOptions { max_pixels_per_frame: PIXELS, seed: 0, max_frames: None }).unwrap();
    let table = residual_table(&audited, &col.pixels, tag);
    let r = infer_mechanisms(&table, &SearchOptions::default(), &col.sims, &MechanismOptions::default()).unwrap();
    let _ = std::fs::remove_dir_all(&dir);
    r
}

/// Ok when every planted mechanism is selected, none unplanted, none ambiguous, and the
/// free parameters are within tolerance.
fn check(planted: &[Mechanism], r: &MechanismReport) -> Result<String, String> {
    let names: Vec<&str> = r.selected.iter().map(|s| s.mechanism.as_str()).collect();
    let what = format!("planted {:?}; named {names:?}; {}", planted, r.verdict);
    for p in planted {
        let Some(s) = r.selected.iter().find(|s| s.mechanism == p.name()) else { return Err(format!("{} not named: {what}", p.name())) };
        if s.ambiguous {
            return Err(format!("{} ambiguous: {what}", p.name()));
        }
        let vals = p.values();
        for &j in free_params(p.name()) {
            let name = p.prior()[j].name;
            let (abs, rel) = tolerance(p.name(), name);
            let got = s.parameters[name];
            if (got - vals[j]).abs() > abs + rel * vals[j].abs() {
                return Err(format!("{}.{name} = {got}, planted {} (tolerance {abs} + {rel}·|x|): {what}", p.name(), vals[j]));
            }
        }
    }
    if names.len() != planted.len() {
        return Err(format!("extra mechanism named: {what}"));
    }
    Ok(what)
}

fn case(kind: &str, seed: u64) -> Result<String, String> {
    match kind {
        "null" => {
            let r = infer(&[], 7000 + seed, &format!("mech-null-{seed}"));
            if r.selected.is_empty() {
                Ok("null: none named".into())
            } else {
                Err(format!("null named {:?}", r.verdict))
            }
        }
        "registration+depth_scale" | "drift+grazing_dropout" => {
            let (a, b) = kind.split_once('+').unwrap();
            let planted = [plant(a, seed), plant(b, seed + 500)];
            check(&planted, &infer(&planted, 8000 + seed, &format!("mech-combo-{seed}")))
        }
        k => {
            let planted = [plant(k, seed)];
            check(&planted, &infer(&planted, 6000 + seed, &format!("mech-{k}-{seed}")))
        }
    }
}

/// The sweep's cases beyond one per mechanism kind (`MECHANISM_NAMES`): two planted together, and a null.
const COMBINED: [&str; 3] = ["registration+depth_scale", "drift+grazing_dropout", "null"];

fn sweep(seeds: std::ops::Range<u64>, kinds: &[&str]) -> BTreeMap<String, (usize, usize)> {
    let mut tally: BTreeMap<String, (usize, usize)> = BTreeMap::new();
    for seed in seeds {
        for &k in kinds {
            let t0 = std::time::Instant::now();
            let r = case(k, seed);
            let e = tally.entry(k.to_string()).or_default();
            e.1 += 1;
            match r {
                Ok(w) => {
                    e.0 += 1;
                    eprintln!("ok   seed {seed} {k} ({:.1} s): {}", t0.elapsed().as_secs_f64(), w.chars().take(400).collect::<String>());
                }
                Err(w) => {
                    eprintln!("FAIL seed {seed} {k} ({:.1} s): {}", t0.elapsed().as_secs_f64(), w.chars().take(600).collect::<String>())
                }
            }
        }
    }
    for (k, (f, n)) in &tally {
        eprintln!("  {k:<26} {f}/{n}");
    }
    tally
}

/// The CI subset (seed 1): a geometric and a value mechanism planted together, a dropout
/// mechanism and a null. Each must pass. (Seed 1 of registration, depth_scale and drift
/// alone pass too; they are in the sweep.)
#[test]
fn planted_mechanisms_are_named_blind() {
    let kinds = ["registration+depth_scale", "grazing_dropout", "null"];
    let tally = sweep(1..2, &kinds);
    let fails: Vec<&String> = tally.iter().filter(|(_, v)| v.0 < v.1).map(|(k, _)| k).collect();
    assert!(fails.is_empty(), "failed: {fails:?}");
}

/// The sweep (≥ 10 seeds per kind). Prints the rates; asserts the floor of the issue
/// (≥ 90 % named with parameters in tolerance, every null clean) over the kinds run.
#[test]
#[ignore]
fn mechanism_sweep() {
    let range = std::env::var("AUDIT_MECH_SEEDS").unwrap_or_else(|_| "100..110".into());
    let (a, b) =
        range.split_once("..").and_then(|(a, b)| Some((a.parse::<u64>().ok()?, b.parse::<u64>().ok()?))).expect("AUDIT_MECH_SEEDS=a..b");
    let only = std::env::var("AUDIT_MECH_KINDS").ok();
    let kinds: Vec<&str> = MECHANISM_NAMES
        .iter()
        .chain(&COMBINED)
        .copied()
        .filter(|k| only.as_ref().is_none_or(|o| o.split(',').any(|x| x.trim() == *k)))
        .collect();
    let tally = sweep(a..b, &kinds);
    let nulls = tally.get("null").copied().unwrap_or((0, 0));
    assert_eq!(nulls.0, nulls.1, "a null named a mechanism");
    let (f, n) = tally.iter().filter(|(k, _)| k.as_str() != "null").fold((0, 0), |a, (_, v)| (a.0 + v.0, a.1 + v.1));
    eprintln!("planted named in tolerance {f}/{n}");
    assert!(f as f64 >= 0.9 * n as f64, "{f}/{n} below the 90 % floor");
}

/// The case: a registration error. The covariate search finds effects in some
/// covariates; the mechanism inference names the registration, and every covariate
/// finding it makes vanish points at it.
#[test]
fn registration_is_named_and_explains_the_covariate_findings() {
    let dir = tmp("mech-full");
    let data = dir.join("data");
    let mut truth = audited_model();
    truth.mechanisms = vec![Mechanism::Registration { du_px: 2.0, dv_px: -1.0 }];
    let opts = SynthOptions { scenes: SCENES, views: VIEWS, seed: 33, width: W, height: H, parts: false, sensor: truth };
    generate(&data, &opts, &|| {}).unwrap();
    let audited = audited_model();
    let col = collect(&data, &audited, &DepthOptions { max_pixels_per_frame: PIXELS, seed: 0, max_frames: None }).unwrap();
    let table = residual_table(&audited, &col.pixels, "registration");
    let search = SearchOptions { bootstrap: 10, interactions: false, max_findings: 3, ..Default::default() };
    let a = audit_depth_frames(&table, &search, &audited, &col.sims, &MechanismOptions::default()).unwrap();
    let m = a.report.mechanisms.as_ref().expect("mechanism section");
    assert_eq!(m.selected.first().map(|s| s.mechanism.as_str()), Some("registration"), "{}", m.verdict);
    assert!(!m.selected[0].ambiguous);
    assert!(
        (m.selected[0].parameters["du_px"] - 2.0).abs() < 0.3 && (m.selected[0].parameters["dv_px"] + 1.0).abs() < 0.3,
        "{:?}",
        m.selected[0]
    );
    let json = serde_json::to_value(&a.report).unwrap();
    assert!(json["mechanisms"]["selected"][0]["runner_up"].is_string());
    assert_eq!(m.findings_explained.len(), a.report.findings.len());
    for (e, f) in m.findings_explained.iter().zip(&a.report.findings) {
        eprintln!("{} p {:.2e} → {:?}: {:?}", e.term, e.p_before, e.p_after, f.explained_by);
    }
    // Every covariate finding says what explains it; the strongest, if any, is the
    // registration (on this seed the covariate search finds nothing at its level: the
    // shift spreads over several covariates, which is the point).
    assert!(a.report.findings.iter().all(|f| f.explained_by.is_some()));
    if let Some(top) = a.report.findings.first() {
        assert_eq!(top.explained_by.as_deref(), Some("registration"), "{}", a.report.summary());
    }
    let summary = a.report.summary();
    assert!(summary.contains("mechanisms (held-out frames") && summary.contains("registration (du_px"), "{summary}");
    // The posterior predictive check: the fitted registration reproduces the measured
    // residual statistics overall and along depth, u and v, and more of them than the
    // audited model alone. (At edge pixels and grazing incidence it need not: there the
    // shift shows the support plane, which the audit's simulation of the GT objects lacks.)
    let pc = &m.predictive_check;
    let failing: Vec<String> = pc
        .rows
        .iter()
        .filter(|r| !r.pass)
        .map(|r| {
            format!(
                "{} {} {}: measured {:.3}, simulated {:.3} [{:.3}, {:.3}]",
                r.statistic, r.covariate, r.bin, r.measured, r.simulated, r.lo, r.hi
            )
        })
        .collect();
    eprintln!("{}: {failing:#?}", pc.verdict);
    assert!(pc.failed.len() < pc.null_failed.len(), "{}", pc.verdict);
    assert!(pc.rows.iter().filter(|r| ["all", "depth", "u", "v"].contains(&r.covariate.as_str())).all(|r| r.pass), "{failing:#?}");
    assert!(pc.rows.iter().any(|r| r.covariate == "u") && pc.rows.iter().any(|r| r.statistic == "missing_rate"));
    // The depth correction: written beside report.json, it reads back, holds the fitted
    // registration, and applied to the measured frames brings them closer to the
    // simulated (clean) depth.
    let mut a = a;
    let out = dir.join("audit");
    recon::audit::write_outputs(&mut a, &out, None).unwrap();
    let corr = recon::sensor::DepthCorrection::load(&out.join(recon::audit::CORRECTION_FILE)).unwrap();
    let m = a.report.mechanisms.as_ref().unwrap();
    let invertible: Vec<Mechanism> = m.fitted.iter().filter(|f| recon::sensor::INVERTIBLE.contains(&f.name())).cloned().collect();
    assert_eq!(corr.corrections, invertible);
    assert!(corr.corrections.iter().any(|c| c.name() == "registration"));
    assert!(std::fs::read_to_string(out.join("report.html")).unwrap().contains("id=\"predictive-verdict\""));
    let ds = recon::dataset::load_dataset(&data).unwrap();
    let (mut before, mut after, mut n) = (0usize, 0usize, 0usize);
    for (fi, (f, sim)) in ds.frames.iter().zip(&col.sims).enumerate() {
        let (raw, w, h) = recon::dataset::frame::load_depth_u16(&ds.depth_path(f)).unwrap();
        let measured: Vec<f32> = raw.iter().map(|&v| (v as f64 * f.depth_scale_m) as f32).collect();
        let fixed = corr.apply(&measured, w, h, sim.k, fi as i64);
        for i in 0..w * h {
            let (x, y) = (i % w, i / w);
            if sim.depth[i] > 0.0 && (4..w - 4).contains(&x) && (4..h - 4).contains(&y) && measured[i] > 0.0 && fixed[i] > 0.0 {
                let far = |z: f32| (z - sim.depth[i]).abs() > 0.03;
                n += 1;
                before += far(measured[i]) as usize;
                after += far(fixed[i]) as usize;
            }
        }
    }
    eprintln!("pixels off the simulated depth by > 3 cm: {before}/{n} measured, {after}/{n} corrected");
    assert!(n > 1000 && (after as f64) < 0.5 * before as f64, "{before} → {after} of {n}");
    let _ = std::fs::remove_dir_all(&dir);
}
