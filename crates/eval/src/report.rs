//! Prediction files, [`evaluate`], and the report (JSON, text table, SVG plot).
//!
//! # Predictions file (JSON)
//! ```json
//! { "predictions": [
//!   { "scene": "000048", "frame": 1, "obj_id": 1,
//!     "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0.01, -0.02, 0.7], "scale": 0.12,
//!     "mesh": "meshes/000048_000001_obj1.ply", "gt_index": 0 } ] }
//! ```
//! - The predicted surface in the camera frame is `R · (scale · v) + t` for the vertices `v`
//!   of `mesh` (a PLY; relative paths are resolved against the predictions file's folder).
//!   `t` is in **metres**; `scale` is unitless (> 0, default 1).
//! - `mesh` may be omitted: the prediction is then pose-only and uses the GT model.
//! - `gt_index` (optional) picks the GT instance by its position in the frame's annotation
//!   list; without it, `obj_id` must be unique in the frame.
//! - ADD / ADD-S use the GT model points with the predicted `(R, t)` only (scale ignored):
//!   they are meaningful when the prediction's frame is the GT model frame.
//! - `model_frame` (optional, default `true`): `false` says the mesh lives in a frame of
//!   the prediction's own choosing (e.g. the `observed` baseline's bounding-box frame), so
//!   `(R, t)` is a placement, not a 6D pose of the GT model: ADD / ADD-S are then not
//!   defined and reported as `null` ("-" in the table); the surface metrics are unaffected.
//!
//! # What is evaluated
//! Every GT instance of every frame that has at least one prediction (with
//! [`EvalOptions::all_frames`], of every frame of the dataset). A GT instance without a
//! prediction is *missed*: it counts as a failure in all success rates and is left out of
//! the means.

use crate::icp::IcpOptions;
use crate::metrics::{self, occlusion_bin, occlusion_bin_label, F1Score, OCCLUSION_BINS};
use recon_core::dataset::bop::{load_dataset, Dataset, GtInstance, Model};
use recon_core::dataset::ply::read_ply;
use recon_core::math::Similarity;
use recon_core::mesh::post::{mesh_quality, MeshQuality};
use recon_core::mesh::trimesh::{diameter, TriMesh};
use recon_core::mesh::Mesh;
use recon_core::spatial::P3;
use recon_core::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
/// A predictions file (format in the module docs).
pub struct PredictionsFile {
    /// All predictions, any order.
    pub predictions: Vec<Prediction>,
}

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
/// One predicted object in one frame: pose, scale and optional mesh.
pub struct Prediction {
    /// BOP scene id (e.g. `"000048"`).
    pub scene: String,
    /// Frame (image) id within the scene.
    pub frame: u32,
    /// BOP object id.
    pub obj_id: u32,
    #[serde(default)]
    /// Position of the GT instance in the frame's annotation list (needed when `obj_id` repeats).
    pub gt_index: Option<usize>,
    #[serde(rename = "R")]
    /// Rotation, row-major (JSON key `R`).
    pub r: [[f64; 3]; 3],
    /// Metres.
    pub t: [f64; 3],
    #[serde(default = "one")]
    /// Uniform scale of the mesh (unitless, > 0, default 1).
    pub scale: f64,
    #[serde(default)]
    /// Predicted mesh (PLY; relative to the predictions file); `None`: pose only, GT model used.
    pub mesh: Option<PathBuf>,
    /// Whether `(R, t)` maps the GT model frame (module docs).
    #[serde(default = "yes")]
    pub model_frame: bool,
}

fn one() -> f64 {
    1.0
}

fn yes() -> bool {
    true
}

/// Reads and validates a predictions file (structure, finite values, orthonormal R with
/// det +1 to 1e-3, positive scale). Errors name the file and the field.
pub fn read_predictions(path: &Path) -> Result<PredictionsFile> {
    let s = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let p: PredictionsFile = serde_json::from_str(&s).map_err(|e| Error::Json { path: path.to_path_buf(), source: e })?;
    let file = path.display().to_string();
    for (i, pr) in p.predictions.iter().enumerate() {
        let f = |n: &str| format!("predictions[{i}].{n}");
        let rr = &pr.r;
        if rr.iter().flatten().any(|x| !x.is_finite()) {
            return Err(Error::config(&file, f("R"), "non-finite value"));
        }
        let mut worst: f64 = 0.0;
        for a in 0..3 {
            for b in 0..3 {
                let d: f64 = (0..3).map(|k| rr[a][k] * rr[b][k]).sum();
                worst = worst.max((d - if a == b { 1.0 } else { 0.0 }).abs());
            }
        }
        let det = rr[0][0] * (rr[1][1] * rr[2][2] - rr[1][2] * rr[2][1]) - rr[0][1] * (rr[1][0] * rr[2][2] - rr[1][2] * rr[2][0])
            + rr[0][2] * (rr[1][0] * rr[2][1] - rr[1][1] * rr[2][0]);
        if worst > 1e-3 || det < 0.0 {
            return Err(Error::config(&file, f("R"), format!("not a rotation (|R Rᵀ − I| = {worst:.2e}, det = {det:.4})")));
        }
        if pr.t.iter().any(|x| !x.is_finite()) {
            return Err(Error::config(&file, f("t"), "non-finite value"));
        }
        if !(pr.scale.is_finite() && pr.scale > 0.0) {
            return Err(Error::config(&file, f("scale"), format!("{} is not a positive number", pr.scale)));
        }
    }
    Ok(p)
}

#[derive(Debug, Clone, Copy, Serialize)]
/// Settings of an evaluation (recorded in the report).
pub struct EvalOptions {
    /// Surface samples per mesh (GT point-cloud models use their points, up to this many).
    pub n_samples: usize,
    /// Sampling seed (GT and prediction both use it, so identical inputs give 0 exactly).
    pub seed: u64,
    /// F1 distance threshold as a fraction of the GT diameter.
    pub f1_tau_rel: f64,
    /// Score every frame of the dataset, not only frames with a prediction (a method that
    /// ran on every frame must not escape its misses by skipping a whole frame).
    pub all_frames: bool,
    /// Only GT instances whose occlusion (percent, `1 − visib_fract`) lies in `[lo, hi)`;
    /// instances without a visibility annotation are left out too.
    pub occlusion: Option<[f64; 2]>,
    #[serde(skip)]
    /// ICP settings of the aligned metrics (not serialised).
    pub icp: IcpOptions,
}

/// Whether GT instance `g` is inside an occlusion range (percent, `[lo, hi)`; `None`: all).
pub fn in_occlusion(g: &GtInstance, range: Option<[f64; 2]>) -> bool {
    match range {
        None => true,
        Some([lo, hi]) => g.visib_fract.map(|v| (1.0 - v) * 100.0).is_some_and(|o| o >= lo && o < hi),
    }
}

impl Default for EvalOptions {
    fn default() -> Self {
        EvalOptions { n_samples: 10_000, seed: 0, f1_tau_rel: 0.05, all_frames: false, occlusion: None, icp: IcpOptions::default() }
    }
}

/// All metrics of one GT instance. Distances in metres; `_norm` values are / GT diameter.
#[derive(Debug, Clone, Serialize)]
pub struct ObjectResult {
    pub scene: String,
    pub frame: u32,
    pub obj_id: u32,
    pub gt_index: usize,
    pub model: String,
    pub visib_fract: Option<f64>,
    /// `visib_fract` is an estimate (dataset without visibility annotation).
    pub visib_estimated: bool,
    /// Occlusion in percent (1 − visib_fract).
    pub occlusion_pct: Option<f64>,
    pub occlusion_bin: Option<String>,
    pub gt_diameter: f64,
    /// `None` when the instance has no prediction (missed).
    pub metrics: Option<ObjectMetrics>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ObjectMetrics {
    /// ADD family: `None` when the prediction is not in the model frame (`model_frame: false`).
    pub add: Option<f64>,
    pub add_s: Option<f64>,
    pub add_norm: Option<f64>,
    pub add_s_norm: Option<f64>,
    pub add_sb: f64,
    pub add_sb_norm: f64,
    pub add_sb_success_10: bool,
    pub add_sb_success_05: bool,
    pub cd_norm: f64,
    pub icp_iters: usize,
    pub icp_converged: bool,
    pub pred_diameter: f64,
    pub dre: f64,
    pub dre_success_05: bool,
    /// F1 of the posed surfaces (same correspondence as ADD-SB).
    pub f1_posed: F1Score,
    /// F1 after the CD_norm ICP alignment (shape only).
    pub f1_aligned: F1Score,
    /// Normal consistency after the CD_norm alignment (surface quality; `None`
    /// for a prediction without faces).
    pub normal_consistency: Option<f64>,
    /// Surface quality of the predicted and of the GT mesh (components, dihedral angles, holes).
    pub mesh_quality: Option<MeshQuality>,
    pub gt_mesh_quality: Option<MeshQuality>,
}

/// Aggregates over a set of GT instances. Rates are fractions in [0, 1] over all
/// instances (missed = failure); means are over predicted instances (NaN if none).
/// ADD rates leave out predictions that are not in the model frame (NaN if no instance
/// remains).
#[derive(Debug, Clone, Serialize, Default)]
pub struct Summary {
    pub label: String,
    pub n_gt: usize,
    pub n_missed: usize,
    pub add_sb_norm_mean: f64,
    pub add_sb_10: f64,
    pub add_sb_05: f64,
    pub cd_norm_mean: f64,
    pub dre_mean: f64,
    pub dre_05: f64,
    pub f1_posed_mean: f64,
    pub f1_aligned_mean: f64,
    /// Over the predictions with faces.
    pub normal_consistency_mean: f64,
    /// Mean dihedral angle (degrees) of the predicted meshes and of their GT meshes.
    pub dihedral_deg_mean: f64,
    pub gt_dihedral_deg_mean: f64,
    /// Fraction of predicted meshes with one component.
    pub one_component: f64,
    pub add_10: f64,
    pub add_s_10: f64,
}

impl Summary {
    fn of(label: String, objs: &[&ObjectResult]) -> Summary {
        let ms: Vec<&ObjectMetrics> = objs.iter().filter_map(|o| o.metrics.as_ref()).collect();
        let n = objs.len();
        let mean = |f: &dyn Fn(&ObjectMetrics) -> f64| {
            if ms.is_empty() {
                f64::NAN
            } else {
                ms.iter().map(|m| f(m)).sum::<f64>() / ms.len() as f64
            }
        };
        // Means over the predictions that have the value.
        let mean_some = |f: &dyn Fn(&ObjectMetrics) -> Option<f64>| {
            let v: Vec<f64> = ms.iter().filter_map(|m| f(m)).filter(|x| x.is_finite()).collect();
            if v.is_empty() {
                f64::NAN
            } else {
                v.iter().sum::<f64>() / v.len() as f64
            }
        };
        let rate =
            |f: &dyn Fn(&ObjectMetrics) -> bool| if n == 0 { f64::NAN } else { ms.iter().filter(|m| f(m)).count() as f64 / n as f64 };
        // ADD needs model-frame predictions; a method that never gives one has no ADD
        // rate at all (its misses must not turn into a 0 %).
        let with_add = ms.iter().filter(|m| m.add.is_some()).count();
        let n_add = if with_add == 0 { 0 } else { with_add + (n - ms.len()) };
        let add_rate = |f: &dyn Fn(&ObjectMetrics) -> Option<f64>| {
            if n_add == 0 {
                f64::NAN
            } else {
                ms.iter().filter(|m| f(m).is_some_and(|x| x < 0.1)).count() as f64 / n_add as f64
            }
        };
        Summary {
            label,
            n_gt: n,
            n_missed: n - ms.len(),
            add_sb_norm_mean: mean(&|m| m.add_sb_norm),
            add_sb_10: rate(&|m| m.add_sb_success_10),
            add_sb_05: rate(&|m| m.add_sb_success_05),
            cd_norm_mean: mean(&|m| m.cd_norm),
            dre_mean: mean(&|m| m.dre),
            dre_05: rate(&|m| m.dre_success_05),
            f1_posed_mean: mean(&|m| m.f1_posed.f1),
            f1_aligned_mean: mean(&|m| m.f1_aligned.f1),
            normal_consistency_mean: mean_some(&|m| m.normal_consistency),
            dihedral_deg_mean: mean_some(&|m| m.mesh_quality.map(|q| q.mean_dihedral_deg)),
            gt_dihedral_deg_mean: mean_some(&|m| m.gt_mesh_quality.map(|q| q.mean_dihedral_deg)),
            one_component: {
                let q: Vec<_> = ms.iter().filter_map(|m| m.mesh_quality).collect();
                if q.is_empty() {
                    f64::NAN
                } else {
                    q.iter().filter(|q| q.components == 1).count() as f64 / q.len() as f64
                }
            },
            add_10: add_rate(&|m| m.add_norm),
            add_s_10: add_rate(&|m| m.add_s_norm),
        }
    }
}

#[derive(Debug, Clone, Serialize)]
/// An evaluation report: settings, overall and per-occlusion summaries, per-object rows.
pub struct Report {
    /// Dataset folder evaluated.
    pub dataset: String,
    /// Predictions file evaluated.
    pub predictions: String,
    /// Settings used.
    pub options: EvalOptions,
    /// Summary over every evaluated GT instance.
    pub overall: Summary,
    /// One row per occlusion bin, then `>70%` and `unknown` rows when non-empty.
    pub by_occlusion: Vec<Summary>,
    /// Metrics of every evaluated GT instance.
    pub objects: Vec<ObjectResult>,
}

fn pose_of(g: &GtInstance) -> Similarity {
    Similarity::rigid(g.r, g.t)
}

fn eval_one(model: &Model, g: &GtInstance, pred: &Prediction, pred_mesh: &TriMesh, opts: &EvalOptions) -> ObjectMetrics {
    let d = model.diameter;
    let gt_pose = pose_of(g);
    let est_rt = Similarity::rigid(pred.r, pred.t);
    // ADD / ADD-S: GT model points (vertices, or the point cloud) under both poses.
    let (add, add_s) = if pred.model_frame {
        let model_pts = model.mesh.used_vertices();
        (Some(metrics::add(&model_pts, &gt_pose, &est_rt)), Some(metrics::add_s(&model_pts, &gt_pose, &est_rt)))
    } else {
        (None, None)
    };
    // Surfaces in the camera frame.
    let (gt_local, gt_faces) = model.mesh.sample_surface_faces(opts.n_samples, opts.seed);
    let gt_s: Vec<P3> = gt_pose.apply_all(&gt_local);
    let est_full = Similarity { rotation: pred.r, translation: pred.t, scale: pred.scale };
    let (pr_local, pr_faces) = pred_mesh.sample_surface_faces(opts.n_samples, opts.seed);
    let pr_s: Vec<P3> = est_full.apply_all(&pr_local);
    let tau = opts.f1_tau_rel * d;
    let posed = metrics::nn_dists(&pr_s, &gt_s);
    let add_sb = posed.chamfer();
    let (cd_norm, icp) = metrics::cd_norm(&pr_s, &gt_s, d, &opts.icp);
    let pr_aligned = icp.transform.apply_all(&pr_s);
    let aligned = metrics::nn_dists(&pr_aligned, &gt_s);
    // Face normals rotated like the samples (scales are positive, so they keep their direction).
    let normals = |m: &TriMesh, faces: &[u32], r: &[[f64; 3]; 3]| -> Vec<P3> {
        faces
            .iter()
            .map(|&f| if f == u32::MAX { [0.0; 3] } else { Similarity::rigid(*r, [0.0; 3]).apply(&m.face_normal(f as usize)) })
            .collect()
    };
    let r_pred = recon_core::math::matmul(&icp.transform.rotation, &pred.r);
    let normal_consistency =
        metrics::normal_consistency(&pr_aligned, &normals(pred_mesh, &pr_faces, &r_pred), &gt_s, &normals(&model.mesh, &gt_faces, &g.r));
    let pred_diameter = diameter(&pred_mesh.used_vertices()).0 * pred.scale;
    let dre = metrics::dre(pred_diameter, d);
    ObjectMetrics {
        add,
        add_s,
        add_norm: add.map(|a| a / d),
        add_s_norm: add_s.map(|a| a / d),
        add_sb,
        add_sb_norm: add_sb / d,
        add_sb_success_10: add_sb < 0.1 * d,
        add_sb_success_05: add_sb < 0.05 * d,
        cd_norm,
        icp_iters: icp.iters,
        icp_converged: icp.converged,
        pred_diameter,
        dre,
        dre_success_05: dre < 0.05,
        f1_posed: posed.f1(tau),
        f1_aligned: aligned.f1(tau),
        normal_consistency,
        mesh_quality: mesh_quality(&Mesh::from(pred_mesh)),
        gt_mesh_quality: mesh_quality(&Mesh::from(&model.mesh)),
    }
}

/// Computes every metric for every GT instance of the frames that have predictions.
/// `pred_file` is used for error messages and to resolve relative mesh paths.
pub fn evaluate(ds: &Dataset, preds: &PredictionsFile, pred_file: &Path, opts: &EvalOptions) -> Result<Report> {
    let file = pred_file.display().to_string();
    let base = pred_file.parent().map(Path::to_path_buf).unwrap_or_default();
    // Match predictions to GT instances.
    let mut matched: BTreeMap<(String, u32), HashMap<usize, usize>> = BTreeMap::new();
    if opts.all_frames {
        for f in &ds.frames {
            matched.insert((f.scene.clone(), f.frame), HashMap::new());
        }
    }
    for (i, p) in preds.predictions.iter().enumerate() {
        let field = |n: &str| format!("predictions[{i}].{n}");
        let fr = ds
            .frame(&p.scene, p.frame)
            .ok_or_else(|| Error::config(&file, field("frame"), format!("scene `{}` frame {} is not in the dataset", p.scene, p.frame)))?;
        let gi = match p.gt_index {
            Some(k) => {
                if fr.gt.get(k).map(|g| g.obj_id) != Some(p.obj_id) {
                    return Err(Error::config(
                        &file,
                        field("gt_index"),
                        format!("GT instance {k} of that frame is not obj_id {}", p.obj_id),
                    ));
                }
                k
            }
            None => {
                let c: Vec<usize> = fr.gt.iter().enumerate().filter(|(_, g)| g.obj_id == p.obj_id).map(|(k, _)| k).collect();
                match c.as_slice() {
                    [k] => *k,
                    [] => {
                        return Err(Error::config(
                            &file,
                            field("obj_id"),
                            format!("obj_id {} is not annotated in scene `{}` frame {}", p.obj_id, p.scene, p.frame),
                        ))
                    }
                    _ => {
                        return Err(Error::config(
                            &file,
                            field("gt_index"),
                            format!("obj_id {} occurs {} times in that frame; give gt_index", p.obj_id, c.len()),
                        ))
                    }
                }
            }
        };
        let m = matched.entry((p.scene.clone(), p.frame)).or_default();
        if let Some(prev) = m.insert(gi, i) {
            return Err(Error::config(&file, field("obj_id"), format!("same GT instance as predictions[{prev}]")));
        }
    }
    let mut mesh_cache: HashMap<PathBuf, TriMesh> = HashMap::new();
    let mut objects = Vec::new();
    for ((scene, frame), m) in &matched {
        let fr = ds.frame(scene, *frame).ok_or_else(|| Error::msg("frame vanished"))?;
        for (gi, g) in fr.gt.iter().enumerate() {
            if !in_occlusion(g, opts.occlusion) {
                continue;
            }
            let model = ds
                .models
                .get(&g.obj_id)
                .ok_or_else(|| Error::input(ds.root.display().to_string(), format!("no model for obj_id {}", g.obj_id)))?;
            let metrics = match m.get(&gi) {
                None => None,
                Some(&pi) => {
                    let p = &preds.predictions[pi];
                    let mesh = match &p.mesh {
                        None => &model.mesh,
                        Some(rel) => {
                            let path = if rel.is_absolute() { rel.clone() } else { base.join(rel) };
                            if !mesh_cache.contains_key(&path) {
                                let mesh =
                                    read_ply(&path).map_err(|e| Error::config(&file, format!("predictions[{pi}].mesh"), e.to_string()))?;
                                mesh_cache.insert(path.clone(), mesh);
                            }
                            &mesh_cache[&path]
                        }
                    };
                    Some(eval_one(model, g, p, mesh, opts))
                }
            };
            let occ = g.visib_fract.map(|v| (1.0 - v) * 100.0);
            objects.push(ObjectResult {
                scene: scene.clone(),
                frame: *frame,
                obj_id: g.obj_id,
                gt_index: gi,
                model: model.name.clone(),
                visib_fract: g.visib_fract,
                visib_estimated: g.visib_estimated,
                occlusion_pct: occ,
                occlusion_bin: g.visib_fract.and_then(occlusion_bin).map(occlusion_bin_label),
                gt_diameter: model.diameter,
                metrics,
            });
        }
    }
    let all: Vec<&ObjectResult> = objects.iter().collect();
    let overall = Summary::of("all".into(), &all);
    let mut by_occlusion: Vec<Summary> = (0..OCCLUSION_BINS.len())
        .map(|b| {
            let lab = occlusion_bin_label(b);
            Summary::of(lab.clone(), &all.iter().copied().filter(|o| o.occlusion_bin.as_deref() == Some(lab.as_str())).collect::<Vec<_>>())
        })
        .collect();
    let over: Vec<&ObjectResult> = all.iter().copied().filter(|o| o.visib_fract.is_some() && o.occlusion_bin.is_none()).collect();
    if !over.is_empty() {
        by_occlusion.push(Summary::of(">70%".into(), &over));
    }
    let unknown: Vec<&ObjectResult> = all.iter().copied().filter(|o| o.visib_fract.is_none()).collect();
    if !unknown.is_empty() {
        by_occlusion.push(Summary::of("unknown".into(), &unknown));
    }
    Ok(Report { dataset: ds.root.display().to_string(), predictions: file, options: *opts, overall, by_occlusion, objects })
}

/// Entry point for `recon eval`: load the dataset (layout auto-detected, see
/// [`load_dataset`]) and the predictions, then evaluate.
pub fn run_eval(dataset: &Path, predictions: &Path, opts: &EvalOptions) -> Result<Report> {
    let ds = load_dataset(dataset)?;
    let preds = read_predictions(predictions)?;
    evaluate(&ds, &preds, predictions, opts)
}

fn pct(x: f64) -> String {
    if x.is_nan() {
        "-".into()
    } else {
        format!("{:.1}", 100.0 * x)
    }
}

fn num(x: f64) -> String {
    if x.is_nan() {
        "-".into()
    } else {
        format!("{x:.4}")
    }
}

impl Report {
    /// Writes `report.json`, `report.txt` (the table) and `plot.svg` into `dir`.
    pub fn write_files(&self, dir: &Path) -> Result<()> {
        for (name, text) in [("report.json", self.to_json()?), ("report.txt", self.text_table()), ("plot.svg", self.svg())] {
            let p = dir.join(name);
            std::fs::write(&p, text).map_err(|e| Error::io(&p, e))?;
        }
        Ok(())
    }

    /// The report as pretty JSON (NaN written as null).
    pub fn to_json(&self) -> Result<String> {
        // NaN (empty means) is not JSON: serde_json writes it as null.
        serde_json::to_string_pretty(self).map_err(|e| Error::msg(format!("serialising report: {e}")))
    }

    /// Human-readable table: overall row, then one row per occlusion bin. Rates in %.
    pub fn text_table(&self) -> String {
        let head = [
            "occlusion",
            "N",
            "missed",
            "ADD-SB/d",
            "ADD-SB@10%",
            "ADD-SB@5%",
            "CD_norm",
            "DRE",
            "DRE@5%",
            "F1 posed",
            "F1 aligned",
            "NC",
            "ADD@10%",
            "ADD-S@10%",
        ];
        let mut rows = vec![head.iter().map(|s| s.to_string()).collect::<Vec<_>>()];
        for s in std::iter::once(&self.overall).chain(&self.by_occlusion) {
            rows.push(vec![
                s.label.clone(),
                s.n_gt.to_string(),
                s.n_missed.to_string(),
                num(s.add_sb_norm_mean),
                pct(s.add_sb_10),
                pct(s.add_sb_05),
                num(s.cd_norm_mean),
                num(s.dre_mean),
                pct(s.dre_05),
                num(s.f1_posed_mean),
                num(s.f1_aligned_mean),
                num(s.normal_consistency_mean),
                pct(s.add_10),
                pct(s.add_s_10),
            ]);
        }
        let w: Vec<usize> = (0..head.len()).map(|c| rows.iter().map(|r| r[c].chars().count()).max().unwrap_or(0)).collect();
        let mut out = String::new();
        for (i, r) in rows.iter().enumerate() {
            let line: Vec<String> = r
                .iter()
                .enumerate()
                .map(|(c, x)| if c == 0 { format!("{x:<w$}", w = w[c]) } else { format!("{x:>w$}", w = w[c]) })
                .collect();
            out.push_str(&line.join("  "));
            out.push('\n');
            if i == 0 {
                out.push_str(&"-".repeat(w.iter().sum::<usize>() + 2 * (w.len() - 1)));
                out.push('\n');
            }
        }
        out.push_str(&format!(
            "F1 threshold = {:.1}% of GT diameter; NC = normal consistency after alignment; {} surface samples per mesh; rates over all GT instances (missed = failure).\n",
            100.0 * self.options.f1_tau_rel,
            self.options.n_samples
        ));
        let o = &self.overall;
        if o.dihedral_deg_mean.is_finite() {
            let gt = if o.gt_dihedral_deg_mean.is_finite() {
                format!("GT meshes {:.1}°", o.gt_dihedral_deg_mean)
            } else {
                "GT: points only".into()
            };
            out.push_str(&format!(
                "Surfaces: mean dihedral angle {:.1}° ({gt}), {}% of predicted meshes in one component.\n",
                o.dihedral_deg_mean,
                pct(o.one_component)
            ));
        }
        let est = self.objects.iter().filter(|o| o.visib_estimated).count();
        if est > 0 {
            out.push_str(&format!(
                "Occlusion of {est} of {} instances estimated from the GT model, pose and visible mask (the dataset has no visib_fract).\n",
                self.objects.len()
            ));
        }
        out
    }

    /// SVG (no dependency): two scatter panels, ADD-SB/d and CD_norm against occlusion (%),
    /// one dot per predicted object with known visibility, bin boundaries as dashed lines.
    pub fn svg(&self) -> String {
        let pts: Vec<(f64, f64, f64)> = self
            .objects
            .iter()
            .filter_map(|o| Some((o.occlusion_pct?, o.metrics.as_ref()?)))
            .map(|(occ, m)| (occ, m.add_sb_norm, m.cd_norm))
            .filter(|p| p.1.is_finite() && p.2.is_finite())
            .collect();
        let (pw, ph, ml, mt, mb) = (420.0, 300.0, 60.0, 30.0, 45.0);
        let width = 2.0 * (pw + ml) + 20.0;
        let height = ph + mt + mb;
        let mut s = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{width}\" height=\"{height}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n");
        for (k, (title, color)) in [("ADD-SB / diameter", "#1f77b4"), ("CD_norm", "#d62728")].iter().enumerate() {
            let x0 = ml + k as f64 * (pw + ml + 20.0);
            let ys: Vec<f64> = pts.iter().map(|p| if k == 0 { p.1 } else { p.2 }).collect();
            let ymax = ys.iter().cloned().fold(0.0, f64::max).max(1e-6) * 1.1;
            let sx = |o: f64| x0 + o / 100.0 * pw;
            let sy = |v: f64| mt + ph - v / ymax * ph;
            s += &format!("<rect x=\"{x0}\" y=\"{mt}\" width=\"{pw}\" height=\"{ph}\" fill=\"none\" stroke=\"black\"/>\n");
            s += &format!("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{title}</text>\n", x0 + pw / 2.0, mt - 10.0);
            s += &format!("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">occlusion (%)</text>\n", x0 + pw / 2.0, mt + ph + 35.0);
            for &(lo, _) in OCCLUSION_BINS.iter().skip(1).chain(std::iter::once(&(70.0, 0.0))) {
                s += &format!(
                    "<line x1=\"{0}\" y1=\"{mt}\" x2=\"{0}\" y2=\"{1}\" stroke=\"#999\" stroke-dasharray=\"4 3\"/>\n",
                    sx(lo),
                    mt + ph
                );
            }
            for t in [0.0, 25.0, 50.0, 75.0, 100.0] {
                s += &format!("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{t:.0}</text>\n", sx(t), mt + ph + 16.0);
            }
            for i in 0..=4 {
                let v = ymax * i as f64 / 4.0;
                s += &format!("<text x=\"{}\" y=\"{}\" text-anchor=\"end\">{v:.3}</text>\n", x0 - 5.0, sy(v) + 4.0);
            }
            for (p, y) in pts.iter().zip(&ys) {
                s += &format!(
                    "<circle cx=\"{:.2}\" cy=\"{:.2}\" r=\"3\" fill=\"{color}\" fill-opacity=\"0.7\"/>\n",
                    sx(p.0.clamp(0.0, 100.0)),
                    sy(*y)
                );
            }
        }
        s += "</svg>\n";
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use recon_testkit::{tmp as tmpdir, write_bop};

    /// Real-data discovery, shared with the integration tests (test support:
    /// it reads `RECON_REALDATA` / `RECON_REQUIRE_REALDATA`, so it lives in tests/).
    #[cfg(test)]
    mod realdata {
        include!(concat!(env!("CARGO_MANIFEST_DIR"), "/../../tests/common/realdata.rs"));
    }

    #[test]
    fn evaluates_predictions_end_to_end() {
        let dir = tmpdir("report");
        write_bop(&dir);
        let model = dir.join("models/obj_000001.ply");
        let preds = format!(
            r#"{{"predictions": [
              {{"scene": "000048", "frame": 1, "obj_id": 1, "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0.01, -0.02, 0.7], "scale": 0.001, "mesh": "{}"}},
              {{"scene": "000048", "frame": 1, "obj_id": 2, "gt_index": 1, "R": [[0,-1,0],[1,0,0],[0,0,1]], "t": [-0.047, 0.004, 0.8]}}
            ]}}"#,
            model.display()
        );
        let pf = dir.join("preds.json");
        std::fs::write(&pf, preds).unwrap();
        let opts = EvalOptions { n_samples: 4000, ..Default::default() };
        let r = run_eval(&dir, &pf, &opts).unwrap();
        // Only frame 1 has predictions: its two GT instances are evaluated.
        assert_eq!(r.objects.len(), 2);
        let a = r.objects[0].metrics.as_ref().unwrap();
        assert_eq!((a.add, a.add_s), (Some(0.0), Some(0.0)));
        // Same seed, mesh in mm × 0.001 vs GT in m: equal up to rounding.
        assert!(a.add_sb < 1e-12, "{}", a.add_sb);
        assert!(a.cd_norm < 1e-12 && a.dre < 1e-12 && a.add_sb_success_05 && a.dre_success_05);
        assert_eq!((a.f1_posed.f1, a.f1_aligned.f1), (1.0, 1.0));
        assert_eq!(r.objects[0].occlusion_bin.as_deref(), Some("0-3%"));
        // Pose-only prediction of object 2, off by (3, 4, 0) mm → ADD = 5 mm exactly.
        let b = r.objects[1].metrics.as_ref().unwrap();
        let (badd, badd_s) = (b.add.unwrap(), b.add_s.unwrap());
        assert!((badd - 0.005).abs() < 1e-12, "{badd}");
        assert!(badd_s <= 0.005 + 1e-12 && b.add_sb <= 0.005 + 1e-12);
        assert!(b.dre < 1e-12 && b.cd_norm < 0.01);
        assert_eq!(r.objects[1].occlusion_bin.as_deref(), Some("20-40%"));
        assert_eq!(r.overall.n_gt, 2);
        assert_eq!(r.overall.n_missed, 0);
        assert_eq!(r.overall.add_sb_10, 1.0);
        let json = r.to_json().unwrap();
        let v: serde_json::Value = serde_json::from_str(&json).unwrap();
        assert_eq!(v["objects"][1]["metrics"]["add"].as_f64().map(|x| (x - 0.005).abs() < 1e-12), Some(true));
        let t = r.text_table();
        assert!(t.contains("0-3%") && t.contains("ADD-SB@10%") && t.lines().count() >= 7, "{t}");
        let svg = r.svg();
        assert!(svg.starts_with("<svg") && svg.matches("<circle").count() == 4);

        // Only one of the two GT instances of frame 1 predicted: the other is missed.
        let p2 = dir.join("p2.json");
        std::fs::write(
            &p2,
            r#"{"predictions": [{"scene": "000048", "frame": 1, "obj_id": 2, "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0,0,1]}]}"#,
        )
        .unwrap();
        let r2 = run_eval(&dir, &p2, &opts).unwrap();
        assert_eq!((r2.overall.n_gt, r2.overall.n_missed), (2, 1));
        assert!(r2.overall.add_sb_10 <= 0.5);

        // Validation errors name the file and the field.
        let cases = [
            (
                r#"{"predictions": [{"scene": "000048", "frame": 1, "obj_id": 1, "R": [[1,0,0],[0,2,0],[0,0,1]], "t": [0,0,1]}]}"#,
                "predictions[0].R",
            ),
            (
                r#"{"predictions": [{"scene": "000048", "frame": 1, "obj_id": 1, "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0,0,1], "scale": -1}]}"#,
                "predictions[0].scale",
            ),
            (
                r#"{"predictions": [{"scene": "000048", "frame": 7, "obj_id": 1, "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0,0,1]}]}"#,
                "predictions[0].frame",
            ),
            (
                r#"{"predictions": [{"scene": "000048", "frame": 1, "obj_id": 5, "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0,0,1]}]}"#,
                "predictions[0].obj_id",
            ),
            (
                r#"{"predictions": [{"scene": "000048", "frame": 1, "obj_id": 1, "R": [[1,0,0],[0,1,0],[0,0,1]], "t": [0,0,1], "mesh": "nope.ply"}]}"#,
                "predictions[0].mesh",
            ),
            (r#"{"predictions": [{"scene": "000048", "frame": 1, "obj_id": 1, "R": [[1,0,0],[0,1,0]], "t": [0,0,1]}]}"#, "bad.json"),
        ];
        for (text, want) in cases {
            let p = dir.join("bad.json");
            std::fs::write(&p, text).unwrap();
            let e = run_eval(&dir, &p, &opts).unwrap_err().to_string();
            assert!(e.contains("bad.json") && e.contains(want), "{e} (want {want})");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    fn ascii_ply(m: &TriMesh) -> String {
        let mut s = format!("ply\nformat ascii 1.0\nelement vertex {}\nproperty double x\nproperty double y\nproperty double z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n", m.vertices.len(), m.faces.len());
        for v in &m.vertices {
            s += &format!("{} {} {}\n", v[0], v[1], v[2]);
        }
        for f in &m.faces {
            s += &format!("3 {} {} {}\n", f[0], f[1], f[2]);
        }
        s
    }

    /// One-frame BOP dataset: obj 1 = closed cylinder r 40, h 100 mm (256 segments, so a
    /// 90° spin maps it onto itself), obj 2 = box 40×20×10 mm; four GT instances.
    fn symmetric_dataset(dir: &Path) -> (Vec<GtInstance>, f64, f64) {
        use recon_core::math::axis_angle;
        let scene = dir.join("test/000001");
        std::fs::create_dir_all(&scene).unwrap();
        std::fs::create_dir_all(dir.join("models")).unwrap();
        std::fs::write(dir.join("models/obj_000001.ply"), ascii_ply(&crate::metrics::tests::cylinder(40.0, 100.0, 256))).unwrap();
        std::fs::write(dir.join("models/obj_000002.ply"), ascii_ply(&recon_core::mesh::primitives::cuboid([20.0, 10.0, 5.0]))).unwrap();
        std::fs::write(scene.join("scene_camera.json"), r#"{"1": {"cam_K": [600, 0, 320, 0, 600, 240, 0, 0, 1], "depth_scale": 1.0}}"#)
            .unwrap();
        let poses = [
            (axis_angle([0.2, 1.0, 0.1], 0.5), [0.0, 0.0, 700.0], 1),
            (axis_angle([1.0, 0.0, 0.3], 1.2), [100.0, 20.0, 800.0], 1),
            (axis_angle([0.0, 1.0, 1.0], 0.8), [-80.0, 10.0, 650.0], 2),
            (axis_angle([1.0, 1.0, 0.0], 2.0), [50.0, -60.0, 900.0], 2),
        ];
        let gt: Vec<serde_json::Value> =
            poses.iter().map(|(r, t, id)| serde_json::json!({"cam_R_m2c": r.concat(), "cam_t_m2c": t, "obj_id": id})).collect();
        std::fs::write(scene.join("scene_gt.json"), serde_json::json!({"1": gt}).to_string()).unwrap();
        let info: Vec<serde_json::Value> = [1.0, 0.9, 0.7, 0.5].iter().map(|v| serde_json::json!({"visib_fract": v})).collect();
        std::fs::write(scene.join("scene_gt_info.json"), serde_json::json!({"1": info}).to_string()).unwrap();
        let ds = load_dataset(dir).unwrap();
        let (d1, d2) = (ds.models[&1].diameter, ds.models[&2].diameter);
        (ds.frames[0].gt.clone(), d1, d2)
    }

    #[test]
    fn rates_pin_identity_symmetry_and_offsets() {
        use recon_core::math::axis_angle;
        let dir = tmpdir("sym");
        let (gt, d_cyl, d_box) = symmetric_dataset(&dir);
        assert!((d_cyl - (0.08f64 * 0.08 + 0.01).sqrt()).abs() < 1e-9 && (d_box - 0.0021f64.sqrt()).abs() < 1e-9);
        let spun = Similarity::rigid(gt[1].r, gt[1].t)
            .compose(&Similarity::rigid(axis_angle([0.0, 0.0, 1.0], std::f64::consts::FRAC_PI_2), [0.0; 3]));
        let box_ply = dir.join("models/obj_000002.ply");
        let preds = serde_json::json!({"predictions": [
            // 0: identical to the GT (pose only: the GT model is used).
            {"scene": "000001", "frame": 1, "obj_id": 1, "gt_index": 0, "R": gt[0].r, "t": gt[0].t},
            // 1: the cylinder spun 90° about its own axis: same surface, other model frame.
            {"scene": "000001", "frame": 1, "obj_id": 1, "gt_index": 1, "R": spun.rotation, "t": spun.translation},
            // 2: the box shifted by exactly 3 mm along camera x.
            {"scene": "000001", "frame": 1, "obj_id": 2, "gt_index": 2, "R": gt[2].r, "t": [gt[2].t[0] + 0.003, gt[2].t[1], gt[2].t[2]]},
            // 3: the box model (mm) at the GT pose, 3 % too large.
            {"scene": "000001", "frame": 1, "obj_id": 2, "gt_index": 3, "R": gt[3].r, "t": gt[3].t, "scale": 0.00103, "mesh": box_ply}
        ]});
        let pf = dir.join("preds.json");
        std::fs::write(&pf, preds.to_string()).unwrap();
        let r = run_eval(&dir, &pf, &EvalOptions { n_samples: 20_000, ..Default::default() }).unwrap();
        let m: Vec<&ObjectMetrics> = r.objects.iter().map(|o| o.metrics.as_ref().unwrap()).collect();
        // Identical: zero errors, every success, F1 = 1.
        assert_eq!((m[0].add, m[0].add_s, m[0].add_sb, m[0].dre), (Some(0.0), Some(0.0), 0.0, 0.0));
        assert!(m[0].cd_norm < 1e-12 && m[0].f1_posed.f1 == 1.0 && m[0].f1_aligned.f1 == 1.0);
        let b0 = &r.by_occlusion[0];
        assert_eq!((b0.label.as_str(), b0.n_gt), ("0-3%", 1));
        for (name, v) in [
            ("ADD-SB@10", b0.add_sb_10),
            ("ADD-SB@5", b0.add_sb_05),
            ("DRE@5", b0.dre_05),
            ("ADD@10", b0.add_10),
            ("ADD-S@10", b0.add_s_10),
            ("F1", b0.f1_posed_mean),
        ] {
            assert_eq!(v, 1.0, "{name}");
        }
        assert!(b0.add_sb_norm_mean == 0.0 && b0.cd_norm_mean < 1e-12 && b0.dre_mean == 0.0, "{b0:?}");
        // Spun cylinder: ADD fails (side points move by r·√2 = 56.6 mm ≫ 12.8 mm), ADD-S and
        // ADD-SB pass (only sampling density remains).
        let b1 = &r.by_occlusion[1];
        assert_eq!(b1.n_gt, 1);
        assert!(m[1].add_norm.unwrap() > 0.3, "{:?}", m[1].add_norm);
        assert!(m[1].add_s_norm.unwrap() < 0.02 && m[1].add_sb_norm < 0.02, "{:?} {}", m[1].add_s_norm, m[1].add_sb_norm);
        assert_eq!((b1.add_10, b1.add_s_10, b1.add_sb_10, b1.add_sb_05), (0.0, 1.0, 1.0, 1.0));
        assert!(m[1].dre < 1e-12);
        // Shifted box: ADD = 3 mm exactly, ADD-S and ADD-SB at most that.
        assert!((m[2].add.unwrap() - 0.003).abs() < 1e-12, "{:?}", m[2].add);
        assert!(m[2].add_s.unwrap() <= 0.003 + 1e-12 && m[2].add_sb <= 0.003 + 1e-12);
        assert!(m[2].dre < 1e-12 && m[2].cd_norm < 0.01);
        // Scaled box: DRE = 3 % exactly (passes @5 %), ADD-S of the pose is 0.
        assert!((m[3].dre - 0.03).abs() < 1e-9, "{}", m[3].dre);
        assert!(m[3].dre_success_05 && m[3].add == Some(0.0));
        assert!((m[3].pred_diameter - 1.03 * d_box).abs() < 1e-9);
        assert_eq!(r.overall.dre_05, 1.0);

        // The same four as own-frame predictions (model_frame: false): no ADD at all.
        let mut p2 = preds.clone();
        for p in p2["predictions"].as_array_mut().unwrap() {
            p["model_frame"] = serde_json::json!(false);
        }
        std::fs::write(&pf, p2.to_string()).unwrap();
        let r2 = run_eval(&dir, &pf, &EvalOptions { n_samples: 20_000, ..Default::default() }).unwrap();
        assert!(r2.objects.iter().all(|o| o.metrics.as_ref().unwrap().add.is_none()));
        assert!(r2.overall.add_10.is_nan() && r2.overall.add_s_10.is_nan());
        assert_eq!(r2.overall.add_sb_10, r.overall.add_sb_10);
        let v: serde_json::Value = serde_json::from_str(&r2.to_json().unwrap()).unwrap();
        assert!(v["overall"]["add_10"].is_null() && v["objects"][0]["metrics"]["add"].is_null());
        // A missed instance does not make an ADD rate of 0 % for a method without ADD.
        p2["predictions"].as_array_mut().unwrap().pop();
        std::fs::write(&pf, p2.to_string()).unwrap();
        let r3 = run_eval(&dir, &pf, &EvalOptions { n_samples: 20_000, ..Default::default() }).unwrap();
        assert_eq!(r3.overall.n_missed, 1);
        assert!(r3.overall.add_10.is_nan() && r3.overall.add_s_10.is_nan());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn all_frames_counts_unpredicted_frames_as_missed() {
        let dir = tmpdir("allframes");
        write_bop(&dir);
        let pf = dir.join("p.json");
        std::fs::write(
            &pf,
            r#"{"predictions": [{"scene": "000048", "frame": 2, "obj_id": 1, "R": [[1,0,0],[0,0,-1],[0,1,0]], "t": [0, 0, 0.6]}]}"#,
        )
        .unwrap();
        let only = run_eval(&dir, &pf, &EvalOptions { n_samples: 2000, ..Default::default() }).unwrap();
        assert_eq!((only.overall.n_gt, only.overall.n_missed, only.overall.add_sb_10), (1, 0, 1.0));
        let all = run_eval(&dir, &pf, &EvalOptions { n_samples: 2000, all_frames: true, ..Default::default() }).unwrap();
        assert_eq!((all.overall.n_gt, all.overall.n_missed), (3, 2));
        assert!((all.overall.add_sb_10 - 1.0 / 3.0).abs() < 1e-12);
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Real data: YCB-Video frame 0001/000001, the BOP mesh of 002_master_chef_can as the
    /// "prediction" at the GT pose, scored against the YCB-Video points.xyz GT model.
    /// The BOP mesh is re-centred (README: x_bop_mm ≈ 1000·x_ycbv_m + off, ±1 mm), which is
    /// folded into t: R(0.001·v_bop) + t − 0.001·R·off.
    #[test]
    fn ycbv_bop_mesh_at_gt_pose_scores_well() {
        let Some(root) = realdata::realdata_for_test(Some("ycbv_video_oprb"), "the YCB-Video evaluation test") else {
            return;
        };
        let root = root.as_path();
        let ds = load_dataset(root).unwrap();
        let g = ds.frame("0001", 1).unwrap().gt[0].clone();
        assert_eq!(g.obj_id, 1);
        let off = [1.39, -0.45, 3.60];
        let t: Vec<f64> = (0..3).map(|i| g.t[i] - 0.001 * (0..3).map(|j| g.r[i][j] * off[j]).sum::<f64>()).collect();
        let dir = tmpdir("ycbv");
        let pf = dir.join("p.json");
        let pred = serde_json::json!({"predictions": [{"scene": "0001", "frame": 1, "obj_id": 1, "R": g.r, "t": t, "scale": 0.001,
            "mesh": root.join("models_bop_ply_recentred/obj_000001.ply")}]});
        std::fs::write(&pf, pred.to_string()).unwrap();
        let r = run_eval(root, &pf, &EvalOptions::default()).unwrap();
        eprintln!("{}", r.text_table());
        let m = r.objects[0].metrics.as_ref().unwrap();
        eprintln!("{m:?}");
        // Same object, two independent models (BOP mesh vs PoseCNN points), ~1 mm offset error.
        assert!(m.add_sb_norm < 0.05 && m.add_sb_success_05, "{m:?}");
        assert!(m.cd_norm < 0.03 && m.dre < 0.05, "{m:?}");
        assert!(m.f1_aligned.f1 > 0.9, "{m:?}");
        // 3 objects of that frame are not predicted: missed, counted as failures.
        assert_eq!((r.overall.n_gt, r.overall.n_missed), (4, 3));
        // No visib_fract in YCB-Video: estimated for every instance; the can is unoccluded.
        assert!(r.objects.iter().all(|o| o.visib_estimated && o.visib_fract.is_some()));
        assert!(r.objects[0].visib_fract.unwrap() > 0.9, "{:?}", r.objects[0].visib_fract);
        assert!(r.text_table().contains("estimated"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
