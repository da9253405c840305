//! The scene description file (`scene.json`, `"version": 1`): objects with
//! their mesh, pose in the world frame, scale and physics overrides; the
//! camera; the support plane. Readable and editable by hand; every problem
//! is reported with the file and the field.
//!
//! World frame: metres, gravity along −z, the support plane is z = 0.
//! An object's pose maps its mesh file's coordinates (times `scale`) to the
//! world: `x_world = R · (scale · x_mesh) + t`. Mesh paths are relative to
//! the scene file's folder (or absolute); meshes are PLY.
//!
//! ```json
//! {
//!   "version": 1,
//!   "camera": { "pose_world": { "rotation": [[1,0,0],[0,-1,0],[0,0,-1]], "translation_m": [0, 0, 0.8] } },
//!   "support_plane": { "material": "wood" },
//!   "objects": [
//!     { "name": "mug", "category": "mug", "mesh": "meshes/mug.ply", "scale": 0.001,
//!       "pose": { "quaternion_wxyz": [1, 0, 0, 0], "translation_m": [0.1, 0, 0] },
//!       "physics": { "mass_kg": 0.3 } }
//!   ]
//! }
//! ```

use crate::physics::TreatmentChoice;
use recon_core::geometry::plane::{Plane, PlaneFit};
use recon_core::math::Similarity32;
use recon_core::{Error, Result};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

pub const VERSION: u32 = 1;

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseSpec {
    /// Rotation matrix (rows), or give `quaternion_wxyz` instead.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation: Option<[[f64; 3]; 3]>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub quaternion_wxyz: Option<[f64; 4]>,
    pub translation_m: [f64; 3],
}

impl PoseSpec {
    pub fn from_similarity(s: &Similarity32) -> Self {
        PoseSpec { rotation: None, quaternion_wxyz: Some(s.quaternion().map(|x| x as f64)), translation_m: s.translation.map(|x| x as f64) }
    }

    /// The rigid transform (scale 1); errors name `file` and `field`.
    pub fn to_similarity(&self, file: &str, field: &str) -> Result<Similarity32> {
        let r = match (self.rotation, self.quaternion_wxyz) {
            (Some(r), None) => r.map(|row| row.map(|x| x as f32)),
            (None, Some(q)) => {
                let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
                if !(n.is_finite() && (n - 1.0).abs() < 1e-3) {
                    return Err(Error::config(
                        file,
                        format!("{field}.quaternion_wxyz"),
                        format!("expected a unit quaternion (w, x, y, z), norm is {n}"),
                    ));
                }
                recon_core::math::quat_to_matrix(q.map(|x| x as f32))
            }
            _ => return Err(Error::config(file, field, "give exactly one of `rotation` (3×3 rows) and `quaternion_wxyz`")),
        };
        if self.translation_m.iter().any(|t| !t.is_finite()) {
            return Err(Error::config(file, format!("{field}.translation_m"), "expected 3 finite numbers (metres)"));
        }
        Similarity32::new(r, self.translation_m.map(|x| x as f32), 1.0)
            .map_err(|e| Error::config(file, format!("{field}.rotation"), format!("expected a proper rotation: {e}")))
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntrinsicsSpec {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub width: usize,
    pub height: usize,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intrinsics: Option<IntrinsicsSpec>,
    /// Camera (OpenCV: x right, y down, z forward) → world.
    pub pose_world: PoseSpec,
}

/// How the support plane was found, in the camera frame (kept for the record).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlaneRecord {
    /// What the points came from (a depth image path).
    pub source: String,
    /// `normal · x + offset = 0` in the camera frame, normal towards the camera.
    pub normal_camera: [f64; 3],
    pub offset_camera_m: f64,
    pub points: usize,
    pub inliers: usize,
    /// RANSAC inlier distance, and the final band after refinement.
    pub threshold_m: f64,
    pub band_m: f64,
    pub rms_residual_m: f64,
    pub median_abs_residual_m: f64,
}

impl PlaneRecord {
    pub fn new(source: String, fit: &PlaneFit, plane_camera: &Plane) -> Self {
        PlaneRecord {
            source,
            normal_camera: plane_camera.normal,
            offset_camera_m: plane_camera.offset,
            points: fit.points,
            inliers: fit.inliers,
            threshold_m: fit.threshold_m,
            band_m: fit.band_m,
            rms_residual_m: fit.rms_residual_m,
            median_abs_residual_m: fit.median_abs_residual_m,
        }
    }
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SupportPlaneSpec {
    /// Material of the plane (default: the table's `support_plane_material`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub restitution: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fit: Option<PlaneRecord>,
}

/// Per-object physics overrides (everything optional).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsOverrides {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub density_kg_m3: Option<f64>,
    /// Total mass; rescales the density.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mass_kg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub restitution: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub treatment: Option<TreatmentChoice>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shell_thickness_m: Option<f64>,
}

fn default_scale() -> f64 {
    1.0
}
fn default_category() -> String {
    "object".into()
}
fn is_one(x: &f64) -> bool {
    *x == 1.0
}
fn is_default_physics(p: &PhysicsOverrides) -> bool {
    *p == PhysicsOverrides::default()
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectSpec {
    pub name: String,
    #[serde(default = "default_category")]
    pub category: String,
    pub mesh: PathBuf,
    /// Mesh units → metres (0.001 for millimetre meshes).
    #[serde(default = "default_scale", skip_serializing_if = "is_one")]
    pub scale: f64,
    pub pose: PoseSpec,
    #[serde(default, skip_serializing_if = "is_default_physics")]
    pub physics: PhysicsOverrides,
    /// Display colour (linear RGBA in [0, 1]); default: the material's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub color_rgba: Option<[f64; 4]>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
/// A scene description file (module docs).
pub struct SceneFile {
    /// File format version (1).
    pub version: u32,
    /// Free text: where the scene came from.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// The camera, if known (frames the directional predicates and the outputs).
    pub camera: Option<CameraSpec>,
    #[serde(default)]
    /// The support plane (material; z = 0 in the world frame).
    pub support_plane: SupportPlaneSpec,
    /// The objects.
    pub objects: Vec<ObjectSpec>,
}

fn parse_part<T: DeserializeOwned>(v: &serde_json::Value, file: &str, field: &str) -> Result<T> {
    serde_json::from_value(v.clone()).map_err(|e| Error::config(file, field, e.to_string()))
}

/// File-system-safe form of an object name (also used for USD prim names).
pub fn safe_name(name: &str) -> String {
    let s: String = name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '_' { c } else { '_' }).collect();
    if s.starts_with(|c: char| c.is_ascii_digit()) {
        format!("o{s}")
    } else {
        s
    }
}

impl SceneFile {
    /// Read and validate; mesh paths are resolved against the file's folder.
    pub fn load(path: &Path) -> Result<Self> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let mut s = Self::parse(&text, &file)?;
        let base = path.parent().unwrap_or(Path::new("."));
        for o in &mut s.objects {
            if o.mesh.is_relative() {
                o.mesh = base.join(&o.mesh);
            }
        }
        s.validate(&file)?;
        Ok(s)
    }

    /// Parse without touching the file system (no mesh-existence check).
    pub fn parse(text: &str, file: &str) -> Result<Self> {
        let v: serde_json::Value = serde_json::from_str(text).map_err(|e| Error::config(file, "<root>", format!("invalid JSON: {e}")))?;
        let root = v.as_object().ok_or_else(|| Error::config(file, "<root>", "expected a JSON object"))?;
        match root.get("version").map(|x| x.as_u64()) {
            None => return Err(Error::config(file, "version", format!("missing; this build reads \"version\": {VERSION}"))),
            Some(Some(n)) if n == VERSION as u64 => {}
            Some(_) => {
                return Err(Error::config(file, "version", format!("unsupported {}; this build reads version {VERSION}", root["version"])))
            }
        }
        const KNOWN: [&str; 5] = ["version", "source", "camera", "support_plane", "objects"];
        if let Some(k) = root.keys().find(|k| !KNOWN.contains(&k.as_str())) {
            return Err(Error::config(file, k.as_str(), format!("unknown field (expected one of {})", KNOWN.join(", "))));
        }
        let objs = root
            .get("objects")
            .ok_or_else(|| Error::config(file, "objects", "missing"))?
            .as_array()
            .ok_or_else(|| Error::config(file, "objects", "expected an array of objects"))?;
        let objects = objs
            .iter()
            .enumerate()
            .map(|(i, o)| parse_part::<ObjectSpec>(o, file, &format!("objects[{i}]")))
            .collect::<Result<Vec<_>>>()?;
        let s = SceneFile {
            version: VERSION,
            source: root.get("source").map(|x| parse_part(x, file, "source")).transpose()?,
            camera: root.get("camera").map(|x| parse_part(x, file, "camera")).transpose()?,
            support_plane: root.get("support_plane").map(|x| parse_part(x, file, "support_plane")).transpose()?.unwrap_or_default(),
            objects,
        };
        s.validate_values(file)?;
        Ok(s)
    }

    fn validate_values(&self, file: &str) -> Result<()> {
        if self.objects.is_empty() {
            return Err(Error::config(file, "objects", "the scene has no objects"));
        }
        let mut names = std::collections::BTreeMap::new();
        for (i, o) in self.objects.iter().enumerate() {
            let f = format!("objects[{i}]");
            if o.name.trim().is_empty() {
                return Err(Error::config(file, format!("{f}.name"), "must not be empty"));
            }
            if let Some(j) = names.insert(safe_name(&o.name), i) {
                return Err(Error::config(
                    file,
                    format!("{f}.name"),
                    format!("`{}` collides with objects[{j}] (`{}`): names must stay distinct as file names", o.name, self.objects[j].name),
                ));
            }
            if !(o.scale.is_finite() && o.scale > 0.0) {
                return Err(Error::config(
                    file,
                    format!("{f}.scale"),
                    format!("expected a positive number (mesh units → metres), got {}", o.scale),
                ));
            }
            o.pose.to_similarity(file, &format!("{f}.pose"))?;
            let p = &o.physics;
            let range = |v: Option<f64>, name: &str, lo: f64, hi: f64, what: &str| -> Result<()> {
                match v {
                    Some(x) if !(x.is_finite() && x > lo && x <= hi) => {
                        Err(Error::config(file, format!("{f}.physics.{name}"), format!("expected {what}, got {x}")))
                    }
                    _ => Ok(()),
                }
            };
            range(p.density_kg_m3, "density_kg_m3", 0.0, 1e5, "a density in (0, 1e5] kg/m³")?;
            range(p.mass_kg, "mass_kg", 0.0, 1e4, "a mass in (0, 1e4] kg")?;
            range(p.shell_thickness_m, "shell_thickness_m", 0.0, 0.1, "a wall thickness in (0, 0.1] m")?;
            range(p.friction.map(|x| x + 1.0), "friction", 0.0, 3.0, "a friction coefficient in [0, 2]")?;
            range(p.restitution.map(|x| x + 1.0), "restitution", 0.0, 2.0, "a restitution in [0, 1]")?;
            if let Some(c) = o.color_rgba {
                crate::materials::check_rgba(c, file, &format!("{f}.color_rgba"))?;
            }
        }
        if let Some(c) = &self.camera {
            c.pose_world.to_similarity(file, "camera.pose_world")?;
            if let Some(k) = &c.intrinsics {
                let ok = [k.fx, k.fy, k.cx, k.cy].iter().all(|x| x.is_finite()) && k.fx > 0.0 && k.fy > 0.0 && k.width > 0 && k.height > 0;
                if !ok {
                    return Err(Error::config(
                        file,
                        "camera.intrinsics",
                        "expected finite fx, fy > 0, cx, cy and a positive width and height",
                    ));
                }
            }
        }
        let sp = &self.support_plane;
        if sp.friction.is_some_and(|x| !(x.is_finite() && (0.0..=2.0).contains(&x))) {
            return Err(Error::config(file, "support_plane.friction", "expected a friction coefficient in [0, 2]"));
        }
        if sp.restitution.is_some_and(|x| !(x.is_finite() && (0.0..=1.0).contains(&x))) {
            return Err(Error::config(file, "support_plane.restitution", "expected a restitution in [0, 1]"));
        }
        Ok(())
    }

    /// Values plus mesh files present and PLY.
    pub fn validate(&self, file: &str) -> Result<()> {
        self.validate_values(file)?;
        for (i, o) in self.objects.iter().enumerate() {
            if !o.mesh.is_file() {
                return Err(Error::config(file, format!("objects[{i}].mesh"), format!("mesh file {} does not exist", o.mesh.display())));
            }
            if o.mesh.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()) != Some("ply".into()) {
                return Err(Error::config(file, format!("objects[{i}].mesh"), format!("{}: only PLY meshes are read", o.mesh.display())));
            }
        }
        Ok(())
    }

    /// The scene file as pretty JSON.
    pub fn to_json(&self) -> Result<String> {
        serde_json::to_string_pretty(self).map_err(|e| Error::msg(format!("scene file: {e}")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOOD: &str = r#"{
      "version": 1,
      "camera": { "pose_world": { "rotation": [[1,0,0],[0,-1,0],[0,0,-1]], "translation_m": [0, 0, 0.8] } },
      "support_plane": { "material": "wood" },
      "objects": [
        { "name": "mug", "category": "mug", "mesh": "mug.ply", "scale": 0.001,
          "pose": { "quaternion_wxyz": [1, 0, 0, 0], "translation_m": [0.1, 0, 0] },
          "physics": { "mass_kg": 0.3 } },
        { "name": "box", "mesh": "box.ply",
          "pose": { "rotation": [[0,-1,0],[1,0,0],[0,0,1]], "translation_m": [0, 0.1, 0.05] } }
      ]
    }"#;

    fn err(text: &str) -> String {
        SceneFile::parse(text, "scene.json").unwrap_err().to_string()
    }

    #[test]
    fn parses_and_round_trips() {
        let s = SceneFile::parse(GOOD, "scene.json").unwrap();
        assert_eq!(s.objects.len(), 2);
        assert_eq!(s.objects[1].category, "object");
        assert_eq!(s.objects[1].scale, 1.0);
        assert_eq!(s.objects[0].physics.mass_kg, Some(0.3));
        let back = SceneFile::parse(&s.to_json().unwrap(), "again.json").unwrap();
        assert_eq!(back, s);
    }

    #[test]
    fn errors_name_file_and_field() {
        let cases = [
            (GOOD.replace("\"version\": 1", "\"version\": 7"), "version"),
            (GOOD.replace("\"version\": 1,", ""), "version"),
            (GOOD.replace("\"scale\": 0.001", "\"scale\": -2"), "objects[0].scale"),
            (GOOD.replace("\"quaternion_wxyz\": [1, 0, 0, 0]", "\"quaternion_wxyz\": [2, 0, 0, 0]"), "objects[0].pose.quaternion_wxyz"),
            (GOOD.replace("[[0,-1,0],[1,0,0],[0,0,1]]", "[[0,1,0],[1,0,0],[0,0,1]]"), "objects[1].pose.rotation"),
            (GOOD.replace("\"mass_kg\": 0.3", "\"mass_kg\": 0"), "objects[0].physics.mass_kg"),
            (GOOD.replace("\"mass_kg\": 0.3", "\"mas_kg\": 0.3"), "objects[0]"),
            (GOOD.replace("\"name\": \"box\"", "\"name\": \"mug\""), "objects[1].name"),
            (GOOD.replace("\"mesh\": \"box.ply\",", ""), "objects[1]"),
            (GOOD.replace("\"support_plane\"", "\"suport_plane\""), "suport_plane"),
            (GOOD.replace("\"translation_m\": [0, 0, 0.8]", "\"translation_m\": [0, 0]"), "camera"),
        ];
        for (text, field) in cases {
            let e = err(&text);
            assert!(e.contains("scene.json") && e.contains(&format!("`{field}`")), "want field {field}: {e}");
        }
        assert!(err(&GOOD.replace("\"mass_kg\"", "\"mas_kg\"")).contains("unknown field `mas_kg`"));
        assert!(err("[1, 2]").contains("expected a JSON object"));
        assert!(err("{\"version\": 1, \"objects\": []}").contains("no objects"));
        // Both rotation forms, or neither.
        let both =
            GOOD.replace("\"quaternion_wxyz\": [1, 0, 0, 0]", "\"quaternion_wxyz\": [1, 0, 0, 0], \"rotation\": [[1,0,0],[0,1,0],[0,0,1]]");
        assert!(err(&both).contains("exactly one"));
    }

    #[test]
    fn load_resolves_meshes_and_checks_they_exist() {
        let dir = recon_testkit::tmp("scene-file");
        std::fs::write(dir.join("scene.json"), GOOD).unwrap();
        let e = SceneFile::load(&dir.join("scene.json")).unwrap_err().to_string();
        assert!(e.contains("objects[0].mesh") && e.contains("does not exist"), "{e}");
        std::fs::write(dir.join("mug.ply"), "x").unwrap();
        std::fs::write(dir.join("box.ply"), "x").unwrap();
        let s = SceneFile::load(&dir.join("scene.json")).unwrap();
        assert_eq!(s.objects[0].mesh, dir.join("mug.ply"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
