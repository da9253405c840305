//! `recon synth` end to end on tiny datasets: determinism (same bytes, any thread count),
//! the BOP round trip through the evaluator's reader, geometric consistency of depth,
//! masks, intrinsics and GT poses, parts mode, and the CLI.

mod common;

use parry3d::math::Vector;
use parry3d::query::PointQuery;
use parry3d::shape::TriMesh as ParryMesh;
use recon::dataset::load_dataset;
use recon::sensor::SensorModel;
use recon::synth::{generate, SynthOptions, MARKER};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

fn tmp(tag: &str) -> PathBuf {
    recon_testkit::tmp(&format!("synth-{tag}"))
}

fn tiny(seed: u64) -> SynthOptions {
    SynthOptions { scenes: 2, views: 2, seed, width: 96, height: 72, parts: false, sensor: SensorModel::ideal() }
}

fn files(root: &Path) -> BTreeMap<String, Vec<u8>> {
    fn walk(d: &Path, root: &Path, out: &mut BTreeMap<String, Vec<u8>>) {
        for e in std::fs::read_dir(d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(&p, root, out);
            } else {
                out.insert(p.strip_prefix(root).unwrap().display().to_string(), std::fs::read(&p).unwrap());
            }
        }
    }
    let mut m = BTreeMap::new();
    walk(root, root, &mut m);
    m
}

fn json(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

/// The split run (what `recon_rgbd.ray.synth` does over workers): shards written in any
/// order, merged, give the bytes of one `generate`; bad shard sets are refused.
#[test]
fn shards_in_any_order_give_the_bytes_of_one_run() {
    use recon::synth::{begin, finish, plan, write_shard};
    let mut opts = tiny(5);
    opts.scenes = 3;
    opts.views = 1;
    let (a, b) = (tmp("shard-a"), tmp("shard-b"));
    generate(&a, &opts, &|| {}).unwrap();
    let staging = begin(&b, &opts).unwrap();
    let ids = plan(&opts).unwrap();
    let late = write_shard(&staging, &opts, 1..3, &ids).unwrap();
    let early = write_shard(&staging, &opts, 0..1, &ids).unwrap();
    let e = finish(&staging, &b, &opts, std::slice::from_ref(&late)).unwrap_err().to_string();
    assert!(e.contains("scene 0 is missing"), "{e}");
    let e = finish(&staging, &b, &opts, &[late.clone(), late.clone()]).unwrap_err().to_string();
    assert!(e.contains("given twice"), "{e}");
    // Through JSON, as shards cross processes.
    let late: recon::synth::Shard = serde_json::from_str(&serde_json::to_string(&late).unwrap()).unwrap();
    finish(&staging, &b, &opts, &[late, early]).unwrap();
    assert_eq!(files(&a), files(&b));
    assert!(write_shard(&staging, &opts, 2..4, &ids).unwrap_err().to_string().contains("scenes 2..4 of 3"));
    let _ = std::fs::remove_dir_all(&a);
    let _ = std::fs::remove_dir_all(&b);
}

#[test]
fn same_bytes_for_a_seed_whatever_the_thread_count() {
    let mut opts = tiny(11);
    opts.sensor = SensorModel::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("models/sensors/stereo.json")).unwrap();
    let (a, b, c) = (tmp("det-a"), tmp("det-b"), tmp("det-c"));
    generate(&a, &opts, &|| {}).unwrap();
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    one.install(|| generate(&b, &opts, &|| {})).unwrap();
    let fa = files(&a);
    assert_eq!(fa, files(&b), "1 thread vs the default pool");
    // Expected layout (2 scenes × 2 views).
    for f in [
        "camera.json",
        MARKER,
        "models/models_info.json",
        "test/000000/scene_gt.json",
        "test/000001/rgb/000001.png",
        "test/000001/depth/000001.png",
        "test/000000/mask/000001_000000.png",
        "test/000000/mask_visib/000000_000000.png",
        "test/000000/scene_meta.json",
    ] {
        assert!(fa.contains_key(f), "missing {f}");
    }
    // A different seed gives a different dataset.
    generate(&c, &tiny(12), &|| {}).unwrap();
    assert_ne!(fa.get("test/000000/rgb/000000.png"), files(&c).get("test/000000/rgb/000000.png"));
    for d in [a, b, c] {
        std::fs::remove_dir_all(d).ok();
    }
}

#[test]
fn bop_round_trip_and_geometric_consistency() {
    let out = tmp("bop");
    let mut opts = tiny(5);
    opts.width = 160;
    opts.height = 120;
    let summary = generate(&out, &opts, &|| {}).unwrap();
    assert!(!out.with_extension("partial").exists(), "staging folder left behind");
    let ds = load_dataset(&out).unwrap();
    assert_eq!(ds.frames.len(), 4);
    assert_eq!(summary.images, 4);
    let total: usize = ds.frames.iter().map(|f| f.gt.len()).sum();
    assert_eq!(total, summary.instances);
    assert_eq!(ds.models.len(), summary.models);
    for f in &ds.frames {
        let sdir = out.join("test").join(&f.scene);
        let meta = json(&sdir.join("scene_meta.json"));
        let info = json(&sdir.join("scene_gt_info.json"));
        let im = f.frame;
        // Exactly one target per image, flagged in scene_meta.json.
        let inst = meta["instances"].as_array().unwrap();
        assert_eq!(inst.len(), f.gt.len());
        assert_eq!(inst.iter().filter(|i| i["target"] == true).count(), 1);
        let depth = image::open(sdir.join("depth").join(format!("{im:06}.png"))).unwrap().into_luma16();
        let (w, h) = (depth.width() as usize, depth.height() as usize);
        assert_eq!((w, h), (160, 120));
        for (g, gt) in f.gt.iter().enumerate() {
            let m = &ds.models[&gt.obj_id];
            assert_eq!(inst[g]["obj_id"].as_u64().unwrap() as u32, gt.obj_id);
            assert!(m.diameter > 0.01 && m.diameter < 0.5, "diameter {} m", m.diameter);
            assert_eq!(m.diameter_source, "models_info.json");
            let amodal = image::open(sdir.join("mask").join(format!("{im:06}_{g:06}.png"))).unwrap().into_luma8();
            let visib = image::open(sdir.join("mask_visib").join(format!("{im:06}_{g:06}.png"))).unwrap().into_luma8();
            let n_all = amodal.pixels().filter(|p| p.0[0] == 255).count();
            let n_vis = visib.pixels().filter(|p| p.0[0] == 255).count();
            assert!(amodal.pixels().zip(visib.pixels()).all(|(a, v)| a.0[0] == 255 || v.0[0] == 0), "visible ⊄ amodal");
            let gi = &info[im.to_string()][g];
            assert_eq!(gi["px_count_all"].as_u64().unwrap() as usize, n_all);
            assert_eq!(gi["px_count_visib"].as_u64().unwrap() as usize, n_vis);
            // Ideal sensor: every silhouette pixel has a valid depth.
            assert_eq!(gi["px_count_valid"].as_u64().unwrap() as usize, n_all);
            if n_all > 0 {
                assert!((gt.visib_fract.unwrap() - n_vis as f64 / n_all as f64).abs() < 1e-12);
            }
            if n_vis < 10 {
                continue;
            }
            // Back-project the visible pixels with K and the depth, move them into the
            // model frame with the GT pose: they must lie on the model surface.
            // Exact point-to-surface distance (parry's projection on the model mesh).
            let verts: Vec<Vector> = m.mesh.vertices.iter().map(|v| Vector::new(v[0] as f32, v[1] as f32, v[2] as f32)).collect();
            let surface = ParryMesh::new(verts, m.mesh.faces.clone()).unwrap();
            let k = f.k;
            let mut worst: f64 = 0.0;
            for (i, p) in visib.pixels().enumerate() {
                if p.0[0] != 255 {
                    continue;
                }
                let (u, v) = ((i % w) as f64, (i / w) as f64);
                let z = depth.as_raw()[i] as f64 * f.depth_scale_m;
                assert!(z > 0.0);
                let c = [(u - k[0][2]) / k[0][0] * z, (v - k[1][2]) / k[1][1] * z, z];
                let d = [c[0] - gt.t[0], c[1] - gt.t[1], c[2] - gt.t[2]];
                // R^T d
                let x = [0, 1, 2].map(|j| (0..3).map(|r| gt.r[r][j] * d[r]).sum::<f64>());
                let p = Vector::new(x[0] as f32, x[1] as f32, x[2] as f32);
                worst = worst.max(surface.distance_to_local_point(p, false) as f64);
            }
            // Depth is stored in 0.1 mm steps; f32 geometry adds far less.
            assert!(worst < 1e-4, "{} image {im} gt {g}: a visible pixel is {worst} m off the model", f.scene);
        }
    }
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn parts_mode_writes_each_part_with_its_pose() {
    let out = tmp("parts");
    // Find a seed whose scenes hold a mug or a bottle (composites) — deterministic search.
    let mut opts = SynthOptions { scenes: 3, views: 1, seed: 0, width: 64, height: 48, parts: true, sensor: SensorModel::ideal() };
    let mut found = false;
    for seed in 0..10 {
        opts.seed = seed;
        generate(&out, &opts, &|| {}).unwrap();
        let ds = load_dataset(&out).unwrap();
        for f in &ds.frames {
            let meta = json(&out.join("test").join(&f.scene).join("scene_meta.json"));
            let inst = meta["instances"].as_array().unwrap();
            for (g, i) in inst.iter().enumerate() {
                if i["part"] != "handle" && i["part"] != "cap" {
                    continue;
                }
                // The body is the instance of the same object with part "body".
                let b = inst.iter().position(|j| j["object_index"] == i["object_index"] && j["part"] == "body").unwrap();
                let rel = |x: &Value| -> ([[f64; 3]; 3], [f64; 3]) {
                    let r: Vec<f64> = x["part_pose_in_object"]["R"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
                    let t: Vec<f64> =
                        x["part_pose_in_object"]["t_mm"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() / 1000.0).collect();
                    ([[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]], [t[0], t[1], t[2]])
                };
                // Parts are translated copies in the object frame, so in the camera
                // frame: t_part − t_body = R_obj (t_part_rel − t_body_rel), R_part = R_body.
                let (gp, gb) = (&f.gt[g], &f.gt[b]);
                let ((_, tp), (_, tb)) = (rel(i), rel(&inst[b]));
                let d = [tp[0] - tb[0], tp[1] - tb[1], tp[2] - tb[2]];
                for r in 0..3 {
                    let want = (0..3).map(|c| gb.r[r][c] * d[c]).sum::<f64>();
                    assert!((gp.t[r] - gb.t[r] - want).abs() < 1e-6);
                    for c in 0..3 {
                        assert!((gp.r[r][c] - gb.r[r][c]).abs() < 1e-9);
                    }
                }
                found = true;
            }
        }
        if found {
            break;
        }
    }
    assert!(found, "no composite object in 10 seeds × 3 scenes");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn refuses_foreign_folders_and_bad_options() {
    let out = tmp("foreign");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("precious.txt"), "keep").unwrap();
    let e = generate(&out, &tiny(0), &|| {}).unwrap_err().to_string();
    assert!(e.contains("not a recon synth dataset"), "{e}");
    assert_eq!(std::fs::read_to_string(out.join("precious.txt")).unwrap(), "keep");
    let mut o = tiny(0);
    o.views = 0;
    let e = generate(&tmp("zero"), &o, &|| {}).unwrap_err().to_string();
    assert!(e.contains("--views"), "{e}");
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn shipped_sensor_models_load() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/sensors");
    assert_eq!(SensorModel::load(&dir.join("stereo.json")).unwrap(), SensorModel::stereo_default());
    assert_eq!(SensorModel::load(&dir.join("ideal.json")).unwrap(), SensorModel::ideal());
    let g = SensorModel::load(&dir.join("gaussian.json")).unwrap();
    assert!(g.base_sd(1.0) > 0.0);
}

#[test]
fn cli_writes_a_dataset_and_reports_bad_sensor_files() {
    let exe = env!("CARGO_BIN_EXE_recon");
    let out = tmp("cli");
    let o = std::process::Command::new(exe)
        .args(["synth", "--out", out.to_str().unwrap(), "--scenes", "2", "--views", "1", "--seed", "3", "--width", "64", "--height", "48"])
        .args(["--sensor", concat!(env!("CARGO_MANIFEST_DIR"), "/models/sensors/gaussian.json")])
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{stdout}\n{}", String::from_utf8_lossy(&o.stderr));
    assert!(stdout.contains("2 scenes, 2 images"), "{stdout}");
    assert!(out.join(MARKER).is_file());
    let marker = json(&out.join(MARKER));
    assert_eq!(marker["sensor_model"]["name"], "gaussian");
    let bad = tmp("badsensor").join("badsensor.json");
    std::fs::write(&bad, r#"{"version": 1, "base": {"kind": "stereo", "focal_px": 0, "baseline_m": 0.05, "disparity_sigma_px": 0.1}}"#)
        .unwrap();
    let o = std::process::Command::new(exe)
        .args(["synth", "--out", tmp("cli2").to_str().unwrap(), "--sensor", bad.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("badsensor.json") && err.contains("base"), "{err}");
    std::fs::remove_dir_all(&out).ok();
    std::fs::remove_file(&bad).ok();
}

/// The renderer against a real camera: the two YCB-Video objects with BOP meshes, placed
/// by the GT poses, must render where the Xtion saw them and at the depth it measured.
#[test]
fn renders_real_ycbv_objects_where_the_camera_saw_them() {
    use recon::dataset::load_ycbv;
    use recon::dataset::read_ply;
    use recon::dataset::Intrinsics;
    use recon::math::Similarity;
    use recon::render::render;
    use recon::synth::{Camera, Instance, RenderMesh, RenderOptions};
    let Some(root) = common::realdata::realdata_for_test(Some("ycbv_video_oprb"), "this real-data test") else {
        return;
    };
    let root = root.as_path();
    let ds = load_ycbv(root).unwrap();
    // BOP meshes (mm, re-centred) → YCB-Video GT frame (m), offsets from the folder's README.
    let offsets = [(1u32, [1.39, -0.45, 3.60]), (2u32, [0.61, 1.76, 4.77])];
    let meshes: Vec<(u32, RenderMesh)> = offsets
        .iter()
        .map(|&(cls, off)| {
            let path = root.join("models_bop_ply_recentred").join(format!("obj_{cls:06}.ply"));
            let mut m = read_ply(&path).unwrap();
            for v in &mut m.vertices {
                *v = [0, 1, 2].map(|k| (v[k] - off[k]) / 1000.0);
            }
            (cls, RenderMesh::from_trimesh(&m, &path.display().to_string()).unwrap())
        })
        .collect();
    let mut checked = 0;
    for f in ds.frames.iter().filter(|f| f.scene == "0001") {
        let insts: Vec<Instance> =
            f.gt.iter()
                .filter_map(|g| {
                    meshes.iter().find(|(c, _)| *c == g.obj_id).map(|(c, m)| Instance::new(m, Similarity::rigid(g.r, g.t), *c as i64))
                })
                .collect();
        assert_eq!(insts.len(), 2);
        let k = Intrinsics { fx: f.k[0][0], fy: f.k[1][1], cx: f.k[0][2], cy: f.k[1][2] };
        let r = render(&insts, &Camera::new(640, 480, k), &RenderOptions::default()).unwrap();
        let base = root.join(&f.scene);
        let depth = image::open(base.join(format!("{:06}-depth.png", f.frame))).unwrap().into_luma16();
        let label = image::open(base.join(format!("{:06}-label.png", f.frame))).unwrap().into_luma8();
        for (i, inst) in insts.iter().enumerate() {
            let cls = inst.id as u8;
            let labelled: Vec<usize> = (0..640 * 480).filter(|&p| label.as_raw()[p] == cls).collect();
            let covered = labelled.iter().filter(|&&p| r.amodal[i][p]).count() as f64 / labelled.len() as f64;
            // Residual measured − rendered depth where both see this object.
            let mut res: Vec<f64> = labelled
                .iter()
                .filter(|&&p| r.index[p] == i as i32 && depth.as_raw()[p] > 0)
                .map(|&p| depth.as_raw()[p] as f64 * f.depth_scale_m - r.depth[p] as f64)
                .collect();
            res.sort_by(|a, b| a.partial_cmp(b).unwrap());
            let median = res[res.len() / 2];
            eprintln!(
                "frame {} class {cls}: {:.3} of {} labelled px covered, median residual {:.4} m over {} px",
                f.frame,
                covered,
                labelled.len(),
                median,
                res.len()
            );
            assert!(covered > 0.9, "class {cls}: only {covered} of the labelled pixels are rendered");
            assert!(median.abs() < 0.01, "class {cls}: median depth residual {median} m");
            checked += 1;
        }
    }
    assert_eq!(checked, 10);
}
