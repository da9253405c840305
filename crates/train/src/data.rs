//! Training data: what a dataset must provide ([`TrainingSource`]) and how
//! each object becomes the model's inputs and targets.
//!
//! A source knows, per object instance seen in an RGB-D view, the frame,
//! the object's visible mask, its mesh (model frame, metres) and the exact
//! model → camera pose — what `recon synth` writes in BOP format
//! ([`crate::bop::BopSource`]) and what the in-memory generator of
//! [`crate::toy`] produces. From that:
//!
//! - **inputs** are made by [`recon_core::geometry::pointmap::prepare_object_with`],
//!   the inference preprocessing itself (erosion, normalisation, square crop,
//!   resizing), with the crop context factor drawn per sample from
//!   `[1.2, 2.0]` (20–100 % context around the mask's box; inference uses 1.2);
//! - the **occupancy target** is the mesh voxelised in its canonical frame
//!   ([`recon_core::geometry::voxelize`]);
//! - the **pose target** is the canonical → camera similarity
//!   (`R`, `R·c + t`, `extent`) expressed in the view's normalised frame by
//!   [`recon_core::geometry::camera_pose::pose_to_normalised`], as a 10-D vector
//!   `[r6, t, s]` z-scored with statistics of the training set
//!   ([`pose_stats_json`], saved in the format [`PoseStats`] reads).

use std::sync::Arc;

use candle_core::{Device, Tensor};

use recon_core::dataset::frame::RgbdFrame;
use recon_core::geometry::camera_pose::pose_to_normalised;
use recon_core::geometry::pointmap::{object_points, prepare_object_with, Normaliser, PrepareOptions};
use recon_core::geometry::pose::{rotation_to_9d, Mat3, NineDLayout, Pose, PoseStats};
use recon_core::geometry::voxelize::{voxelize, CanonicalFrame, Fill};
use recon_core::mesh::trimesh::TriMesh;
use recon_core::rng::SeededRng;
use recon_core::{Error, Result};

/// One object model (mesh in its model frame, metres).
#[derive(Debug, Clone)]
pub struct ModelEntry {
    /// Stable identifier (BOP `obj_id`, generator index, ...).
    pub key: String,
    pub mesh: Arc<TriMesh>,
    /// Per-vertex colours in [0, 1] (stage-2 colour supervision), if known.
    pub colors: Option<Arc<Vec<[f32; 3]>>>,
}

/// One object instance seen in one RGB-D view.
#[derive(Debug, Clone)]
pub struct ObjectView {
    pub frame: Arc<RgbdFrame>,
    /// Visible mask at frame resolution (row-major, `true` = object).
    pub mask: Vec<bool>,
    /// Model → camera: `x_cam = r·x_model + t` (metres).
    pub r: [[f64; 3]; 3],
    pub t: [f64; 3],
}

/// One training sample: an object (index into the source's models) and one
/// or two views of it (view 0 is the anchor).
#[derive(Debug, Clone)]
pub struct ObjectSample {
    pub model: usize,
    pub views: Vec<ObjectView>,
}

/// A training dataset. Implementations must be deterministic: the same index
/// always gives the same data.
pub trait TrainingSource: Sync {
    /// One line naming the data (for logs and the run record).
    fn describe(&self) -> String;
    /// Number of object models.
    fn num_models(&self) -> usize;
    /// Model `i`: its key, mesh and (when known) vertex colours.
    fn model(&self, i: usize) -> Result<ModelEntry>;
    /// Number of samples.
    fn num_samples(&self) -> usize;
    /// Sample `i`: an object and one or two views of it.
    fn sample(&self, i: usize) -> Result<ObjectSample>;
}

/// Canonical frame of a model's mesh (bounding box centre, longest side).
pub fn canonical_frame(mesh: &TriMesh) -> Result<CanonicalFrame> {
    CanonicalFrame::of(&mesh.vertices, &mesh.faces)
}

/// Occupancy `[1, r, r, r]` (f32 0/1) of a mesh in its canonical frame.
pub fn occupancy(mesh: &TriMesh, r: usize, fill: Fill) -> Result<Tensor> {
    let c = canonical_frame(mesh)?;
    let v: Vec<[f64; 3]> = mesh.vertices.iter().map(|p| c.to_canonical(*p)).collect();
    let occ = voxelize(&v, &mesh.faces, r, fill)?;
    let vals: Vec<f32> = occ.iter().map(|&b| if b { 1.0 } else { 0.0 }).collect();
    Ok(Tensor::from_vec(vals, (1, r, r, r), &Device::Cpu)?)
}

/// Canonical → camera pose (metres) of a view: `x_cam = e·R·x_can + (R·c + t)`.
pub fn camera_pose(view: &ObjectView, canon: &CanonicalFrame) -> Pose {
    let r = view.r;
    let rc: [f64; 3] = std::array::from_fn(|i| (0..3).map(|k| r[i][k] * canon.centre[k]).sum::<f64>() + view.t[i]);
    let rotation: Mat3 = std::array::from_fn(|i| std::array::from_fn(|j| r[i][j] as f32));
    Pose { rotation, translation: rc.map(|x| x as f32), scale: canon.extent as f32 }
}

/// Preprocessing options of training views: inference's, with the crop
/// context factor given.
pub fn train_prepare_options(context: f64) -> PrepareOptions {
    PrepareOptions { context, ..PrepareOptions::default() }
}

/// The normaliser inference would fit for this view (no crop, cheap).
pub fn view_normaliser(view: &ObjectView) -> Result<Normaliser> {
    let opts = PrepareOptions::default();
    let (pts, _) = object_points(&view.frame, &view.mask, opts.erosion)?;
    if pts.is_empty() {
        return Err(Error::input(view.frame.rgb_path.display().to_string(), "object has no valid depth under its eroded mask"));
    }
    Normaliser::fit(&pts, opts.quantile_drop)
}

/// One view turned into model inputs and its pose target.
#[derive(Debug, Clone)]
pub struct TrainView {
    /// `[1, 3, S, S]` ImageNet-normalised colour.
    pub pixels: Tensor,
    /// `[1, 3, S, S]` normalised point map.
    pub pointmap: Tensor,
    /// `[1, 1, S, S]` eroded mask.
    pub mask: Tensor,
    /// Canonical → normalised-frame pose (the stage-1 target before z-scoring).
    pub pose: Pose,
}

/// Turns one view into model inputs (crop of `size` pixels with `context`) and its pose target.
pub fn prepare_train_view(view: &ObjectView, canon: &CanonicalFrame, size: usize, context: f64) -> Result<TrainView> {
    let p = prepare_object_with(&view.frame, &view.mask, size, &train_prepare_options(context), &Device::Cpu)?;
    let pose = pose_to_normalised(&camera_pose(view, canon), &p.normaliser);
    Ok(TrainView { pixels: p.pixel_values, pointmap: p.pointmap, mask: p.mask, pose })
}

fn mean_std(rows: &[Vec<f64>], file: &str) -> Result<(Vec<f64>, Vec<f64>)> {
    let n = rows.len();
    if n == 0 {
        return Err(Error::input(file, "no object views to compute pose statistics from"));
    }
    let d = rows[0].len();
    let mean: Vec<f64> = (0..d).map(|k| rows.iter().map(|r| r[k]).sum::<f64>() / n as f64).collect();
    // A constant component (e.g. one sample) gets a floor so z-scoring stays finite.
    let std: Vec<f64> =
        (0..d).map(|k| (rows.iter().map(|r| (r[k] - mean[k]).powi(2)).sum::<f64>() / n as f64).sqrt().max(MIN_POSE_STD)).collect();
    Ok((mean, std))
}

/// Floor of every pose statistic's standard deviation.
pub const MIN_POSE_STD: f64 = 1e-3;

/// Inputs of drawn samples `(sample index, seed)`: each sample's model and
/// its first `n_views` views, prepared with a crop context drawn in
/// `context` from the sample's own seeded stream (in parallel; the result
/// does not depend on scheduling).
pub fn prepare_picks(
    source: &dyn TrainingSource,
    canon: &[CanonicalFrame],
    picks: &[(usize, u64)],
    n_views: usize,
    image_size: usize,
    context: [f64; 2],
) -> Result<Vec<(usize, Vec<TrainView>)>> {
    use rayon::prelude::*;
    picks
        .par_iter()
        .map(|&(i, seed)| {
            let s = source.sample(i)?;
            let mut r = SeededRng::new(seed);
            let c = &canon[s.model];
            let views = s.views[..n_views]
                .iter()
                .map(|v| prepare_train_view(v, c, image_size, context[0] + (context[1] - context[0]) * r.uniform()))
                .collect::<Result<Vec<_>>>()?;
            Ok((s.model, views))
        })
        .collect()
}

/// What a pass over the source found: the samples whose anchor view has
/// depth under its mask (usable), those whose first two views both do, and
/// the normalised-frame pose of every usable view.
#[derive(Debug, Clone)]
pub struct Scan {
    /// The model of every sample (by sample index).
    pub models: Vec<usize>,
    pub usable: Vec<usize>,
    pub two_view: Vec<usize>,
    pub poses: Vec<Pose>,
    pub skipped_views: usize,
}

/// Scan every sample (in parallel; the result does not depend on scheduling).
pub fn scan(source: &dyn TrainingSource) -> Result<Scan> {
    use rayon::prelude::*;
    let canon: Vec<CanonicalFrame> =
        (0..source.num_models()).into_par_iter().map(|i| canonical_frame(&source.model(i)?.mesh)).collect::<Result<_>>()?;
    let per: Vec<(usize, Vec<Option<Pose>>)> = (0..source.num_samples())
        .into_par_iter()
        .map(|i| {
            let s = source.sample(i)?;
            let c = canon
                .get(s.model)
                .ok_or_else(|| Error::input(source.describe(), format!("sample {i} names model {} of {}", s.model, canon.len())))?;
            Ok((s.model, s.views.iter().map(|v| view_normaliser(v).ok().map(|n| pose_to_normalised(&camera_pose(v, c), &n))).collect()))
        })
        .collect::<Result<_>>()?;
    let mut out = Scan {
        models: per.iter().map(|(m, _)| *m).collect(),
        usable: Vec::new(),
        two_view: Vec::new(),
        poses: Vec::new(),
        skipped_views: 0,
    };
    for (i, (_, views)) in per.iter().enumerate() {
        out.skipped_views += views.iter().filter(|v| v.is_none()).count();
        if views.first().is_some_and(|v| v.is_some()) {
            out.usable.push(i);
            if views.get(1).is_some_and(|v| v.is_some()) {
                out.two_view.push(i);
            }
        }
        out.poses.extend(views.iter().flatten().copied());
    }
    if out.usable.is_empty() {
        return Err(Error::input(source.describe(), "no sample has valid depth under its object mask"));
    }
    Ok(out)
}

/// Pose statistics of `poses` in the JSON format of RecGen's
/// `stereo_pose_stats.json` ([`PoseStats`]): 6-D rotation (first two
/// columns), 9-D rotation in `layout`, translation and scale, each with
/// per-component mean and population std (floored at `MIN_POSE_STD`).
pub fn pose_stats_json(poses: &[Pose], layout: NineDLayout, source: &str) -> Result<serde_json::Value> {
    let (mut r6, mut r9, mut tr, mut sc) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for p in poses {
        let v10 = p.to_10d();
        r6.push(v10[..6].iter().map(|&x| x as f64).collect::<Vec<_>>());
        r9.push(rotation_to_9d(&p.rotation, layout).iter().map(|&x| x as f64).collect::<Vec<_>>());
        tr.push(p.translation.iter().map(|&x| x as f64).collect::<Vec<_>>());
        sc.push(vec![p.scale as f64]);
    }
    let (m6, s6) = mean_std(&r6, source)?;
    let (m9, s9) = mean_std(&r9, source)?;
    let (mt, st) = mean_std(&tr, source)?;
    let (ms, ss) = mean_std(&sc, source)?;
    let v = serde_json::json!({
        "_source": format!("computed by recon train from {} object views of {source}; 9d layout {layout:?}", poses.len()),
        "version": "1.0",
        "global_statistics": {
            "6d_rotation": {"mean": m6, "std": s6},
            "9d_rotation": {"mean": m9, "std": s9},
            "translation": {"mean": mt, "std": st},
            "scale": {"mean": ms[0], "std": ss[0]},
        }
    });
    PoseStats::from_json(&v, source)?;
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toy::{ToyConfig, ToySource};

    #[test]
    fn targets_of_a_toy_sample_are_consistent() -> Result<()> {
        let src = ToySource::new(ToyConfig { samples: 4, occluders: false, ..Default::default() })?;
        let s = src.sample(0)?;
        let mesh = src.model(s.model)?.mesh;
        let canon = canonical_frame(&mesh)?;
        // The camera pose maps canonical vertices onto the posed model.
        let cam = camera_pose(&s.views[0], &canon);
        for p in mesh.vertices.iter().take(10) {
            let q = canon.to_canonical(*p);
            let v = &s.views[0];
            for i in 0..3 {
                let want = (0..3).map(|k| v.r[i][k] * p[k]).sum::<f64>() + v.t[i];
                let got = cam.scale as f64 * (0..3).map(|k| cam.rotation[i][k] as f64 * q[k]).sum::<f64>() + cam.translation[i] as f64;
                assert!((want - got).abs() < 1e-5, "{want} vs {got}");
            }
        }
        // The normalised-frame pose puts the object near the normalised centre
        // (its box centre lies behind the visible surface, so z is larger)
        // with a size of order 1 (the normaliser's diameter is ~2× the spread).
        let tv = prepare_train_view(&s.views[0], &canon, 28, 1.5)?;
        assert_eq!(tv.pixels.dims(), &[1, 3, 28, 28]);
        assert!(tv.pose.translation.iter().all(|t| (t - 0.5).abs() < 1.0), "{:?}", tv.pose.translation);
        assert!(tv.pose.scale > 0.3 && tv.pose.scale < 5.0, "{}", tv.pose.scale);
        let occ = occupancy(&mesh, 16, Fill::Solid)?;
        let n = occ.sum_all()?.to_scalar::<f32>()?;
        assert!(n > 50.0 && n < 4096.0, "{n} occupied");
        // Stats over the scan parse as PoseStats and z-score the mean pose to ~0.
        let scan = scan(&src)?;
        assert_eq!(scan.usable.len(), 4);
        let v = pose_stats_json(&scan.poses, NineDLayout::PipelineColumns, "toy")?;
        let stats = PoseStats::from_json(&v, "toy")?;
        let mean10: Vec<f32> = (0..10).map(|k| scan.poses.iter().map(|p| p.to_10d()[k]).sum::<f32>() / scan.poses.len() as f32).collect();
        assert!(stats.normalize(&mean10)?.iter().all(|x| x.abs() < 1e-4));
        assert!(pose_stats_json(&[], NineDLayout::RowMajor, "none").is_err());
        Ok(())
    }
}
