//! The audit report: JSON (stable schema below), a readable summary and SVG plots.
//!
//! ```text
//! {
//!   "version": 1, "kind": "depth" | "table",
//!   "data":     {source, rows, valid, missing, units, unit_names, covariates, folds, split},
//!   "method":   {likelihood, test, correction, alpha, screen_alpha, parsimony_alpha, uncertainty, …},
//!   "input":    metrics of the simulation as given (no refit; log-likelihoods null),
//!   "baseline": {"parameters": {bias, noise, dropout, outlier_fraction},
//!                "standard_errors": {same keys}, "heldout": metrics},
//!   "findings": [{"target", "covariate", "form", "by" (interactions only),
//!                 "parameters": the form's fields (slope | linear, quadratic | threshold, delta | values),
//!                 "standard_errors": same keys, "heldout_gain": nats per held-out pixel of the
//!                 target's channel, "heldout_gain_total": nats, "folds_improved": "k/n",
//!                 "t" (of the fold gains, descriptive), "p_value": family-wise
//!                 (randomisation max statistic over the round's candidates),
//!                 "p_value_raw": the candidate's own randomisation p, "candidates",
//!                 "heldout_units": "frames" | "frame×object",
//!                 "cause", "effect": the sensor-model Effect (depth only)}], strongest first,
//!   "extended_model": path | null,
//!   "after":    {"parameters", "standard_errors", "heldout": metrics,
//!                "improvement": {rmse, robust_sd, loglik_per_row, bias_error, noise_error,
//!                                missing_rate_error}: before − after (positive = better;
//!                                loglik: after − before)},
//!   "outliers": {fraction_baseline, fraction_final, stated, flagged, flag_level, tested,
//!                "dependence": [{covariate, kind: rate|sign, split, rate_below, rate_above,
//!                outlier_residual_below, outlier_residual_above, t, p_value}] strongest first}
//!                (robust fits; see `audit::outliers`),
//!   "rounds":   per selection round: candidates, fitted, top candidates, selected
//!               (a bias step seeded from the outliers is marked "[outlier subset]")
//! }
//! metrics = {rows, valid, rmse, robust_sd, loglik_gauss_per_valid, loglik_dropout_per_row,
//!            loglik_per_row, missing_rate, missing_rate_predicted, bias_error, noise_error,
//!            missing_rate_error}
//! ```
//! Metrics are on held-out frames (each predicted by the fit that did not see it):
//! `rmse` of measured − predicted mean over valid pixels (outliers included),
//! `robust_sd` its 1.4826·MAD; the three `*_error`s are calibration errors binned along
//! every covariate (10 equal-count bins, or per category): RMS over bins and covariates of
//! the binned median residual (bias), of observed robust sd − predicted sd (noise), and of
//! observed − predicted missing rate.
use crate::fit::{Ctx, Pred};
use crate::search::{bootstrap, globals, Cv, SearchOptions, SearchResult};
use crate::stats::{median, quantile_sorted, robust_sd};
use crate::svg::{esc, PlotArea};
use crate::table::ColumnKind;
use recon_core::sensor::{Effect, Form, Target};
use serde::Serialize;
use serde_json::{json, Value};
use std::collections::BTreeMap;

pub const REPORT_VERSION: u32 = 1;

#[derive(Serialize, Clone, Debug, Default)]
pub struct Metrics {
    pub rows: usize,
    pub valid: usize,
    pub rmse: f64,
    pub robust_sd: f64,
    pub loglik_gauss_per_valid: Option<f64>,
    pub loglik_dropout_per_row: Option<f64>,
    pub loglik_per_row: Option<f64>,
    pub missing_rate: f64,
    pub missing_rate_predicted: Option<f64>,
    pub bias_error: f64,
    pub noise_error: Option<f64>,
    pub missing_rate_error: Option<f64>,
}

#[derive(Serialize, Clone, Debug)]
pub struct Finding {
    pub target: String,
    pub covariate: String,
    pub form: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub by: Option<String>,
    pub parameters: Value,
    pub standard_errors: Value,
    pub heldout_gain: f64,
    pub heldout_gain_total: f64,
    pub folds_improved: String,
    pub t: f64,
    pub p_value: f64,
    pub p_value_raw: f64,
    pub candidates: usize,
    /// Held-out units of its test: `frames` or `frame×object` (see `audit::search`).
    pub heldout_units: String,
    pub cause: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub effect: Option<Effect>,
    /// Depth audits with frames: the mechanism whose fit makes this finding vanish
    /// (see the report's `mechanisms.findings_explained`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub explained_by: Option<String>,
    /// The fitted form (for plots and the extended model).
    #[serde(skip)]
    pub fitted: Option<Form>,
    #[serde(skip)]
    pub term_index: usize,
}

#[derive(Serialize, Clone, Debug)]
pub struct Report {
    pub version: u32,
    pub kind: String,
    pub data: Value,
    pub method: Value,
    pub input: Metrics,
    pub baseline: Value,
    pub findings: Vec<Finding>,
    pub extended_model: Option<String>,
    pub after: Value,
    /// The outlier component audited (robust fits).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub outliers: Option<crate::outliers::OutlierAudit>,
    pub rounds: Vec<Value>,
    /// Mechanism-level inference (depth audits with frames; `audit::mechanism`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub mechanisms: Option<crate::mechanism::MechanismReport>,
}

/// Binned calibration along one column: per bin (rows), x (median), n.
fn bins(ctx: &Ctx, col: usize, rows: &[usize], nb: usize) -> Vec<(f64, Vec<usize>)> {
    let c = &ctx.table.columns[col];
    if c.kind == ColumnKind::Categorical {
        let mut m: BTreeMap<i64, Vec<usize>> = BTreeMap::new();
        for &i in rows {
            m.entry(c.values[i].round() as i64).or_default().push(i);
        }
        return m.into_iter().map(|(k, v)| (k as f64, v)).collect();
    }
    let mut sorted = rows.to_vec();
    sorted.sort_by(|&a, &b| c.values[a].total_cmp(&c.values[b]));
    let n = sorted.len();
    let mut out: Vec<(f64, Vec<usize>)> = vec![];
    let mut start = 0;
    for b in 0..nb {
        let mut end = ((b + 1) * n) / nb;
        // Ties stay in one bin.
        while end < n && end > 0 && c.values[sorted[end]] == c.values[sorted[end - 1]] {
            end += 1;
        }
        if end <= start {
            continue;
        }
        let chunk = sorted[start..end].to_vec();
        let x = c.values[chunk[chunk.len() / 2]];
        out.push((x, chunk));
        start = end;
        if start >= n {
            break;
        }
    }
    out
}

/// Binned statistics of one target for plotting and calibration: (x, observed, predicted, n).
pub fn binned(ctx: &Ctx, col: usize, rows: &[usize], preds: &[Pred], target: Target, nb: usize) -> Vec<(f64, f64, f64, usize)> {
    let t = ctx.table;
    bins(ctx, col, rows, nb)
        .into_iter()
        .filter_map(|(x, b)| {
            let valid: Vec<usize> = b.iter().copied().filter(|&i| !t.missing(i)).collect();
            match target {
                Target::Bias => {
                    if valid.len() < 5 {
                        return None;
                    }
                    let r: Vec<f64> = valid.iter().map(|&i| ctx.resid[i]).collect();
                    let mu = valid.iter().map(|&i| preds[i].mu).sum::<f64>() / valid.len() as f64;
                    Some((x, median(&r), mu, valid.len()))
                }
                Target::Noise => {
                    if valid.len() < 5 {
                        return None;
                    }
                    let d: Vec<f64> = valid.iter().map(|&i| ctx.resid[i] - preds[i].mu).collect();
                    let s = (valid.iter().map(|&i| preds[i].sigma.powi(2)).sum::<f64>() / valid.len() as f64).sqrt();
                    Some((x, robust_sd(&d), s, valid.len()))
                }
                Target::Dropout => {
                    if b.len() < 5 {
                        return None;
                    }
                    let obs = b.iter().filter(|&&i| t.missing(i)).count() as f64 / b.len() as f64;
                    let p = b.iter().map(|&i| preds[i].p).sum::<f64>() / b.len() as f64;
                    Some((x, obs, p, b.len()))
                }
            }
        })
        .collect()
}

/// RMS over covariates of the count-weighted RMS over bins of (observed − predicted).
fn calibration(ctx: &Ctx, rows: &[usize], preds: &[Pred], target: Target) -> f64 {
    let mut acc = 0.0;
    let mut ncol = 0;
    for col in 0..ctx.table.columns.len() {
        let b = binned(ctx, col, rows, preds, target, 10);
        let n: usize = b.iter().map(|x| x.3).sum();
        if n == 0 || b.len() < 2 {
            continue;
        }
        let ms = b.iter().map(|x| x.3 as f64 * (x.1 - x.2).powi(2)).sum::<f64>() / n as f64;
        acc += ms;
        ncol += 1;
    }
    if ncol == 0 {
        0.0
    } else {
        (acc / ncol as f64).sqrt()
    }
}

/// Metrics of predictions `preds` over all rows; `ll` = (gauss, bern) totals when known.
pub fn metrics(ctx: &Ctx, preds: &[Pred], ll: Option<(f64, f64)>, with_noise: bool, with_dropout: bool) -> Metrics {
    let t = ctx.table;
    let rows: Vec<usize> = (0..t.len()).collect();
    let valid: Vec<usize> = rows.iter().copied().filter(|&i| !t.missing(i)).collect();
    let d: Vec<f64> = valid.iter().map(|&i| ctx.resid[i] - preds[i].mu).collect();
    let rmse = (d.iter().map(|x| x * x).sum::<f64>() / d.len().max(1) as f64).sqrt();
    let nrows = rows.len().max(1) as f64;
    Metrics {
        rows: rows.len(),
        valid: valid.len(),
        rmse,
        robust_sd: robust_sd(&d),
        loglik_gauss_per_valid: ll.map(|l| l.0 / valid.len().max(1) as f64),
        loglik_dropout_per_row: ll.map(|l| l.1 / nrows),
        loglik_per_row: ll.map(|l| (l.0 + l.1) / nrows),
        missing_rate: (rows.len() - valid.len()) as f64 / nrows,
        missing_rate_predicted: with_dropout.then(|| preds.iter().map(|p| p.p).sum::<f64>() / nrows),
        bias_error: calibration(ctx, &rows, preds, Target::Bias),
        noise_error: with_noise.then(|| calibration(ctx, &rows, preds, Target::Noise)),
        missing_rate_error: with_dropout.then(|| calibration(ctx, &rows, preds, Target::Dropout)),
    }
}

fn cv_metrics(ctx: &Ctx, res: &SearchResult, cv: &Cv) -> (Metrics, Vec<Pred>) {
    let preds = cv.heldout_predictions(ctx, &res.folds);
    let ll = (cv.unit_ll_gauss.iter().sum(), cv.unit_ll_bern.iter().sum());
    (metrics(ctx, &preds, Some(ll), true, true), preds)
}

fn params_json(form: &Form, se: &BTreeMap<String, f64>, ctx: &Ctx, col: usize) -> (Value, Value) {
    let num = |x: f64| if x.is_finite() { json!(x) } else { Value::Null };
    let se_of = |k: &str| num(se.get(k).copied().unwrap_or(f64::NAN));
    match form {
        Form::Linear { slope } => (json!({"slope": slope}), json!({"slope": se_of("slope")})),
        Form::Quadratic { linear, quadratic } => {
            (json!({"linear": linear, "quadratic": quadratic}), json!({"linear": se_of("linear"), "quadratic": se_of("quadratic")}))
        }
        Form::Step { threshold, delta } => {
            (json!({"threshold": threshold, "delta": delta}), json!({"threshold": se_of("threshold"), "delta": se_of("delta")}))
        }
        Form::Group { values } => {
            let c = &ctx.table.columns[col];
            let label = |k: &String| k.parse::<i64>().map(|code| c.label(code)).unwrap_or_else(|_| k.clone());
            let v: serde_json::Map<String, Value> = values.iter().map(|(k, x)| (label(k), json!(x))).collect();
            let s: serde_json::Map<String, Value> = values.keys().map(|k| (label(k), se_of(&format!("values.{k}")))).collect();
            (json!({"values": v}), json!({"values": s}))
        }
    }
}

/// Observed range of a column.
pub fn col_range(ctx: &Ctx, col: usize) -> (f64, f64) {
    let v = &ctx.table.columns[col].values;
    let mut s = v.clone();
    s.sort_by(|a, b| a.total_cmp(b));
    (quantile_sorted(&s, 0.01), quantile_sorted(&s, 0.99))
}

/// What the input model predicted (for the "input" metrics): mean 0 (the simulation
/// already includes its bias), its sd and missing rate when known.
pub struct InputPrediction {
    pub noise: Option<f64>,
    pub dropout: Option<f64>,
}

pub struct Built {
    pub report: Report,
    /// Held-out predictions before (baseline) and after (extended), per row.
    pub before: Vec<Pred>,
    pub after: Vec<Pred>,
}

/// Assembles the report from a finished search.
pub fn build(ctx: &Ctx, res: &SearchResult, opts: &SearchOptions, kind: &str, input: &InputPrediction, depth_sensor: bool) -> Built {
    let t = ctx.table;
    let nrows = t.len();
    let nvalid = (0..nrows).filter(|&i| !t.missing(i)).count();
    let input_preds: Vec<Pred> = (0..nrows)
        .map(|i| {
            let sd = input.noise.map(|n| (t.sd_floor[i].powi(2) + n * n).sqrt() + t.sd_offset[i]).unwrap_or(f64::NAN);
            let p = input.dropout.map(|d| (d + t.p_offset[i]).clamp(0.0, 1.0)).unwrap_or(f64::NAN);
            Pred { mu: 0.0, sigma: sd, p }
        })
        .collect();
    let input_m = metrics(ctx, &input_preds, None, input.noise.is_some(), input.dropout.is_some());
    let (base_m, before) = cv_metrics(ctx, res, &res.baseline);
    let (after_m, after) = cv_metrics(ctx, res, &res.final_cv);
    let full = res.final_cv.full();
    let unc = bootstrap(ctx, full, opts.bootstrap, opts.seed);
    let unc_base = bootstrap(ctx, res.baseline.full(), opts.bootstrap, opts.seed);
    let mut findings = vec![];
    for (ti, s) in res.selected.iter().enumerate() {
        let ft = &full.terms[ti];
        let form = ft.form(ctx);
        let se = &unc.terms[ti];
        let (params, ses) = params_json(&form, se, ctx, ft.term.col);
        let cov = t.columns[ft.term.col].name.clone();
        let by = ft.term.by.map(|b| t.columns[b].name.clone());
        let cause =
            crate::cause::describe(ft.term.target, &cov, &form, by.as_deref(), col_range(ctx, ft.term.col), &t.value_unit, depth_sensor);
        let ev = &s.evidence;
        findings.push(Finding {
            target: ft.term.target.name().into(),
            covariate: cov,
            form: ft.term.form.name().into(),
            by,
            parameters: params,
            standard_errors: ses,
            heldout_gain: ev.gain_per_row,
            heldout_gain_total: ev.gain_total,
            folds_improved: format!("{}/{}", ev.gains.iter().filter(|&&g| g > 0.0).count(), ev.gains.len()),
            t: ev.t,
            p_value: s.p_adjusted,
            p_value_raw: ev.p,
            candidates: s.candidates,
            heldout_units: if ev.fine { "frame×object" } else { "frames" }.into(),
            effect: if depth_sensor { crate::fit::effect(ctx, ft, Some(cause.clone())) } else { None },
            cause,
            fitted: Some(form),
            explained_by: None,
            term_index: ti,
        });
    }
    findings.sort_by(|a, b| b.heldout_gain_total.total_cmp(&a.heldout_gain_total));
    let num = |x: Option<f64>| x.filter(|v| v.is_finite()).map(|v| json!(v)).unwrap_or(Value::Null);
    let improvement = json!({
        "rmse": base_m.rmse - after_m.rmse,
        "robust_sd": base_m.robust_sd - after_m.robust_sd,
        "loglik_per_row": num(after_m.loglik_per_row.zip(base_m.loglik_per_row).map(|(a, b)| a - b)),
        "bias_error": base_m.bias_error - after_m.bias_error,
        "noise_error": num(base_m.noise_error.zip(after_m.noise_error).map(|(a, b)| a - b)),
        "missing_rate_error": num(base_m.missing_rate_error.zip(after_m.missing_rate_error).map(|(a, b)| a - b)),
    });
    let split = if res.folds.k == t.n_units() {
        format!("leave-one-unit-out over {} units", res.folds.k)
    } else {
        format!("{} folds of shuffled units (seed {})", res.folds.k, opts.seed)
    };
    let data = json!({
        "source": t.source, "rows": nrows, "valid": nvalid, "missing": nrows - nvalid,
        "units": t.n_units(), "unit_names": t.unit_names,
        "covariates": t.columns.iter().map(|c| json!({"name": c.name, "kind": if c.kind == ColumnKind::Categorical { "categorical" } else { "numeric" }})).collect::<Vec<_>>(),
        "folds": res.folds.k, "split": split, "value_unit": t.value_unit,
    });
    let method = json!({
        "likelihood": if opts.robust { "Gaussian with a uniform outlier component (valid rows) + Bernoulli (missing)" } else { "Gaussian (valid rows) + Bernoulli (missing)" },
        "test": "randomisation test: signs of whole held-out folds' log-likelihood gains flipped (all 2^K patterns for K ≤ 16 folds, else 20000 draws)",
        "correction": "max statistic over the round's fitted candidates (Westfall–Young), on fold-t and on totals, combined by Bonferroni (2·min); screened-out candidates (pixel-level score p ≥ screen_alpha) are not fitted",
        "alpha": opts.alpha, "screen_alpha": opts.screen_alpha, "parsimony_alpha": opts.parsimony_alpha,
        "uncertainty": format!("bootstrap over units (frames): {} resamples of the units with replacement, every parameter refitted (step thresholds re-chosen)", opts.bootstrap),
        "max_findings": opts.max_findings, "interactions": opts.interactions,
    });
    let gjson = |m: &BTreeMap<String, f64>| -> Value {
        m.iter().map(|(k, v)| (k.clone(), num(Some(*v)))).collect::<serde_json::Map<_, _>>().into()
    };
    let baseline = json!({
        "parameters": gjson(&globals(ctx, res.baseline.full())),
        "standard_errors": gjson(&unc_base.globals),
        "heldout": base_m,
    });
    let after_v = json!({
        "parameters": gjson(&globals(ctx, full)),
        "standard_errors": gjson(&unc.globals),
        "heldout": after_m,
        "improvement": improvement,
    });
    let term_name = |tm: &crate::fit::Term| {
        let by = tm.by.map(|b| format!(" × {}", t.columns[b].name)).unwrap_or_default();
        let subset = if tm.form == crate::fit::FormKind::Subset { " [outlier subset]" } else { "" };
        format!("{} ~ {}({}){by}{subset}", tm.target.name(), tm.form.name(), t.columns[tm.col].name)
    };
    let rounds = res
        .rounds
        .iter()
        .map(|r| {
            json!({
                "candidates": r.candidates, "fitted": r.fitted,
                "selected": r.selected.as_ref().map(term_name),
                "top": r.top.iter().map(|e| json!({"term": term_name(&e.term), "heldout_gain_total": e.gain_total, "t": num(Some(e.t)), "p_value_raw": e.p, "p_screen": e.p_screen})).collect::<Vec<_>>(),
            })
        })
        .collect();
    Built {
        report: Report {
            version: REPORT_VERSION,
            kind: kind.into(),
            data,
            method,
            input: input_m,
            baseline,
            findings,
            extended_model: None,
            after: after_v,
            outliers: opts.robust.then(|| crate::outliers::audit(ctx, res.baseline.full(), full, opts.outlier_flag, opts.seed)),
            rounds,
            mechanisms: None,
        },
        before,
        after,
    }
}

impl Report {
    /// Readable summary (plain text).
    pub fn summary(&self) -> String {
        let mm = self.data["value_unit"] == "m";
        let v = |x: f64| if mm { format!("{:.2} mm", 1000.0 * x) } else { format!("{x:.4}") };
        let mut s = String::new();
        s += &format!(
            "recon audit ({}): {} rows ({} valid, {:.1}% missing) in {} units; {}\n",
            self.kind,
            self.data["rows"],
            self.data["valid"],
            100.0 * self.input.missing_rate,
            self.data["units"],
            self.data["split"].as_str().unwrap_or("")
        );
        s += &format!(
            "test: held-out log-likelihood gain per fold, sign-flip randomisation with a max-statistic correction over each round's candidates, alpha {}\n",
            self.method["alpha"]
        );
        let bp = &self.baseline["parameters"];
        let g = |k: &str| bp[k].as_f64().unwrap_or(f64::NAN);
        s += &format!(
            "baseline: bias {}, noise {}, dropout {:.2}%, outliers {:.2}%\n",
            v(g("bias")),
            v(g("noise")),
            100.0 * g("dropout"),
            100.0 * g("outlier_fraction")
        );
        if self.findings.is_empty() {
            s += "findings: none significant — the model explains the data as well as any candidate effect on held-out units.\n";
        } else {
            s += "findings (strongest held-out gain first):\n";
            for (i, f) in self.findings.iter().enumerate() {
                let by = f.by.as_ref().map(|b| format!(" × {b}")).unwrap_or_default();
                s += &format!(
                    "  {}. {} ~ {}({}){by}: {} ± {}\n     held-out gain {:.4} nats/pixel ({:.1} total, {} folds better), p = {:.2e} ({} candidates)\n     {}\n",
                    i + 1,
                    f.target,
                    f.form,
                    f.covariate,
                    f.parameters,
                    f.standard_errors,
                    f.heldout_gain,
                    f.heldout_gain_total,
                    f.folds_improved,
                    f.p_value,
                    f.candidates,
                    f.cause
                );
            }
        }
        let b = &self.baseline["heldout"];
        let a = &self.after["heldout"];
        let f = |x: &Value| x.as_f64().unwrap_or(f64::NAN);
        s += &format!(
            "held out, before → after: rmse {} → {}; robust sd {} → {}\n",
            v(f(&b["rmse"])),
            v(f(&a["rmse"])),
            v(f(&b["robust_sd"])),
            v(f(&a["robust_sd"]))
        );
        s += &format!(
            "  log-likelihood/row {:.4} → {:.4}; calibration errors: bias {} → {}, noise {} → {}, missing rate {:.4} → {:.4}\n",
            f(&b["loglik_per_row"]),
            f(&a["loglik_per_row"]),
            v(f(&b["bias_error"])),
            v(f(&a["bias_error"])),
            v(f(&b["noise_error"])),
            v(f(&a["noise_error"])),
            f(&b["missing_rate_error"]),
            f(&a["missing_rate_error"])
        );
        if let Some(o) = &self.outliers {
            let alpha = self.method["alpha"].as_f64().unwrap_or(0.01);
            s += &format!(
                "outliers: {:.2}% at baseline, {:.2}% after (the sensor model states {:.0}%){}\n",
                100.0 * o.fraction_baseline,
                100.0 * o.fraction_final,
                100.0 * o.stated,
                if o.flagged { " — unexplained, to be explained" } else { "" }
            );
            let opt = |x: Option<f64>| x.map(v).unwrap_or_else(|| "–".into());
            let mut any = false;
            for d in o.significant(alpha).take(4) {
                any = true;
                s += &format!(
                    "  {} ~ {} (split {:.3}): outlier share {:.2}% below → {:.2}% above, outlier residual {} / {}; t {:.1}, p = {:.2e}\n",
                    d.kind,
                    d.covariate,
                    d.split,
                    100.0 * d.rate_below,
                    100.0 * d.rate_above,
                    opt(d.outlier_residual_below),
                    opt(d.outlier_residual_above),
                    d.t,
                    d.p_value
                );
            }
            if !any && o.tested > 0 {
                s += &format!("  no dependence on any covariate ({} tested, family-wise alpha {alpha})\n", o.tested);
            }
        }
        s += &format!("input simulation as given: rmse {}, robust sd {}\n", v(self.input.rmse), v(self.input.robust_sd));
        if let Some(m) = &self.mechanisms {
            s += &m.summary();
        }
        if let Some(p) = &self.extended_model {
            s += &format!("extended sensor model: {p}\n");
        }
        s
    }
}

/// SVG plot of one finding: the target's binned statistic along its covariate on
/// held-out units — observed (dots), baseline prediction (grey, before) and the extended
/// model's prediction (red, after); for bias/noise a light scatter of residuals behind.
pub fn finding_svg(ctx: &Ctx, f: &Finding, col: usize, before: &[Pred], after: &[Pred], mm: bool) -> String {
    let target = match f.target.as_str() {
        "bias" => Target::Bias,
        "noise" => Target::Noise,
        _ => Target::Dropout,
    };
    let rows: Vec<usize> = (0..ctx.table.len()).collect();
    let nb = if ctx.table.columns[col].kind == ColumnKind::Categorical { 64 } else { 20 };
    let b = binned(ctx, col, &rows, before, target, nb);
    let a = binned(ctx, col, &rows, after, target, nb);
    let scale = if mm && target != Target::Dropout {
        1000.0
    } else if target == Target::Dropout {
        100.0
    } else {
        1.0
    };
    let ylab = match target {
        Target::Bias => format!("median residual ({})", if mm { "mm" } else { "units" }),
        Target::Noise => format!("residual spread, robust sd ({})", if mm { "mm" } else { "units" }),
        Target::Dropout => "missing rate (%)".to_string(),
    };
    // Scatter of residuals (bias/noise): every k-th valid row, clipped to the 1–99 % range.
    let mut scatter = vec![];
    if target != Target::Dropout {
        let valid: Vec<usize> = rows.iter().copied().filter(|&i| !ctx.table.missing(i)).collect();
        let step = (valid.len() / 1500).max(1);
        for &i in valid.iter().step_by(step) {
            let y = if target == Target::Bias { ctx.resid[i] } else { (ctx.resid[i] - after[i].mu).abs() * 1.2533 };
            scatter.push((ctx.table.columns[col].values[i], y * scale));
        }
    }
    let mut ys: Vec<f64> =
        b.iter().flat_map(|x| [x.1, x.2]).chain(a.iter().map(|x| x.2)).map(|y| y * scale).filter(|y| y.is_finite()).collect();
    let mut sc: Vec<f64> = scatter.iter().map(|p| p.1).collect();
    sc.sort_by(|x, y| x.total_cmp(y));
    if !sc.is_empty() {
        ys.push(quantile_sorted(&sc, 0.02));
        ys.push(quantile_sorted(&sc, 0.98));
    }
    let (mut y0, mut y1) = ys.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &y| (lo.min(y), hi.max(y)));
    if !(y1 > y0) {
        y0 -= 1.0;
        y1 += 1.0;
    }
    let pad = 0.08 * (y1 - y0);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let xs: Vec<f64> = b.iter().map(|x| x.0).collect();
    let (r0, r1) = col_range(ctx, col);
    let (mut x0, mut x1) =
        (r0.min(xs.iter().cloned().fold(f64::INFINITY, f64::min)), r1.max(xs.iter().cloned().fold(f64::NEG_INFINITY, f64::max)));
    if !(x1 > x0) {
        x0 -= 1.0;
        x1 += 1.0;
    }
    let by = f.by.as_ref().map(|b| format!(" × {b}")).unwrap_or_default();
    let area = PlotArea { x0, x1, y0, y1 };
    let (sx, sy) = (|x: f64| area.sx(x), |y: f64| area.sy(y));
    let mut s = area.open(
        &format!("{} ~ {}({}){} — held out: observed (dots), before (grey), after (red)", f.target, f.form, esc(&f.covariate), esc(&by)),
        &esc(&f.covariate),
        &esc(&ylab),
    );
    for (x, y) in &scatter {
        if *x >= x0 && *x <= x1 && *y >= y0 && *y <= y1 {
            s += &format!("<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"1.2\" fill=\"#1f77b4\" fill-opacity=\"0.15\"/>\n", sx(*x), sy(*y));
        }
    }
    let line = |pts: &[(f64, f64)], color: &str, dash: &str| -> String {
        let p: Vec<String> = pts.iter().filter(|p| p.1.is_finite()).map(|(x, y)| format!("{:.1},{:.1}", sx(*x), sy(*y))).collect();
        format!("<polyline points=\"{}\" fill=\"none\" stroke=\"{color}\" stroke-width=\"2\" stroke-dasharray=\"{dash}\"/>\n", p.join(" "))
    };
    s += &line(&b.iter().map(|x| (x.0, x.2 * scale)).collect::<Vec<_>>(), "#888", "6 4");
    s += &line(&a.iter().map(|x| (x.0, x.2 * scale)).collect::<Vec<_>>(), "#d62728", "");
    for x in &b {
        s += &format!("<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"4\" fill=\"black\"/>\n", sx(x.0), sy(x.1 * scale));
    }
    s += "</svg>\n";
    s
}
