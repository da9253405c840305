//! A settled, annotated scene: objects with physics and collision, built from a scene file.

use crate::collision::{build_collision, Collision, CollisionMethod, CollisionOptions};
use crate::materials::{MaterialSource, MaterialTable};
use crate::physics::{annotate, check_mesh, Inertial, MeshReport, TreatmentChoice};
use crate::scene_file::{safe_name, ObjectSpec, PoseSpec, SceneFile};
use crate::settle::{settle, Body, BodySettle, SettleOptions, SettleResult};
use rayon::prelude::*;
use recon_core::engine::MeshColour;
use recon_core::math::Similarity32;
use recon_core::mesh::trimesh::TriMesh;
use recon_core::mesh::{Mesh, TexturedMesh};
use recon_core::{Error, Result};
use serde::Serialize;
use std::path::PathBuf;

/// The settings `build_scene` runs with (derived from [`crate::SceneOptions`], the flags a user sets).
#[derive(Debug, Clone)]
pub struct SceneSettings {
    /// How collision geometry is built.
    pub collision: CollisionMethod,
    /// Parameters of the collision builders (VHACD, primitive fits).
    pub collision_opts: CollisionOptions,
    /// Settling parameters.
    pub settle: SettleOptions,
    /// Whether meshes with vertex colours get a UV atlas and a baked texture.
    pub colour: MeshColour,
    /// Side of a baked texture, texels.
    pub texture_size: u32,
}

impl Default for SceneSettings {
    fn default() -> Self {
        Self {
            collision: CollisionMethod::Convex,
            collision_opts: CollisionOptions::new(),
            settle: SettleOptions::default(),
            colour: MeshColour::Texture,
            texture_size: recon_core::engine::DEFAULT_TEXTURE_SIZE,
        }
    }
}

/// Friction and restitution of the support plane.
#[derive(Debug, Clone, Serialize)]
pub struct PlaneMaterial {
    /// Material name.
    pub material: String,
    /// Coulomb friction coefficient.
    pub friction: f64,
    /// Restitution coefficient.
    pub restitution: f64,
}

/// One annotated, settled object. Geometry is in its body frame: origin at
/// the centre of mass, axes of the mesh file (scaled to metres).
#[derive(Debug, Clone)]
pub struct SimObject {
    /// Object name (from the scene file).
    pub name: String,
    /// File and prim name.
    pub id: String,
    /// Category (selects the default material).
    pub category: String,
    /// Material name.
    pub material: String,
    /// Where the material came from (explicit, category or default).
    pub material_source: MaterialSource,
    /// Coulomb friction coefficient.
    pub friction: f64,
    /// Restitution coefficient.
    pub restitution: f64,
    /// Display colour (linear RGBA): the object's own, else its material's.
    pub color_rgba: Option<[f32; 4]>,
    /// The mesh file it was loaded from.
    pub mesh_file: PathBuf,
    /// Visual mesh in the body frame (metres).
    pub visual: Mesh,
    /// The visual mesh on a UV atlas with a texture baked from the mesh file's vertex
    /// colours (`--colour texture` and a mesh with colours; `None` otherwise): written as
    /// `visual.obj` + `visual.mtl` + `texture.png` and used by the MJCF, URDF and USD.
    pub textured: Option<TexturedMesh>,
    /// Mesh checks (closed, oriented, ...) and the treatment chosen.
    pub mesh_report: MeshReport,
    /// `com` is in the scaled mesh file frame; the inertia is about it.
    pub inertial: Inertial,
    /// Collision geometry in the body frame.
    pub collision: Collision,
    /// Body → world before settling.
    pub start: Similarity32,
    /// Body → world after settling.
    pub end: Similarity32,
    /// Settling outcome of the body (motion, contacts, flags).
    pub settle: BodySettle,
    /// Lowest visual-mesh point above the plane after settling (metres).
    pub bottom_z_m: f64,
    /// The object's entry in the input scene file.
    pub spec: ObjectSpec,
}

impl SimObject {
    /// Principal moments and axes (columns, det +1) of the inertia tensor.
    pub fn principal_inertia(&self) -> ([f64; 3], [[f64; 3]; 3]) {
        principal(&self.inertial.inertia)
    }
}

/// Eigen-decomposition of a symmetric tensor: moments and a proper rotation.
pub fn principal(i: &[[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let m = nalgebra::Matrix3::from_fn(|r, c| 0.5 * (i[r][c] + i[c][r]));
    let e = m.symmetric_eigen();
    let mut idx = [0usize, 1, 2];
    idx.sort_by(|a, b| e.eigenvalues[*a].total_cmp(&e.eigenvalues[*b]));
    let mut axes: [[f64; 3]; 3] = std::array::from_fn(|r| idx.map(|c| e.eigenvectors[(r, c)]));
    let det = nalgebra::Matrix3::from_fn(|r, c| axes[r][c]).determinant();
    if det < 0.0 {
        for row in &mut axes {
            row[2] = -row[2];
        }
    }
    (idx.map(|k| e.eigenvalues[k].max(0.0)), axes)
}

#[derive(Debug, Clone, Serialize, Default)]
/// Wall-clock time of each phase of `recon scene`, in seconds.
pub struct Timings {
    /// Physics annotation and collision geometry.
    pub annotate_and_collision_s: f64,
    /// Settling.
    pub settle_s: f64,
    /// Writing the outputs.
    pub export_s: f64,
}

#[derive(Debug, Clone)]
/// A built, settled scene: what [`crate::write_outputs`] writes.
pub struct SimScene {
    /// The scene file it was built from.
    pub input: SceneFile,
    /// The support plane's material.
    pub plane: PlaneMaterial,
    /// The objects, in input order.
    pub objects: Vec<SimObject>,
    /// Outcome of the settle.
    pub settle: SettleResult,
    /// Options it was built with.
    pub options: SceneSettings,
    /// Wall-clock times of the phases.
    pub timings: Timings,
}

/// Load meshes, annotate physics, build collision geometry (objects in
/// parallel, results in input order) and settle.
pub fn build_scene(scene: &SceneFile, table: &MaterialTable, opts: &SceneSettings, file: &str) -> Result<SimScene> {
    opts.settle.validate()?;
    let t0 = std::time::Instant::now();
    let prepared: Vec<Result<Prepared>> =
        scene.objects.par_iter().enumerate().map(|(i, o)| prepare_object(i, o, table, opts, file)).collect();
    let prepared = prepared.into_iter().collect::<Result<Vec<_>>>()?;
    let annotate_s = t0.elapsed().as_secs_f64();

    let pm_name = scene.support_plane.material.clone().unwrap_or_else(|| table.support_plane_material.clone());
    let pm = table.get(&pm_name).ok_or_else(|| Error::config(file, "support_plane.material", format!("unknown material `{pm_name}`")))?;
    let plane = PlaneMaterial {
        friction: scene.support_plane.friction.unwrap_or(pm.friction),
        restitution: scene.support_plane.restitution.unwrap_or(pm.restitution),
        material: pm_name,
    };
    let bodies: Vec<Body> = prepared.iter().map(Prepared::body).collect();
    let t1 = std::time::Instant::now();
    let result = settle(&bodies, plane.friction, plane.restitution, &opts.settle)?;
    let settle_s = t1.elapsed().as_secs_f64();
    let objects = prepared.into_iter().zip(&result.bodies).map(|(p, s)| p.finish(s)).collect();
    Ok(SimScene {
        input: scene.clone(),
        plane,
        objects,
        settle: result,
        options: opts.clone(),
        timings: Timings { annotate_and_collision_s: annotate_s, settle_s, export_s: 0.0 },
    })
}

/// An annotated object with collision geometry, before settling. Its body
/// frame has the origin at the centre of mass.
#[derive(Debug, Clone)]
pub(crate) struct Prepared {
    pub spec: ObjectSpec,
    pub material: String,
    pub material_source: MaterialSource,
    pub friction: f64,
    pub restitution: f64,
    pub visual: Mesh,
    pub textured: Option<TexturedMesh>,
    pub mesh_report: MeshReport,
    pub inertial: Inertial,
    pub collision: Collision,
    pub start: Similarity32,
    pub color_rgba: Option<[f32; 4]>,
}

impl Prepared {
    pub fn body(&self) -> Body {
        Body {
            name: self.spec.name.clone(),
            pose: self.start,
            mass_kg: self.inertial.mass_kg,
            inertia: self.inertial.inertia,
            friction: self.friction,
            restitution: self.restitution,
            parts: self.collision.parts.clone(),
        }
    }

    /// The settled object.
    pub fn finish(self, s: &BodySettle) -> SimObject {
        let p = self;
        let end = Similarity32 { rotation: s.rotation, translation: s.translation_m, scale: 1.0 };
        let bottom = p.visual.vertices.iter().map(|v| end.apply(v)[2] as f64).fold(f64::INFINITY, f64::min);
        SimObject {
            name: p.spec.name.clone(),
            id: safe_name(&p.spec.name),
            category: p.spec.category.clone(),
            material: p.material,
            material_source: p.material_source,
            friction: p.friction,
            restitution: p.restitution,
            color_rgba: p.color_rgba,
            mesh_file: p.spec.mesh.clone(),
            visual: p.visual,
            textured: p.textured,
            mesh_report: p.mesh_report,
            inertial: p.inertial,
            collision: p.collision,
            start: p.start,
            end,
            settle: s.clone(),
            bottom_z_m: bottom,
            spec: p.spec,
        }
    }
}

fn prepare_object(i: usize, o: &ObjectSpec, table: &MaterialTable, opts: &SceneSettings, file: &str) -> Result<Prepared> {
    let mesh_file = o.mesh.display().to_string();
    let (tm, colours): (TriMesh, _) = recon_core::dataset::ply::read_ply_with_colors(&o.mesh)?;
    if tm.faces.is_empty() {
        return Err(Error::input(&mesh_file, "mesh has no faces (a point cloud cannot be simulated)"));
    }
    let s = o.scale;
    // Vertex colours ride along as attributes (RGB, then a neutral normal-map triple) for the texture bake.
    let vertex_attrs = colours.map(|c| c.into_iter().map(|c| [c[0], c[1], c[2], 0.5, 0.5, 1.0]).collect());
    let raw = Mesh { vertices: tm.vertices.iter().map(|v| v.map(|x| (x * s) as f32)).collect(), faces: tm.faces, vertex_attrs };
    prepare_mesh(i, o, &raw, &mesh_file, table, opts, file)
}

/// `raw`'s vertex colours (`attrs`) on the vertices of `checked` (`raw` after
/// [`check_mesh`]: welded and cleaned, the same positions), found by exact position.
fn colours_by_position(raw: &Mesh, attrs: &[[f32; 6]], checked: &Mesh) -> Vec<[f32; 6]> {
    let key = |v: &[f32; 3]| v.map(|x| if x == 0.0 { 0 } else { x.to_bits() });
    let by_position: std::collections::HashMap<[u32; 3], [f32; 6]> = raw.vertices.iter().map(key).zip(attrs.iter().copied()).collect();
    checked.vertices.iter().map(|v| by_position.get(&key(v)).copied().unwrap_or([0.5, 0.5, 0.5, 0.5, 0.5, 1.0])).collect()
}

/// Check, annotate and build collision for `raw` (the object's mesh in
/// metres, in the frame `o.pose` places); `mesh_file` names it in errors.
pub(crate) fn prepare_mesh(
    i: usize,
    o: &ObjectSpec,
    raw: &Mesh,
    mesh_file: &str,
    table: &MaterialTable,
    opts: &SceneSettings,
    file: &str,
) -> Result<Prepared> {
    let field = format!("objects[{i}]");
    let (mesh, mesh_report) = check_mesh(raw, mesh_file)?;
    let (material, material_source) =
        table.resolve(o.physics.material.as_deref(), &o.category, file, &format!("{field}.physics.material"))?;
    let mat = table.get(&material).copied().ok_or_else(|| Error::msg(format!("material {material} vanished")))?;
    let inertial = annotate(
        &mesh,
        &mesh_report,
        o.physics.treatment.unwrap_or(TreatmentChoice::Auto),
        o.physics.density_kg_m3.unwrap_or(mat.density_kg_m3),
        o.physics.shell_thickness_m.unwrap_or(mat.shell_thickness_m),
        o.physics.mass_kg,
        mesh_file,
    )?;
    let com = inertial.com.map(|x| x as f32);
    let colours = raw.vertex_attrs.as_ref().filter(|_| opts.colour == MeshColour::Texture).map(|a| colours_by_position(raw, a, &mesh));
    let visual = Mesh { vertices: mesh.vertices.iter().map(|v| [v[0] - com[0], v[1] - com[1], v[2] - com[2]]).collect(), ..mesh };
    // The texture of a mesh with vertex colours: its atlas baked from those colours.
    let textured = match colours {
        Some(c) => {
            let coloured = Mesh { vertex_attrs: Some(c), ..visual.clone() };
            let bake = recon_core::render::texture_mesh(&coloured, opts.texture_size, &[], &recon_core::render::BakeOptions::default());
            Some(bake.map_err(|e| Error::input(mesh_file, format!("texture: {e}")))?.0)
        }
        None => None,
    };
    let mut copts = opts.collision_opts.clone();
    copts.seed = copts.seed.wrapping_add(i as u64);
    let collision = build_collision(&visual, mesh_report.volume_m3, opts.collision, &copts, mesh_file)?;
    let pose = o.pose.to_similarity(file, &format!("{field}.pose"))?;
    let start = Similarity32 { rotation: pose.rotation, translation: pose.apply(&com), scale: 1.0 };
    Ok(Prepared {
        spec: o.clone(),
        material,
        material_source,
        friction: o.physics.friction.unwrap_or(mat.friction),
        restitution: o.physics.restitution.unwrap_or(mat.restitution),
        visual,
        textured,
        mesh_report,
        inertial,
        collision,
        start,
        color_rgba: o.color_rgba.or(mat.color_rgba).map(|c| c.map(|x| x as f32)),
    })
}

/// Per-object summary row (also the displacement table printed by the CLI).
#[derive(Debug, Clone, Serialize)]
pub struct ObjectSummary<'a> {
    /// Object name.
    pub name: &'a str,
    /// Category.
    pub category: &'a str,
    /// Material name.
    pub material: &'a str,
    /// Where the material came from.
    pub material_source: MaterialSource,
    /// Mesh file, as written.
    pub mesh: String,
    /// Mesh checks.
    pub mesh_check: &'a MeshReport,
    /// Mass, centre of mass and inertia.
    pub physics: &'a Inertial,
    /// Coulomb friction coefficient.
    pub friction: f64,
    /// Restitution coefficient.
    pub restitution: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    /// Display colour (linear RGBA), if any.
    pub color_rgba: Option<[f32; 4]>,
    /// How the collision geometry was built and what it is.
    pub collision: &'a crate::collision::CollisionReport,
    /// Pose before settling.
    pub start_pose: PoseSpec,
    /// Pose after settling.
    pub settled_pose: PoseSpec,
    /// Deepest overlap at the start pose (with the plane or another object), and what with.
    pub start_penetration_mm: f64,
    /// What the deepest start overlap was with (`None`: no overlap).
    pub start_penetration_with: Option<&'a str>,
    /// Deepest overlap left after settling.
    pub end_penetration_mm: f64,
    /// Translation of the body origin (centre of mass) during settling (mm).
    pub displacement_mm: f64,
    /// Rotation during settling (degrees).
    pub rotation_deg: f64,
    /// Lowest mesh point above the plane after settling.
    pub bottom_above_plane_mm: f64,
    /// Bodies (or "plane") in contact after settling.
    pub touching: &'a [String],
    /// Whether settling raised a concern (large motion, overlap left, still moving).
    pub flagged: bool,
    /// Why it was flagged.
    pub flag_reasons: &'a [String],
}

impl SimScene {
    /// One summary row per object, in input order.
    pub fn summaries(&self) -> Vec<ObjectSummary<'_>> {
        self.objects
            .iter()
            .map(|o| ObjectSummary {
                name: &o.name,
                category: &o.category,
                material: &o.material,
                material_source: o.material_source,
                mesh: o.mesh_file.display().to_string(),
                mesh_check: &o.mesh_report,
                physics: &o.inertial,
                friction: o.friction,
                restitution: o.restitution,
                color_rgba: o.color_rgba,
                collision: &o.collision.report,
                start_pose: PoseSpec::from_similarity(&o.start),
                settled_pose: PoseSpec::from_similarity(&o.end),
                start_penetration_mm: o.settle.start_penetration_m * 1e3,
                start_penetration_with: o.settle.start_penetration_with.as_deref(),
                end_penetration_mm: o.settle.end_penetration_m * 1e3,
                displacement_mm: o.settle.displacement_m * 1e3,
                rotation_deg: o.settle.rotation_deg,
                bottom_above_plane_mm: o.bottom_z_m * 1e3,
                touching: &o.settle.touching,
                flagged: o.settle.flagged,
                flag_reasons: &o.settle.flag_reasons,
            })
            .collect()
    }

    /// The settled scene as a scene file whose meshes are the written
    /// body-frame visual meshes (`meshes/<id>/visual.ply`).
    pub fn settled_scene_file(&self) -> SceneFile {
        let mut s = self.input.clone();
        s.source = Some(format!("recon scene: settled from {}", self.input.source.clone().unwrap_or_else(|| "a scene file".into())));
        for (spec, o) in s.objects.iter_mut().zip(&self.objects) {
            spec.mesh = PathBuf::from(format!("meshes/{}/visual.ply", o.id));
            spec.scale = 1.0;
            spec.pose = PoseSpec::from_similarity(&o.end);
        }
        s
    }

    /// Fixed-width per-object table: deepest overlap (mm) at the start and
    /// after settling, displacement, rotation, lowest point above the plane
    /// (`gap_mm`), collision parts, mass model, flags.
    pub fn table(&self) -> String {
        let mut s = format!(
            "{:<20} {:>8} {:>9} {:>8} {:>8} {:>8} {:>6} {:>8} {:>10} {:>6}  {}\n",
            "object", "mass_kg", "overlap0", "overlap1", "move_mm", "rot_deg", "parts", "gap_mm", "collision", "model", "flag"
        );
        for o in &self.objects {
            s += &format!(
                "{:<20} {:>8.4} {:>9.2} {:>8.2} {:>8.2} {:>8.2} {:>6} {:>8.2} {:>10} {:>6}  {}\n",
                o.name,
                o.inertial.mass_kg,
                o.settle.start_penetration_m * 1e3,
                o.settle.end_penetration_m * 1e3,
                o.settle.displacement_m * 1e3,
                o.settle.rotation_deg,
                o.collision.report.parts,
                o.bottom_z_m * 1e3,
                o.collision.report.used,
                if o.inertial.treatment == crate::physics::Treatment::Shell { "shell" } else { "solid" },
                if o.settle.flagged { o.settle.flag_reasons.join("; ") } else { "-".into() }
            );
        }
        s
    }
}

/// The texture of a textured object, beside its `visual.obj` (`meshes/<id>/texture.png`).
pub const TEXTURE_FILE: &str = "texture.png";

/// File name of hull part `k` under `meshes/<id>/`.
pub fn hull_file(k: usize) -> String {
    format!("collision_{k:02}.obj")
}
