//! Settling with rapier3d: every object starts at its reconstructed pose,
//! overlapping objects are pushed apart at a bounded corrective velocity
//! (rapier's `max_corrective_velocity`, so deep overlaps resolve gently
//! instead of exploding), and the simulation runs until every object is at
//! rest on the plane z = 0 (gravity −z) or the time limit is reached.
//!
//! Single-threaded (rapier without its `parallel` feature): the same input
//! gives the same poses bit for bit on a given build. Bit-identity across
//! platforms is not claimed (that needs rapier's `enhanced-determinism`,
//! which would also force libm/scalar math on the synth renderer's parry).

use crate::collision::{Part, Primitive};
use rapier3d::prelude::*;
use recon_core::math::{matrix_to_quat, quat_to_matrix, Similarity32};
use recon_core::{Error, Result};
use serde::Serialize;

#[derive(Debug, Clone, Serialize)]
pub struct SettleOptions {
    /// Simulated time limit (s).
    pub max_time_s: f64,
    pub dt_s: f64,
    pub solver_iterations: usize,
    /// Bound on the speed at which overlaps are pushed apart (m/s).
    pub max_corrective_velocity_m_s: f64,
    /// Quasi-static depenetration before the dynamic settle: at most this long
    /// (simulated s), until no overlap is deeper than `depenetrated_m`.
    pub max_depenetration_s: f64,
    pub depenetrated_m: f64,
    /// Angular velocity damping (1/s), standing in for rolling resistance, which
    /// rapier does not model: without it a sphere or can nudged by the
    /// depenetration rolls on a flat plane forever.
    pub angular_damping: f64,
    /// At rest: every body slower than these for `rest_duration_s`.
    pub rest_linear_m_s: f64,
    pub rest_angular_rad_s: f64,
    pub rest_duration_s: f64,
    /// Objects that moved more than this are flagged.
    pub flag_displacement_m: f64,
    pub flag_rotation_deg: f64,
}

impl Default for SettleOptions {
    fn default() -> Self {
        Self {
            max_time_s: 5.0,
            dt_s: 1.0 / 240.0,
            solver_iterations: 8,
            max_corrective_velocity_m_s: 0.05,
            max_depenetration_s: 1.0,
            depenetrated_m: 0.0003,
            angular_damping: 1.0,
            rest_linear_m_s: 0.0005,
            rest_angular_rad_s: 0.01,
            rest_duration_s: 0.25,
            flag_displacement_m: 0.01,
            flag_rotation_deg: 10.0,
        }
    }
}

impl SettleOptions {
    pub fn validate(&self) -> Result<()> {
        let pos = |v: f64, name: &str| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(Error::input("settle options", format!("{name} must be positive, got {v}")))
            }
        };
        pos(self.max_time_s, "settle time")?;
        pos(self.dt_s, "time step")?;
        pos(self.max_corrective_velocity_m_s, "max corrective velocity")?;
        pos(self.max_depenetration_s, "depenetration time")?;
        pos(self.depenetrated_m, "depenetration tolerance")?;
        if !(self.angular_damping.is_finite() && self.angular_damping >= 0.0) {
            return Err(Error::input("settle options", format!("angular damping must be ≥ 0, got {}", self.angular_damping)));
        }
        pos(self.flag_displacement_m, "flag displacement")?;
        pos(self.flag_rotation_deg, "flag rotation")?;
        if self.solver_iterations == 0 || self.dt_s > 0.05 || self.max_time_s > 600.0 {
            return Err(Error::input("settle options", "need solver iterations ≥ 1, time step ≤ 0.05 s, settle time ≤ 600 s"));
        }
        Ok(())
    }
}

/// One rigid body: frame origin at its centre of mass.
#[derive(Debug, Clone)]
pub struct Body {
    /// Body name (for reports).
    pub name: String,
    /// Body frame → world at the start (scale 1).
    pub pose: Similarity32,
    /// Mass in kilograms.
    pub mass_kg: f64,
    /// About the body origin, body axes.
    pub inertia: [[f64; 3]; 3],
    /// Coulomb friction coefficient.
    pub friction: f64,
    /// Restitution coefficient.
    pub restitution: f64,
    /// Collision parts in the body frame.
    pub parts: Vec<Part>,
}

#[derive(Debug, Clone, Serialize)]
pub struct BodySettle {
    pub name: String,
    /// Settled body pose (rotation rows, translation in metres).
    pub rotation: [[f32; 3]; 3],
    pub translation_m: [f32; 3],
    /// Deepest overlap with the plane or another object at the start pose.
    pub start_penetration_m: f64,
    /// What that overlap was with ("plane" or an object name).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub start_penetration_with: Option<String>,
    /// Deepest overlap left after settling.
    pub end_penetration_m: f64,
    pub displacement_m: f64,
    pub rotation_deg: f64,
    pub final_speed_m_s: f64,
    /// Bodies (or "plane") in contact at the end.
    pub touching: Vec<String>,
    pub flagged: bool,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub flag_reasons: Vec<String>,
    /// Bound on how far any point of the body moved over the last
    /// `rest_duration_s` of the run (translation + rotation × reach), for
    /// callers that need a position-based rest test. Not in reports.
    #[serde(skip)]
    pub rest_motion_m: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct SettleResult {
    /// Simulated time of the whole settle, depenetration included.
    pub simulated_s: f64,
    /// Simulated time of the quasi-static depenetration phase (0 without overlaps).
    pub depenetration_s: f64,
    pub steps: usize,
    pub at_rest: bool,
    pub bodies: Vec<BodySettle>,
}

pub const PLANE: &str = "plane";

// Collision groups. parry builds a contact manifold from at most four
// vertices of a convex polyhedron's face (the first four of its loop), so a
// hull resting on a large polygon (a can's base, a flat-bottomed VHACD
// part) is held on a small arc of its rim and tips over. Against the plane,
// hull parts therefore collide through their surface triangles (a triangle
// mesh copy, `FOOT`), which gives the whole support polygon; between
// objects they collide as solid convex shapes (`OBJECT`) so overlaps are
// pushed apart. Primitives have exact plane contacts.
const OBJECT: Group = Group::GROUP_1;
const FOOT: Group = Group::GROUP_2;
const GROUND: Group = Group::GROUP_3;

fn groups(member: Group, filter: Group) -> InteractionGroups {
    InteractionGroups::new(member, filter, InteractionTestMode::And)
}

fn to_pose(s: &Similarity32) -> Pose {
    let q = matrix_to_quat(&s.rotation);
    Pose::from_parts(
        Vector::new(s.translation[0], s.translation[1], s.translation[2]),
        Rotation::from_xyzw(q[1], q[2], q[3], q[0]).normalize(),
    )
}

fn from_pose(p: &Pose) -> Similarity32 {
    let q = p.rotation;
    Similarity32 {
        rotation: quat_to_matrix([q.w, q.x, q.y, q.z]),
        translation: [p.translation.x, p.translation.y, p.translation.z],
        scale: 1.0,
    }
}

fn mat_pose(r: &[[f32; 3]; 3], t: [f32; 3]) -> Pose {
    to_pose(&Similarity32 { rotation: *r, translation: t, scale: 1.0 })
}

/// A part's shape and its pose in the body frame.
fn part_shape(p: &Part) -> Option<(Pose, SharedShape)> {
    Some(match p {
        Part::Hull(m) => {
            let pts: Vec<Vector> = m.vertices.iter().map(|v| Vector::new(v[0], v[1], v[2])).collect();
            (Pose::IDENTITY, SharedShape::convex_hull(&pts)?)
        }
        Part::Primitive(Primitive::Box { center, rotation, half_extents: h }) => {
            (mat_pose(rotation, *center), SharedShape::cuboid(h[0], h[1], h[2]))
        }
        Part::Primitive(Primitive::Cylinder { center, rotation, radius, half_height }) => {
            // rapier's cylinder axis is y; ours is the local z: rotate y onto z.
            let y_to_z = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]];
            let r = recon_core::math::matmul(rotation, &y_to_z);
            (mat_pose(&r, *center), SharedShape::cylinder(*half_height, *radius))
        }
        Part::Primitive(Primitive::Sphere { center, radius }) => {
            (Pose::from_translation(Vector::new(center[0], center[1], center[2])), SharedShape::ball(*radius))
        }
    })
}

fn part_collider(p: &Part) -> Option<ColliderBuilder> {
    let (pose, shape) = part_shape(p)?;
    Some(ColliderBuilder::new(shape).position(pose))
}

/// A body's collision parts as parry shapes with their poses in the body frame.
pub fn part_shapes(b: &Body) -> Result<Vec<(Pose, SharedShape)>> {
    b.parts.iter().map(|p| part_shape(p).ok_or_else(|| Error::msg(format!("{}: degenerate collision part", b.name)))).collect()
}

/// Smallest distance between two sets of posed shapes (negative: the deepest overlap).
pub fn shapes_distance(a: &[(Pose, SharedShape)], pose_a: &Similarity32, b: &[(Pose, SharedShape)], pose_b: &Similarity32) -> Result<f64> {
    let (wa, wb) = (to_pose(pose_a), to_pose(pose_b));
    let mut best = f64::INFINITY;
    for (la, ga) in a {
        for (lb, gb) in b {
            let (pa, pb) = (wa * *la, wb * *lb);
            let d = match parry3d::query::contact(&pa, &**ga, &pb, &**gb, 0.0) {
                Ok(Some(c)) => c.dist as f64,
                _ => {
                    parry3d::query::distance(&pa, &**ga, &pb, &**gb).map_err(|e| Error::msg(format!("distance query: {e:?}")))?.distance
                        as f64
                }
            };
            best = best.min(d);
        }
    }
    Ok(best)
}

/// Smallest distance between two bodies' collision geometry at their
/// poses (negative: the deepest overlap between two of their parts).
pub fn body_distance(a: &Body, b: &Body) -> Result<f64> {
    let shapes = |x: &Body| -> Result<Vec<(Pose, SharedShape)>> {
        let world = to_pose(&x.pose);
        x.parts
            .iter()
            .map(|p| part_shape(p).map(|(l, s)| (world * l, s)).ok_or_else(|| Error::msg(format!("{}: degenerate collision part", x.name))))
            .collect()
    };
    let (sa, sb) = (shapes(a)?, shapes(b)?);
    let mut best = f64::INFINITY;
    for (pa, ga) in &sa {
        for (pb, gb) in &sb {
            let d = match parry3d::query::contact(pa, &**ga, pb, &**gb, 0.0) {
                Ok(Some(c)) => c.dist as f64,
                _ => {
                    parry3d::query::distance(pa, &**ga, pb, &**gb).map_err(|e| Error::msg(format!("distance query: {e:?}")))?.distance
                        as f64
                }
            };
            best = best.min(d);
        }
    }
    Ok(best)
}

/// Per body: the deepest overlap of its collision geometry with the plane
/// (lowest point below z = 0) or with another body (solid convex parts).
fn penetrations(
    world: &PhysicsWorld,
    owner: &std::collections::HashMap<ColliderHandle, String>,
    bodies: &[Body],
    handles: &[RigidBodyHandle],
) -> Vec<(f64, Option<String>)> {
    use parry3d::bounding_volume::BoundingVolume;
    let mut out: Vec<(f64, Option<String>)> = bodies
        .iter()
        .zip(handles)
        .map(|(b, h)| {
            let pose = from_pose(world.bodies[*h].position());
            let low =
                b.parts.iter().flat_map(|p| p.surface_mesh().vertices).map(|v| pose.apply(&v)[2] as f64).fold(f64::INFINITY, f64::min);
            if low < 0.0 {
                (-low, Some(PLANE.to_string()))
            } else {
                (0.0, None)
            }
        })
        .collect();
    let index: std::collections::HashMap<RigidBodyHandle, usize> = handles.iter().enumerate().map(|(i, h)| (*h, i)).collect();
    let cols: Vec<(ColliderHandle, &Collider, usize)> = world
        .colliders
        .iter()
        .filter(|(_, c)| c.collision_groups().memberships.contains(OBJECT))
        .filter_map(|(h, c)| Some((h, c, *index.get(&c.parent()?)?)))
        .collect();
    for (a, (ha, ca, ba)) in cols.iter().enumerate() {
        for (hb, cb, bb) in &cols[a + 1..] {
            if ba == bb || !ca.compute_aabb().intersects(&cb.compute_aabb()) {
                continue;
            }
            let Ok(Some(c)) = parry3d::query::contact(ca.position(), ca.shape(), cb.position(), cb.shape(), 0.0) else { continue };
            let depth = -(c.dist as f64);
            for (me, other) in [(ba, hb), (bb, ha)] {
                if depth > out[*me].0 {
                    out[*me] = (depth, owner.get(other).cloned());
                }
            }
        }
    }
    out
}

/// Rotation angle (degrees) between two rotation matrices.
pub fn rotation_angle_deg(a: &[[f32; 3]; 3], b: &[[f32; 3]; 3]) -> f64 {
    // trace(Aᵀ B) = 1 + 2 cos θ
    let tr: f64 = (0..3).map(|i| (0..3).map(|k| a[k][i] as f64 * b[k][i] as f64).sum::<f64>()).sum();
    ((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Run the settling simulation; `plane_friction`/`plane_restitution` for z = 0.
pub fn settle(bodies: &[Body], plane_friction: f64, plane_restitution: f64, opts: &SettleOptions) -> Result<SettleResult> {
    opts.validate()?;
    let (mut world, handles, owner) = build_world(bodies, plane_friction, plane_restitution, opts)?;
    let start_pen = penetrations(&world, &owner, bodies, &handles);
    let depen_steps =
        if start_pen.iter().any(|(p, _)| *p > opts.depenetrated_m) { depenetrate(&mut world, &owner, bodies, &handles, opts) } else { 0 };
    let run = run_to_rest(&mut world, &handles, depen_steps, opts);
    // Collider poses follow their bodies at the next step; refresh them so the
    // end-state overlap query sees the settled poses.
    world.integration_parameters.dt = 0.0;
    world.step();
    let end_pen = penetrations(&world, &owner, bodies, &handles);
    let mut out = Vec::new();
    for (((b, h), start), (end_pen, _)) in bodies.iter().zip(&handles).zip(start_pen).zip(end_pen) {
        let k = out.len();
        out.push(body_outcome(&world, &owner, b, *h, k, start, end_pen, &run, opts));
    }
    let steps = run.steps;
    Ok(SettleResult {
        simulated_s: steps as f64 * opts.dt_s,
        depenetration_s: depen_steps as f64 * opts.dt_s,
        steps,
        at_rest: run.at_rest,
        bodies: out,
    })
}

/// Collider → name of the body owning it (`PLANE` for the ground).
type Owners = std::collections::HashMap<ColliderHandle, String>;

/// The world with its solver settings, the ground and every body with its
/// colliders; body handles in input order.
fn build_world(
    bodies: &[Body],
    plane_friction: f64,
    plane_restitution: f64,
    opts: &SettleOptions,
) -> Result<(PhysicsWorld, Vec<RigidBodyHandle>, Owners)> {
    let mut world = PhysicsWorld::new();
    world.gravity = Vector::new(0.0, 0.0, -9.81);
    let ip = &mut world.integration_parameters;
    ip.dt = opts.dt_s as f32;
    ip.num_solver_iterations = opts.solver_iterations;
    // Tabletop objects are centimetres: tolerances scaled to decimetres.
    ip.length_unit = 0.1;
    ip.normalized_max_corrective_velocity = (opts.max_corrective_velocity_m_s / 0.1) as f32;
    // Recycled contacts may be stale by several millimetres; resting heights must be exact.
    ip.contact_recycling = false;
    // Contact slop 0.1 mm (0.001 × length_unit): resting overlaps stay well under a millimetre.
    ip.normalized_allowed_linear_error = 0.001;
    // Friction also in the position-correction pass: otherwise floor friction
    // in the relax pass undoes the push-apart and leaves ~0.5 mm overlaps
    // between resting neighbours. (Rapier warns this destabilises tall
    // stacks; tabletop scenes are one layer.)
    ip.friction_in_bias_pass = true;
    let ground = world.insert_collider(
        ColliderBuilder::new(SharedShape::halfspace(Vector::Z))
            .friction(plane_friction as f32)
            .restitution(plane_restitution as f32)
            .collision_groups(groups(GROUND, FOOT.union(OBJECT))),
        None,
    );
    let mut handles = Vec::new();
    let mut owner = Owners::new();
    owner.insert(ground, PLANE.to_string());
    for b in bodies {
        handles.push(insert_body(&mut world, &mut owner, b, opts)?);
    }
    Ok((world, handles, owner))
}

/// One dynamic body with its mass properties and its parts' colliders.
fn insert_body(world: &mut PhysicsWorld, owner: &mut Owners, b: &Body, opts: &SettleOptions) -> Result<RigidBodyHandle> {
    let i = b.inertia.map(|r| r.map(|x| x as f32));
    let inertia =
        parry3d::math::Mat3::from_cols_array_2d(&[[i[0][0], i[1][0], i[2][0]], [i[0][1], i[1][1], i[2][1]], [i[0][2], i[1][2], i[2][2]]]);
    let mp = MassProperties::with_inertia_matrix(Vector::ZERO, b.mass_kg as f32, inertia);
    let h = world.insert_body(
        RigidBodyBuilder::dynamic()
            .pose(to_pose(&b.pose))
            .additional_mass_properties(mp)
            .angular_damping(opts.angular_damping as f32)
            .can_sleep(false),
    );
    for p in &b.parts {
        let degenerate = || Error::msg(format!("{}: a collision part is degenerate (no convex hull)", b.name));
        let mut builders = vec![];
        match p {
            Part::Hull(m) => {
                builders.push(part_collider(p).ok_or_else(degenerate)?.collision_groups(groups(OBJECT, OBJECT)));
                let v: Vec<Vector> = m.vertices.iter().map(|v| Vector::new(v[0], v[1], v[2])).collect();
                let foot = ColliderBuilder::trimesh(v, m.faces.clone()).map_err(|_| degenerate())?;
                builders.push(foot.collision_groups(groups(FOOT, GROUND)));
            }
            Part::Primitive(_) => {
                builders.push(part_collider(p).ok_or_else(degenerate)?.collision_groups(groups(OBJECT, OBJECT.union(GROUND))))
            }
        }
        for c in builders {
            let ch = world.insert_collider(c.density(0.0).friction(b.friction as f32).restitution(b.restitution as f32), Some(h));
            owner.insert(ch, b.name.clone());
        }
    }
    Ok(h)
}

/// Depenetration: overlaps are pushed apart at the bounded corrective speed
/// while every velocity is cleared after each step, so the push moves objects
/// without giving them momentum (a sphere pushed out of the table would
/// otherwise keep rolling: nothing on a flat plane stops it). Returns the steps taken.
fn depenetrate(world: &mut PhysicsWorld, owner: &Owners, bodies: &[Body], handles: &[RigidBodyHandle], opts: &SettleOptions) -> usize {
    let mut depen_steps = 0;
    let max_steps = (opts.max_depenetration_s / opts.dt_s).ceil() as usize;
    let check_every = (0.025 / opts.dt_s).ceil().max(1.0) as usize;
    // Translations only: the reconstructed orientations are kept (an
    // off-centre push would otherwise tip a sphere off its resting facet).
    for h in handles {
        if let Some(b) = world.bodies.get_mut(*h) {
            b.lock_rotations(true, true);
        }
    }
    while depen_steps < max_steps {
        world.step();
        depen_steps += 1;
        for h in handles {
            if let Some(b) = world.bodies.get_mut(*h) {
                b.set_linvel(Vector::ZERO, true);
                b.set_angvel(Vector::ZERO, true);
            }
        }
        if depen_steps % check_every == 0 && penetrations(world, owner, bodies, handles).iter().all(|(p, _)| *p <= opts.depenetrated_m) {
            break;
        }
    }
    for h in handles {
        if let Some(b) = world.bodies.get_mut(*h) {
            b.lock_rotations(false, true);
        }
    }
    depen_steps
}

/// How the dynamic settle ended.
struct RestRun {
    /// Steps taken in all, depenetration included.
    steps: usize,
    at_rest: bool,
    /// Body poses over the last rest window, for the position-based rest bound.
    recent: std::collections::VecDeque<Vec<Pose>>,
}

/// The dynamic settle: steps until every body has been still for the rest
/// duration (and at least 0.1 s has passed) or the time limit is reached.
fn run_to_rest(world: &mut PhysicsWorld, handles: &[RigidBodyHandle], depen_steps: usize, opts: &SettleOptions) -> RestRun {
    let steps_max = (opts.max_time_s / opts.dt_s).ceil() as usize + depen_steps;
    let rest_steps = (opts.rest_duration_s / opts.dt_s).ceil() as usize;
    let min_steps = (0.1 / opts.dt_s).ceil() as usize;
    let mut calm = 0;
    let mut steps = depen_steps;
    let mut at_rest = false;
    let mut recent: std::collections::VecDeque<Vec<Pose>> = std::collections::VecDeque::with_capacity(rest_steps + 1);
    while steps < steps_max {
        world.step();
        steps += 1;
        if recent.len() == rest_steps.max(1) {
            recent.pop_front();
        }
        recent.push_back(handles.iter().map(|h| *world.bodies[*h].position()).collect());
        let still = handles.iter().all(|h| {
            let b = &world.bodies[*h];
            (b.linvel().length() as f64) < opts.rest_linear_m_s && (b.angvel().length() as f64) < opts.rest_angular_rad_s
        });
        calm = if still { calm + 1 } else { 0 };
        if calm >= rest_steps && steps >= min_steps + depen_steps {
            at_rest = true;
            break;
        }
    }
    RestRun { steps, at_rest, recent }
}

/// Names of the bodies (or the plane) in active contact with body `rb`, sorted.
fn touching(world: &PhysicsWorld, owner: &Owners, rb: &RigidBody, name: &str) -> Vec<String> {
    let mut touching: Vec<String> = Vec::new();
    for ch in rb.colliders() {
        for pair in world.narrow_phase.contact_pairs_with(*ch) {
            if !pair.has_any_active_contact() {
                continue;
            }
            let other = if pair.collider1 == *ch { pair.collider2 } else { pair.collider1 };
            if let Some(other) = owner.get(&other).filter(|n| **n != name) {
                if !touching.contains(other) {
                    touching.push(other.clone());
                }
            }
        }
    }
    touching.sort();
    touching
}

/// The settled state of body `b` (index `k`, handle `h`): its motion, contacts,
/// overlaps (`start`: deepest at the start pose and with what) and flags.
fn body_outcome(
    world: &PhysicsWorld,
    owner: &Owners,
    b: &Body,
    h: RigidBodyHandle,
    k: usize,
    start: (f64, Option<String>),
    end_pen: f64,
    run: &RestRun,
    opts: &SettleOptions,
) -> BodySettle {
    let (pen, pen_with) = start;
    let rb = &world.bodies[h];
    let end = from_pose(rb.position());
    let d = (0..3).map(|k| ((end.translation[k] - b.pose.translation[k]) as f64).powi(2)).sum::<f64>().sqrt();
    let rot = rotation_angle_deg(&b.pose.rotation, &end.rotation);
    let touching = touching(world, owner, rb, &b.name);
    let reach = b
        .parts
        .iter()
        .flat_map(|p| p.surface_mesh().vertices)
        .map(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt())
        .fold(0.0f32, f32::max);
    let rest_motion = run
        .recent
        .iter()
        .map(|poses| {
            let p = from_pose(&poses[k]);
            let dt = (0..3).map(|a| ((p.translation[a] - end.translation[a]) as f64).powi(2)).sum::<f64>().sqrt();
            dt + rotation_angle_deg(&p.rotation, &end.rotation).to_radians() * reach as f64
        })
        .fold(0.0, f64::max);
    let speed = rb.linvel().length() as f64;
    let mut reasons = Vec::new();
    if d > opts.flag_displacement_m {
        reasons.push(format!("moved {:.1} mm (> {:.1} mm)", d * 1e3, opts.flag_displacement_m * 1e3));
    }
    if rot > opts.flag_rotation_deg {
        reasons.push(format!("rotated {rot:.1}° (> {:.1}°)", opts.flag_rotation_deg));
    }
    if !run.at_rest && speed >= opts.rest_linear_m_s {
        reasons.push(format!("still moving at {:.1} mm/s when the time limit was reached", speed * 1e3));
    }
    BodySettle {
        name: b.name.clone(),
        rotation: end.rotation,
        translation_m: end.translation,
        start_penetration_m: pen,
        start_penetration_with: pen_with,
        end_penetration_m: end_pen,
        displacement_m: d,
        rotation_deg: rot,
        final_speed_m_s: speed,
        touching,
        flagged: !reasons.is_empty(),
        flag_reasons: reasons,
        rest_motion_m: rest_motion,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::collision::{build_collision, CollisionMethod, CollisionOptions};
    use crate::physics::tests::box_at;
    use crate::physics::{annotate, check_mesh, TreatmentChoice};

    fn cube_body(name: &str, half: f32, at: [f32; 3], method: CollisionMethod) -> Body {
        let (m, rep) = check_mesh(&box_at([half; 3], [0.0; 3]), name).unwrap();
        let i = annotate(&m, &rep, TreatmentChoice::Auto, 500.0, 0.002, None, name).unwrap();
        let c = build_collision(&m, rep.volume_m3, method, &CollisionOptions::new(), name).unwrap();
        Body {
            name: name.into(),
            pose: Similarity32 { translation: at, ..Similarity32::identity() },
            mass_kg: i.mass_kg,
            inertia: i.inertia,
            friction: 0.6,
            restitution: 0.0,
            parts: c.parts,
        }
    }

    #[test]
    fn resting_cube_stays_and_dropped_cube_lands() {
        let bodies = vec![
            cube_body("rest", 0.03, [0.0, 0.0, 0.03], CollisionMethod::Hull),
            cube_body("drop", 0.03, [0.2, 0.0, 0.05], CollisionMethod::Primitive),
        ];
        let r = settle(&bodies, 0.6, 0.0, &SettleOptions::default()).unwrap();
        assert!(r.at_rest, "{r:?}");
        let rest = &r.bodies[0];
        assert!(rest.displacement_m < 5e-4, "resting cube moved {} m", rest.displacement_m);
        assert!(!rest.flagged);
        assert!(rest.start_penetration_m < 1e-5, "{rest:?}");
        assert_eq!(rest.touching, vec![PLANE.to_string()]);
        let drop = &r.bodies[1];
        assert!((drop.translation_m[2] - 0.03).abs() < 5e-4, "landed at {}", drop.translation_m[2]);
        assert!((drop.displacement_m - 0.02).abs() < 1e-3);
        assert!(drop.flagged && drop.flag_reasons[0].contains("moved"), "{drop:?}");
    }

    #[test]
    fn overlapping_cubes_separate_gently_and_deterministically() {
        // Two 6 cm cubes overlapping by 5 mm along x.
        let bodies = vec![
            cube_body("a", 0.03, [0.0, 0.0, 0.03], CollisionMethod::Convex),
            cube_body("b", 0.03, [0.055, 0.0, 0.03], CollisionMethod::Convex),
        ];
        let r = settle(&bodies, 0.6, 0.0, &SettleOptions::default()).unwrap();
        assert!(r.at_rest);
        for (b, other) in r.bodies.iter().zip(["b", "a"]) {
            assert!((b.start_penetration_m - 0.005).abs() < 2e-4, "{b:?}");
            assert_eq!(b.start_penetration_with.as_deref(), Some(other));
        }
        let gap = r.bodies[1].translation_m[0] - r.bodies[0].translation_m[0];
        assert!(gap >= 0.0595, "still overlapping: centre distance {gap}");
        for b in &r.bodies {
            assert!((b.translation_m[2] - 0.03).abs() < 1e-3, "{} at z {}", b.name, b.translation_m[2]);
            assert!(b.rotation_deg < 2.0 && b.displacement_m < 0.01, "{b:?}");
            assert!(b.end_penetration_m < 5e-4, "{b:?}");
        }
        let again = settle(&bodies, 0.6, 0.0, &SettleOptions::default()).unwrap();
        assert_eq!(serde_json::to_string(&again).unwrap(), serde_json::to_string(&r).unwrap());
    }
}
