//! Random tabletop scenes: a support plane, one target object and 3–10 distractors,
//! cameras looking at the target, random appearance and lighting.
//!
//! World frame: the table top is the plane z = 0, z up, the target stands near the
//! origin. Occlusion of the target is aimed, not left to chance: each scene draws a goal
//! occlusion for its first view (a RecGen occlusion bin at random, uniform inside it; at
//! most `max_occlusion`) and places one or two
//! "front" distractors between that camera and the target, keeping the trial placement
//! (low-resolution render) whose occlusion is closest to the goal. The other distractors
//! stand away from the camera–target line. Further views circle the target at random.

use crate::objects::{Kind, Object};

use recon_core::dataset::frame::Intrinsics;
use recon_core::math::{axis_angle, normalize, Similarity};
use recon_core::mesh::primitives::box_mesh;
use recon_core::mesh::Mesh;
use recon_core::render::{render, Camera, Instance, Light, Material, Pattern, RenderMesh, RenderOptions, Rendered};
use recon_core::rng::SeededRng;
use recon_core::Result;
use std::f64::consts::{PI, TAU};

#[derive(Clone, Debug)]
/// Settings of scene generation.
pub struct SceneConfig {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Camera views per scene.
    pub views: usize,
    /// Distractor count range (inclusive).
    pub min_distractors: usize,
    /// Most distractors (inclusive).
    pub max_distractors: usize,
    /// Upper end of the target occlusion goal of the first view.
    pub max_occlusion: f64,
}

impl Default for SceneConfig {
    fn default() -> Self {
        SceneConfig { width: 640, height: 480, views: 1, min_distractors: 3, max_distractors: 10, max_occlusion: 0.7 }
    }
}

/// An object standing on the table.
#[derive(Clone, Debug)]
pub struct Placed {
    pub object: Object,
    /// Object → world.
    pub pose: Similarity,
    pub material: Material,
    pub target: bool,
}

#[derive(Clone, Debug)]
pub struct View {
    pub camera: Camera,
    pub light: Light,
}

#[derive(Clone, Debug)]
/// A generated scene: objects on a table, views, and the occlusion aimed at.
pub struct Scene {
    /// Seed the scene was generated from.
    pub seed: u64,
    /// Index 0 is the target.
    pub objects: Vec<Placed>,
    /// The table: a thin slab whose top face is z = 0.
    pub support: Mesh,
    /// Support slab → world.
    pub support_pose: Similarity,
    /// Appearance of the table.
    pub support_material: Material,
    /// Camera and light of each view.
    pub views: Vec<View>,
    /// Target occlusion aimed at in view 0, and what the low-resolution trial achieved.
    pub occlusion_goal: f64,
    /// Target occlusion the low-resolution trial achieved.
    pub occlusion_trial: f64,
}

/// One ray-casting unit of a scene: the support, a whole object, or (parts mode) a part.
pub struct Unit {
    pub mesh: RenderMesh,
    /// Mesh → world.
    pub pose: Similarity,
    pub material: Material,
    /// `None` for the support plane.
    pub object: Option<usize>,
    /// Part index within the object in parts mode.
    pub part: Option<usize>,
}

/// Half side and thickness of the table slab (metres).
pub const SUPPORT_HALF: f64 = 2.0;
pub const SUPPORT_THICK: f64 = 0.02;

fn yaw(a: f64) -> [[f64; 3]; 3] {
    axis_angle([0.0, 0.0, 1.0], a)
}

/// Radius of the object's footprint about its z axis (yaw-invariant).
fn footprint(o: &Object) -> f64 {
    o.mesh().vertices.iter().map(|v| ((v[0] * v[0] + v[1] * v[1]) as f64).sqrt()).fold(0.0, f64::max)
}

/// Pose standing the object on the table at (x, y) with a yaw.
fn stand(o: &Object, x: f64, y: f64, a: f64) -> Similarity {
    let (lo, _) = o.bounds();
    Similarity::rigid(yaw(a), [x, y, -lo[2]])
}

fn hsv(h: f64, s: f64, v: f64) -> [f32; 3] {
    let h6 = (h.rem_euclid(1.0)) * 6.0;
    let c = v * s;
    let x = c * (1.0 - (h6 % 2.0 - 1.0).abs());
    let (r, g, b) = match h6 as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [(r + m) as f32, (g + m) as f32, (b + m) as f32]
}

fn random_material(rng: &mut SeededRng) -> Material {
    let h = rng.uniform();
    let s = 0.25 + 0.7 * rng.uniform();
    // Dark to bright, so intensity-dependent sensor effects have something to act on.
    let v = 0.1 + 0.85 * rng.uniform();
    let color = hsv(h, s, v);
    let color2 = hsv(h + 0.3 + 0.4 * rng.uniform(), s, (v + 0.3 + 0.4 * rng.uniform()) % 1.0);
    let pick = rng.uniform();
    let pattern = if pick < 0.5 {
        Pattern::Solid
    } else if pick < 0.75 {
        Pattern::Checker { cell: 0.01 + 0.02 * rng.uniform() }
    } else {
        Pattern::Stripes { axis: (rng.next_u64() % 3) as usize, period: 0.01 + 0.03 * rng.uniform() }
    };
    Material { color, color2, pattern }
}

fn random_kind(rng: &mut SeededRng) -> Kind {
    Kind::ALL[(rng.next_u64() % Kind::ALL.len() as u64) as usize]
}

/// A camera on a sphere around `target` (distance, elevation, azimuth), aimed at the
/// target with a little jitter so the target is not always at the image centre.
fn view_camera(rng: &mut SeededRng, cfg: &SceneConfig, k: Intrinsics, target: [f64; 3], azimuth: f64) -> Camera {
    let dist = 0.55 + 0.55 * rng.uniform();
    let elev = (20.0 + 35.0 * rng.uniform()).to_radians();
    let eye = [target[0] + dist * elev.cos() * azimuth.cos(), target[1] + dist * elev.cos() * azimuth.sin(), target[2] + dist * elev.sin()];
    let aim =
        [target[0] + 0.04 * (rng.uniform() - 0.5), target[1] + 0.04 * (rng.uniform() - 0.5), target[2] + 0.03 * (rng.uniform() - 0.5)];
    Camera { width: cfg.width, height: cfg.height, k, world_to_cam: Camera::look_at(eye, aim, [0.0, 0.0, 1.0]) }
}

fn random_light(rng: &mut SeededRng, cam: &Camera) -> Light {
    let el = (30.0 + 50.0 * rng.uniform()).to_radians();
    let az = TAU * rng.uniform();
    let d_world = [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()];
    let r = cam.world_to_cam.rotation;
    let d = [0, 1, 2].map(|i| (0..3).map(|j| r[i][j] * d_world[j]).sum::<f64>());
    Light { direction_cam: normalize(d), ambient: (0.2 + 0.2 * rng.uniform()) as f32, diffuse: (0.6 + 0.3 * rng.uniform()) as f32 }
}

/// Target occlusion (1 − visible / amodal pixels) of objects `target` among `units`.
fn target_occlusion(r: &Rendered, target: &[usize]) -> f64 {
    let all: usize = (0..r.depth.len()).filter(|&p| target.iter().any(|&t| r.amodal[t][p])).count();
    if all == 0 {
        return 1.0;
    }
    let vis = r.index.iter().filter(|&&i| i >= 0 && target.contains(&(i as usize))).count();
    1.0 - vis as f64 / all as f64
}

impl Scene {
    /// A random scene, a pure function of `seed` and `cfg`.
    pub fn generate(seed: u64, cfg: &SceneConfig) -> Result<Scene> {
        let mut rng = SeededRng::new(seed);
        // Intrinsics like a 640×480 consumer RGB-D camera, scaled to the image size.
        let sx = cfg.width as f64 / 640.0;
        let sy = cfg.height as f64 / 480.0;
        let f = 600.0 * (0.97 + 0.06 * rng.uniform());
        let k = Intrinsics {
            fx: f * sx,
            fy: f * sy,
            cx: (cfg.width as f64 - 1.0) / 2.0 + 6.0 * sx * (rng.uniform() - 0.5),
            cy: (cfg.height as f64 - 1.0) / 2.0 + 6.0 * sy * (rng.uniform() - 0.5),
        };

        let target_obj = Object::random(random_kind(&mut rng), &mut rng);
        let target_pose = stand(&target_obj, 0.0, 0.0, TAU * rng.uniform());
        let target_centre = target_pose.translation;
        let r_target = footprint(&target_obj);
        let mut objects = vec![Placed { object: target_obj, pose: target_pose, material: random_material(&mut rng), target: true }];

        let az0 = TAU * rng.uniform();
        let cam0 = view_camera(&mut rng, cfg, k, target_centre, az0);
        let n_distract = cfg.min_distractors + (rng.next_u64() % (cfg.max_distractors - cfg.min_distractors + 1) as u64) as usize;
        // Goal: one of the RecGen occlusion bins (0–3, 3–20, 20–40, 40–max %) with equal
        // probability, uniform inside it, so every bin gets scenes.
        let edges = [0.0, 0.03, 0.2, 0.4, cfg.max_occlusion.max(0.4)];
        let bin = (rng.next_u64() % 4) as usize;
        let goal = (edges[bin] + (edges[bin + 1] - edges[bin]) * rng.uniform()).min(cfg.max_occlusion);
        let n_front = if goal < 0.03 {
            0
        } else if goal > 0.35 {
            2
        } else {
            1
        }
        .min(n_distract);

        // Ground direction from the target towards camera 0, and its left normal.
        let eye = cam0.eye();
        let g = normalize([eye[0] - target_centre[0], eye[1] - target_centre[1], 0.0]);
        let side = [-g[1], g[0], 0.0];
        let ground_dist = ((eye[0] - target_centre[0]).powi(2) + (eye[1] - target_centre[1]).powi(2)).sqrt();

        // A front distractor is the tallest of three draws: low objects in front of the
        // target hide little of it from an elevated camera.
        let mut distractors: Vec<(Object, f64, Material)> = (0..n_distract)
            .map(|i| {
                let draws = if i < n_front { 3 } else { 1 };
                let o = (0..draws)
                    .map(|_| Object::random(random_kind(&mut rng), &mut rng))
                    .max_by(|a, b| {
                        let (ha, hb) = (a.bounds().1[2], b.bounds().1[2]);
                        ha.partial_cmp(&hb).unwrap_or(std::cmp::Ordering::Equal)
                    })
                    .expect("at least one draw");
                let r = footprint(&o);
                (o, r, random_material(&mut rng))
            })
            .collect();

        // Front distractors: trial placements scored by a low-resolution render.
        let lowres = SceneConfig { width: (cfg.width / 4).max(16), height: (cfg.height / 4).max(12), ..cfg.clone() };
        let lk = Intrinsics {
            fx: k.fx * lowres.width as f64 / cfg.width as f64,
            fy: k.fy * lowres.height as f64 / cfg.height as f64,
            cx: (k.cx + 0.5) * lowres.width as f64 / cfg.width as f64 - 0.5,
            cy: (k.cy + 0.5) * lowres.height as f64 / cfg.height as f64 - 0.5,
        };
        let lcam = Camera { width: lowres.width, height: lowres.height, k: lk, world_to_cam: cam0.world_to_cam };
        let target_mesh = RenderMesh::from_mesh(&objects[0].object.mesh(), "target")?;
        let front_meshes: Vec<RenderMesh> =
            distractors[..n_front].iter().map(|(o, _, _)| RenderMesh::from_mesh(&o.mesh(), "distractor")).collect::<Result<_>>()?;
        let mut best: Option<(f64, Vec<Similarity>)> = None;
        let mut achieved = 0.0;
        if n_front > 0 {
            for _trial in 0..32 {
                let mut poses: Vec<Similarity> = Vec::new();
                let mut spots: Vec<([f64; 2], f64)> = vec![([target_centre[0], target_centre[1]], r_target)];
                for (o, r, _) in &distractors[..n_front] {
                    let mut placed = None;
                    for _ in 0..20 {
                        // Close in front of the target; the lateral offset sets how much it covers.
                        let along = r_target + r + 0.006 + (0.3 * ground_dist - r_target - r).clamp(0.0, 0.08) * rng.uniform();
                        let lateral = (r_target + r) * (2.0 * rng.uniform() - 1.0) * 1.2;
                        let p = [target_centre[0] + along * g[0] + lateral * side[0], target_centre[1] + along * g[1] + lateral * side[1]];
                        if spots.iter().all(|(q, rq)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt() > r + rq + 0.005) {
                            placed = Some((p, *r));
                            break;
                        }
                    }
                    let Some((p, r)) = placed else { break };
                    spots.push((p, r));
                    poses.push(stand(o, p[0], p[1], TAU * rng.uniform()));
                }
                if poses.len() < n_front {
                    continue;
                }
                let mut insts = vec![Instance::new(&target_mesh, objects[0].pose, 0)];
                for (m, p) in front_meshes.iter().zip(&poses) {
                    insts.push(Instance::new(m, *p, 1));
                }
                let r = render(&insts, &lcam, &RenderOptions::default())?;
                let occ = target_occlusion(&r, &[0]);
                let err = (occ - goal).abs();
                if best.as_ref().is_none_or(|b| err < b.0) {
                    best = Some((err, poses));
                    achieved = occ;
                }
                if err < 0.02 {
                    break;
                }
            }
        }
        let front_poses = best.map(|b| b.1).unwrap_or_default();
        let mut spots: Vec<([f64; 2], f64)> = vec![([target_centre[0], target_centre[1]], r_target)];
        for (i, (o, r, m)) in distractors.drain(..).enumerate() {
            let pose = if i < front_poses.len() {
                front_poses[i]
            } else {
                // Away from camera 0's line of sight: at least 60° off the camera direction.
                let mut pose = None;
                for _ in 0..60 {
                    let ang = (PI / 3.0 + (2.0 * PI - 2.0 * PI / 3.0) * rng.uniform()) + g[1].atan2(g[0]);
                    let d = r_target + r + 0.02 + 0.35 * rng.uniform();
                    let p = [target_centre[0] + d * ang.cos(), target_centre[1] + d * ang.sin()];
                    if spots.iter().all(|(q, rq)| ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2)).sqrt() > r + rq + 0.005) {
                        pose = Some(stand(&o, p[0], p[1], TAU * rng.uniform()));
                        break;
                    }
                }
                match pose {
                    Some(p) => p,
                    // Crowded: drop it rather than interpenetrate.
                    None => continue,
                }
            };
            spots.push(([pose.translation[0], pose.translation[1]], r));
            objects.push(Placed { object: o, pose, material: m, target: false });
        }

        let mut views = vec![View { light: random_light(&mut rng, &cam0), camera: cam0 }];
        for _ in 1..cfg.views {
            let az = TAU * rng.uniform();
            let cam = view_camera(&mut rng, cfg, k, target_centre, az);
            views.push(View { light: random_light(&mut rng, &cam), camera: cam });
        }
        let support_material = {
            let h = rng.uniform();
            let color = hsv(h, 0.1 + 0.3 * rng.uniform(), 0.35 + 0.5 * rng.uniform());
            let color2 = hsv(h, 0.1 + 0.3 * rng.uniform(), 0.35 + 0.5 * rng.uniform());
            let pattern = if rng.uniform() < 0.5 {
                Pattern::Checker { cell: 0.05 + 0.1 * rng.uniform() }
            } else {
                Pattern::Stripes { axis: (rng.next_u64() % 2) as usize, period: 0.04 + 0.1 * rng.uniform() }
            };
            Material { color, color2, pattern }
        };
        Ok(Scene {
            seed,
            objects,
            support: box_mesh(2.0 * SUPPORT_HALF, 2.0 * SUPPORT_HALF, SUPPORT_THICK),
            support_pose: Similarity::rigid(Similarity::identity().rotation, [0.0, 0.0, -SUPPORT_THICK / 2.0]),
            support_material,
            views,
            occlusion_goal: goal,
            occlusion_trial: achieved,
        })
    }

    /// Ray-casting units: the support first, then every object (or every part of every
    /// object in parts mode), in object order.
    pub fn units(&self, parts: bool) -> Result<Vec<Unit>> {
        let mut out = vec![Unit {
            mesh: RenderMesh::from_mesh(&self.support, "support")?,
            pose: self.support_pose,
            material: self.support_material,
            object: None,
            part: None,
        }];
        for (i, p) in self.objects.iter().enumerate() {
            if parts {
                for (j, part) in p.object.parts.iter().enumerate() {
                    out.push(Unit {
                        mesh: RenderMesh::from_mesh(&part.mesh, part.name)?,
                        pose: p.pose.compose(&part.pose),
                        material: p.material,
                        object: Some(i),
                        part: Some(j),
                    });
                }
            } else {
                out.push(Unit {
                    mesh: RenderMesh::from_mesh(&p.object.mesh(), p.object.kind.name())?,
                    pose: p.pose,
                    material: p.material,
                    object: Some(i),
                    part: None,
                });
            }
        }
        Ok(out)
    }

    /// Render view `v` of the units; `ids[i]` is the id reported for unit i.
    pub fn render_view(&self, units: &[Unit], ids: &[i64], v: usize) -> Result<Rendered> {
        let view = &self.views[v];
        let insts: Vec<Instance> =
            units.iter().zip(ids).map(|(u, &id)| Instance { mesh: &u.mesh, pose: u.pose, id, material: u.material }).collect();
        render(&insts, &view.camera, &RenderOptions { light: view.light, ..Default::default() })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small() -> SceneConfig {
        SceneConfig { width: 96, height: 72, views: 2, ..Default::default() }
    }

    #[test]
    fn scenes_are_deterministic_and_objects_do_not_overlap() {
        for seed in 0..6 {
            let a = Scene::generate(seed, &small()).unwrap();
            let b = Scene::generate(seed, &small()).unwrap();
            assert_eq!(a.objects.len(), b.objects.len());
            assert!(a.objects.iter().zip(&b.objects).all(|(x, y)| x.pose == y.pose && x.object.dims == y.object.dims));
            assert!(a.objects.len() >= 2 && a.objects.len() <= 11, "{}", a.objects.len());
            assert!(a.objects[0].target && a.objects[1..].iter().all(|o| !o.target));
            // Every object stands on the table and footprints are disjoint.
            for (i, p) in a.objects.iter().enumerate() {
                let m = p.object.mesh();
                let zmin = m.vertices.iter().map(|v| p.pose.apply(&v.map(|x| x as f64))[2]).fold(f64::INFINITY, f64::min);
                assert!(zmin.abs() < 1e-6, "object {i} bottom at {zmin}");
                for q in &a.objects[i + 1..] {
                    let d = ((p.pose.translation[0] - q.pose.translation[0]).powi(2)
                        + (p.pose.translation[1] - q.pose.translation[1]).powi(2))
                    .sqrt();
                    assert!(d > footprint(&p.object) + footprint(&q.object), "overlap in scene {seed}");
                }
            }
            assert_eq!(a.views.len(), 2);
        }
    }

    #[test]
    fn target_is_in_view_and_occlusion_follows_the_goal() {
        let cfg = SceneConfig { width: 160, height: 120, views: 1, ..Default::default() };
        let mut pairs = Vec::new();
        for seed in 0..16 {
            let s = Scene::generate(100 + seed, &cfg).unwrap();
            let units = s.units(false).unwrap();
            let ids: Vec<i64> = (0..units.len() as i64).collect();
            let r = s.render_view(&units, &ids, 0).unwrap();
            let amodal = r.amodal[1].iter().filter(|&&x| x).count();
            assert!(amodal > 30, "scene {seed}: target covers {amodal} px");
            let occ = target_occlusion(&r, &[1]);
            pairs.push((s.occlusion_goal, occ));
        }
        // Aimed, not random: the achieved occlusion tracks the goal.
        let close = pairs.iter().filter(|(g, o)| (g - o).abs() < 0.15).count();
        assert!(close >= 12, "{pairs:?}");
        assert!(pairs.iter().any(|p| p.1 > 0.3) && pairs.iter().any(|p| p.1 < 0.05), "{pairs:?}");
    }
}
