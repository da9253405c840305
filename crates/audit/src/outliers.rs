//! The outlier component audited: is what the robust fit calls "outliers" structured?
//!
//! The fit's uniform outlier component explains gross errors without a cause, so a large
//! fraction can hide a systematic effect (a bias confined to a subset of pixels looks like
//! outliers; the search's `FormKind::Subset` candidates turn such outliers back into a
//! term). What remains is tested here, at the final model, for dependence on every numeric
//! covariate: per unit (frame), the contrast between its rows above and below the column's
//! median of (`rate`) the outlier weight `1 − inlier responsibility` and (`sign`) the signed
//! outlier weight. With no dependence each unit's contrast is symmetric about 0, so the
//! signs of whole units are flipped, as in the search; the family-wise p-value is the
//! share of sign patterns whose largest |t| over all columns × {rate, sign} reaches the
//! contrast's own (Westfall–Young max-T). The median split is fixed before the outliers are
//! looked at, so no threshold is selected on the tested data. Columns constant within
//! every unit (frame) have no within-unit contrast and are not tested.
use crate::fit::{Ctx, Model};
use crate::search::{flipped_t, sign_patterns};
use crate::table::ColumnKind;
use serde::Serialize;

/// Rows a unit needs on each side of the median for its contrast to count.
const MIN_SIDE: usize = 5;
/// Expected outliers (Σ outlier weights) below which nothing is tested.
const MIN_OUTLIERS: f64 = 20.0;

/// One tested dependence of the outliers on a covariate.
#[derive(Serialize, Clone, Debug)]
pub struct Dependence {
    pub covariate: String,
    /// `rate` (outlier weight) or `sign` (signed outlier weight).
    pub kind: String,
    /// The covariate's median: the split.
    pub split: f64,
    /// Outlier share below / above the split (posterior weights, all units).
    pub rate_below: f64,
    pub rate_above: f64,
    /// Mean residual from the model's mean over the outliers (weight > ½) below / above.
    pub outlier_residual_below: Option<f64>,
    pub outlier_residual_above: Option<f64>,
    /// t of the per-unit contrasts (descriptive) and its family-wise p-value.
    pub t: f64,
    pub p_value: f64,
}

/// The outlier component of the baseline and final models.
#[derive(Serialize, Clone, Debug)]
pub struct OutlierAudit {
    pub fraction_baseline: f64,
    pub fraction_final: f64,
    /// What the audited model states (the sensor model has no outlier component).
    pub stated: f64,
    /// `fraction_final` above `flag_level`: an unexplained finding, not a nuisance.
    pub flagged: bool,
    pub flag_level: f64,
    pub tested: usize,
    /// Every tested dependence, strongest (largest |t|) first.
    pub dependence: Vec<Dependence>,
}

impl OutlierAudit {
    /// Dependences significant at `alpha` (family-wise).
    pub fn significant(&self, alpha: f64) -> impl Iterator<Item = &Dependence> {
        self.dependence.iter().filter(move |d| d.p_value < alpha)
    }
}

/// Audits the outlier component of `last` (the final model) on the valid rows;
/// `first` is the baseline (its fraction is reported).
pub fn audit(ctx: &Ctx, first: &Model, last: &Model, flag_level: f64, seed: u64) -> OutlierAudit {
    let t = ctx.table;
    let nu = t.n_units();
    let valid: Vec<usize> = (0..t.len()).filter(|&i| !t.missing(i)).collect();
    let w: Vec<f64> = (0..t.len()).map(|i| if t.missing(i) { 0.0 } else { last.outlier_weight(ctx, i) }).collect();
    let d: Vec<f64> = (0..t.len()).map(|i| if t.missing(i) { 0.0 } else { ctx.resid[i] - last.predict(ctx, i).mu }).collect();
    let mut stats: Vec<(Dependence, Vec<f64>)> = vec![];
    // A handful of outliers has no structure to test (and contrasts of near-zero weights
    // would be numerical dust).
    let expected: f64 = valid.iter().map(|&i| w[i]).sum();
    for col in &t.columns {
        if col.kind != ColumnKind::Numeric || expected < MIN_OUTLIERS {
            continue;
        }
        let mut xs: Vec<f64> = valid.iter().map(|&i| col.values[i]).collect();
        xs.sort_by(|a, b| a.total_cmp(b));
        let split = crate::stats::quantile_sorted(&xs, 0.5);
        // Per unit and side: rows, Σ weight, Σ signed weight.
        let mut acc = vec![[[0.0f64; 3]; 2]; nu];
        let mut tot = [[0.0f64; 4]; 2]; // rows, Σ w, Σ d over outliers, outliers
        for &i in &valid {
            let s = usize::from(col.values[i] > split);
            let a = &mut acc[t.unit[i]][s];
            a[0] += 1.0;
            a[1] += w[i];
            a[2] += w[i] * d[i].signum();
            tot[s][0] += 1.0;
            tot[s][1] += w[i];
            if w[i] > 0.5 {
                tot[s][2] += d[i];
                tot[s][3] += 1.0;
            }
        }
        let contrast = |k: usize| -> Vec<f64> {
            acc.iter()
                .map(|a| if a[0][0] >= MIN_SIDE as f64 && a[1][0] >= MIN_SIDE as f64 { a[1][k] / a[1][0] - a[0][k] / a[0][0] } else { 0.0 })
                .collect()
        };
        let (rate, sign) = (contrast(1), contrast(2));
        if rate.iter().filter(|&&x| x != 0.0).count() < 3 {
            continue; // constant within units (frame) or too few units with both sides
        }
        let share = |s: usize| if tot[s][0] > 0.0 { tot[s][1] / tot[s][0] } else { 0.0 };
        let mean_d = |s: usize| (tot[s][3] > 0.0).then(|| tot[s][2] / tot[s][3]);
        for (kind, g) in [("rate", rate), ("sign", sign)] {
            let dep = Dependence {
                covariate: col.name.clone(),
                kind: kind.into(),
                split,
                rate_below: share(0),
                rate_above: share(1),
                outlier_residual_below: mean_d(0),
                outlier_residual_above: mean_d(1),
                t: 0.0,
                p_value: 1.0,
            };
            stats.push((dep, g));
        }
    }
    // Two-sided max-|t| over every contrast, units' signs flipped together.
    let units_with_rows = (0..nu).filter(|&u| stats.iter().any(|s| s.1[u] != 0.0)).count();
    let patterns = sign_patterns(nu, seed ^ 0x7E57_0071);
    let sq: Vec<f64> = stats.iter().map(|s| s.1.iter().map(|x| x * x).sum()).collect();
    let maxes: Vec<f64> =
        patterns.iter().map(|&m| stats.iter().zip(&sq).map(|(s, &q)| flipped_t(&s.1, q, m).abs()).fold(0.0, f64::max)).collect();
    for (s, &q) in stats.iter_mut().zip(&sq) {
        let obs = flipped_t(&s.1, q, 0);
        let tol = 1e-9 * obs.abs().max(1e-12);
        s.0.t = obs;
        s.0.p_value =
            if units_with_rows < 2 { 1.0 } else { maxes.iter().filter(|&&x| x >= obs.abs() - tol).count() as f64 / patterns.len() as f64 };
    }
    let tested = stats.len();
    let mut dependence: Vec<Dependence> = stats.into_iter().map(|s| s.0).collect();
    dependence.sort_by(|a, b| b.t.abs().total_cmp(&a.t.abs()));
    OutlierAudit {
        fraction_baseline: first.outlier,
        fraction_final: last.outlier,
        stated: 0.0,
        flagged: last.outlier > flag_level,
        flag_level,
        tested,
        dependence,
    }
}
