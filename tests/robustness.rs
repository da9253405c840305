//! Long runs: determinism across runs and thread counts, an Engine shared by
//! threads, nothing lost when one object fails, exit codes, and a run killed
//! mid-way. All on the shipped YCB-Video sample with the tiny random-weight
//! model and one sampler step, so each run takes seconds.

mod common;

use common::{repo, tmp};
use recon::dataset::{FrameOptions, InstanceMap, RgbdFrame};
use recon::engine::{Engine, InferSettings, LoadOptions, ModelSource, MARKER};
use std::path::{Path, PathBuf};
use std::process::Command;

const COLOR: &str = "data/sample/000001-color.png";
const LABEL: &str = "data/sample/000001-label.png";

fn recon_cmd() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_recon"));
    c.current_dir(repo());
    c
}

/// `recon infer` with the tiny random model, one step, on ids `objects`.
fn infer_args(out: &Path, objects: &str, threads: usize) -> Vec<String> {
    let tiny = common::tiny_config();
    [
        "infer",
        "--rgbd",
        COLOR,
        "--masks",
        LABEL,
        "--objects",
        objects,
        "--weights",
        "random",
        "--config",
        tiny.to_str().unwrap(),
        "--steps",
        "1",
        "--max-faces",
        "0",
        "--threads",
        &threads.to_string(),
        "--out",
        out.to_str().unwrap(),
    ]
    .iter()
    .map(|s| s.to_string())
    .collect()
}

/// pose.json without the fields that are wall-clock timings.
fn pose_without_timings(p: &Path) -> serde_json::Value {
    let mut v = common::read_json(p);
    let o = v.as_object_mut().unwrap();
    for k in ["timings_s", "postprocess_s", "select_s"] {
        assert!(o.remove(k).is_some(), "{k} missing from {}", p.display());
    }
    v
}

/// An output folder's files: relative path and bytes.
type Files = Vec<(String, Vec<u8>)>;

/// Every file of an output folder, relative path → bytes (pose.json: parsed, timings removed).
fn output_files(out: &Path) -> Files {
    let mut files = Vec::new();
    let mut stack = vec![out.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
                continue;
            }
            let rel = p.strip_prefix(out).unwrap().to_string_lossy().into_owned();
            let bytes = if p.file_name().unwrap() == "pose.json" {
                serde_json::to_vec(&pose_without_timings(&p)).unwrap()
            } else if p.file_name().unwrap() == MARKER {
                // The index names the output folder's own paths.
                std::fs::read_to_string(&p).unwrap().replace(out.to_str().unwrap(), "OUT").into_bytes()
            } else {
                std::fs::read(&p).unwrap()
            };
            files.push((rel, bytes));
        }
    }
    files.sort();
    files
}

/// One seed gives bit-identical outputs (pose.json minus timings, meshes,
/// Gaussians, scene, observed points, index) across runs and across 1, 2 and
/// 4 threads.
#[test]
fn same_seed_same_bytes_across_runs_and_thread_counts() {
    let dir = tmp("determinism");
    let mut reference: Option<(usize, Files)> = None;
    for (run, threads) in [1usize, 2, 4, 2].into_iter().enumerate() {
        let out = dir.join(format!("run{run}_t{threads}"));
        let o = recon_cmd().args(infer_args(&out, "8", threads)).output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let files = output_files(&out);
        let names: Vec<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
        for want in ["id_8/pose.json", "id_8/mesh.ply", "id_8/mesh.glb", "id_8/gaussians.ply", "scene.glb", "observed_points.ply", MARKER] {
            assert!(names.contains(&want), "{want} missing: {names:?}");
        }
        match &reference {
            None => reference = Some((threads, files)),
            Some((t0, want)) => {
                assert_eq!(want.len(), files.len());
                for ((n0, b0), (n1, b1)) in want.iter().zip(&files) {
                    assert_eq!(n0, n1);
                    assert!(b0 == b1, "{n1} differs between {t0} and {threads} threads (run {run})");
                }
            }
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn engine() -> Engine {
    Engine::load(&ModelSource::Random { config: Some(common::tiny_config()), seed: 7 }, &LoadOptions::default()).unwrap()
}

fn fast_opts() -> InferSettings {
    let mut opts = InferSettings::default();
    opts.run.ss_steps = Some(1);
    opts.run.slat_steps = Some(1);
    opts.max_faces = None;
    opts
}

/// The sample mirrored left–right (colour, depth, labels; same intrinsics
/// file): a second, genuinely different frame.
fn mirrored_sample(dir: &Path) -> PathBuf {
    let src = repo().join("data/sample");
    for name in ["000001-color.png", "000001-depth.png", "000001-label.png"] {
        let img = image::open(src.join(name)).unwrap().fliph();
        img.save(dir.join(name)).unwrap();
    }
    std::fs::copy(src.join("000001-meta.mat"), dir.join("000001-meta.mat")).unwrap();
    dir.join("000001-color.png")
}

type Fingerprint = Vec<(String, [f32; 3], f32, usize, usize, u64)>;

/// What must not depend on scheduling: per object its label, translation,
/// scale, face and Gaussian counts and a hash of the mesh vertices' bits.
fn fingerprint(r: &recon::engine::FrameResult) -> Fingerprint {
    use std::hash::{Hash, Hasher};
    r.objects
        .iter()
        .map(|o| {
            let mut h = std::collections::hash_map::DefaultHasher::new();
            if let Some(m) = &o.mesh_camera {
                for v in &m.vertices {
                    v.map(f32::to_bits).hash(&mut h);
                }
            }
            if let Some(g) = &o.gaussians_camera {
                for p in &g.positions {
                    p.map(f32::to_bits).hash(&mut h);
                }
            }
            (
                o.label.clone(),
                o.pose_camera.translation,
                o.pose_camera.scale,
                o.mesh_camera.as_ref().map_or(0, |m| m.faces.len()),
                o.gaussians_camera.as_ref().map_or(0, |g| g.len()),
                h.finish(),
            )
        })
        .collect()
}

/// One Engine shared by four threads on two different frames gives what
/// sequential runs give, bit for bit.
#[test]
fn one_engine_shared_by_threads_matches_sequential_runs() {
    let dir = tmp("shared-engine");
    let frames = [repo().join(COLOR), mirrored_sample(&dir)];
    let inputs: Vec<(RgbdFrame, InstanceMap)> = frames
        .iter()
        .map(|c| {
            let f = RgbdFrame::open(c, &FrameOptions::default()).unwrap();
            let m = InstanceMap::open(&c.with_file_name("000001-label.png")).unwrap();
            (f, m)
        })
        .collect();
    let engine = engine();
    let opts = fast_opts();
    let run = |k: usize| {
        let (f, m) = &inputs[k];
        let (objs, _) = m.objects(Some(&[8, 14]));
        fingerprint(&engine.reconstruct(f, objs, &opts).unwrap())
    };
    let sequential: Vec<Fingerprint> = (0..2).map(run).collect();
    assert_eq!(sequential[0].len(), 2);
    assert_ne!(sequential[0], sequential[1], "the mirrored frame must give other results");
    let concurrent: Vec<(usize, Fingerprint)> = std::thread::scope(|s| {
        let hs: Vec<_> = [0usize, 1, 1, 0].into_iter().map(|k| (k, s.spawn(move || run(k)))).collect();
        hs.into_iter().map(|(k, h)| (k, h.join().unwrap())).collect()
    });
    for (k, fp) in concurrent {
        assert_eq!(fp, sequential[k], "frame {k} differs when run beside others");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

fn exit(o: &std::process::Output) -> i32 {
    o.status.code().unwrap_or(-1)
}

/// Exit codes: 0 when every object is written, 3 when some are (the missing
/// ones listed in the index file), 2 when none is.
#[test]
fn exit_codes_say_all_some_or_none() {
    let dir = tmp("exit-codes");
    let all = dir.join("all");
    let o = recon_cmd().args(infer_args(&all, "8", 2)).output().unwrap();
    assert_eq!(exit(&o), 0, "{}", String::from_utf8_lossy(&o.stderr));

    // Id 99 is not in the label map: object 8 is still written, 99 is listed.
    let some = dir.join("some");
    let o = recon_cmd().args(infer_args(&some, "8,99", 2)).output().unwrap();
    assert!(!String::from_utf8_lossy(&o.stderr).contains("panicked"));
    assert_eq!(exit(&o), 3, "{}", String::from_utf8_lossy(&o.stderr));
    assert!(some.join("id_8/pose.json").is_file() && some.join("id_8/mesh.glb").is_file());
    let index = common::read_json(&some.join(MARKER));
    let skipped = index["skipped"].as_array().unwrap();
    assert_eq!(skipped.len(), 1, "{index}");
    assert!(skipped[0].as_str().unwrap().contains("99"), "{index}");

    // Weights whose stage-1 decoder never marks a voxel occupied: every
    // object fails inside the model (an empty occupancy), each is reported
    // with the reason, and nothing aborts.
    let w = dir.join("empty-occupancy");
    empty_occupancy_weights(&w);
    let none = dir.join("none");
    let o = recon_cmd()
        .args([
            "infer",
            "--rgbd",
            COLOR,
            "--masks",
            LABEL,
            "--weights",
            w.to_str().unwrap(),
            "--steps",
            "1",
            "--out",
            none.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert_eq!(exit(&o), 2, "{}", String::from_utf8_lossy(&o.stderr));
    let index = common::read_json(&none.join(MARKER));
    let skipped: Vec<&str> = index["skipped"].as_array().unwrap().iter().map(|s| s.as_str().unwrap()).collect();
    let n_objects = InstanceMap::open(&repo().join(LABEL)).unwrap().present_ids().len();
    assert_eq!(skipped.len(), n_objects, "{skipped:?}");
    assert!(skipped.iter().all(|s| s.contains("empty occupancy")), "{skipped:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// The shipped recgen-nano folder with its SS decoder's last layer set so that
/// every logit is −10⁴.
fn empty_occupancy_weights(dst: &Path) {
    let src = repo().join("models/recgen-nano");
    std::fs::create_dir_all(dst).unwrap();
    for e in std::fs::read_dir(&src).unwrap() {
        let p = e.unwrap().path();
        if p.is_file() {
            std::fs::copy(&p, dst.join(p.file_name().unwrap())).unwrap();
        }
    }
    let f = dst.join("ss_decoder.safetensors");
    let mut t = candle_core::safetensors::load(&f, &candle_core::Device::Cpu).unwrap();
    let w = t["out_layer.2.weight"].zeros_like().unwrap();
    let b = (t["out_layer.2.bias"].zeros_like().unwrap() - 1e4).unwrap();
    t.insert("out_layer.2.weight".into(), w);
    t.insert("out_layer.2.bias".into(), b);
    candle_core::safetensors::save(&t, &f).unwrap();
}

/// A run killed mid-way (during inference, and as soon as its output starts
/// being written) leaves no complete-looking output: the folder is either
/// absent or complete (its index file and every file the index lists).
#[test]
fn killed_run_leaves_no_complete_looking_output() {
    let dir = tmp("kill");
    for (case, wait_for_staging) in [("mid-inference", false), ("mid-write", true)] {
        let out = dir.join(case);
        let staging = out.with_extension("partial");
        let mut child = recon_cmd()
            .args(infer_args(&out, "8", 2))
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let t0 = std::time::Instant::now();
        if wait_for_staging {
            // Poll for the staging folder: the run is then writing its files.
            while !staging.exists() && child.try_wait().unwrap().is_none() && t0.elapsed().as_secs() < 300 {
                std::thread::sleep(std::time::Duration::from_micros(200));
            }
        } else {
            std::thread::sleep(std::time::Duration::from_millis(300));
        }
        let finished = child.try_wait().unwrap().is_some();
        child.kill().unwrap_or(()); // SIGKILL: no cleanup runs
        child.wait().unwrap();
        if !out.exists() {
            eprintln!("{case}: killed after {:.2} s; no output folder", t0.elapsed().as_secs_f64());
            assert!(!finished, "{case}: the run finished but left no output");
            continue;
        }
        // Present: then it must be complete (the kill came after the final rename).
        let index = common::read_json(&out.join(MARKER));
        for o in index["objects"].as_array().unwrap() {
            for k in ["pose", "mesh_glb", "mesh_ply", "gaussians_ply"] {
                if let Some(p) = o[k].as_str() {
                    assert!(Path::new(p).is_file(), "{case}: index lists {p}, which is missing");
                }
            }
        }
        eprintln!("{case}: the run completed before the kill; its output is complete");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
