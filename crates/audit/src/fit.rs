//! Maximum-likelihood fit of the audit's residual model.
//!
//! Per row with residual `r = measured − simulated` and covariates `x`:
//! ```text
//! r ~ (1−π)·N(μ(x), σ(x)²) + π·U(−W, W)          on rows with a measurement
//! missing ~ Bernoulli(p(x))                         on every row
//! μ(x) = bias + Σ bias terms
//! σ(x) = sqrt(floor² + noise²) + sd_offset + Σ noise terms      (floor, offsets: table columns)
//! p(x) = clamp(dropout + p_offset + Σ dropout terms, ε, 1−ε)
//! ```
//! which is the sensor model's parameterisation (`recon_core::sensor`), so fitted terms
//! become [`Effect`]s unchanged. The uniform outlier component (weight π, fitted; off
//! with `robust = false`) absorbs gross errors such as mixed pixels at depth edges
//! without letting them inflate σ; on clean Gaussian data π → 0 and σ is the plain sd.
//! The Gaussian and the Bernoulli parts have separate parameters, so they are fitted
//! (and candidate terms scored) independently. Fitting is Fisher scoring with
//! step halving, the outlier weight by EM; a term's threshold (`step`) or category set
//! (`group`) is fixed from the training rows before its coefficients are fitted. A noise
//! group's reference is its quietest category (the others' excess then adds to σ as in
//! the sensor model) and dropout group rates are shrunk toward the overall rate by a
//! prior of a few rows (a category with no missing training pixel stays off the clamp).
use crate::stats::solve_spd;
use crate::table::{ColumnKind, ResidualTable};
use recon_core::sensor::{Effect, Form, Target};
use std::collections::BTreeMap;

/// Probability clamp of the dropout channel.
pub const P_EPS: f64 = 1e-6;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum FormKind {
    Linear,
    Quadratic,
    Step,
    Group,
    /// A bias step whose subset is found among the parent model's outliers (where a
    /// plain step's score is blind: the outlier component gives those rows no weight).
    /// The same `Form::Step` in the sensor model.
    Subset,
}

impl FormKind {
    pub fn name(self) -> &'static str {
        match self {
            FormKind::Linear => "linear",
            FormKind::Quadratic => "quadratic",
            FormKind::Step | FormKind::Subset => "step",
            FormKind::Group => "group",
        }
    }
}

/// A candidate term: `target += form(column) [· by]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Term {
    pub target: Target,
    pub col: usize,
    pub form: FormKind,
    pub by: Option<usize>,
}

/// Channel a target's likelihood lives in.
pub fn is_gauss(t: Target) -> bool {
    matches!(t, Target::Bias | Target::Noise)
}

/// What the fit needs besides the table: per-column scales (conditioning only), the
/// residuals, the outlier density and the σ parameterisation.
pub struct Ctx<'a> {
    pub table: &'a ResidualTable,
    pub scale: Vec<f64>,
    pub resid: Vec<f64>,
    /// σ0 = sqrt(floor² + v) with v = noise² (some floor > 0), else σ0 = noise.
    pub quadrature: bool,
    pub sd_min: f64,
    /// Density of the uniform outlier component, 1/(2W).
    pub outlier_density: f64,
    pub robust: bool,
}

impl<'a> Ctx<'a> {
    pub fn new(table: &'a ResidualTable, robust: bool) -> Self {
        let n = table.len();
        let scale = table
            .columns
            .iter()
            .map(|c| {
                let ms = c.values.iter().map(|v| v * v).sum::<f64>() / n.max(1) as f64;
                if ms > 0.0 && ms.is_finite() {
                    ms.sqrt()
                } else {
                    1.0
                }
            })
            .collect();
        let resid: Vec<f64> = (0..n).map(|i| table.residual(i)).collect();
        let valid: Vec<f64> = resid.iter().copied().filter(|r| r.is_finite()).collect();
        let rsd = crate::stats::robust_sd(&valid);
        let maxdev = valid.iter().fold(0.0f64, |m, r| m.max(r.abs()));
        let floor_scale = table.sd_floor.iter().cloned().fold(0.0, f64::max);
        let scale_r = if rsd > 0.0 { rsd } else { floor_scale.max(maxdev).max(1e-300) };
        // Outliers spread over ±W: at least 20 robust sd, so they never compete with the
        // Gaussian's tails on clean data.
        let w = maxdev.max(20.0 * scale_r).max(1e-300);
        Ctx {
            table,
            scale,
            resid,
            quadrature: table.sd_floor.iter().any(|&f| f > 0.0),
            sd_min: (1e-4 * scale_r).max(1e-12),
            outlier_density: 1.0 / (2.0 * w),
            robust,
        }
    }

    /// Lowest σ of row i: the table's clamp (quantisation) or the numerical floor.
    pub fn sd_lowest(&self, i: usize) -> f64 {
        self.table.sd_clamp.get(i).copied().unwrap_or(0.0).max(self.sd_min)
    }

    pub fn value(&self, col: usize, i: usize) -> f64 {
        self.table.columns[col].values[i]
    }
    pub fn is_categorical(&self, col: usize) -> bool {
        self.table.columns[col].kind == ColumnKind::Categorical
    }
}

/// A term with its structure fixed (threshold, categories) and its coefficients,
/// which multiply features in scaled units (x / scale).
#[derive(Clone, Debug)]
pub struct FittedTerm {
    pub term: Term,
    pub threshold: f64,
    /// Group: the non-reference categories (reference = most frequent training category).
    pub cats: Vec<i64>,
    pub reference: i64,
    pub coef: Vec<f64>,
}

impl FittedTerm {
    pub fn k(&self) -> usize {
        match self.term.form {
            FormKind::Linear | FormKind::Step | FormKind::Subset => 1,
            FormKind::Quadratic => 2,
            FormKind::Group => self.cats.len(),
        }
    }

    /// Writes the k feature values of row i into `out`.
    pub fn features(&self, ctx: &Ctx, i: usize, out: &mut [f64]) {
        let x = ctx.value(self.term.col, i);
        let by = self.term.by.map(|b| ctx.value(b, i) / ctx.scale[b]).unwrap_or(1.0);
        match self.term.form {
            FormKind::Linear => out[0] = by * x / ctx.scale[self.term.col],
            FormKind::Quadratic => {
                let xs = x / ctx.scale[self.term.col];
                out[0] = by * xs;
                out[1] = by * xs * xs;
            }
            FormKind::Step | FormKind::Subset => out[0] = if x > self.threshold { by } else { 0.0 },
            FormKind::Group => {
                let c = x.round() as i64;
                for (o, &k) in out.iter_mut().zip(&self.cats) {
                    *o = if k == c { by } else { 0.0 };
                }
            }
        }
    }

    pub fn value(&self, ctx: &Ctx, i: usize) -> f64 {
        let x = ctx.value(self.term.col, i);
        let by = self.term.by.map(|b| ctx.value(b, i) / ctx.scale[b]).unwrap_or(1.0);
        let f = match self.term.form {
            FormKind::Linear => self.coef[0] * x / ctx.scale[self.term.col],
            FormKind::Quadratic => {
                let xs = x / ctx.scale[self.term.col];
                self.coef[0] * xs + self.coef[1] * xs * xs
            }
            FormKind::Step | FormKind::Subset => {
                if x > self.threshold {
                    self.coef[0]
                } else {
                    0.0
                }
            }
            FormKind::Group => {
                let c = x.round() as i64;
                self.cats.iter().position(|&k| k == c).map(|k| self.coef[k]).unwrap_or(0.0)
            }
        };
        by * f
    }

    /// The term in sensor-model units (`Form` of the raw covariate; `by` raw).
    pub fn form(&self, ctx: &Ctx) -> Form {
        let sb = self.term.by.map(|b| ctx.scale[b]).unwrap_or(1.0);
        let sx = ctx.scale[self.term.col];
        match self.term.form {
            FormKind::Linear => Form::Linear { slope: self.coef[0] / (sx * sb) },
            FormKind::Quadratic => Form::Quadratic { linear: self.coef[0] / (sx * sb), quadratic: self.coef[1] / (sx * sx * sb) },
            FormKind::Step | FormKind::Subset => Form::Step { threshold: self.threshold, delta: self.coef[0] / sb },
            FormKind::Group => Form::Group { values: self.cats.iter().zip(&self.coef).map(|(k, c)| (k.to_string(), c / sb)).collect() },
        }
    }

    /// Named parameters in model units (for reports and the bootstrap).
    pub fn params(&self, ctx: &Ctx) -> BTreeMap<String, f64> {
        form_params(&self.form(ctx))
    }
}

/// A `Form`'s parameters by name; group values as `values.<category>`.
pub fn form_params(f: &Form) -> BTreeMap<String, f64> {
    let mut m = BTreeMap::new();
    match f {
        Form::Linear { slope } => {
            m.insert("slope".into(), *slope);
        }
        Form::Quadratic { linear, quadratic } => {
            m.insert("linear".into(), *linear);
            m.insert("quadratic".into(), *quadratic);
        }
        Form::Step { threshold, delta } => {
            m.insert("threshold".into(), *threshold);
            m.insert("delta".into(), *delta);
        }
        Form::Group { values } => {
            for (k, v) in values {
                m.insert(format!("values.{k}"), *v);
            }
        }
    }
    m
}

/// A fitted residual model (see the module docs).
#[derive(Clone, Debug)]
pub struct Model {
    pub bias: f64,
    /// σ parameter: noise (direct) or noise² (quadrature).
    pub sd0: f64,
    pub outlier: f64,
    pub dropout: f64,
    pub terms: Vec<FittedTerm>,
}

/// Per-row prediction.
#[derive(Clone, Copy, Debug, Default)]
pub struct Pred {
    pub mu: f64,
    pub sigma: f64,
    pub p: f64,
}

impl Model {
    /// Starting values from robust statistics of the rows.
    pub fn initial(ctx: &Ctx, valid: &[usize], all: &[usize]) -> Self {
        let r: Vec<f64> = valid.iter().map(|&i| ctx.resid[i]).collect();
        let bias = if r.is_empty() { 0.0 } else { crate::stats::median(&r) };
        let sd = crate::stats::robust_sd(&r).max(ctx.sd_min);
        let sd0 = if ctx.quadrature {
            let mf2 = valid.iter().map(|&i| ctx.table.sd_floor[i].powi(2)).sum::<f64>() / valid.len().max(1) as f64;
            (sd * sd - mf2).max(0.0)
        } else {
            sd
        };
        let miss = all.iter().filter(|&&i| ctx.table.missing(i)).count() as f64 / all.len().max(1) as f64;
        let off = all.iter().map(|&i| ctx.table.p_offset[i]).sum::<f64>() / all.len().max(1) as f64;
        Model { bias, sd0, outlier: if ctx.robust { 0.01 } else { 0.0 }, dropout: (miss - off).clamp(0.0, 1.0 - P_EPS), terms: vec![] }
    }

    /// The global noise sd (sensor-model `noise_m`).
    pub fn noise(&self, ctx: &Ctx) -> f64 {
        if ctx.quadrature {
            self.sd0.max(0.0).sqrt()
        } else {
            self.sd0
        }
    }

    fn sum(&self, ctx: &Ctx, t: Target, i: usize) -> f64 {
        self.terms.iter().filter(|f| f.term.target == t).map(|f| f.value(ctx, i)).sum()
    }

    pub fn predict(&self, ctx: &Ctx, i: usize) -> Pred {
        let mu = self.bias + self.sum(ctx, Target::Bias, i);
        let (s0, _) = sd0(ctx, self.sd0, i);
        let sigma = (s0 + ctx.table.sd_offset[i] + self.sum(ctx, Target::Noise, i)).max(ctx.sd_lowest(i));
        let p = (self.dropout + ctx.table.p_offset[i] + self.sum(ctx, Target::Dropout, i)).clamp(P_EPS, 1.0 - P_EPS);
        Pred { mu, sigma, p }
    }

    /// Gaussian-part log-likelihoods of rows (0 for missing rows).
    pub fn ll_gauss_rows(&self, ctx: &Ctx, rows: &[usize]) -> Vec<f64> {
        let mix = Mix::new(ctx, self.outlier);
        rows.iter()
            .map(|&i| {
                if ctx.table.missing(i) {
                    return 0.0;
                }
                let p = self.predict(ctx, i);
                mix.ll(ctx.resid[i], p.mu, p.sigma).0
            })
            .collect()
    }

    /// Posterior weight of the outlier component for valid row i (0 when not robust).
    pub fn outlier_weight(&self, ctx: &Ctx, i: usize) -> f64 {
        let p = self.predict(ctx, i);
        1.0 - Mix::new(ctx, self.outlier).ll(ctx.resid[i], p.mu, p.sigma).1
    }

    pub fn ll_bern(&self, ctx: &Ctx, i: usize) -> f64 {
        let p = self.predict(ctx, i).p;
        if ctx.table.missing(i) {
            p.ln()
        } else {
            (1.0 - p).ln()
        }
    }

    pub fn terms_of(&self, target: Target) -> impl Iterator<Item = &FittedTerm> {
        self.terms.iter().filter(move |t| t.term.target == target)
    }
}

/// σ0 and dσ0/d(sd0) of row i.
fn sd0(ctx: &Ctx, p: f64, i: usize) -> (f64, f64) {
    if ctx.quadrature {
        let f = ctx.table.sd_floor[i];
        let s = (f * f + p.max(0.0)).sqrt();
        (s, 0.5 / s.max(ctx.sd_min))
    } else {
        (p, 1.0)
    }
}

/// The mixture's constants for one outlier weight: ln(1−π) and ln(π·u).
#[derive(Clone, Copy)]
struct Mix {
    robust: bool,
    ln_in: f64,
    ln_out: f64,
}

impl Mix {
    fn new(ctx: &Ctx, outlier: f64) -> Self {
        Mix { robust: ctx.robust, ln_in: (1.0 - outlier).ln(), ln_out: outlier.ln() + ctx.outlier_density.ln() }
    }

    /// (log-likelihood, inlier responsibility) of one residual.
    #[inline]
    fn ll(&self, r: f64, mu: f64, sigma: f64) -> (f64, f64) {
        const HALF_LN_2PI: f64 = 0.918_938_533_204_672_7;
        let z = (r - mu) / sigma;
        let lphi = -0.5 * z * z - sigma.ln() - HALF_LN_2PI;
        if !self.robust {
            return (lphi, 1.0);
        }
        let a = self.ln_in + lphi;
        let d = self.ln_out - a;
        // log(e^a + e^b) = a + log1p(e^(b−a)); skip the exp where it cannot matter.
        if d < -37.0 {
            (a, 1.0)
        } else if d > 37.0 {
            (self.ln_out, (-d).exp())
        } else {
            let e = d.exp();
            (a + e.ln_1p(), 1.0 / (1.0 + e))
        }
    }
}

/// Fisher-scoring working quantities of one channel at the current model: per row the
/// score `g` and information `w` with respect to the channel's linear predictor, and the
/// nuisance design (the derivative of the predictor with respect to each current
/// parameter of that channel).
pub struct Working {
    pub rows: Vec<usize>,
    pub g: Vec<f64>,
    pub w: Vec<f64>,
    pub x: Vec<f64>,
    pub kx: usize,
}

/// Builds the working quantities of `target`'s channel on `rows` (valid rows for the
/// Gaussian targets, all rows for dropout).
pub fn working(ctx: &Ctx, m: &Model, target: Target, rows: &[usize]) -> Working {
    let terms: Vec<&FittedTerm> = m.terms_of(target).collect();
    let kx = 1 + terms.iter().map(|t| t.k()).sum::<usize>();
    let n = rows.len();
    let mut out = Working { rows: rows.to_vec(), g: vec![0.0; n], w: vec![0.0; n], x: vec![0.0; n * kx], kx };
    let mix = Mix::new(ctx, m.outlier);
    for (j, &i) in rows.iter().enumerate() {
        let p = m.predict(ctx, i);
        let xr = &mut out.x[j * kx..(j + 1) * kx];
        let mut o = 1;
        for t in &terms {
            let k = t.k();
            t.features(ctx, i, &mut xr[o..o + k]);
            o += k;
        }
        match target {
            Target::Bias | Target::Noise => {
                let r = ctx.resid[i];
                let (_, resp) = mix.ll(r, p.mu, p.sigma);
                let z = (r - p.mu) / p.sigma;
                if target == Target::Bias {
                    xr[0] = 1.0;
                    out.g[j] = resp * z / p.sigma;
                    out.w[j] = resp / (p.sigma * p.sigma);
                } else {
                    xr[0] = sd0(ctx, m.sd0, i).1;
                    out.g[j] = resp * (z * z - 1.0) / p.sigma;
                    out.w[j] = 2.0 * resp / (p.sigma * p.sigma);
                }
            }
            Target::Dropout => {
                xr[0] = 1.0;
                let y = if ctx.table.missing(i) { 1.0 } else { 0.0 };
                let v = p.p * (1.0 - p.p);
                out.g[j] = (y - p.p) / v;
                out.w[j] = 1.0 / v;
            }
        }
    }
    out
}

/// Score statistic `Uᵀ I_adj⁻¹ U` of adding features `z` (row-major n×kz, rows as in
/// `wk`) to the channel, adjusted for the nuisance parameters.
pub fn score_stat(wk: &Working, z: &[f64], kz: usize) -> f64 {
    let (kx, n) = (wk.kx, wk.rows.len());
    let mut u = vec![0.0; kz];
    let mut izz = vec![0.0; kz * kz];
    let mut izx = vec![0.0; kz * kx];
    let mut ixx = vec![0.0; kx * kx];
    for j in 0..n {
        let (g, w) = (wk.g[j], wk.w[j]);
        let zr = &z[j * kz..(j + 1) * kz];
        let xr = &wk.x[j * kx..(j + 1) * kx];
        for a in 0..kz {
            u[a] += g * zr[a];
            if zr[a] == 0.0 {
                continue;
            }
            for b in 0..kz {
                izz[a * kz + b] += w * zr[a] * zr[b];
            }
            for b in 0..kx {
                izx[a * kx + b] += w * zr[a] * xr[b];
            }
        }
        for a in 0..kx {
            for b in 0..kx {
                ixx[a * kx + b] += w * xr[a] * xr[b];
            }
        }
    }
    adjusted_score(&u, &izz, &izx, &ixx, kz, kx)
}

fn adjusted_score(u: &[f64], izz: &[f64], izx: &[f64], ixx: &[f64], kz: usize, kx: usize) -> f64 {
    let mut adj = izz.to_vec();
    for a in 0..kz {
        let col: Vec<f64> = (0..kx).map(|b| izx[a * kx + b]).collect();
        if let Some(sol) = solve_spd(ixx, &col) {
            for c in 0..kz {
                adj[c * kz + a] -= (0..kx).map(|b| izx[c * kx + b] * sol[b]).sum::<f64>();
            }
        }
    }
    // Symmetrise against round-off.
    for a in 0..kz {
        for b in 0..a {
            let m = 0.5 * (adj[a * kz + b] + adj[b * kz + a]);
            adj[a * kz + b] = m;
            adj[b * kz + a] = m;
        }
    }
    if (0..kz).any(|a| !(adj[a * kz + a] > 1e-12 * izz[a * kz + a].abs().max(1e-300))) {
        return 0.0;
    }
    match solve_spd(&adj, u) {
        Some(s) => s.iter().zip(u).map(|(a, b)| a * b).sum::<f64>().max(0.0),
        None => 0.0,
    }
}

/// The step threshold with the largest score statistic on `wk`'s rows (ties: lowest);
/// thresholds keep at least max(30, n/200) rows on each side. Returns (threshold, score).
pub fn best_step(ctx: &Ctx, wk: &Working, col: usize, by: Option<usize>) -> Option<(f64, f64)> {
    let (kx, n) = (wk.kx, wk.rows.len());
    let min_side = (n / 200).max(30);
    if n < 2 * min_side {
        return None;
    }
    let mut order: Vec<usize> = (0..n).collect();
    let xv: Vec<f64> = wk.rows.iter().map(|&i| ctx.value(col, i)).collect();
    // Descending: prefix sums accumulate the rows above a threshold.
    order.sort_by(|&a, &b| xv[b].total_cmp(&xv[a]));
    let mut ixx = vec![0.0; kx * kx];
    for j in 0..n {
        let xr = &wk.x[j * kx..(j + 1) * kx];
        for a in 0..kx {
            for b in 0..kx {
                ixx[a * kx + b] += wk.w[j] * xr[a] * xr[b];
            }
        }
    }
    let (mut u, mut izz) = (0.0, 0.0);
    let mut izx = vec![0.0; kx];
    let mut best: Option<(f64, f64)> = None;
    for (cnt, &j) in order.iter().enumerate() {
        let zb = by.map(|b| ctx.value(b, wk.rows[j]) / ctx.scale[b]).unwrap_or(1.0);
        u += wk.g[j] * zb;
        izz += wk.w[j] * zb * zb;
        let xr = &wk.x[j * kx..(j + 1) * kx];
        for b in 0..kx {
            izx[b] += wk.w[j] * zb * xr[b];
        }
        let above = cnt + 1;
        if above < min_side || n - above < min_side {
            continue;
        }
        let next = xv[order[cnt + 1]];
        if next == xv[j] {
            continue; // a threshold must separate distinct values
        }
        let s = adjusted_score(&[u], &[izz], &izx, &ixx, 1, kx);
        if best.is_none_or(|(_, bs)| s >= bs) {
            best = Some((0.5 * (xv[j] + next), s));
        }
    }
    best
}

/// Where the parent model's outliers concentrate along one column: the threshold whose
/// two sides differ most in the mean signed outlier weight `(1 − inlier responsibility)
/// · sign(r − μ)`, the side that holds them and their level there.
#[derive(Clone, Copy, Debug)]
pub struct SubsetSplit {
    pub threshold: f64,
    /// The outliers sit above the threshold (else at or below it).
    pub above: bool,
    /// Median of `r − μ` over that side's outliers of the dominant sign.
    pub level: f64,
    /// Two-sample z of the mean signed outlier weight, above vs below.
    pub z: f64,
    /// Thresholds tried (for a Bonferroni screen).
    pub tried: usize,
}

/// [`SubsetSplit`] of `col` on `rows` (valid rows) at `parent`; None without outliers
/// or distinct values. Each side keeps at least max(30, n/200) rows, as for steps.
pub fn subset_split(ctx: &Ctx, parent: &Model, col: usize, rows: &[usize]) -> Option<SubsetSplit> {
    let n = rows.len();
    let min_side = (n / 200).max(30);
    if n < 2 * min_side || !ctx.robust {
        return None;
    }
    let mix = Mix::new(ctx, parent.outlier);
    // (x, signed outlier weight, r − μ, outlier weight)
    let mut v: Vec<(f64, f64, f64, f64)> = rows
        .iter()
        .map(|&i| {
            let p = parent.predict(ctx, i);
            let d = ctx.resid[i] - p.mu;
            let w = 1.0 - mix.ll(ctx.resid[i], p.mu, p.sigma).1;
            (ctx.value(col, i), w * d.signum(), d, w)
        })
        .collect();
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let total: f64 = v.iter().map(|e| e.1).sum();
    let mean = total / n as f64;
    let var = v.iter().map(|e| (e.1 - mean).powi(2)).sum::<f64>() / n as f64;
    if var.is_nan() || var <= 1e-12 {
        return None;
    }
    let (mut below, mut best, mut tried) = (0.0, None::<(f64, f64, usize)>, 0);
    for j in 0..n - 1 {
        below += v[j].1;
        let nb = j + 1;
        if nb < min_side || n - nb < min_side || v[j + 1].0 == v[j].0 {
            continue;
        }
        tried += 1;
        let na = n - nb;
        let z = ((total - below) / na as f64 - below / nb as f64) / (var * (1.0 / na as f64 + 1.0 / nb as f64)).sqrt();
        if best.is_none_or(|(_, bz, _)| z.abs() > bz.abs()) {
            best = Some((0.5 * (v[j].0 + v[j + 1].0), z, nb));
        }
    }
    let (threshold, z, nb) = best?;
    let side_mean = |s: &[(f64, f64, f64, f64)]| s.iter().map(|e| e.1).sum::<f64>() / s.len() as f64;
    let (lo, hi) = v.split_at(nb);
    let above = side_mean(hi).abs() > side_mean(lo).abs();
    let side = if above { hi } else { lo };
    let sign = side_mean(side).signum();
    let d: Vec<f64> = side.iter().filter(|e| e.3 > 0.5 && e.2.signum() == sign).map(|e| e.2).collect();
    if d.is_empty() {
        return None;
    }
    let level = crate::stats::median(&d);
    Some(SubsetSplit { threshold, above, level, z, tried })
}

/// Starts the last term of `m` (a fresh [`FormKind::Subset`]) at the level of its
/// subset's outliers, so that the fit begins in the mode where those rows are inliers
/// of a shifted mean; from zero the outlier component keeps them at zero weight.
pub fn seed_subset(ctx: &Ctx, m: &mut Model, rows: &[usize]) {
    let Some(last) = m.terms.len().checked_sub(1) else { return };
    if m.terms[last].term.form != FormKind::Subset || m.terms[last].term.by.is_some() {
        return;
    }
    let Some(s) = subset_split(ctx, m, m.terms[last].term.col, rows) else { return };
    m.terms[last].threshold = s.threshold;
    if s.above {
        m.terms[last].coef[0] = s.level;
    } else {
        // The subset lies below: it takes the intercept, the rest the step.
        m.bias += s.level;
        m.terms[last].coef[0] = -s.level;
    }
}

/// Rows a category needs for its robust excess noise ([`category_excess`]).
const MIN_CATEGORY: usize = 30;

/// Robust excess noise of each category of `col` (with ≥ [`MIN_CATEGORY`] rows) at
/// `parent`: the `v` for which the median of `|r − μ| / (σ + v)` over the category's rows
/// is the standard normal's (0.6745). A median, so outliers (up to half the rows) do not
/// move it, where a squared-residual estimate would be inflated by them.
pub fn category_excess(ctx: &Ctx, parent: &Model, col: usize, rows: &[usize]) -> BTreeMap<i64, f64> {
    let mut by_cat: BTreeMap<i64, Vec<(f64, f64)>> = BTreeMap::new();
    for &i in rows {
        let p = parent.predict(ctx, i);
        by_cat.entry(ctx.value(col, i).round() as i64).or_default().push(((ctx.resid[i] - p.mu).abs(), p.sigma));
    }
    const MEDIAN_ABS_Z: f64 = 0.674_489_750_196_081_7;
    let mut out = BTreeMap::new();
    let mut buf = vec![];
    for (k, v) in by_cat {
        if v.len() < MIN_CATEGORY {
            continue;
        }
        let smin = v.iter().map(|e| e.1).fold(f64::INFINITY, f64::min);
        let med = |x: f64, buf: &mut Vec<f64>| -> f64 {
            buf.clear();
            buf.extend(v.iter().map(|e| e.0 / (e.1 + x)));
            let m = buf.len() / 2;
            *buf.select_nth_unstable_by(m, f64::total_cmp).1
        };
        // Bisection on the decreasing median, σ + v kept above 10 % of the smallest σ.
        let (mut lo, mut hi) = (-0.9 * smin, 0.0f64);
        while med(hi, &mut buf) > MEDIAN_ABS_Z && hi < 1e6 * smin.max(1e-12) {
            hi = 2.0 * hi + smin;
        }
        if med(lo, &mut buf) <= MEDIAN_ABS_Z {
            out.insert(k, lo);
            continue;
        }
        for _ in 0..50 {
            let mid = 0.5 * (lo + hi);
            if med(mid, &mut buf) > MEDIAN_ABS_Z {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        out.insert(k, 0.5 * (lo + hi));
    }
    out
}

/// Starts the last term of `m` (a fresh noise group) at each category's robust excess
/// noise over the reference's ([`category_excess`]): from zero, the rows of a noisy
/// category start as outliers of the uniform component, which gives them no weight, and
/// the fit can stall with part of that category's noise left to the outliers.
pub fn seed_noise_group(ctx: &Ctx, m: &mut Model, rows: &[usize]) {
    let Some(last) = m.terms.len().checked_sub(1) else { return };
    let ft = &m.terms[last];
    if ft.term.form != FormKind::Group || ft.term.target != Target::Noise || ft.term.by.is_some() {
        return;
    }
    let ex = category_excess(ctx, m, ft.term.col, rows);
    let Some(&base) = ex.get(&ft.reference) else { return };
    let coef: Vec<f64> = ft.cats.iter().map(|k| ex.get(k).map_or(0.0, |v| v - base)).collect();
    m.terms[last].coef = coef;
}

/// Makes a term's structure from the training rows: the category set of a group, the
/// threshold of a step (largest score at the parent model). None when the column cannot
/// carry the term on these rows (one category, too few distinct values).
pub fn structure(ctx: &Ctx, parent: &Model, term: Term, rows: &[usize]) -> Option<FittedTerm> {
    let mut ft = FittedTerm { term, threshold: 0.0, cats: vec![], reference: 0, coef: vec![] };
    match term.form {
        FormKind::Group => {
            let mut counts: BTreeMap<i64, usize> = BTreeMap::new();
            for &i in rows {
                *counts.entry(ctx.value(term.col, i).round() as i64).or_default() += 1;
            }
            if counts.len() < 2 {
                return None;
            }
            let frequent = counts.iter().max_by(|a, b| a.1.cmp(b.1).then(b.0.cmp(a.0))).map(|(k, _)| *k)?;
            // Noise: the quietest well-observed category is the reference, so the others'
            // excess noise adds to σ (the sensor model's form) instead of a noisy reference
            // sitting in the global noise, where it adds in quadrature and misfits every
            // depth but one.
            let quiet = if term.target == Target::Noise && term.by.is_none() {
                let big = counts.values().max().copied().unwrap_or(0) / 4;
                category_excess(ctx, parent, term.col, rows)
                    .into_iter()
                    .filter(|(k, _)| counts.get(k).is_some_and(|&c| c >= big.max(MIN_CATEGORY)))
                    .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
                    .map(|(k, _)| k)
            } else {
                None
            };
            let reference = quiet.unwrap_or(frequent);
            ft.reference = reference;
            ft.cats = counts.keys().copied().filter(|&k| k != reference).collect();
        }
        FormKind::Step => {
            let wk = working(ctx, parent, term.target, rows);
            ft.threshold = best_step(ctx, &wk, term.col, term.by)?.0;
        }
        FormKind::Subset => ft.threshold = subset_split(ctx, parent, term.col, rows)?.threshold,
        _ => {
            let first = rows.first().map(|&i| ctx.value(term.col, i))?;
            if rows.iter().all(|&i| ctx.value(term.col, i) == first) {
                return None;
            }
        }
    }
    ft.coef = vec![0.0; ft.k()];
    Some(ft)
}

/// Convergence: stop when an iteration gains less than TOL_ABS + TOL_REL·|ll| nats
/// (far below the held-out gains that matter, ≳ 1 nat per frame).
const TOL_ABS: f64 = 1e-3;
const TOL_REL: f64 = 1e-9;
const MAX_ITER: usize = 200;

/// Fits the Gaussian part (bias, noise, outlier weight and their terms) on `rows`
/// (rows with a measurement), starting from `m`. Returns the log-likelihood.
pub fn fit_gauss(ctx: &Ctx, rows: &[usize], m: &mut Model) -> f64 {
    if rows.is_empty() {
        return 0.0;
    }
    let bt: Vec<usize> = (0..m.terms.len()).filter(|&t| m.terms[t].term.target == Target::Bias).collect();
    let nt: Vec<usize> = (0..m.terms.len()).filter(|&t| m.terms[t].term.target == Target::Noise).collect();
    let kb = 1 + bt.iter().map(|&t| m.terms[t].k()).sum::<usize>();
    let ks = 1 + nt.iter().map(|&t| m.terms[t].k()).sum::<usize>();
    let n = rows.len();
    // Cached designs: bias features (intercept first), noise features (without the σ0 column).
    let mut xb = vec![0.0; n * kb];
    let mut xs = vec![0.0; n * (ks - 1)];
    for (j, &i) in rows.iter().enumerate() {
        xb[j * kb] = 1.0;
        let mut o = 1;
        for &t in &bt {
            let k = m.terms[t].k();
            m.terms[t].features(ctx, i, &mut xb[j * kb + o..j * kb + o + k]);
            o += k;
        }
        let mut o = 0;
        for &t in &nt {
            let k = m.terms[t].k();
            m.terms[t].features(ctx, i, &mut xs[j * (ks - 1) + o..j * (ks - 1) + o + k]);
            o += k;
        }
    }
    let pack = |m: &Model| -> (Vec<f64>, Vec<f64>) {
        let mut b = vec![m.bias];
        for &t in &bt {
            b.extend_from_slice(&m.terms[t].coef);
        }
        let mut s = vec![m.sd0];
        for &t in &nt {
            s.extend_from_slice(&m.terms[t].coef);
        }
        (b, s)
    };
    let (mut tb, mut ts) = pack(m);
    let mut pi = m.outlier;
    // One pass: log-likelihood, the scoring system and the EM outlier update.
    let eval = |tb: &[f64], ts: &[f64], pi: f64| -> GaussPass {
        let mix = Mix::new(ctx, pi);
        let mut ps =
            GaussPass { ll: 0.0, ab: vec![0.0; kb * kb], bb: vec![0.0; kb], as_: vec![0.0; ks * ks], bs: vec![0.0; ks], outl: 0.0 };
        let mut jac = vec![0.0; ks];
        for (j, &i) in rows.iter().enumerate() {
            let xbr = &xb[j * kb..(j + 1) * kb];
            let xsr = &xs[j * (ks - 1)..(j + 1) * (ks - 1)];
            let mut mu = 0.0;
            for a in 0..kb {
                mu += xbr[a] * tb[a];
            }
            let (s0, d0) = sd0(ctx, ts[0], i);
            let mut sig_raw = s0 + ctx.table.sd_offset[i];
            for a in 1..ks {
                sig_raw += xsr[a - 1] * ts[a];
            }
            let lowest = ctx.sd_lowest(i);
            let sigma = sig_raw.max(lowest);
            let r = ctx.resid[i];
            let (l, resp) = mix.ll(r, mu, sigma);
            ps.ll += l;
            let z = (r - mu) / sigma;
            let (gb, wb) = (resp * z / sigma, resp / (sigma * sigma));
            for a in 0..kb {
                ps.bb[a] += gb * xbr[a];
                let wa = wb * xbr[a];
                for c in 0..=a {
                    ps.ab[a * kb + c] += wa * xbr[c];
                }
            }
            // At the clamp σ does not move with the noise parameters.
            let (gs, ws) = if sig_raw < lowest { (0.0, 0.0) } else { (resp * (z * z - 1.0) / sigma, 2.0 * resp / (sigma * sigma)) };
            jac[0] = d0;
            jac[1..].copy_from_slice(xsr);
            for a in 0..ks {
                ps.bs[a] += gs * jac[a];
                let wa = ws * jac[a];
                for c in 0..=a {
                    ps.as_[a * ks + c] += wa * jac[c];
                }
            }
            ps.outl += 1.0 - resp;
        }
        symmetrise(&mut ps.ab, kb);
        symmetrise(&mut ps.as_, ks);
        ps
    };
    let mut cur = eval(&tb, &ts, pi);
    for _ in 0..MAX_ITER {
        let db = solve_spd(&cur.ab, &cur.bb).unwrap_or_else(|| vec![0.0; kb]);
        let mut ds = solve_spd(&cur.as_, &cur.bs).unwrap_or_else(|| vec![0.0; ks]);
        if ts[0] <= 0.0 && ds[0] < 0.0 {
            // The global noise sits on its bound (≥ 0) and wants to leave it: solve for the
            // other σ parameters with it held there (active set), instead of creeping along.
            let r = ks - 1;
            let sub: Vec<f64> = (1..ks).flat_map(|a| (1..ks).map(move |c| (a, c))).map(|(a, c)| cur.as_[a * ks + c]).collect();
            let rest = solve_spd(&sub, &cur.bs[1..]).unwrap_or_else(|| vec![0.0; r]);
            ds = std::iter::once(0.0).chain(rest).collect();
        }
        let pi_new = if ctx.robust { (cur.outl / n as f64).clamp(1e-9, 0.5) } else { 0.0 };
        let mut step = 1.0;
        let mut accepted = false;
        for _ in 0..30 {
            let nb: Vec<f64> = tb.iter().zip(&db).map(|(a, d)| a + step * d).collect();
            let mut ns: Vec<f64> = ts.iter().zip(&ds).map(|(a, d)| a + step * d).collect();
            ns[0] = ns[0].max(0.0);
            let next = eval(&nb, &ns, pi_new);
            if next.ll.is_finite() && next.ll >= cur.ll - 1e-12 * cur.ll.abs() {
                let gain = next.ll - cur.ll;
                tb = nb;
                ts = ns;
                pi = pi_new;
                cur = next;
                accepted = gain > TOL_ABS + TOL_REL * cur.ll.abs();
                break;
            }
            step *= 0.5;
        }
        if !accepted {
            break;
        }
    }
    let ll = cur.ll;
    m.bias = tb[0];
    m.sd0 = ts[0];
    m.outlier = pi;
    let (mut ob, mut os) = (1, 1);
    for &t in &bt {
        let k = m.terms[t].k();
        m.terms[t].coef = tb[ob..ob + k].to_vec();
        ob += k;
    }
    for &t in &nt {
        let k = m.terms[t].k();
        m.terms[t].coef = ts[os..os + k].to_vec();
        os += k;
    }
    ll
}

/// Prior weight (in rows at the overall missing rate) on each dropout group category.
const GROUP_PSEUDO: f64 = 4.0;

/// Fits the dropout part on `rows` (all rows), starting from `m`. Returns the penalised
/// log-likelihood (group categories carry a weak prior, see [`GROUP_PSEUDO`]).
pub fn fit_bern(ctx: &Ctx, rows: &[usize], m: &mut Model) -> f64 {
    if rows.is_empty() {
        return 0.0;
    }
    let dt: Vec<usize> = (0..m.terms.len()).filter(|&t| m.terms[t].term.target == Target::Dropout).collect();
    let k = 1 + dt.iter().map(|&t| m.terms[t].k()).sum::<usize>();
    let n = rows.len();
    let mut x = vec![0.0; n * k];
    let mut y = vec![0.0; n];
    for (j, &i) in rows.iter().enumerate() {
        x[j * k] = 1.0;
        let mut o = 1;
        for &t in &dt {
            let kk = m.terms[t].k();
            m.terms[t].features(ctx, i, &mut x[j * k + o..j * k + o + kk]);
            o += kk;
        }
        y[j] = if ctx.table.missing(i) { 1.0 } else { 0.0 };
    }
    let mut th = vec![m.dropout];
    for &t in &dt {
        th.extend_from_slice(&m.terms[t].coef);
    }
    // A group category's rate is shrunk toward the overall rate by a Beta prior worth
    // GROUP_PSEUDO rows at that rate (pseudo-rows with fractional outcome, at the
    // category's mean offset): a category whose few training rows happen to have no
    // missing pixel would otherwise sit at the clamp (p = 1e-6) and cost ~14 nats for
    // every missing pixel it has in a held-out frame.
    let ybar = y.iter().sum::<f64>() / n as f64;
    let mut pseudo: Vec<(Vec<f64>, f64)> = vec![];
    let mut o = 1;
    for &t in &dt {
        let ft = &m.terms[t];
        if ft.term.form == FormKind::Group && ft.term.by.is_none() {
            let mut off = vec![(0.0, 0usize); ft.cats.len()];
            for &i in rows {
                let c = ctx.value(ft.term.col, i).round() as i64;
                if let Some(q) = ft.cats.iter().position(|&k| k == c) {
                    off[q].0 += ctx.table.p_offset[i];
                    off[q].1 += 1;
                }
            }
            for (q, (s, cnt)) in off.into_iter().enumerate() {
                let mut xr = vec![0.0; k];
                xr[0] = 1.0;
                xr[o + q] = 1.0;
                pseudo.push((xr, s / cnt.max(1) as f64));
            }
        }
        o += ft.k();
    }
    let eval = |th: &[f64]| -> (f64, Vec<f64>, Vec<f64>) {
        let (mut ll, mut a, mut b) = (0.0, vec![0.0; k * k], vec![0.0; k]);
        let real = rows.iter().enumerate().map(|(j, &i)| (&x[j * k..(j + 1) * k], ctx.table.p_offset[i], y[j], 1.0));
        let prior = pseudo.iter().map(|(xr, off)| (xr.as_slice(), *off, ybar, GROUP_PSEUDO));
        for (xr, off, yj, wt) in real.chain(prior) {
            let mut eta = off;
            for r in 0..k {
                eta += xr[r] * th[r];
            }
            let p = eta.clamp(P_EPS, 1.0 - P_EPS);
            ll += wt * (yj * p.ln() + (1.0 - yj) * (1.0 - p).ln());
            let v = p * (1.0 - p);
            let g = wt * (yj - p) / v;
            for r in 0..k {
                b[r] += g * xr[r];
                let wr = wt * xr[r] / v;
                for c in 0..=r {
                    a[r * k + c] += wr * xr[c];
                }
            }
        }
        symmetrise(&mut a, k);
        (ll, a, b)
    };
    let mut cur = eval(&th);
    for _ in 0..MAX_ITER {
        let mut d = solve_spd(&cur.1, &cur.2).unwrap_or_else(|| vec![0.0; k]);
        if th[0] <= 0.0 && d[0] < 0.0 {
            // The global rate is a probability (≥ 0 in the sensor model): hold it at its bound.
            let sub: Vec<f64> = (1..k).flat_map(|a| (1..k).map(move |c| (a, c))).map(|(a, c)| cur.1[a * k + c]).collect();
            let rest = solve_spd(&sub, &cur.2[1..]).unwrap_or_else(|| vec![0.0; k - 1]);
            d = std::iter::once(0.0).chain(rest).collect();
        }
        let mut step = 1.0;
        let mut accepted = false;
        for _ in 0..30 {
            let mut nt: Vec<f64> = th.iter().zip(&d).map(|(a, d)| a + step * d).collect();
            nt[0] = nt[0].max(0.0);
            let next = eval(&nt);
            if next.0.is_finite() && next.0 >= cur.0 - 1e-12 * cur.0.abs() {
                let gain = next.0 - cur.0;
                th = nt;
                cur = next;
                accepted = gain > TOL_ABS + TOL_REL * cur.0.abs();
                break;
            }
            step *= 0.5;
        }
        if !accepted {
            break;
        }
    }
    let ll = cur.0;
    m.dropout = th[0];
    let mut o = 1;
    for &t in &dt {
        let kk = m.terms[t].k();
        m.terms[t].coef = th[o..o + kk].to_vec();
        o += kk;
    }
    ll
}

struct GaussPass {
    ll: f64,
    ab: Vec<f64>,
    bb: Vec<f64>,
    as_: Vec<f64>,
    bs: Vec<f64>,
    outl: f64,
}

fn symmetrise(a: &mut [f64], k: usize) {
    for r in 0..k {
        for c in 0..r {
            a[c * k + r] = a[r * k + c];
        }
    }
}

/// A fitted term as a sensor-model effect.
pub fn effect(ctx: &Ctx, ft: &FittedTerm, cause: Option<String>) -> Option<Effect> {
    let cov = recon_core::sensor::Covariate::from_name(&ctx.table.columns[ft.term.col].name)?;
    let by = match ft.term.by {
        Some(b) => Some(recon_core::sensor::Covariate::from_name(&ctx.table.columns[b].name)?),
        None => None,
    };
    Some(Effect { target: ft.term.target, covariate: cov, form: ft.form(ctx), by, cause })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::table::Column;
    use recon_core::rng::SeededRng;

    /// Rows with x ~ U(0, 2) in 10 units, residual = 0.01 + 0.02·x + (0.005 + 0.01·x)·N, 5 % gross
    /// outliers, missing with p = 0.05 + 0.4·[x > 1.5].
    fn table(seed: u64) -> ResidualTable {
        let mut rng = SeededRng::new(seed);
        let n = 6000;
        let mut t = ResidualTable { source: "test".into(), ..Default::default() };
        let mut xs = vec![];
        for i in 0..n {
            let x = 2.0 * rng.uniform();
            let miss = rng.uniform() < 0.05 + if x > 1.5 { 0.4 } else { 0.0 };
            let mut r = 0.01 + 0.02 * x + (0.005 + 0.01 * x) * rng.normal();
            if rng.uniform() < 0.05 {
                r = 2.0 * rng.uniform() - 1.0;
            }
            t.measured.push(if miss { f64::NAN } else { 1.0 + r });
            t.simulated.push(1.0);
            t.unit.push(i % 10);
            xs.push(x);
        }
        finish(t, Column::numeric("x", xs))
    }

    /// Ten units, no sensor-model offsets, and the one covariate column.
    fn finish(mut t: ResidualTable, column: Column) -> ResidualTable {
        let n = t.measured.len();
        t.unit_names = (0..10).map(|u| u.to_string()).collect();
        t.sd_floor = vec![0.0; n];
        t.sd_offset = vec![0.0; n];
        t.p_offset = vec![0.0; n];
        t.columns.push(column);
        t
    }

    #[test]
    fn recovers_heteroscedastic_bias_noise_and_dropout_step_with_outliers() {
        let t = table(1);
        let ctx = Ctx::new(&t, true);
        let all: Vec<usize> = (0..t.len()).collect();
        let valid: Vec<usize> = all.iter().copied().filter(|&i| !t.missing(i)).collect();
        let mut m = Model::initial(&ctx, &valid, &all);
        let base_g = fit_gauss(&ctx, &valid, &mut m);
        let base_b = fit_bern(&ctx, &all, &mut m);
        for (target, form) in [(Target::Bias, FormKind::Linear), (Target::Noise, FormKind::Linear), (Target::Dropout, FormKind::Step)] {
            let rows = if target == Target::Dropout { &all } else { &valid };
            let ft = structure(&ctx, &m, Term { target, col: 0, form, by: None }, rows).unwrap();
            m.terms.push(ft);
        }
        let lg = fit_gauss(&ctx, &valid, &mut m);
        let lb = fit_bern(&ctx, &all, &mut m);
        assert!(lg > base_g + 100.0 && lb > base_b + 100.0, "{lg} {base_g} {lb} {base_b}");
        let p = |i: usize| m.terms[i].params(&ctx);
        assert!((m.bias - 0.01).abs() < 0.002 && (p(0)["slope"] - 0.02).abs() < 0.002, "bias {} {:?}", m.bias, p(0));
        assert!((m.noise(&ctx) - 0.005).abs() < 0.001 && (p(1)["slope"] - 0.01).abs() < 0.001, "noise {} {:?}", m.noise(&ctx), p(1));
        assert!((p(2)["threshold"] - 1.5).abs() < 0.03 && (p(2)["delta"] - 0.4).abs() < 0.05, "{:?}", p(2));
        assert!((m.dropout - 0.05).abs() < 0.015);
        assert!((m.outlier - 0.05).abs() < 0.015, "outlier {}", m.outlier);
        // The effect form in model units predicts the same as the scaled coefficients.
        let e = effect(&ctx, &m.terms[0], None);
        assert!(e.is_none(), "`x` is not a sensor covariate");
        for i in 0..50 {
            let x = t.columns[0].values[i];
            assert!((m.terms[0].form(&ctx).eval(x) - m.terms[0].value(&ctx, i)).abs() < 1e-12);
        }
    }

    /// Rows in categories 0..5 with residual sd 0.002 + `excess[c]`, 5 % gross outliers,
    /// missing with probability `miss[c]`; category 5 has only `small` rows.
    fn grouped(seed: u64, excess: [f64; 6], miss: [f64; 6], small: usize) -> ResidualTable {
        let mut rng = SeededRng::new(seed);
        let mut t = ResidualTable { source: "test".into(), ..Default::default() };
        let mut cats = vec![];
        for c in 0..6 {
            let n = if c == 5 { small } else { 1500 };
            for i in 0..n {
                let mut r = (0.002 + excess[c]) * rng.normal();
                if rng.uniform() < 0.05 {
                    r = 0.4 * rng.uniform() - 0.2;
                }
                t.measured.push(if rng.uniform() < miss[c] { f64::NAN } else { 1.0 + r });
                t.simulated.push(1.0);
                t.unit.push(i % 10);
                cats.push(c as f64);
            }
        }
        finish(t, Column::categorical("object", cats))
    }

    #[test]
    fn noise_group_takes_the_quietest_category_as_reference_despite_outliers() {
        let excess = [0.003, 0.0, 0.001, 0.004, 0.002, 0.0];
        let t = grouped(3, excess, [0.01; 6], 1500);
        let ctx = Ctx::new(&t, true);
        let all: Vec<usize> = (0..t.len()).collect();
        let valid: Vec<usize> = all.iter().copied().filter(|&i| !t.missing(i)).collect();
        let mut m = Model::initial(&ctx, &valid, &all);
        fit_gauss(&ctx, &valid, &mut m);
        // The robust excess orders the categories as planted, outliers notwithstanding.
        let ex = category_excess(&ctx, &m, 0, &valid);
        let order: Vec<i64> = {
            let mut v: Vec<(i64, f64)> = ex.into_iter().collect();
            v.sort_by(|a, b| a.1.total_cmp(&b.1));
            v.into_iter().map(|e| e.0).collect()
        };
        assert_eq!(&order[2..], &[2, 4, 0, 3], "{order:?}");
        let ft = structure(&ctx, &m, Term { target: Target::Noise, col: 0, form: FormKind::Group, by: None }, &valid).unwrap();
        assert!(ft.reference == 1 || ft.reference == 5, "reference {}", ft.reference);
        m.terms.push(ft);
        seed_noise_group(&ctx, &mut m, &valid);
        fit_gauss(&ctx, &valid, &mut m);
        for c in 0..6 {
            let i = valid.iter().copied().find(|&i| t.columns[0].values[i] == c as f64).unwrap();
            let sd = m.predict(&ctx, i).sigma;
            assert!((sd - 0.002 - excess[c]).abs() < 0.0003, "category {c}: σ {sd}");
        }
        assert!((m.outlier - 0.05).abs() < 0.015, "outlier {}", m.outlier);
    }

    #[test]
    fn dropout_group_category_without_missing_rows_stays_off_the_clamp() {
        // Category 5: 60 rows, none missing (rate 0); the others 20–40 %.
        let t = grouped(4, [0.0; 6], [0.2, 0.3, 0.4, 0.25, 0.35, 0.0], 60);
        let ctx = Ctx::new(&t, true);
        let all: Vec<usize> = (0..t.len()).collect();
        let valid: Vec<usize> = all.iter().copied().filter(|&i| !t.missing(i)).collect();
        let mut m = Model::initial(&ctx, &valid, &all);
        fit_bern(&ctx, &all, &mut m);
        let ft = structure(&ctx, &m, Term { target: Target::Dropout, col: 0, form: FormKind::Group, by: None }, &all).unwrap();
        m.terms.push(ft);
        fit_bern(&ctx, &all, &mut m);
        let p = |c: f64| m.predict(&ctx, all.iter().copied().find(|&i| t.columns[0].values[i] == c).unwrap()).p;
        // The prior (4 rows at the overall ~25 %) gives ≈ 1/64, not the clamp 1e-6.
        assert!(p(5.0) > 0.005 && p(5.0) < 0.03, "p {}", p(5.0));
        for (c, want) in [(0.0, 0.2), (1.0, 0.3), (2.0, 0.4)] {
            assert!((p(c) - want).abs() < 0.035, "category {c}: {} vs {want}", p(c));
        }
    }
}
