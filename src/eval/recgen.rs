//! `recon eval --method recgen`: the model itself as the predictor. Every
//! GT instance of every frame is reconstructed from its visible mask (the
//! inference path of `recon infer`: preprocessing, both stages, samples and
//! pose selection, decimation), and its camera-frame mesh is written as the
//! prediction (identity placement, `model_frame: false`: the surface
//! metrics ADD-SB, CD_norm, DRE and F1 score it; ADD/ADD-S need a GT-model
//! frame and are not defined).

use std::path::{Path, PathBuf};

use super::baseline::ObservedSkip;
use super::bop::{Dataset, Frame, MaskSource};
use super::report::{Prediction, PredictionsFile};
use crate::decoders::Mesh;
use crate::infer::{Engine, InferOptions};
use crate::inputs::frame::{FrameOptions, Intrinsics, RgbdFrame};
use crate::inputs::masks::{load_binary_mask, InstanceMap, ObjectMask};
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

fn mesh_name(scene: &str, frame: u32, gi: usize, obj_id: u32) -> String {
    let s: String = scene.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect();
    format!("{s}_{frame:06}_gt{gi:02}_obj{obj_id:06}.ply")
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
        let (w, h, mask) = match ds.visible_mask_source(f, gi) {
            MaskSource::Binary(p) => {
                let m = load_binary_mask(&p)?;
                (m.width, m.height, m.mask)
            }
            MaskSource::Label(p, id) => {
                if label.is_none() {
                    label = Some(InstanceMap::open(&p)?);
                }
                let l = label.as_ref().ok_or_else(|| Error::msg("label map"))?;
                (l.width, l.height, l.ids.iter().map(|&v| v == id).collect())
            }
        };
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
    pub fn predictions_file(&self) -> PredictionsFile {
        PredictionsFile { predictions: self.predictions.iter().map(|p| p.prediction.clone()).collect() }
    }

    /// Writes `dir/predictions.json` and `dir/meshes/*.ply` (camera frame, metres).
    pub fn write(&self, dir: &Path) -> Result<PathBuf> {
        use crate::export::{ply::save_mesh_ply, ply::PlyOptions, Axes};
        let meshes = dir.join("meshes");
        std::fs::create_dir_all(&meshes).map_err(|e| Error::io(&meshes, e))?;
        let opts = PlyOptions { axes: Axes::ZUp, normals: false, vertex_colors: false };
        for p in &self.predictions {
            let rel = p.prediction.mesh.as_ref().ok_or_else(|| Error::msg("recgen prediction without mesh"))?;
            let m = Mesh { vertices: p.mesh.vertices.clone(), faces: p.mesh.faces.clone(), vertex_attrs: None };
            save_mesh_ply(&m, &dir.join(rel), &opts)?;
        }
        let path = dir.join("predictions.json");
        let text = serde_json::to_string_pretty(&self.predictions_file()).map_err(|e| Error::msg(format!("serialising predictions: {e}")))?;
        std::fs::write(&path, text).map_err(|e| Error::io(&path, e))?;
        Ok(path)
    }
}
