//! Physics annotation of one object mesh: mesh checks (with the explicit
//! repairs listed), solid-or-shell choice, mass, centre of mass and inertia.
//!
//! Solids use parry3d's `MassProperties::from_trimesh` (signed tetrahedra).
//! Open meshes (boundary edges: bowls, mugs, lidless boxes) have no inside,
//! so they are shells: a wall of the material's thickness over the surface,
//! mass = area × thickness × density and the thin-lamina inertia integrated
//! over the triangles (parry has no 3D shell mass properties).

use recon_core::mesh::post::remove_unreferenced_vertices;
use recon_core::mesh::Mesh;
use recon_core::mesh::{face_area, Topology};
use recon_core::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::{HashMap, HashSet};

/// How the object's mass is distributed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Treatment {
    Solid,
    Shell,
}

/// Requested treatment; `Auto` picks shell for open meshes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TreatmentChoice {
    #[default]
    Auto,
    Solid,
    Shell,
}

/// What the checks found and what was changed.
#[derive(Debug, Clone, Serialize)]
pub struct MeshReport {
    pub vertices: usize,
    pub faces: usize,
    pub boundary_edges: usize,
    pub components: usize,
    pub closed: bool,
    /// Enclosed volume (closed meshes only).
    pub volume_m3: Option<f64>,
    pub area_m2: f64,
    /// Every change made to the input mesh, in order.
    pub repairs: Vec<String>,
}

/// Mass properties in the mesh's own frame (metres, kilograms).
#[derive(Debug, Clone, Serialize)]
pub struct Inertial {
    pub treatment: Treatment,
    /// Why this treatment (auto choice or request).
    pub treatment_reason: String,
    pub mass_kg: f64,
    pub com: [f64; 3],
    /// Inertia tensor about the centre of mass, mesh axes (kg·m²).
    pub inertia: [[f64; 3]; 3],
    pub density_kg_m3: f64,
    /// Wall thickness (shells only).
    pub shell_thickness_m: Option<f64>,
}

/// Check `mesh` and apply the explicit repairs: exact-duplicate vertices
/// welded, degenerate and duplicate faces dropped, unreferenced vertices
/// removed, a closed inside-out mesh flipped. Refused (error naming `file`):
/// non-finite coordinates, non-manifold edges (more than two faces),
/// inconsistently oriented faces, and a closed mesh enclosing no volume.
pub fn check_mesh(mesh: &Mesh, file: &str) -> Result<(Mesh, MeshReport)> {
    mesh.validate().map_err(|e| Error::input(file, e.to_string()))?;
    if let Some(v) = mesh.vertices.iter().find(|v| v.iter().any(|x| !x.is_finite())) {
        return Err(Error::input(file, format!("mesh has a non-finite vertex {v:?}")));
    }
    let mut repairs = Vec::new();
    // Weld vertices with bit-identical positions (seams split for UVs or normals).
    let mut index: HashMap<[u32; 3], u32> = HashMap::new();
    let mut remap = Vec::with_capacity(mesh.vertices.len());
    let mut vertices = Vec::new();
    for v in &mesh.vertices {
        let key = v.map(|x| if x == 0.0 { 0 } else { x.to_bits() });
        let id = *index.entry(key).or_insert_with(|| {
            vertices.push(*v);
            vertices.len() as u32 - 1
        });
        remap.push(id);
    }
    if vertices.len() < mesh.vertices.len() {
        repairs.push(format!("welded {} duplicate vertices", mesh.vertices.len() - vertices.len()));
    }
    let mut faces = Vec::with_capacity(mesh.faces.len());
    let mut seen = HashSet::new();
    let (mut degenerate, mut duplicate) = (0, 0);
    let scale = bbox_diagonal(&vertices).max(1e-12);
    for f in &mesh.faces {
        let f = f.map(|i| remap[i as usize]);
        if f[0] == f[1] || f[1] == f[2] || f[0] == f[2] || face_area(&vertices, &f) <= 1e-12 * scale * scale {
            degenerate += 1;
            continue;
        }
        let mut key = f;
        key.sort_unstable();
        if !seen.insert(key) {
            duplicate += 1;
            continue;
        }
        faces.push(f);
    }
    if degenerate > 0 {
        repairs.push(format!("dropped {degenerate} degenerate (zero-area) faces"));
    }
    if duplicate > 0 {
        repairs.push(format!("dropped {duplicate} duplicate faces"));
    }
    let before = vertices.len();
    let mut out = remove_unreferenced_vertices(&Mesh { vertices, faces, vertex_attrs: None });
    if out.vertices.len() < before {
        repairs.push(format!("removed {} unreferenced vertices", before - out.vertices.len()));
    }
    if out.faces.is_empty() {
        return Err(Error::input(file, "mesh has no (non-degenerate) faces"));
    }
    let topo: Topology = out.topology();
    if topo.nonmanifold_edges > 0 {
        return Err(Error::input(
            file,
            format!(
                "mesh has {} non-manifold edges (shared by more than two faces): mass and collision geometry are undefined; \
                 repair the mesh (split those edges or remesh) before `recon scene`",
                topo.nonmanifold_edges
            ),
        ));
    }
    if topo.misoriented_edges > 0 {
        return Err(Error::input(
            file,
            format!(
                "mesh has {} edges whose two faces are oriented inconsistently: inside and outside are undefined; \
                 re-orient the faces consistently before `recon scene`",
                topo.misoriented_edges
            ),
        ));
    }
    let closed = topo.boundary_edges == 0;
    let area = out.area();
    let mut volume = None;
    if closed {
        let mut v = signed_volume(&out);
        let bb = bbox_diagonal(&out.vertices);
        if v.abs() <= 1e-6 * bb * bb * bb {
            return Err(Error::input(
                file,
                format!("closed mesh encloses no volume ({v:.3e} m³ for a {bb:.3} m diagonal): a flat or self-cancelling mesh cannot be simulated"),
            ));
        }
        if v < 0.0 {
            for f in &mut out.faces {
                f.swap(1, 2);
            }
            v = -v;
            repairs.push("flipped all faces (the mesh was inside out: negative enclosed volume)".into());
        }
        volume = Some(v);
    }
    let report = MeshReport {
        vertices: out.vertices.len(),
        faces: out.faces.len(),
        boundary_edges: topo.boundary_edges,
        components: topo.components,
        closed,
        volume_m3: volume,
        area_m2: area,
        repairs,
    };
    Ok((out, report))
}

/// Signed enclosed volume (positive for outward-oriented closed meshes).
pub fn signed_volume(mesh: &Mesh) -> f64 {
    mesh.faces
        .iter()
        .map(|f| {
            let [a, b, c] = f.map(|i| mesh.vertices[i as usize].map(|x| x as f64));
            (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0])) / 6.0
        })
        .sum()
}

pub(crate) fn bbox_diagonal(v: &[[f32; 3]]) -> f64 {
    let (lo, hi) = bbox(v);
    ((0..3).map(|k| ((hi[k] - lo[k]) as f64).powi(2)).sum::<f64>()).sqrt()
}

pub(crate) fn bbox(v: &[[f32; 3]]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in v {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (lo, hi)
}

/// Choose solid or shell and compute the mass properties. `mass_kg`, when
/// given, rescales the density so the total mass matches.
pub fn annotate(
    mesh: &Mesh,
    report: &MeshReport,
    choice: TreatmentChoice,
    density_kg_m3: f64,
    shell_thickness_m: f64,
    mass_kg: Option<f64>,
    file: &str,
) -> Result<Inertial> {
    let (treatment, reason) = match (choice, report.closed) {
        (TreatmentChoice::Auto, true) => (Treatment::Solid, "auto: closed mesh".to_string()),
        (TreatmentChoice::Auto, false) => {
            (Treatment::Shell, format!("auto: open mesh ({} boundary edges), treated as a thin-walled shell", report.boundary_edges))
        }
        (TreatmentChoice::Solid, true) => (Treatment::Solid, "requested".to_string()),
        (TreatmentChoice::Solid, false) => {
            return Err(Error::input(
                file,
                format!(
                    "treatment \"solid\" requested but the mesh is open ({} boundary edges): it has no volume; use \"shell\" or \"auto\"",
                    report.boundary_edges
                ),
            ))
        }
        (TreatmentChoice::Shell, _) => (Treatment::Shell, "requested".to_string()),
    };
    let (mut mass, com, mut inertia) = match treatment {
        Treatment::Solid => solid_mass_properties(mesh, density_kg_m3),
        Treatment::Shell => shell_mass_properties(mesh, density_kg_m3 * shell_thickness_m),
    };
    if !(mass.is_finite() && mass > 0.0) {
        return Err(Error::input(file, format!("mesh gives a non-positive mass ({mass} kg)")));
    }
    let mut density = density_kg_m3;
    if let Some(m) = mass_kg {
        let k = m / mass;
        density *= k;
        mass = m;
        inertia = inertia.map(|r| r.map(|x| x * k));
    }
    Ok(Inertial {
        treatment,
        treatment_reason: reason,
        mass_kg: mass,
        com,
        inertia,
        density_kg_m3: density,
        shell_thickness_m: (treatment == Treatment::Shell).then_some(shell_thickness_m),
    })
}

/// Solid mass properties with parry3d (mass, COM, inertia about the COM).
pub fn solid_mass_properties(mesh: &Mesh, density: f64) -> (f64, [f64; 3], [[f64; 3]; 3]) {
    use parry3d::mass_properties::MassProperties;
    use parry3d::math::Vector;
    // Centre the vertices first: parry works in f32 and the COM shift keeps
    // the tetrahedron sums well conditioned for meshes far from the origin.
    let (lo, hi) = bbox(&mesh.vertices);
    let c = [0, 1, 2].map(|k| 0.5 * (lo[k] + hi[k]));
    let pts: Vec<Vector> = mesh.vertices.iter().map(|v| Vector::new(v[0] - c[0], v[1] - c[1], v[2] - c[2])).collect();
    let mp = MassProperties::from_trimesh(density as f32, &pts, &mesh.faces);
    let i = mp.reconstruct_inertia_matrix();
    let cols = i.to_cols_array_2d();
    let inertia = std::array::from_fn(|r| std::array::from_fn(|k| cols[k][r] as f64));
    let com = [0, 1, 2].map(|k| (mp.local_com[k] + c[k]) as f64);
    (mp.mass() as f64, com, inertia)
}

/// Thin-shell mass properties with areal density `sigma` (kg/m²): each
/// triangle is a uniform lamina with `∫ x xᵀ dA = A/12 (Σ vᵢvᵢᵀ + s sᵀ)`,
/// `s = Σ vᵢ`.
pub fn shell_mass_properties(mesh: &Mesh, sigma: f64) -> (f64, [f64; 3], [[f64; 3]; 3]) {
    let mut m = 0.0;
    let mut first = [0.0; 3];
    let mut second = [[0.0; 3]; 3];
    for f in &mesh.faces {
        let a = face_area(&mesh.vertices, f) * sigma;
        let v = f.map(|i| mesh.vertices[i as usize].map(|x| x as f64));
        let s = [0, 1, 2].map(|k| v[0][k] + v[1][k] + v[2][k]);
        m += a;
        for k in 0..3 {
            first[k] += a * s[k] / 3.0;
        }
        for r in 0..3 {
            for c in 0..3 {
                second[r][c] += a / 12.0 * (v.iter().map(|p| p[r] * p[c]).sum::<f64>() + s[r] * s[c]);
            }
        }
    }
    let com = first.map(|x| x / m);
    // Second moment about the COM, then inertia = tr(S)·I − S.
    let sc: [[f64; 3]; 3] = std::array::from_fn(|r| std::array::from_fn(|c| second[r][c] - m * com[r] * com[c]));
    let tr = sc[0][0] + sc[1][1] + sc[2][2];
    let inertia = std::array::from_fn(|r| std::array::from_fn(|c| if r == c { tr - sc[r][c] } else { -sc[r][c] }));
    (m, com, inertia)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub use recon_testkit::meshes::box_at;

    /// The box without its top (z+) faces: an open tray.
    pub fn tray_mesh(half: [f32; 3]) -> Mesh {
        let mut m = box_at(half, [0.0; 3]);
        m.faces.drain(2..4);
        m
    }

    /// UV sphere, closed, outward.
    pub fn sphere_mesh(r: f32, rings: usize, segs: usize) -> Mesh {
        let mut vertices = vec![[0.0, 0.0, r]];
        for i in 1..rings {
            let th = std::f32::consts::PI * i as f32 / rings as f32;
            for j in 0..segs {
                let ph = std::f32::consts::TAU * j as f32 / segs as f32;
                vertices.push([r * th.sin() * ph.cos(), r * th.sin() * ph.sin(), r * th.cos()]);
            }
        }
        vertices.push([0.0, 0.0, -r]);
        let s = segs as u32;
        let last = vertices.len() as u32 - 1;
        let mut faces = Vec::new();
        for j in 0..s {
            faces.push([0, 1 + j, 1 + (j + 1) % s]);
        }
        for i in 0..(rings as u32 - 2) {
            for j in 0..s {
                let (a, b) = (1 + i * s + j, 1 + i * s + (j + 1) % s);
                let (c, d) = (a + s, b + s);
                faces.push([a, c, b]);
                faces.push([b, c, d]);
            }
        }
        let base = 1 + (rings as u32 - 2) * s;
        for j in 0..s {
            faces.push([base + j, last, base + (j + 1) % s]);
        }
        Mesh { vertices, faces, vertex_attrs: None }
    }

    fn close(a: f64, b: f64, rel: f64) -> bool {
        (a - b).abs() <= rel * b.abs().max(1e-12)
    }

    #[test]
    fn solid_box_matches_analytic_mass_and_inertia() {
        let (hx, hy, hz) = (0.05f32, 0.03, 0.1);
        let m = box_at([hx, hy, hz], [0.2, -0.1, 0.3]);
        let (mesh, rep) = check_mesh(&m, "box").unwrap();
        assert!(rep.closed && rep.repairs.is_empty());
        assert!(close(rep.volume_m3.unwrap(), 8.0 * (hx * hy * hz) as f64, 1e-5));
        let inert = annotate(&mesh, &rep, TreatmentChoice::Auto, 500.0, 0.002, None, "box").unwrap();
        assert_eq!(inert.treatment, Treatment::Solid);
        let mass = 500.0 * 8.0 * (hx * hy * hz) as f64;
        assert!(close(inert.mass_kg, mass, 1e-5), "{}", inert.mass_kg);
        assert!((0..3).all(|k| (inert.com[k] - [0.2, -0.1, 0.3][k]).abs() < 1e-6), "{:?}", inert.com);
        let (a, b, c) = (2.0 * hx as f64, 2.0 * hy as f64, 2.0 * hz as f64);
        let want = [mass / 12.0 * (b * b + c * c), mass / 12.0 * (a * a + c * c), mass / 12.0 * (a * a + b * b)];
        for k in 0..3 {
            assert!(close(inert.inertia[k][k], want[k], 1e-4), "I{k}{k} {} vs {}", inert.inertia[k][k], want[k]);
        }
        assert!(inert.inertia[0][1].abs() < 1e-9 && inert.inertia[1][2].abs() < 1e-9);
        // Mass override rescales density and inertia together.
        let o = annotate(&mesh, &rep, TreatmentChoice::Auto, 500.0, 0.002, Some(2.0), "box").unwrap();
        assert!(close(o.mass_kg, 2.0, 1e-12) && close(o.inertia[2][2], want[2] * 2.0 / mass, 1e-4));
    }

    #[test]
    fn open_tray_is_a_shell_with_lamina_inertia() {
        let h = [0.1f32, 0.1, 0.05];
        let (mesh, rep) = check_mesh(&tray_mesh(h), "tray").unwrap();
        assert!(!rep.closed && rep.boundary_edges == 4 && rep.volume_m3.is_none());
        let sigma_rho = 1000.0;
        let t = 0.002;
        let i = annotate(&mesh, &rep, TreatmentChoice::Auto, sigma_rho, t, None, "tray").unwrap();
        assert_eq!(i.treatment, Treatment::Shell);
        assert!(i.treatment_reason.contains("open mesh"));
        // Bottom 0.2×0.2 + four walls 0.2×0.1 = 0.12 m².
        assert!(close(i.mass_kg, 0.12 * t * sigma_rho, 1e-5), "{}", i.mass_kg);
        // COM: bottom (0.04 m² at z = −0.05), walls (0.08 m² at z = 0) → z = −0.05·0.04/0.12.
        assert!((i.com[2] - (-0.05 * 0.04 / 0.12)).abs() < 1e-6, "{:?}", i.com);
        // Solid requested on an open mesh is refused.
        let e = annotate(&mesh, &rep, TreatmentChoice::Solid, 1000.0, t, None, "tray.ply").unwrap_err().to_string();
        assert!(e.contains("tray.ply") && e.contains("open"), "{e}");
    }

    #[test]
    fn sphere_shell_inertia_is_two_thirds_m_r2() {
        let r = 0.1;
        let (mesh, rep) = check_mesh(&sphere_mesh(r, 48, 96), "sphere").unwrap();
        let i = annotate(&mesh, &rep, TreatmentChoice::Shell, 1000.0, 0.001, None, "sphere").unwrap();
        let want = 2.0 / 3.0 * i.mass_kg * (r as f64).powi(2);
        for k in 0..3 {
            assert!(close(i.inertia[k][k], want, 3e-3), "{} vs {want}", i.inertia[k][k]);
        }
        // The solid sphere is 2/5 m r².
        let s = annotate(&mesh, &rep, TreatmentChoice::Auto, 1000.0, 0.001, None, "sphere").unwrap();
        assert!(close(s.inertia[2][2], 0.4 * s.mass_kg * (r as f64).powi(2), 3e-3));
    }

    #[test]
    fn repairs_are_explicit_and_bad_meshes_refused() {
        // Inside-out box with split (duplicated) vertices and a degenerate face.
        let b = box_at([0.1; 3], [0.0; 3]);
        let mut split = Mesh::default();
        for f in &b.faces {
            let base = split.vertices.len() as u32;
            split.vertices.extend(f.map(|i| b.vertices[i as usize]));
            split.faces.push([base, base + 2, base + 1]);
        }
        split.faces.push([0, 0, 1]);
        let (m, rep) = check_mesh(&split, "split").unwrap();
        assert_eq!(m.vertices.len(), 8);
        assert_eq!(m.faces.len(), 12);
        assert!(rep.closed);
        assert!(rep.volume_m3.unwrap() > 0.0);
        let joined = rep.repairs.join("; ");
        assert!(joined.contains("welded 28") && joined.contains("degenerate") && joined.contains("flipped"), "{joined}");

        // Non-manifold: a third face on an edge.
        let mut nm = box_at([0.1; 3], [0.0; 3]);
        nm.vertices.push([0.5, 0.5, 0.5]);
        nm.faces.push([0, 1, 8]);
        let e = check_mesh(&nm, "nm.ply").unwrap_err().to_string();
        assert!(e.contains("nm.ply") && e.contains("non-manifold"), "{e}");

        // Zero volume: a tetrahedron collapsed into a plane (closed, manifold, no inside).
        let flat = Mesh {
            vertices: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, 0.3, 0.0]],
            faces: vec![[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]],
            vertex_attrs: None,
        };
        let e = check_mesh(&flat, "flat.ply").unwrap_err().to_string();
        assert!(e.contains("flat.ply") && e.contains("no volume"), "{e}");

        // Misoriented: one face of the box reversed.
        let mut mo = box_at([0.1; 3], [0.0; 3]);
        mo.faces[0].swap(1, 2);
        let e = check_mesh(&mo, "mo.ply").unwrap_err().to_string();
        assert!(e.contains("oriented inconsistently"), "{e}");
        let mut nan = box_at([0.1; 3], [0.0; 3]);
        nan.vertices[3][1] = f32::NAN;
        assert!(check_mesh(&nan, "nan.ply").unwrap_err().to_string().contains("non-finite"));
    }
}
