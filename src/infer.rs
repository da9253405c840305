//! `recon infer` as a library: RGB-D frame + object masks → per-object pose,
//! mesh and Gaussians in the metric camera frame.
//!
//! ```no_run
//! use recon::infer::{Engine, InferOptions};
//! use recon::inputs::frame::{FrameOptions, RgbdFrame};
//! use recon::inputs::masks::InstanceMap;
//! # fn main() -> recon::Result<()> {
//! let engine = Engine::random("models/recgen-tiny.json".as_ref(), 0)?; // or Engine::load(config, weights_dir)
//! let frame = RgbdFrame::open("data/sample/000001-color.png".as_ref(), &FrameOptions::default())?;
//! let (objects, _skipped) = InstanceMap::open("data/sample/000001-label.png".as_ref())?.objects(None);
//! let result = engine.reconstruct(&frame, objects, &InferOptions::default())?;
//! for o in &result.objects { println!("{} {:?}", o.label, o.pose_camera.translation); }
//! # Ok(()) }
//! ```
//!
//! The model is loaded once ([`Engine`]) and reused for every object.
//! Objects that fail validation or preprocessing are reported in
//! [`FrameResult::skipped`] and do not stop the others.

use crate::decoders::Mesh;
use crate::export::glb::{save_glb, GlbOptions};
use crate::export::ply::{save_mesh_ply, PlyOptions};
use crate::export::splat::{save_splat_ply, Gaussians};
use crate::export::Axes;
use crate::geometry::camera_pose::{canonical_to_camera, pose_to_camera};
use crate::geometry::pointmap::{prepare_frame_objects, PrepareOptions};
use crate::geometry::pose::Pose;
use crate::inputs::frame::RgbdFrame;
use crate::inputs::masks::{MaskSkip, ObjectMask};
use crate::pipeline::{LoadOptions, ObjectInputs, Pipeline, RunMetadata, RunOptions, StageTimings, Stages, ViewInput};
use crate::{Error, Result};
use candle_core::Device;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Per-frame settings.
#[derive(Debug, Clone)]
pub struct InferOptions {
    pub run: RunOptions,
    /// Minimum eroded-mask pixels with valid depth for an object to run.
    pub min_valid_depth_pixels: usize,
    pub prepare: PrepareOptions,
}

impl Default for InferOptions {
    fn default() -> Self {
        Self { run: RunOptions::default(), min_valid_depth_pixels: 100, prepare: PrepareOptions::default() }
    }
}

/// A loaded model, reused across objects and frames.
pub struct Engine {
    pub pipeline: Pipeline,
}

/// One reconstructed object.
#[derive(Debug, Clone)]
pub struct ObjectResult {
    pub label: String,
    pub id: Option<u32>,
    /// Canonical object frame → normalised pointmap frame (as predicted).
    pub pose_normalised: Pose,
    /// Canonical object frame → metric camera frame.
    pub pose_camera: Pose,
    pub occupied_voxels: usize,
    /// Mesh and Gaussians placed in the camera frame (metres).
    pub mesh_camera: Option<Mesh>,
    pub gaussians_camera: Option<Gaussians>,
    /// Observed object points (camera frame, metres) that entered the normaliser.
    pub observed_points: Vec<[f32; 3]>,
    pub timings: StageTimings,
    pub metadata: RunMetadata,
}

/// Everything one frame produces.
#[derive(Debug, Clone)]
pub struct FrameResult {
    pub objects: Vec<ObjectResult>,
    /// Objects left out, with the reason (validation, preprocessing or model failure).
    pub skipped: Vec<MaskSkip>,
    pub preprocess_seconds: f64,
}

impl Engine {
    /// Trained (or `recon weights init`) weights from `weights_dir`.
    pub fn load(config: &Path, weights_dir: &Path) -> Result<Self> {
        Ok(Self { pipeline: Pipeline::load(config, weights_dir)? })
    }

    /// In-memory random weights: NOT a trained model (results say so).
    pub fn random(config: &Path, seed: u64) -> Result<Self> {
        Ok(Self { pipeline: Pipeline::random(config, seed)? })
    }

    /// [`Engine::load`] with explicit kernels/precision (`--dtype`) and residency.
    pub fn load_with(config: &Path, weights_dir: &Path, options: &LoadOptions) -> Result<Self> {
        Ok(Self { pipeline: Pipeline::load_with(config, weights_dir, Stages::All, options)? })
    }

    /// [`Engine::random`] with explicit kernels/precision and residency.
    pub fn random_with(config: &Path, seed: u64, options: &LoadOptions) -> Result<Self> {
        Ok(Self { pipeline: Pipeline::random_with(config, seed, Stages::All, options)? })
    }

    /// Reconstruct every object of a frame (single view).
    pub fn reconstruct(&self, frame: &RgbdFrame, objects: Vec<ObjectMask>, opts: &InferOptions) -> Result<FrameResult> {
        let t0 = std::time::Instant::now();
        let size = self.pipeline.image_size();
        let (prepared, mut skipped) =
            prepare_frame_objects(frame, objects, size, opts.min_valid_depth_pixels, &opts.prepare, &Device::Cpu);
        let preprocess_seconds = t0.elapsed().as_secs_f64();
        let mut results = Vec::new();
        for p in prepared {
            let v = &p.view;
            let inputs = ObjectInputs {
                views: vec![ViewInput { pixels: v.pixel_values.clone(), pointmap: v.pointmap.clone(), mask: v.mask.clone() }],
            };
            let rec = match self.pipeline.run(&inputs, &opts.run) {
                Ok(r) => r,
                Err(e) => {
                    skipped.push(MaskSkip {
                        label: p.object.label.clone(),
                        reason: crate::inputs::masks::SkipReason::Preprocessing(format!("model: {e}")),
                    });
                    continue;
                }
            };
            let pose_n = rec.pose.pose;
            let sim = canonical_to_camera(&pose_n, &v.normaliser)?;
            let observed = crate::geometry::pointmap::object_points(frame, &v.mask_full, None)?
                .0
                .iter()
                .map(|q| [q[0] as f32, q[1] as f32, q[2] as f32])
                .collect();
            results.push(ObjectResult {
                label: p.object.label.clone(),
                id: p.object.id,
                pose_normalised: pose_n,
                pose_camera: pose_to_camera(&pose_n, &v.normaliser),
                occupied_voxels: rec.coords.len(),
                mesh_camera: rec.mesh.as_ref().map(|m| sim.apply_mesh(m)),
                gaussians_camera: rec.gaussians.as_ref().map(|g| sim.apply_gaussians(g)),
                observed_points: observed,
                timings: rec.timings,
                metadata: rec.metadata,
            });
        }
        Ok(FrameResult { objects: results, skipped, preprocess_seconds })
    }
}

/// The pose file written per object.
#[derive(Debug, Serialize)]
pub struct PoseRecord<'a> {
    pub object: &'a str,
    pub id: Option<u32>,
    pub frame: &'static str,
    /// `x_camera = scale · rotation · x_object + translation`, metres; object
    /// frame = the decoder's canonical [-0.5, 0.5]³ (z up).
    pub rotation: [[f32; 3]; 3],
    pub translation_m: [f32; 3],
    pub scale_m: f32,
    pub pose_normalised: PoseJson,
    pub occupied_voxels: usize,
    pub timings_s: &'a StageTimings,
    pub run: &'a RunMetadata,
}

#[derive(Debug, Serialize)]
pub struct PoseJson {
    pub rotation: [[f32; 3]; 3],
    pub translation: [f32; 3],
    pub scale: f32,
}

/// Paths written for one object.
#[derive(Debug, Clone, Serialize)]
pub struct WrittenObject {
    pub object: String,
    pub pose: PathBuf,
    pub mesh_glb: Option<PathBuf>,
    pub mesh_ply: Option<PathBuf>,
    pub gaussians_ply: Option<PathBuf>,
}

/// Index file written last into every output folder; its presence marks a
/// complete recon output.
pub const MARKER: &str = "recon-output.json";

fn safe_name(label: &str) -> String {
    label.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}

/// Write per-object files, the scene GLB (all meshes in the camera frame)
/// and the observed points into `out`. Files are written to a staging
/// folder first and moved into place at the end, so an interrupted run never
/// leaves a complete-looking output.
///
/// An existing `out` is replaced only when it is an earlier recon output
/// (it holds [`MARKER`]); any other existing non-empty folder is an error.
pub fn write_outputs(result: &FrameResult, out: &Path) -> Result<Vec<WrittenObject>> {
    if out.exists() {
        let empty = std::fs::read_dir(out).map(|mut d| d.next().is_none()).unwrap_or(false);
        if !empty && !out.join(MARKER).exists() {
            return Err(Error::input(
                out.display().to_string(),
                format!("output folder exists and is not a recon output (no {MARKER}); remove it or choose another --out"),
            ));
        }
    }
    let staging = out.with_extension("partial");
    if staging.exists() {
        std::fs::remove_dir_all(&staging).map_err(|e| Error::io(&staging, e))?;
    }
    std::fs::create_dir_all(&staging).map_err(|e| Error::io(&staging, e))?;
    // Camera frame stays as is (OpenCV: x right, y down, z forward) in every file.
    let glb = GlbOptions { axes: Axes::ZUp, vertex_colors: true };
    let ply = PlyOptions { axes: Axes::ZUp, normals: true, vertex_colors: true };
    let mut written = Vec::new();
    let mut scene = Mesh::default();
    let mut observed = Mesh::default();
    for o in &result.objects {
        let name = safe_name(&o.label);
        let dir = staging.join(&name);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let rec = PoseRecord {
            object: &o.label,
            id: o.id,
            frame: "camera (OpenCV: x right, y down, z forward), metres",
            rotation: o.pose_camera.rotation,
            translation_m: o.pose_camera.translation,
            scale_m: o.pose_camera.scale,
            pose_normalised: PoseJson {
                rotation: o.pose_normalised.rotation,
                translation: o.pose_normalised.translation,
                scale: o.pose_normalised.scale,
            },
            occupied_voxels: o.occupied_voxels,
            timings_s: &o.timings,
            run: &o.metadata,
        };
        let pose_path = dir.join("pose.json");
        let text = serde_json::to_string_pretty(&rec).map_err(|e| Error::msg(e.to_string()))?;
        std::fs::write(&pose_path, text).map_err(|e| Error::io(&pose_path, e))?;
        let mut w = WrittenObject { object: o.label.clone(), pose: out.join(&name).join("pose.json"), mesh_glb: None, mesh_ply: None, gaussians_ply: None };
        if let Some(m) = o.mesh_camera.as_ref().filter(|m| !m.faces.is_empty()) {
            save_glb(m, &dir.join("mesh.glb"), &glb)?;
            save_mesh_ply(m, &dir.join("mesh.ply"), &ply)?;
            w.mesh_glb = Some(out.join(&name).join("mesh.glb"));
            w.mesh_ply = Some(out.join(&name).join("mesh.ply"));
            append_mesh(&mut scene, m);
        }
        if let Some(g) = o.gaussians_camera.as_ref().filter(|g| !g.is_empty()) {
            save_splat_ply(g, &dir.join("gaussians.ply"), Axes::ZUp)?;
            w.gaussians_ply = Some(out.join(&name).join("gaussians.ply"));
        }
        observed.vertices.extend_from_slice(&o.observed_points);
        written.push(w);
    }
    if !scene.faces.is_empty() {
        save_glb(&scene, &staging.join("scene.glb"), &glb)?;
    }
    if !observed.vertices.is_empty() {
        let pts = PlyOptions { axes: Axes::ZUp, normals: false, vertex_colors: false };
        save_mesh_ply(&observed, &staging.join("observed_points.ply"), &pts)?;
    }
    let index = serde_json::json!({ "objects": written, "skipped": result.skipped.iter().map(|s| s.to_string()).collect::<Vec<_>>() });
    let marker = staging.join(MARKER);
    std::fs::write(&marker, serde_json::to_string_pretty(&index).map_err(|e| Error::msg(e.to_string()))?)
        .map_err(|e| Error::io(&marker, e))?;
    if out.exists() {
        std::fs::remove_dir_all(out).map_err(|e| Error::io(out, e))?;
    }
    std::fs::rename(&staging, out).map_err(|e| Error::io(out, e))?;
    Ok(written)
}

fn append_mesh(scene: &mut Mesh, m: &Mesh) {
    let base = scene.vertices.len() as u32;
    scene.vertices.extend_from_slice(&m.vertices);
    scene.faces.extend(m.faces.iter().map(|f| [f[0] + base, f[1] + base, f[2] + base]));
    let attrs = m.vertex_attrs.clone().unwrap_or_else(|| vec![[0.7, 0.7, 0.7, 0.0, 0.0, 0.0]; m.vertices.len()]);
    scene.vertex_attrs.get_or_insert_with(Vec::new).extend(attrs);
}
