//! Poses on the support plane under spatial predicates: objects are placed
//! one by one (supports before their loads, anchors before the objects
//! related to them), each by rejection sampling around its anchor until it
//! is clear of everything placed (parry distance queries on the collision
//! geometry) and every predicate between placed objects holds.

use super::profile::Profile;
use super::spec::Predicate;
use crate::settle::shapes_distance;
use rapier3d::prelude::{Pose, SharedShape};
use recon_core::math::Similarity32;
use recon_core::rng::SeededRng;
use recon_core::{Error, Result};

/// Clearance between placed objects before settling (m).
const CLEARANCE: f64 = 0.002;
/// Height a load is dropped from above its support (m).
const DROP: f64 = 0.003;
/// Proposals per object before the whole placement is given up.
const TRIES: usize = 200;

/// One object as the placer sees it. The resting frame is the body frame
/// turned by `orient`: z up, origin at the centre of mass.
#[derive(Clone)]
pub struct Placeable {
    pub orient: [[f32; 3]; 3],
    /// Convex-hull vertices of the visual mesh and of the collision parts, resting frame.
    pub hull: Vec<[f64; 3]>,
    pub zmin: f64,
    pub zmax: f64,
    /// Footprint radius about the centre of mass.
    pub radius: f64,
    pub profile: Profile,
    /// Collision parts in the body frame.
    pub shapes: Vec<(Pose, SharedShape)>,
}

impl Placeable {
    /// Body pose for a yaw about world z and a centre-of-mass position.
    pub fn pose(&self, yaw: f64, t: [f64; 3]) -> Similarity32 {
        let r = recon_core::math::axis_angle([0.0, 0.0, 1.0], yaw).map(|row| row.map(|x| x as f32));
        Similarity32 { rotation: recon_core::math::matmul(&r, &self.orient), translation: t.map(|x| x as f32), scale: 1.0 }
    }

    /// Half extents of the footprint at `yaw` relative to another frame's yaw.
    fn half_at(&self, yaw: f64) -> [f64; 2] {
        let (c, s) = (yaw.cos(), yaw.sin());
        let mut h = [0.0f64; 2];
        for p in &self.hull {
            h[0] = h[0].max((c * p[0] - s * p[1]).abs());
            h[1] = h[1].max((s * p[0] + c * p[1]).abs());
        }
        h
    }
}

/// The world-frame facts the predicates are judged on.
pub struct WorldView<'a> {
    pub objs: &'a [Placeable],
    pub poses: &'a [Option<Similarity32>],
    /// Unit directions on the plane: [right, behind].
    pub axes: [[f64; 2]; 2],
}

/// The resting-frame → world transform of a body pose.
fn rest_to_world(o: &Placeable, pose: &Similarity32) -> ([[f64; 3]; 3], [f64; 3]) {
    // pose.rotation = Rz · orient, so Rz = pose.rotation · orientᵀ.
    let ot = transpose(&o.orient);
    let r = recon_core::math::matmul(&pose.rotation, &ot).map(|row| row.map(|x| x as f64));
    (r, pose.translation.map(|x| x as f64))
}

fn transpose(m: &[[f32; 3]; 3]) -> [[f32; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]))
}

/// World point → the resting frame of `o` at `pose`.
fn to_rest(o: &Placeable, pose: &Similarity32, p: [f64; 3]) -> [f64; 3] {
    let (r, t) = rest_to_world(o, pose);
    let d = [p[0] - t[0], p[1] - t[1], p[2] - t[2]];
    std::array::from_fn(|i| (0..3).map(|k| r[k][i] * d[k]).sum())
}

/// World bounds of the hull points at `pose`.
fn world_bounds(o: &Placeable, pose: &Similarity32) -> ([f64; 3], [f64; 3]) {
    let (r, t) = rest_to_world(o, pose);
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in &o.hull {
        for k in 0..3 {
            let w = t[k] + (0..3).map(|j| r[k][j] * p[j]).sum::<f64>();
            lo[k] = lo[k].min(w);
            hi[k] = hi[k].max(w);
        }
    }
    (lo, hi)
}

/// A predicate judged on poses, with the measured quantity it was judged by.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Judged {
    pub holds: bool,
    /// on_top / inside: gap between the load's bottom and the support's top
    /// (m, negative below it); directions: displacement along the direction
    /// (m); near: distance between the collision geometries (m).
    pub measured_m: f64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub angle_deg: Option<f64>,
}

impl WorldView<'_> {
    pub fn judge(&self, p: &Predicate, ia: usize, ib: usize) -> Result<Judged> {
        let (a, b) = (&self.objs[ia], &self.objs[ib]);
        let (pa, pb) = match (self.poses[ia], self.poses[ib]) {
            (Some(x), Some(y)) => (x, y),
            _ => return Err(Error::msg(format!("{}: judged before both objects were placed", p.label()))),
        };
        let (la, _) = world_bounds(a, &pa);
        let (lb, hb) = world_bounds(b, &pb);
        let ca = pa.translation.map(|x| x as f64);
        let cb = pb.translation.map(|x| x as f64);
        Ok(match p {
            Predicate::OnTop { .. } => {
                let gap = la[2] - hb[2];
                let over = ca[0] >= lb[0] && ca[0] <= hb[0] && ca[1] >= lb[1] && ca[1] <= hb[1];
                Judged { holds: gap >= -0.005 && la[2] > 0.005 && over, measured_m: gap, angle_deg: None }
            }
            Predicate::Inside { .. } => {
                let q = to_rest(b, &pb, ca);
                let gap = la[2] - hb[2];
                Judged { holds: b.profile.in_cavity(q[0], q[1]) && la[2] < hb[2], measured_m: gap, angle_deg: None }
            }
            Predicate::Near { distance_m, .. } => {
                let d = shapes_distance(&a.shapes, &pa, &b.shapes, &pb)?;
                Judged { holds: d <= *distance_m, measured_m: d, angle_deg: None }
            }
            _ => {
                let (axis, sign) = p.direction().ok_or_else(|| Error::msg("not a direction"))?;
                let u = self.axes[axis].map(|x| x * sign);
                let d = [ca[0] - cb[0], ca[1] - cb[1]];
                let along = d[0] * u[0] + d[1] * u[1];
                let across = (d[0] * -u[1] + d[1] * u[0]).abs();
                let angle = across.atan2(along).to_degrees();
                Judged { holds: along >= 0.01 && along >= across, measured_m: along, angle_deg: Some(angle) }
            }
        })
    }
}

/// A predicate with its objects resolved to indices.
#[derive(Debug, Clone)]
pub struct Bound {
    pub pred: Predicate,
    pub a: usize,
    pub b: usize,
}

/// Placement order: supports before loads, anchors before the objects
/// related to them, otherwise object order.
fn order(n: usize, preds: &[Bound]) -> Vec<usize> {
    let mut done = vec![false; n];
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let ready = |i: usize, strict: bool| !done[i] && preds.iter().all(|p| p.a != i || done[p.b] || (!strict && !p.pred.is_support()));
        let next = (0..n)
            .find(|&i| ready(i, true))
            .or_else(|| (0..n).find(|&i| ready(i, false)))
            .unwrap_or_else(|| (0..n).find(|&i| !done[i]).unwrap_or(0));
        done[next] = true;
        out.push(next);
    }
    out
}

pub struct Region {
    pub centre: [f64; 2],
    pub half: [f64; 2],
}

/// Sample poses for all objects; `Err(i)` names the first object that found no place.
pub fn place(
    objs: &[Placeable],
    preds: &[Bound],
    region: &Region,
    axes: [[f64; 2]; 2],
    rng: &mut SeededRng,
) -> Result<std::result::Result<Vec<Similarity32>, usize>> {
    let mut poses: Vec<Option<Similarity32>> = vec![None; objs.len()];
    for i in order(objs.len(), preds) {
        let mut found = None;
        for _ in 0..TRIES {
            let Some(cand) = propose(i, objs, &poses, preds, region, axes, rng)? else { continue };
            if !clear(i, &cand, objs, &poses)? {
                continue;
            }
            poses[i] = Some(cand);
            let view = WorldView { objs, poses: &poses, axes };
            let mut ok = true;
            for p in preds.iter().filter(|p| (p.a == i || p.b == i) && poses[p.a].is_some() && poses[p.b].is_some()) {
                if !view.judge(&p.pred, p.a, p.b)?.holds {
                    ok = false;
                    break;
                }
            }
            poses[i] = None;
            if ok {
                found = Some(cand);
                break;
            }
        }
        match found {
            Some(p) => poses[i] = Some(p),
            None => return Ok(Err(i)),
        }
    }
    Ok(Ok(poses.into_iter().map(|p| p.unwrap_or_else(Similarity32::identity)).collect()))
}

/// Clear of every placed object by [`CLEARANCE`] (AABB test first).
fn clear(i: usize, cand: &Similarity32, objs: &[Placeable], poses: &[Option<Similarity32>]) -> Result<bool> {
    let (lo, hi) = world_bounds(&objs[i], cand);
    for (j, p) in poses.iter().enumerate() {
        let Some(p) = p else { continue };
        if j == i {
            continue;
        }
        let (lo2, hi2) = world_bounds(&objs[j], p);
        if (0..3).any(|k| lo[k] > hi2[k] + CLEARANCE * 2.0 || lo2[k] > hi[k] + CLEARANCE * 2.0) {
            continue;
        }
        if shapes_distance(&objs[i].shapes, cand, &objs[j].shapes, p)? < CLEARANCE {
            return Ok(false);
        }
    }
    Ok(true)
}

fn on_plane(o: &Placeable, yaw: f64, xy: [f64; 2]) -> Similarity32 {
    o.pose(yaw, [xy[0], xy[1], -o.zmin + 0.0002])
}

/// One candidate pose for object `i`, from its anchor predicate if one is placed.
fn propose(
    i: usize,
    objs: &[Placeable],
    poses: &[Option<Similarity32>],
    preds: &[Bound],
    region: &Region,
    axes: [[f64; 2]; 2],
    rng: &mut SeededRng,
) -> Result<Option<Similarity32>> {
    let o = &objs[i];
    let yaw = rng.uniform() * std::f64::consts::TAU;
    // The first predicate with `i` as its subject and a placed anchor; else one with `i` as the anchor.
    let anchor = preds
        .iter()
        .filter(|p| p.a == i && poses[p.b].is_some())
        .min_by_key(|p| !p.pred.is_support())
        .map(|p| (p, p.b, 1.0))
        .or_else(|| preds.iter().find(|p| p.b == i && poses[p.a].is_some() && !p.pred.is_support()).map(|p| (p, p.a, -1.0)));
    let Some((p, j, sign)) = anchor else {
        let xy = [
            region.centre[0] + region.half[0] * (2.0 * rng.uniform() - 1.0),
            region.centre[1] + region.half[1] * (2.0 * rng.uniform() - 1.0),
        ];
        return Ok(Some(on_plane(o, yaw, xy)));
    };
    let b = &objs[j];
    let pb = poses[j].ok_or_else(|| Error::msg("anchor not placed"))?;
    let (rb, tb) = rest_to_world(b, &pb);
    let cb = [tb[0], tb[1]];
    match &p.pred {
        Predicate::OnTop { .. } | Predicate::Inside { .. } => {
            // Align the load's frame with the support's (quarter turns), sample a cell.
            let b_yaw = rb[1][0].atan2(rb[0][0]);
            let rel = (rng.next_u64() % 4) as f64 * std::f64::consts::FRAC_PI_2;
            let half = o.half_at(rel);
            let inside = matches!(p.pred, Predicate::Inside { .. });
            let set = if inside { &b.profile.cavity } else { &b.profile.plateau };
            let cells = b.profile.centres(set);
            if cells.is_empty() {
                return Ok(None);
            }
            let c = cells[(rng.next_u64() % cells.len() as u64) as usize];
            if !b.profile.rect_in(set, c, half) {
                return Ok(None);
            }
            let base_z = if inside { b.profile.floor_under(c, half) } else { b.zmax };
            let local = [c[0], c[1], base_z - o.zmin + DROP];
            let w: [f64; 3] = std::array::from_fn(|k| tb[k] + (0..3).map(|m| rb[k][m] * local[m]).sum::<f64>());
            Ok(Some(o.pose(b_yaw + rel, w)))
        }
        Predicate::Near { distance_m, .. } => {
            // Bisection along a random direction for a surface gap in [0.2, 0.7]·d.
            let th = rng.uniform() * std::f64::consts::TAU;
            let u = [th.cos(), th.sin()];
            let target = distance_m * (0.2 + 0.5 * rng.uniform());
            let (mut lo, mut hi) = (0.0, o.radius + b.radius + distance_m);
            for _ in 0..14 {
                let t = 0.5 * (lo + hi);
                let cand = on_plane(o, yaw, [cb[0] + u[0] * t, cb[1] + u[1] * t]);
                let d = shapes_distance(&o.shapes, &cand, &b.shapes, &pb)?;
                if d < target {
                    lo = t;
                } else {
                    hi = t;
                }
            }
            Ok(Some(on_plane(o, yaw, [cb[0] + u[0] * hi, cb[1] + u[1] * hi])))
        }
        _ => {
            let (axis, s) = p.pred.direction().ok_or_else(|| Error::msg("not a direction"))?;
            let u = axes[axis].map(|x| x * s * sign);
            let v = [-u[1], u[0]];
            let along = o.radius + b.radius + 0.01 + 0.1 * rng.uniform();
            let across = along * 0.8 * (2.0 * rng.uniform() - 1.0);
            let xy = [cb[0] + u[0] * along + v[0] * across, cb[1] + u[1] * along + v[1] * across];
            Ok(Some(on_plane(o, yaw, xy)))
        }
    }
}

/// The yaw that turns `pts` (resting frame) to their smallest axis-aligned
/// footprint: a box's sides then run along the frame's axes, so its flat top
/// fills the profile grid and loads are aligned with it.
pub fn canonical_yaw(pts: &[[f64; 3]]) -> f64 {
    let mut best = (f64::INFINITY, 0.0);
    // Candidate directions: every pair of extreme points is too many; the
    // footprint hull's edges are enough (the minimum-area rectangle has a side on one).
    let hull2 = hull_2d(pts);
    for k in 0..hull2.len() {
        let (p, q) = (hull2[k], hull2[(k + 1) % hull2.len()]);
        let th = (q[1] - p[1]).atan2(q[0] - p[0]);
        let (c, s) = (th.cos(), th.sin());
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for r in &hull2 {
            let x = c * r[0] + s * r[1];
            let y = -s * r[0] + c * r[1];
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        }
        let area = (hi[0] - lo[0]) * (hi[1] - lo[1]);
        // Ties (circles, squares) keep the first edge: deterministic.
        if area < best.0 * (1.0 - 1e-9) {
            best = (area, -th);
        }
    }
    best.1
}

/// Convex hull of the points' xy (Andrew's monotone chain), counter-clockwise.
fn hull_2d(pts: &[[f64; 3]]) -> Vec<[f64; 2]> {
    let mut p: Vec<[f64; 2]> = pts.iter().map(|q| [q[0], q[1]]).collect();
    p.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    p.dedup();
    if p.len() < 3 {
        return p;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
    let mut h: Vec<[f64; 2]> = Vec::new();
    for pass in 0..2 {
        let start = h.len();
        let iter: Box<dyn Iterator<Item = &[f64; 2]>> = if pass == 0 { Box::new(p.iter()) } else { Box::new(p.iter().rev()) };
        for &q in iter {
            while h.len() >= start + 2 && cross(h[h.len() - 2], h[h.len() - 1], q) <= 0.0 {
                h.pop();
            }
            h.push(q);
        }
        h.pop();
    }
    h
}

/// Whether `a` can stand on `b`'s top, or fit in `b`'s cavity, at some
/// quarter turn and position: the checks behind the spec's size errors.
pub fn fits(a: &Placeable, b: &Placeable, inside: bool) -> bool {
    let set = if inside { &b.profile.cavity } else { &b.profile.plateau };
    let cells = b.profile.centres(set);
    (0..2).any(|k| {
        let half = a.half_at(k as f64 * std::f64::consts::FRAC_PI_2);
        cells.iter().any(|c| b.profile.rect_in(set, *c, half))
    })
}
