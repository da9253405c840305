//! `recon eval` end to end through the binary: the `observed` baseline on the real
//! YCB-Video frames (skipped, with a note, when ../shared/realdata is absent), re-scoring its
//! predictions file, and clear errors on bad input.

mod common;

use common::{read_json, recon, tmp};

#[test]
fn observed_baseline_on_ycbv_frames_and_rescoring() {
    let Some(root) = common::realdata::realdata_for_test(Some("ycbv_video_oprb"), "the YCB-Video baseline test") else {
        return;
    };
    let root = root.as_path();
    let dir = tmp("ycbv");
    let out = dir.join("observed");
    let (r, o) = (root.to_str().unwrap(), out.to_str().unwrap());
    let run = recon(&["eval", "--dataset", r, "--method", "observed", "--scenes", "1", "--surface-samples", "3000", "--out", o]);
    let (stdout, stderr) = (String::from_utf8_lossy(&run.stdout), String::from_utf8_lossy(&run.stderr));
    eprintln!("{stdout}{stderr}");
    assert!(run.status.success());
    assert!(stdout.contains("ADD-SB@10%") && stdout.contains("0-3%") && stdout.contains("estimated"), "{stdout}");
    for f in ["report.json", "report.txt", "plot.svg", "predictions.json", "recon-output.json"] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    // The index names the recon that wrote it.
    assert_eq!(read_json(&out.join("recon-output.json"))["recon_version"], env!("CARGO_PKG_VERSION"));
    let rep = read_json(&out.join("report.json"));
    let objs = rep["objects"].as_array().unwrap();
    // Sequence 0001: 5 frames × 4 objects, all visible, all scored.
    assert_eq!(objs.len(), 20);
    assert_eq!(rep["overall"]["n_missed"].as_u64(), Some(0));
    for ob in objs {
        let m = &ob["metrics"];
        // Own (box) frame: no ADD; surface metrics finite and in a sane range for
        // "the visible part is the object" on 7–30 cm objects.
        assert!(m["add"].is_null() && m["add_s"].is_null(), "{m}");
        let (sb, cd, dre) = (m["add_sb_norm"].as_f64().unwrap(), m["cd_norm"].as_f64().unwrap(), m["dre"].as_f64().unwrap());
        assert!(sb > 0.0 && sb < 0.4, "ADD-SB/d {sb} for {}", ob["model"]);
        assert!(cd > 0.0 && cd < 0.3, "CD_norm {cd} for {}", ob["model"]);
        assert!(dre < 0.6, "DRE {dre} for {}", ob["model"]);
    }
    // The predictions file written by the baseline re-scores to the same numbers.
    let pf = out.join("predictions.json");
    let out2 = dir.join("rescored");
    let run2 = recon(&[
        "eval",
        "--dataset",
        r,
        "--predictions",
        pf.to_str().unwrap(),
        "--surface-samples",
        "3000",
        "--out",
        out2.to_str().unwrap(),
        "--json",
    ]);
    assert!(run2.status.success(), "{}", String::from_utf8_lossy(&run2.stderr));
    let rep2: serde_json::Value = serde_json::from_slice(&run2.stdout).unwrap();
    assert_eq!(rep2["overall"], rep["overall"]);
    assert_eq!(read_json(&out2.join("report.json"))["overall"], rep["overall"]);
    // --occlusion keeps only the instances of that range, with the same per-object scores.
    let run4 = recon(&[
        "eval",
        "--dataset",
        r,
        "--predictions",
        pf.to_str().unwrap(),
        "--surface-samples",
        "3000",
        "--occlusion",
        "0-3",
        "--json",
    ]);
    assert!(run4.status.success(), "{}", String::from_utf8_lossy(&run4.stderr));
    let rep4: serde_json::Value = serde_json::from_slice(&run4.stdout).unwrap();
    let want: Vec<&serde_json::Value> = objs.iter().filter(|o| o["occlusion_pct"].as_f64().is_some_and(|x| x < 3.0)).collect();
    let got = rep4["objects"].as_array().unwrap();
    assert!(!want.is_empty() && want.len() < objs.len(), "the test needs instances on both sides of 3 %");
    assert_eq!(got.len(), want.len());
    for (g, w) in got.iter().zip(&want) {
        assert_eq!(&g, w);
    }
    // A foreign non-empty folder is never overwritten.
    let foreign = dir.join("foreign");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("keep.txt"), "x").unwrap();
    let run3 = recon(&["eval", "--dataset", r, "--method", "observed", "--scenes", "1", "--out", foreign.to_str().unwrap()]);
    assert!(!run3.status.success());
    assert!(foreign.join("keep.txt").is_file());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn bad_input_gives_clear_errors() {
    let dir = tmp("bad");
    let d = dir.to_str().unwrap();
    // Not a dataset.
    let run = recon(&["eval", "--dataset", d, "--method", "observed"]);
    let e = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && e.contains(d) && e.contains("scene_gt.json"), "{e}");
    // A reversed occlusion range.
    let run = recon(&["eval", "--dataset", d, "--method", "observed", "--occlusion", "70-20"]);
    let e = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && e.contains("--occlusion") && e.contains("LO-HI"), "{e}");
    // Neither --predictions nor --method.
    let run = recon(&["eval", "--dataset", d]);
    assert!(!run.status.success());
    // A BOP scene whose scene_gt.json has a malformed pose: the file and field are named.
    let scene = dir.join("test").join("000001");
    std::fs::create_dir_all(&scene).unwrap();
    std::fs::create_dir_all(dir.join("models")).unwrap();
    std::fs::write(dir.join("models/models_info.json"), "{}").unwrap();
    std::fs::write(scene.join("scene_camera.json"), r#"{"0": {"cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1], "depth_scale": 1.0}}"#)
        .unwrap();
    std::fs::write(scene.join("scene_gt.json"), r#"{"0": [{"cam_R_m2c": [1, 0, 0], "cam_t_m2c": [0, 0, 500], "obj_id": 1}]}"#).unwrap();
    let run = recon(&["eval", "--dataset", d, "--method", "observed"]);
    let e = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && e.contains("scene_gt.json") && e.contains("0[0].cam_R_m2c"), "{e}");
    // Unknown scene name.
    std::fs::write(scene.join("scene_gt.json"), r#"{"0": [{"cam_R_m2c": [1,0,0, 0,1,0, 0,0,1], "cam_t_m2c": [0, 0, 500], "obj_id": 1}]}"#)
        .unwrap();
    std::fs::write(dir.join("models/obj_000001.ply"), "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n10 0 0\n0 10 0\n3 0 1 2\n").unwrap();
    let run = recon(&["eval", "--dataset", d, "--method", "observed", "--scenes", "7"]);
    let e = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && e.contains("no scene `7`") && e.contains("000001"), "{e}");
    // A depth correction outside its prior: the file and the field are named.
    let corr = dir.join("corr.json");
    std::fs::write(&corr, r#"{"version": 1, "corrections": [{"mechanism": "depth_scale", "scale": 0.5}]}"#).unwrap();
    let run = recon(&["eval", "--dataset", d, "--method", "observed", "--depth-correction", corr.to_str().unwrap()]);
    let e = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && e.contains("corr.json") && e.contains("corrections[0].scale") && e.contains("[-0.05, 0.05]"), "{e}");
    // Missing depth image: named.
    let out = dir.join("o");
    let run = recon(&["eval", "--dataset", d, "--method", "observed", "--out", out.to_str().unwrap()]);
    let e = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success() && e.contains("depth/000000.png"), "{e}");
    assert!(!out.exists() && !out.with_extension("partial").exists(), "a failed run left an output folder");
    let _ = std::fs::remove_dir_all(&dir);
}
