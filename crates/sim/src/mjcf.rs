//! MJCF (MuJoCo) export of a settled scene: an infinite ground plane at
//! z = 0, one free body per object at its settled pose with its explicit
//! inertial (centre of mass at the body origin, full inertia tensor), a
//! visual mesh geom that does not collide, and one collision geom per
//! convex part (mesh asset; MuJoCo collides with its convex hull, which is
//! the part itself) or primitive, carrying the object's friction.
//!
//! A textured object (`SimObject::textured`) gets a 2D `<texture>` (its PNG) and a
//! `<material>` on its visual geom; the UVs are the `vt` of its `visual.obj`.
//!
//! MuJoCo has no restitution coefficient (bounce comes from the contact
//! solver's `solref`), so restitution is recorded in a comment only.

use crate::collision::{Part, Primitive};
use crate::scene::{hull_file, SimScene, TEXTURE_FILE};
use crate::urdf::xml_escape;
use recon_core::math::matrix_to_quat;
use std::fmt::Write as _;

fn quat(r: &[[f32; 3]; 3]) -> String {
    let q = matrix_to_quat(r);
    format!("{} {} {} {}", q[0], q[1], q[2], q[3])
}

/// MuJoCo's friction triple: sliding, torsional, rolling.
fn friction(mu: f64) -> String {
    format!("{mu} 0.005 0.0001")
}

/// The scene as MJCF; mesh files are found under `mesh_dir` (relative to
/// the MJCF file).
pub fn scene_mjcf(scene: &SimScene, mesh_dir: &str) -> String {
    let mut s = String::new();
    s += "<!-- recon scene: settled; world frame z up, support plane z = 0; body frames at the centre of mass -->\n";
    s += "<mujoco model=\"recon_scene\">\n";
    // Inertials are explicit: geoms must not add mass (open visual meshes have no volume).
    // Textures sit beside their meshes (`texturedir` only when there is one: untextured scenes keep their bytes).
    let texturedir = if scene.objects.iter().any(|o| o.textured.is_some()) { format!(" texturedir=\"{mesh_dir}\"") } else { String::new() };
    let _ = writeln!(s, "  <compiler angle=\"radian\" meshdir=\"{mesh_dir}\"{texturedir} inertiafromgeom=\"false\" autolimits=\"true\"/>");
    s += "  <option gravity=\"0 0 -9.81\" timestep=\"0.002\"/>\n";
    s += "  <asset>\n";
    for o in &scene.objects {
        // Open meshes have no volume; "shell" lets MuJoCo process them (mass comes from <inertial>).
        let inertia = if o.mesh_report.closed { "" } else { " inertia=\"shell\"" };
        let _ = writeln!(s, "    <mesh name=\"{}_visual\" file=\"{}/visual.obj\"{inertia}/>", o.id, o.id);
        if o.textured.is_some() {
            // The OBJ's `vt` map the texture onto the visual mesh.
            let _ = writeln!(s, "    <texture name=\"{}_texture\" type=\"2d\" file=\"{}/{TEXTURE_FILE}\"/>", o.id, o.id);
            let _ = writeln!(s, "    <material name=\"{}_material\" texture=\"{}_texture\" specular=\"0\" shininess=\"0\"/>", o.id, o.id);
        }
        for (k, p) in o.collision.parts.iter().enumerate() {
            if matches!(p, Part::Hull(_)) {
                let _ = writeln!(s, "    <mesh name=\"{}_part{k:02}\" file=\"{}/{}\"/>", o.id, o.id, hull_file(k));
            }
        }
    }
    s += "  </asset>\n  <worldbody>\n";
    let _ =
        writeln!(s, "    <geom name=\"support_plane\" type=\"plane\" size=\"0 0 0.05\" friction=\"{}\"/>", friction(scene.plane.friction));
    s += "    <light name=\"top\" pos=\"0 0 2\" dir=\"0 0 -1\"/>\n";
    for o in &scene.objects {
        let t = o.end.translation;
        let i = &o.inertial.inertia;
        let _ = writeln!(
            s,
            "    <!-- {} ({}): material {}, {:?}, restitution {} (not modelled by MuJoCo) -->",
            xml_escape(&o.name),
            xml_escape(&o.category),
            o.material,
            o.inertial.treatment,
            o.restitution
        );
        let _ = writeln!(s, "    <body name=\"{}\" pos=\"{} {} {}\" quat=\"{}\">", o.id, t[0], t[1], t[2], quat(&o.end.rotation));
        let _ = writeln!(s, "      <freejoint name=\"{}_free\"/>", o.id);
        let _ = writeln!(
            s,
            "      <inertial pos=\"0 0 0\" mass=\"{}\" fullinertia=\"{} {} {} {} {} {}\"/>",
            o.inertial.mass_kg, i[0][0], i[1][1], i[2][2], i[0][1], i[0][2], i[1][2]
        );
        // A textured geom takes its colour from its material (a geom rgba would override it).
        let rgba = match &o.textured {
            Some(_) => format!(" material=\"{}_material\"", o.id),
            None => o.color_rgba.map(|c| format!(" rgba=\"{} {} {} {}\"", c[0], c[1], c[2], c[3])).unwrap_or_default(),
        };
        let _ = writeln!(
            s,
            "      <geom name=\"{}_visual\" type=\"mesh\" mesh=\"{}_visual\" contype=\"0\" conaffinity=\"0\" group=\"1\"{rgba}/>",
            o.id, o.id
        );
        let f = friction(o.friction);
        for (k, p) in o.collision.parts.iter().enumerate() {
            let name = format!("{}_part{k:02}", o.id);
            let _ = match p {
                Part::Hull(_) => writeln!(s, "      <geom name=\"{name}\" type=\"mesh\" mesh=\"{name}\" friction=\"{f}\" group=\"3\"/>"),
                Part::Primitive(Primitive::Box { center: c, rotation, half_extents: h }) => writeln!(
                    s,
                    "      <geom name=\"{name}\" type=\"box\" pos=\"{} {} {}\" quat=\"{}\" size=\"{} {} {}\" friction=\"{f}\" group=\"3\"/>",
                    c[0], c[1], c[2], quat(rotation), h[0], h[1], h[2]
                ),
                Part::Primitive(Primitive::Cylinder { center: c, rotation, radius, half_height }) => writeln!(
                    s,
                    "      <geom name=\"{name}\" type=\"cylinder\" pos=\"{} {} {}\" quat=\"{}\" size=\"{radius} {half_height}\" friction=\"{f}\" group=\"3\"/>",
                    c[0], c[1], c[2], quat(rotation)
                ),
                Part::Primitive(Primitive::Sphere { center: c, radius }) => writeln!(
                    s,
                    "      <geom name=\"{name}\" type=\"sphere\" pos=\"{} {} {}\" size=\"{radius}\" friction=\"{f}\" group=\"3\"/>",
                    c[0], c[1], c[2]
                ),
            };
        }
        s += "    </body>\n";
    }
    s += "  </worldbody>\n</mujoco>\n";
    s
}
