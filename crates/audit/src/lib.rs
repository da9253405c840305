//! `recon audit`: compare measured with simulated data, find what the simulation
//! gets wrong, name the cause, extend the sensor model and measure the gain.
//!
//! - `table`: the residual table (measured, simulated, missing, unit, covariates);
//! - `depth`: building it from a BOP / YCB-Video dataset and a sensor model;
//! - `fit`: the residual model and its maximum-likelihood fit;
//! - `search`: candidate effects, held-out testing by unit, greedy selection;
//! - `mechanism`: which physical sensor mechanism explains the frames (fitted on the images);
//! - `outliers`: is the fit's outlier component structured (rate and sign by covariate)?
//! - `predictive`: posterior predictive check of the fitted mechanisms (simulated vs measured residual statistics);
//! - `report`: report JSON (schema in its docs), summary, plots; `cause`: the words;
//! - `stats`: t / χ² tails, robust statistics, a small SPD solver.

// Clippy lints allowed crate-wide, for the reasons given in recon-core's lib.rs.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord, clippy::too_many_arguments, clippy::type_complexity)]
#![warn(missing_docs)]
pub(crate) mod cause;
pub(crate) mod depth;
pub(crate) mod fit;
pub(crate) mod html;
pub(crate) mod mechanism;
pub(crate) mod outliers;
pub(crate) mod predictive;
pub(crate) mod report;
pub(crate) mod search;
pub(crate) mod stats;
pub(crate) mod svg;
pub(crate) mod table;
pub use self::depth::{collect, quantisation_sd, residual_table, DepthOptions, PixelSample};
pub use self::mechanism::{free_params, Candidate, Explained, MechFinding, MechRound, MechanismOptions, MechanismReport, Versus};
pub use self::predictive::{CheckRow, PredictiveCheck};
pub use self::search::{Round, SearchOptions, SearchResult, Selected, Uncertainty};
pub use self::table::ResidualTable;

use fit::Ctx;
use recon_core::sensor::SensorModel;
use recon_core::{Error, Result};
use report::{InputPrediction, Report};
use std::path::{Path, PathBuf};

/// A finished audit: the report, the extended sensor model (depth audits) and the plots
/// (file name, SVG text).
pub struct Audit {
    /// The report (serialised to `report.json`).
    pub report: Report,
    /// The sensor model extended with the selected effects (depth audits only).
    pub extended: Option<SensorModel>,
    /// Plots as (file name, SVG text).
    pub plots: Vec<(String, String)>,
    /// Residual maps per frame for `report.html` (depth audits).
    pub(crate) maps: Option<html::Maps>,
}

/// Audits any table of measured vs simulated values (`recon audit table`).
pub fn audit_table(table: &ResidualTable, opts: &SearchOptions) -> Result<Audit> {
    run(table, opts, "table", None)
}

/// Audits a depth residual table built against `model` (`recon audit depth`): findings
/// become effects of the extended model.
pub fn audit_depth(table: &ResidualTable, opts: &SearchOptions, model: &SensorModel) -> Result<Audit> {
    run(table, opts, "depth", Some(model))
}

/// [`audit_depth`] plus the mechanism inference on the frames' simulated images
/// (`frames[i]` is the frame whose `frame` covariate is i; see [`collect`]): the report's
/// `mechanisms` section, and each covariate finding says which mechanism explains it.
pub fn audit_depth_frames(
    table: &ResidualTable,
    opts: &SearchOptions,
    model: &SensorModel,
    frames: &[recon_core::sensor::SimFrame],
    mopts: &MechanismOptions,
) -> Result<Audit> {
    run_with(table, opts, "depth", Some(model), Some((frames, mopts)))
}

/// The mechanism inference alone (no covariate search): what `audit_depth_frames`
/// reports under `mechanisms`, without the comparison with covariate findings.
pub fn infer_mechanisms(
    table: &ResidualTable,
    opts: &SearchOptions,
    frames: &[recon_core::sensor::SimFrame],
    mopts: &MechanismOptions,
) -> Result<MechanismReport> {
    let ctx = Ctx::new(table, opts.robust);
    mechanism::infer(&ctx, frames, opts, mopts, None)
}

fn run(table: &ResidualTable, opts: &SearchOptions, kind: &str, model: Option<&SensorModel>) -> Result<Audit> {
    run_with(table, opts, kind, model, None)
}

fn run_with(
    table: &ResidualTable,
    opts: &SearchOptions,
    kind: &str,
    model: Option<&SensorModel>,
    frames: Option<(&[recon_core::sensor::SimFrame], &MechanismOptions)>,
) -> Result<Audit> {
    let ctx = Ctx::new(table, opts.robust);
    let res = search::search(&ctx, opts)?;
    let input = InputPrediction { noise: model.map(|m| m.noise_m), dropout: model.map(|m| m.dropout) };
    let mut built = report::build(&ctx, &res, opts, kind, &input, model.is_some());
    if let Some((frames, mopts)) = frames {
        let terms: Vec<fit::Term> = res.selected.iter().map(|s| s.evidence.term).collect();
        let unit_ll: Vec<f64> = res.final_cv.unit_ll_gauss.iter().zip(&res.final_cv.unit_ll_bern).map(|(a, b)| a + b).collect();
        let mut m = mechanism::infer(&ctx, frames, opts, mopts, Some((terms.as_slice(), unit_ll.as_slice())))?;
        // Point each finding at its mechanism; index the report's (sorted) findings.
        for e in &mut m.findings_explained {
            if let Some(pos) = built.report.findings.iter().position(|f| f.term_index == e.finding) {
                built.report.findings[pos].explained_by =
                    Some(e.explained_by.clone().unwrap_or_else(|| "none of the fitted mechanisms".into()));
                e.finding = pos;
            }
        }
        built.report.mechanisms = Some(m);
    }
    let extended = model.map(|m| {
        let full = res.final_cv.full();
        let mut e = m.clone();
        e.name = if m.name.is_empty() { "audited".into() } else { format!("{} (audited)", m.name) };
        e.bias_m += full.bias;
        e.noise_m = full.noise(&ctx);
        e.dropout = full.dropout.clamp(0.0, 1.0);
        for f in &built.report.findings {
            if let Some(eff) = &f.effect {
                e.effects.push(eff.clone());
            }
        }
        e
    });
    let mm = table.value_unit == "m";
    let plots = built
        .report
        .findings
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let col = table.column(&f.covariate).expect("finding column exists");
            let by = f.by.as_ref().map(|b| format!("_x_{b}")).unwrap_or_default();
            (
                format!("finding{}_{}_{}_{}{by}.svg", i + 1, f.target, f.form, safe(&f.covariate)),
                report::finding_svg(&ctx, f, col, &built.before, &built.after, mm),
            )
        })
        .collect::<Vec<_>>();
    let partials: Vec<(String, String)> = built
        .report
        .findings
        .iter()
        .enumerate()
        .filter_map(|(i, f)| {
            let col = table.column(&f.covariate)?;
            let svg = html::partial_residual_svg(&ctx, f, col, &built.after, mm)?;
            Some((format!("partial{}_{}_{}_{}.svg", i + 1, f.target, f.form, safe(&f.covariate)), svg))
        })
        .collect();
    let plots = plots.into_iter().chain(partials).collect();
    let maps = html::residual_maps(&ctx, &built.after);
    Ok(Audit { report: built.report, extended, plots, maps })
}

fn safe(s: &str) -> String {
    s.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}

/// The depth correction a depth audit with mechanisms writes beside `report.json`
/// (`recon infer --depth-correction`, `recon eval --depth-correction`).
pub const CORRECTION_FILE: &str = "depth_correction.json";

/// Marker written last into an audit output folder.
pub const MARKER: &str = "recon-audit.json";

/// Writes `report.json`, `summary.txt`, `report.html`, `sensor_extended.json` (depth),
/// `depth_correction.json` (depth audits with mechanisms), the
/// plots and the residual maps (depth) into `out` through a staging folder (an interrupted run leaves no complete-looking
/// output; an existing folder is replaced only if it is an earlier audit output), and
/// the report JSON also to `json` when given. Sets the report's `extended_model`.
pub fn write_outputs(audit: &mut Audit, out: &Path, json: Option<&Path>) -> Result<Vec<PathBuf>> {
    if out.exists() {
        let empty = std::fs::read_dir(out).map(|mut d| d.next().is_none()).unwrap_or(false);
        if !empty && !out.join(MARKER).exists() {
            return Err(Error::input(
                out.display().to_string(),
                format!("output folder exists and is not a recon audit output (no {MARKER}); remove it or choose another --out"),
            ));
        }
    }
    let staging = out.with_extension("partial");
    if staging.exists() {
        std::fs::remove_dir_all(&staging).map_err(|e| Error::io(&staging, e))?;
    }
    std::fs::create_dir_all(staging.join("plots")).map_err(|e| Error::io(&staging, e))?;
    let mut written = vec![];
    if let Some(m) = &audit.extended {
        m.save(&staging.join("sensor_extended.json"))?;
        let p = out.join("sensor_extended.json");
        audit.report.extended_model = Some(p.display().to_string());
        written.push(p);
    }
    if let Some(m) = &audit.report.mechanisms {
        m.depth_correction.save(&staging.join(CORRECTION_FILE))?;
        written.push(out.join(CORRECTION_FILE));
    }
    let text = serde_json::to_string_pretty(&audit.report).map_err(|e| Error::msg(e.to_string()))?;
    let put = |name: &str, body: &str| -> Result<()> {
        let p = staging.join(name);
        std::fs::write(&p, body).map_err(|e| Error::io(&p, e))
    };
    put("report.json", &text)?;
    put("summary.txt", &audit.report.summary())?;
    written.push(out.join("report.json"));
    written.push(out.join("summary.txt"));
    for (name, svg) in &audit.plots {
        put(&format!("plots/{name}"), svg)?;
        written.push(out.join("plots").join(name));
    }
    if let Some(m) = &audit.maps {
        std::fs::create_dir_all(staging.join("maps")).map_err(|e| Error::io(&staging, e))?;
        for r in &m.maps {
            let p = staging.join("maps").join(&r.file);
            std::fs::write(&p, &r.png).map_err(|e| Error::io(&p, e))?;
            written.push(out.join("maps").join(&r.file));
        }
    }
    let names: Vec<String> = audit.plots.iter().map(|p| p.0.clone()).collect();
    put("report.html", &html::page(&audit.report, &names, audit.maps.as_ref()))?;
    written.push(out.join("report.html"));
    put(MARKER, &serde_json::json!({"report": "report.json", "files": written}).to_string())?;
    if out.exists() {
        std::fs::remove_dir_all(out).map_err(|e| Error::io(out, e))?;
    }
    std::fs::rename(&staging, out).map_err(|e| Error::io(out, e))?;
    if let Some(j) = json {
        let tmp = j.with_extension("json.partial");
        std::fs::write(&tmp, &text).map_err(|e| Error::io(&tmp, e))?;
        std::fs::rename(&tmp, j).map_err(|e| Error::io(j, e))?;
        written.push(j.to_path_buf());
    }
    Ok(written)
}
