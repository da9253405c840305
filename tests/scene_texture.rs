//! Textures in the simulator formats (`recon scene --colour texture`, the default): a
//! box whose top is red at x < 0, y > 0, green at x > 0, y > 0 and blue elsewhere (vertex
//! colours) becomes a UV atlas and
//! a baked PNG that the OBJ + MTL, MJCF, USD and URDF refer to; MuJoCo renders the
//! colours at the object's pixels, usd-core resolves the material binding and texture,
//! pybullet loads the textured URDF. `--colour vertex` writes no texture.
//!
//! Python-backed checks skip with a printed reason when python3, the package or an
//! OpenGL context (MuJoCo's renderer: MUJOCO_GL=egl or osmesa) is missing, unless
//! RECON_REQUIRE_PYTHON_TESTS=1, where a missing mujoco or usd-core fails (a missing GL
//! context fails too).

mod common;

use common::tmp;
use recon::export::{save_mesh_ply, PlyOptions};
use recon::mesh::Mesh;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A closed box of side `s` from six `n`×`n` grids (shared edges weld by position).
fn coloured_box(s: f32, n: u32) -> Mesh {
    let mut m = Mesh::default();
    let mut index = std::collections::HashMap::new();
    let mut vid = |m: &mut Mesh, p: [f32; 3]| -> u32 {
        *index.entry(p.map(f32::to_bits)).or_insert_with(|| {
            m.vertices.push(p);
            m.vertices.len() as u32 - 1
        })
    };
    // Each face: its axis k, its side, and two in-plane axes (u × v points outwards).
    for (k, side, a, b) in [(0, 1.0, 1, 2), (0, -1.0, 2, 1), (1, 1.0, 2, 0), (1, -1.0, 0, 2), (2, 1.0, 0, 1), (2, -1.0, 1, 0)] {
        let at = |i: u32, j: u32| {
            let mut p = [0f32; 3];
            p[k] = side * s / 2.0;
            p[a] = (i as f32 / n as f32 - 0.5) * s;
            p[b] = (j as f32 / n as f32 - 0.5) * s;
            p
        };
        for i in 0..n {
            for j in 0..n {
                let q = [at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)].map(|p| vid(&mut m, p));
                m.faces.push([q[0], q[1], q[2]]);
                m.faces.push([q[0], q[2], q[3]]);
            }
        }
    }
    // The top face (z = s/2) at y > 0: red at x < 0, green at x > 0 (yellowish on x = 0);
    // everything else blue, so a texture read from the wrong place (a flipped u or v, the
    // wrong chart) shows blue or the wrong colour on the wrong side.
    m.vertex_attrs = Some(
        m.vertices
            .iter()
            .map(|v| match (v[2] > s / 2.0 - 1e-6 && v[1] > 1e-6, v[0]) {
                (false, _) => [0.1, 0.1, 0.9, 0.5, 0.5, 1.0],
                (true, x) if x < -1e-6 => [0.9, 0.1, 0.1, 0.5, 0.5, 1.0],
                (true, x) if x > 1e-6 => [0.1, 0.8, 0.1, 0.5, 0.5, 1.0],
                _ => [0.5, 0.45, 0.1, 0.5, 0.5, 1.0],
            })
            .collect(),
    );
    m
}

fn scene(dir: &Path) -> PathBuf {
    save_mesh_ply(&coloured_box(0.08, 8), &dir.join("cube.ply"), &PlyOptions::default()).unwrap();
    let text = r#"{ "version": 1, "source": "texture test", "support_plane": { "material": "wood" },
      "objects": [ { "name": "cube", "category": "food_box", "mesh": "cube.ply",
                     "pose": { "quaternion_wxyz": [1, 0, 0, 0], "translation_m": [0, 0, 0.04] } } ] }"#;
    std::fs::write(dir.join("scene.json"), text).unwrap();
    dir.join("scene.json")
}

fn recon_scene(scene: &Path, out: &Path, extra: &[&str]) {
    let mut args = vec!["scene", "--input", scene.to_str().unwrap(), "--out", out.to_str().unwrap(), "--collision", "primitive"];
    args.extend_from_slice(extra);
    let o = Command::new(env!("CARGO_BIN_EXE_recon")).args(&args).output().unwrap();
    assert!(o.status.success(), "{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
}

/// Runs `tests/sim/validate_texture.py KIND PATH cube`; `false` when skipped.
fn python(module: &str, kind: &str, path: &Path) -> bool {
    let require = module != "pybullet" && std::env::var("RECON_REQUIRE_PYTHON_TESTS").is_ok_and(|v| v == "1");
    let probe = Command::new("python3").args(["-c", &format!("import {module}")]).output();
    if !probe.as_ref().is_ok_and(|o| o.status.success()) {
        assert!(!require, "RECON_REQUIRE_PYTHON_TESTS=1 but python module `{module}` is unavailable");
        eprintln!("note: skipping the {module} texture check: python3 or {module} missing");
        return false;
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/sim/validate_texture.py");
    let mut cmd = Command::new("python3");
    cmd.arg(&script).args([kind, path.to_str().unwrap(), "cube"]);
    if std::env::var_os("MUJOCO_GL").is_none() {
        cmd.env("MUJOCO_GL", "egl");
    }
    let o = cmd.output().unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout).to_string();
    if o.status.code() == Some(3) {
        assert!(!require, "RECON_REQUIRE_PYTHON_TESTS=1 but MuJoCo has no OpenGL context: {stdout}");
        eprintln!("note: skipping the MuJoCo render: {stdout} (set MUJOCO_GL=egl or osmesa; apt install libegl1 or libosmesa6)");
        return false;
    }
    assert!(o.status.success(), "{kind} texture check failed:\n{stdout}\n{}", String::from_utf8_lossy(&o.stderr));
    println!("{kind}: {}", stdout.trim());
    true
}

#[test]
fn textured_scene_in_every_format() {
    let dir = tmp("scene-texture");
    let input = scene(&dir);
    let out = dir.join("out");
    recon_scene(&input, &out, &["--texture-size", "256"]);
    let m = out.join("meshes/cube");
    let obj = std::fs::read_to_string(m.join("visual.obj")).unwrap();
    assert!(obj.contains("mtllib visual.mtl") && obj.lines().any(|l| l.starts_with("vt ")), "visual.obj has no UVs");
    assert!(std::fs::read_to_string(m.join("visual.mtl")).unwrap().contains("map_Kd texture.png"));
    let png = image::open(m.join("texture.png")).unwrap().to_rgb8();
    assert_eq!(png.dimensions(), (256, 256));
    // The texture carries the mesh's three colours, in large areas.
    let count = |f: &dyn Fn(&image::Rgb<u8>) -> bool| png.pixels().filter(|p| f(p)).count();
    let red = count(&|p| p[0] > 180 && p[1] < 60 && p[2] < 60);
    let green = count(&|p| p[1] > 160 && p[0] < 60 && p[2] < 60);
    let blue = count(&|p| p[2] > 180 && p[0] < 60 && p[1] < 60);
    assert!(red > 500 && green > 500 && blue > 5000, "{red} red, {green} green and {blue} blue texels");
    let mjcf = std::fs::read_to_string(out.join("scene.xml")).unwrap();
    assert!(mjcf.contains("<texture name=\"cube_texture\" type=\"2d\" file=\"cube/texture.png\"/>"), "{mjcf}");
    assert!(mjcf.contains("material=\"cube_material\""));
    let usda = std::fs::read_to_string(out.join("scene.usda")).unwrap();
    assert!(usda.contains("rel material:binding = </World/Looks/cube>") && usda.contains("texCoord2f[] primvars:st"));
    let urdf = std::fs::read_to_string(out.join("urdf/cube.urdf")).unwrap();
    assert!(urdf.contains("<texture filename=\"../meshes/cube/texture.png\"/>"), "{urdf}");
    python("mujoco", "mujoco", &out.join("scene.xml"));
    python("pxr", "usd", &out.join("scene.usda"));
    python("pybullet", "pybullet", &out);

    // With vertex colours chosen there is no texture anywhere.
    let plain = dir.join("plain");
    recon_scene(&input, &plain, &["--colour", "vertex"]);
    assert!(!plain.join("meshes/cube/texture.png").exists() && !plain.join("meshes/cube/visual.mtl").exists());
    for f in ["scene.xml", "scene.usda", "urdf/cube.urdf", "meshes/cube/visual.obj"] {
        let t = std::fs::read_to_string(plain.join(f)).unwrap();
        assert!(!t.contains("texture") && !t.contains("vt ") && !t.contains("primvars:st"), "{f} mentions a texture");
    }
}

/// `recon infer` (random tiny weights, one object of the sample): `mesh.glb` carries
/// TEXCOORD_0 for every vertex and the texture as an embedded PNG of `--texture-size`,
/// no COLOR_0; pose.json's `texture` says part of it came from the photo.
#[test]
fn infer_writes_a_textured_glb() {
    let dir = tmp("infer-texture");
    let sample = common::repo().join("data/sample");
    let out = dir.join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_recon"))
        .args(["infer", "--rgbd"])
        .arg(sample.join("000001-color.png"))
        .arg("--masks")
        .arg(sample.join("000001-label.png"))
        .args([
            "--objects",
            "21",
            "--weights",
            "random",
            "--steps",
            "1",
            "--max-faces",
            "3000",
            "--colour",
            "texture",
            "--texture-size",
            "256",
            "--out",
        ])
        .arg(&out)
        .env("RECON_CACHE", dir.join("cache"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let b = std::fs::read(out.join("id_21/mesh.glb")).unwrap();
    let u32_at = |i: usize| u32::from_le_bytes(b[i..i + 4].try_into().unwrap()) as usize;
    assert_eq!((&b[0..4], u32_at(8)), (&b"glTF"[..], b.len()));
    let jlen = u32_at(12);
    let doc: serde_json::Value = serde_json::from_slice(&b[20..20 + jlen]).unwrap();
    let bin = &b[20 + jlen + 8..];
    let prim = &doc["meshes"][0]["primitives"][0];
    let count = |a: &serde_json::Value| doc["accessors"][a.as_u64().unwrap() as usize]["count"].as_u64().unwrap();
    assert!(prim["attributes"].get("COLOR_0").is_none());
    assert_eq!(count(&prim["attributes"]["TEXCOORD_0"]), count(&prim["attributes"]["POSITION"]));
    let pose: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("id_21/pose.json")).unwrap()).unwrap();
    assert_eq!(count(&prim["indices"]), 3 * pose["faces"].as_u64().unwrap());
    let tex = &doc["textures"][doc["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"].as_u64().unwrap() as usize];
    let view = &doc["bufferViews"][doc["images"][tex["source"].as_u64().unwrap() as usize]["bufferView"].as_u64().unwrap() as usize];
    let off = view["byteOffset"].as_u64().unwrap() as usize;
    let png = image::load_from_memory(&bin[off..off + view["byteLength"].as_u64().unwrap() as usize]).unwrap();
    assert_eq!((png.width(), png.height()), (256, 256));
    let t = &pose["texture"];
    let texels = |k: &str| t[k].as_u64().unwrap();
    assert_eq!(texels("size"), 256);
    assert!(texels("texels_from_views") > 0, "no texel from the photo: {t}");
    assert_eq!(texels("texels_surface"), texels("texels_from_views") + texels("texels_from_vertices"));
    let _ = std::fs::remove_dir_all(&dir);
}
