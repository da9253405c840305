//! URDF export of a settled scene: one robot file per object (a single
//! link: inertial at the centre of mass, visual mesh, one collision element
//! per convex part or primitive, pybullet's `<contact>` friction and
//! restitution), and a scene file whose `world` link carries the support
//! plane and holds every object by a floating joint at its settled pose.

use crate::collision::{Part, Primitive};
use crate::scene::{hull_file, SimObject, SimScene};
use std::fmt::Write as _;

/// Roll, pitch, yaw (URDF: `R = Rz(yaw)·Ry(pitch)·Rx(roll)`) of a rotation.
pub fn rpy(r: &[[f32; 3]; 3]) -> [f64; 3] {
    let r = r.map(|row| row.map(|x| x as f64));
    let sp = (-r[2][0]).clamp(-1.0, 1.0);
    let pitch = sp.asin();
    if sp.abs() > 1.0 - 1e-9 {
        // Gimbal lock: only yaw − roll (or yaw + roll) is defined; put it in yaw.
        let yaw = (-r[0][1]).atan2(r[1][1]);
        return [0.0, pitch, yaw];
    }
    [r[2][1].atan2(r[2][2]), pitch, r[1][0].atan2(r[0][0])]
}

fn origin(xyz: [f32; 3], r: &[[f32; 3]; 3]) -> String {
    let a = rpy(r);
    format!("<origin xyz=\"{} {} {}\" rpy=\"{} {} {}\"/>", xyz[0], xyz[1], xyz[2], a[0], a[1], a[2])
}

const IDENTITY: [[f32; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

fn link(o: &SimObject, mesh_dir: &str) -> String {
    let i = &o.inertial.inertia;
    let mut s = String::new();
    let _ = writeln!(s, "  <link name=\"{}\">", o.id);
    let _ = writeln!(s, "    <inertial>");
    let _ = writeln!(s, "      {}", origin([0.0; 3], &IDENTITY));
    let _ = writeln!(s, "      <mass value=\"{}\"/>", o.inertial.mass_kg);
    let _ = writeln!(
        s,
        "      <inertia ixx=\"{}\" ixy=\"{}\" ixz=\"{}\" iyy=\"{}\" iyz=\"{}\" izz=\"{}\"/>",
        i[0][0], i[0][1], i[0][2], i[1][1], i[1][2], i[2][2]
    );
    let _ = writeln!(s, "    </inertial>");
    // The material's (or the object's) colour; URDF names materials, so the name is the object's.
    // A textured object: white times its texture (the OBJ's MTL names it too, for pybullet).
    let color = match &o.textured {
        Some(_) => format!(
            "\n      <material name=\"{}_{}\"><color rgba=\"1 1 1 {}\"/><texture filename=\"{mesh_dir}/{}/{}\"/></material>",
            o.id,
            o.material,
            o.color_rgba.map_or(1.0, |c| c[3]),
            o.id,
            crate::scene::TEXTURE_FILE
        ),
        None => o
            .color_rgba
            .map(|c| {
                format!(
                    "\n      <material name=\"{}_{}\"><color rgba=\"{} {} {} {}\"/></material>",
                    o.id, o.material, c[0], c[1], c[2], c[3]
                )
            })
            .unwrap_or_default(),
    };
    let _ = writeln!(
        s,
        "    <visual>\n      {}\n      <geometry><mesh filename=\"{mesh_dir}/{}/visual.obj\"/></geometry>{color}\n    </visual>",
        origin([0.0; 3], &IDENTITY),
        o.id
    );
    for (k, p) in o.collision.parts.iter().enumerate() {
        let (org, geom) = match p {
            Part::Hull(_) => (origin([0.0; 3], &IDENTITY), format!("<mesh filename=\"{mesh_dir}/{}/{}\"/>", o.id, hull_file(k))),
            Part::Primitive(Primitive::Box { center, rotation, half_extents: h }) => {
                (origin(*center, rotation), format!("<box size=\"{} {} {}\"/>", 2.0 * h[0], 2.0 * h[1], 2.0 * h[2]))
            }
            Part::Primitive(Primitive::Cylinder { center, rotation, radius, half_height }) => {
                (origin(*center, rotation), format!("<cylinder radius=\"{radius}\" length=\"{}\"/>", 2.0 * half_height))
            }
            Part::Primitive(Primitive::Sphere { center, radius }) => (origin(*center, &IDENTITY), format!("<sphere radius=\"{radius}\"/>")),
        };
        let _ =
            writeln!(s, "    <collision name=\"{}_part{k:02}\">\n      {org}\n      <geometry>{geom}</geometry>\n    </collision>", o.id);
    }
    // pybullet reads friction/restitution from <contact>; other consumers ignore it.
    let _ = writeln!(
        s,
        "    <contact>\n      <lateral_friction value=\"{}\"/>\n      <restitution value=\"{}\"/>\n    </contact>",
        o.friction, o.restitution
    );
    let _ = writeln!(s, "  </link>");
    s
}

/// One object as its own robot; mesh paths are `<mesh_dir>/<id>/…`.
pub fn object_urdf(o: &SimObject, mesh_dir: &str) -> String {
    let mut s = String::from("<?xml version=\"1.0\"?>\n");
    let _ = writeln!(
        s,
        "<!-- recon scene: {} ({}), material {}, {:?} mass model; link frame at the centre of mass -->",
        xml_escape(&o.name),
        xml_escape(&o.category),
        o.material,
        o.inertial.treatment
    );
    let _ = writeln!(s, "<robot name=\"{}\">", o.id);
    s += &link(o, mesh_dir);
    s += "</robot>\n";
    s
}

/// The whole scene: `world` link with the support plane (a 2 m slab whose
/// top face is z = 0), every object on a floating joint at its settled pose.
pub fn scene_urdf(scene: &SimScene, mesh_dir: &str) -> String {
    let mut s = String::from(
        "<?xml version=\"1.0\"?>\n<!-- recon scene: settled; world frame z up, support plane z = 0 -->\n<robot name=\"scene\">\n",
    );
    let _ = writeln!(
        s,
        "  <link name=\"world\">\n    <collision name=\"support_plane\">\n      <origin xyz=\"0 0 -0.01\" rpy=\"0 0 0\"/>\n      <geometry><box size=\"2 2 0.02\"/></geometry>\n    </collision>\n    <contact>\n      <lateral_friction value=\"{}\"/>\n      <restitution value=\"{}\"/>\n    </contact>\n  </link>",
        scene.plane.friction, scene.plane.restitution
    );
    for o in &scene.objects {
        s += &link(o, mesh_dir);
        let _ = writeln!(
            s,
            "  <joint name=\"{}_float\" type=\"floating\">\n    <parent link=\"world\"/>\n    <child link=\"{}\"/>\n    {}\n  </joint>",
            o.id,
            o.id,
            origin(o.end.translation, &o.end.rotation)
        );
    }
    s += "</robot>\n";
    s
}

pub(crate) fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;").replace("--", "- -")
}

#[cfg(test)]
mod tests {
    use super::*;
    use recon_core::math::axis_angle;

    #[test]
    fn rpy_reconstructs_the_rotation() {
        for (axis, angle) in
            [([0.3, -0.5, 0.8], 0.7), ([1.0, 0.0, 0.0], 2.0), ([0.0, 1.0, 0.0], std::f64::consts::FRAC_PI_2), ([0.2, 0.9, -0.1], -2.5)]
        {
            let r = axis_angle(axis, angle).map(|row| row.map(|x| x as f32));
            let [ro, pi, ya] = rpy(&r);
            let rx = axis_angle([1.0, 0.0, 0.0], ro);
            let ry = axis_angle([0.0, 1.0, 0.0], pi);
            let rz = axis_angle([0.0, 0.0, 1.0], ya);
            let m = |a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]| -> [[f64; 3]; 3] {
                std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
            };
            let back = m(&m(&rz, &ry), &rx);
            for i in 0..3 {
                for j in 0..3 {
                    assert!((back[i][j] - r[i][j] as f64).abs() < 1e-5, "{axis:?} {angle}: {back:?} vs {r:?}");
                }
            }
        }
    }
}
