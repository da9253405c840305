//! What RecGen's `recgen_inference.generate` returns for an object (`RecGenResult`) and
//! what its `save` writes, from a recon [`ObjectResult`].
//!
//! **Frames.** RecGen's pose outputs live in the *normalised* frame of the anchor view's
//! point map ([`crate::geometry::pointmap`]: `x_n = (x − c)/d + 0.5`), not in the camera
//! frame. `pose_matrix` maps the object frame (the decoder's canonical `[-0.5, 0.5]³`, z up:
//! RecGen's `raw_mesh`) into it; `cam2ncam` maps the camera frame into it; the camera-frame
//! mesh is `inv(cam2ncam) · pose_matrix · raw_mesh` (`_build_result_from_outputs`). recon
//! refines and selects its pose in the camera frame ([`ObjectResult::pose_camera`], metres),
//! so its RecGen form is `pose_matrix = cam2ncam · pose_camera`: upstream's identity holds,
//! and without refinement or shape fit (`--pose-fit recgen --shape-fit none`, one view)
//! `pose_matrix` is the model's own pose token as upstream reports it. With the shape fit the
//! object frame is the canonical cube re-fitted around the fitted solid (same axes; the pose
//! absorbs the shift and scale), as [`ObjectResult::mesh_object`] says.
//!
//! **Quaternions.** `pose_quat` is `[tx, ty, tz, qx, qy, qz, qw]` and `pose.quaternion`
//! `[qx, qy, qz, qw]`, scipy's order as upstream's (here with `qw ≥ 0`); recon's own files
//! and the Gaussians use `(w, x, y, z)`. docs/infer.md tabulates every output.

use crate::engine::infer::{FrameImage, FrameResult, ObjectResult};
use crate::engine::posthoc_color::{write_posthoc_color, PosthocColorRecord};
use crate::export::obj::save_obj;
use crate::export::splat::save_splat_ply;
use crate::export::Axes;
use crate::gaussians::Gaussians;
use crate::geometry::pointmap::{Normaliser, NORMALISED_CENTRE};
use crate::geometry::pose::{Pose, PoseRepresentation};
use crate::math::matrix_to_quat;
use crate::mesh::Mesh;
use crate::render::save_overlay;
use crate::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// RecGen's parsed pose (`utils.parse_pose`'s dict), in the normalised anchor frame:
/// `x_n = scale · rotation_matrix · x_object + translation`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ParsedPose {
    /// Unit quaternion of `rotation_matrix`, `[qx, qy, qz, qw]` (scipy order), `qw ≥ 0`.
    pub quaternion: [f64; 4],
    /// Translation, normalised units.
    pub translation: [f64; 3],
    /// Uniform scale, normalised units per object-frame unit.
    pub scale: f64,
    /// Rotation, row-major.
    pub rotation_matrix: [[f64; 3]; 3],
}

/// RecGen's pose fields of a result (`RecGenResult`: `pose_matrix`, `pose_quat`, `pose`,
/// `cam2ncam`); module docs for the frames.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RecgenPose {
    /// Object frame → normalised anchor frame, `[s·R | t; 0 0 0 1]`, row-major.
    pub pose_matrix: [[f64; 4]; 4],
    /// `[tx, ty, tz, qx, qy, qz, qw]` of `pose_matrix` (scale aside).
    pub pose_quat: [f64; 7],
    /// The parts of `pose_matrix`.
    pub pose: ParsedPose,
    /// Anchor camera frame (metres) → normalised anchor frame: `[I/d | 0.5 − c/d]`, row-major.
    pub cam2ncam: [[f64; 4]; 4],
}

/// `[s·R | t; 0 0 0 1]`.
fn similarity_matrix(r: &[[f64; 3]; 3], t: [f64; 3], s: f64) -> [[f64; 4]; 4] {
    let mut m = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = s * r[i][j];
        }
        m[i][3] = t[i];
    }
    m[3][3] = 1.0;
    m
}

fn matmul4(a: &[[f64; 4]; 4], b: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..4).map(|k| a[i][k] * b[k][j]).sum()))
}

impl RecgenPose {
    /// RecGen's form of a camera-frame pose (`x = scale · R · x_object + t`, metres) for the
    /// anchor view's normaliser.
    pub fn new(pose_camera: &Pose, normaliser: &Normaliser) -> Self {
        let rotation_matrix = pose_camera.rotation.map(|row| row.map(f64::from));
        let translation = normaliser.to_normalised(pose_camera.translation.map(f64::from));
        let scale = pose_camera.scale as f64 / normaliser.diameter;
        let q = matrix_to_quat(&pose_camera.rotation); // (w, x, y, z), w ≥ 0
        let quaternion = [q[1], q[2], q[3], q[0]].map(f64::from);
        let t = translation;
        RecgenPose {
            pose_matrix: similarity_matrix(&rotation_matrix, translation, scale),
            pose_quat: [t[0], t[1], t[2], quaternion[0], quaternion[1], quaternion[2], quaternion[3]],
            pose: ParsedPose { quaternion, translation, scale, rotation_matrix },
            cam2ncam: normaliser.cam2ncam(),
        }
    }

    /// `inv(cam2ncam) · pose_matrix`: object frame → anchor camera frame (metres), the map
    /// that places `raw_mesh` as `mesh` (RecGen: translate by `−cam2ncam[:3, 3]`, then scale
    /// by `1 / cam2ncam[0, 0]`).
    pub fn camera_matrix(&self) -> [[f64; 4]; 4] {
        let s = self.cam2ncam[0][0];
        let t = [0, 1, 2].map(|i| self.cam2ncam[i][3]);
        let eye = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let inv = similarity_matrix(&eye, t.map(|x| -x / s), 1.0 / s);
        matmul4(&inv, &self.pose_matrix)
    }
}

impl ObjectResult {
    /// The anchor view's point-map normaliser (RecGen's `cam2ncam`, as a map).
    pub fn anchor_normaliser(&self) -> Normaliser {
        match self.views.first() {
            Some(v) => Normaliser { centre: v.normaliser_centre_m, diameter: v.normaliser_diameter_m },
            // No view (not produced by the engine): the identity cam2ncam.
            None => Normaliser { centre: [NORMALISED_CENTRE; 3], diameter: 1.0 },
        }
    }

    /// RecGen's pose fields of this object ([`RecgenPose`]).
    pub fn recgen_pose(&self) -> RecgenPose {
        RecgenPose::new(&self.pose_camera, &self.anchor_normaliser())
    }
}

/// `metadata.json` of RecGen's `save`: its keys, in its order.
#[derive(Debug, Serialize)]
pub struct RecgenMetadata<'a> {
    /// `pose_matrix`, `pose_quat`, `pose`, `cam2ncam`.
    #[serde(flatten)]
    pub pose: &'a RecgenPose,
    /// The stage-1 pose layout (`6d_translation_scale`, …).
    pub pose_representation: PoseRepresentation,
    /// The anchor camera's K, row-major.
    pub intrinsics: [[f64; 3]; 3],
}

/// The files RecGen's `RecGenResult.save` writes, in its order.
pub const RECGEN_FILES: [&str; 6] = ["mesh.obj", "posed_mesh.obj", "gaussian.ply", "posed_gaussian.ply", "overlay.png", "metadata.json"];

/// What RecGen's `save` writes for one object, borrowed from a result.
#[derive(Debug, Clone, Copy)]
pub struct RecgenFiles<'a> {
    /// `mesh.obj`: the object-frame mesh ([`ObjectResult::mesh_object`]).
    pub mesh_object: Option<&'a Mesh>,
    /// `posed_mesh.obj` and the overlay: the camera-frame mesh.
    pub mesh_camera: Option<&'a Mesh>,
    /// `gaussian.ply`: the object-frame Gaussians.
    pub gaussians_object: Option<&'a Gaussians>,
    /// `posed_gaussian.ply`: the camera-frame Gaussians.
    pub gaussians_camera: Option<&'a Gaussians>,
    /// `metadata.json`'s pose fields.
    pub pose: RecgenPose,
    /// `metadata.json`'s `pose_representation`.
    pub pose_representation: PoseRepresentation,
    /// The anchor view's image and camera (overlay, `intrinsics`).
    pub image: &'a FrameImage,
    /// `posthoc_color.json`, when the calibration was asked for.
    pub posthoc_color: Option<&'a PosthocColorRecord>,
}

impl<'a> RecgenFiles<'a> {
    /// The files of object `o` of `frame`.
    pub fn of(o: &'a ObjectResult, frame: &'a FrameResult) -> Self {
        RecgenFiles {
            mesh_object: o.mesh_object.as_ref(),
            mesh_camera: o.mesh_camera.as_ref(),
            gaussians_object: o.gaussians_object.as_ref(),
            gaussians_camera: o.gaussians_camera.as_ref(),
            pose: o.recgen_pose(),
            pose_representation: frame.pose_representation,
            image: &frame.image,
            posthoc_color: o.posthoc_color.as_ref(),
        }
    }

    /// `metadata.json`'s content.
    pub fn metadata(&self) -> RecgenMetadata<'_> {
        let k = &self.image.intrinsics;
        RecgenMetadata {
            pose: &self.pose,
            pose_representation: self.pose_representation,
            intrinsics: [[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]],
        }
    }

    /// Writes the files into the existing folder `dir` and returns their paths: both OBJ
    /// meshes (vertex colours; z up as decoded, no axis change) when there is a mesh with
    /// faces, both splat PLYs (recon's `gaussians.ply` layout, the standard 3DGS one) when
    /// there are Gaussians, and always `overlay.png` and `metadata.json`. `save_splat`
    /// false leaves the PLYs out, as RecGen's `save(save_splat=False)`.
    pub fn write(&self, dir: &Path, save_splat: bool) -> Result<Vec<PathBuf>> {
        let mut written = Vec::new();
        let meshes = [(self.mesh_object, "mesh.obj"), (self.mesh_camera, "posed_mesh.obj")];
        for (m, name) in meshes {
            if let Some(m) = m.filter(|m| !m.faces.is_empty()) {
                save_obj(m, &dir.join(name), Axes::ZUp, true)?;
                written.push(dir.join(name));
            }
        }
        let splats = [(self.gaussians_object, "gaussian.ply"), (self.gaussians_camera, "posed_gaussian.ply")];
        for (g, name) in splats.into_iter().filter(|_| save_splat) {
            if let Some(g) = g.filter(|g| !g.is_empty()) {
                save_splat_ply(g, &dir.join(name), Axes::ZUp)?;
                written.push(dir.join(name));
            }
        }
        let im = self.image;
        let overlay = dir.join("overlay.png");
        save_overlay(&im.rgb, im.width, im.height, im.intrinsics, self.mesh_camera, &overlay)?;
        written.push(overlay);
        let path = dir.join("metadata.json");
        let text = serde_json::to_string_pretty(&self.metadata()).map_err(|e| Error::msg(e.to_string()))?;
        std::fs::write(&path, text).map_err(|e| Error::io(&path, e))?;
        written.push(path);
        if let Some(r) = self.posthoc_color {
            written.push(write_posthoc_color(r, dir)?);
        }
        Ok(written)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::axis_angle;

    fn pose() -> (Pose, Normaliser) {
        let r = axis_angle([0.3, -1.0, 0.4], 2.1).map(|row| row.map(|x| x as f32));
        (Pose { rotation: r, translation: [0.12, -0.05, 0.83], scale: 0.21 }, Normaliser { centre: [0.1, -0.04, 0.8], diameter: 0.37 })
    }

    /// scipy's `Rotation.from_quat([x, y, z, w]).as_matrix()`, written out.
    fn scipy_matrix(q: [f64; 4]) -> [[f64; 3]; 3] {
        let [x, y, z, w] = q;
        [
            [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - z * w), 2.0 * (x * z + y * w)],
            [2.0 * (x * y + z * w), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - x * w)],
            [2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)],
        ]
    }

    #[test]
    fn pose_matrix_is_the_parts_composed() {
        let (p, n) = pose();
        let rp = RecgenPose::new(&p, &n);
        let pp = &rp.pose;
        for i in 0..3 {
            for j in 0..3 {
                assert_eq!(rp.pose_matrix[i][j], pp.scale * pp.rotation_matrix[i][j]);
                assert_eq!(pp.rotation_matrix[i][j], p.rotation[i][j] as f64);
            }
            assert_eq!(rp.pose_matrix[i][3], pp.translation[i]);
            assert_eq!(rp.pose_matrix[3][i], 0.0);
        }
        assert_eq!(rp.pose_matrix[3][3], 1.0);
        assert_eq!(rp.pose_quat[..3], pp.translation);
        assert_eq!(rp.pose_quat[3..], pp.quaternion);
        // The normalised frame: translation (t − c)/d + 0.5, scale s/d.
        assert!((pp.translation[2] - ((0.83f32 as f64 - 0.8) / 0.37 + 0.5)).abs() < 1e-12);
        assert!((pp.scale - 0.21f32 as f64 / 0.37).abs() < 1e-12);
        assert_eq!(rp.cam2ncam, n.cam2ncam());
    }

    #[test]
    fn pose_quat_is_scipy_order() {
        let (p, n) = pose();
        let q = RecgenPose::new(&p, &n).pose.quaternion;
        assert!((q.iter().map(|x| x * x).sum::<f64>() - 1.0).abs() < 1e-6 && q[3] >= 0.0);
        let m = scipy_matrix(q);
        for i in 0..3 {
            for j in 0..3 {
                assert!((m[i][j] - p.rotation[i][j] as f64).abs() < 1e-5, "{m:?} vs {:?}", p.rotation);
            }
        }
        // A quarter turn about z: [0, 0, sin 45°, cos 45°] in scipy's order, w last.
        let rz = Pose { rotation: [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], ..p };
        let q = RecgenPose::new(&rz, &n).pose.quaternion;
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!(q.iter().zip([0.0, 0.0, h, h]).all(|(a, b)| (a - b).abs() < 1e-6), "{q:?}");
    }

    #[test]
    fn undoing_cam2ncam_gives_the_camera_pose() {
        let (p, n) = pose();
        let m = RecgenPose::new(&p, &n).camera_matrix();
        let want = similarity_matrix(&p.rotation.map(|r| r.map(f64::from)), p.translation.map(f64::from), p.scale as f64);
        for i in 0..4 {
            for j in 0..4 {
                assert!((m[i][j] - want[i][j]).abs() < 1e-12, "{m:?} vs {want:?}");
            }
        }
        // And cam2ncam · camera point = the normaliser's map.
        let x = [0.3, -0.2, 1.1];
        let c = RecgenPose::new(&p, &n).cam2ncam;
        let y: [f64; 3] = std::array::from_fn(|i| (0..3).map(|k| c[i][k] * x[k]).sum::<f64>() + c[i][3]);
        let want = n.to_normalised(x);
        assert!((0..3).all(|i| (y[i] - want[i]).abs() < 1e-12));
    }
}
