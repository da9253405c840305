//! The effect search: greedy forward selection of covariate terms, judged on held-out
//! units (frames).
//!
//! **Protocol.** Units are split into folds (leave-one-unit-out up to `max_folds`
//! units, else `max_folds` folds of shuffled units). Every model is fitted on each
//! fold's training units and scored on its held-out units, so every unit gets a
//! cross-fitted held-out log-likelihood. A candidate term's held-out gain per fold is
//! its log-likelihood minus the current model's, in the candidate's channel (the
//! Gaussian part for bias/noise, the Bernoulli part for dropout); nats are comparable
//! across channels. A step's threshold and a group's categories are chosen inside each
//! training fold, so that choice is validated too.
//!
//! **Significance: a randomisation test with frames as the unit.** If no candidate
//! helps, a fold's gain is as likely to be negative as positive (overfitting even makes
//! it lean negative), so flipping the signs of whole folds' gains generates the null.
//! A candidate's p-value is the share of the 2^K sign patterns (all of them for K ≤ 16,
//! else 20 000 seeded draws) under which its flipped total reaches the observed total.
//! The multiple-comparison correction is a max statistic (Westfall–Young): the
//! family-wise p-value is the share of patterns under which the largest flipped fold-t
//! (studentised, max-T) of *any* fitted candidate of the round reaches the candidate's
//! own; the same with flipped totals (raw max) is computed too, and the reported p is
//! twice the smaller of the two (Bonferroni over the two statistics). Pixels never count as independent
//! evidence, so correlation within a frame (a pose error, warm-up) cannot manufacture
//! significance; the price is that K folds can give at best p = 2^-K (K ≥ 7 for 0.01).
//! A cheap pixel-level score test at the full-data fit (loose, `screen_alpha`) skips the
//! fits of candidates with no sign of an effect; their small held-out gains would not
//! raise the null maximum noticeably.
//!
//! **Few units.** A term on a column that is constant within each frame (the frame
//! index) can only be extrapolated to a held-out frame, and a per-object group is seen in
//! few frames, so with ~12 frames neither reaches significance. Those candidates are
//! judged on finer units instead: (frame, object) pairs in `max_folds` folds of them
//! shuffled ([`Folds::fine`]), with the current model cross-fitted in those folds too.
//! They form a second family with its own randomisation test (sign flips of its folds'
//! gains, the same max statistics); with both families present every family-wise p is
//! doubled (Bonferroni over the two), so a round's family-wise error stays at `alpha`.
//! The price: pixels of one object in one frame are exchangeable with other objects'
//! only if nothing ties the objects of a frame together beyond the tested term.
//! A group has a parameter per object, each seen in few frames, so its fit is guarded
//! where a held-out unit would otherwise pay for one fold's noise: a noise group is
//! referenced to its quietest well-observed object and started at robust (median-based)
//! per-object excess noise, and a dropout group's rates carry a weak prior toward the
//! overall rate ([`crate::fit`]). Both are fixed from the training rows of each
//! fold, like a step's threshold, so the randomisation test and its family-wise level
//! are unchanged.
//!
//! **Outliers.** The robust fit's outlier component gives gross residuals no weight, so
//! a bias confined to a subset of pixels (a step of 5–15 σ on a few % of them) is
//! invisible to the score screen and to a fit started at zero. Each numeric column also
//! gets a `Subset` candidate: a bias step at the threshold where the parent's signed
//! outlier weights concentrate, started at those outliers' level ([`seed_subset`]);
//! it is accepted, like any other term, by its held-out gain under the same test.
//!
//! **Selection.** Among candidates with family-wise p < `alpha` the largest total
//! held-out gain wins; a more complex form (quadratic, step) replaces a significant
//! linear term of the same target and covariate only if it beats it on held-out folds
//! (paired randomisation test at `parsimony_alpha`). The winner joins the model (all
//! parameters refitted) and the search repeats until nothing is significant or
//! `max_findings` is reached. Then one interaction round tries each finding multiplied
//! by another numeric covariate.
//!
//! **Uncertainty.** Parameter standard errors come from a bootstrap over units
//! ([`bootstrap`]): frames resampled with replacement, the final model refitted on each
//! resample (thresholds re-chosen), so within-frame correlation is accounted for.
use crate::fit::{
    fit_bern, fit_gauss, is_gauss, score_stat, seed_noise_group, seed_subset, structure, subset_split, working, Ctx, FormKind, Model, Pred,
    Term,
};
use crate::stats::{chi2_upper_tail, one_sided_t};
use crate::table::ColumnKind;
use rayon::prelude::*;
use recon_core::rng::SeededRng;
use recon_core::sensor::Target;
use recon_core::{Error, Result};
use std::collections::BTreeMap;

#[derive(Clone, Debug)]
/// Settings of the effect search (levels, limits, robustness).
pub struct SearchOptions {
    /// Family-wise level of each selection round (randomisation max statistic).
    pub alpha: f64,
    /// Pixel-level score pre-screen: candidates with p_score above this are not fitted.
    pub screen_alpha: f64,
    /// A more complex form must beat the linear one at this level (paired, held out).
    pub parsimony_alpha: f64,
    /// Stop after this many accepted terms.
    pub max_findings: usize,
    /// Outlier-robust Gaussian part (uniform contamination component).
    pub robust: bool,
    /// Try one interaction (a finding × another covariate) at the end.
    pub interactions: bool,
    /// Leave-one-unit-out up to this many units; K-fold beyond.
    pub max_folds: usize,
    /// Fold assignment when K-fold.
    pub seed: u64,
    /// Targets searched (default all three).
    pub targets: Vec<Target>,
    /// Bootstrap resamples (over units) for the standard errors.
    pub bootstrap: usize,
    /// A final outlier fraction above this is reported as a finding to explain
    /// (the sensor model states none).
    pub outlier_flag: f64,
}

impl Default for SearchOptions {
    fn default() -> Self {
        SearchOptions {
            alpha: 0.01,
            screen_alpha: 0.01,
            parsimony_alpha: 0.01,
            max_findings: 8,
            robust: true,
            interactions: true,
            max_folds: 20,
            seed: 0,
            targets: vec![Target::Bias, Target::Noise, Target::Dropout],
            bootstrap: 100,
            outlier_flag: 0.01,
        }
    }
}

impl SearchOptions {
    /// Checks the options a user sets (`recon audit`'s flags, `recon_rgbd.audit_depth`'s
    /// keywords); the error names the option.
    pub fn validate(&self) -> std::result::Result<(), recon_core::engine::OptionError> {
        use recon_core::engine::OptionError;
        if !(self.alpha > 0.0 && self.alpha < 1.0) {
            return Err(OptionError::new("alpha", "in (0, 1)", self.alpha));
        }
        if !(3..=64).contains(&self.max_folds) {
            return Err(OptionError::new("max_folds", "in 3..=64", self.max_folds));
        }
        Ok(())
    }
}

/// Row sets per fold; index `k` (= number of folds) is the full data.
pub struct Folds {
    pub k: usize,
    /// Held-out unit of each row (the table's unit, or a finer one, see [`Folds::fine`]).
    pub row_unit: Vec<usize>,
    pub n_units: usize,
    pub unit_fold: Vec<usize>,
    pub train_valid: Vec<Vec<usize>>,
    pub train_all: Vec<Vec<usize>>,
    pub test_valid: Vec<Vec<usize>>,
    pub test_all: Vec<Vec<usize>>,
}

impl Folds {
    /// Folds of the table's units (frames).
    pub fn new(ctx: &Ctx, max_folds: usize, seed: u64) -> Self {
        Self::of_units(ctx, ctx.table.unit.clone(), ctx.table.n_units(), max_folds, seed)
    }

    /// Folds of finer units: (frame, object) pairs when the table has an `object`
    /// column, which let a covariate that is constant within a frame (the frame index,
    /// a per-frame exposure) or a per-object group be estimated for a held-out unit from
    /// the rest of its frame or the object's other frames. None without such a column.
    pub fn fine(ctx: &Ctx, max_folds: usize, seed: u64) -> Option<Self> {
        let t = ctx.table;
        let oc = t.columns.iter().position(|c| c.kind == ColumnKind::Categorical && c.name == "object")?;
        let mut ids: BTreeMap<(usize, i64), usize> = BTreeMap::new();
        for i in 0..t.len() {
            let key = (t.unit[i], t.columns[oc].values[i].round() as i64);
            let n = ids.len();
            ids.entry(key).or_insert(n);
        }
        let row_unit: Vec<usize> = (0..t.len()).map(|i| ids[&(t.unit[i], t.columns[oc].values[i].round() as i64)]).collect();
        let n = ids.len();
        // Seeded differently from the frame folds: K-fold over shuffled fine units.
        Some(Self::of_units(ctx, row_unit, n, max_folds.min(n.saturating_sub(1)).max(2), seed ^ 0xF1_4E))
    }

    fn of_units(ctx: &Ctx, row_unit: Vec<usize>, nu: usize, max_folds: usize, seed: u64) -> Self {
        let t = ctx.table;
        let mut present = vec![false; nu];
        for &u in &row_unit {
            present[u] = true;
        }
        let units: Vec<usize> = (0..nu).filter(|&u| present[u]).collect();
        let mut unit_fold = vec![usize::MAX; nu];
        let k = if units.len() <= max_folds {
            for (f, &u) in units.iter().enumerate() {
                unit_fold[u] = f;
            }
            units.len()
        } else {
            // Seeded Fisher–Yates shuffle, then round-robin.
            let mut order = units.clone();
            let mut rng = SeededRng::new(seed);
            for i in (1..order.len()).rev() {
                let j = (rng.next_u64() % (i as u64 + 1)) as usize;
                order.swap(i, j);
            }
            for (p, &u) in order.iter().enumerate() {
                unit_fold[u] = p % max_folds;
            }
            max_folds
        };
        let mut f = Folds {
            k,
            row_unit,
            n_units: nu,
            unit_fold,
            train_valid: vec![vec![]; k + 1],
            train_all: vec![vec![]; k + 1],
            test_valid: vec![vec![]; k],
            test_all: vec![vec![]; k],
        };
        for i in 0..t.len() {
            let fold = f.unit_fold[f.row_unit[i]];
            let valid = !t.missing(i);
            for g in 0..=k {
                if g == fold {
                    f.test_all[g].push(i);
                    if valid {
                        f.test_valid[g].push(i);
                    }
                } else {
                    f.train_all[g].push(i);
                    if valid {
                        f.train_valid[g].push(i);
                    }
                }
            }
        }
        f
    }
}

/// A model fitted in every fold (and on the full data, last) with its cross-fitted
/// held-out log-likelihood per unit and channel.
#[derive(Clone)]
pub struct Cv {
    pub models: Vec<Model>,
    pub unit_ll_gauss: Vec<f64>,
    pub unit_ll_bern: Vec<f64>,
}

impl Cv {
    pub fn full(&self) -> &Model {
        self.models.last().expect("full-data model")
    }

    fn baseline(ctx: &Ctx, folds: &Folds) -> Self {
        let nu = folds.n_units;
        let mut cv = Cv { models: vec![], unit_ll_gauss: vec![0.0; nu], unit_ll_bern: vec![0.0; nu] };
        for f in 0..=folds.k {
            let mut m = Model::initial(ctx, &folds.train_valid[f], &folds.train_all[f]);
            fit_gauss(ctx, &folds.train_valid[f], &mut m);
            fit_bern(ctx, &folds.train_all[f], &mut m);
            if f < folds.k {
                for (&i, l) in folds.test_valid[f].iter().zip(m.ll_gauss_rows(ctx, &folds.test_valid[f])) {
                    cv.unit_ll_gauss[folds.row_unit[i]] += l;
                }
                for &i in &folds.test_all[f] {
                    cv.unit_ll_bern[folds.row_unit[i]] += m.ll_bern(ctx, i);
                }
            }
            cv.models.push(m);
        }
        cv
    }

    /// The parent plus `term`, refitted in the term's channel in every fold. None when a
    /// fold's training rows cannot carry the term.
    fn with(&self, ctx: &Ctx, folds: &Folds, term: Term) -> Option<Cv> {
        let gauss = is_gauss(term.target);
        let nu = folds.n_units;
        let mut models = Vec::with_capacity(folds.k + 1);
        let mut ll = vec![0.0; nu];
        for f in 0..=folds.k {
            let rows = if gauss { &folds.train_valid[f] } else { &folds.train_all[f] };
            let mut m = self.models[f].clone();
            let ft = structure(ctx, &m, term, rows)?;
            m.terms.push(ft.clone());
            let seeded = match (term.form, term.target) {
                (FormKind::Subset, _) => {
                    seed_subset(ctx, &mut m, rows);
                    true
                }
                (FormKind::Group, Target::Noise) => {
                    seed_noise_group(ctx, &mut m, rows);
                    true
                }
                _ => false,
            };
            if gauss {
                let ll = fit_gauss(ctx, rows, &mut m);
                // A seeded start can end in a mode worse than the parent's (a subset that
                // holds no outliers' level): then the fit starts from zero, as a nested fit would.
                if seeded && ll < self.models[f].ll_gauss_rows(ctx, rows).iter().sum::<f64>() {
                    m = self.models[f].clone();
                    m.terms.push(ft);
                    if term.form != FormKind::Subset {
                        fit_gauss(ctx, rows, &mut m);
                    }
                }
            } else {
                fit_bern(ctx, rows, &mut m);
            }
            if f < folds.k {
                if gauss {
                    for (&i, l) in folds.test_valid[f].iter().zip(m.ll_gauss_rows(ctx, &folds.test_valid[f])) {
                        ll[folds.row_unit[i]] += l;
                    }
                } else {
                    for &i in &folds.test_all[f] {
                        ll[folds.row_unit[i]] += m.ll_bern(ctx, i);
                    }
                }
            }
            models.push(m);
        }
        let (g, b) = if gauss { (ll, self.unit_ll_bern.clone()) } else { (self.unit_ll_gauss.clone(), ll) };
        Some(Cv { models, unit_ll_gauss: g, unit_ll_bern: b })
    }

    fn unit_ll(&self, gauss: bool) -> &[f64] {
        if gauss {
            &self.unit_ll_gauss
        } else {
            &self.unit_ll_bern
        }
    }

    /// Held-out predictions of every row (from the fold that held it out).
    pub fn heldout_predictions(&self, ctx: &Ctx, folds: &Folds) -> Vec<Pred> {
        let mut out = vec![Pred::default(); ctx.table.len()];
        for f in 0..folds.k {
            for &i in &folds.test_all[f] {
                out[i] = self.models[f].predict(ctx, i);
            }
        }
        out
    }
}

/// Held-out evidence for one candidate in one round.
#[derive(Clone, Debug)]
pub struct Evidence {
    pub term: Term,
    /// Pixel-level score-test p-value at the full-data fit (the pre-screen).
    pub p_screen: f64,
    /// Held-out gains per fold (nats; = per unit when leave-one-unit-out); empty when not fitted.
    pub gains: Vec<f64>,
    /// t statistic of the fold gains (descriptive).
    pub t: f64,
    /// Randomisation p-value of this candidate alone (sign flips of fold gains).
    pub p: f64,
    /// Family-wise p-value over the round's fitted candidates (max statistic).
    pub p_adjusted: f64,
    /// Held-out gain per held-out row of the channel (nats).
    pub gain_per_row: f64,
    pub gain_total: f64,
    /// Held out by (frame, object) units ([`Folds::fine`]) instead of frames.
    pub fine: bool,
}

/// One accepted term.
#[derive(Clone, Debug)]
pub struct Selected {
    /// Its held-out evidence in the round that accepted it.
    pub evidence: Evidence,
    /// Family-wise p-value (max-statistic randomisation test over the round's candidates).
    pub p_adjusted: f64,
    /// Candidates in the round (m).
    pub candidates: usize,
    /// Candidates fitted after the screen.
    pub fitted: usize,
    /// Selection round that accepted it (0-based).
    pub round: usize,
}

#[derive(Clone, Debug)]
/// What one selection round tried and what it accepted.
pub struct Round {
    /// Candidates in the round.
    pub candidates: usize,
    /// Candidates fitted after the score screen.
    pub fitted: usize,
    /// Fitted candidates, best held-out gain first (at most 12 kept).
    pub top: Vec<Evidence>,
    /// The accepted term, if any was significant.
    pub selected: Option<Term>,
}

/// Outcome of the search: the folds, the models before and after, and every round.
pub struct SearchResult {
    /// Row sets of the cross-fitting folds (by unit).
    pub folds: Folds,
    /// The starting model (no added terms), cross-fitted.
    pub baseline: Cv,
    /// The final model (all selected terms), cross-fitted.
    pub final_cv: Cv,
    /// Accepted terms, in order of acceptance.
    pub selected: Vec<Selected>,
    /// Every round, in order.
    pub rounds: Vec<Round>,
}

/// Candidate terms for the table's columns: numeric columns × {linear, quadratic, step},
/// categorical × {group}, for each target, and (robust fits) a bias subset step per
/// numeric column; constant columns are skipped, and dropout when no row is missing.
pub fn candidates(ctx: &Ctx, targets: &[Target]) -> Vec<Term> {
    let t = ctx.table;
    let any_missing = (0..t.len()).any(|i| t.missing(i));
    let mut out = vec![];
    for &target in targets {
        if target == Target::Dropout && !any_missing {
            continue;
        }
        for (c, col) in t.columns.iter().enumerate() {
            let first = col.values[0];
            if col.values.iter().all(|&v| v == first) {
                continue;
            }
            let forms: &[FormKind] = match col.kind {
                ColumnKind::Categorical => &[FormKind::Group],
                ColumnKind::Numeric => &[FormKind::Linear, FormKind::Quadratic, FormKind::Step],
            };
            for &form in forms {
                out.push(Term { target, col: c, form, by: None });
            }
            if target == Target::Bias && ctx.robust && col.kind == ColumnKind::Numeric {
                out.push(Term { target, col: c, form: FormKind::Subset, by: None });
            }
        }
    }
    out
}

fn screen(ctx: &Ctx, full: &Model, folds: &Folds, term: Term) -> f64 {
    let rows = if is_gauss(term.target) { &folds.train_valid[folds.k] } else { &folds.train_all[folds.k] };
    if term.form == FormKind::Subset {
        // The score test cannot see rows the outlier component owns: screen on the
        // concentration of signed outliers instead (normal tail, Bonferroni over thresholds).
        return subset_split(ctx, full, term.col, rows).map_or(1.0, |s| (s.tried as f64 * chi2_upper_tail(s.z * s.z, 1.0)).min(1.0));
    }
    let Some(ft) = structure(ctx, full, term, rows) else { return 1.0 };
    let wk = working(ctx, full, term.target, rows);
    let k = ft.k();
    let mut z = vec![0.0; rows.len() * k];
    for (j, &i) in rows.iter().enumerate() {
        ft.features(ctx, i, &mut z[j * k..(j + 1) * k]);
    }
    chi2_upper_tail(score_stat(&wk, &z, k), k as f64)
}

/// Pixel-level score-test p of adding `term` to the baseline model (no terms) fitted on
/// every row: how strongly the residuals still show the term (used to tell whether a
/// finding disappears once a mechanism is fitted).
pub(crate) fn term_score_p(ctx: &Ctx, term: Term) -> f64 {
    let folds = Folds::new(ctx, 3, 0);
    let mut full = Model::initial(ctx, &folds.train_valid[folds.k], &folds.train_all[folds.k]);
    fit_gauss(ctx, &folds.train_valid[folds.k], &mut full);
    fit_bern(ctx, &folds.train_all[folds.k], &mut full);
    screen(ctx, &full, &folds, term)
}

fn evidence(ctx: &Ctx, folds: &Folds, parent: &Cv, term: Term, p_screen: f64, fit: bool) -> (Evidence, Option<Cv>) {
    let mut ev =
        Evidence { term, p_screen, gains: vec![], t: f64::NAN, p: 1.0, p_adjusted: 1.0, gain_per_row: 0.0, gain_total: 0.0, fine: false };
    if !fit {
        return (ev, None);
    }
    let Some(cv) = parent.with(ctx, folds, term) else { return (ev, None) };
    let gauss = is_gauss(term.target);
    let (a, b) = (cv.unit_ll(gauss), parent.unit_ll(gauss));
    // Gains per fold (= per unit when leave-one-unit-out): the exchangeable blocks.
    ev.gains = vec![0.0; folds.k];
    for u in 0..a.len() {
        if folds.unit_fold[u] < folds.k {
            ev.gains[folds.unit_fold[u]] += a[u] - b[u];
        }
    }
    let rows = (0..ctx.table.len()).filter(|&i| !gauss || !ctx.table.missing(i)).count();
    ev.t = one_sided_t(&ev.gains).0;
    ev.gain_total = ev.gains.iter().sum();
    ev.gain_per_row = ev.gain_total / rows.max(1) as f64;
    (ev, Some(cv))
}

/// Sign-flip patterns over `k` folds (bit f set: fold f's gain changes sign): all 2^k
/// for k ≤ 16, else 20 000 seeded random ones; the identity is always included.
pub fn sign_patterns(k: usize, seed: u64) -> Vec<u64> {
    if k <= 16 {
        return (0..(1u64 << k)).collect();
    }
    let mask = if k >= 64 { u64::MAX } else { (1u64 << k) - 1 };
    let mut rng = SeededRng::new(seed ^ 0x51_6E_F1_1B);
    std::iter::once(0).chain((1..20_000).map(|_| rng.next_u64() & mask)).collect()
}

fn flipped(g: &[f64], m: u64) -> f64 {
    g.iter().enumerate().map(|(f, &x)| if (m >> f) & 1 == 1 { -x } else { x }).sum()
}

/// One-sample t of the flipped gains (`sumsq`: their sum of squares, unchanged by flips).
pub(crate) fn flipped_t(g: &[f64], sumsq: f64, m: u64) -> f64 {
    let k = g.len() as f64;
    let mean = flipped(g, m) / k;
    if g.len() < 2 {
        return mean;
    }
    let var = (sumsq - k * mean * mean) / (k - 1.0);
    if var <= 1e-12 * sumsq.max(1e-300) {
        return if mean > 0.0 {
            f64::INFINITY
        } else if mean < 0.0 {
            f64::NEG_INFINITY
        } else {
            0.0
        };
    }
    mean / (var / k).sqrt()
}

/// Share of sign patterns whose flipped total reaches `obs` (ties count).
fn flip_p(g: &[f64], obs: f64, patterns: &[u64]) -> f64 {
    let tol = 1e-9 * obs.abs().max(1e-12);
    patterns.iter().filter(|&&m| flipped(g, m) >= obs - tol).count() as f64 / patterns.len() as f64
}

/// Paired randomisation test that `a`'s per-fold gains exceed `b`'s.
fn beats(a: &Evidence, b: &Evidence, patterns: &[u64]) -> f64 {
    if a.gains.len() != b.gains.len() || a.gains.is_empty() {
        return 1.0;
    }
    let d: Vec<f64> = a.gains.iter().zip(&b.gains).map(|(x, y)| x - y).collect();
    let obs: f64 = d.iter().sum();
    if obs <= 0.0 {
        return 1.0;
    }
    flip_p(&d, obs, patterns)
}

/// Fills `p` (one candidate's own randomisation p-value) and `p_adjusted` (family-wise:
/// the share of sign patterns under which the largest flipped fold-t of *any* fitted
/// candidate reaches this candidate's own t; Westfall–Young max-T).
fn randomisation_test(results: &mut [(Evidence, Option<Cv>)], patterns: &[u64]) {
    let fitted: Vec<usize> = (0..results.len()).filter(|&i| results[i].1.is_some()).collect();
    if fitted.is_empty() {
        return;
    }
    // Studentised (max-T): on raw totals a candidate whose gains swing widely between
    // folds (a per-object offset fitted to one frame) would dominate the null maximum
    // and mask a consistent effect. Under sign flips t is monotone in the total, so a
    // candidate's own p-value is the same on either scale.
    let gains: Vec<(Vec<f64>, f64)> = fitted
        .iter()
        .map(|&i| {
            let g = results[i].0.gains.clone();
            let q = g.iter().map(|x| x * x).sum::<f64>();
            (g, q)
        })
        .collect();
    // Also max of the raw totals: a candidate whose gains are all positive but of very
    // unequal size (a bias on a subset that some held-out frames show much more of) has a
    // modest t, yet no other candidate's flipped total comes near its own. The two max
    // statistics are combined by Bonferroni (p = 2·min), so the family-wise level holds.
    let maxes: Vec<(f64, f64)> = patterns
        .par_iter()
        .map(|&m| {
            gains
                .iter()
                .fold((f64::NEG_INFINITY, f64::NEG_INFINITY), |(mt, ms), (g, q)| (mt.max(flipped_t(g, *q, m)), ms.max(flipped(g, m))))
        })
        .collect();
    for (&i, (g, q)) in fitted.iter().zip(&gains) {
        let obs = results[i].0.gain_total;
        let p = flip_p(&results[i].0.gains, obs, patterns);
        let t_obs = flipped_t(g, *q, 0);
        let t_tol = 1e-9 * t_obs.abs().max(1e-12);
        let s_tol = 1e-9 * obs.abs().max(1e-12);
        let share = |f: &dyn Fn(&(f64, f64)) -> bool| maxes.iter().filter(|x| f(x)).count() as f64 / patterns.len() as f64;
        let pa_t = share(&|x| x.0 >= t_obs - t_tol);
        let pa_s = share(&|x| x.1 >= obs - s_tol);
        results[i].0.p = p;
        results[i].0.p_adjusted = (2.0 * pa_t.min(pa_s)).min(1.0);
    }
}

/// One held-out scheme: folds and the current model cross-fitted in them.
type Scheme<'a> = (&'a Folds, &'a Cv);

/// Whether a term is judged on the fine (frame, object) units: groups, and terms on a
/// column (or interaction) that is constant within every frame, which frame hold-out can
/// only extrapolate to.
fn needs_fine(ctx: &Ctx, frame_constant: &[bool], t: &Term) -> bool {
    ctx.is_categorical(t.col) || frame_constant[t.col] || t.by.is_some_and(|b| frame_constant[b])
}

/// Columns whose value is the same on every row of each table unit.
fn frame_constant(ctx: &Ctx) -> Vec<bool> {
    let t = ctx.table;
    t.columns
        .iter()
        .map(|c| {
            let mut first: Vec<Option<f64>> = vec![None; t.n_units()];
            (0..t.len()).all(|i| *first[t.unit[i]].get_or_insert(c.values[i]) == c.values[i])
        })
        .collect()
}

/// One selection round. Candidates are judged in their scheme (frames, or the fine units
/// when `fine` is given and [`needs_fine`]); each scheme's candidates form a family with
/// its own randomisation test, and with two families every family-wise p is doubled
/// (Bonferroni), so the round's family-wise level stays `alpha`. Returns the selection,
/// its cross-fitted model and whether that model is of the fine scheme.
fn run_round(
    ctx: &Ctx,
    main: Scheme,
    fine: Option<Scheme>,
    frame_const: &[bool],
    cands: &[Term],
    opts: &SearchOptions,
    round: usize,
) -> (Round, Option<(Selected, Cv, bool)>) {
    let scheme = |t: &Term| -> (Scheme, bool) {
        match fine {
            Some(f) if needs_fine(ctx, frame_const, t) => (f, true),
            _ => (main, false),
        }
    };
    let screened: Vec<(Term, f64)> = cands
        .par_iter()
        .map(|&t| {
            let ((folds, parent), _) = scheme(&t);
            (t, screen(ctx, parent.full(), folds, t))
        })
        .collect();
    let results: Vec<(Evidence, Option<Cv>)> = screened
        .par_iter()
        .map(|&(t, ps)| {
            let ((folds, parent), f) = scheme(&t);
            let (mut e, cv) = evidence(ctx, folds, parent, t, ps, ps < opts.screen_alpha);
            e.fine = f;
            (e, cv)
        })
        .collect();
    let (mut coarse, mut fined): (Vec<_>, Vec<_>) = results.into_iter().partition(|r| !r.0.fine);
    let patterns = sign_patterns(main.0.k, opts.seed);
    let fine_patterns = fine.map(|f| sign_patterns(f.0.k, opts.seed)).unwrap_or_default();
    randomisation_test(&mut coarse, &patterns);
    randomisation_test(&mut fined, &fine_patterns);
    if !coarse.is_empty() && !fined.is_empty() {
        for r in coarse.iter_mut().chain(fined.iter_mut()) {
            r.0.p_adjusted = (2.0 * r.0.p_adjusted).min(1.0);
        }
    }
    let mut results = coarse;
    results.extend(fined);
    let m = cands.len();
    let fitted = results.iter().filter(|r| r.1.is_some()).count();
    let significant = |e: &Evidence| e.p_adjusted < opts.alpha && e.gain_total > 0.0;
    let mut best: Option<usize> = None;
    for (i, (e, cv)) in results.iter().enumerate() {
        if cv.is_some() && significant(e) && best.is_none_or(|b| e.gain_total > results[b].0.gain_total) {
            best = Some(i);
        }
    }
    // Parsimony: prefer the linear form of the same target and covariate unless the
    // chosen form beats it on held-out folds.
    if let Some(b) = best {
        let e = &results[b].0;
        if e.term.form != FormKind::Linear {
            let lin = results.iter().position(|(x, cv)| cv.is_some() && x.term == Term { form: FormKind::Linear, ..e.term });
            if let Some(l) = lin {
                let pats = if e.fine { &fine_patterns } else { &patterns };
                if significant(&results[l].0) && beats(e, &results[l].0, pats) >= opts.parsimony_alpha {
                    best = Some(l);
                }
            }
        }
    }
    let mut top: Vec<Evidence> = results.iter().filter(|r| r.1.is_some()).map(|r| r.0.clone()).collect();
    top.sort_by(|a, b| b.gain_total.total_cmp(&a.gain_total));
    top.truncate(12);
    let mut rd = Round { candidates: m, fitted, top, selected: None };
    let sel = best.map(|b| {
        let (e, cv) = results.into_iter().nth(b).expect("index in range");
        rd.selected = Some(e.term);
        let f = e.fine;
        (Selected { p_adjusted: e.p_adjusted, evidence: e, candidates: m, fitted, round }, cv.expect("fitted"), f)
    });
    (rd, sel)
}

/// Runs the search on the context's table.
pub fn search(ctx: &Ctx, opts: &SearchOptions) -> Result<SearchResult> {
    let t = ctx.table;
    t.validate()?;
    let folds = Folds::new(ctx, opts.max_folds.clamp(2, 64), opts.seed);
    if folds.k < 3 {
        return Err(Error::input(t.source.clone(), format!("{} split unit(s) (frames); the held-out test needs at least 3", folds.k)));
    }
    if (0..t.len()).all(|i| t.missing(i)) {
        return Err(Error::input(t.source.clone(), "every measurement is missing"));
    }
    let baseline = Cv::baseline(ctx, &folds);
    let mut current = baseline.clone();
    let frame_const = frame_constant(ctx);
    let fine_folds = Folds::fine(ctx, opts.max_folds.clamp(2, 64), opts.seed).filter(|f| f.k >= 3);
    let mut fine_cv = fine_folds.as_ref().map(|f| Cv::baseline(ctx, f));
    // Adds a selected term to both schemes' current models; false when the frame scheme
    // cannot carry it (then the search stops: every finding must be in the final model).
    let accept = |current: &mut Cv, fine_cv: &mut Option<Cv>, cv: Cv, is_fine: bool, term: Term| -> bool {
        if is_fine {
            match current.with(ctx, &folds, term) {
                Some(c) => *current = c,
                None => return false,
            }
            *fine_cv = Some(cv);
        } else {
            *fine_cv = fine_cv.as_ref().zip(fine_folds.as_ref()).and_then(|(c, f)| c.with(ctx, f, term));
            *current = cv;
        }
        true
    };
    let all = candidates(ctx, &opts.targets);
    let mut selected: Vec<Selected> = vec![];
    let mut rounds = vec![];
    while selected.len() < opts.max_findings {
        let taken: Vec<(Target, usize)> = selected.iter().map(|s| (s.evidence.term.target, s.evidence.term.col)).collect();
        let cands: Vec<Term> = all.iter().copied().filter(|c| !taken.contains(&(c.target, c.col))).collect();
        if cands.is_empty() {
            break;
        }
        let fine = fine_folds.as_ref().zip(fine_cv.as_ref());
        let (rd, sel) = run_round(ctx, (&folds, &current), fine, &frame_const, &cands, opts, rounds.len());
        rounds.push(rd);
        match sel {
            Some((s, cv, is_fine)) => {
                if !accept(&mut current, &mut fine_cv, cv, is_fine, s.evidence.term) {
                    break;
                }
                selected.push(s);
            }
            None => break,
        }
    }
    if opts.interactions && !selected.is_empty() && selected.len() < opts.max_findings {
        let mut cands = vec![];
        for s in selected.iter().filter(|s| s.evidence.term.form != FormKind::Subset) {
            let base = s.evidence.term;
            for (c, col) in t.columns.iter().enumerate() {
                let first = col.values[0];
                if c != base.col && col.kind == ColumnKind::Numeric && col.values.iter().any(|&v| v != first) {
                    cands.push(Term { by: Some(c), ..base });
                }
            }
        }
        if !cands.is_empty() {
            let fine = fine_folds.as_ref().zip(fine_cv.as_ref());
            let (rd, sel) = run_round(ctx, (&folds, &current), fine, &frame_const, &cands, opts, rounds.len());
            rounds.push(rd);
            if let Some((s, cv, is_fine)) = sel {
                if accept(&mut current, &mut fine_cv, cv, is_fine, s.evidence.term) {
                    selected.push(s);
                }
            }
        }
    }
    Ok(SearchResult { folds, baseline, final_cv: current, selected, rounds })
}

/// The global parameters of a model, in sensor-model units.
pub fn globals(ctx: &Ctx, m: &Model) -> BTreeMap<String, f64> {
    let mut g = BTreeMap::new();
    g.insert("bias".to_string(), m.bias);
    g.insert("noise".to_string(), m.noise(ctx));
    g.insert("dropout".to_string(), m.dropout);
    g.insert("outlier_fraction".to_string(), m.outlier);
    g
}

/// Standard errors of a model's parameters from a bootstrap over units (frames).
#[derive(Clone, Debug, Default)]
pub struct Uncertainty {
    /// Bootstrap resamples drawn.
    pub resamples: usize,
    /// Standard error of each global parameter, by name.
    pub globals: BTreeMap<String, f64>,
    /// Per term, by parameter name (`form_params` names).
    pub terms: Vec<BTreeMap<String, f64>>,
}

/// Resamples units with replacement `b` times and refits `full` (all terms; steps
/// re-choose their thresholds, as the search did) on each resample; the standard error
/// of a parameter is its standard deviation over the resamples. Units, not pixels, are
/// resampled, so correlation within a frame is accounted for. A group value counts only
/// in resamples that contain its category.
pub fn bootstrap(ctx: &Ctx, full: &Model, b: usize, seed: u64) -> Uncertainty {
    let t = ctx.table;
    let nu = t.n_units();
    let mut valid_of = vec![vec![]; nu];
    let mut all_of = vec![vec![]; nu];
    for i in 0..t.len() {
        all_of[t.unit[i]].push(i);
        if !t.missing(i) {
            valid_of[t.unit[i]].push(i);
        }
    }
    let units: Vec<usize> = (0..nu).filter(|&u| !all_of[u].is_empty()).collect();
    let samples: Vec<(BTreeMap<String, f64>, Vec<BTreeMap<String, f64>>)> = (0..b)
        .into_par_iter()
        .map(|k| {
            let mut rng = SeededRng::new(seed ^ (k as u64 + 1).wrapping_mul(0xD1B5_4A32_D192_ED03));
            let (mut valid, mut all) = (vec![], vec![]);
            for _ in 0..units.len() {
                let u = units[(rng.next_u64() % units.len() as u64) as usize];
                valid.extend_from_slice(&valid_of[u]);
                all.extend_from_slice(&all_of[u]);
            }
            let mut m = full.clone();
            for j in 0..m.terms.len() {
                let term = m.terms[j].term;
                if term.form == FormKind::Step {
                    let mut parent = m.clone();
                    parent.terms.remove(j);
                    let rows = if is_gauss(term.target) { &valid } else { &all };
                    if let Some((thr, _)) = crate::fit::best_step(ctx, &working(ctx, &parent, term.target, rows), term.col, term.by) {
                        m.terms[j].threshold = thr;
                    }
                } else if term.form == FormKind::Subset {
                    let mut parent = m.clone();
                    parent.terms.remove(j);
                    if let Some(s) = subset_split(ctx, &parent, term.col, &valid) {
                        m.terms[j].threshold = s.threshold;
                    }
                }
            }
            fit_gauss(ctx, &valid, &mut m);
            fit_bern(ctx, &all, &mut m);
            let terms = m
                .terms
                .iter()
                .map(|ft| {
                    let rows = if is_gauss(ft.term.target) { &valid } else { &all };
                    let mut p = ft.params(ctx);
                    if ft.term.form == FormKind::Group {
                        let present: std::collections::BTreeSet<i64> =
                            rows.iter().map(|&i| ctx.value(ft.term.col, i).round() as i64).collect();
                        p.retain(|k, _| {
                            k.strip_prefix("values.")
                                .and_then(|c| c.parse::<i64>().ok())
                                .is_none_or(|c| present.contains(&c) && present.contains(&ft.reference))
                        });
                    }
                    p
                })
                .collect();
            (globals(ctx, &m), terms)
        })
        .collect();
    let sd = |xs: Vec<f64>| -> f64 {
        if xs.len() < 2 {
            return f64::NAN;
        }
        let n = xs.len() as f64;
        let m = xs.iter().sum::<f64>() / n;
        (xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    };
    let globals_se =
        globals(ctx, full).keys().map(|k| (k.clone(), sd(samples.iter().filter_map(|s| s.0.get(k).copied()).collect()))).collect();
    let terms = full
        .terms
        .iter()
        .enumerate()
        .map(|(j, ft)| {
            ft.params(ctx).keys().map(|k| (k.clone(), sd(samples.iter().filter_map(|s| s.1[j].get(k).copied()).collect()))).collect()
        })
        .collect();
    Uncertainty { resamples: b, globals: globals_se, terms }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::depth::{residual_table, PixelSample};
    use recon_core::sensor::{Covariate, Effect, Form, PixelCovariates, SensorModel};

    /// Pseudo-rendered pixels: `per` per frame with plausible, partly correlated covariates,
    /// measured through `model`.
    pub(crate) fn pixels(model: &SensorModel, frames: usize, per: usize, seed: u64) -> Vec<PixelSample> {
        let mut rng = SeededRng::new(seed);
        let mut out = vec![];
        for f in 0..frames {
            let objs = [1 + f % 4, 1 + (f + 1) % 4, 1 + (f + 2) % 4];
            let zf = 0.5 + 0.8 * rng.uniform();
            for _ in 0..per {
                let u = 640.0 * rng.uniform();
                let v = 480.0 * rng.uniform();
                let c = PixelCovariates {
                    depth: zf + 0.6 * rng.uniform(),
                    radius: ((u - 320.0f64).powi(2) + (v - 240.0f64).powi(2)).sqrt() / 400.0,
                    incidence: 88.0 * rng.uniform().powf(0.7),
                    edge_distance: (-8.0 * rng.uniform().ln()).floor().min(60.0),
                    intensity: 0.05 + 0.9 * rng.uniform(),
                    object: objs[(rng.next_u64() % 3) as usize] as i64,
                    frame: f as i64,
                    u,
                    v,
                };
                let m = model.sample(&c, &mut rng);
                out.push(PixelSample { cov: c, measured: m });
            }
        }
        out
    }

    fn run(audited: &SensorModel, truth: &SensorModel, seed: u64) -> (SearchResult, crate::table::ResidualTable) {
        let px = pixels(truth, 10, 1200, seed);
        let t = residual_table(audited, &px, "synthetic");
        let ctx = Ctx::new(&t, true);
        let r = search(&ctx, &SearchOptions::default()).unwrap();
        drop(ctx);
        (r, t)
    }

    #[test]
    fn null_data_gives_no_finding() {
        let m = SensorModel::stereo_default();
        let (r, _) = run(&m, &m, 11);
        let names: Vec<_> = r.selected.iter().map(|s| s.evidence.term).collect();
        assert!(
            r.selected.is_empty(),
            "spurious findings {names:?}; rounds {:?}",
            r.rounds.iter().map(|x| x.top.first().map(|e| (e.term, e.p))).collect::<Vec<_>>()
        );
    }

    #[test]
    fn finds_planted_quadratic_depth_bias() {
        let audited = SensorModel::stereo_default();
        let mut truth = audited.clone();
        truth.effects.push(Effect {
            target: Target::Bias,
            covariate: Covariate::Depth,
            form: Form::Quadratic { linear: 0.0, quadratic: 0.004 },
            by: None,
            cause: None,
        });
        let (r, t) = run(&audited, &truth, 12);
        let ctx = Ctx::new(&t, true);
        assert!(!r.selected.is_empty());
        let s = &r.selected[0].evidence.term;
        assert_eq!(
            (s.target, t.columns[s.col].name.as_str(), s.form),
            (Target::Bias, "depth", FormKind::Quadratic),
            "{:?}",
            r.rounds[0].top
        );
        let f = r.final_cv.full().terms[0].form(&ctx);
        let full = r.final_cv.full();
        for z in [0.7, 1.0, 1.3, 1.6] {
            let got = full.bias + f.eval(z);
            let want = 0.004 * z * z;
            assert!((got - want).abs() < 0.0004, "z {z}: {got} vs {want} ({f:?}, bias {})", full.bias);
        }
    }

    #[test]
    fn randomisation_p_values_are_exact_on_small_cases() {
        let pats = sign_patterns(4, 0);
        assert_eq!(pats.len(), 16);
        // All positive, distinct magnitudes: only the identity reaches the total.
        assert_eq!(flip_p(&[1.0, 2.0, 3.0, 4.0], 10.0, &pats), 1.0 / 16.0);
        // A fold with zero gain ties under its flip.
        assert_eq!(flip_p(&[0.0, 2.0, 3.0, 4.0], 9.0, &pats), 2.0 / 16.0);
        // Totals ≥ 8: the identity (10) and the flip of the 1 (8).
        assert_eq!(flip_p(&[1.0, 2.0, 3.0, 4.0], 8.0, &pats), 2.0 / 16.0);
        let many = sign_patterns(20, 1);
        assert_eq!((many.len(), many[0]), (20_000, 0));
        assert!(many.iter().all(|&m| m < (1 << 20)));
    }

    #[test]
    fn table_audit_finds_a_categorical_offset_with_rows_as_units() {
        // Weighed vs annotated masses: metal parts weigh 50 g more than annotated.
        let dir = recon_testkit::tmp("audit-table");
        let mut rng = SeededRng::new(5);
        let mut csv = String::from("id,annotated_kg,weighed_kg,material,volume_l\n");
        for i in 0..400 {
            let m = 0.1 + 1.9 * rng.uniform();
            let mat = ["wood", "metal", "plastic"][(rng.next_u64() % 3) as usize];
            let w = m + if mat == "metal" { 0.05 } else { 0.0 } + 0.01 * rng.normal();
            let weighed = if rng.uniform() < 0.03 { String::new() } else { format!("{w:.5}") };
            csv += &format!("{i},{m:.5},{weighed},{mat},{:.3}\n", 2.0 * rng.uniform());
        }
        let p = dir.join("masses.csv");
        std::fs::write(&p, csv).unwrap();
        let (t, skipped) = crate::table::ResidualTable::from_csv(&p, "weighed_kg", "annotated_kg", None, &[], &["id".to_string()]).unwrap();
        assert_eq!((skipped, t.n_units()), (0, 400));
        let a = crate::audit_table(&t, &SearchOptions { bootstrap: 20, ..Default::default() }).unwrap();
        let r = &a.report;
        assert_eq!(r.findings.len(), 1, "{}", r.summary());
        let f = &r.findings[0];
        assert_eq!((f.target.as_str(), f.covariate.as_str(), f.form.as_str()), ("bias", "material", "group"));
        // The metal offset, whichever category is the reference: metal − others ≈ 0.05.
        let v = &f.parameters["values"];
        let val = |k: &str| v.get(k).and_then(|x| x.as_f64()).unwrap_or(0.0);
        let (metal, wood, plastic) = (val("metal"), val("wood"), val("plastic"));
        assert!((metal - wood - 0.05).abs() < 0.006 && (metal - plastic - 0.05).abs() < 0.006, "{v}");
        assert!(f.heldout_gain > 0.0 && f.p_value < 0.01);
        assert!(a.extended.is_none() && f.effect.is_none(), "plain tables have no sensor model");
        assert!(r.summary().contains("material"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
