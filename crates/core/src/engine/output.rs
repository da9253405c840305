//! The output folder of `recon infer`: per object `pose.json`, meshes and
//! Gaussians, `posthoc_color.json` when the colour calibration ran, RecGen's result
//! files ([`RecgenFiles`]), the placed scene, and the
//! index file written last, through a staging folder so that an interrupted run
//! never looks complete.

use crate::engine::infer::*;
use crate::engine::pipeline::{ModelIdentity, RunMetadata, StageTimings};
use crate::engine::pose_fit::PoseSpread;
use crate::engine::posthoc_color::write_posthoc_color;
use crate::engine::recgen_result::RecgenFiles;
use crate::engine::shape_fit::ShapeFitReport;
use crate::export::glb::{save_glb, scene_glb_bytes, GlbOptions, PointCloud};
use crate::export::ply::{save_mesh_ply, PlyOptions};
use crate::export::splat::save_splat_ply;
use crate::export::Axes;
use crate::mesh::Mesh;
use crate::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// The pose file written per object.
#[derive(Debug, Serialize)]
pub struct PoseRecord<'a> {
    /// The object's mask label.
    pub object: &'a str,
    /// The mask's instance id, when it has one.
    pub id: Option<u32>,
    /// The frame the pose maps into, in words.
    pub frame: &'static str,
    /// `x_camera = scale · rotation · x_object + translation`, metres; object
    /// frame = the decoder's canonical [-0.5, 0.5]³ (z up).
    pub rotation: [[f32; 3]; 3],
    /// Translation, metres.
    pub translation_m: [f32; 3],
    /// Scale: the side of the object frame's unit cube, in metres.
    pub scale_m: f32,
    /// The selected token's pose in its view's normalised frame.
    pub pose_normalised: PoseJson,
    /// Which candidate won.
    pub selection: &'a Selection,
    /// Spread of the per-sample poses (with two or more samples).
    pub uncertainty: Option<&'a PoseSpread>,
    /// Each view of the object, view 1 first.
    pub views: &'a [ViewPose],
    /// Every scored candidate.
    pub candidates: &'a [Candidate],
    /// Samples requested per object.
    pub samples: usize,
    /// Seed of the first candidate's sample (the selected run's seed when there is none).
    pub base_seed: u64,
    /// Occupied voxels stage 2 ran on ([`ObjectResult::occupied_voxels`]).
    pub occupied_voxels: usize,
    /// What the shape fit changed in the occupancy (absent with `--shape-fit none`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub shape_fit: Option<&'a ShapeFitReport>,
    /// Faces as decoded, before the face budget.
    pub faces_decoded: usize,
    /// Faces of the written mesh (0 without one).
    pub faces: usize,
    /// Model stage seconds, summed over samples.
    pub timings_s: &'a StageTimings,
    /// Mesh post-processing seconds ([`ObjectResult::postprocess_seconds`]).
    pub postprocess_s: f64,
    /// Scoring and selection seconds.
    pub select_s: f64,
    /// The selected sample's run: its seed, sampler settings, weights.
    pub run: &'a RunMetadata,
    /// Remarks on the object ([`ObjectResult::notes`]).
    pub notes: &'a [String],
    /// The recon that wrote the file ([`crate::VERSION`]).
    pub recon_version: &'static str,
    /// The model that answered: name and weights' hash (the run's, as [`ModelIdentity::of`]).
    pub model_identity: ModelIdentity,
    /// The baked texture of `mesh.glb` (absent with `--colour vertex`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub texture: Option<&'a TextureReport>,
}

/// The per-stage seconds `recon infer` reports for every object, in its table's column
/// order: model stages summed over samples, then decimation, pose selection and the total.
pub const STAGE_COLUMNS: [&str; 10] =
    ["encoder", "ss_sampling", "ss_decoder", "shape_fit", "slat_sampling", "mesh", "gaussians", "decimate", "select", "total"];

/// One object's seconds per [`STAGE_COLUMNS`] entry.
pub fn stage_seconds(o: &ObjectResult) -> [f64; 10] {
    let t = &o.timings;
    [
        t.image_encoder,
        t.ss_condition + t.ss_sampling,
        t.ss_decoder + t.pose,
        t.shape_fit,
        t.slat_condition + t.slat_sampling,
        t.mesh_decoder + t.flexicubes,
        t.gaussian_decoder,
        o.postprocess_seconds,
        o.select_seconds,
        t.total + o.postprocess_seconds + o.select_seconds,
    ]
}

/// Paths written for one object.
#[derive(Debug, Clone, Serialize)]
pub struct WrittenObject {
    /// The object's mask label.
    pub object: String,
    /// Its `pose.json`.
    pub pose: PathBuf,
    /// Its `mesh.glb`, when it has a mesh with faces.
    pub mesh_glb: Option<PathBuf>,
    /// Its `mesh.ply`, when it has a mesh with faces.
    pub mesh_ply: Option<PathBuf>,
    /// Its Gaussians as a splat PLY (`gaussians.ply`), when it has any.
    pub gaussians_ply: Option<PathBuf>,
}

/// Index file written last into every output folder; its presence marks a
/// complete recon output.
pub const MARKER: &str = "recon-output.json";

fn safe_name(label: &str) -> String {
    label.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}

/// Write per-object files (recon's; RecGen's too with [`write_outputs_with`]), the scene GLB
/// (all meshes and the observed points, coloured, in the anchor camera frame) and the
/// observed points (PLY) into `out`. Files are written to a staging
/// folder first and moved into place at the end, so an interrupted run never
/// leaves a complete-looking output.
///
/// An existing `out` is replaced only when it is an earlier recon output
/// (it holds [`MARKER`]); any other existing non-empty folder is an error.
pub fn write_outputs(result: &FrameResult, out: &Path) -> Result<Vec<WrittenObject>> {
    write_outputs_with(result, out, &OutputOptions::default())
}

/// What [`write_outputs_with`] writes beyond recon's own files.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct OutputOptions {
    /// Also RecGen's `save` files per object ([`RecgenFiles`]: object- and
    /// camera-frame OBJ meshes, both splat PLYs, the overlay, `metadata.json`).
    /// Off by default: the two text meshes triple the sample's output (47 → 143 MB).
    pub recgen_files: bool,
}

/// [`write_outputs`] with [`OutputOptions`].
pub fn write_outputs_with(result: &FrameResult, out: &Path, opts: &OutputOptions) -> Result<Vec<WrittenObject>> {
    let staging = begin_output(out)?;
    // Camera frame stays as is (OpenCV: x right, y down, z forward) in every file.
    let glb = GlbOptions { axes: Axes::ZUp, vertex_colors: true };
    let ply = PlyOptions { axes: Axes::ZUp, normals: true, vertex_colors: true };
    let mut written = Vec::new();
    let mut observed = Mesh::default();
    let mut clouds: Vec<(String, Vec<[f32; 3]>, Vec<[u8; 3]>)> = Vec::new();
    let mut used = std::collections::HashSet::new();
    for o in &result.objects {
        let mut name = safe_name(&o.label);
        // Binary masks from different folders may share a file name.
        let base = name.clone();
        let mut k = 2;
        while !used.insert(name.clone()) {
            name = format!("{base}_{k}");
            k += 1;
        }
        let dir = staging.join(&name);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        let rec = PoseRecord {
            object: &o.label,
            id: o.id,
            frame: "camera of view 1 (OpenCV: x right, y down, z forward), metres",
            rotation: o.pose_camera.rotation,
            translation_m: o.pose_camera.translation,
            scale_m: o.pose_camera.scale,
            pose_normalised: PoseJson::from(&o.pose_normalised),
            selection: &o.selection,
            uncertainty: o.uncertainty.as_ref(),
            views: &o.views,
            candidates: &o.candidates,
            samples: o.samples,
            base_seed: o.candidates.first().map_or(o.metadata.seed, |c| c.seed),
            occupied_voxels: o.occupied_voxels,
            shape_fit: o.shape_fit.as_ref(),
            faces_decoded: o.faces_decoded,
            faces: o.mesh_camera.as_ref().map_or(0, |m| m.faces.len()),
            timings_s: &o.timings,
            postprocess_s: o.postprocess_seconds,
            select_s: o.select_seconds,
            run: &o.metadata,
            notes: &o.notes,
            recon_version: crate::VERSION,
            model_identity: ModelIdentity::of(&o.metadata),
            texture: o.texture_report.as_ref(),
        };
        let pose_path = dir.join("pose.json");
        let text = serde_json::to_string_pretty(&rec).map_err(|e| Error::msg(e.to_string()))?;
        std::fs::write(&pose_path, text).map_err(|e| Error::io(&pose_path, e))?;
        let mut w = WrittenObject {
            object: o.label.clone(),
            pose: out.join(&name).join("pose.json"),
            mesh_glb: None,
            mesh_ply: None,
            gaussians_ply: None,
        };
        if let Some(m) = o.mesh_camera.as_ref().filter(|m| !m.faces.is_empty()) {
            // Textured (UVs, embedded PNG) with `--colour texture`, vertex-coloured otherwise.
            match &o.textured {
                Some(tm) => crate::export::glb::save_textured_glb(tm, &dir.join("mesh.glb"), glb.axes)?,
                None => save_glb(m, &dir.join("mesh.glb"), &glb)?,
            }
            save_mesh_ply(m, &dir.join("mesh.ply"), &ply)?;
            w.mesh_glb = Some(out.join(&name).join("mesh.glb"));
            w.mesh_ply = Some(out.join(&name).join("mesh.ply"));
        }
        if let Some(g) = o.gaussians_camera.as_ref().filter(|g| !g.is_empty()) {
            save_splat_ply(g, &dir.join("gaussians.ply"), Axes::ZUp)?;
            w.gaussians_ply = Some(out.join(&name).join("gaussians.ply"));
        }
        // RecGen's `save` beside recon's own files (the index keeps its earlier form).
        if opts.recgen_files {
            RecgenFiles::of(o, result).write(&dir, true)?;
        } else if let Some(r) = &o.posthoc_color {
            write_posthoc_color(r, &dir)?;
        }
        observed.vertices.extend_from_slice(&o.observed_points);
        clouds.push((format!("observed {name}"), o.observed_points.clone(), o.observed_colors.clone()));
        written.push(w);
    }
    let meshes: Vec<(&str, &Mesh)> = result
        .objects
        .iter()
        .zip(&written)
        .filter_map(|(o, w)| o.mesh_camera.as_ref().filter(|m| !m.faces.is_empty()).map(|m| (w.object.as_str(), m)))
        .collect();
    let pcs: Vec<PointCloud> = clouds.iter().map(|(n, p, c)| PointCloud { name: n, points: p, colors: c }).collect();
    if !meshes.is_empty() || pcs.iter().any(|c| !c.points.is_empty()) {
        let bytes = scene_glb_bytes(&meshes, &pcs, &glb)?;
        let p = staging.join("scene.glb");
        std::fs::write(&p, bytes).map_err(|e| Error::io(&p, e))?;
    }
    if !observed.vertices.is_empty() {
        let pts = PlyOptions { axes: Axes::ZUp, normals: false, vertex_colors: false };
        save_mesh_ply(&observed, &staging.join("observed_points.ply"), &pts)?;
    }
    let index = serde_json::json!({
        "objects": written,
        "skipped": result.skipped.iter().map(|s| s.to_string()).collect::<Vec<_>>(),
        "notes": result.notes,
    });
    finish_output(&staging, out, &index)?;
    Ok(written)
}

/// Starts a recon output folder `out`: checks that an existing `out` is empty or an
/// earlier recon output (holds [`MARKER`]), and returns a fresh, empty staging folder
/// beside it to write into. [`finish_output`] then moves it into place.
pub fn begin_output(out: &Path) -> Result<PathBuf> {
    begin_output_marked(out, MARKER)
}

/// [`begin_output`] for an output family with its own marker file (`recon scene`).
pub fn begin_output_marked(out: &Path, marker: &str) -> Result<PathBuf> {
    if out.exists() {
        let empty = std::fs::read_dir(out).map(|mut d| d.next().is_none()).unwrap_or(false);
        if !empty && !out.join(marker).exists() {
            return Err(Error::input(
                out.display().to_string(),
                format!("output folder exists and is not a recon output of this kind (no {marker}); remove it or choose another --out"),
            ));
        }
    }
    let staging = out.with_extension("partial");
    if staging.exists() {
        std::fs::remove_dir_all(&staging).map_err(|e| Error::io(&staging, e))?;
    }
    std::fs::create_dir_all(&staging).map_err(|e| Error::io(&staging, e))?;
    Ok(staging)
}

/// Writes the [`MARKER`] index last, then replaces `out` with the staging folder.
pub fn finish_output(staging: &Path, out: &Path, index: &serde_json::Value) -> Result<()> {
    finish_output_marked(staging, out, MARKER, index)
}

/// [`finish_output`] with the output family's own marker file.
pub fn finish_output_marked(staging: &Path, out: &Path, marker: &str, index: &serde_json::Value) -> Result<()> {
    let marker = staging.join(marker);
    std::fs::write(&marker, serde_json::to_string_pretty(index).map_err(|e| Error::msg(e.to_string()))?)
        .map_err(|e| Error::io(&marker, e))?;
    if out.exists() {
        std::fs::remove_dir_all(out).map_err(|e| Error::io(out, e))?;
    }
    std::fs::rename(staging, out).map_err(|e| Error::io(out, e))?;
    Ok(())
}
