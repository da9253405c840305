//! Issue 20: `recon scene --variations N --seed S [--spec variations.json]`.
//!
//! On a `recon synth` scene and on a hand-made scene with an open bowl:
//! every predicate holds after settling in ≥ 95 % of the variants (judged by
//! recon, and re-checked here from the written files), every MJCF variant
//! stays at rest for 2 s in MuJoCo and every USD variant opens in usd-core
//! (python checks skip when the packages are missing, unless
//! RECON_REQUIRE_PYTHON_TESTS=1); the same seed gives byte-identical
//! outputs; each bad-spec class fails before any output is written.
//!
//! On a real `recon infer` output of the README sample (the README's command
//! with a 4000-face budget, run here with the shipped recgen-nano, ~1 min in
//! the dev profile): the same checks.
//!
//! Distractors from a folder of user assets (GLB, OBJ, PLY with physics
//! JSONs) and colour/material variants: masses consistent with the
//! material's density × the written mesh's volume, colours in every export,
//! byte-identical per seed; a bad asset stops the run before any scene work
//! with an error naming that file.

mod common;

use common::tmp;
use recon::export::{save_mesh_ply, PlyOptions};
use recon::mesh::Mesh;
use recon::mesh::{bowl_mesh, box_mesh, cylinder_mesh};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

fn recon(args: &[&str]) -> (bool, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_recon")).args(args).output().unwrap();
    (o.status.success(), format!("{}\n{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)))
}

fn recon_ok(args: &[&str]) -> String {
    let (ok, out) = recon(args);
    assert!(ok, "recon {args:?} failed:\n{out}");
    out
}

/// Same policy as tests/scene.rs: skip with a reason, or fail under RECON_REQUIRE_PYTHON_TESTS=1.
fn python(module: &str, script: &str, args: &[&str]) {
    let require = std::env::var("RECON_REQUIRE_PYTHON_TESTS").is_ok_and(|v| v == "1");
    let ok = Command::new("python3").args(["-c", &format!("import {module}")]).output().is_ok_and(|o| o.status.success());
    if !ok {
        assert!(!require, "RECON_REQUIRE_PYTHON_TESTS=1 but python module `{module}` is unavailable");
        eprintln!("note: skipping the {module} validation: python3 or `{module}` is missing");
        return;
    }
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/sim").join(script);
    let o = Command::new("python3").arg(&script).args(args).output().unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{} {args:?}:\n{stdout}\n{}", script.display(), String::from_utf8_lossy(&o.stderr));
}

fn json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))).unwrap()
}

fn write_ply(m: &Mesh, p: &Path) {
    save_mesh_ply(m, p, &PlyOptions::default()).unwrap();
}

/// World-frame bounds of each object of a written variant, from its
/// scene.json (settled poses) and meshes: the files a user gets.
fn settled_bounds(dir: &Path) -> BTreeMap<String, ([f64; 3], [f64; 3])> {
    settled(dir).into_iter().map(|(k, (lo, hi, _))| (k, (lo, hi))).collect()
}

/// Lowest corner, highest corner, centre of mass.
type Settled = ([f64; 3], [f64; 3], [f64; 3]);

/// [`settled_bounds`] with each object's centre of mass (its body origin in scene.json).
fn settled(dir: &Path) -> BTreeMap<String, Settled> {
    let scene = recon::sim::SceneFile::load(&dir.join("scene.json")).unwrap();
    let mut out = BTreeMap::new();
    for (i, o) in scene.objects.iter().enumerate() {
        let pose = o.pose.to_similarity("scene.json", &format!("objects[{i}]")).unwrap();
        let m = recon::dataset::read_ply(&o.mesh).unwrap();
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for v in &m.vertices {
            let w = pose.apply(&v.map(|x| (x * o.scale) as f32));
            for k in 0..3 {
                lo[k] = lo[k].min(w[k] as f64);
                hi[k] = hi[k].max(w[k] as f64);
            }
        }
        out.insert(o.name.clone(), (lo, hi, o.pose.translation_m));
    }
    out
}

/// Checks every kept variant of a run: rest statistics, predicates (pass
/// rate ≥ 95 %, on_top and world-frame directions re-checked from the
/// files), MuJoCo 2 s at rest, usd-core. Returns the manifest.
fn check_run(out: &Path, requested: usize) -> serde_json::Value {
    let m = json(&out.join("manifest.json"));
    let kept = m["kept"].as_u64().unwrap() as usize;
    assert!(kept as f64 >= 0.95 * requested as f64, "only {kept} of {requested} variants kept");
    let rate = m["predicate_pass_rate"].as_f64().unwrap();
    assert!(rate >= 0.95, "predicates hold in only {:.1} % of the variants", rate * 100.0);
    // The directions the manifest states (camera or world frame, on the plane).
    let axis = |k: &str| -> [f64; 2] { [0, 1].map(|i| m["frame"][k][i].as_f64().unwrap()) };
    let (right, behind) = (axis("right"), axis("behind"));
    let mut rechecked = 0;
    for v in m["variants"].as_array().unwrap().iter().filter(|v| v["kept"] == true) {
        let dir = out.join(v["dir"].as_str().unwrap());
        let s = &v["settle"];
        assert!(s["max_rest_motion_mm"].as_f64().unwrap() < 1.0, "{}: {s}", dir.display());
        let com = settled(&dir);
        let bounds = settled_bounds(&dir);
        assert_eq!(bounds.len(), v["objects"].as_array().unwrap().len());
        for p in v["predicates"].as_array().unwrap() {
            let (a, b) = (p["predicate"]["a"].as_str().unwrap(), p["predicate"]["b"].as_str().unwrap());
            let (ba, bb) = (&bounds[a], &bounds[b]);
            let holds = p["holds"].as_bool().unwrap();
            match p["predicate"]["predicate"].as_str().unwrap() {
                "on_top" if holds => {
                    // Resting on b's top, off the table.
                    assert!((ba.0[2] - bb.1[2]).abs() < 0.006 && ba.0[2] > 0.005, "{}: {p}: {ba:?} {bb:?}", dir.display());
                    rechecked += 1;
                }
                "inside" if holds => {
                    assert!(ba.0[2] < bb.1[2] && (0..2).all(|k| ba.0[k] > bb.0[k] - 0.01 && ba.1[k] < bb.1[k] + 0.01), "{p}");
                    rechecked += 1;
                }
                // Centre of mass to centre of mass, at least 1 cm along the stated direction.
                kind @ ("left_of" | "right_of" | "behind" | "in_front_of") if holds => {
                    let (ta, tb) = (com[a].2, com[b].2);
                    let ax = if kind == "left_of" || kind == "right_of" { right } else { behind };
                    let d = (ta[0] - tb[0]) * ax[0] + (ta[1] - tb[1]) * ax[1];
                    let d = if kind == "left_of" || kind == "in_front_of" { -d } else { d };
                    assert!(d > 0.0099, "{}: {p}: {:.1} mm along {ax:?}", dir.display(), d * 1e3);
                    rechecked += 1;
                }
                // The collision geometries within d: their boxes are at least that close.
                "near" if holds => {
                    let gap = (0..3).map(|k| (ba.0[k] - bb.1[k]).max(bb.0[k] - ba.1[k]).max(0.0)).fold(0.0, |s: f64, g| s.hypot(g));
                    let d = p["predicate"]["distance_m"].as_f64().unwrap();
                    assert!(gap <= d + 0.005, "{}: {p}: boxes {:.1} mm apart", dir.display(), gap * 1e3);
                    rechecked += 1;
                }
                _ => {}
            }
        }
        // Within a millimetre of the plane or resting on something.
        for (name, (lo, _)) in &bounds {
            assert!(lo[2] > -0.001, "{}: {name} sinks {:.2} mm into the table", dir.display(), lo[2] * 1e3);
        }
        python("mujoco", "validate_mjcf.py", &[dir.join("scene.xml").to_str().unwrap(), "2.0", "0.005", "-0.002"]);
        python("pxr", "validate_usd.py", &[dir.join("scene.usda").to_str().unwrap(), &bounds.len().to_string()]);
    }
    println!("{kept}/{requested} kept, pass rate {:.1} %, {rechecked} predicates re-checked from the files", rate * 100.0);
    m
}

fn synth_scene(dir: &Path) -> PathBuf {
    let data = dir.join("synth");
    recon_ok(&["synth", "--out", data.to_str().unwrap(), "--scenes", "1", "--seed", "3", "--width", "320", "--height", "240"]);
    data.join("test/000000")
}

#[test]
fn synth_scene_variations_hold_settle_and_load() {
    let dir = tmp("synth");
    let scene = synth_scene(&dir);
    // The synth seed-3 scene: two bottles (obj 1, 2), a torus (3), mugs (4, 7), spheres (5, 6), a box (8)
    // (no object here fits on another: on_top and inside are covered by the bowl scene below).
    let spec = dir.join("spec.json");
    std::fs::write(
        &spec,
        r#"{"version": 1, "frame": "world",
            "predicates": [
              {"predicate": "in_front_of", "a": "obj_000001", "b": "obj_000008"},
              {"predicate": "left_of", "a": "obj_000003", "b": "obj_000008"},
              {"predicate": "behind", "a": "obj_000004", "b": "obj_000003"},
              {"predicate": "near", "a": "obj_000002", "b": "obj_000004", "distance_m": 0.04}],
            "distractors": {"count": [1, 2], "categories": ["box", "cylinder", "torus", "l_shape"], "scale": [0.6, 0.9]},
            "object_variants": {"probability": 0.5, "scale": [0.9, 1.1], "aspect": [0.9, 1.1], "materials": ["plastic", "wood", "metal"]}}"#,
    )
    .unwrap();
    let out = dir.join("spec_run");
    let args = ["--collision", "primitive", "--vhacd-resolution", "32", "--vhacd-max-hulls", "8", "--seed", "5", "--variations", "6"];
    let s = recon_ok(
        &[&["scene", "--input", scene.to_str().unwrap(), "--out", out.to_str().unwrap(), "--spec", spec.to_str().unwrap()], &args[..]]
            .concat(),
    );
    println!("{s}");
    let m = check_run(&out, 6);
    let vs = m["variants"].as_array().unwrap();
    // Distractors and object variants are there, with masses recomputed.
    assert!(vs.iter().all(|v| v["objects"].as_array().unwrap().iter().any(|o| o["source"] == "distractor")));
    let base_mass: BTreeMap<String, f64> = vs
        .iter()
        .flat_map(|v| v["objects"].as_array().unwrap())
        .filter(|o| o["source"] == "scene" && o["scale"][2] == 1.0)
        .map(|o| (o["name"].as_str().unwrap().to_string(), o["mass_kg"].as_f64().unwrap()))
        .collect();
    let varied: Vec<&serde_json::Value> =
        vs.iter().flat_map(|v| v["objects"].as_array().unwrap()).filter(|o| o["source"] == "scene" && o["scale"][2] != 1.0).collect();
    assert!(!varied.is_empty(), "no object variant in 6 variants at probability 0.5");
    for o in varied {
        let s: f64 = (0..3).map(|k| o["scale"][k].as_f64().unwrap()).product();
        if let Some(m0) = base_mass.get(o["name"].as_str().unwrap()) {
            assert!((o["mass_kg"].as_f64().unwrap() - m0).abs() > 1e-6 || (s - 1.0).abs() < 1e-3, "{o}: mass not recomputed");
        }
        assert!(["plastic", "wood", "metal"].contains(&o["material"].as_str().unwrap()), "{o}");
    }

    // Without a spec: predicates sampled per variant (camera frame of the synth view).
    let out2 = dir.join("sampled");
    println!(
        "{}",
        recon_ok(
            &[
                &["scene", "--input", scene.to_str().unwrap(), "--out", out2.to_str().unwrap(), "--variations", "6"],
                &args[..6],
                &["--seed", "9"]
            ]
            .concat()
        )
    );
    let m2 = check_run(&out2, 6);
    assert_eq!(m2["frame"]["used"], "camera");
    assert!(m2["predicates_total"].as_u64().unwrap() >= 6, "{}", m2["predicates_total"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A bowl (open container), a small block, a box and a can on the plane.
fn bowl_scene(dir: &Path) -> PathBuf {
    write_ply(&bowl_mesh(0.09, 0.06, 0.05, 0.006), &dir.join("bowl.ply"));
    write_ply(&box_mesh(0.03, 0.03, 0.03), &dir.join("block.ply"));
    write_ply(&box_mesh(0.16, 0.10, 0.06), &dir.join("box.ply"));
    write_ply(&cylinder_mesh(0.03, 0.10, 0.002), &dir.join("can.ply"));
    let text = r#"{
  "version": 1,
  "support_plane": { "material": "wood" },
  "objects": [
    { "name": "bowl", "category": "bowl", "mesh": "bowl.ply", "pose": { "quaternion_wxyz": [1, 0, 0, 0], "translation_m": [0, 0, 0.03] } },
    { "name": "block", "category": "block", "mesh": "block.ply", "pose": { "quaternion_wxyz": [1, 0, 0, 0], "translation_m": [0.2, 0, 0.015] } },
    { "name": "box", "category": "food_box", "mesh": "box.ply", "pose": { "quaternion_wxyz": [1, 0, 0, 0], "translation_m": [-0.2, 0.1, 0.03] } },
    { "name": "can", "category": "can", "mesh": "can.ply", "pose": { "quaternion_wxyz": [1, 0, 0, 0], "translation_m": [0, 0.2, 0.05] } }
  ]
}"#;
    let p = dir.join("scene.json");
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn inside_an_open_bowl_and_byte_identical_reruns() {
    let dir = tmp("bowl");
    let scene = bowl_scene(&dir);
    let spec = dir.join("spec.json");
    std::fs::write(
        &spec,
        r#"{"version": 1, "frame": "world", "predicates": [
              {"predicate": "inside", "a": "block", "b": "bowl"},
              {"predicate": "on_top", "a": "can", "b": "box"},
              {"predicate": "right_of", "a": "bowl", "b": "box"}],
            "distractors": {"count": [1, 1], "categories": ["cylinder", "box"], "scale": [0.5, 0.7]}}"#,
    )
    .unwrap();
    let run = |out: &Path, seed: &str| {
        recon_ok(&[
            "scene",
            "--input",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--spec",
            spec.to_str().unwrap(),
            "--collision",
            "convex",
            "--vhacd-resolution",
            "48",
            "--variations",
            "4",
            "--seed",
            seed,
        ])
    };
    let (a, b, c) = (dir.join("a"), dir.join("b"), dir.join("c"));
    println!("{}", run(&a, "7"));
    check_run(&a, 4);
    // Same seed: byte-identical folders; another seed: other poses.
    run(&b, "7");
    let files = |d: &Path| -> BTreeMap<PathBuf, Vec<u8>> {
        let mut m = BTreeMap::new();
        let mut stack = vec![d.to_path_buf()];
        while let Some(p) = stack.pop() {
            for e in std::fs::read_dir(&p).unwrap() {
                let e = e.unwrap().path();
                if e.is_dir() {
                    stack.push(e);
                } else {
                    m.insert(e.strip_prefix(d).unwrap().to_path_buf(), std::fs::read(&e).unwrap());
                }
            }
        }
        m
    };
    let (fa, fb) = (files(&a), files(&b));
    assert!(fa.len() > 20, "{} files", fa.len());
    assert_eq!(fa.keys().collect::<Vec<_>>(), fb.keys().collect::<Vec<_>>());
    for (k, v) in &fa {
        assert!(v == &fb[k], "{} differs between two runs with the same seed", k.display());
    }
    run(&c, "8");
    assert_ne!(std::fs::read(a.join("manifest.json")).unwrap(), std::fs::read(c.join("manifest.json")).unwrap());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_specs_fail_before_any_work() {
    let dir = tmp("bad");
    let scene = bowl_scene(&dir);
    let cases = [
        // Unknown object.
        (
            r#"{"predicate": "near", "a": "mug", "b": "bowl", "distance_m": 0.05}"#,
            vec!["predicates[0]", "unknown object `mug`", "near(mug, bowl"],
        ),
        // on_top of an object smaller than its load: the box on the block.
        (
            r#"{"predicate": "on_top", "a": "box", "b": "block"}"#,
            vec!["predicates[0]", "on_top(box, block)", "smaller than its load `box`"],
        ),
        // inside a closed shape.
        (r#"{"predicate": "inside", "a": "block", "b": "box"}"#, vec!["predicates[0]", "inside(block, box)", "`box` is a closed shape"]),
        // A cycle of supports.
        (
            r#"{"predicate": "on_top", "a": "block", "b": "box"}, {"predicate": "on_top", "a": "box", "b": "block"}"#,
            vec!["cycle", "block → box → block"],
        ),
        // An unknown predicate.
        (r#"{"predicate": "under", "a": "block", "b": "box"}"#, vec!["predicates[0]", "unknown variant `under`"]),
    ];
    for (i, (preds, want)) in cases.iter().enumerate() {
        let spec = dir.join(format!("bad{i}.json"));
        std::fs::write(&spec, format!(r#"{{"version": 1, "predicates": [{preds}]}}"#)).unwrap();
        let out = dir.join(format!("out{i}"));
        let (ok, text) = recon(&[
            "scene",
            "--input",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--spec",
            spec.to_str().unwrap(),
            "--variations",
            "3",
        ]);
        assert!(!ok, "case {i} succeeded:\n{text}");
        for w in want {
            assert!(text.contains(w), "case {i}: want `{w}` in:\n{text}");
        }
        assert!(text.contains(spec.to_str().unwrap()), "the error names the spec file:\n{text}");
        // Nothing written, and the run stopped before any scene work (no support plane
        // fitted, nothing settled or timed).
        assert!(!out.exists(), "case {i} wrote {}", out.display());
        for later in ["support plane:", "settled", "timings:"] {
            assert!(!text.contains(later), "case {i} got as far as `{later}`:\n{text}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// On a real `recon infer` output of the README sample: the README's command
/// (`recon infer --rgbd data/sample/000001-color.png --masks data/sample/000001-label.png`)
/// with `--max-faces 4000` so that the dev-profile run stays near a minute.
#[test]
fn infer_output_of_the_readme_sample() {
    let dir = tmp("infer");
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let color = root.join("data/sample/000001-color.png");
    let infer = dir.join("recon");
    let (ok, text) = recon(&[
        "infer",
        "--rgbd",
        color.to_str().unwrap(),
        "--masks",
        root.join("data/sample/000001-label.png").to_str().unwrap(),
        "--out",
        infer.to_str().unwrap(),
        "--max-faces",
        "4000",
    ]);
    // Exit 3 (some objects written) still leaves a usable output.
    assert!(ok || infer.join(recon::engine::MARKER).is_file(), "recon infer failed:\n{text}");
    let out = dir.join("variations");
    println!(
        "{}",
        recon_ok(&[
            "scene",
            "--input",
            infer.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--collision",
            "primitive",
            "--variations",
            "10",
            "--seed",
            "1"
        ])
    );
    let m = check_run(&out, 10);
    assert_eq!(m["frame"]["used"], "camera");
    assert_eq!(m["objects"].as_array().unwrap().len(), 3, "{}", m["objects"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Enclosed volume and area of a written mesh (divergence theorem).
fn volume_and_area(p: &Path) -> (f64, f64) {
    let m = recon::dataset::read_ply(p).unwrap();
    let (mut vol, mut area) = (0.0, 0.0);
    for f in &m.faces {
        let [a, b, c] = f.map(|i| m.vertices[i as usize]);
        let cr = [
            (b[1] - a[1]) * (c[2] - a[2]) - (b[2] - a[2]) * (c[1] - a[1]),
            (b[2] - a[2]) * (c[0] - a[0]) - (b[0] - a[0]) * (c[2] - a[2]),
            (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]),
        ];
        area += 0.5 * (cr[0] * cr[0] + cr[1] * cr[1] + cr[2] * cr[2]).sqrt();
        vol += (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0])) / 6.0;
    }
    (vol, area)
}

/// The JSON chunk of a GLB file.
fn glb_json(p: &Path) -> serde_json::Value {
    let b = std::fs::read(p).unwrap();
    let n = u32::from_le_bytes(b[12..16].try_into().unwrap()) as usize;
    serde_json::from_slice(&b[20..20 + n]).unwrap()
}

/// An asset folder: a GLB apple (y up, mass given), an OBJ block in
/// millimetres (wood) in `tools/`, a PLY can at the top (category `object`).
fn asset_folder(dir: &Path) -> PathBuf {
    let a = dir.join("assets");
    std::fs::create_dir_all(a.join("fruit")).unwrap();
    std::fs::create_dir_all(a.join("tools")).unwrap();
    // A bevelled puck (a ball would roll away): 8 cm across, 5 cm high.
    let apple = cylinder_mesh(0.04, 0.05, 0.01);
    let glb =
        recon::export::glb_bytes(&apple, &recon::export::GlbOptions { axes: recon::export::Axes::YUp, vertex_colors: false }).unwrap();
    std::fs::write(a.join("fruit/apple.glb"), glb).unwrap();
    std::fs::write(a.join("fruit/apple.json"), r#"{"version": 1, "mass_kg": 0.15, "color_rgba": [0.9, 0.1, 0.1, 1.0]}"#).unwrap();
    let block = box_mesh(30.0, 40.0, 25.0);
    let mut obj = String::from("# a block in millimetres\n");
    for v in &block.vertices {
        obj += &format!("v {} {} {}\n", v[0], v[1], v[2]);
    }
    for f in &block.faces {
        obj += &format!("f {} {} {}\n", f[0] + 1, f[1] + 1, f[2] + 1);
    }
    std::fs::write(a.join("tools/block.obj"), obj).unwrap();
    std::fs::write(a.join("tools/block.json"), r#"{"version": 1, "units_m": 0.001, "material": "wood"}"#).unwrap();
    write_ply(&cylinder_mesh(0.025, 0.07, 0.002), &a.join("can.ply"));
    a
}

#[test]
fn user_asset_distractors_and_colour_material_variants() {
    let dir = tmp("assets");
    let scene = bowl_scene(&dir);
    asset_folder(&dir);
    let spec = dir.join("spec.json");
    std::fs::write(
        &spec,
        r#"{"version": 1, "frame": "world", "predicates": [{"predicate": "right_of", "a": "bowl", "b": "box"}],
            "distractors": {"assets": {"dir": "assets", "count": [2, 3], "size_m": [0.04, 0.08]}},
            "object_variants": {"probability": 0.6, "scale": [0.9, 1.1], "materials": ["wood", "metal", "rubber"]}}"#,
    )
    .unwrap();
    let run = |out: &Path| {
        recon_ok(&[
            "scene",
            "--input",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--spec",
            spec.to_str().unwrap(),
            "--collision",
            "primitive",
            "--variations",
            "4",
            "--seed",
            "3",
        ])
    };
    let (a, b) = (dir.join("a"), dir.join("b"));
    println!("{}", run(&a));
    let m = check_run(&a, 4);
    let table = recon::sim::MaterialTable::builtin();
    let (mut assets, mut varied, mut colours) = (BTreeMap::new(), 0, 0);
    for v in m["variants"].as_array().unwrap().iter().filter(|v| v["kept"] == true) {
        let vd = a.join(v["dir"].as_str().unwrap());
        let report = json(&vd.join("recon-scene.json"));
        let urdf = std::fs::read_to_string(vd.join("urdf/scene.urdf")).unwrap();
        let mjcf = std::fs::read_to_string(vd.join("scene.xml")).unwrap();
        let usd = std::fs::read_to_string(vd.join("scene.usda")).unwrap();
        let glb = glb_json(&vd.join("scene.glb"));
        for (k, o) in v["objects"].as_array().unwrap().iter().enumerate() {
            let name = o["name"].as_str().unwrap();
            let r = &report["objects"][k];
            assert_eq!(r["name"], o["name"]);
            let id = recon::sim::SceneFile::load(&vd.join("scene.json")).unwrap().objects[k]
                .mesh
                .parent()
                .unwrap()
                .file_name()
                .unwrap()
                .to_str()
                .unwrap()
                .to_string();
            // Mass from the density and the written mesh: solid density × volume, shell density × area × wall.
            let (vol, area) = volume_and_area(&vd.join("meshes").join(&id).join("visual.ply"));
            let density = r["physics"]["density_kg_m3"].as_f64().unwrap();
            let mass = o["mass_kg"].as_f64().unwrap();
            assert_eq!(density, o["density_kg_m3"].as_f64().unwrap());
            let want = match r["physics"]["shell_thickness_m"].as_f64() {
                Some(t) => density * area * t,
                None => density * vol,
            };
            assert!((mass - want).abs() <= 2e-3 * want, "{name}: mass {mass} kg, density × size gives {want}");
            let material = o["material"].as_str().unwrap();
            match o["source"].as_str().unwrap() {
                "asset" => {
                    let path = o["asset"].as_str().unwrap();
                    *assets.entry(path.to_string()).or_insert(0) += 1;
                    let (cat, mat) = match path {
                        "fruit/apple.glb" => ("fruit", "produce"),
                        "tools/block.obj" => ("tools", "wood"),
                        "can.ply" => ("object", "plastic"),
                        p => panic!("unknown asset {p}"),
                    };
                    assert_eq!((o["category"].as_str().unwrap(), material), (cat, mat), "{o}");
                    // size_m: the largest extent drawn in [4, 8] cm.
                    let s = o["scale"][0].as_f64().unwrap();
                    let own = match path {
                        "fruit/apple.glb" => 0.08,
                        "tools/block.obj" => 0.04,
                        _ => 0.07,
                    };
                    assert!(s * own > 0.04 - 1e-3 && s * own < 0.08 + 1e-3, "{o}");
                    if path == "fruit/apple.glb" {
                        // The JSON's mass is for the asset at its own size.
                        assert!((mass - 0.15 * s * s * s).abs() < 1e-6 * mass.max(1.0), "{o}");
                        assert_eq!(o["color_rgba"], serde_json::json!([0.9, 0.1, 0.1, 1.0]));
                    }
                }
                "scene" if o["scale"][2] != 1.0 => {
                    varied += 1;
                    assert!(["wood", "metal", "rubber"].contains(&material), "{o}");
                    assert_eq!(density, table.materials[material].density_kg_m3, "{o}");
                }
                _ => {}
            }
            // The colour is the material's unless the object has its own, and every export carries it.
            let c: Vec<f32> = o["color_rgba"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap() as f32).collect();
            if o["source"] != "asset" || o["asset"] != "fruit/apple.glb" {
                let want: Vec<f32> = table.materials[material].color_rgba.unwrap().iter().map(|x| *x as f32).collect();
                assert_eq!(c, want, "{o}");
            }
            let rgba = format!("{} {} {} {}", c[0], c[1], c[2], c[3]);
            assert!(urdf.contains(&format!("<color rgba=\"{rgba}\"/>")), "{name}: {rgba} not in the URDF");
            assert!(
                mjcf.contains(&format!("mesh=\"{id}_visual\" contype=\"0\" conaffinity=\"0\" group=\"1\" rgba=\"{rgba}\"")),
                "{name}: not in the MJCF"
            );
            assert!(usd.contains(&format!("primvars:displayColor = [({}, {}, {})]", c[0], c[1], c[2])), "{name}: not in the USD");
            let gm = glb["meshes"].as_array().unwrap().iter().position(|x| x["name"] == id.as_str()).unwrap();
            let mat = glb["meshes"][gm]["primitives"][0]["material"].as_u64().unwrap() as usize;
            let base: Vec<f32> = glb["materials"][mat]["pbrMetallicRoughness"]["baseColorFactor"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap() as f32)
                .collect();
            assert_eq!(base, c, "{name}: GLB material");
            colours += 1;
        }
    }
    println!("asset draws {assets:?}, {varied} varied scene objects, {colours} colours checked in 4 exports");
    assert!(assets.len() >= 2, "{assets:?}");
    assert!(varied >= 2, "{varied} varied scene objects");
    // Same seed: byte-identical folders.
    run(&b);
    let files = |d: &Path| -> BTreeMap<PathBuf, Vec<u8>> {
        let mut m = BTreeMap::new();
        let mut stack = vec![d.to_path_buf()];
        while let Some(p) = stack.pop() {
            for e in std::fs::read_dir(&p).unwrap() {
                let e = e.unwrap().path();
                if e.is_dir() {
                    stack.push(e);
                } else {
                    m.insert(e.strip_prefix(d).unwrap().to_path_buf(), std::fs::read(&e).unwrap());
                }
            }
        }
        m
    };
    let (fa, fb) = (files(&a), files(&b));
    assert_eq!(fa.keys().collect::<Vec<_>>(), fb.keys().collect::<Vec<_>>());
    for (k, v) in &fa {
        assert!(v == &fb[k], "{} differs between two runs with the same seed", k.display());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_bad_asset_fails_before_any_work_naming_the_file() {
    let dir = tmp("bad_asset");
    let scene = bowl_scene(&dir);
    let assets = asset_folder(&dir);
    let good = std::fs::read(assets.join("fruit/apple.glb")).unwrap();
    type Case<'a> = (&'a str, Box<dyn Fn() + 'a>, Vec<&'a str>);
    let cases: Vec<Case> = vec![
        // A truncated GLB.
        (
            "fruit/broken.glb",
            Box::new(|| std::fs::write(assets.join("fruit/broken.glb"), &good[..good.len() / 2]).unwrap()),
            vec!["broken.glb", "header.length", "truncated"],
        ),
        // An OBJ face pointing past its vertices.
        (
            "tools/bad.obj",
            Box::new(|| std::fs::write(assets.join("tools/bad.obj"), "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n").unwrap()),
            vec!["bad.obj", "line 4 (`f`)", "index 9 out of range"],
        ),
        // A physics JSON with a negative mass.
        (
            "fruit/apple.json",
            Box::new(|| std::fs::write(assets.join("fruit/apple.json"), r#"{"version": 1, "mass_kg": -1}"#).unwrap()),
            vec!["apple.json", "`mass_kg`", "expected a mass"],
        ),
        // A GLB whose accessor claims a billion vertices.
        (
            "fruit/huge.glb",
            Box::new(|| {
                let n = u32::from_le_bytes(good[12..16].try_into().unwrap()) as usize;
                let mut doc: serde_json::Value = serde_json::from_slice(&good[20..20 + n]).unwrap();
                doc["accessors"][0]["count"] = 999_999_999u64.into();
                let mut js = serde_json::to_vec(&doc).unwrap();
                while !js.len().is_multiple_of(4) {
                    js.push(b' ');
                }
                let bin = &good[20 + n..];
                let mut b = Vec::new();
                b.extend_from_slice(&good[0..8]);
                b.extend(((20 + js.len() + bin.len()) as u32).to_le_bytes());
                b.extend((js.len() as u32).to_le_bytes());
                b.extend_from_slice(&good[16..20]);
                b.extend(js);
                b.extend_from_slice(bin);
                std::fs::write(assets.join("fruit/huge.glb"), b).unwrap()
            }),
            vec!["huge.glb", "accessors[0].count", "999999999"],
        ),
    ];
    let spec = dir.join("spec.json");
    std::fs::write(&spec, r#"{"version": 1, "distractors": {"assets": {"dir": "assets", "count": [1, 1]}}}"#).unwrap();
    let apple_json = std::fs::read(assets.join("fruit/apple.json")).unwrap();
    for (i, (file, make, want)) in cases.iter().enumerate() {
        make();
        let out = dir.join(format!("out{i}"));
        let (ok, text) = recon(&[
            "scene",
            "--input",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--spec",
            spec.to_str().unwrap(),
            "--variations",
            "2",
        ]);
        assert!(!ok, "case {i} succeeded:\n{text}");
        for w in want {
            assert!(text.contains(w), "case {i} ({file}): want `{w}` in:\n{text}");
        }
        // Only the bad file is named, and nothing was built, settled or written.
        for other in ["block.obj", "can.ply"] {
            assert!(!text.contains(other), "case {i}: names {other}:\n{text}");
        }
        assert!(!out.exists(), "case {i} wrote {}", out.display());
        for later in ["support plane:", "settled", "timings:"] {
            assert!(!text.contains(later), "case {i} got as far as `{later}`:\n{text}");
        }
        // Undo the case.
        let p = assets.join(file);
        if file.ends_with("apple.json") {
            std::fs::write(&p, &apple_json).unwrap();
        } else {
            std::fs::remove_file(&p).unwrap();
        }
    }
    // A category the folder does not have names the spec's field.
    std::fs::write(&spec, r#"{"version": 1, "distractors": {"assets": {"dir": "assets", "count": [1, 1], "categories": ["toys"]}}}"#)
        .unwrap();
    let (ok, text) = recon(&[
        "scene",
        "--input",
        scene.to_str().unwrap(),
        "--out",
        dir.join("o").to_str().unwrap(),
        "--spec",
        spec.to_str().unwrap(),
        "--variations",
        "2",
    ]);
    assert!(!ok && text.contains("distractors.assets.categories[0]") && text.contains("fruit, object, tools"), "{text}");
    std::fs::remove_dir_all(&dir).unwrap();
}
