//! Procedural tabletop objects: boxes, cans, bottles, bowls, mugs, spheres, tori, L-shapes.
//!
//! Canonical frame of every object (and of every part): metres, origin at the centre of
//! its axis-aligned bounding box, **z up** (the object stands on its bottom face, which
//! lies at `z = -size_z / 2`), mug handles point along **+x**. Every part is a closed,
//! consistently outward-oriented triangle mesh (every edge shared by exactly two faces).
//! Bowls and mugs are open *containers* modelled with a wall thickness, so their meshes are
//! still closed ([`Shell::Walled`]). A composite's merged mesh is the union of its closed
//! parts (where parts touch, e.g. the mug handle sunk into the wall, the hidden internal
//! faces are kept).

use recon_core::math::{axis_angle, Similarity};
use recon_core::mesh::primitives::{
    bounds, bowl_mesh, box_mesh, centre_of, centred, cup_mesh, cylinder_mesh, l_shape_mesh, revolve, sphere_mesh, torus_mesh, tube_mesh,
    SEGMENTS,
};
use recon_core::mesh::Mesh;
use recon_core::rng::SeededRng;
use serde::Serialize;
use std::f64::consts::{FRAC_PI_2, PI};

#[derive(Serialize, Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
/// Procedural object kinds.
pub enum Kind {
    /// A rectangular box.
    Box,
    /// A closed cylinder (a can).
    Cylinder,
    /// A bottle: body and cap.
    Bottle,
    /// An open bowl.
    Bowl,
    /// A mug: body and handle.
    Mug,
    /// A sphere.
    Sphere,
    /// A torus.
    Torus,
    /// An L-shaped solid.
    LShape,
}

impl Kind {
    /// Every kind, in declaration order.
    pub const ALL: [Kind; 8] = [Kind::Box, Kind::Cylinder, Kind::Bottle, Kind::Bowl, Kind::Mug, Kind::Sphere, Kind::Torus, Kind::LShape];
    /// Snake-case name (as serialised).
    pub fn name(self) -> &'static str {
        match self {
            Kind::Box => "box",
            Kind::Cylinder => "cylinder",
            Kind::Bottle => "bottle",
            Kind::Bowl => "bowl",
            Kind::Mug => "mug",
            Kind::Sphere => "sphere",
            Kind::Torus => "torus",
            Kind::LShape => "l_shape",
        }
    }
}

/// How a container's opening is modelled.
#[derive(Serialize, Clone, Copy, Debug, PartialEq)]
#[serde(tag = "shell", rename_all = "snake_case")]
pub enum Shell {
    /// A closed solid.
    Solid,
    /// An open container with walls of this thickness (the mesh is closed).
    Walled {
        /// Wall thickness in metres.
        wall_thickness_m: f64,
    },
}

/// Geometric symmetries in the canonical frame (BOP `models_info.json` style).
#[derive(Serialize, Clone, Debug, Default, PartialEq)]
pub struct Symmetry {
    /// Axes of continuous rotational symmetry through the origin.
    pub continuous_axes: Vec<[f64; 3]>,
    /// Proper rotations (besides the identity) mapping the shape onto itself.
    pub discrete: Vec<[[f64; 3]; 3]>,
}

/// A rigid part: its own closed mesh in its own canonical frame and its pose in the
/// object frame (`X_object = R · X_part + t`).
#[derive(Clone, Debug)]
pub struct Part {
    /// Part name (e.g. `body`, `handle`).
    pub name: &'static str,
    /// Closed mesh in the part's canonical frame (metres).
    pub mesh: Mesh,
    /// Part → object frame.
    pub pose: Similarity,
    /// Symmetries of the part alone.
    pub symmetry: Symmetry,
}

#[derive(Clone, Debug)]
/// A procedural object: its rigid parts, shell and symmetries.
pub struct Object {
    /// What kind of object.
    pub kind: Kind,
    /// Solid or walled container.
    pub shell: Shell,
    /// One part for primitives; body + handle (mug), body + cap (bottle).
    pub parts: Vec<Part>,
    /// Symmetries of the whole object.
    pub symmetry: Symmetry,
    /// The randomised dimensions (metres), for the record.
    pub dims: Vec<(&'static str, f64)>,
}

impl Object {
    /// All parts merged into the object frame.
    pub fn mesh(&self) -> Mesh {
        let mut out = Mesh::default();
        for p in &self.parts {
            let base = out.vertices.len() as u32;
            out.vertices.extend(p.mesh.vertices.iter().map(|v| {
                let q = p.pose.apply(&[v[0] as f64, v[1] as f64, v[2] as f64]);
                [q[0] as f32, q[1] as f32, q[2] as f32]
            }));
            out.faces.extend(p.mesh.faces.iter().map(|f| [f[0] + base, f[1] + base, f[2] + base]));
        }
        out
    }

    /// Axis-aligned bounds of the merged mesh (object frame).
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        bounds(&self.mesh())
    }

    /// A random instance of `kind` (tabletop sizes, 3–30 cm).
    pub fn random(kind: Kind, rng: &mut SeededRng) -> Object {
        let mut u = |lo: f64, hi: f64| lo + (hi - lo) * rng.uniform();
        match kind {
            Kind::Box => {
                let (x, y, z) = (u(0.05, 0.20), u(0.04, 0.15), u(0.03, 0.22));
                single(kind, Shell::Solid, box_mesh(x, y, z), box_symmetry(), vec![("size_x", x), ("size_y", y), ("size_z", z)])
            }
            Kind::Cylinder => {
                let (r, h) = (u(0.025, 0.06), u(0.05, 0.18));
                let bevel = 0.08 * r.min(h / 2.0);
                let sym = Symmetry { continuous_axes: vec![Z], discrete: vec![rot_x_pi()] };
                single(kind, Shell::Solid, cylinder_mesh(r, h, bevel), sym, vec![("radius", r), ("height", h)])
            }
            Kind::Sphere => {
                let r = u(0.03, 0.07);
                let sym = Symmetry { continuous_axes: vec![Z], discrete: vec![rot_x_pi()] };
                single(kind, Shell::Solid, sphere_mesh(r), sym, vec![("radius", r)])
            }
            Kind::Torus => {
                let (big, small) = (u(0.035, 0.07), u(0.01, 0.025));
                let sym = Symmetry { continuous_axes: vec![Z], discrete: vec![rot_x_pi()] };
                single(kind, Shell::Solid, torus_mesh(big, small), sym, vec![("major_radius", big), ("minor_radius", small)])
            }
            Kind::LShape => {
                let (a, b) = (u(0.08, 0.20), u(0.06, 0.16));
                let (ta, tb) = (u(0.02, 0.05), u(0.02, 0.05));
                let h = u(0.03, 0.12);
                single(
                    kind,
                    Shell::Solid,
                    l_shape_mesh(a, b, ta, tb, h),
                    Symmetry::default(),
                    vec![("leg_x", a), ("leg_y", b), ("width_x_leg", tb), ("width_y_leg", ta), ("height", h)],
                )
            }
            Kind::Bowl => {
                let r = u(0.06, 0.11);
                let h = u(0.04, 0.08);
                let foot = u(0.45, 0.65) * r;
                let t = u(0.004, 0.008);
                let sym = Symmetry { continuous_axes: vec![Z], discrete: vec![] };
                single(
                    kind,
                    Shell::Walled { wall_thickness_m: t },
                    bowl_mesh(r, h, foot, t),
                    sym,
                    vec![("rim_radius", r), ("height", h), ("foot_radius", foot), ("wall", t)],
                )
            }
            Kind::Mug => {
                let (r, h, t) = (u(0.035, 0.05), u(0.08, 0.12), u(0.004, 0.007));
                let (a, rho) = (u(0.25, 0.35) * h, u(0.005, 0.008));
                mug(r, h, t, a, rho)
            }
            Kind::Bottle => {
                let (r, h) = (u(0.025, 0.045), u(0.15, 0.28));
                let neck = u(0.35, 0.5) * r;
                let cap_h = u(0.015, 0.03);
                bottle(r, h, neck, cap_h)
            }
        }
    }
}

const Z: [f64; 3] = [0.0, 0.0, 1.0];

fn rot_x_pi() -> [[f64; 3]; 3] {
    [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]
}

fn box_symmetry() -> Symmetry {
    let d = |a: [f64; 3]| [[a[0], 0.0, 0.0], [0.0, a[1], 0.0], [0.0, 0.0, a[2]]];
    Symmetry { continuous_axes: vec![], discrete: vec![d([1.0, -1.0, -1.0]), d([-1.0, 1.0, -1.0]), d([-1.0, -1.0, 1.0])] }
}

fn single(kind: Kind, shell: Shell, mesh: Mesh, symmetry: Symmetry, dims: Vec<(&'static str, f64)>) -> Object {
    let mesh = centred(mesh);
    Object {
        kind,
        shell,
        parts: vec![Part { name: "body", mesh, pose: Similarity::identity(), symmetry: symmetry.clone() }],
        symmetry,
        dims,
    }
}

/// Build a composite from parts given in a common frame: each part is re-centred in its
/// own frame (pose = translation to where it was), then the whole object is centred.
fn composite(
    kind: Kind,
    shell: Shell,
    parts: Vec<(&'static str, Mesh, Symmetry)>,
    symmetry: Symmetry,
    dims: Vec<(&'static str, f64)>,
) -> Object {
    let mut all = Mesh::default();
    for (_, m, _) in &parts {
        let base = all.vertices.len() as u32;
        all.vertices.extend_from_slice(&m.vertices);
        all.faces.extend(m.faces.iter().map(|f| [f[0] + base, f[1] + base, f[2] + base]));
    }
    let oc = centre_of(&all);
    let parts = parts
        .into_iter()
        .map(|(name, m, sym)| {
            let pc = centre_of(&m);
            let mesh = centred(m);
            let t = [pc[0] - oc[0], pc[1] - oc[1], pc[2] - oc[2]];
            Part { name, mesh, pose: Similarity { translation: t, ..Similarity::identity() }, symmetry: sym }
        })
        .collect();
    Object { kind, shell, parts, symmetry, dims }
}

fn mug(r: f64, h: f64, t: f64, a: f64, rho: f64) -> Object {
    let body = cup_mesh(r, h, t);
    // Semicircular handle in the xz-plane, its ends sunk into the middle of the wall.
    let cx = r - t / 2.0;
    let zc = h / 2.0;
    let m = 16;
    let path: Vec<[f64; 3]> = (0..=m)
        .map(|i| {
            let al = -FRAC_PI_2 + PI * i as f64 / m as f64;
            [cx + a * al.cos(), 0.0, zc + a * al.sin()]
        })
        .collect();
    let handle = tube_mesh(&path, rho, 12);
    let body_sym = Symmetry { continuous_axes: vec![Z], discrete: vec![] };
    let handle_sym = Symmetry { continuous_axes: vec![], discrete: vec![axis_angle([1.0, 0.0, 0.0], PI)] };
    composite(
        Kind::Mug,
        Shell::Walled { wall_thickness_m: t },
        vec![("body", body, body_sym), ("handle", handle, handle_sym)],
        Symmetry::default(),
        vec![("radius", r), ("height", h), ("wall", t), ("handle_radius", a), ("handle_thickness", rho)],
    )
}

fn bottle(r: f64, h: f64, neck: f64, cap_h: f64) -> Object {
    let bevel = 0.1 * r;
    let shoulder0 = 0.55 * h;
    let shoulder1 = 0.75 * h;
    let neck_top = h - cap_h;
    let mut p = vec![[0.0, 0.0], [r - bevel, 0.0], [r, bevel], [r, shoulder0]];
    let m = 8;
    for i in 1..=m {
        let s = i as f64 / m as f64;
        // Smooth (cosine) shoulder from the body radius down to the neck radius.
        let rr = neck + (r - neck) * 0.5 * (1.0 + (PI * s).cos());
        p.push([rr, shoulder0 + (shoulder1 - shoulder0) * s]);
    }
    p.push([neck, neck_top]);
    p.push([0.0, neck_top]);
    let body = revolve(&p, false, SEGMENTS);
    let rc = neck * 1.15;
    let cap: Vec<[f64; 2]> = vec![[0.0, neck_top], [rc, neck_top], [rc, h], [0.0, h]];
    let cap = revolve(&cap, false, SEGMENTS);
    let rev = Symmetry { continuous_axes: vec![Z], discrete: vec![] };
    let cap_sym = Symmetry { continuous_axes: vec![Z], discrete: vec![rot_x_pi()] };
    composite(
        Kind::Bottle,
        Shell::Solid,
        vec![("body", body, rev.clone()), ("cap", cap, cap_sym)],
        rev,
        vec![("radius", r), ("height", h), ("neck_radius", neck), ("cap_height", cap_h)],
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use recon_core::mesh::primitives::signed_volume;
    use std::f64::consts::TAU;

    fn check_closed(m: &Mesh, what: &str) {
        let t = m.topology();
        assert!(t.is_closed_oriented_manifold(), "{what}: {t:?}");
        assert!(signed_volume(m) > 0.0, "{what}: inward-oriented (volume {})", signed_volume(m));
    }

    fn objects(seed: u64) -> Vec<Object> {
        let mut rng = SeededRng::new(seed);
        Kind::ALL.iter().map(|&k| Object::random(k, &mut rng)).collect()
    }

    #[test]
    fn every_part_is_closed_and_outward() {
        for seed in 0..5 {
            for o in objects(seed) {
                for p in &o.parts {
                    check_closed(&p.mesh, &format!("{} {} (seed {seed})", o.kind.name(), p.name));
                    // Each part is centred in its own frame.
                    let (lo, hi) = bounds(&p.mesh);
                    for k in 0..3 {
                        assert!((lo[k] + hi[k]).abs() < 1e-5, "{} {} not centred: {lo:?} {hi:?}", o.kind.name(), p.name);
                    }
                }
                // The merged mesh is closed too (a union of closed parts) and centred.
                check_closed(&o.mesh(), o.kind.name());
                let (lo, hi) = o.bounds();
                for k in 0..3 {
                    assert!((lo[k] + hi[k]).abs() < 1e-5, "{}: {lo:?} {hi:?}", o.kind.name());
                    assert!(hi[k] - lo[k] > 0.005 && hi[k] - lo[k] < 0.35, "{}: size {:?}", o.kind.name(), hi[k] - lo[k]);
                }
            }
        }
    }

    #[test]
    fn dimensions_follow_the_seed() {
        let a: Vec<_> = objects(7).iter().map(|o| o.dims.clone()).collect();
        let b: Vec<_> = objects(7).iter().map(|o| o.dims.clone()).collect();
        let c: Vec<_> = objects(8).iter().map(|o| o.dims.clone()).collect();
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn known_volumes() {
        // Box and L: exact. Revolved shapes: the inscribed polygon's volume.
        assert!((signed_volume(&box_mesh(0.1, 0.2, 0.3)) - 0.006).abs() < 1e-9);
        let l = l_shape_mesh(0.2, 0.1, 0.03, 0.02, 0.05);
        assert!((signed_volume(&l) - 0.05 * (0.2 * 0.02 + 0.03 * 0.08)).abs() < 1e-9);
        let poly = |r: f64| 0.5 * SEGMENTS as f64 * r * r * (TAU / SEGMENTS as f64).sin();
        let c = cylinder_mesh(0.05, 0.1, 0.0);
        assert!((signed_volume(&c) - poly(0.05) * 0.1).abs() < 1e-8);
        let cup = cup_mesh(0.05, 0.1, 0.01);
        assert!((signed_volume(&cup) - (poly(0.05) * 0.1 - poly(0.04) * 0.09)).abs() < 1e-8);
        let s = sphere_mesh(0.05);
        let v = signed_volume(&s) / (4.0 / 3.0 * PI * 0.05f64.powi(3));
        assert!(v > 0.97 && v < 1.0, "{v}");
        let t = torus_mesh(0.05, 0.01);
        let v = signed_volume(&t) / (2.0 * PI * PI * 0.05 * 0.01 * 0.01);
        assert!(v > 0.95 && v < 1.0, "{v}");
    }

    #[test]
    fn mug_handle_points_along_x_and_parts_rebuild_the_object() {
        let mut rng = SeededRng::new(3);
        let o = Object::random(Kind::Mug, &mut rng);
        assert_eq!(o.parts.len(), 2);
        assert!(matches!(o.shell, Shell::Walled { wall_thickness_m } if wall_thickness_m > 0.0));
        let h = &o.parts[1];
        assert_eq!(h.name, "handle");
        assert!(h.pose.translation[0] > 0.0 && h.pose.translation[1].abs() < 1e-9, "{:?}", h.pose.translation);
        // Parts placed by their poses reproduce the merged mesh vertex for vertex.
        let merged = o.mesh();
        let n0 = o.parts[0].mesh.vertices.len();
        for (i, v) in h.mesh.vertices.iter().enumerate() {
            let q = h.pose.apply(&v.map(|x| x as f64));
            let m = merged.vertices[n0 + i];
            assert!((0..3).all(|k| (q[k] - m[k] as f64).abs() < 1e-6));
        }
    }

    #[test]
    fn declared_symmetries_map_the_shape_onto_itself() {
        let step = axis_angle(Z, TAU / SEGMENTS as f64);
        for seed in 0..3 {
            for o in objects(seed) {
                for p in &o.parts {
                    let mut rots: Vec<[[f64; 3]; 3]> = p.symmetry.discrete.clone();
                    if !p.symmetry.continuous_axes.is_empty() {
                        rots.push(step);
                    }
                    let vs: Vec<[f64; 3]> = p.mesh.vertices.iter().map(|v| v.map(|x| x as f64)).collect();
                    for r in &rots {
                        let s = Similarity::rigid(*r, [0.0; 3]);
                        for v in &vs {
                            let q = s.apply(v);
                            let d = vs.iter().map(|w| (0..3).map(|k| (q[k] - w[k]).powi(2)).sum::<f64>()).fold(f64::INFINITY, f64::min);
                            assert!(d.sqrt() < 1e-5, "{} {}: symmetry {r:?} moves {v:?} off the shape", o.kind.name(), p.name);
                        }
                    }
                }
            }
        }
        // A mug (its handle) has no symmetry, and the check above can fail: a quarter turn
        // does not map a box with distinct sides onto itself.
        let mut rng = SeededRng::new(0);
        assert_eq!(Object::random(Kind::Mug, &mut rng).symmetry, Symmetry::default());
        let b = box_mesh(0.1, 0.2, 0.3);
        let q = Similarity::rigid(axis_angle(Z, PI / 2.0), [0.0; 3]);
        let moved = q.apply(&b.vertices[0].map(|x| x as f64));
        assert!(b.vertices.iter().all(|w| (0..3).map(|k| (moved[k] - w[k] as f64).powi(2)).sum::<f64>().sqrt() > 1e-3));
    }
}
