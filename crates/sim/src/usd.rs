//! USD (usda text) export of a settled scene with the UsdPhysics schemas:
//! a `PhysicsScene` (gravity −z), one rigid body per object
//! (`PhysicsRigidBodyAPI` + `PhysicsMassAPI`: mass, centre of mass at the
//! body origin, principal inertia and axes), its visual mesh, and one
//! collider per convex part (`PhysicsCollisionAPI` +
//! `PhysicsMeshCollisionAPI`, approximation `convexHull`) or primitive
//! (Cube/Cylinder/Sphere with `PhysicsCollisionAPI`), every collider bound
//! to a per-object `PhysicsMaterialAPI` material. The support plane is a
//! static 2 m slab whose top face is z = 0. Stage: z up, metres, kilograms.
//! A textured object's visual mesh carries its UVs as the `st` primvar and is
//! bound (`material:binding`) to a `UsdPreviewSurface` material under
//! `/World/Looks` whose diffuse colour is a `UsdUVTexture` of its PNG, read
//! through a `UsdPrimvarReader_float2` of `st`.

use crate::collision::{Part, Primitive};
use crate::scene::SimScene;
use recon_core::math::matrix_to_quat;
use recon_core::mesh::Mesh;
use std::fmt::Write as _;

fn mesh_body(s: &mut String, m: &Mesh, indent: &str) {
    let pts: Vec<String> = m.vertices.iter().map(|v| format!("({}, {}, {})", v[0], v[1], v[2])).collect();
    let idx: Vec<String> = m.faces.iter().flatten().map(|i| i.to_string()).collect();
    let _ = writeln!(s, "{indent}int[] faceVertexCounts = [{}]", vec!["3"; m.faces.len()].join(", "));
    let _ = writeln!(s, "{indent}int[] faceVertexIndices = [{}]", idx.join(", "));
    let _ = writeln!(s, "{indent}point3f[] points = [{}]", pts.join(", "));
    let _ = writeln!(s, "{indent}uniform token subdivisionScheme = \"none\"");
}

fn quat_str(q: [f32; 4]) -> String {
    format!("({}, {}, {}, {})", q[0], q[1], q[2], q[3])
}

fn xform(s: &mut String, t: [f32; 3], r: &[[f32; 3]; 3], scale: Option<[f32; 3]>, indent: &str) {
    let _ = writeln!(s, "{indent}double3 xformOp:translate = ({}, {}, {})", t[0], t[1], t[2]);
    let _ = writeln!(s, "{indent}quatf xformOp:orient = {}", quat_str(matrix_to_quat(r)));
    match scale {
        Some(k) => {
            let _ = writeln!(s, "{indent}float3 xformOp:scale = ({}, {}, {})", k[0], k[1], k[2]);
            let _ = writeln!(s, "{indent}uniform token[] xformOpOrder = [\"xformOp:translate\", \"xformOp:orient\", \"xformOp:scale\"]");
        }
        None => {
            let _ = writeln!(s, "{indent}uniform token[] xformOpOrder = [\"xformOp:translate\", \"xformOp:orient\"]");
        }
    }
}

const IDENTITY: [[f32; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// The `UsdPreviewSurface` material of a textured object, `/World/Looks/<id>`.
fn texture_material(s: &mut String, id: &str) {
    let at = format!("/World/Looks/{id}");
    let _ = writeln!(s, "        def Material \"{id}\"\n        {{");
    let _ = writeln!(s, "            token outputs:surface.connect = <{at}/PreviewSurface.outputs:surface>\n");
    let _ = writeln!(
        s,
        "            def Shader \"PreviewSurface\"\n            {{\n                uniform token info:id = \"UsdPreviewSurface\""
    );
    let _ = writeln!(s, "                color3f inputs:diffuseColor.connect = <{at}/Texture.outputs:rgb>");
    let _ = writeln!(s, "                float inputs:metallic = 0\n                float inputs:roughness = 1\n                token outputs:surface\n            }}\n");
    let _ = writeln!(s, "            def Shader \"Texture\"\n            {{\n                uniform token info:id = \"UsdUVTexture\"");
    let _ = writeln!(s, "                asset inputs:file = @meshes/{id}/{}@", crate::scene::TEXTURE_FILE);
    let _ = writeln!(s, "                token inputs:sourceColorSpace = \"sRGB\"");
    let _ = writeln!(s, "                float2 inputs:st.connect = <{at}/StReader.outputs:result>");
    let _ = writeln!(s, "                token inputs:wrapS = \"clamp\"\n                token inputs:wrapT = \"clamp\"\n                float3 outputs:rgb\n            }}\n");
    let _ = writeln!(
        s,
        "            def Shader \"StReader\"\n            {{\n                uniform token info:id = \"UsdPrimvarReader_float2\""
    );
    let _ =
        writeln!(s, "                string inputs:varname = \"st\"\n                float2 outputs:result\n            }}\n        }}");
}

/// The scene as a usda document.
pub fn scene_usda(scene: &SimScene) -> String {
    let mut s = String::from("#usda 1.0\n(\n    defaultPrim = \"World\"\n    doc = \"recon scene: settled, simulation-ready\"\n    kilogramsPerUnit = 1\n    metersPerUnit = 1\n    upAxis = \"Z\"\n)\n\n");
    s += "def Xform \"World\"\n{\n";
    s += "    def PhysicsScene \"PhysicsScene\"\n    {\n        vector3f physics:gravityDirection = (0, 0, -1)\n        float physics:gravityMagnitude = 9.81\n    }\n\n";
    s += "    def Scope \"PhysicsMaterials\"\n    {\n";
    let material = |s: &mut String, name: &str, friction: f64, restitution: f64, density: Option<f64>| {
        let _ = writeln!(
            s,
            "        def Material \"{name}\" (\n            prepend apiSchemas = [\"PhysicsMaterialAPI\"]\n        )\n        {{"
        );
        if let Some(d) = density {
            let _ = writeln!(s, "            float physics:density = {d}");
        }
        let _ = writeln!(
            s,
            "            float physics:dynamicFriction = {friction}\n            float physics:restitution = {restitution}\n            float physics:staticFriction = {friction}\n        }}"
        );
    };
    material(&mut s, "support_plane", scene.plane.friction, scene.plane.restitution, None);
    for o in &scene.objects {
        material(&mut s, &o.id, o.friction, o.restitution, Some(o.inertial.density_kg_m3));
    }
    s += "    }\n\n";
    s += "    def Cube \"support_plane\" (\n        prepend apiSchemas = [\"PhysicsCollisionAPI\", \"MaterialBindingAPI\"]\n    )\n    {\n";
    s += "        rel material:binding:physics = </World/PhysicsMaterials/support_plane>\n        double size = 1\n";
    xform(&mut s, [0.0, 0.0, -0.01], &IDENTITY, Some([2.0, 2.0, 0.02]), "        ");
    s += "    }\n";
    if scene.objects.iter().any(|o| o.textured.is_some()) {
        s += "\n    def Scope \"Looks\"\n    {\n";
        for o in scene.objects.iter().filter(|o| o.textured.is_some()) {
            texture_material(&mut s, &o.id);
        }
        s += "    }\n";
    }
    for o in &scene.objects {
        let (moments, axes) = o.principal_inertia();
        let axes32 = axes.map(|r| r.map(|x| x as f32));
        let _ = writeln!(
            s,
            "\n    def Xform \"{}\" (\n        prepend apiSchemas = [\"PhysicsRigidBodyAPI\", \"PhysicsMassAPI\"]\n    )\n    {{",
            o.id
        );
        let _ = writeln!(s, "        custom string recon:name = \"{}\"", o.name.replace('\\', "\\\\").replace('"', "\\\""));
        let _ = writeln!(s, "        custom string recon:massModel = \"{:?}\"", o.inertial.treatment);
        let _ = writeln!(s, "        custom string recon:material = \"{}\"", o.material.replace('\\', "\\\\").replace('"', "\\\""));
        let _ = writeln!(s, "        point3f physics:centerOfMass = (0, 0, 0)");
        let _ = writeln!(s, "        float3 physics:diagonalInertia = ({}, {}, {})", moments[0], moments[1], moments[2]);
        let _ = writeln!(s, "        float physics:mass = {}", o.inertial.mass_kg);
        let _ = writeln!(s, "        quatf physics:principalAxes = {}", quat_str(matrix_to_quat(&axes32)));
        xform(&mut s, o.end.translation, &o.end.rotation, None, "        ");
        match &o.textured {
            Some(tm) => {
                s += "\n        def Mesh \"visual\" (\n            prepend apiSchemas = [\"MaterialBindingAPI\"]\n        )\n        {\n";
                let _ = writeln!(s, "            rel material:binding = </World/Looks/{}>", o.id);
                mesh_body(&mut s, &tm.atlas.mesh, "            ");
                // USD's st has v up.
                let st: Vec<String> = tm.atlas.uv.iter().map(|t| format!("({}, {})", t[0], 1.0 - t[1])).collect();
                let _ = writeln!(
                    s,
                    "            texCoord2f[] primvars:st = [{}] (\n                interpolation = \"vertex\"\n            )",
                    st.join(", ")
                );
            }
            None => {
                s += "\n        def Mesh \"visual\"\n        {\n";
                mesh_body(&mut s, &o.visual, "            ");
            }
        }
        if let Some(c) = o.color_rgba {
            let _ = writeln!(s, "            color3f[] primvars:displayColor = [({}, {}, {})]", c[0], c[1], c[2]);
            let _ = writeln!(s, "            float[] primvars:displayOpacity = [{}]", c[3]);
        }
        s += "        }\n";
        for (k, p) in o.collision.parts.iter().enumerate() {
            let bind = format!(
                "            rel material:binding:physics = </World/PhysicsMaterials/{}>\n            uniform token purpose = \"guide\"\n",
                o.id
            );
            match p {
                Part::Hull(m) => {
                    let _ = writeln!(
                        s,
                        "\n        def Mesh \"collision_{k:02}\" (\n            prepend apiSchemas = [\"PhysicsCollisionAPI\", \"PhysicsMeshCollisionAPI\", \"MaterialBindingAPI\"]\n        )\n        {{"
                    );
                    s += &bind;
                    s += "            uniform token physics:approximation = \"convexHull\"\n";
                    mesh_body(&mut s, m, "            ");
                }
                Part::Primitive(pr) => {
                    let kind = match pr {
                        Primitive::Box { .. } => "Cube",
                        Primitive::Cylinder { .. } => "Cylinder",
                        Primitive::Sphere { .. } => "Sphere",
                    };
                    let _ = writeln!(
                        s,
                        "\n        def {kind} \"collision_{k:02}\" (\n            prepend apiSchemas = [\"PhysicsCollisionAPI\", \"MaterialBindingAPI\"]\n        )\n        {{"
                    );
                    s += &bind;
                    let ind = "            ";
                    match *pr {
                        Primitive::Box { center, rotation, half_extents } => {
                            let _ = writeln!(s, "{ind}double size = 2");
                            xform(&mut s, center, &rotation, Some(half_extents), ind);
                        }
                        Primitive::Cylinder { center, rotation, radius, half_height } => {
                            let _ = writeln!(
                                s,
                                "{ind}uniform token axis = \"Z\"\n{ind}double height = {}\n{ind}double radius = {radius}",
                                2.0 * half_height
                            );
                            xform(&mut s, center, &rotation, None, ind);
                        }
                        Primitive::Sphere { center, radius } => {
                            let _ = writeln!(s, "{ind}double radius = {radius}");
                            xform(&mut s, center, &IDENTITY, None, ind);
                        }
                    }
                }
            }
            s += "        }\n";
        }
        s += "    }\n";
    }
    s += "}\n";
    s
}
