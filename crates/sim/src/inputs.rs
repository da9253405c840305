//! Where scenes come from besides a hand-written scene file: the support
//! plane of an RGB-D frame, and a `recon infer` output folder.

use crate::materials::MaterialTable;
use crate::scene_file::{
    CameraSpec, IntrinsicsSpec, ObjectSpec, PhysicsOverrides, PlaneRecord, PoseSpec, SceneFile, SupportPlaneSpec, VERSION,
};
use recon_core::dataset::frame::RgbdFrame;
use recon_core::geometry::plane::{fit_plane, world_from_camera, PlaneFit, PlaneFitOptions};
use recon_core::math::dot;
use recon_core::math::Similarity32;
use recon_core::{Error, Result};
use std::path::{Path, PathBuf};

/// The support plane seen in a frame's depth and the world frame it
/// defines: `(fit, T_world←camera, record for the scene file)`.
pub fn support_plane_from_frame(frame: &RgbdFrame, opts: &PlaneFitOptions) -> Result<(PlaneFit, Similarity32, PlaneRecord)> {
    let pts = recon_core::geometry::pointmap::backproject(&frame.depth_m, frame.width, frame.height, &frame.intrinsics)?;
    let src = frame.depth_path.display().to_string();
    let fit = fit_plane(&pts, opts).map_err(|e| Error::input(&src, format!("support plane: {e}")))?;
    let plane = fit.plane.facing(&[0.0; 3]);
    let world = world_from_camera(&plane).map_err(|e| Error::input(&src, e.to_string()))?;
    let rec = PlaneRecord::new(src, &fit, &plane);
    Ok((fit, world, rec))
}

/// The camera entry of a scene file for `frame` at `world_from_camera`.
pub fn camera_spec(frame: &RgbdFrame, world_from_camera: &Similarity32) -> CameraSpec {
    let k = frame.intrinsics;
    CameraSpec {
        intrinsics: Some(IntrinsicsSpec { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy, width: frame.width, height: frame.height }),
        pose_world: PoseSpec::from_similarity(world_from_camera),
    }
}

/// Category of an object label: the longest category name of the table
/// contained in the label (`"025_mug"` → `mug`), else `"object"`.
pub fn guess_category(label: &str, table: &MaterialTable) -> String {
    let l = label.to_ascii_lowercase();
    table.categories.keys().filter(|c| l.contains(c.as_str())).max_by_key(|c| c.len()).cloned().unwrap_or_else(|| "object".into())
}

/// The colour image `recon infer` read for `dir` (its first object's
/// `pose.json`, `views[0].frame`), when that file still exists.
pub fn infer_frame(dir: &Path) -> Option<PathBuf> {
    let v: serde_json::Value = recon_core::util::json::read_json(&dir.join(recon_core::engine::output::MARKER)).ok()?;
    for o in v.get("objects")?.as_array()? {
        let p = PathBuf::from(o.get("pose")?.as_str()?);
        let pose = dir.join(p.parent()?.file_name()?).join(p.file_name()?);
        let Ok(rec) = recon_core::util::json::read_json::<serde_json::Value>(&pose) else { continue };
        let frame = PathBuf::from(rec.get("views")?.get(0)?.get("frame")?.as_str()?);
        return frame.is_file().then_some(frame);
    }
    None
}

/// Scene file for a `recon infer` output folder: each object's camera-frame
/// mesh (`<object>/mesh.ply`, metres) placed in the world frame of the
/// support plane seen in `frame` (the colour image given to `recon infer`).
/// Objects without a mesh are left out, listed in the returned notes.
pub fn scene_from_infer_output(
    dir: &Path,
    frame: &RgbdFrame,
    table: &MaterialTable,
    plane: &PlaneFitOptions,
) -> Result<(SceneFile, Vec<String>)> {
    let index = dir.join(recon_core::engine::output::MARKER);
    let file = index.display().to_string();
    let v: serde_json::Value = recon_core::util::json::read_json(&index)?;
    let objs = v
        .get("objects")
        .and_then(|o| o.as_array())
        .ok_or_else(|| Error::config(&file, "objects", "expected the array written by `recon infer`"))?;
    let mut notes = Vec::new();
    let mut meshes = Vec::new();
    for (i, o) in objs.iter().enumerate() {
        let name = o
            .get("object")
            .and_then(|x| x.as_str())
            .ok_or_else(|| Error::config(&file, format!("objects[{i}].object"), "expected the object label"))?;
        // Paths were written relative to the folder `recon infer` was given;
        // the folder may have moved since, so keep only `<object>/<file>`.
        let local = |key: &str| -> Option<PathBuf> {
            let p = PathBuf::from(o.get(key)?.as_str()?);
            let sub = p.parent()?.file_name()?;
            Some(dir.join(sub).join(p.file_name()?))
        };
        let Some(mesh) = local("mesh_ply") else {
            notes.push(format!("{name}: no mesh in the recon infer output; left out"));
            continue;
        };
        if !mesh.is_file() {
            return Err(Error::config(&file, format!("objects[{i}].mesh_ply"), format!("{} does not exist", mesh.display())));
        }
        meshes.push((name.to_string(), mesh));
    }
    if meshes.is_empty() {
        return Err(Error::input(&file, "no object with a mesh in this recon infer output"));
    }
    let source = format!("recon infer output {} with the depth of {}", dir.display(), frame.rgb_path.display());
    Ok((camera_frame_scene(meshes, frame, table, plane, source)?, notes))
}

/// Scene file for objects held in memory (e.g. the engine's results): each
/// `(name, mesh)`, the mesh in the camera frame of `frame` in metres, is
/// written to `mesh_dir/NNN.ply` (the bytes `recon infer` writes as
/// `mesh.ply`, so the scene equals the one of the same objects' infer
/// folder) and placed as [`scene_from_infer_output`] places it. The scene
/// reads its meshes from those files: keep `mesh_dir` until it is built.
pub fn scene_from_meshes(
    objects: &[(String, recon_core::mesh::Mesh)],
    mesh_dir: &Path,
    frame: &RgbdFrame,
    table: &MaterialTable,
    plane: &PlaneFitOptions,
) -> Result<SceneFile> {
    if objects.is_empty() {
        return Err(Error::input("objects", "no object with a mesh to place in a scene"));
    }
    std::fs::create_dir_all(mesh_dir).map_err(|e| Error::io(mesh_dir, e))?;
    let ply = recon_core::export::ply::PlyOptions { axes: recon_core::export::Axes::ZUp, normals: true, vertex_colors: true };
    let mut meshes = Vec::with_capacity(objects.len());
    for (i, (name, mesh)) in objects.iter().enumerate() {
        let path = mesh_dir.join(format!("{i:03}.ply"));
        recon_core::export::ply::save_mesh_ply(mesh, &path, &ply)?;
        meshes.push((name.clone(), path));
    }
    let source = format!("{} objects in memory with the depth of {}", objects.len(), frame.depth_path.display());
    camera_frame_scene(meshes, frame, table, plane, source)
}

/// Camera-frame meshes `(name, PLY file)` in the world frame of the support
/// plane seen in `frame`.
fn camera_frame_scene(
    meshes: Vec<(String, PathBuf)>,
    frame: &RgbdFrame,
    table: &MaterialTable,
    plane: &PlaneFitOptions,
    source: String,
) -> Result<SceneFile> {
    let (_fit, world, rec) = support_plane_from_frame(frame, plane)?;
    let objects = meshes
        .into_iter()
        .map(|(name, mesh)| ObjectSpec {
            category: guess_category(&name, table),
            name,
            mesh,
            scale: 1.0,
            // The mesh is in the camera frame already.
            pose: PoseSpec::from_similarity(&world),
            physics: PhysicsOverrides::default(),
            color_rgba: None,
        })
        .collect();
    Ok(SceneFile {
        version: VERSION,
        source: Some(source),
        camera: Some(camera_spec(frame, &world)),
        support_plane: SupportPlaneSpec { fit: Some(rec), ..Default::default() },
        objects,
    })
}

/// How far the fitted support plane is from the dataset's ground-truth
/// world plane (BOP `cam_R_w2c`/`cam_t_w2c`, table top z = 0), if known.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct PlaneCheck {
    pub normal_error_deg: f64,
    /// Camera-to-plane distance error (metres).
    pub offset_error_m: f64,
}

/// Scene file for one view of a BOP scene folder (`<root>/<split>/<scene>`
/// with `scene_gt.json`, `scene_camera.json`, `rgb/`, `depth/`; models in
/// `<root>/models/obj_NNNNNN.ply`, millimetres): every GT object at its GT
/// pose, placed in the world frame of the support plane fitted to the view's
/// depth. `view` defaults to the first image id.
pub fn scene_from_bop(
    scene_dir: &Path,
    view: Option<u32>,
    table: &MaterialTable,
    plane: &PlaneFitOptions,
) -> Result<(SceneFile, Option<PlaneCheck>)> {
    let gt_path = scene_dir.join("scene_gt.json");
    let cam_path = scene_dir.join("scene_camera.json");
    let gt_file = gt_path.display().to_string();
    let gt: serde_json::Value = recon_core::util::json::read_json(&gt_path)?;
    let cams: serde_json::Value = recon_core::util::json::read_json(&cam_path)?;
    let gt = gt.as_object().ok_or_else(|| Error::config(&gt_file, "<root>", "expected an object keyed by image id"))?;
    let mut ids: Vec<u32> = gt.keys().filter_map(|k| k.parse().ok()).collect();
    ids.sort_unstable();
    let id = match view {
        Some(v) => v,
        None => *ids.first().ok_or_else(|| Error::config(&gt_file, "<root>", "no images"))?,
    };
    let key = id.to_string();
    let entries = gt
        .get(&key)
        .and_then(|v| v.as_array())
        .ok_or_else(|| Error::config(&gt_file, key.as_str(), format!("no ground truth for image {id} (images: {ids:?})")))?;
    let rgb = ["png", "jpg"]
        .iter()
        .map(|e| scene_dir.join("rgb").join(format!("{id:06}.{e}")))
        .find(|p| p.is_file())
        .ok_or_else(|| Error::input(scene_dir.display().to_string(), format!("no rgb/{id:06}.png")))?;
    let frame = RgbdFrame::open(&rgb, &Default::default())?;
    let (_fit, world, rec) = support_plane_from_frame(&frame, plane)?;
    let root = scene_dir.parent().and_then(|p| p.parent()).unwrap_or(Path::new("."));
    let models = root.join("models");
    let nums = |v: &serde_json::Value, field: &str, n: usize| -> Result<Vec<f64>> {
        let a = v.as_array().filter(|a| a.len() == n).ok_or_else(|| Error::config(&gt_file, field, format!("expected {n} numbers")))?;
        a.iter().map(|x| x.as_f64().ok_or_else(|| Error::config(&gt_file, field, "expected numbers"))).collect()
    };
    // `recon synth` records each GT instance's object kind in scene_meta.json.
    let meta: Option<serde_json::Value> = match scene_dir.join("scene_meta.json") {
        p if p.is_file() => Some(recon_core::util::json::read_json(&p)?),
        _ => None,
    };
    let kind_of = |gt_idx: usize| -> Option<String> {
        let inst = meta.as_ref()?.get("instances")?.as_array()?;
        let e = inst.iter().find(|e| e.get("gt_idx").and_then(|g| g.as_u64()) == Some(gt_idx as u64))?;
        Some(e.get("kind")?.as_str()?.to_string())
    };
    let mut objects = Vec::new();
    let mut seen = std::collections::BTreeMap::<u64, usize>::new();
    for (i, e) in entries.iter().enumerate() {
        let f = format!("{key}[{i}]");
        let obj_id = e.get("obj_id").and_then(|x| x.as_u64()).ok_or_else(|| Error::config(&gt_file, format!("{f}.obj_id"), "missing"))?;
        let r = nums(e.get("cam_R_m2c").unwrap_or(&serde_json::Value::Null), &format!("{f}.cam_R_m2c"), 9)?;
        let t = nums(e.get("cam_t_m2c").unwrap_or(&serde_json::Value::Null), &format!("{f}.cam_t_m2c"), 3)?;
        let m2c = Similarity32::new(
            [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]].map(|row| row.map(|x| x as f32)),
            [t[0], t[1], t[2]].map(|x| (x * 1e-3) as f32),
            1.0,
        )
        .map_err(|e| Error::config(&gt_file, format!("{f}.cam_R_m2c"), e.to_string()))?;
        let n = seen.entry(obj_id).or_default();
        *n += 1;
        let name = if *n == 1 { format!("obj_{obj_id:06}") } else { format!("obj_{obj_id:06}_{n}") };
        let category = kind_of(i).filter(|k| table.categories.contains_key(k)).unwrap_or_else(|| guess_category(&name, table));
        objects.push(ObjectSpec {
            category,
            name,
            mesh: models.join(format!("obj_{obj_id:06}.ply")),
            scale: 1e-3,
            pose: PoseSpec::from_similarity(&world.compose(&m2c)),
            physics: PhysicsOverrides::default(),
            color_rgba: None,
        });
    }
    if objects.is_empty() {
        return Err(Error::config(&gt_file, key.as_str(), "no objects in this image"));
    }
    // Ground-truth plane, when the dataset gives the world → camera transform.
    let check = cams.get(&key).and_then(|c| {
        let r = nums(c.get("cam_R_w2c")?, "cam_R_w2c", 9).ok()?;
        let t = nums(c.get("cam_t_w2c")?, "cam_t_w2c", 3).ok()?;
        let n_gt = [r[2], r[5], r[8]]; // R · e_z
        let t_m = [t[0] * 1e-3, t[1] * 1e-3, t[2] * 1e-3];
        let d_gt = -dot(n_gt, t_m); // plane n·x + d = 0 through the world origin
        let fit = recon_core::geometry::plane::Plane { normal: rec.normal_camera, offset: rec.offset_camera_m };
        let gt_plane = recon_core::geometry::plane::Plane { normal: n_gt, offset: d_gt }.facing(&[0.0; 3]);
        Some(PlaneCheck {
            normal_error_deg: dot(fit.normal, gt_plane.normal).clamp(-1.0, 1.0).acos().to_degrees(),
            offset_error_m: (fit.offset - gt_plane.offset).abs(),
        })
    });
    let scene = SceneFile {
        version: VERSION,
        source: Some(format!("BOP scene {} image {id}: ground-truth models and poses", scene_dir.display())),
        camera: Some(camera_spec(&frame, &world)),
        support_plane: SupportPlaneSpec { fit: Some(rec), ..Default::default() },
        objects,
    };
    Ok((scene, check))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn categories_from_labels() {
        let t = MaterialTable::builtin();
        assert_eq!(guess_category("025_mug", &t), "mug");
        assert_eq!(guess_category("003_cracker_box", &t), "box");
        assert_eq!(guess_category("024_bowl", &t), "bowl");
        assert_eq!(guess_category("obj_000007", &t), "object");
    }

    #[test]
    fn in_memory_meshes_become_a_scene_of_their_files() {
        let color = recon_testkit::repo().join("data/sample/000001-color.png");
        let frame = RgbdFrame::open(&color, &Default::default()).unwrap();
        let mut mesh = recon_core::mesh::box_mesh(0.05, 0.04, 0.03);
        for v in &mut mesh.vertices {
            v[2] += 0.6;
        }
        let dir = recon_testkit::tmp("scene-meshes");
        let table = MaterialTable::builtin();
        let plane = PlaneFitOptions::default();
        let objects = vec![("025_mug".to_string(), mesh.clone())];
        let scene = scene_from_meshes(&objects, &dir, &frame, &table, &plane).unwrap();
        let (_, world, rec) = support_plane_from_frame(&frame, &plane).unwrap();
        assert_eq!(scene.objects.len(), 1);
        let o = &scene.objects[0];
        assert_eq!((o.name.as_str(), o.category.as_str(), o.scale), ("025_mug", "mug", 1.0));
        assert_eq!(o.pose, PoseSpec::from_similarity(&world));
        assert_eq!(scene.support_plane.fit.as_ref().map(|f| f.inliers), Some(rec.inliers));
        // The file holds the mesh exactly (binary float32 PLY).
        let back: recon_core::mesh::trimesh::TriMesh = recon_core::dataset::ply::read_ply(&o.mesh).unwrap();
        assert_eq!(back.faces, mesh.faces);
        let v: Vec<[f32; 3]> = back.vertices.iter().map(|v| v.map(|x| x as f32)).collect();
        assert_eq!(v, mesh.vertices);
        let err = scene_from_meshes(&[], &dir, &frame, &table, &plane).unwrap_err();
        assert!(err.to_string().contains("no object"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn ycb_sample_table_plane() {
        let color = recon_testkit::repo().join("data/sample/000001-color.png");
        let frame = RgbdFrame::open(&color, &Default::default()).unwrap();
        let (fit, world, rec) = support_plane_from_frame(&frame, &PlaneFitOptions::default()).unwrap();
        // The YCB-Video table fills much of the view; real Xtion depth noise is a few mm.
        assert!(fit.inlier_fraction > 0.3, "{fit:?}");
        assert!(fit.rms_residual_m < 0.005, "{fit:?}");
        // The camera looks down at the table from above.
        let cam = world.apply(&[0.0; 3]);
        assert!(cam[2] > 0.3 && cam[2] < 2.0, "camera height {}", cam[2]);
        assert_eq!(rec.inliers, fit.inliers);
    }
}
