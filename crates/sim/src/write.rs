//! The scene's output folder: meshes, collision hulls, URDF, MJCF, USD and GLB,
//! written through a staging folder with the index last.

use crate::scene::*;
use recon_core::mesh::Mesh;
use recon_core::{Error, Result};
use serde::Serialize;
use std::path::Path;

/// Index file written last into every `recon scene` output folder; its
/// presence marks a complete output.
pub const MARKER: &str = "recon-scene.json";

/// Paths of what [`write_outputs`] wrote, relative to the output folder.
#[derive(Debug, Clone, Serialize)]
pub struct Written {
    /// The scene file (`scene.json`).
    pub scene_json: &'static str,
    /// The URDF world.
    pub urdf_scene: &'static str,
    /// One URDF per object.
    pub urdf_objects: Vec<String>,
    /// The MJCF (MuJoCo) scene.
    pub mjcf: &'static str,
    /// The USD scene.
    pub usd: &'static str,
    /// The GLB of the settled scene.
    pub glb: &'static str,
    /// Absent for outputs written without wall-clock timings.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub timings: Option<&'static str>,
}

/// Write the settled scene (scene.json, meshes, URDF, MJCF, USD, GLB and the
/// report) to a staging folder, then move it to `out`. An existing `out` is
/// replaced only when it is an earlier `recon scene` output.
pub fn write_outputs(scene: &mut SimScene, out: &Path) -> Result<Written> {
    write_outputs_with(scene, out, true)
}

/// [`write_outputs`]; without `timings` no `timings.json` is written, so
/// the folder depends on its inputs only (byte-identical for a fixed seed).
pub fn write_outputs_with(scene: &mut SimScene, out: &Path, timings: bool) -> Result<Written> {
    let t0 = std::time::Instant::now();
    let staging = recon_core::engine::output::begin_output_marked(out, MARKER)?;
    let mkdir = |p: &Path| std::fs::create_dir_all(p).map_err(|e| Error::io(p, e));
    let write = |p: &Path, bytes: &[u8]| std::fs::write(p, bytes).map_err(|e| Error::io(p, e));
    mkdir(&staging.join("urdf"))?;
    for o in &scene.objects {
        let dir = staging.join("meshes").join(&o.id);
        mkdir(&dir)?;
        match &o.textured {
            // visual.obj with `vt`, visual.mtl (`map_Kd texture.png`) and texture.png.
            Some(tm) => recon_core::export::obj::save_textured_obj(tm, &dir, "visual", TEXTURE_FILE, recon_core::export::Axes::ZUp)?,
            None => recon_core::export::obj::save_obj(&o.visual, &dir.join("visual.obj"), recon_core::export::Axes::ZUp, false)?,
        }
        recon_core::export::ply::save_mesh_ply(&o.visual, &dir.join("visual.ply"), &recon_core::export::ply::PlyOptions::default())?;
        for (k, part) in o.collision.parts.iter().enumerate() {
            if let crate::collision::Part::Hull(m) = part {
                recon_core::export::obj::save_obj(m, &dir.join(hull_file(k)), recon_core::export::Axes::ZUp, false)?;
            }
        }
    }
    let mut urdf_objects = Vec::new();
    for o in &scene.objects {
        let name = format!("urdf/{}.urdf", o.id);
        write(&staging.join(&name), crate::urdf::object_urdf(o, "../meshes").as_bytes())?;
        urdf_objects.push(name);
    }
    write(&staging.join("urdf/scene.urdf"), crate::urdf::scene_urdf(scene, "../meshes").as_bytes())?;
    write(&staging.join("scene.xml"), crate::mjcf::scene_mjcf(scene, "meshes").as_bytes())?;
    write(&staging.join("scene.usda"), crate::usd::scene_usda(scene).as_bytes())?;
    // One node per object, placed in the world, with the object's colour as its material.
    let placed: Vec<Mesh> = scene.objects.iter().map(|o| o.end.apply_mesh(&o.visual)).collect();
    let nodes: Vec<(&str, &Mesh, Option<[f32; 4]>)> =
        scene.objects.iter().zip(&placed).map(|(o, m)| (o.id.as_str(), m, o.color_rgba)).collect();
    // glTF is y-up; the world is z-up.
    let glb = recon_core::export::glb::colored_meshes_glb_bytes(
        &nodes,
        &recon_core::export::GlbOptions { axes: recon_core::export::Axes::YUp, vertex_colors: false },
    )?;
    write(&staging.join("scene.glb"), &glb)?;
    let settled = scene.settled_scene_file();
    write(&staging.join("scene.json"), settled.to_json()?.as_bytes())?;
    let input_path = staging.join("scene.input.json");
    write(&input_path, scene.input.to_json()?.as_bytes())?;
    let written = Written {
        scene_json: "scene.json",
        urdf_scene: "urdf/scene.urdf",
        urdf_objects,
        mjcf: "scene.xml",
        usd: "scene.usda",
        glb: "scene.glb",
        timings: timings.then_some("timings.json"),
    };
    if timings {
        scene.timings.export_s = t0.elapsed().as_secs_f64();
        let timings = serde_json::to_string_pretty(&scene.timings).map_err(|e| Error::msg(e.to_string()))?;
        write(&staging.join("timings.json"), timings.as_bytes())?;
    }
    let report = serde_json::json!({
        "version": 1,
        "world": "metres; gravity along -z; support plane z = 0",
        "support_plane": { "material": scene.plane, "fit": scene.input.support_plane.fit },
        "settle": {
            "options": scene.options.settle,
            "simulated_s": scene.settle.simulated_s,
            "depenetration_s": scene.settle.depenetration_s,
            "steps": scene.settle.steps,
            "at_rest": scene.settle.at_rest,
        },
        "collision_method": scene.options.collision,
        "objects": scene.summaries(),
        "files": written,
        "recon_version": recon_core::VERSION,
    });
    recon_core::engine::output::finish_output_marked(&staging, out, MARKER, &report)?;
    Ok(written)
}
