//! `recon eval --method recgen`: the model itself as the predictor. Every
//! GT instance of every frame is reconstructed from its visible mask (the
//! inference path of `recon infer`: preprocessing, both stages, samples and
//! pose selection, decimation), and its camera-frame mesh is written as the
//! prediction (identity placement, `model_frame: false`: the surface
//! metrics ADD-SB, CD_norm, DRE and F1 score it; ADD/ADD-S need a GT-model
//! frame and are not defined).
//!
//! **Two views** ([`recgen_dataset`] with `two_view`): each frame is paired
//! with the next frame of its scene (cyclically, [`partners`]) and every object seen in
//! both is reconstructed from both (RecGen two-view conditioning, the
//! relative camera pose from the frames' world poses, pose selection across
//! views); results stay in the first frame's camera, scored against its GT.
//!
//! **N views** ([`recgen_dataset_views`]): each frame with the next N − 1
//! frames of its scene (cyclically; fewer when the scene has fewer), every
//! object seen in another frame reconstructed from all the frames it is seen
//! in (pair fusion beyond two views, as `recon infer --view`). Without camera
//! poses (YCB-Video) the relative pose comes from the GT pose of an object
//! both frames annotate ([`relative_pose_from_objects`]: the scene's objects
//! stay put).

use std::path::{Path, PathBuf};

use crate::baseline::{mesh_name, visible_mask, write_predictions, ObservedSkip};
use crate::correction::DatasetCorrection;
use crate::report::in_occlusion;
use crate::report::Prediction;
use recon_core::dataset::bop::{Dataset, Frame};
use recon_core::dataset::frame::{FrameOptions, Intrinsics, RgbdFrame};
use recon_core::dataset::masks::{InstanceMap, ObjectMask};
use recon_core::engine::infer::{Engine, InferSettings, SecondView};
use recon_core::geometry::pose::Pose;
use recon_core::math::Similarity;
use recon_core::mesh::Mesh;
use recon_core::{Error, Result};

pub struct RecgenPrediction {
    pub prediction: Prediction,
    /// Camera frame, metres.
    pub mesh: Mesh,
    /// The selected pose: canonical object frame → camera (metres), and the
    /// number of views the object was reconstructed from.
    pub pose: Pose,
    pub views: usize,
}

impl RecgenPrediction {
    /// One line of `recon-output.json`'s `poses` (what the model predicted, for diagnosis).
    pub fn pose_record(&self) -> serde_json::Value {
        let p = &self.prediction;
        serde_json::json!({
            "scene": p.scene, "frame": p.frame, "gt_index": p.gt_index, "obj_id": p.obj_id,
            "rotation": self.pose.rotation, "translation_m": self.pose.translation, "scale_m": self.pose.scale, "views": self.views,
        })
    }
}

/// Camera 2 → camera 1 of two frames with world poses (`None` without them).
pub fn relative_pose(f1: &Frame, f2: &Frame) -> Option<Similarity> {
    let ((r1, t1), (r2, t2)) = (f1.cam_w2c?, f2.cam_w2c?);
    // T_c1_c2 = T_c1_w · T_c2_w⁻¹
    Some(Similarity::rigid(r1, t1).compose(&(Similarity::rigid(r2, t2)).inverse()))
}

/// Camera 2 → camera 1 from an object both frames annotate (frame 1's first
/// such, in annotation order): `T_c1_obj · T_c2_obj⁻¹`. For datasets without
/// camera poses whose objects stay put between frames (YCB-Video).
pub fn relative_pose_from_objects(f1: &Frame, f2: &Frame) -> Option<Similarity> {
    f1.gt.iter().find_map(|g1| {
        let g2 = f2.gt.iter().find(|g| g.obj_id == g1.obj_id)?;
        Some(Similarity::rigid(g1.r, g1.t).compose(&Similarity::rigid(g2.r, g2.t).inverse()))
    })
}

/// Camera 2 → camera 1: from the frames' world poses, else from an object both annotate.
pub fn frame_relative_pose(f1: &Frame, f2: &Frame) -> Option<Similarity> {
    relative_pose(f1, f2).or_else(|| relative_pose_from_objects(f1, f2))
}

#[derive(Default)]
pub struct RecgenRun {
    pub predictions: Vec<RecgenPrediction>,
    pub skipped: Vec<ObservedSkip>,
    pub seconds_model: f64,
}

fn open_frame(ds: &Dataset, f: &Frame, correction: Option<&DatasetCorrection>) -> Result<RgbdFrame> {
    let at = || format!("{} scene {} frame {}", ds.root.display(), f.scene, f.frame);
    let k = Intrinsics::new(f.k[0][0], f.k[1][1], f.k[0][2], f.k[1][2]).map_err(|e| Error::input(at(), e.to_string()))?;
    let fo =
        FrameOptions { depth: Some(ds.depth_path(f)), intrinsics: Some(k), intrinsics_file: None, depth_scale_m: Some(f.depth_scale_m) };
    let mut frame = RgbdFrame::open(&ds.rgb_path(f), &fo)?;
    if let Some(c) = correction {
        frame.depth_m = c.apply(f, &frame.depth_m, frame.width, frame.height, &frame.intrinsics);
    }
    Ok(frame)
}

/// The frames paired with frame `i` for `others + 1`-view evaluation: of the
/// next `others` frames of its scene (cyclically, at most the scene's other
/// frames), those related to it by a relative pose ([`frame_relative_pose`]).
pub fn partners(ds: &Dataset, i: usize, others: usize) -> Vec<usize> {
    let f = &ds.frames[i];
    let same: Vec<usize> = (0..ds.frames.len()).filter(|&j| ds.frames[j].scene == f.scene).collect();
    let Some(pos) = same.iter().position(|&j| j == i) else { return Vec::new() };
    (1..same.len().min(others + 1))
        .map(|k| same[(pos + k) % same.len()])
        .filter(|&j| frame_relative_pose(f, &ds.frames[j]).is_some())
        .collect()
}

/// Reconstructs every GT instance of one frame; with `others` (view 2, 3, …),
/// objects also visible there (matched by `obj_id`) are reconstructed from
/// every frame they are seen in. With `occlusion`, only GT instances in that
/// occlusion range (percent, [`in_occlusion`]) are reconstructed. With `correction`,
/// every view's depth is corrected first.
pub fn recgen_frame_views(
    ds: &Dataset,
    f: &Frame,
    others: &[&Frame],
    engine: &Engine,
    opts: &InferSettings,
    occlusion: Option<[f64; 2]>,
    correction: Option<&DatasetCorrection>,
) -> Result<RecgenRun> {
    let keep = |gi: usize| in_occlusion(&f.gt[gi], occlusion);
    // The metrics read geometry only: no texture is baked.
    let plain = InferSettings { colour: recon_core::engine::MeshColour::Vertex, ..opts.clone() };
    let opts = &plain;
    let mut run = RecgenRun::default();
    if !(0..f.gt.len()).any(keep) {
        return Ok(run);
    }
    let frame = open_frame(ds, f, correction)?;
    let mut label: Option<InstanceMap> = None;
    let mut masks = Vec::with_capacity(f.gt.len());
    for gi in (0..f.gt.len()).filter(|&gi| keep(gi)) {
        let (w, h, mask, _) = visible_mask(ds, f, gi, &mut label)?;
        masks.push(ObjectMask::from_bools(Some(gi as u32), format!("gt {gi}"), w, h, &mask));
    }
    let mut opened = Vec::with_capacity(others.len());
    for (i, f2) in others.iter().enumerate() {
        let rel = frame_relative_pose(f, f2).ok_or_else(|| {
            Error::input(
                ds.root.display().to_string(),
                format!(
                    "scene {}: frames {} and {} need cam_R_w2c/cam_t_w2c, or an object both annotate, for several views",
                    f.scene, f.frame, f2.frame
                ),
            )
        })?;
        let frame2 = open_frame(ds, f2, correction)?;
        let mut label2: Option<InstanceMap> = None;
        let mut masks2 = Vec::new();
        for (gj, g2) in f2.gt.iter().enumerate() {
            // The same instance in frame 1 (ids of frame 1's masks are its GT indices).
            let Some(gi) = f.gt.iter().position(|g| g.obj_id == g2.obj_id).filter(|&gi| keep(gi)) else { continue };
            let (w, h, mask, _) = visible_mask(ds, f2, gj, &mut label2)?;
            if mask.iter().any(|&b| b) {
                masks2.push(ObjectMask::from_bools(Some(gi as u32), format!("view {} gt {gj}", i + 2), w, h, &mask));
            }
        }
        opened.push((frame2, masks2, rel));
    }
    let t0 = std::time::Instant::now();
    let r = if opened.is_empty() {
        engine.reconstruct(&frame, masks, opts)?
    } else {
        let views =
            opened.iter().map(|(frame2, masks2, rel)| SecondView { frame: frame2, objects: masks2.clone(), t_c1_c2: *rel }).collect();
        engine.reconstruct_views(&frame, masks, views, opts, &|_| {})?
    };
    run.seconds_model = t0.elapsed().as_secs_f64();
    for s in r.skipped {
        let gi: usize = s.label.trim_start_matches("gt ").parse().unwrap_or(usize::MAX);
        let obj_id = f.gt.get(gi).map_or(0, |g| g.obj_id);
        run.skipped.push(ObservedSkip { scene: f.scene.clone(), frame: f.frame, gt_index: gi, obj_id, reason: s.to_string() });
    }
    for o in r.objects {
        let gi = o.id.ok_or_else(|| Error::msg("recgen eval: object without id"))? as usize;
        let obj_id = f.gt[gi].obj_id;
        let Some(mesh) = o.mesh_camera else {
            run.skipped.push(ObservedSkip {
                scene: f.scene.clone(),
                frame: f.frame,
                gt_index: gi,
                obj_id,
                reason: "no mesh decoded".into(),
            });
            continue;
        };
        if mesh.faces.is_empty() {
            run.skipped.push(ObservedSkip { scene: f.scene.clone(), frame: f.frame, gt_index: gi, obj_id, reason: "empty mesh".into() });
            continue;
        }
        let prediction = Prediction {
            scene: f.scene.clone(),
            frame: f.frame,
            obj_id,
            gt_index: Some(gi),
            r: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            t: [0.0; 3],
            scale: 1.0,
            mesh: Some(PathBuf::from("meshes").join(mesh_name(&f.scene, f.frame, gi, obj_id))),
            model_frame: false,
        };
        run.predictions.push(RecgenPrediction { prediction, mesh, pose: o.pose_camera, views: o.views.len() });
    }
    Ok(run)
}

/// Every frame of `ds`, in order (with `two_view`, each with its `partner`;
/// frames without one are reconstructed from one view); `progress(done, total)` after each frame.
pub fn recgen_dataset(
    ds: &Dataset,
    engine: &Engine,
    opts: &InferSettings,
    two_view: bool,
    occlusion: Option<[f64; 2]>,
    progress: &dyn Fn(usize, usize),
) -> Result<RecgenRun> {
    recgen_dataset_views(ds, engine, opts, if two_view { 2 } else { 1 }, occlusion, progress)
}

/// Every frame of `ds`, in order, each with its next `views − 1` frames
/// ([`partners`]; `views` 2 is [`recgen_dataset`]'s `two_view`); frames
/// without partners are reconstructed from one view.
pub fn recgen_dataset_views(
    ds: &Dataset,
    engine: &Engine,
    opts: &InferSettings,
    views: usize,
    occlusion: Option<[f64; 2]>,
    progress: &dyn Fn(usize, usize),
) -> Result<RecgenRun> {
    recgen_dataset_corrected(ds, engine, opts, views, occlusion, None, progress)
}

/// [`recgen_dataset_views`] on depth corrected by `correction` first (`recon eval
/// --depth-correction`).
pub fn recgen_dataset_corrected(
    ds: &Dataset,
    engine: &Engine,
    opts: &InferSettings,
    views: usize,
    occlusion: Option<[f64; 2]>,
    correction: Option<&DatasetCorrection>,
    progress: &dyn Fn(usize, usize),
) -> Result<RecgenRun> {
    let mut all = RecgenRun::default();
    for (i, f) in ds.frames.iter().enumerate() {
        let others: Vec<&Frame> = partners(ds, i, views.saturating_sub(1)).into_iter().map(|j| &ds.frames[j]).collect();
        let r = recgen_frame_views(ds, f, &others, engine, opts, occlusion, correction)?;
        all.predictions.extend(r.predictions);
        all.skipped.extend(r.skipped);
        all.seconds_model += r.seconds_model;
        progress(i + 1, ds.frames.len());
    }
    Ok(all)
}

impl RecgenRun {
    /// Writes `dir/predictions.json` and `dir/meshes/*.ply` (camera frame, metres).
    pub fn write(&self, dir: &Path) -> Result<PathBuf> {
        write_predictions(dir, self.predictions.iter().map(|p| (&p.prediction, std::borrow::Cow::Borrowed(&p.mesh))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use recon_core::dataset::bop::GtInstance;

    fn rot(axis: usize, a: f64) -> [[f64; 3]; 3] {
        let (c, s) = (a.cos(), a.sin());
        let (i, j) = ((axis + 1) % 3, (axis + 2) % 3);
        let mut r = [[0.0; 3]; 3];
        r[axis][axis] = 1.0;
        r[i][i] = c;
        r[i][j] = -s;
        r[j][i] = s;
        r[j][j] = c;
        r
    }

    fn frame(scene: &str, id: u32, w2c: Option<([[f64; 3]; 3], [f64; 3])>) -> Frame {
        Frame {
            scene: scene.into(),
            frame: id,
            k: [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]],
            depth_scale_m: 1e-3,
            gt: Vec::new(),
            cam_w2c: w2c,
        }
    }

    fn apply(r: &[[f64; 3]; 3], t: &[f64; 3], x: &[f64; 3]) -> [f64; 3] {
        std::array::from_fn(|i| (0..3).map(|k| r[i][k] * x[k]).sum::<f64>() + t[i])
    }

    #[test]
    fn relative_pose_maps_camera_2_points_to_camera_1() {
        let (r1, t1) = (rot(0, 0.7), [0.1, -0.2, 0.9]);
        let (r2, t2) = (rot(1, -1.1), [-0.3, 0.05, 1.2]);
        let f1 = frame("a", 0, Some((r1, t1)));
        let f2 = frame("a", 1, Some((r2, t2)));
        let rel = relative_pose(&f1, &f2).unwrap();
        let xw = [0.2, 0.4, -0.1];
        let (x1, x2) = (apply(&r1, &t1, &xw), apply(&r2, &t2, &xw));
        let got = apply(&rel.rotation, &rel.translation, &x2);
        for k in 0..3 {
            assert!((got[k] - x1[k]).abs() < 1e-12, "{got:?} vs {x1:?}");
        }
        assert!(relative_pose(&f1, &frame("a", 2, None)).is_none());
        // The same from an object both frames see (no camera poses): T_ci_obj = T_ci_w · T_w_obj.
        let (ro, to) = (rot(2, 0.4), [0.05, 0.1, -0.2]);
        let obj = |r: &[[f64; 3]; 3], t: &[f64; 3]| {
            let s = Similarity::rigid(*r, *t).compose(&Similarity::rigid(ro, to));
            GtInstance { obj_id: 7, r: s.rotation, t: s.translation, visib_fract: None, visib_estimated: false, bbox_visib: None }
        };
        let (mut g1, mut g2) = (frame("y", 1, None), frame("y", 2, None));
        g1.gt.push(obj(&r1, &t1));
        g2.gt.push(obj(&r2, &t2));
        let rel = relative_pose_from_objects(&g1, &g2).unwrap();
        let got = apply(&rel.rotation, &rel.translation, &x2);
        for k in 0..3 {
            assert!((got[k] - x1[k]).abs() < 1e-9, "{got:?} vs {x1:?}");
        }
        assert!(frame_relative_pose(&g1, &g2).is_some() && relative_pose(&g1, &g2).is_none());
        g2.gt[0].obj_id = 8;
        assert!(frame_relative_pose(&g1, &g2).is_none());
    }

    #[test]
    fn partner_is_the_next_frame_of_the_same_scene() {
        let p = Some((rot(2, 0.0), [0.0; 3]));
        let ds = Dataset {
            frames: vec![frame("a", 0, p), frame("a", 3, p), frame("a", 5, p), frame("b", 0, p), frame("c", 0, p), frame("c", 1, None)],
            ..Default::default()
        };
        let partner = |i: usize| partners(&ds, i, 1).first().copied();
        assert_eq!((0..6).map(partner).collect::<Vec<_>>(), vec![Some(1), Some(2), Some(0), None, None, None]);
        // N views: the next frames in turn, at most the scene's others; the first is `partner`'s.
        assert_eq!(partners(&ds, 1, 3), vec![2, 0]);
        assert_eq!(partners(&ds, 2, 1), vec![0]);
        assert_eq!(partners(&ds, 0, 0), Vec::<usize>::new());
        assert_eq!(partners(&ds, 3, 3), Vec::<usize>::new());
        assert_eq!((partners(&ds, 4, 3), partners(&ds, 5, 3)), (vec![], vec![]));
    }
}
