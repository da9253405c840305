//! `report.html`: the audit for a person to read, beside `report.json` for machines.
//!
//! One self-contained page (no scripts, no network) that links the files of the same output
//! folder: the summary, the findings table, the physical mechanisms (verdict, accepted
//! mechanisms with runner-up and margin, every round's candidates), the before/after metrics, any further report
//! sections that are arrays of records (mechanism comparison, downstream before/after) as
//! tables, the findings' plots, the partial-residual plots of bias findings, and residual
//! maps per frame (measured − simulated beside the extended model's predicted residual and
//! what remains).
use crate::fit::{Ctx, Pred};
use crate::report::{col_range, Finding, Report};
use crate::stats::{median, quantile_sorted, robust_sd};
use crate::svg::{esc, PlotArea};
use crate::table::ColumnKind;
use serde_json::Value;

/// Residual maps are drawn for at most this many frames (the first units by index).
const MAX_MAP_FRAMES: usize = 8;
/// Longest side of one map panel, pixels.
const MAP_SIDE: usize = 240;

/// A residual map image of one frame: file name under `maps/`, PNG bytes.
pub(crate) struct ResidualMap {
    pub file: String,
    pub unit: String,
    pub png: Vec<u8>,
}

/// The residual maps and their colour scale (± this many value units, red positive).
pub(crate) struct Maps {
    pub maps: Vec<ResidualMap>,
    pub scale: f64,
}

/// Per frame of a depth audit (the table has `u` and `v` columns): three panels, measured −
/// simulated, the extended model's held-out predicted residual mean, and their difference.
/// Sampled pixels are averaged into cells; cells without a sample are grey, cells whose
/// samples are all missing returns black.
pub(crate) fn residual_maps(ctx: &Ctx, after: &[Pred]) -> Option<Maps> {
    let t = ctx.table;
    let (cu, cv) = (t.column("u")?, t.column("v")?);
    let (us, vs) = (&t.columns[cu].values, &t.columns[cv].values);
    let width = us.iter().fold(0.0f64, |m, &u| m.max(u)) as usize + 1;
    let height = vs.iter().fold(0.0f64, |m, &v| m.max(v)) as usize + 1;
    let valid: Vec<f64> = (0..t.len()).filter(|&i| !t.missing(i)).map(|i| ctx.resid[i]).collect();
    if valid.is_empty() {
        return None;
    }
    let mut abs: Vec<f64> = valid.iter().map(|r| r.abs()).collect();
    abs.sort_by(|a, b| a.total_cmp(b));
    let scale = quantile_sorted(&abs, 0.95).max(3.0 * robust_sd(&valid)).max(1e-12);
    // Cells of `cell`×`cell` pixels, so the longer side has about MAP_SIDE cells.
    let cell = width.max(height).div_ceil(MAP_SIDE).max(1);
    let (pw, ph) = (width.div_ceil(cell), height.div_ceil(cell));
    let gap = 4;
    let iw = 3 * pw + 2 * gap;
    let mut units: Vec<usize> = t.unit.clone();
    units.sort_unstable();
    units.dedup();
    let mut maps = vec![];
    for &unit in units.iter().take(MAX_MAP_FRAMES) {
        // Per panel and cell: (sum, valid count, rows).
        let mut acc = vec![[(0.0f64, 0usize, 0usize); 3]; pw * ph];
        for i in (0..t.len()).filter(|&i| t.unit[i] == unit) {
            let k = (vs[i] as usize / cell).min(ph - 1) * pw + (us[i] as usize / cell).min(pw - 1);
            let vals = [ctx.resid[i], after[i].mu, ctx.resid[i] - after[i].mu];
            for (p, v) in vals.iter().enumerate() {
                let a = &mut acc[k][p];
                a.2 += 1;
                if !t.missing(i) && v.is_finite() {
                    a.0 += v;
                    a.1 += 1;
                }
            }
        }
        let mut rgb = vec![255u8; iw * ph * 3];
        for y in 0..ph {
            for x in 0..pw {
                for (p, a) in acc[y * pw + x].iter().enumerate() {
                    let c = match a {
                        (_, _, 0) => [200, 200, 200],
                        (_, 0, _) => [0, 0, 0],
                        (s, n, _) => diverging(s / *n as f64 / scale),
                    };
                    let o = (y * iw + p * (pw + gap) + x) * 3;
                    rgb[o..o + 3].copy_from_slice(&c);
                }
            }
        }
        let mut png = vec![];
        let enc = image::codecs::png::PngEncoder::new(&mut png);
        if image::ImageEncoder::write_image(enc, &rgb, iw as u32, ph as u32, image::ExtendedColorType::Rgb8).is_err() {
            continue;
        }
        let name = t.unit_names.get(unit).cloned().unwrap_or_else(|| unit.to_string());
        maps.push(ResidualMap { file: format!("frame{:03}_{}.png", maps.len() + 1, safe(&name)), unit: name, png });
    }
    Some(Maps { maps, scale })
}

/// Blue (−1) – white (0) – red (+1), clamped.
fn diverging(x: f64) -> [u8; 3] {
    let x = x.clamp(-1.0, 1.0);
    let fade = |a: f64| (255.0 * (1.0 - a)).round() as u8;
    if x >= 0.0 {
        [255, fade(x), fade(x)]
    } else {
        [fade(-x), fade(-x), 255]
    }
}

fn safe(s: &str) -> String {
    s.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}

/// Partial-residual plot of a bias finding without interaction: each valid row's residual
/// minus the extended model's held-out prediction plus this term (so the other terms and the
/// global bias are removed), binned medians along the covariate, and the fitted term.
pub(crate) fn partial_residual_svg(ctx: &Ctx, f: &Finding, col: usize, after: &[Pred], mm: bool) -> Option<String> {
    let form = f.fitted.as_ref()?;
    if f.target != "bias" || f.by.is_some() {
        return None;
    }
    let t = ctx.table;
    let c = &t.columns[col];
    let scale = if mm { 1000.0 } else { 1.0 };
    let mut pts: Vec<(f64, f64)> = (0..t.len())
        .filter(|&i| !t.missing(i))
        .map(|i| (c.values[i], (ctx.resid[i] - after[i].mu + form.eval(c.values[i])) * scale))
        .filter(|p| p.1.is_finite())
        .collect();
    if pts.len() < 10 {
        return None;
    }
    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
    let nb = if c.kind == ColumnKind::Categorical { 64 } else { 20 };
    let mut meds: Vec<(f64, f64)> = vec![];
    if c.kind == ColumnKind::Categorical {
        let mut i = 0;
        while i < pts.len() {
            let j = pts[i..].iter().position(|p| p.0 != pts[i].0).map_or(pts.len(), |k| i + k);
            meds.push((pts[i].0, median(&pts[i..j].iter().map(|p| p.1).collect::<Vec<_>>())));
            i = j;
        }
    } else {
        for b in 0..nb {
            let (s, e) = (b * pts.len() / nb, (b + 1) * pts.len() / nb);
            if e > s {
                let chunk = &pts[s..e];
                meds.push((chunk[chunk.len() / 2].0, median(&chunk.iter().map(|p| p.1).collect::<Vec<_>>())));
            }
        }
    }
    let (r0, r1) = col_range(ctx, col);
    let (x0, x1) = if r1 > r0 { (r0, r1) } else { (r0 - 1.0, r0 + 1.0) };
    let curve: Vec<(f64, f64)> = if c.kind == ColumnKind::Categorical {
        meds.iter().map(|m| (m.0, form.eval(m.0) * scale)).collect()
    } else {
        (0..=100).map(|k| x0 + (x1 - x0) * k as f64 / 100.0).map(|x| (x, form.eval(x) * scale)).collect()
    };
    let mut ys: Vec<f64> = pts.iter().map(|p| p.1).collect();
    ys.sort_by(|a, b| a.total_cmp(b));
    let (mut y0, mut y1) = (quantile_sorted(&ys, 0.02), quantile_sorted(&ys, 0.98));
    for y in meds.iter().chain(&curve).map(|p| p.1) {
        y0 = y0.min(y);
        y1 = y1.max(y);
    }
    if !(y1 > y0) {
        y0 -= 1.0;
        y1 += 1.0;
    }
    let pad = 0.08 * (y1 - y0);
    let (y0, y1) = (y0 - pad, y1 + pad);
    let area = PlotArea { x0, x1, y0, y1 };
    let (sx, sy) = (|x: f64| area.sx(x), |y: f64| area.sy(y));
    let ylab = format!("partial residual ({})", if mm { "mm" } else { "units" });
    let mut s = area.open(
        &format!("partial residual of bias ~ {}({}): binned medians (dots), fitted term (red)", f.form, esc(&f.covariate)),
        &esc(&f.covariate),
        &esc(&ylab),
    );
    let step = (pts.len() / 1500).max(1);
    for (x, y) in pts.iter().step_by(step) {
        if *y >= y0 && *y <= y1 {
            s += &format!("<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"1.2\" fill=\"#1f77b4\" fill-opacity=\"0.15\"/>\n", sx(*x), sy(*y));
        }
    }
    let line: Vec<String> = curve.iter().map(|(x, y)| format!("{:.1},{:.1}", sx(*x), sy(*y))).collect();
    s += &format!("<polyline points=\"{}\" fill=\"none\" stroke=\"#d62728\" stroke-width=\"2\"/>\n", line.join(" "));
    for (x, y) in &meds {
        s += &format!("<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"4\" fill=\"black\"/>\n", sx(*x), sy(*y));
    }
    s += "</svg>\n";
    Some(s)
}

/// A JSON value as table-cell text: numbers to 4 significant digits, objects inline.
fn cell(v: &Value) -> String {
    match v {
        Value::Null => "–".into(),
        Value::String(s) => s.clone(),
        Value::Number(n) => match n.as_f64() {
            Some(x) if n.is_f64() => sig(x),
            _ => n.to_string(),
        },
        Value::Object(m) => m.iter().map(|(k, v)| format!("{k}: {}", cell(v))).collect::<Vec<_>>().join(", "),
        Value::Array(a) => a.iter().map(cell).collect::<Vec<_>>().join(", "),
        Value::Bool(b) => b.to_string(),
    }
}

fn sig(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        return format!("{x}");
    }
    if x.abs() >= 1e5 || x.abs() < 1e-3 {
        format!("{x:.3e}")
    } else {
        let digits = (3 - x.abs().log10().floor() as i32).max(0) as usize;
        format!("{x:.digits$}")
    }
}

/// An array of records as a table (columns: the union of their keys, first-seen order).
fn records_table(id: &str, rows: &[Value]) -> String {
    let mut keys: Vec<String> = vec![];
    for r in rows {
        if let Value::Object(m) = r {
            for k in m.keys() {
                if !keys.contains(k) {
                    keys.push(k.clone());
                }
            }
        }
    }
    let mut s = format!("<table id=\"{id}\"><thead><tr>");
    for k in &keys {
        s += &format!("<th>{}</th>", esc(k));
    }
    s += "</tr></thead><tbody>\n";
    for r in rows {
        s += "<tr>";
        for k in &keys {
            s += &format!("<td>{}</td>", esc(&cell(r.get(k).unwrap_or(&Value::Null))));
        }
        s += "</tr>\n";
    }
    s + "</tbody></table>\n"
}

/// The mechanism section: the verdict, the accepted mechanisms (winner, runner-up, margin),
/// the comparison with the covariate findings, and every round's candidates.
fn mechanisms(m: &Value) -> String {
    let mut s = String::from("<h2>Physical mechanisms</h2>\n");
    s += &format!("<p id=\"mechanism-verdict\"><b>{}</b></p>\n", esc(m["verdict"].as_str().unwrap_or("")));
    if let Some(v) = m.get("versus_findings").filter(|v| v.is_object()) {
        s += &format!(
            "<p>Mechanisms against the covariate findings, held out: {} nats (p mechanisms better {}, p findings better {}).</p>\n",
            cell(&v["mechanisms_minus_findings"]),
            cell(&v["p_mechanisms_better"]),
            cell(&v["p_findings_better"])
        );
    }
    if let Some(sel) = m["selected"].as_array().filter(|a| !a.is_empty()) {
        s += &records_table("mechanisms-selected", sel);
    }
    // The comparison: every candidate of every round, one row each.
    let rows: Vec<Value> = m["rounds"]
        .as_array()
        .map(|rounds| {
            rounds
                .iter()
                .enumerate()
                .flat_map(|(r, round)| {
                    let chosen = round["selected"].as_str().map(str::to_string);
                    round["candidates"].as_array().cloned().unwrap_or_default().into_iter().map(move |mut c| {
                        let accepted = chosen.as_deref() == c["mechanism"].as_str();
                        if let Value::Object(o) = &mut c {
                            o.insert("round".into(), Value::from(r + 1));
                            o.insert("accepted".into(), Value::from(accepted));
                        }
                        c
                    })
                })
                .collect()
        })
        .unwrap_or_default();
    if !rows.is_empty() {
        s += "<h3>Mechanism comparison (every round's candidates)</h3>\n";
        s += &records_table("mechanism-comparison", &rows);
    }
    if let Some(c) = m.get("depth_correction").filter(|c| c.is_object()) {
        s += &depth_correction(c);
    }
    if let Some(p) = m.get("predictive_check").filter(|p| p.is_object()) {
        s += "<h3>Posterior predictive check</h3>\n";
        s += &format!("<p id=\"predictive-verdict\"><b>{}</b></p>\n", esc(p["verdict"].as_str().unwrap_or("")));
        s += &format!("<p>{}</p>\n", esc(p["method"].as_str().unwrap_or("")));
        if let Some(rows) = p["rows"].as_array().filter(|a| !a.is_empty()) {
            s += &records_table("predictive-check", rows);
        }
    }
    s
}

/// What `depth_correction.json` corrects, and what not (with the reason).
fn depth_correction(c: &Value) -> String {
    let mut s = String::from("<h3>Depth correction (<a href=\"depth_correction.json\">depth_correction.json</a>)</h3>\n");
    let list = |k: &str| c[k].as_array().cloned().unwrap_or_default();
    let corr = list("corrections");
    s += &format!(
        "<p id=\"depth-correction\">{}</p>\n",
        if corr.is_empty() {
            "Nothing to correct: no accepted mechanism can be undone on a depth image.".to_string()
        } else {
            format!("Corrected: {}.", esc(&corr.iter().map(cell).collect::<Vec<_>>().join("; ")))
        }
    );
    let not = list("not_corrected");
    if !not.is_empty() {
        let rows: Vec<Value> =
            not.iter().map(|n| serde_json::json!({"not corrected": n["fitted"].clone(), "reason": n["reason"].clone()})).collect();
        s += &records_table("not-corrected", &rows);
    }
    for n in list("notes") {
        s += &format!("<p>{}</p>\n", esc(n.as_str().unwrap_or("")));
    }
    s
}

/// The page. `plots` are file names under `plots/`; maps under `maps/`.
pub(crate) fn page(report: &Report, plots: &[String], maps: Option<&Maps>) -> String {
    let json = serde_json::to_value(report).unwrap_or(Value::Null);
    let mm = report.data["value_unit"] == "m";
    let mut s = String::from(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\n<title>recon audit</title>\n<style>\n\
         body{font-family:sans-serif;margin:2em;max-width:1400px}table{border-collapse:collapse;margin:1em 0}\
         td,th{border:1px solid #bbb;padding:3px 8px;text-align:left;font-size:13px;vertical-align:top}\
         th{background:#eee}pre{background:#f6f6f6;padding:1em;white-space:pre-wrap}figure{display:inline-block;margin:0.5em}\
         figcaption{font-size:12px}\n</style></head><body>\n",
    );
    s += &format!("<h1>recon audit ({}): {}</h1>\n", esc(&report.kind), esc(report.data["source"].as_str().unwrap_or("")));
    s += &format!("<h2>Summary</h2>\n<pre id=\"summary\">{}</pre>\n", esc(&report.summary()));

    s += "<h2>Findings</h2>\n";
    if report.findings.is_empty() {
        s += "<p id=\"no-findings\">No effect is significant on held-out units.</p>\n";
    } else {
        s += "<table id=\"findings\"><thead><tr><th>#</th><th>target</th><th>covariate</th><th>form</th><th>parameters</th>\
              <th>standard errors</th><th>held-out gain (nats/pixel)</th><th>folds better</th><th>p (family-wise)</th><th>cause</th>\
              <th>explained by mechanism</th></tr></thead><tbody>\n";
        for (i, f) in report.findings.iter().enumerate() {
            let cov = match &f.by {
                Some(b) => format!("{} × {b}", f.covariate),
                None => f.covariate.clone(),
            };
            s += &format!(
                "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>\n",
                i + 1,
                esc(&f.target),
                esc(&cov),
                esc(&f.form),
                esc(&cell(&f.parameters)),
                esc(&cell(&f.standard_errors)),
                sig(f.heldout_gain),
                esc(&f.folds_improved),
                sig(f.p_value),
                esc(&f.cause),
                esc(f.explained_by.as_deref().unwrap_or("–"))
            );
        }
        s += "</tbody></table>\n";
    }

    if let Some(m) = json.get("mechanisms").filter(|m| m.is_object()) {
        s += &mechanisms(m);
    }

    s += "<h2>Held out, before and after</h2>\n<table id=\"before-after\"><thead><tr><th>metric</th><th>input simulation</th>\
          <th>baseline refit</th><th>extended model</th></tr></thead><tbody>\n";
    let input = serde_json::to_value(&report.input).unwrap_or(Value::Null);
    let (b, a) = (&report.baseline["heldout"], &report.after["heldout"]);
    let unit = |k: &str| if mm && ["rmse", "robust_sd", "bias_error", "noise_error"].contains(&k) { " (mm)" } else { "" };
    for k in ["rmse", "robust_sd", "loglik_per_row", "bias_error", "noise_error", "missing_rate", "missing_rate_error"] {
        let f = |v: &Value| match v.get(k).and_then(Value::as_f64) {
            Some(x) if !unit(k).is_empty() => sig(1000.0 * x),
            Some(x) => sig(x),
            None => "–".into(),
        };
        s += &format!("<tr><td>{k}{}</td><td>{}</td><td>{}</td><td>{}</td></tr>\n", unit(k), f(&input), f(b), f(a));
    }
    s += "</tbody></table>\n";

    // Further sections that are arrays of records (the mechanism comparison, the downstream
    // before/after): tables, whatever their fields.
    if let Value::Object(m) = &json {
        for (k, v) in m {
            if ["findings", "rounds", "data", "method", "baseline", "after", "input", "outliers", "mechanisms"].contains(&k.as_str()) {
                continue;
            }
            if let Value::Array(rows) = v {
                if !rows.is_empty() && rows.iter().all(Value::is_object) {
                    s += &format!("<h2>{}</h2>\n{}", esc(&k.replace('_', " ")), records_table(k, rows));
                }
            }
        }
    }

    if let Some(o) = json.get("outliers").and_then(|o| o.get("dependence")).and_then(Value::as_array) {
        if !o.is_empty() {
            s += &format!("<h2>Outlier structure</h2>\n{}", records_table("outliers", o));
        }
    }

    if !plots.is_empty() {
        s += "<h2>Findings along their covariates</h2>\n<div id=\"plots\">\n";
        for p in plots {
            s += &format!(
                "<figure><img src=\"plots/{0}\" alt=\"{0}\" width=\"640\" height=\"400\"><figcaption>{0}</figcaption></figure>\n",
                esc(p)
            );
        }
        s += "</div>\n";
    }

    if let Some(m) = maps.filter(|m| !m.maps.is_empty()) {
        let v = if mm { format!("{:.2} mm", 1000.0 * m.scale) } else { sig(m.scale) };
        s += &format!(
            "<h2>Residual maps</h2>\n<p>Per frame, left to right: measured − simulated; the extended model's predicted residual \
             (held out); what remains. Red positive (farther than simulated), blue negative, full colour at ±{v}; grey: no sampled \
             pixel; black: missing returns.</p>\n<div id=\"maps\">\n"
        );
        for r in &m.maps {
            s += &format!(
                "<figure><img src=\"maps/{}\" alt=\"residual map {}\"><figcaption>{}</figcaption></figure>\n",
                esc(&r.file),
                esc(&r.unit),
                esc(&r.unit)
            );
        }
        s += "</div>\n";
    }
    s += "<p>Machine-readable: <a href=\"report.json\">report.json</a>.</p>\n</body></html>\n";
    s
}
