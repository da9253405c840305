//! Training data from a BOP-format folder, the format `recon synth` writes:
//! `<split>/<scene>/{rgb,depth,mask_visib}/`, `scene_gt.json`,
//! `scene_camera.json` (optionally `scene_gt_info.json`) and
//! `models/obj_XXXXXX.ply` in millimetres. Annotations and models are read
//! by [`recon_core::dataset::bop::load_bop`]; images are read when a sample is
//! asked for.
//!
//! One sample per annotated instance (`scene_gt.json[frame][j]`, visible
//! mask `mask_visib/<frame>_<j>.png`) whose `visib_fract` (when known) is at
//! least `min_visib_fract`. With `second_view`, the sample's second view is
//! the next frame (cyclically) of the same scene showing the same object
//! exactly once.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::data::{ModelEntry, ObjectSample, ObjectView, TrainingSource};
use recon_core::dataset::bop::{load_bop, Dataset};
use recon_core::dataset::frame::{FrameOptions, Intrinsics, RgbdFrame};
use recon_core::dataset::masks::load_binary_mask;
use recon_core::{Error, Result};

#[derive(Debug, Clone)]
/// Which annotated instances of a BOP folder become samples.
pub struct BopOptions {
    /// Smallest visible fraction of an instance (when annotated).
    pub min_visib_fract: f64,
    /// Give each sample a second view (the next frame of the scene showing the object once).
    pub second_view: bool,
}

impl Default for BopOptions {
    fn default() -> Self {
        Self { min_visib_fract: 0.1, second_view: true }
    }
}

#[derive(Debug, Clone, Copy)]
struct InstanceRef {
    frame: usize,
    gt: usize,
}

/// Training data read from a BOP-format folder (module docs).
pub struct BopSource {
    root: PathBuf,
    ds: Dataset,
    model_ids: Vec<u32>,
    meshes: Vec<Arc<recon_core::mesh::trimesh::TriMesh>>,
    colors: Vec<Option<Arc<Vec<[f32; 3]>>>>,
    samples: Vec<(usize, InstanceRef, Option<InstanceRef>)>,
}

impl BopSource {
    /// `split_dir` holds the scene folders; `models_dir` the PLY models
    /// (for `recon synth` output: `<out>/train` and `<out>/models`).
    pub fn open(split_dir: &Path, models_dir: &Path, opts: &BopOptions) -> Result<Self> {
        let ds = load_bop(split_dir, models_dir)?;
        let model_ids: Vec<u32> = ds.models.keys().copied().collect();
        let index: BTreeMap<u32, usize> = model_ids.iter().enumerate().map(|(i, id)| (*id, i)).collect();
        // Frames of each scene in order, for second views.
        let mut by_scene: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
        for (fi, f) in ds.frames.iter().enumerate() {
            by_scene.entry(f.scene.as_str()).or_default().push(fi);
        }
        let mut samples = Vec::new();
        for (fi, f) in ds.frames.iter().enumerate() {
            for (gi, g) in f.gt.iter().enumerate() {
                if g.visib_fract.is_some_and(|v| v < opts.min_visib_fract) {
                    continue;
                }
                let second = if opts.second_view {
                    let frames = &by_scene[f.scene.as_str()];
                    let pos = frames.iter().position(|&x| x == fi).unwrap_or(0);
                    (1..frames.len()).map(|d| frames[(pos + d) % frames.len()]).find_map(|other| {
                        let hits: Vec<usize> =
                            ds.frames[other].gt.iter().enumerate().filter(|(_, h)| h.obj_id == g.obj_id).map(|(i, _)| i).collect();
                        let visible = |i: usize| ds.frames[other].gt[i].visib_fract.is_none_or(|v| v >= opts.min_visib_fract);
                        (hits.len() == 1 && visible(hits[0])).then(|| InstanceRef { frame: other, gt: hits[0] })
                    })
                } else {
                    None
                };
                samples.push((index[&g.obj_id], InstanceRef { frame: fi, gt: gi }, second));
            }
        }
        if samples.is_empty() {
            return Err(Error::input(
                split_dir.display().to_string(),
                format!("no annotated instance with visib_fract ≥ {}", opts.min_visib_fract),
            ));
        }
        let meshes = model_ids.iter().map(|id| Arc::new(ds.models[id].mesh.clone())).collect();
        // Vertex colours (stage-2 supervision); models without them stay uncoloured.
        let colors = model_ids
            .iter()
            .map(|id| {
                let m = &ds.models[id];
                let is_ply = m.path.extension().is_some_and(|e| e.eq_ignore_ascii_case("ply"));
                Ok(if is_ply { recon_core::dataset::ply::read_ply_with_colors(&m.path)?.1.map(Arc::new) } else { None })
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { root: split_dir.to_path_buf(), ds, model_ids, meshes, colors, samples })
    }

    fn view(&self, r: InstanceRef) -> Result<ObjectView> {
        let f = &self.ds.frames[r.frame];
        let scene = self.root.join(&f.scene);
        let name = format!("{:06}", f.frame);
        let rgb = ["png", "jpg"]
            .iter()
            .map(|e| scene.join("rgb").join(format!("{name}.{e}")))
            .find(|p| p.is_file())
            .ok_or_else(|| Error::input(scene.join("rgb").display().to_string(), format!("no {name}.png or {name}.jpg")))?;
        let k = Intrinsics::new(f.k[0][0], f.k[1][1], f.k[0][2], f.k[1][2])?;
        let opts = FrameOptions {
            depth: Some(scene.join("depth").join(format!("{name}.png"))),
            intrinsics: Some(k),
            intrinsics_file: None,
            depth_scale_m: Some(f.depth_scale_m),
        };
        let frame = RgbdFrame::open(&rgb, &opts)?;
        let mp = scene.join("mask_visib").join(format!("{name}_{:06}.png", r.gt));
        let m = load_binary_mask(&mp)?;
        if (m.width, m.height) != (frame.width, frame.height) {
            return Err(Error::input(
                mp.display().to_string(),
                format!("mask is {}×{}, the frame {}×{}", m.width, m.height, frame.width, frame.height),
            ));
        }
        let g = &f.gt[r.gt];
        Ok(ObjectView { frame: Arc::new(frame), mask: m.to_bools(), r: g.r, t: g.t })
    }
}

impl TrainingSource for BopSource {
    fn describe(&self) -> String {
        format!(
            "BOP {} ({} frames, {} models, {} instances)",
            self.root.display(),
            self.ds.frames.len(),
            self.model_ids.len(),
            self.samples.len()
        )
    }
    fn num_models(&self) -> usize {
        self.model_ids.len()
    }
    fn model(&self, i: usize) -> Result<ModelEntry> {
        let id = *self.model_ids.get(i).ok_or_else(|| Error::msg(format!("BOP source: no model {i}")))?;
        Ok(ModelEntry { key: self.ds.models[&id].name.clone(), mesh: self.meshes[i].clone(), colors: self.colors[i].clone() })
    }
    fn num_samples(&self) -> usize {
        self.samples.len()
    }
    fn sample(&self, i: usize) -> Result<ObjectSample> {
        let &(model, first, second) = self.samples.get(i).ok_or_else(|| Error::msg(format!("BOP source: no sample {i}")))?;
        let mut views = vec![self.view(first)?];
        if let Some(s) = second {
            views.push(self.view(s)?);
        }
        Ok(ObjectSample { model, views })
    }
}
