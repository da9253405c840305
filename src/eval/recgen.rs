//! `recon eval --method recgen`: the model itself as the predictor. Every
//! GT instance of every frame is reconstructed from its visible mask (the
//! inference path of `recon infer`: preprocessing, both stages, samples and
//! pose selection, decimation), and its camera-frame mesh is written as the
//! prediction (identity placement, `model_frame: false`: the surface
//! metrics ADD-SB, CD_norm, DRE and F1 score it; ADD/ADD-S need a GT-model
//! frame and are not defined).

use std::path::{Path, PathBuf};

use super::baseline::{mesh_name, visible_mask, write_predictions, ObservedSkip};
use super::bop::{Dataset, Frame};
use super::report::Prediction;
use crate::decoders::Mesh;
use crate::infer::{Engine, InferOptions};
use crate::inputs::frame::{FrameOptions, Intrinsics, RgbdFrame};
use crate::inputs::masks::{InstanceMap, ObjectMask};
use crate::{Error, Result};

pub struct RecgenPrediction {
    pub prediction: Prediction,
    /// Camera frame, metres.
    pub mesh: Mesh,
}

#[derive(Default)]
pub struct RecgenRun {
    pub predictions: Vec<RecgenPrediction>,
    pub skipped: Vec<ObservedSkip>,
    pub seconds_model: f64,
}

/// Reconstructs every GT instance of one frame.
pub fn recgen_frame(ds: &Dataset, f: &Frame, engine: &Engine, opts: &InferOptions) -> Result<RecgenRun> {
    let at = || format!("{} scene {} frame {}", ds.root.display(), f.scene, f.frame);
    let k = Intrinsics::new(f.k[0][0], f.k[1][1], f.k[0][2], f.k[1][2]).map_err(|e| Error::input(at(), e.to_string()))?;
    let fo = FrameOptions { depth: Some(ds.depth_path(f)), intrinsics: Some(k), intrinsics_file: None, depth_scale: Some(f.depth_scale_mm * 1e-3) };
    let frame = RgbdFrame::open(&ds.rgb_path(f), &fo)?;
    let mut label: Option<InstanceMap> = None;
    let mut masks = Vec::with_capacity(f.gt.len());
    for gi in 0..f.gt.len() {
        let (w, h, mask, _) = visible_mask(ds, f, gi, &mut label)?;
        masks.push(ObjectMask { id: Some(gi as u32), label: format!("gt {gi}"), width: w, height: h, mask });
    }
    let t0 = std::time::Instant::now();
    let r = engine.reconstruct(&frame, masks, opts)?;
    let mut run = RecgenRun { seconds_model: t0.elapsed().as_secs_f64(), ..Default::default() };
    for s in r.skipped {
        let gi: usize = s.label.trim_start_matches("gt ").parse().unwrap_or(usize::MAX);
        let obj_id = f.gt.get(gi).map_or(0, |g| g.obj_id);
        run.skipped.push(ObservedSkip { scene: f.scene.clone(), frame: f.frame, gt_index: gi, obj_id, reason: s.to_string() });
    }
    for o in r.objects {
        let gi = o.id.ok_or_else(|| Error::msg("recgen eval: object without id"))? as usize;
        let obj_id = f.gt[gi].obj_id;
        let Some(mesh) = o.mesh_camera else {
            run.skipped.push(ObservedSkip { scene: f.scene.clone(), frame: f.frame, gt_index: gi, obj_id, reason: "no mesh decoded".into() });
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
        run.predictions.push(RecgenPrediction { prediction, mesh });
    }
    Ok(run)
}

/// Every frame of `ds`, in order; `progress(done, total)` after each frame.
pub fn recgen_dataset(ds: &Dataset, engine: &Engine, opts: &InferOptions, progress: &dyn Fn(usize, usize)) -> Result<RecgenRun> {
    let mut all = RecgenRun::default();
    for (i, f) in ds.frames.iter().enumerate() {
        let r = recgen_frame(ds, f, engine, opts)?;
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
