//! Scene variations: many settled, simulator-ready scenes from one scene.
//!
//! The scene is settled once; each object keeps its resting orientation and
//! is re-placed (with a random yaw) on the support plane under the spec's
//! spatial predicates, or under predicates sampled per variant. Distractors
//! come from `recon synth`'s procedural library and from a folder of the
//! user's meshes ([`AssetLibrary`]); scene objects may be rescaled,
//! stretched and given another material or colour (mass, inertia and
//! collision geometry are rebuilt). Every variant is settled with rapier
//! and kept only when at rest (every point of every object moved < 1 mm over
//! the last 0.5 s); the predicates are then judged on the settled poses.
//!
//! Output: `variant_NNNN/` folders as `recon scene` writes them (without
//! wall-clock timings) and `manifest.json`, written last. A run depends on
//! the scene, the spec, the options and the seed only: the same seed gives
//! byte-identical files.

mod assets;
mod place;
mod profile;
pub mod spec;

pub use assets::{Asset, AssetLibrary, AssetPhysics, UpAxis};
pub use place::Judged;
pub use spec::{AssetSpec, Category, DirFrame, Predicate, VariationSpec};

use crate::materials::MaterialTable;
use crate::scene::{build_scene, prepare_mesh, Prepared, SceneSettings, SimScene, Timings};
use crate::scene_file::{safe_name, ObjectSpec, PoseSpec, SceneFile};
use crate::settle::{part_shapes, settle, SettleOptions};
use place::{Bound, Placeable, Region, WorldView};
use profile::Profile;
use rayon::prelude::*;
use recon_core::math::Similarity32;
use recon_core::mesh::Mesh;
use recon_core::rng::SeededRng;
use recon_core::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Written last into a variations output folder; marks it complete.
pub const MANIFEST: &str = "manifest.json";
/// Placement and settle attempts per variant before it is reported as failed.
const ATTEMPTS: u64 = 4;
/// Placements from scratch per attempt.
const PLACEMENTS: usize = 4;
/// The rest test: every point moved less than this over the last `REST_WINDOW_S`.
const REST_MOTION_M: f64 = 0.001;
const REST_WINDOW_S: f64 = 0.5;

/// What [`run_variations`] is asked for.
#[derive(Debug, Clone)]
pub struct VariationOptions {
    /// Variants to write (1 to 10 000).
    pub count: usize,
    /// Every variant's seed derives from it: the same seed gives byte-identical files.
    pub seed: u64,
    /// Predicates, region, distractors and object variants.
    pub spec: VariationSpec,
    /// Names the spec in errors.
    pub spec_file: String,
    /// The spec's asset folder, loaded ahead (the CLI does, to fail before
    /// reading the scene); `None` loads it at the start of the run.
    pub assets: Option<AssetLibrary>,
}

impl VariationOptions {
    /// Options whose asset folder (if the spec has one) is loaded by the run.
    pub fn new(count: usize, seed: u64, spec: VariationSpec, spec_file: impl Into<String>) -> Self {
        Self { count, seed, spec, spec_file: spec_file.into(), assets: None }
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct FrameRecord {
    /// "camera" or "world" (the camera frame falls back to world without a camera).
    pub used: &'static str,
    /// Unit directions on the plane (world x, y) of `right_of` and `behind`.
    pub right: [f64; 2],
    pub behind: [f64; 2],
}

#[derive(Debug, Clone, Serialize)]
pub struct ObjectRecord {
    pub name: String,
    pub category: String,
    /// "scene", "distractor" (procedural library) or "asset" (the user's folder).
    pub source: &'static str,
    /// The asset's path in its folder.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub asset: Option<String>,
    /// Scale of the scene object along its resting axes (x, y, z); distractors: their size factor.
    pub scale: [f64; 3],
    pub material: String,
    /// Density the mass came from (the material's, or the object's override).
    pub density_kg_m3: f64,
    pub mass_kg: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub color_rgba: Option<[f32; 4]>,
    pub start_pose: PoseSpec,
    pub settled_pose: PoseSpec,
    /// Bound on any point's motion over the last 0.5 s of the settle.
    pub rest_motion_mm: f64,
    pub displacement_mm: f64,
    pub rotation_deg: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct PredicateRecord {
    pub label: String,
    pub predicate: Predicate,
    #[serde(flatten)]
    pub judged: Judged,
}

#[derive(Debug, Clone, Serialize)]
pub struct SettleStats {
    pub simulated_s: f64,
    pub steps: usize,
    pub at_rest: bool,
    /// Largest motion bound of any object over the last 0.5 s.
    pub max_rest_motion_mm: f64,
    pub max_displacement_mm: f64,
    pub max_end_penetration_mm: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct VariantRecord {
    pub index: usize,
    /// Folder under the output, when kept.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dir: Option<String>,
    pub kept: bool,
    /// Attempts made (each with its own seed); the last one is described here.
    pub attempts: u64,
    pub seed: u64,
    pub all_predicates_hold: bool,
    pub predicates: Vec<PredicateRecord>,
    pub objects: Vec<ObjectRecord>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub settle: Option<SettleStats>,
    /// Why the last attempt was rejected.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rejected: Option<String>,
    /// Why each earlier attempt was rejected.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub earlier_attempts: Vec<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct RegionRecord {
    pub center_m: [f64; 2],
    pub half_extent_m: [f64; 2],
}

#[derive(Debug, Clone, Serialize)]
/// The `manifest.json` of a variations run.
pub struct Manifest {
    /// File format version.
    pub version: u32,
    /// Seed of the run.
    pub seed: u64,
    /// Variants asked for.
    pub requested: usize,
    /// Variants kept (settled at rest).
    pub kept: usize,
    /// Kept variants whose every predicate holds after settling, over kept variants.
    pub predicate_pass_rate: f64,
    /// Predicates that held, over all kept variants.
    pub predicates_held: usize,
    /// Predicates judged, over all kept variants.
    pub predicates_total: usize,
    /// Where the input scene came from (its `source`).
    pub source: Option<String>,
    /// The spec used.
    pub spec: VariationSpec,
    /// Frame of the directional predicates.
    pub frame: FrameRecord,
    /// Region objects were placed in.
    pub region: RegionRecord,
    /// The rest test a variant had to pass, in words.
    pub rest_test: String,
    /// Names of the scene objects.
    pub objects: Vec<String>,
    /// One record per variant kept.
    pub variants: Vec<VariantRecord>,
}

/// What [`run_variations`] returns: the manifest it wrote and the wall time (not written).
pub struct RunSummary {
    /// The manifest written.
    pub manifest: Manifest,
    /// Wall time of the run in seconds (not written).
    pub seconds: f64,
}

/// One scene object's data shared by all variants.
struct BaseObject {
    prepared: Prepared,
    /// Body → resting frame: the settled orientation.
    orient: [[f32; 3]; 3],
    placeable: Placeable,
}

/// Placer data for a body-frame mesh and collision, turned by `orient` to its resting frame.
fn placeable(name: &str, visual: &Mesh, parts_body: &Prepared, orient: [[f32; 3]; 3], shapes: bool, file: &str) -> Result<Placeable> {
    let orient = canonical(orient, &visual.vertices);
    let rot = |v: &[f32; 3]| -> [f64; 3] { std::array::from_fn(|i| (0..3).map(|k| orient[i][k] as f64 * v[k] as f64).sum()) };
    let rest = Mesh {
        vertices: visual.vertices.iter().map(|v| rot(v).map(|x| x as f32)).collect(),
        faces: visual.faces.clone(),
        vertex_attrs: None,
    };
    let hull_mesh = crate::collision::convex_hull(&rest.vertices, file)?;
    let mut hull: Vec<[f64; 3]> = hull_mesh.vertices.iter().map(|v| v.map(|x| x as f64)).collect();
    for p in &parts_body.collision.parts {
        hull.extend(p.surface_mesh().vertices.iter().map(rot));
    }
    let zmin = hull.iter().map(|p| p[2]).fold(f64::INFINITY, f64::min);
    let zmax = hull.iter().map(|p| p[2]).fold(f64::NEG_INFINITY, f64::max);
    let radius = hull.iter().map(|p| p[0].hypot(p[1])).fold(0.0, f64::max);
    let profile = Profile::new(&rest).ok_or_else(|| Error::input(file, format!("{name}: degenerate mesh (no extent)")))?;
    let shapes = if shapes { part_shapes(&parts_body.body())? } else { vec![] };
    Ok(Placeable { orient, hull, zmin, zmax, radius, profile, shapes })
}

/// The orientation `p` comes to rest in when dropped alone on the plane from
/// `orient`: a resting pose in a crowded scene (a sphere balanced on a
/// vertex of its hull, held by a neighbour) need not be stable alone.
fn settle_alone(p: &Prepared, orient: [[f32; 3]; 3], plane: &crate::scene::PlaneMaterial, opts: &SettleOptions) -> Result<[[f32; 3]; 3]> {
    let zmin = p
        .collision
        .parts
        .iter()
        .flat_map(|q| q.surface_mesh().vertices)
        .map(|v| (0..3).map(|k| orient[2][k] * v[k]).sum::<f32>())
        .fold(f32::INFINITY, f32::min);
    let mut b = p.body();
    b.pose = Similarity32 { rotation: orient, translation: [0.0, 0.0, -zmin + 1e-4], scale: 1.0 };
    let r = settle(&[b], plane.friction, plane.restitution, opts)?;
    Ok(r.bodies[0].rotation)
}

/// `orient` followed by the yaw of the smallest footprint (see [`place::canonical_yaw`]).
fn canonical(orient: [[f32; 3]; 3], body_pts: &[[f32; 3]]) -> [[f32; 3]; 3] {
    let pts: Vec<[f64; 3]> =
        body_pts.iter().map(|v| std::array::from_fn(|i| (0..3).map(|k| orient[i][k] as f64 * v[k] as f64).sum())).collect();
    let yaw = place::canonical_yaw(&pts);
    let r = recon_core::math::axis_angle([0.0, 0.0, 1.0], yaw).map(|row| row.map(|x| x as f32));
    recon_core::math::matmul(&r, &orient)
}

/// Shape checks of the spec's predicates on the input meshes at their input
/// orientation (cheap: no collision geometry, no settling).
fn check_shapes(scene: &SceneFile, spec: &VariationSpec, file: &str) -> Result<()> {
    let need: std::collections::BTreeSet<&str> =
        spec.predicates.iter().filter(|p| p.is_support()).flat_map(|p| [p.objects().0, p.objects().1]).collect();
    let mut shapes = std::collections::BTreeMap::new();
    for (i, o) in scene.objects.iter().enumerate().filter(|(_, o)| need.contains(o.name.as_str())) {
        let tm = recon_core::dataset::ply::read_ply(&o.mesh)?;
        let pose = o.pose.to_similarity(file, &format!("objects[{i}].pose"))?;
        let r = canonical(pose.rotation, &tm.vertices.iter().map(|v| v.map(|x| (x * o.scale) as f32)).collect::<Vec<_>>());
        let turn = |v: &[f64; 3]| -> [f32; 3] { std::array::from_fn(|i| (0..3).map(|k| r[i][k] * (v[k] * o.scale) as f32).sum()) };
        let mesh = Mesh { vertices: tm.vertices.iter().map(turn).collect(), faces: tm.faces, vertex_attrs: None };
        let mf = o.mesh.display().to_string();
        let hull = crate::collision::convex_hull(&mesh.vertices, &mf)?;
        let profile = Profile::new(&mesh).ok_or_else(|| Error::input(&mf, format!("{}: degenerate mesh", o.name)))?;
        let hv: Vec<[f64; 3]> = hull.vertices.iter().map(|v| v.map(|x| x as f64)).collect();
        let zmin = hv.iter().map(|p| p[2]).fold(f64::INFINITY, f64::min);
        let zmax = hv.iter().map(|p| p[2]).fold(f64::NEG_INFINITY, f64::max);
        let p = Placeable {
            orient: recon_core::math::Similarity32::identity().rotation,
            radius: hv.iter().map(|p| p[0].hypot(p[1])).fold(0.0, f64::max),
            hull: hv,
            zmin,
            zmax,
            profile,
            shapes: vec![],
        };
        shapes.insert(o.name.as_str(), p);
    }
    let size = |p: &Placeable| {
        let (lo, hi) = (p.profile.lo, p.profile.hi);
        format!("{:.0} × {:.0} mm", (hi[0] - lo[0]) * 1e3, (hi[1] - lo[1]) * 1e3)
    };
    for (i, p) in spec.predicates.iter().enumerate() {
        let (a, b) = p.objects();
        let (Some(pa), Some(pb)) = (shapes.get(a), shapes.get(b)) else { continue };
        let field = format!("predicates[{i}]");
        match p {
            Predicate::OnTop { .. } => {
                if !place::fits(pa, pb, false) {
                    let top = pb.profile.plateau.iter().filter(|c| **c).count();
                    return Err(Error::config(
                        file,
                        field,
                        format!(
                            "{}: the flat top of `{b}` ({} of its {} footprint cells, footprint {}) is smaller than its load `{a}` ({})",
                            p.label(),
                            top,
                            pb.profile.plateau.len(),
                            size(pb),
                            size(pa)
                        ),
                    ));
                }
                if !pa.profile.flat_base() {
                    return Err(Error::config(
                        file,
                        field,
                        format!("{}: `{a}` has no flat base to stand on `{b}` (it would roll off)", p.label()),
                    ));
                }
            }
            Predicate::Inside { .. } => {
                if !pb.profile.has_cavity() {
                    return Err(Error::config(
                        file,
                        field,
                        format!("{}: `{b}` is a closed shape (no open cavity seen from above), nothing can go inside it", p.label()),
                    ));
                }
                if !place::fits(pa, pb, true) {
                    return Err(Error::config(
                        file,
                        field,
                        format!("{}: `{a}` ({}) does not fit in the opening of `{b}` ({})", p.label(), size(pa), size(pb)),
                    ));
                }
            }
            _ => {}
        }
    }
    Ok(())
}

/// Directions of the directional predicates on the plane.
fn frame_axes(scene: &SceneFile, frame: DirFrame, file: &str) -> Result<FrameRecord> {
    let world = FrameRecord { used: "world", right: [1.0, 0.0], behind: [0.0, 1.0] };
    let (DirFrame::Camera, Some(cam)) = (frame, &scene.camera) else { return Ok(world) };
    let r = cam.pose_world.to_similarity(file, "camera.pose_world")?.rotation;
    let unit = |v: [f64; 2]| {
        let n = v[0].hypot(v[1]);
        (n > 1e-3).then(|| [v[0] / n, v[1] / n])
    };
    // Camera axes in the world: columns of camera → world. Image up is −y.
    let right = unit([r[0][0] as f64, r[1][0] as f64]);
    let behind = unit([-r[0][1] as f64, -r[1][1] as f64]);
    Ok(match (right, behind) {
        (Some(right), Some(behind)) => FrameRecord { used: "camera", right, behind },
        _ => world,
    })
}

fn mix(seed: u64, index: usize, attempt: u64) -> u64 {
    // SplitMix-style mixing so neighbouring indices give unrelated streams.
    let mut z = seed ^ (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ attempt.wrapping_mul(0xD1B5_4A32_D192_ED03);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Build `count` variations of `scene` into `out` (see the module docs).
/// Every spec problem is reported before any collision geometry is built or
/// anything is settled.
pub fn run_variations(
    scene: &SceneFile,
    table: &MaterialTable,
    opts: &SceneSettings,
    v: &VariationOptions,
    file: &str,
    out: &Path,
) -> Result<RunSummary> {
    let t0 = std::time::Instant::now();
    let spec = &v.spec;
    let names: Vec<String> = scene.objects.iter().map(|o| o.name.clone()).collect();
    spec.check_names(&names, table, &v.spec_file)?;
    let loaded;
    let assets = match (&spec.distractors.assets, &v.assets) {
        (Some(_), Some(l)) => Some(l),
        (Some(a), None) => {
            loaded = AssetLibrary::load(a, table, &v.spec_file)?;
            Some(&loaded)
        }
        (None, _) => None,
    };
    check_shapes(scene, spec, &v.spec_file)?;
    if v.count == 0 || v.count > 10_000 {
        return Err(Error::input("--variations", format!("expected 1 to 10000 variations, got {}", v.count)));
    }
    if out.exists() {
        let empty = std::fs::read_dir(out).map(|mut d| d.next().is_none()).unwrap_or(false);
        if !empty && !out.join(MANIFEST).is_file() {
            return Err(Error::input(
                out.display().to_string(),
                format!("output folder exists and is not a variations output (no {MANIFEST}); remove it or choose another --out"),
            ));
        }
    }
    let frame = frame_axes(scene, spec.frame, file)?;
    let axes = [frame.right, frame.behind];

    // The scene settled once: resting orientations, annotated objects.
    let base = build_scene(scene, table, opts, file)?;
    let mut settle_opts = opts.settle.clone();
    settle_opts.rest_duration_s = REST_WINDOW_S;
    let bases: Vec<BaseObject> = base
        .objects
        .iter()
        .map(|o| {
            let prepared = Prepared {
                spec: o.spec.clone(),
                material: o.material.clone(),
                material_source: o.material_source,
                friction: o.friction,
                restitution: o.restitution,
                visual: o.visual.clone(),
                textured: o.textured.clone(),
                mesh_report: o.mesh_report.clone(),
                inertial: o.inertial.clone(),
                collision: o.collision.clone(),
                start: o.end,
                color_rgba: o.color_rgba,
            };
            let orient = settle_alone(&prepared, o.end.rotation, &base.plane, &settle_opts)?;
            let placeable = placeable(&o.name, &o.visual, &prepared, orient, true, &o.mesh_file.display().to_string())?;
            Ok(BaseObject { prepared, orient, placeable })
        })
        .collect::<Result<_>>()?;
    let region = match &spec.region {
        Some(r) => Region { centre: r.center_m, half: r.half_extent_m },
        None => {
            let n = bases.len() as f64;
            let c = [0, 1].map(|k| bases.iter().map(|b| b.prepared.start.translation[k] as f64).sum::<f64>() / n);
            let half = [0, 1].map(|k| {
                let spread =
                    bases.iter().map(|b| (b.prepared.start.translation[k] as f64 - c[k]).abs() + b.placeable.radius).fold(0.0, f64::max);
                (spread + 0.05).max(0.2)
            });
            Region { centre: c, half }
        }
    };

    let ctx = Ctx { scene, table, opts, spec, assets, bases: &bases, base: &base, region: &region, axes, settle: settle_opts, file, out };
    let variants: Vec<VariantRecord> = (0..v.count).into_par_iter().map(|i| ctx.variant(i, v.seed)).collect::<Result<_>>()?;

    let kept: Vec<&VariantRecord> = variants.iter().filter(|r| r.kept).collect();
    let all_hold = kept.iter().filter(|r| r.all_predicates_hold).count();
    let manifest = Manifest {
        version: 1,
        seed: v.seed,
        requested: v.count,
        kept: kept.len(),
        predicate_pass_rate: if kept.is_empty() { 0.0 } else { all_hold as f64 / kept.len() as f64 },
        predicates_held: kept.iter().flat_map(|r| &r.predicates).filter(|p| p.judged.holds).count(),
        predicates_total: kept.iter().map(|r| r.predicates.len()).sum(),
        source: scene.source.clone(),
        spec: spec.clone(),
        frame,
        region: RegionRecord { center_m: region.centre, half_extent_m: region.half },
        rest_test: format!("every point of every object moved < {} mm over the last {REST_WINDOW_S} s of the settle", REST_MOTION_M * 1e3),
        objects: names,
        variants,
    };
    // Drop variant folders of an earlier run that this one did not write.
    if let Ok(rd) = std::fs::read_dir(out) {
        let mut stale: Vec<PathBuf> = rd.filter_map(|e| e.ok().map(|e| e.path())).collect();
        stale.sort();
        for p in stale {
            let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("").to_string();
            let ours = manifest.variants.iter().any(|r| r.dir.as_deref() == Some(name.as_str()));
            if name.starts_with("variant_") && !ours && p.is_dir() {
                std::fs::remove_dir_all(&p).map_err(|e| Error::io(&p, e))?;
            }
        }
    }
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let text = serde_json::to_string_pretty(&manifest).map_err(|e| Error::msg(e.to_string()))?;
    let path = out.join(MANIFEST);
    std::fs::write(&path, text).map_err(|e| Error::io(&path, e))?;
    Ok(RunSummary { manifest, seconds: t0.elapsed().as_secs_f64() })
}

struct Ctx<'a> {
    scene: &'a SceneFile,
    table: &'a MaterialTable,
    opts: &'a SceneSettings,
    spec: &'a VariationSpec,
    assets: Option<&'a AssetLibrary>,
    bases: &'a [BaseObject],
    base: &'a SimScene,
    region: &'a Region,
    axes: [[f64; 2]; 2],
    settle: SettleOptions,
    file: &'a str,
    out: &'a Path,
}

/// One object of a variant.
struct VObj {
    prepared: Prepared,
    placeable: Placeable,
    source: &'static str,
    scale: [f64; 3],
    asset: Option<String>,
}

/// A variant's objects and predicates, before placement.
struct Draft {
    objs: Vec<VObj>,
    preds: Vec<Bound>,
}

impl Ctx<'_> {
    fn variant(&self, index: usize, seed: u64) -> Result<VariantRecord> {
        let mut earlier = Vec::new();
        let mut last = None;
        for attempt in 0..ATTEMPTS {
            let s = mix(seed, index, attempt);
            let mut rec = self.attempt(index, s, attempt + 1)?;
            if let Some(prev) = last.take().and_then(|r: VariantRecord| r.rejected) {
                earlier.push(prev);
            }
            rec.earlier_attempts = earlier.clone();
            if rec.kept {
                return Ok(rec);
            }
            last = Some(rec);
        }
        last.ok_or_else(|| Error::msg("no attempt made"))
    }

    fn attempt(&self, index: usize, seed: u64, attempts: u64) -> Result<VariantRecord> {
        let mut rng = SeededRng::new(seed);
        let draft = self.draft(&mut rng)?;
        let objs: Vec<Placeable> = draft.objs.iter().map(|o| o.placeable.clone()).collect();
        let mut rec = VariantRecord {
            index,
            dir: None,
            kept: false,
            attempts,
            seed,
            all_predicates_hold: false,
            predicates: vec![],
            objects: vec![],
            settle: None,
            rejected: None,
            earlier_attempts: vec![],
        };
        // A failed placement is restarted from scratch (the anchors land elsewhere) before the draft is redrawn.
        let mut placed = Err(0);
        for _ in 0..PLACEMENTS {
            placed = place::place(&objs, &draft.preds, self.region, self.axes, &mut rng)?;
            if placed.is_ok() {
                break;
            }
        }
        let poses = match placed {
            Ok(p) => p,
            Err(i) => {
                rec.rejected = Some(format!(
                    "no collision-free place for `{}` satisfying the predicates ({PLACEMENTS} placements tried)",
                    draft.objs[i].prepared.spec.name
                ));
                return Ok(rec);
            }
        };
        let mut prepared: Vec<Prepared> = draft.objs.iter().map(|o| o.prepared.clone()).collect();
        for (p, pose) in prepared.iter_mut().zip(&poses) {
            p.start = *pose;
            p.spec.pose = PoseSpec::from_similarity(pose);
        }
        let bodies: Vec<_> = prepared.iter().map(Prepared::body).collect();
        let plane = &self.base.plane;
        let result = settle(&bodies, plane.friction, plane.restitution, &self.settle)?;
        let ends: Vec<Option<Similarity32>> =
            result.bodies.iter().map(|b| Some(Similarity32 { rotation: b.rotation, translation: b.translation_m, scale: 1.0 })).collect();
        let view = WorldView { objs: &objs, poses: &ends, axes: self.axes };
        for p in &draft.preds {
            rec.predicates.push(PredicateRecord {
                label: p.pred.label(),
                predicate: p.pred.clone(),
                judged: view.judge(&p.pred, p.a, p.b)?,
            });
        }
        rec.all_predicates_hold = rec.predicates.iter().all(|p| p.judged.holds);
        let max = |f: &dyn Fn(&crate::settle::BodySettle) -> f64| result.bodies.iter().map(f).fold(0.0, f64::max);
        let motion = max(&|b| b.rest_motion_m);
        rec.settle = Some(SettleStats {
            simulated_s: result.simulated_s,
            steps: result.steps,
            at_rest: result.at_rest,
            max_rest_motion_mm: motion * 1e3,
            max_displacement_mm: max(&|b| b.displacement_m) * 1e3,
            max_end_penetration_mm: max(&|b| b.end_penetration_m) * 1e3,
        });
        for ((o, b), start) in draft.objs.iter().zip(&result.bodies).zip(&poses) {
            rec.objects.push(ObjectRecord {
                name: o.prepared.spec.name.clone(),
                category: o.prepared.spec.category.clone(),
                source: o.source,
                asset: o.asset.clone(),
                scale: o.scale,
                material: o.prepared.material.clone(),
                density_kg_m3: o.prepared.inertial.density_kg_m3,
                mass_kg: o.prepared.inertial.mass_kg,
                color_rgba: o.prepared.color_rgba,
                start_pose: PoseSpec::from_similarity(start),
                settled_pose: PoseSpec::from_similarity(&Similarity32 { rotation: b.rotation, translation: b.translation_m, scale: 1.0 }),
                rest_motion_mm: b.rest_motion_m * 1e3,
                displacement_mm: b.displacement_m * 1e3,
                rotation_deg: b.rotation_deg,
            });
        }
        // The rest test is on positions: a slow spin that moves no
        // point by a millimetre in the window passes, although the velocity
        // test that ends the settle early did not.
        if motion >= REST_MOTION_M {
            rec.rejected = Some(format!("not at rest: an object moved {:.2} mm over the last {REST_WINDOW_S} s", motion * 1e3));
            return Ok(rec);
        }
        // The variant as a recon scene output.
        let objects: Vec<_> = prepared.into_iter().zip(&result.bodies).map(|(p, s)| p.finish(s)).collect();
        let mut input = self.scene.clone();
        input.source = Some(format!(
            "recon scene --variations: variant {index} (seed {seed}) of {}",
            self.scene.source.as_deref().unwrap_or("a scene file")
        ));
        input.objects = objects.iter().map(|o| o.spec.clone()).collect();
        let mut sim = SimScene {
            input,
            plane: self.base.plane.clone(),
            objects,
            settle: result,
            options: self.opts.clone(),
            timings: Timings::default(),
        };
        let dir = format!("variant_{index:04}");
        crate::write::write_outputs_with(&mut sim, &self.out.join(&dir), false)?;
        rec.dir = Some(dir);
        rec.kept = true;
        Ok(rec)
    }

    /// Objects (scene objects, possibly varied, and distractors) and predicates of one variant.
    fn draft(&self, rng: &mut SeededRng) -> Result<Draft> {
        let ov = &self.spec.object_variants;
        let mut objs = Vec::new();
        for (i, b) in self.bases.iter().enumerate() {
            let vary = ov.probability > 0.0 && rng.uniform() < ov.probability;
            if !vary {
                objs.push(self.unvaried(i));
                continue;
            }
            let u = |rng: &mut SeededRng, r: [f64; 2]| r[0] + (r[1] - r[0]) * rng.uniform();
            let s = u(rng, ov.scale);
            let stretch = [u(rng, ov.aspect), u(rng, ov.aspect)];
            // Round objects (no flat base: balls) are only scaled: stretched they
            // lose their exact primitive and, as convex parts, rock without end.
            let scale = if b.placeable.profile.flat_base() { [s * stretch[0], s * stretch[1], s] } else { [s; 3] };
            let material = (!ov.materials.is_empty()).then(|| ov.materials[(rng.next_u64() % ov.materials.len() as u64) as usize].clone());
            let color = (!ov.colors.is_empty()).then(|| ov.colors[(rng.next_u64() % ov.colors.len() as u64) as usize]);
            // The body-frame mesh turned to rest, then stretched along the resting axes
            // (`build` settles it alone again: the stretched shape may rest differently).
            let o = b.orient;
            let raw = Mesh {
                vertices: b
                    .prepared
                    .visual
                    .vertices
                    .iter()
                    .map(|v| std::array::from_fn(|r| (0..3).map(|k| o[r][k] * v[k]).sum::<f32>() * scale[r] as f32))
                    .collect(),
                faces: b.prepared.visual.faces.clone(),
                // The texture's colours ride along, so the varied object is textured again.
                vertex_attrs: b.prepared.textured.as_ref().and_then(|t| {
                    let a = t.atlas.mesh.vertex_attrs.as_ref()?;
                    let mut c = vec![[0.5, 0.5, 0.5, 0.5, 0.5, 1.0]; b.prepared.visual.vertices.len()];
                    for (&src, attr) in t.atlas.source_vertex.iter().zip(a) {
                        c[src as usize] = *attr;
                    }
                    Some(c)
                }),
            };
            let mut spec = b.prepared.spec.clone();
            spec.pose = PoseSpec::from_similarity(&Similarity32::identity());
            spec.scale = 1.0;
            spec.mesh = PathBuf::from(format!("meshes/{}/visual.ply", safe_name(&spec.name)));
            if let Some(m) = &material {
                // The material's colour, unless a colour is drawn below.
                spec.color_rgba = None;
                spec.physics.material = Some(m.clone());
                spec.physics.density_kg_m3 = None;
                spec.physics.friction = None;
                spec.physics.restitution = None;
                spec.physics.mass_kg = None;
            } else if let Some(m) = spec.physics.mass_kg {
                spec.physics.mass_kg = Some(m * scale[0] * scale[1] * scale[2]);
            }
            if color.is_some() {
                spec.color_rgba = color;
            }
            objs.push(self.build(i, spec, &raw, "scene", scale, None)?);
        }
        let ds = &self.spec.distractors;
        let n = ds.count[0] + (rng.next_u64() % (ds.count[1] - ds.count[0] + 1) as u64) as u32;
        let cats: Vec<Category> = if ds.categories.is_empty() { Category::ALL.to_vec() } else { ds.categories.clone() };
        for k in 0..n as usize {
            let cat = cats[(rng.next_u64() % cats.len() as u64) as usize];
            let obj = recon_synth::objects::Object::random(cat.kind(), rng);
            let f = ds.scale[0] + (ds.scale[1] - ds.scale[0]) * rng.uniform();
            let mut raw = obj.mesh();
            for v in &mut raw.vertices {
                *v = v.map(|x| x * f as f32);
            }
            let name = format!("distractor_{k}");
            let spec = ObjectSpec {
                name: name.clone(),
                category: cat.kind().name().to_string(),
                mesh: PathBuf::from(format!("meshes/{name}/visual.ply")),
                scale: 1.0,
                pose: PoseSpec::from_similarity(&Similarity32::identity()),
                physics: Default::default(),
                color_rgba: None,
            };
            objs.push(self.build(self.bases.len() + k, spec, &raw, "distractor", [f; 3], None)?);
        }
        // The user's assets, drawn after the library's (a spec without assets draws as before).
        if let (Some(lib), Some(a)) = (self.assets, &ds.assets) {
            let m = a.count[0] + (rng.next_u64() % (a.count[1] - a.count[0] + 1) as u64) as u32;
            for k in 0..m as usize {
                let asset = &lib.assets[(rng.next_u64() % lib.assets.len() as u64) as usize];
                let u = |rng: &mut SeededRng, r: [f64; 2]| r[0] + (r[1] - r[0]) * rng.uniform();
                let size = a.size_m.map_or(1.0, |r| u(rng, r) / asset.extent_m);
                let f = size * u(rng, a.scale);
                let raw = Mesh {
                    vertices: asset.mesh.vertices.iter().map(|v| v.map(|x| x * f as f32)).collect(),
                    faces: asset.mesh.faces.clone(),
                    vertex_attrs: None,
                };
                let name = format!("distractor_{}", n as usize + k);
                let mut physics = asset.physics.clone();
                // A given mass is the asset's at its own size: it scales with the volume.
                physics.mass_kg = physics.mass_kg.map(|m| m * f * f * f);
                let spec = ObjectSpec {
                    name: name.clone(),
                    category: asset.category.clone(),
                    mesh: PathBuf::from(format!("meshes/{name}/visual.ply")),
                    scale: 1.0,
                    pose: PoseSpec::from_similarity(&Similarity32::identity()),
                    physics,
                    color_rgba: asset.color_rgba,
                };
                let i = self.bases.len() + n as usize + k;
                objs.push(self.build(i, spec, &raw, "asset", [f; 3], Some(asset.rel.clone()))?);
            }
        }
        let preds = if self.spec.predicates.is_empty() { self.sample_predicates(&objs, rng) } else { self.bind(&objs)? };
        // A variant that no longer fits its support (a grown load, a shrunk
        // top) is undone: the spec was checked on the unvaried shapes.
        for p in preds.iter().filter(|p| p.pred.is_support()) {
            let inside = matches!(p.pred, Predicate::Inside { .. });
            if !place::fits(&objs[p.a].placeable, &objs[p.b].placeable, inside) {
                for k in [p.a, p.b] {
                    objs[k] = self.unvaried(k);
                }
            }
        }
        Ok(Draft { objs, preds })
    }

    /// Scene object `i` as it is in the scene.
    fn unvaried(&self, i: usize) -> VObj {
        let b = &self.bases[i];
        let mut prepared = b.prepared.clone();
        prepared.spec.mesh = PathBuf::from(format!("meshes/{}/visual.ply", safe_name(&prepared.spec.name)));
        prepared.spec.scale = 1.0;
        VObj { prepared, placeable: b.placeable.clone(), source: "scene", scale: [1.0; 3], asset: None }
    }

    /// Annotate and build collision for a resting-frame mesh.
    #[allow(clippy::too_many_arguments)]
    fn build(&self, i: usize, spec: ObjectSpec, raw: &Mesh, source: &'static str, scale: [f64; 3], asset: Option<String>) -> Result<VObj> {
        let what = format!("{} (variant)", spec.name);
        let prepared = prepare_mesh(i, &spec, raw, &what, self.table, self.opts, self.file)?;
        let orient = settle_alone(&prepared, Similarity32::identity().rotation, &self.base.plane, &self.settle)?;
        let placeable = placeable(&spec.name, &prepared.visual, &prepared, orient, true, &what)?;
        Ok(VObj { prepared, placeable, source, scale, asset })
    }

    fn bind(&self, objs: &[VObj]) -> Result<Vec<Bound>> {
        let idx = |n: &str| objs.iter().position(|o| o.prepared.spec.name == n).ok_or_else(|| Error::msg(format!("object {n} vanished")));
        self.spec
            .predicates
            .iter()
            .map(|p| {
                let (a, b) = p.objects();
                Ok(Bound { pred: p.clone(), a: idx(a)?, b: idx(b)? })
            })
            .collect()
    }

    /// Predicates drawn among the scene objects: each object is the subject
    /// of at most one, loads carry nothing and relate to nothing else, and
    /// supports need room (checked on the variant's shapes).
    fn sample_predicates(&self, objs: &[VObj], rng: &mut SeededRng) -> Vec<Bound> {
        let n = self.bases.len();
        let mut out: Vec<Bound> = Vec::new();
        if n < 2 {
            return out;
        }
        for _ in 0..60 {
            if out.len() >= self.spec.sampled_predicates {
                break;
            }
            let a = (rng.next_u64() % n as u64) as usize;
            let b = (rng.next_u64() % n as u64) as usize;
            let kind = rng.next_u64() % 7;
            let (na, nb) = (objs[a].prepared.spec.name.clone(), objs[b].prepared.spec.name.clone());
            let pred = match kind {
                0 => Predicate::OnTop { a: na, b: nb },
                1 => Predicate::Inside { a: na, b: nb },
                2 => Predicate::LeftOf { a: na, b: nb },
                3 => Predicate::RightOf { a: na, b: nb },
                4 => Predicate::InFrontOf { a: na, b: nb },
                5 => Predicate::Behind { a: na, b: nb },
                _ => Predicate::Near { a: na, b: nb, distance_m: ((0.03 + 0.05 * rng.uniform()) * 1e3).round() / 1e3 },
            };
            if a == b || out.iter().any(|p| p.a == a) {
                continue;
            }
            let load = |i: usize| out.iter().any(|p| p.a == i && p.pred.is_support());
            let involved = |i: usize| out.iter().any(|p| p.a == i || p.b == i);
            if load(b) || out.iter().any(|p| spec::contradicts(&p.pred, &pred)) {
                continue;
            }
            if pred.is_support() {
                let (pa, pb) = (&objs[a].placeable, &objs[b].placeable);
                let inside = matches!(pred, Predicate::Inside { .. });
                let carrying = out.iter().any(|p| p.b == b && p.pred.is_support());
                let ok = !involved(a) && !carrying && place::fits(pa, pb, inside) && (inside || pa.profile.flat_base());
                let ok = ok && if inside { pb.profile.has_cavity() } else { true };
                if !ok {
                    continue;
                }
            }
            out.push(Bound { pred, a, b });
        }
        out
    }
}
