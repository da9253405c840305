//! Hidden-effect tests of `recon audit depth`: a `recon synth` dataset is generated
//! through a sensor model with one planted effect that the audited model lacks (target
//! fixed per test; covariate, form and parameters drawn from the test's seed), and the
//! audit must name the planted target/covariate/form, recover its parameters, report a
//! positive held-out gain, and report nothing on a dataset without a planted effect.
//!
//! `AUDIT_PLANTED_SEEDS=a..b cargo test --release --test audit_planted -- --ignored sweep`
//! runs the same checks over a range of seeds (default 10..16), prints a table per class and
//! asserts the floor (≥ 90 % found exactly, every null clean); `sweep_small_holds_its_floor`
//! is its CI-sized version.
#![allow(clippy::neg_cmp_op_on_partial_ord)] // `!(x > t)` also rejects NaN
mod common;

use common::tmp;
use recon::audit::{audit_depth, write_outputs, Audit};
use recon::audit::{collect, quantisation_sd, residual_table, DepthOptions, PixelSample, SearchOptions};
use recon::rng::SeededRng;
use recon::sensor::{Covariate, Effect, Form, PixelCovariates, SensorModel, Target};
use recon::synth::{generate, SynthOptions};
use std::collections::BTreeMap;
use std::path::PathBuf;

const W: usize = 160;
const H: usize = 120;
const SCENES: usize = 4;
const VIEWS: usize = 3;

/// Typical range of each covariate on object pixels of these synth scenes (for sizing
/// effects; recovery is checked on the observed values).
fn typical(c: Covariate) -> (f64, f64) {
    // 5–95 % quantiles of object pixels in these scenes (see `covariate_ranges`).
    match c {
        Covariate::Depth => (0.37, 1.05),
        Covariate::Radius => (0.07, 0.76),
        Covariate::Incidence => (17.0, 76.0),
        Covariate::EdgeDistance => (0.0, 10.0),
        Covariate::Intensity => (0.03, 0.6),
        Covariate::U => (0.1 * W as f64, 0.9 * W as f64),
        Covariate::V => (0.15 * H as f64, 0.85 * H as f64),
        Covariate::Frame => (0.0, (SCENES * VIEWS - 1) as f64),
        Covariate::Object => (0.0, 0.0),
    }
}

#[derive(Clone, Debug)]
struct Planted {
    effect: Effect,
    /// Added to the global dropout of the truth (a dropout effect that falls with its covariate).
    dropout_shift: f64,
    /// Effect size over the typical range (metres or probability).
    amplitude: f64,
    /// Added to the global bias of the truth (a subset below its threshold).
    bias_shift: f64,
}

/// Draws a planted effect of `target` from `seed`: a numeric covariate with a linear,
/// quadratic (vertex inside the range) or step form, or (`group`) per-object values.
fn plant(target: Target, seed: u64, group: bool) -> Planted {
    let mut rng = SeededRng::new(seed);
    let mut u = || rng.uniform();
    let amplitude = match target {
        Target::Bias => 0.0025 + 0.0025 * u(),
        Target::Noise => 0.002 + 0.002 * u(),
        Target::Dropout => 0.2 + 0.3 * u(),
    };
    let sign = if target == Target::Bias && u() < 0.5 { -1.0 } else { 1.0 };
    if group {
        let mut values = BTreeMap::new();
        for id in 1..=80 {
            let v = match target {
                Target::Bias => amplitude * (2.0 * u() - 1.0),
                _ => amplitude * u(),
            };
            values.insert(id.to_string(), v);
        }
        return Planted {
            effect: Effect { target, covariate: Covariate::Object, form: Form::Group { values }, by: None, cause: None },
            dropout_shift: 0.0,
            amplitude,
            bias_shift: 0.0,
        };
    }
    let numeric = [
        Covariate::Depth,
        Covariate::Radius,
        Covariate::Incidence,
        Covariate::EdgeDistance,
        Covariate::Intensity,
        Covariate::U,
        Covariate::V,
        Covariate::Frame,
    ];
    let cov = numeric[((u() * numeric.len() as f64) as usize).min(numeric.len() - 1)];
    let (lo, hi) = typical(cov);
    let kind = ((u() * 3.0) as usize).min(2);
    let mut dropout_shift = 0.0;
    let form = match kind {
        0 => {
            let slope = sign * amplitude / (hi - lo);
            // Missing returns falling with the covariate: start high, end near zero.
            if target == Target::Dropout && u() < 0.5 {
                dropout_shift = amplitude * hi / (hi - lo);
                Form::Linear { slope: -slope }
            } else {
                if target == Target::Dropout {
                    dropout_shift = -amplitude * lo / (hi - lo);
                }
                Form::Linear { slope }
            }
        }
        1 => {
            // q·(x − c)² with the vertex inside the range: no straight line mimics it.
            let c = lo + (0.3 + 0.4 * u()) * (hi - lo);
            let half = (hi - c).max(c - lo);
            let q = sign * amplitude / (half * half);
            Form::Quadratic { linear: -2.0 * q * c, quadratic: q }
        }
        _ => {
            let threshold = lo + (0.35 + 0.35 * u()) * (hi - lo);
            if target == Target::Dropout && u() < 0.5 {
                dropout_shift = amplitude;
                Form::Step { threshold, delta: -amplitude }
            } else {
                Form::Step { threshold, delta: sign * amplitude }
            }
        }
    };
    // The constant of a vertex-form quadratic is left to the global terms.
    if let (Target::Dropout, Form::Quadratic { linear, quadratic }) = (target, &form) {
        let c = -linear / (2.0 * quadratic);
        dropout_shift = quadratic * c * c;
    }
    Planted { effect: Effect { target, covariate: cov, form, by: None, cause: None }, dropout_shift, amplitude, bias_shift: 0.0 }
}

/// Generates the dataset through `truth`, audits it against `audited`.
fn audit(truth: &SensorModel, audited: &SensorModel, seed: u64, tag: &str) -> (Audit, recon::audit::ResidualTable, PathBuf) {
    audit_with(truth, audited, seed, tag, &mut |_| {})
}

/// [`audit`] with `plant` applied to the measured pixels before the table is built.
fn audit_with(
    truth: &SensorModel,
    audited: &SensorModel,
    seed: u64,
    tag: &str,
    plant: &mut dyn FnMut(&mut Vec<PixelSample>),
) -> (Audit, recon::audit::ResidualTable, PathBuf) {
    let dir = tmp(tag);
    let data = dir.join("data");
    let opts = SynthOptions { scenes: SCENES, views: VIEWS, seed, width: W, height: H, parts: false, sensor: truth.clone() };
    generate(&data, &opts, &|| {}).unwrap();
    let mut col = collect(&data, audited, &DepthOptions { max_pixels_per_frame: 1500, seed: 0, max_frames: None }).unwrap();
    plant(&mut col.pixels);
    let table = residual_table(audited, &col.pixels, "planted");
    let a = audit_depth(&table, &SearchOptions::default(), audited).unwrap();
    (a, table, dir)
}

fn audited_model() -> SensorModel {
    SensorModel::stereo_default()
}

fn truth_with(p: &Planted) -> SensorModel {
    let mut t = audited_model();
    t.effects.push(p.effect.clone());
    t.dropout = (t.dropout + p.dropout_shift).clamp(0.0, 1.0);
    t.bias_m += p.bias_shift;
    t
}

/// Checks one planted effect; returns Err(reason) instead of panicking (for the sweep).
fn check(p: &Planted, a: &Audit, table: &recon::audit::ResidualTable) -> Result<(), String> {
    let r = &a.report;
    let f = r.findings.first().ok_or_else(|| format!("no finding; rounds {:?}", r.rounds.first().map(|x| &x["top"])))?;
    let want = (p.effect.target.name(), p.effect.covariate.name(), p.effect.form.name());
    if (f.target.as_str(), f.covariate.as_str(), f.form.as_str()) != want {
        return Err(format!(
            "first finding {} ~ {}({}), planted {want:?}; findings {:?}",
            f.target,
            f.form,
            f.covariate,
            r.findings.iter().map(|x| format!("{}~{}({})", x.target, x.form, x.covariate)).collect::<Vec<_>>()
        ));
    }
    if !(f.heldout_gain > 0.0 && f.p_value < 0.01) {
        return Err(format!("held-out gain {} p {}", f.heldout_gain, f.p_value));
    }
    let after = &r.after["heldout"];
    let before = &r.baseline["heldout"];
    if !(after["loglik_per_row"].as_f64() > before["loglik_per_row"].as_f64()) {
        return Err(format!("log-likelihood did not improve: {} → {}", before["loglik_per_row"], after["loglik_per_row"]));
    }
    let fitted = f.effect.as_ref().ok_or("no effect")?;
    let ext = a.extended.as_ref().ok_or("no extended model")?;
    let truth = truth_with(p);
    // The target's total (global + effect) along the covariate, fitted vs planted, at
    // quantiles of the observed values (groups: every object with ≥ 300 pixels).
    let col = table.column(p.effect.covariate.name()).unwrap();
    let vals = &table.columns[col].values;
    let points: Vec<f64> = if p.effect.covariate == Covariate::Object {
        let mut n: BTreeMap<i64, usize> = BTreeMap::new();
        for v in vals {
            *n.entry(*v as i64).or_default() += 1;
        }
        n.into_iter().filter(|(_, c)| *c >= 300).map(|(k, _)| k as f64).collect()
    } else {
        let mut s = vals.clone();
        s.sort_by(|a, b| a.total_cmp(b));
        (1..=9).map(|i| s[(i * (s.len() - 1)) / 10]).collect()
    };
    // Whole-model prediction at a pixel with this covariate value (depth 0.8 m otherwise).
    let total = |m: &SensorModel, x: f64| -> f64 {
        let mut c = recon::sensor::PixelCovariates { depth: 0.8, ..Default::default() };
        set(&mut c, p.effect.covariate, x);
        match p.effect.target {
            Target::Bias => m.bias(&c),
            Target::Noise => m.sd(&c),
            Target::Dropout => m.p_missing(&c),
        }
    };
    let tol = 0.3 * p.amplitude + if p.effect.target == Target::Dropout { 0.02 } else { 0.0004 };
    for &x in &points {
        let (got, want) = (total(ext, x), total(&truth, x));
        if (got - want).abs() > tol {
            return Err(format!(
                "{} at {x}: fitted {got:.5} vs planted {want:.5} (tol {tol:.5}); fitted {:?}, planted {:?}",
                p.effect.covariate.name(),
                fitted.form,
                p.effect.form
            ));
        }
    }
    if let (Form::Step { threshold: a, .. }, Form::Step { threshold: b, .. }) = (&fitted.form, &p.effect.form) {
        let (lo, hi) = typical(p.effect.covariate);
        if (a - b).abs() > 0.1 * (hi - lo) {
            return Err(format!("threshold {a} vs planted {b}"));
        }
    }
    Ok(())
}

fn set(c: &mut recon::sensor::PixelCovariates, cv: Covariate, x: f64) {
    match cv {
        Covariate::Depth => c.depth = x,
        Covariate::Radius => c.radius = x,
        Covariate::Incidence => c.incidence = x,
        Covariate::EdgeDistance => c.edge_distance = x,
        Covariate::Intensity => c.intensity = x,
        Covariate::Frame => c.frame = x as i64,
        Covariate::U => c.u = x,
        Covariate::V => c.v = x,
        Covariate::Object => c.object = x as i64,
    }
}

/// Pixel-level covariates a planted subset is defined by. Frame-level subsets (1–3 whole
/// frames) are left out: with frames as held-out units they cannot be predicted.
const SUBSET_COVARIATES: [Covariate; 7] =
    [Covariate::Depth, Covariate::Radius, Covariate::Incidence, Covariate::EdgeDistance, Covariate::Intensity, Covariate::U, Covariate::V];

/// The class that hides in the outlier component: a bias of k·σ (k ∈ [5, 15]; σ the
/// audited model's sd at the median depth) on the valid pixels on one side (drawn) of a
/// threshold of a covariate drawn from the seed, 3–20 % of them. It is applied to the
/// measured pixels (a bias does not change which pixels exist or their covariates), so
/// the threshold can be set at the drawn share exactly. `null`: the same shift on as many
/// pixels drawn at random — truly random outliers at the same rate (then None).
fn plant_subset(seed: u64, pixels: &mut [PixelSample], audited: &SensorModel, null: bool) -> Option<Planted> {
    let mut rng = SeededRng::new(seed ^ 0x5B_5E7);
    let cov = SUBSET_COVARIATES[((rng.uniform() * 7.0) as usize).min(6)];
    let share = 0.03 + 0.17 * rng.uniform();
    let k = 5.0 + 10.0 * rng.uniform();
    let sign = if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
    let above = rng.uniform() < 0.5;
    let valid: Vec<usize> = (0..pixels.len()).filter(|&i| pixels[i].measured.is_finite() && pixels[i].measured > 0.0).collect();
    let mut z: Vec<f64> = valid.iter().map(|&i| pixels[i].cov.depth).collect();
    z.sort_by(f64::total_cmp);
    let zmed = z[z.len() / 2];
    let sigma = audited.sd(&PixelCovariates { depth: zmed, ..Default::default() }).hypot(quantisation_sd(audited, zmed));
    let delta = sign * k * sigma;
    // The cut between distinct values whose side holds the share nearest the drawn one.
    let mut xs: Vec<f64> = valid.iter().map(|&i| pixels[i].cov.get(cov)).collect();
    xs.sort_by(f64::total_cmp);
    let n = xs.len();
    let threshold = (0..n - 1)
        .filter(|&j| xs[j + 1] > xs[j])
        .map(|j| {
            let side = if above { n - 1 - j } else { j + 1 } as f64 / n as f64;
            ((side - share).abs(), 0.5 * (xs[j] + xs[j + 1]))
        })
        .min_by(|a, b| a.0.total_cmp(&b.0))
        .expect("covariate varies")
        .1;
    let inside = |x: f64| if above { x > threshold } else { x <= threshold };
    let mut chosen: Vec<usize> = valid.iter().copied().filter(|&i| inside(pixels[i].cov.get(cov))).collect();
    if null {
        let m = chosen.len();
        chosen = valid.clone();
        for j in 0..m {
            let r = j + (rng.next_u64() % (chosen.len() - j) as u64) as usize;
            chosen.swap(j, r);
        }
        chosen.truncate(m);
    }
    for &i in &chosen {
        pixels[i].measured += if null {
            // Random sign and size, in the pixel's own σ: outliers that no covariate orders.
            let z = pixels[i].cov.depth;
            let s = audited.sd(&PixelCovariates { depth: z, ..Default::default() }).hypot(quantisation_sd(audited, z));
            (if rng.uniform() < 0.5 { -1.0 } else { 1.0 }) * (5.0 + 10.0 * rng.uniform()) * s
        } else {
            delta
        };
    }
    eprintln!(
        "planted{}: bias {:+.2} mm ({k:.1} σ) on {:.1} % of valid pixels, {} {} {threshold:.3}",
        if null { " (null twin: random pixels)" } else { "" },
        1000.0 * delta,
        100.0 * chosen.len() as f64 / valid.len() as f64,
        cov.name(),
        if above { ">" } else { "≤" }
    );
    if null {
        return None;
    }
    // A subset below the threshold: the global bias carries it, the step takes it back above.
    let (d, shift) = if above { (delta, 0.0) } else { (-delta, delta) };
    Some(Planted {
        effect: Effect { target: Target::Bias, covariate: cov, form: Form::Step { threshold, delta: d }, by: None, cause: None },
        dropout_shift: 0.0,
        amplitude: k * sigma,
        bias_shift: shift,
    })
}

/// Nothing named: no finding and no significant dependence of the outliers.
fn clean(a: &Audit) -> Result<(), String> {
    let r = &a.report;
    if !r.findings.is_empty() {
        return Err(format!(
            "spurious: {:?}",
            r.findings.iter().map(|f| format!("{}~{}({}) p={:.2e}", f.target, f.form, f.covariate, f.p_value)).collect::<Vec<_>>()
        ));
    }
    let alpha = SearchOptions::default().alpha;
    let o = r.outliers.as_ref().ok_or("no outlier audit")?;
    if let Some(d) = o.significant(alpha).next() {
        return Err(format!("spurious outlier dependence {} ~ {} t {:.1} p {:.2e}", d.kind, d.covariate, d.t, d.p_value));
    }
    Ok(())
}

/// The subset class (or its null twin) for one seed: found exactly and the outliers
/// it hid are no longer outliers (or nothing named).
fn run_subset(seed: u64, null: bool) -> Result<(), String> {
    let m = audited_model();
    let mut planted = None;
    let (a, table, dir) =
        audit_with(&m, &m, 3000 + seed, &format!("subset-{seed}-{null}"), &mut |px| planted = plant_subset(seed, px, &m, null));
    eprint!("{}", a.report.summary());
    let _ = std::fs::remove_dir_all(&dir);
    let Some(p) = planted else { return clean(&a) };
    check(&p, &a, &table)?;
    let o = a.report.outliers.as_ref().ok_or("no outlier audit")?;
    if o.fraction_final >= 0.5 * o.fraction_baseline {
        return Err(format!("outliers {:.3} → {:.3}: the subset stayed in the outlier component", o.fraction_baseline, o.fraction_final));
    }
    Ok(())
}

#[test]
fn planted_subset_bias_hidden_in_outliers_is_found() {
    run_subset(21, false).unwrap_or_else(|e| panic!("seed 21: {e}"));
}

#[test]
fn random_outliers_at_the_same_rate_give_no_finding() {
    run_subset(21, true).unwrap_or_else(|e| panic!("seed 21 (null twin): {e}"));
}

fn run_planted(target: Target, seed: u64, group: bool) {
    let p = plant(target, seed, group);
    eprintln!("planted: {:?} (amplitude {:.4}, dropout shift {:.3})", p.effect, p.amplitude, p.dropout_shift);
    let (a, table, dir) = audit(&truth_with(&p), &audited_model(), 1000 + seed, &format!("{}-{seed}", target.name()));
    eprint!("{}", a.report.summary());
    if let Err(e) = check(&p, &a, &table) {
        panic!("seed {seed}: {e}");
    }
    // The outputs are written and the extended model round-trips through the sensor type.
    let mut a = a;
    let out = dir.join("out");
    write_outputs(&mut a, &out, None).unwrap();
    let ext = SensorModel::load(&out.join("sensor_extended.json")).unwrap();
    assert_eq!(ext.effects.last().map(|e| e.target), Some(target));
    assert!(std::fs::read_dir(out.join("plots")).unwrap().count() >= 1);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn planted_bias_is_found() {
    run_planted(Target::Bias, 1, false);
}

#[test]
fn planted_noise_is_found() {
    run_planted(Target::Noise, 2, false);
}

#[test]
fn planted_dropout_is_found() {
    run_planted(Target::Dropout, 3, false);
}

#[test]
fn planted_object_group_effect_is_found() {
    run_planted(Target::Bias, 4, true);
}

#[test]
fn null_dataset_gives_no_finding() {
    let m = audited_model();
    let (a, _, dir) = audit(&m, &m, 77, "null");
    eprint!("{}", a.report.summary());
    assert!(
        a.report.findings.is_empty(),
        "spurious: {:?}",
        a.report.findings.iter().map(|f| (&f.target, &f.covariate, &f.form, f.p_value)).collect::<Vec<_>>()
    );
    // Nothing to add: the extended model has no effects and its globals match the truth.
    let ext = a.extended.unwrap();
    assert!(ext.effects.is_empty());
    assert!(ext.bias_m.abs() < 3e-4 && ext.noise_m < 1e-3 && (ext.dropout - m.dropout).abs() < 0.005, "{ext:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The sweep's case kinds: six planted classes, the subset class, and two nulls.
const KINDS: [&str; 9] = ["bias", "noise", "dropout", "bias group", "noise group", "dropout group", "subset", "null", "subset null"];

/// One sweep case; Ok when found exactly (target, covariate, form, size within 30 %) or,
/// for a null, when nothing is named.
fn sweep_case(seed: u64, kind: &str) -> Result<String, String> {
    let (target, group) = match kind {
        "subset" => return run_subset(seed, false).map(|_| "subset".into()),
        "subset null" => return run_subset(seed, true).map(|_| "subset null".into()),
        "null" => {
            let m = audited_model();
            let (au, _, dir) = audit(&m, &m, 5000 + seed, &format!("sweepnull-{seed}"));
            let _ = std::fs::remove_dir_all(&dir);
            return clean(&au).map(|_| "null".into());
        }
        "bias" => (Target::Bias, false),
        "noise" => (Target::Noise, false),
        "dropout" => (Target::Dropout, false),
        "bias group" => (Target::Bias, true),
        "noise group" => (Target::Noise, true),
        "dropout group" => (Target::Dropout, true),
        other => return Err(format!("unknown sweep kind {other}")),
    };
    let p = plant(target, seed, group);
    let (au, table, dir) = audit(&truth_with(&p), &audited_model(), 1000 + seed, &format!("sweep-{seed}"));
    let _ = std::fs::remove_dir_all(&dir);
    let what = format!("{} ~ {}({})", target.name(), p.effect.form.name(), p.effect.covariate.name());
    check(&p, &au, &table).map(|_| what.clone()).map_err(|e| format!("{what}: {e}"))
}

/// Runs `kinds` over `seeds`, prints a table (found / planted per kind) and asserts the
/// floor: at least `floor` of the planted effects found exactly and every null clean.
fn sweep_assert(seeds: std::ops::Range<u64>, kinds: &[&str], floor: f64) {
    let mut tally: BTreeMap<&str, (usize, usize)> = BTreeMap::new();
    let mut fails = vec![];
    for seed in seeds.clone() {
        for &kind in kinds {
            let r = sweep_case(seed, kind);
            let e = tally.entry(kind).or_default();
            e.1 += 1;
            match r {
                Ok(w) => {
                    e.0 += 1;
                    eprintln!("ok   seed {seed} {kind}: {w}");
                }
                Err(why) => {
                    eprintln!("FAIL seed {seed} {kind}: {}", why.chars().take(300).collect::<String>());
                    fails.push(format!("seed {seed} {kind}"));
                }
            }
        }
    }
    let is_null = |k: &str| k.ends_with("null");
    eprintln!("sweep seeds {seeds:?}:");
    for k in kinds {
        let (f, n) = tally[k];
        eprintln!("  {k:<14} {f}/{n}");
    }
    let (found, planted) = tally.iter().filter(|(k, _)| !is_null(k)).fold((0, 0), |a, (_, v)| (a.0 + v.0, a.1 + v.1));
    let (clean_n, nulls) = tally.iter().filter(|(k, _)| is_null(k)).fold((0, 0), |a, (_, v)| (a.0 + v.0, a.1 + v.1));
    eprintln!(
        "  planted found exactly {found}/{planted}; nulls clean {clean_n}/{nulls}; all cases {}/{}",
        found + clean_n,
        planted + nulls
    );
    assert_eq!(clean_n, nulls, "a null named something: {fails:?}");
    assert!(found as f64 >= floor * planted as f64, "found {found}/{planted} < {floor}: {fails:?}");
}

/// The sweep with its floor: ≥ 90 % of planted effects found exactly, every null clean.
/// Run explicitly (about 10 min in release on 2 cores for 6 seeds):
///
/// `AUDIT_PLANTED_SEEDS=10..16 cargo test --release --test audit_planted -- --ignored sweep --nocapture`
#[test]
#[ignore]
fn sweep() {
    let range = std::env::var("AUDIT_PLANTED_SEEDS").unwrap_or_else(|_| "10..16".into());
    let (a, b) =
        range.split_once("..").and_then(|(a, b)| Some((a.parse::<u64>().ok()?, b.parse::<u64>().ok()?))).expect("AUDIT_PLANTED_SEEDS=a..b");
    // AUDIT_PLANTED_KINDS=a,b: only these kinds (for diagnosing; the floor is the full set's).
    let only = std::env::var("AUDIT_PLANTED_KINDS").ok();
    let kinds: Vec<&str> = KINDS.iter().copied().filter(|k| only.as_ref().is_none_or(|o| o.split(',').any(|x| x.trim() == *k))).collect();
    sweep_assert(a..b, &kinds, 0.9);
}

/// The CI-sized sweep: a per-object dropout group (which frame hold-out alone was too weak
/// for) and a null, on seed 31 (not used while developing the search; the other classes are
/// the ignored sweep's).
#[test]
fn sweep_small_holds_its_floor() {
    sweep_assert(31..32, &["dropout group", "null"], 0.9);
}

/// Prints covariate quantiles of the object pixels of a planted-test-sized dataset.
#[test]
#[ignore]
fn covariate_ranges() {
    let m = audited_model();
    let dir = tmp("ranges");
    let data = dir.join("data");
    generate(
        &data,
        &SynthOptions { scenes: SCENES, views: VIEWS, seed: 1001, width: W, height: H, parts: false, sensor: m.clone() },
        &|| {},
    )
    .unwrap();
    let col = collect(&data, &m, &DepthOptions { max_pixels_per_frame: 1500, seed: 0, max_frames: None }).unwrap();
    let t = residual_table(&m, &col.pixels, "ranges");
    for c in &t.columns {
        let mut v = c.values.clone();
        v.sort_by(|a, b| a.total_cmp(b));
        let q: Vec<String> =
            [0.0, 0.05, 0.25, 0.5, 0.75, 0.95, 1.0].iter().map(|&q| format!("{:.3}", v[((v.len() - 1) as f64 * q) as usize])).collect();
        eprintln!("{:>14}: {}", c.name, q.join(" "));
    }
    let _ = std::fs::remove_dir_all(&dir);
}
