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
//! The run on a real `recon infer` output of the README sample needs the
//! release build and the model: `cargo test --release --test scene_variations -- --ignored`.

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
        out.insert(o.name.clone(), (lo, hi));
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
    let world = m["frame"]["used"] == "world";
    let mut rechecked = 0;
    for v in m["variants"].as_array().unwrap().iter().filter(|v| v["kept"] == true) {
        let dir = out.join(v["dir"].as_str().unwrap());
        let s = &v["settle"];
        assert!(s["max_rest_motion_mm"].as_f64().unwrap() < 1.0, "{}: {s}", dir.display());
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
                "left_of" | "right_of" if holds && world => {
                    let d = (ba.0[0] + ba.1[0] - bb.0[0] - bb.1[0]) / 2.0;
                    assert!(if p["predicate"]["predicate"] == "right_of" { d > 0.0 } else { d < 0.0 }, "{p}");
                    rechecked += 1;
                }
                "behind" | "in_front_of" if holds && world => {
                    let d = (ba.0[1] + ba.1[1] - bb.0[1] - bb.1[1]) / 2.0;
                    assert!(if p["predicate"]["predicate"] == "behind" { d > 0.0 } else { d < 0.0 }, "{p}");
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

/// On a real `recon infer` output of the README sample (release build, the shipped model).
/// `cargo test --release --test scene_variations -- --ignored`
#[test]
#[ignore]
fn infer_output_of_the_readme_sample() {
    let dir = tmp("infer");
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let color = root.join("data/sample/000001-color.png");
    let infer = dir.join("recon");
    recon_ok(&[
        "infer",
        "--rgbd",
        color.to_str().unwrap(),
        "--masks",
        root.join("data/sample/000001-label.png").to_str().unwrap(),
        "--out",
        infer.to_str().unwrap(),
    ]);
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
            "20",
            "--seed",
            "1"
        ])
    );
    let m = check_run(&out, 20);
    assert_eq!(m["frame"]["used"], "camera");
    std::fs::remove_dir_all(&dir).unwrap();
}
