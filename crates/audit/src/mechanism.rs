//! Mechanism-level inference: which physical sensor mechanism ([`Mechanism`]) explains
//! the measured depth, with what parameters, and how sure the data make us.
//!
//! **Likelihood.** Each table row is an object pixel of a frame whose simulated images
//! ([`SimFrame`]) are kept, so a mechanism's forward model ([`expect`]) is evaluated on
//! the image (a registration shift or a distortion moves where a pixel looks). Per row,
//! with the mechanisms' expectation `e` and the audited model's bias `b`, floor and offsets:
//! ```text
//! μ = e.gain·(z_e + b) + e.offset        (z_e: the seen depth; mixed pixels: halfway)
//! σ = sqrt(floor² + v + e.var + Δz²/12) + sd_offset
//! r ~ (1−π)·N(μ, σ²) + π·U(−W, W)        valid rows (a row whose seen surface is not in
//!                                        the simulation: U(−W, W) alone)
//! missing ~ Bernoulli(clamp(p0 + p_offset + e.p))   (shadowed rows: 1 − 10⁻³)
//! ```
//! with the nuisance `v` (noise², in quadrature), `π` (outliers, the same uniform
//! density as the covariate search) and `p0` (dropout) refitted with the mechanism.
//! The null is the audited model with only the nuisance fitted: no free global bias, so a
//! depth offset is a mechanism to find, not a nuisance to absorb.
//!
//! **Fit.** Maximum likelihood over each mechanism's free parameters ([`free_params`]):
//! a grid over the prior, then Nelder–Mead inside it (the nuisance re-fitted at every
//! point by a few warm-started EM / Newton steps).
//!
//! **Test.** The covariate search's protocol ([`crate::search`]): folds of frames, every
//! candidate fitted on each fold's training frames and scored on its held-out frames;
//! gains per fold against the current model; a sign-flip randomisation test with the
//! max-T / raw-max family-wise correction over the round's fitted candidates. A cheap
//! full-data likelihood-ratio screen (`screen_alpha`, then the `max_fitted` largest
//! full-data gains) skips the fold fits of candidates with no sign of an effect. The winner (largest held-out gain among the significant)
//! is compared with the runner-up (the next largest gain) by a paired sign-flip test of
//! their fold gains: above `ambiguity_alpha` the report says "ambiguous between X and
//! Y". Greedy: the winner joins the model and the remaining kinds are tried on top.
//! After each acceptance the earlier mechanisms are refitted with the others fixed
//! (backfitting, in every fold). Standard errors: the jackknife over the fold fits
//! (frames left out), which carries the correlation of pixels within a frame.
use crate::fit::{Ctx, Term, P_EPS};
use crate::predictive::{PredictiveCheck, RowModel};
use crate::search::{flipped_t, sign_patterns, Folds, SearchOptions};
use crate::table::ResidualTable;
use rayon::prelude::*;
use recon_core::sensor::{expect, DepthCorrection, Expect, Mechanism, SimFrame, MECHANISM_NAMES};
use recon_core::{Error, Result};
use serde::Serialize;
use std::collections::BTreeMap;

/// Settings of the mechanism inference.
#[derive(Clone, Debug)]
pub struct MechanismOptions {
    /// Family-wise level of each round (as the covariate search).
    pub alpha: f64,
    /// Full-data likelihood-ratio screen: candidates above it are not fold-fitted.
    pub screen_alpha: f64,
    /// The winner must beat the runner-up at this level (paired, held out), else "ambiguous".
    pub ambiguity_alpha: f64,
    /// At most this many mechanisms.
    pub max_mechanisms: usize,
    /// At most this many candidates per round are fold-fitted (those passing the screen
    /// with the largest full-data gain; a data-dependent screen like the search's).
    pub max_fitted: usize,
    /// Kinds tried (default: all of [`MECHANISM_NAMES`]).
    pub kinds: Vec<String>,
}

impl Default for MechanismOptions {
    fn default() -> Self {
        MechanismOptions {
            alpha: 0.01,
            screen_alpha: 0.01,
            ambiguity_alpha: 0.05,
            max_mechanisms: 3,
            max_fitted: 4,
            kinds: MECHANISM_NAMES.iter().map(|s| s.to_string()).collect(),
        }
    }
}

impl MechanismOptions {
    /// The levels of the covariate search, all kinds.
    pub fn from_search(o: &SearchOptions) -> Self {
        MechanismOptions { alpha: o.alpha, screen_alpha: o.screen_alpha, ..Default::default() }
    }
}

/// Parameters a kind's fit frees (indices into [`Mechanism::prior`]); the others stay
/// neutral. Rotation: the roll only (about x and y it is a registration shift);
/// distortion: k1 only (k2 is poorly identified on small images).
pub fn free_params(kind: &str) -> &'static [usize] {
    match kind {
        "registration" | "drift" | "grazing_dropout" | "dark_dropout" => &[0, 1],
        "extrinsic_rotation" => &[2],
        "material_group" => &[0, 1, 2],
        _ => &[0],
    }
}

/// Kinds whose likelihood is piecewise constant in the parameter (pixel bands): grid only.
fn grid_only(kind: &str) -> bool {
    matches!(kind, "edge_fattening" | "mixed_pixels" | "occlusion_shadow")
}

/// One tried mechanism in one round.
#[derive(Serialize, Clone, Debug)]
pub struct Candidate {
    /// Kind.
    pub mechanism: String,
    /// Full-data fit (free parameters only).
    pub parameters: BTreeMap<String, f64>,
    /// Full-data log-likelihood gain over the current model (nats; the screen).
    pub fulldata_gain: f64,
    /// Fold-fitted (passed the screen).
    pub fitted: bool,
    /// Held-out gain over the current model, nats (sum over folds).
    pub heldout_gain_total: f64,
    /// The same per compared row.
    pub heldout_gain_per_row: f64,
    /// Folds whose held-out gain is positive, "k/n".
    pub folds_improved: String,
    /// t of the fold gains (descriptive).
    pub t: f64,
    /// Family-wise p (max statistic over the round's fitted candidates).
    pub p_value: f64,
    /// This candidate's own randomisation p.
    pub p_value_raw: f64,
    #[serde(skip)]
    gains: Vec<f64>,
}

/// One greedy round.
#[derive(Serialize, Clone, Debug)]
pub struct MechRound {
    /// Candidates, largest held-out gain first.
    pub candidates: Vec<Candidate>,
    /// The accepted kind, if any was significant.
    pub selected: Option<String>,
}

/// An accepted mechanism.
#[derive(Serialize, Clone, Debug)]
pub struct MechFinding {
    /// Kind.
    pub mechanism: String,
    /// Fitted parameters (full data), free ones only.
    pub parameters: BTreeMap<String, f64>,
    /// Jackknife standard errors over the held-out folds.
    pub standard_errors: BTreeMap<String, f64>,
    /// Family-wise p against the model before it (the null for the first).
    pub p_value: f64,
    /// Held-out gain over the model before it, nats.
    pub heldout_gain_total: f64,
    /// Folds improved, "k/n".
    pub folds_improved: String,
    /// The next best kind of its round.
    pub runner_up: Option<String>,
    /// Runner-up's held-out gain, nats.
    pub runner_up_gain_total: Option<f64>,
    /// Winner − runner-up, nats (held out).
    pub margin_nats: Option<f64>,
    /// Paired sign-flip p that the winner beats the runner-up.
    pub margin_p: Option<f64>,
    /// The margin is not significant at `ambiguity_alpha`.
    pub ambiguous: bool,
    /// The sentence.
    pub statement: String,
}

/// The fitted mechanisms against the covariate search's final model (same folds).
#[derive(Serialize, Clone, Debug)]
pub struct Versus {
    /// Mechanism model − covariate model, held-out nats (positive: mechanisms better).
    pub mechanisms_minus_findings: f64,
    /// Paired sign-flip p that the mechanisms are better.
    pub p_mechanisms_better: f64,
    /// Paired sign-flip p that the covariate findings are better.
    pub p_findings_better: f64,
}

/// Whether a covariate finding disappears once the mechanisms are fitted.
#[derive(Serialize, Clone, Debug)]
pub struct Explained {
    /// Index into the report's findings.
    pub finding: usize,
    /// "target ~ form(covariate)".
    pub term: String,
    /// Score-test p of the finding's term at the baseline on the original residuals.
    pub p_before: f64,
    /// The same with each accepted mechanism alone fitted, then (two or more) all of them.
    pub p_after: Vec<(String, f64)>,
    /// The first mechanism that alone makes the term non-significant (`screen_alpha`),
    /// else the set ("a + b") if together they do.
    pub explained_by: Option<String>,
}

/// The mechanism section of the report.
#[derive(Serialize, Clone, Debug)]
pub struct MechanismReport {
    /// How it was done (one line).
    pub method: String,
    /// Family-wise level of each round.
    pub alpha: f64,
    /// Level of the winner-vs-runner-up test.
    pub ambiguity_alpha: f64,
    /// Folds (held-out frame groups).
    pub folds: usize,
    /// Null model's held-out log-likelihood, nats.
    pub null_heldout_loglik: f64,
    /// Accepted mechanisms in order.
    pub selected: Vec<MechFinding>,
    /// The accepted mechanisms with full-data parameters (sensor-model JSON form): the
    /// input of a correction or of an extended model.
    pub fitted: Vec<Mechanism>,
    /// One line: what the data support.
    pub verdict: String,
    /// Against the covariate findings (depth audits with a search).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub versus_findings: Option<Versus>,
    /// Which covariate findings each mechanism explains.
    pub findings_explained: Vec<Explained>,
    /// Posterior predictive check: the residual statistics the fitted mechanisms simulate
    /// against the measured ones (module `predictive`).
    pub predictive_check: PredictiveCheck,
    /// What `depth_correction.json` holds: the accepted invertible mechanisms, and the
    /// others with the reason they are not corrected.
    pub depth_correction: DepthCorrection,
    /// Every round.
    pub rounds: Vec<MechRound>,
}

/// Per-row constants of the likelihood.
struct Rows {
    meas: Vec<f64>,
    sim: Vec<f64>,
    bias: Vec<f64>,
    floor2: Vec<f64>,
    sd_off: Vec<f64>,
    lowest: Vec<f64>,
    p_off: Vec<f64>,
    /// (frame slot, pixel index) of each row.
    px: Vec<(usize, usize)>,
    ln_dens: f64,
    robust: bool,
}

/// The data of the inference: the table's rows located in their frames.
pub struct MechData<'a> {
    rows: Rows,
    frames: &'a [SimFrame],
    n: usize,
}

impl<'a> MechData<'a> {
    /// Locates every table row (columns `frame`, `u`, `v`) in `frames` (indexed by the
    /// frame column's value).
    pub fn new(ctx: &Ctx, frames: &'a [SimFrame]) -> Result<Self> {
        let t = ctx.table;
        let col = |name: &str| {
            t.column(name).ok_or_else(|| Error::input(t.source.clone(), format!("the mechanism inference needs a `{name}` column")))
        };
        let (cf, cu, cv, cd) = (col("frame")?, col("u")?, col("v")?, col("depth")?);
        let n = t.len();
        let mut px = Vec::with_capacity(n);
        for i in 0..n {
            let fi = t.columns[cf].values[i].round();
            let f = (fi >= 0.0).then_some(fi as usize).and_then(|s| frames.get(s)).ok_or_else(|| {
                Error::input(t.source.clone(), format!("row {i}: frame {fi} has no simulated image ({} given)", frames.len()))
            })?;
            let (u, v) = (t.columns[cu].values[i].round(), t.columns[cv].values[i].round());
            if !(u >= 0.0 && v >= 0.0 && (u as usize) < f.width && (v as usize) < f.height) {
                return Err(Error::input(t.source.clone(), format!("row {i}: pixel ({u}, {v}) is outside frame {fi}")));
            }
            px.push((fi as usize, v as usize * f.width + u as usize));
        }
        let rows = Rows {
            meas: t.measured.iter().map(|&m| if m.is_finite() { m } else { f64::NAN }).collect(),
            sim: t.simulated.clone(),
            bias: (0..n).map(|i| t.simulated[i] - t.columns[cd].values[i]).collect(),
            floor2: t.sd_floor.iter().map(|f| f * f).collect(),
            sd_off: t.sd_offset.clone(),
            lowest: (0..n).map(|i| ctx.sd_lowest(i)).collect(),
            p_off: t.p_offset.clone(),
            px,
            ln_dens: ctx.outlier_density.ln(),
            robust: ctx.robust,
        };
        Ok(MechData { rows, frames, n })
    }

    /// Expectations of `rows` under `mechs`, in `rows` order.
    fn expect_rows(&self, mechs: &[Mechanism], rows: &[usize]) -> Vec<Expect> {
        let mut by_frame: BTreeMap<usize, (Vec<usize>, Vec<usize>)> = BTreeMap::new();
        for (j, &i) in rows.iter().enumerate() {
            let (s, p) = self.rows.px[i];
            let e = by_frame.entry(s).or_default();
            e.0.push(j);
            e.1.push(p);
        }
        let ident = Expect { src: None, z: 0.0, other: 0.0, unknown: false, shadow: false, gain: 1.0, offset: 0.0, var: 0.0, p: 0.0 };
        let mut out = vec![ident; rows.len()];
        for (s, (js, ps)) in by_frame {
            for (j, e) in js.into_iter().zip(expect(mechs, &self.frames[s], &ps)) {
                out[j] = e;
            }
        }
        out
    }

    /// Table for the covariate search with the mechanisms' predictions as the simulation.
    pub fn corrected_table(&self, table: &ResidualTable, mechs: &[Mechanism]) -> ResidualTable {
        let all: Vec<usize> = (0..self.n).collect();
        let ex = self.expect_rows(mechs, &all);
        let mut t = table.clone();
        for (i, e) in ex.iter().enumerate() {
            if let Some(pr) = predict(&self.rows, i, e, 0.0) {
                t.simulated[i] = pr.0;
                t.sd_floor[i] = (self.rows.floor2[i] + pr.2).sqrt();
            }
            t.p_offset[i] += if e.shadow { 1.0 } else { e.p };
        }
        t
    }
}

/// (μ, σ, extra variance) of a valid row; None: its surface is not in the simulation.
#[inline]
fn predict(r: &Rows, i: usize, e: &Expect, v: f64) -> Option<(f64, f64, f64)> {
    if e.src.is_none() || !(e.z > 0.0) || e.unknown {
        return None;
    }
    let (zeff, mixvar) = if e.other > 0.0 { (0.5 * (e.z + e.other), e.gain * e.gain * (e.other - e.z).powi(2) / 12.0) } else { (e.z, 0.0) };
    let mu = e.gain * (zeff + r.bias[i]) + e.offset;
    let extra = e.var + mixvar;
    let s = ((r.floor2[i] + v.max(0.0) + extra).sqrt() + r.sd_off[i]).max(r.lowest[i]);
    Some((mu, s, extra))
}

const HALF_LN_2PI: f64 = 0.918_938_533_204_672_7;
const P_SHADOW: f64 = 1.0 - 1e-3;

/// Nuisance parameters: noise² (quadrature), outlier weight, dropout.
#[derive(Clone, Copy, Debug)]
struct Nuis {
    v: f64,
    pi: f64,
    p0: f64,
}

/// (log-likelihood, inlier responsibility).
#[inline]
fn mix_ll(robust: bool, pi: f64, ln_dens: f64, r: f64, mu: f64, s: f64) -> (f64, f64) {
    let z = (r - mu) / s;
    let lphi = -0.5 * z * z - s.ln() - HALF_LN_2PI;
    if !robust {
        return (lphi, 1.0);
    }
    let a = (1.0 - pi).ln() + lphi;
    let b = pi.ln() + ln_dens;
    let d = b - a;
    if d < -37.0 {
        (a, 1.0)
    } else if d > 37.0 {
        (b, (-d).exp())
    } else {
        let e = d.exp();
        (a + e.ln_1p(), 1.0 / (1.0 + e))
    }
}

fn p_row(r: &Rows, i: usize, e: &Expect, p0: f64) -> f64 {
    if e.shadow {
        P_SHADOW
    } else {
        (p0 + r.p_off[i] + e.p).clamp(P_EPS, 1.0 - P_EPS)
    }
}

/// Log-likelihood of each row in `rows` (Gaussian + Bernoulli parts).
fn row_ll(d: &MechData, rows: &[usize], ex: &[Expect], n: Nuis) -> Vec<f64> {
    let r = &d.rows;
    rows.iter()
        .zip(ex)
        .map(|(&i, e)| {
            let p = p_row(r, i, e, n.p0);
            if !r.meas[i].is_finite() {
                return p.ln();
            }
            let g = match predict(r, i, e, n.v) {
                Some((mu, s, _)) => mix_ll(r.robust, n.pi, r.ln_dens, r.meas[i], mu, s).0,
                None => r.ln_dens,
            };
            g + (1.0 - p).ln()
        })
        .collect()
}

/// The fitted model's prediction of every row (the posterior predictive check's input).
fn row_models(d: &MechData, fit: &Fit) -> Vec<RowModel> {
    let all: Vec<usize> = (0..d.n).collect();
    let ex = d.expect_rows(&fit.mechs, &all);
    let r = &d.rows;
    all.iter()
        .zip(&ex)
        .map(|(&i, e)| RowModel {
            mean_sd: predict(r, i, e, fit.nuis.v).map(|(mu, s, _)| (mu, s)),
            outlier: if r.robust { fit.nuis.pi } else { 0.0 },
            // As the sensor model simulates (`SensorModel::apply_frame`): a pixel that sees
            // off the image returns nothing. One that sees a surface the simulation lacks
            // (the audit's frames hold the GT objects only) returns that surface: the
            // likelihood's uniform.
            p_missing: if e.src.is_none() { 1.0 } else { p_row(r, i, e, fit.nuis.p0) },
        })
        .collect()
}

/// Warm-started EM (π), Fisher scoring (v) and Newton (p0) steps; returns the total
/// log-likelihood at the result.
fn fit_nuisance(d: &MechData, rows: &[usize], ex: &[Expect], start: Nuis, iters: usize) -> (Nuis, f64) {
    let r = &d.rows;
    let mut n = start;
    for _ in 0..iters {
        let (mut out_w, mut cnt, mut g, mut w) = (0.0, 0.0, 0.0, 0.0);
        for (&i, e) in rows.iter().zip(ex) {
            if !r.meas[i].is_finite() {
                continue;
            }
            let Some((mu, s, extra)) = predict(r, i, e, n.v) else { continue };
            let (_, resp) = mix_ll(r.robust, n.pi, r.ln_dens, r.meas[i], mu, s);
            out_w += 1.0 - resp;
            cnt += 1.0;
            let z = (r.meas[i] - mu) / s;
            let s0 = (r.floor2[i] + n.v.max(0.0) + extra).sqrt();
            if s > r.lowest[i] && s0 > 0.0 {
                let ds = 0.5 / s0;
                g += resp * (z * z - 1.0) / s * ds;
                w += resp * 2.0 / (s * s) * ds * ds;
            }
        }
        if r.robust && cnt > 0.0 {
            n.pi = (out_w / cnt).clamp(1e-6, 0.5);
        }
        if w > 0.0 {
            n.v = (n.v + g / w).max(0.0);
        }
        // Dropout: Newton on p0 over the rows not clamped.
        for _ in 0..2 {
            let (mut g1, mut h1) = (0.0, 0.0);
            for (&i, e) in rows.iter().zip(ex) {
                if e.shadow {
                    continue;
                }
                let q = n.p0 + r.p_off[i] + e.p;
                if !(q > P_EPS && q < 1.0 - P_EPS) {
                    continue;
                }
                if r.meas[i].is_finite() {
                    g1 -= 1.0 / (1.0 - q);
                    h1 += 1.0 / ((1.0 - q) * (1.0 - q));
                } else {
                    g1 += 1.0 / q;
                    h1 += 1.0 / (q * q);
                }
            }
            if h1 > 0.0 {
                n.p0 = (n.p0 + g1 / h1).clamp(0.0, 1.0 - P_EPS);
            }
        }
    }
    let ll = row_ll(d, rows, ex, n).iter().sum();
    (n, ll)
}

/// A fitted state: mechanisms (with parameters) and nuisance.
#[derive(Clone, Debug)]
struct Fit {
    mechs: Vec<Mechanism>,
    nuis: Nuis,
    ll: f64,
}

fn start_nuis(d: &MechData, rows: &[usize]) -> Nuis {
    let miss = rows.iter().filter(|&&i| !d.rows.meas[i].is_finite()).count() as f64 / rows.len().max(1) as f64;
    let valid: Vec<usize> = rows.iter().copied().filter(|&i| d.rows.meas[i].is_finite()).collect();
    let resid: Vec<f64> = valid.iter().map(|&i| d.rows.meas[i] - d.rows.sim[i]).collect();
    let sd = crate::stats::robust_sd(&resid);
    let f2 = valid.iter().map(|&i| d.rows.floor2[i]).sum::<f64>() / valid.len().max(1) as f64;
    // Never exactly 0: the Fisher step in v needs σ above its clamp to move.
    let v = (sd * sd - f2).max(1e-4 * sd * sd).max(1e-14);
    Nuis { v, pi: if d.rows.robust { 0.01 } else { 0.0 }, p0: miss }
}

/// Fits the nuisance of `mechs` (no free mechanism parameter).
fn fit_fixed(d: &MechData, rows: &[usize], mechs: &[Mechanism], start: Nuis) -> Fit {
    let ex = d.expect_rows(mechs, rows);
    let (nuis, ll) = fit_nuisance(d, rows, &ex, start, 25);
    Fit { mechs: mechs.to_vec(), nuis, ll }
}

/// Maximum-likelihood fit of `cand`'s free parameters on top of `base` (fixed).
fn fit_candidate(d: &MechData, rows: &[usize], base: &Fit, cand: &Mechanism) -> Fit {
    let kind = cand.name();
    let free = free_params(kind);
    let prior = cand.prior();
    let to_mech = |x: &[f64]| -> Mechanism {
        let mut vals = cand.values();
        for (k, &j) in free.iter().enumerate() {
            let pr = prior[j];
            vals[j] = pr.lo + x[k].clamp(0.0, 1.0) * (pr.hi - pr.lo);
        }
        cand.with_values(&vals)
    };
    let eval = |x: &[f64], iters: usize| -> (f64, Nuis) {
        let mut mechs = base.mechs.clone();
        mechs.push(to_mech(x));
        let ex = d.expect_rows(&mechs, rows);
        let (n, ll) = fit_nuisance(d, rows, &ex, base.nuis, iters);
        (ll, n)
    };
    let dim = free.len();
    let per: usize = match (dim, grid_only(kind)) {
        (1, true) => 31,
        (1, false) => 17,
        (2, _) => 9,
        _ => 5,
    };
    let mut best: (f64, Vec<f64>) = (f64::NEG_INFINITY, vec![0.5; dim]);
    let total = per.pow(dim as u32);
    for g in 0..total {
        let mut x = vec![0.0; dim];
        let mut r = g;
        for xk in x.iter_mut() {
            *xk = (r % per) as f64 / (per - 1) as f64;
            r /= per;
        }
        let (ll, _) = eval(&x, 3);
        if ll > best.0 {
            best = (ll, x);
        }
    }
    let mut x = best.1;
    if !grid_only(kind) {
        x = nelder_mead(&|x: &[f64]| -eval(x, 3).0, &x, 0.5 / (per - 1) as f64, 40);
    }
    let (_, nuis) = eval(&x, 3);
    let mut mechs = base.mechs.clone();
    mechs.push(to_mech(&x));
    let ex = d.expect_rows(&mechs, rows);
    let (nuis, ll) = fit_nuisance(d, rows, &ex, nuis, 25);
    Fit { mechs, nuis, ll }
}

/// Nelder–Mead minimisation of `f` on the unit cube (points clamped), from `x0` with
/// initial step `step`, at most `max_evals` evaluations.
fn nelder_mead(f: &dyn Fn(&[f64]) -> f64, x0: &[f64], step: f64, max_evals: usize) -> Vec<f64> {
    let n = x0.len();
    let clamp = |x: Vec<f64>| -> Vec<f64> { x.into_iter().map(|v| v.clamp(0.0, 1.0)).collect() };
    let mut simplex: Vec<(f64, Vec<f64>)> = vec![(f(x0), x0.to_vec())];
    for k in 0..n {
        let mut x = x0.to_vec();
        x[k] = if x[k] + step <= 1.0 { x[k] + step } else { x[k] - step };
        let x = clamp(x);
        simplex.push((f(&x), x));
    }
    let mut evals = n + 1;
    while evals < max_evals {
        simplex.sort_by(|a, b| a.0.total_cmp(&b.0));
        let spread = simplex[n].0 - simplex[0].0;
        if spread.abs() < 1e-7 * (1.0 + simplex[0].0.abs()) {
            break;
        }
        let centroid: Vec<f64> = (0..n).map(|k| simplex[..n].iter().map(|s| s.1[k]).sum::<f64>() / n as f64).collect();
        let along = |t: f64| -> Vec<f64> { clamp((0..n).map(|k| centroid[k] + t * (simplex[n].1[k] - centroid[k])).collect()) };
        let xr = along(-1.0);
        let fr = f(&xr);
        evals += 1;
        if fr < simplex[0].0 {
            let xe = along(-2.0);
            let fe = f(&xe);
            evals += 1;
            simplex[n] = if fe < fr { (fe, xe) } else { (fr, xr) };
        } else if fr < simplex[n - 1].0 {
            simplex[n] = (fr, xr);
        } else {
            let xc = along(0.5);
            let fc = f(&xc);
            evals += 1;
            if fc < simplex[n].0 {
                simplex[n] = (fc, xc);
            } else {
                let best = simplex[0].1.clone();
                for s in simplex.iter_mut().skip(1) {
                    let x: Vec<f64> = (0..n).map(|k| best[k] + 0.5 * (s.1[k] - best[k])).collect();
                    *s = (f(&x), x);
                    evals += 1;
                }
            }
        }
    }
    simplex.sort_by(|a, b| a.0.total_cmp(&b.0));
    simplex.swap_remove(0).1
}

/// A state fitted in every fold (full data last) with its held-out ll per unit.
#[derive(Clone)]
struct CvFit {
    fits: Vec<Fit>,
    unit_ll: Vec<f64>,
}

fn heldout(d: &MechData, folds: &Folds, fits: Vec<Fit>) -> CvFit {
    let mut unit_ll = vec![0.0; folds.n_units];
    for f in 0..folds.k {
        let rows = &folds.test_all[f];
        let ex = d.expect_rows(&fits[f].mechs, rows);
        for (&i, l) in rows.iter().zip(row_ll(d, rows, &ex, fits[f].nuis)) {
            unit_ll[folds.row_unit[i]] += l;
        }
    }
    CvFit { fits, unit_ll }
}

fn fold_gains(folds: &Folds, a: &CvFit, b: &CvFit) -> Vec<f64> {
    let mut g = vec![0.0; folds.k];
    for u in 0..folds.n_units {
        if folds.unit_fold[u] < folds.k {
            g[folds.unit_fold[u]] += a.unit_ll[u] - b.unit_ll[u];
        }
    }
    g
}

fn flipped(g: &[f64], m: u64) -> f64 {
    g.iter().enumerate().map(|(f, &x)| if (m >> f) & 1 == 1 { -x } else { x }).sum()
}

fn flip_p(g: &[f64], obs: f64, patterns: &[u64]) -> f64 {
    let tol = 1e-9 * obs.abs().max(1e-12);
    patterns.iter().filter(|&&m| flipped(g, m) >= obs - tol).count() as f64 / patterns.len() as f64
}

/// Paired sign-flip p that per-fold gains `a` exceed `b` (1 when they do not on the whole).
fn paired_p(a: &[f64], b: &[f64], patterns: &[u64]) -> f64 {
    let dlt: Vec<f64> = a.iter().zip(b).map(|(x, y)| x - y).collect();
    let obs: f64 = dlt.iter().sum();
    if !(obs > 0.0) {
        return 1.0;
    }
    flip_p(&dlt, obs, patterns)
}

/// The sentence of an accepted mechanism (`also`: its close runner-up is accepted too).
fn statement(s: &MechFinding, also: bool) -> String {
    let what = format!("{} ({})", s.mechanism, fmt_params(&s.parameters, Some(&s.standard_errors)));
    let r = s.runner_up.as_deref().unwrap_or("?");
    let (m, mp) = (s.margin_nats.unwrap_or(0.0), s.margin_p.unwrap_or(1.0));
    if s.ambiguous {
        format!(
            "ambiguous between {} and {r}: {} leads by only {m:.1} held-out nats (paired p = {mp:.3}); fitted {what}",
            s.mechanism, s.mechanism
        )
    } else {
        let vs = match (&s.runner_up, also) {
            (Some(_), true) => format!("; runner-up {r} ({m:.1} nats behind, paired p = {mp:.3}) is selected too: both present"),
            (Some(_), false) => format!("; runner-up {r}, {m:.1} nats behind (paired p = {mp:.3})"),
            (None, _) => String::new(),
        };
        format!("{what}: held-out gain {:.1} nats over the model before it (p = {:.3}){vs}", s.heldout_gain_total, s.p_value)
    }
}

/// Jackknife standard errors of mechanism `kind`'s free parameters over the fold fits.
fn jackknife(fold_fits: &[Fit], kind: &str) -> BTreeMap<String, f64> {
    let k = fold_fits.len() as f64;
    let per: Vec<BTreeMap<String, f64>> = fold_fits.iter().filter_map(|f| f.mechs.iter().find(|m| m.name() == kind).map(named)).collect();
    let mut se = BTreeMap::new();
    if let Some(first) = per.first() {
        for name in first.keys() {
            let xs: Vec<f64> = per.iter().map(|p| p[name]).collect();
            let mean = xs.iter().sum::<f64>() / k;
            se.insert(name.clone(), ((k - 1.0) / k * xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>()).sqrt());
        }
    }
    se
}

fn named(m: &Mechanism) -> BTreeMap<String, f64> {
    let free = free_params(m.name());
    let vals = m.values();
    free.iter().map(|&j| (m.prior()[j].name.to_string(), vals[j])).collect()
}

fn fmt_params(p: &BTreeMap<String, f64>, se: Option<&BTreeMap<String, f64>>) -> String {
    p.iter()
        .map(|(k, v)| match se.and_then(|s| s.get(k)) {
            Some(e) => format!("{k} = {} ± {}", sig(*v), sig(*e)),
            None => format!("{k} = {}", sig(*v)),
        })
        .collect::<Vec<_>>()
        .join(", ")
}

fn sig(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        format!("{x}")
    } else {
        let d = (3 - x.abs().log10().floor() as i32).clamp(0, 10) as usize;
        format!("{x:.d$}")
    }
}

/// Mechanism inference on `ctx`'s table, whose rows lie in `frames` (module docs).
/// `findings`: the covariate search's selected terms and its final model's held-out
/// log-likelihood per unit (same folds), to compare with and to explain.
pub fn infer(
    ctx: &Ctx,
    frames: &[SimFrame],
    search: &SearchOptions,
    opts: &MechanismOptions,
    findings: Option<(&[Term], &[f64])>,
) -> Result<MechanismReport> {
    let t = ctx.table;
    t.validate()?;
    for k in &opts.kinds {
        if Mechanism::neutral(k).is_none() {
            return Err(Error::config(
                "mechanism options",
                "kinds",
                format!("unknown mechanism {k:?}; expected one of {}", MECHANISM_NAMES.join(", ")),
            ));
        }
    }
    let d = MechData::new(ctx, frames)?;
    let folds = Folds::new(ctx, search.max_folds.clamp(2, 64), search.seed);
    if folds.k < 3 {
        return Err(Error::input(t.source.clone(), format!("{} split unit(s) (frames); the held-out test needs at least 3", folds.k)));
    }
    let patterns = sign_patterns(folds.k, search.seed);
    let null_fits: Vec<Fit> =
        (0..=folds.k).into_par_iter().map(|f| fit_fixed(&d, &folds.train_all[f], &[], start_nuis(&d, &folds.train_all[f]))).collect();
    let null = heldout(&d, &folds, null_fits);
    let mut current = null.clone();
    let mut rounds: Vec<MechRound> = vec![];
    let mut selected: Vec<MechFinding> = vec![];
    let valid_rows = t.len();
    while selected.len() < opts.max_mechanisms {
        let taken: Vec<&str> = current.fits[folds.k].mechs.iter().map(|m| m.name()).collect();
        let kinds: Vec<Mechanism> =
            opts.kinds.iter().filter(|k| !taken.contains(&k.as_str())).filter_map(|k| Mechanism::neutral(k)).collect();
        if kinds.is_empty() {
            break;
        }
        // Full-data fit of every kind: the screen.
        let full: Vec<Fit> = kinds.par_iter().map(|m| fit_candidate(&d, &folds.train_all[folds.k], &current.fits[folds.k], m)).collect();
        let mut cands: Vec<(Candidate, Option<CvFit>)> = kinds
            .iter()
            .zip(&full)
            .map(|(m, fit)| {
                let gain = fit.ll - current.fits[folds.k].ll;
                let df = free_params(m.name()).len() as f64;
                let pass = gain > 0.0 && crate::stats::chi2_upper_tail(2.0 * gain, df) < opts.screen_alpha;
                let c = Candidate {
                    mechanism: m.name().into(),
                    parameters: named(fit.mechs.last().expect("candidate")),
                    fulldata_gain: gain,
                    fitted: pass,
                    heldout_gain_total: 0.0,
                    heldout_gain_per_row: 0.0,
                    folds_improved: String::new(),
                    t: f64::NAN,
                    p_value: 1.0,
                    p_value_raw: 1.0,
                    gains: vec![],
                };
                (c, None)
            })
            .collect();
        let mut by_gain: Vec<usize> = (0..cands.len()).filter(|&c| cands[c].0.fitted).collect();
        by_gain.sort_by(|&a, &b| cands[b].0.fulldata_gain.total_cmp(&cands[a].0.fulldata_gain).then(a.cmp(&b)));
        for &c in by_gain.iter().skip(opts.max_fitted.max(2)) {
            cands[c].0.fitted = false;
        }
        let jobs: Vec<(usize, usize)> =
            (0..cands.len()).filter(|&c| cands[c].0.fitted).flat_map(|c| (0..folds.k).map(move |f| (c, f))).collect();
        let fold_fits: Vec<Fit> =
            jobs.par_iter().map(|&(c, f)| fit_candidate(&d, &folds.train_all[f], &current.fits[f], &kinds[c])).collect();
        let mut per_cand: BTreeMap<usize, Vec<Fit>> = BTreeMap::new();
        for (&(c, _), fit) in jobs.iter().zip(fold_fits) {
            per_cand.entry(c).or_default().push(fit);
        }
        for (c, mut fits) in per_cand {
            fits.push(full[c].clone());
            let cv = heldout(&d, &folds, fits);
            let g = fold_gains(&folds, &cv, &current);
            let cand = &mut cands[c].0;
            cand.heldout_gain_total = g.iter().sum();
            cand.heldout_gain_per_row = cand.heldout_gain_total / valid_rows.max(1) as f64;
            cand.folds_improved = format!("{}/{}", g.iter().filter(|&&x| x > 0.0).count(), g.len());
            cand.t = crate::stats::one_sided_t(&g).0;
            cand.gains = g;
            cands[c].1 = Some(cv);
        }
        // Family-wise p: max-T and raw max over the fitted candidates, Bonferroni over the two.
        let fitted: Vec<usize> = (0..cands.len()).filter(|&c| cands[c].1.is_some()).collect();
        if !fitted.is_empty() {
            let gq: Vec<(Vec<f64>, f64)> =
                fitted.iter().map(|&c| (cands[c].0.gains.clone(), cands[c].0.gains.iter().map(|x| x * x).sum())).collect();
            let maxes: Vec<(f64, f64)> = patterns
                .par_iter()
                .map(|&m| {
                    gq.iter().fold((f64::NEG_INFINITY, f64::NEG_INFINITY), |(mt, ms), (g, q)| {
                        (mt.max(flipped_t(g, *q, m)), ms.max(flipped(g, m)))
                    })
                })
                .collect();
            for (&c, (g, q)) in fitted.iter().zip(&gq) {
                let obs = cands[c].0.heldout_gain_total;
                let t_obs = flipped_t(g, *q, 0);
                let (tt, st) = (1e-9 * t_obs.abs().max(1e-12), 1e-9 * obs.abs().max(1e-12));
                let share = |f: &dyn Fn(&(f64, f64)) -> bool| maxes.iter().filter(|x| f(x)).count() as f64 / patterns.len() as f64;
                let pa = share(&|x| x.0 >= t_obs - tt).min(share(&|x| x.1 >= obs - st));
                cands[c].0.p_value_raw = flip_p(g, obs, &patterns);
                cands[c].0.p_value = if obs > 0.0 { (2.0 * pa).min(1.0) } else { 1.0 };
            }
        }
        let mut order: Vec<usize> = (0..cands.len()).collect();
        order.sort_by(|&a, &b| {
            let key = |c: usize| if cands[c].0.fitted { cands[c].0.heldout_gain_total } else { f64::NEG_INFINITY };
            key(b).total_cmp(&key(a)).then(cands[b].0.fulldata_gain.total_cmp(&cands[a].0.fulldata_gain)).then(a.cmp(&b))
        });
        let winner = order.iter().copied().find(|&c| cands[c].1.is_some() && cands[c].0.p_value < opts.alpha);
        let round_cands: Vec<Candidate> = order.iter().map(|&c| cands[c].0.clone()).collect();
        let Some(w) = winner else {
            rounds.push(MechRound { candidates: round_cands, selected: None });
            break;
        };
        let runner = order.iter().copied().find(|&c| c != w && cands[c].1.is_some());
        let cv_w = cands[w].1.clone().expect("winner is fitted");
        let fits_w = &cv_w.fits;
        let params_full = named(fits_w[folds.k].mechs.last().expect("winner"));
        let se = jackknife(&fits_w[..folds.k], &cands[w].0.mechanism);
        let (cw, name_w) = (&cands[w].0, cands[w].0.mechanism.clone());
        let (runner_up, rg, margin, margin_p) = match runner {
            Some(r) => {
                let cr = &cands[r].0;
                let mp = paired_p(&cw.gains, &cr.gains, &patterns);
                (Some(cr.mechanism.clone()), Some(cr.heldout_gain_total), Some(cw.heldout_gain_total - cr.heldout_gain_total), Some(mp))
            }
            None => (None, None, None, None),
        };
        let ambiguous = margin_p.is_some_and(|p| p >= opts.ambiguity_alpha);
        selected.push(MechFinding {
            mechanism: name_w.clone(),
            parameters: params_full,
            standard_errors: se,
            p_value: cw.p_value,
            heldout_gain_total: cw.heldout_gain_total,
            folds_improved: cw.folds_improved.clone(),
            runner_up,
            runner_up_gain_total: rg,
            margin_nats: margin,
            margin_p,
            ambiguous,
            statement: String::new(),
        });
        rounds.push(MechRound { candidates: round_cands, selected: Some(name_w) });
        current = cv_w;
        let n_acc = current.fits[folds.k].mechs.len();
        if n_acc > 1 {
            // Backfitting: each earlier mechanism refitted with the others fixed, in every
            // fold, so a parameter fitted before a later mechanism was known settles.
            let refit: Vec<Fit> = (0..=folds.k)
                .into_par_iter()
                .map(|f| {
                    let mut fit = current.fits[f].clone();
                    for j in 0..n_acc - 1 {
                        let mut others = fit.mechs.clone();
                        let cand = others.remove(j);
                        let base = Fit { mechs: others, nuis: fit.nuis, ll: fit.ll };
                        let mut nf = fit_candidate(&d, &folds.train_all[f], &base, &cand);
                        let m = nf.mechs.pop().expect("refitted");
                        nf.mechs.insert(j, m);
                        if nf.ll >= fit.ll {
                            fit = nf;
                        }
                    }
                    fit
                })
                .collect();
            current = heldout(&d, &folds, refit);
        }
    }
    // Parameters and standard errors of the final (backfitted) model. A winner whose
    // close runner-up is selected in a later round is not ambiguous: both are present.
    let names: Vec<String> = selected.iter().map(|s| s.mechanism.clone()).collect();
    for s in selected.iter_mut() {
        if let Some(full) = current.fits[folds.k].mechs.iter().find(|m| m.name() == s.mechanism).map(named) {
            s.standard_errors = jackknife(&current.fits[..folds.k], &s.mechanism);
            s.parameters = full;
        }
        let also = s.ambiguous && s.runner_up.as_ref().is_some_and(|r| names.contains(r));
        if also {
            s.ambiguous = false;
        }
        s.statement = statement(s, also);
    }
    let fitted = current.fits[folds.k].mechs.clone();
    let verdict = if selected.is_empty() {
        "no mechanism beats the audited model on held-out frames".to_string()
    } else {
        selected.iter().map(|s| s.statement.clone()).collect::<Vec<_>>().join("; then ")
    };
    let predictive_check = crate::predictive::check(
        t,
        &row_models(&d, &current.fits[folds.k]),
        &row_models(&d, &null.fits[folds.k]),
        0.5 / ctx.outlier_density,
        search.seed ^ 0x00C0_FFEE,
    );
    let mut depth_correction = DepthCorrection::from_fitted(&fitted, &t.source);
    for s in selected.iter().filter(|s| s.ambiguous) {
        depth_correction.notes.push(format!(
            "the audit found {} ambiguous with {}: the correction applies {} as fitted",
            s.mechanism,
            s.runner_up.as_deref().unwrap_or("?"),
            s.mechanism
        ));
    }
    let mut report = MechanismReport {
        method: "each mechanism fitted by maximum likelihood (outlier component kept) on the frame images of each fold's training frames; held-out log-likelihood gain per fold, sign-flip randomisation with a max-statistic correction per round; winner vs runner-up by a paired sign-flip test; jackknife standard errors over the folds".into(),
        alpha: opts.alpha,
        ambiguity_alpha: opts.ambiguity_alpha,
        folds: folds.k,
        null_heldout_loglik: null.unit_ll.iter().sum(),
        selected,
        fitted,
        verdict,
        versus_findings: None,
        findings_explained: vec![],
        predictive_check,
        depth_correction,
        rounds,
    };
    if let Some((terms, cov_unit_ll)) = findings {
        if cov_unit_ll.len() == folds.n_units {
            let cov = CvFit { fits: vec![], unit_ll: cov_unit_ll.to_vec() };
            let gm = fold_gains(&folds, &current, &null);
            let gc = fold_gains(&folds, &cov, &null);
            report.versus_findings = Some(Versus {
                mechanisms_minus_findings: gm.iter().sum::<f64>() - gc.iter().sum::<f64>(),
                p_mechanisms_better: paired_p(&gm, &gc, &patterns),
                p_findings_better: paired_p(&gc, &gm, &patterns),
            });
        }
        let before: Vec<f64> = terms.iter().map(|&term| crate::search::term_score_p(ctx, term)).collect();
        // Each mechanism alone, then all together: a finding is explained by the first
        // mechanism that alone makes it vanish, else by the set.
        let mut after: Vec<Vec<(String, f64)>> = vec![vec![]; terms.len()];
        let mechs = &report.fitted;
        let mut sets: Vec<(String, Vec<Mechanism>)> = mechs.iter().map(|m| (m.name().to_string(), vec![m.clone()])).collect();
        if mechs.len() > 1 {
            sets.push((mechs.iter().map(|m| m.name()).collect::<Vec<_>>().join(" + "), mechs.clone()));
        }
        for (name, set) in &sets {
            let tab = d.corrected_table(t, set);
            let c2 = Ctx::new(&tab, ctx.robust);
            for (a, &term) in after.iter_mut().zip(terms) {
                a.push((name.clone(), crate::search::term_score_p(&c2, term)));
            }
        }
        report.findings_explained = terms
            .iter()
            .enumerate()
            .map(|(i, term)| {
                let name = t.columns[term.col].name.clone();
                Explained {
                    finding: i,
                    term: format!("{} ~ {}({name})", term.target.name(), term.form.name()),
                    p_before: before[i],
                    explained_by: after[i].iter().find(|(_, p)| *p > opts.screen_alpha).map(|(n, _)| n.clone()),
                    p_after: after[i].clone(),
                }
            })
            .collect();
    }
    Ok(report)
}

impl MechanismReport {
    /// Summary lines.
    pub fn summary(&self) -> String {
        let mut s = format!("mechanisms (held-out frames, {} folds, family-wise alpha {}):\n", self.folds, self.alpha);
        if self.selected.is_empty() {
            s += "  none beats the audited model on held-out frames\n";
        }
        for (i, m) in self.selected.iter().enumerate() {
            s += &format!("  {}. {}\n", i + 1, m.statement);
        }
        if let Some(v) = &self.versus_findings {
            s += &format!(
                "  against the covariate findings: {:+.1} held-out nats (p mechanisms better {:.3}, p findings better {:.3})\n",
                v.mechanisms_minus_findings, v.p_mechanisms_better, v.p_findings_better
            );
        }
        s += &format!("  posterior predictive check {}\n", self.predictive_check.verdict);
        s += &format!("  depth correction: {}\n", self.depth_correction.describe());
        for e in &self.findings_explained {
            s += &format!(
                "  finding {} ({}): {}\n",
                e.finding + 1,
                e.term,
                match &e.explained_by {
                    Some(m) => format!("explained by {m}"),
                    None => "not explained by the fitted mechanisms".into(),
                }
            );
        }
        s
    }
}
