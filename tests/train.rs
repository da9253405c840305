//! `recon train` on CI-sized data: the smoke training (losses go down, the
//! trained folder runs stage 1), determinism, bit-identical resume, refusal
//! of foreign output folders, and the BOP reader on a folder written from
//! the toy generator. Uses a micro architecture derived from recgen-nano,
//! so every run takes seconds.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use candle_core::Device;
use recon::engine::ModelSource;
use recon::engine::{LoadOptions, ObjectInputs, Pipeline, RunOptions, Stages, ViewInput, Weights};
use recon::model::ModuleKey;
use recon::train::{canonical_frame, prepare_train_view, TrainingSource};
use recon::train::{micro_architecture, ToyConfig, ToySource};
use recon::train::{run, Resume, Stage, TrainOptions};
use recon::train::{BopOptions, BopSource};

use recon_testkit::repo;

/// A fresh temp folder holding the micro architecture file and its pose stats.
fn workdir(tag: &str) -> PathBuf {
    let d = recon_testkit::tmp(&format!("train-{tag}"));
    let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(repo().join("models/recgen-nano.json")).unwrap()).unwrap();
    std::fs::write(d.join("recgen-micro.json"), serde_json::to_string_pretty(&micro_architecture(&v)).unwrap()).unwrap();
    for f in ["stereo_pose_stats.example.json", "slat_pose_stats.example.json"] {
        std::fs::copy(repo().join("models").join(f), d.join(f)).unwrap();
    }
    d
}

fn toy(second_view: bool) -> ToySource {
    ToySource::new(ToyConfig { models: 4, samples: 10, width: 96, height: 72, seed: 7, occluders: true, second_view }).unwrap()
}

fn opts(stage: Stage, dir: &Path, out: &str, steps: usize, lr: f64) -> TrainOptions {
    let mut o = TrainOptions::new(stage, dir.join("recgen-micro.json"), dir.join(out));
    o.settings.steps = steps;
    o.settings.batch = 4;
    o.settings.lr = lr;
    o.settings.checkpoint_every = 1000;
    o.progress = false;
    o.eval_batches = 3;
    o
}

fn tensors(path: &Path) -> BTreeMap<String, Vec<f32>> {
    candle_core::safetensors::load(path, &Device::Cpu)
        .unwrap()
        .into_iter()
        .map(|(k, t)| (k, t.flatten_all().unwrap().to_vec1::<f32>().unwrap()))
        .collect()
}

/// The CI smoke training: both stage-1 objectives reduce their fixed-batch
/// loss, and the ss-flow folder loads and runs as a stage-1 pipeline.
#[test]
fn smoke_training_reduces_loss_and_output_runs_stage1() {
    let dir = workdir("smoke");
    let src = toy(true);
    let vae = run(&src, &{
        let mut o = opts(Stage::SsVae, &dir, "vae", 40, 3e-3);
        o.recon_loss = recon::model::ReconLoss::Bce;
        o
    })
    .unwrap();
    let (b, a) = (vae.eval_before.unwrap(), vae.eval_after.unwrap());
    eprintln!("ss-vae fixed-batch loss {b:.4} → {a:.4}; {:?}", vae.summary);
    assert!(a < 0.6 * b, "ss-vae loss did not go down enough: {b} → {a}");
    assert!(dir.join("vae/ss_encoder.safetensors").is_file() && dir.join("vae/loss.svg").is_file());

    let mut fo = opts(Stage::SsFlow, &dir, "flow", 40, 2e-3);
    fo.vae = Some(dir.join("vae"));
    let flow = run(&src, &fo).unwrap();
    let (b, a) = (flow.eval_before.unwrap(), flow.eval_after.unwrap());
    eprintln!("ss-flow fixed-batch loss {b:.4} → {a:.4}; {:?}; notes {:?}", flow.summary, flow.notes);
    assert!(a < 0.8 * b, "ss-flow loss did not go down enough: {b} → {a}");
    let log = std::fs::read_to_string(dir.join("flow/loss.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 40);
    assert!(log.contains("mse_pose"));

    // The folder is a stage-1 model: trained weights (not labelled random),
    // the architecture copy reading the training-set pose stats.
    let out = dir.join("flow");
    for key in ModuleKey::STAGE1 {
        assert!(!recon::weights::is_random_init(&out.join(format!("{key}.safetensors"))).unwrap());
    }
    let p = Pipeline::load(&out.join("recgen-micro.json"), Weights::Dir(&out), Stages::SparseStructure, &LoadOptions::default()).unwrap();
    assert!(!p.weights().is_random());
    let s = src.sample(0).unwrap();
    let canon = canonical_frame(&src.model(s.model).unwrap().mesh).unwrap();
    let v = prepare_train_view(&s.views[0], &canon, p.image_size(), 1.2).unwrap();
    let inputs = ObjectInputs { views: vec![ViewInput { pixels: v.pixels, pointmap: v.pointmap, mask: v.mask }] };
    match p.run(&inputs, &RunOptions { stage1_only: true, ss_steps: Some(4), ..Default::default() }) {
        Ok(r) => assert!(r.pose.pose.scale.is_finite() && r.pose.pose.scale > 0.0),
        // 40 steps may not yet give an occupied grid; the error must say so.
        Err(e) => assert!(e.to_string().contains("empty occupancy"), "{e}"),
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The stage-2 autoencoder smoke training: the SDF, colour and Gaussian
/// losses go down on crops of the toy primitives, and the written modules
/// hold exactly the tensors the pipeline loads.
#[test]
fn slat_autoencoder_smoke_training_reduces_loss() {
    let dir = workdir("slat");
    let src = toy(false);
    let mut o = opts(Stage::SlatAe, &dir, "slat", 30, 2e-3);
    o.crop = 4;
    o.max_voxels = 24;
    o.settings.batch = 2;
    let r = run(&src, &o).unwrap();
    let (b, a) = (r.eval_before.unwrap(), r.eval_after.unwrap());
    eprintln!("slat-ae fixed-batch loss {b:.4} → {a:.4}; {:?}", r.summary);
    assert!(a < 0.7 * b, "slat-ae loss did not go down enough: {b} → {a}");
    let log = std::fs::read_to_string(dir.join("slat/loss.jsonl")).unwrap();
    assert_eq!(log.lines().count(), 30);
    for term in ["\"sdf\"", "\"color\"", "\"gs_xyz\"", "\"sign_acc\""] {
        assert!(log.contains(term), "{term} missing from the log");
    }
    let arch = recon::model::RecGenConfig::load(&dir.join("recgen-micro.json")).unwrap();
    for key in [ModuleKey::SlatDecMesh, ModuleKey::SlatDecGs, ModuleKey::SlatEncoder] {
        let t = tensors(&dir.join(format!("slat/{key}.safetensors")));
        let want = recon::weights::expected_tensors(&arch.module_args(key).unwrap(), key.name()).unwrap();
        assert_eq!(t.len(), want.len(), "{key}");
        assert!(want.iter().all(|s| t.get(&s.name).is_some_and(|v| v.len() == s.shape.iter().product::<usize>())), "{key}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The whole recipe on CI-sized data: ss-vae → ss-flow → slat-ae →
/// slat-flow. The SLat flow's loss goes down and its folder is a complete
/// model (every module trained, pose statistics and the latent
/// normalisation of the run in its architecture file) that the pipeline loads.
#[test]
fn slat_flow_smoke_training_writes_a_complete_model() {
    let dir = workdir("s2");
    let src = toy(true);
    run(&src, &opts(Stage::SsVae, &dir, "vae", 5, 3e-3)).unwrap();
    let mut fo = opts(Stage::SsFlow, &dir, "flow", 5, 2e-3);
    fo.vae = Some(dir.join("vae"));
    run(&src, &fo).unwrap();
    let mut ao = opts(Stage::SlatAe, &dir, "ae", 5, 2e-3);
    ao.crop = 4;
    ao.max_voxels = 24;
    run(&src, &ao).unwrap();
    let mut so = opts(Stage::SlatFlow, &dir, "s2", 30, 2e-3);
    so.stage1 = Some(dir.join("flow"));
    so.slat_ae = Some(dir.join("ae"));
    so.settings.batch = 2;
    let r = run(&src, &so).unwrap();
    let (b, a) = (r.eval_before.unwrap(), r.eval_after.unwrap());
    eprintln!("slat-flow fixed-batch loss {b:.4} → {a:.4}; {:?}; notes {:?}", r.summary, r.notes);
    assert!(a < 0.8 * b, "slat-flow loss did not go down enough: {b} → {a}");
    let out = dir.join("s2");
    let arch: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("recgen-micro.json")).unwrap()).unwrap();
    let std: Vec<f64> = arch["slat_normalization"]["std"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert_eq!(std.len(), 8);
    assert!(std.iter().all(|s| s.is_finite() && *s > 0.0), "{std:?}");
    for key in ModuleKey::ALL {
        assert!(!recon::weights::is_random_init(&out.join(format!("{key}.safetensors"))).unwrap(), "{key}");
    }
    let p = Pipeline::load(&out.join("recgen-micro.json"), Weights::Dir(&out), Stages::All, &LoadOptions::default()).unwrap();
    assert!(!p.weights().is_random());
    // `recon eval --method recgen`'s predictor runs the folder on a BOP dataset: every GT
    // instance is either predicted (a camera-frame mesh) or skipped with a reason.
    write_toy_bop(&src, &dir.join("data"));
    let ds = recon::dataset::load_dataset(&dir.join("data/train")).unwrap();
    let engine = recon::engine::Engine::load(
        &ModelSource::Dir { dir: out.clone(), config: Some(out.join("recgen-micro.json")) },
        &LoadOptions::default(),
    )
    .unwrap();
    let mut io = recon::engine::InferSettings { max_faces: Some(2000), ..Default::default() };
    io.run.ss_steps = Some(3);
    io.run.slat_steps = Some(2);
    let n_gt: usize = ds.frames.iter().map(|f| f.gt.len()).sum();
    let er = recon::eval::recgen_dataset(&ds, &engine, &io, false, None, &|_, _| {}).unwrap();
    eprintln!("recgen eval: {} predicted, {} skipped of {n_gt}", er.predictions.len(), er.skipped.len());
    assert_eq!(er.predictions.len() + er.skipped.len(), n_gt);
    assert!(er.predictions.iter().all(|p| !p.prediction.model_frame && !p.mesh.faces.is_empty()));
    assert!(er.skipped.iter().all(|s| !s.reason.is_empty()));
    // Missing inputs are named.
    let mut bad = opts(Stage::SlatFlow, &dir, "s2-bad", 1, 1e-3);
    bad.stage1 = Some(dir.join("flow"));
    let e = run(&src, &bad).err().unwrap().to_string();
    assert!(e.contains("--slat-ae"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Same seed → same weights; another seed → other weights; a run stopped
/// at a checkpoint and resumed ends bit-identical to the uninterrupted run
/// (VAE and flow, the flow with two-view batches and CFG dropout).
#[test]
fn training_is_deterministic_and_resume_is_bit_identical() {
    let dir = workdir("resume");
    let src = toy(true);
    let mk = |stage: Stage, out: &str, steps: usize, seed: u64| {
        let mut o = opts(stage, &dir, out, steps, 2e-3);
        o.settings.seed = seed;
        o.settings.checkpoint_every = 2;
        o.eval_batches = 0;
        o.vae = Some(dir.join("vae-a"));
        o.flow.p_uncond = 0.3;
        o.crop = 4;
        o.max_voxels = 24;
        o
    };
    for stage in [Stage::SsVae, Stage::SsFlow, Stage::SlatAe] {
        let (n, key) = match stage {
            Stage::SsVae => ("vae", ModuleKey::SsEncoder),
            Stage::SsFlow => ("flow", ModuleKey::SsFlow),
            Stage::SlatAe => ("slat", ModuleKey::SlatDecMesh),
            Stage::SlatFlow => unreachable!("covered by slat_flow_smoke_training_writes_a_complete_model"),
        };
        run(&src, &mk(stage, &format!("{n}-a"), 4, 1)).unwrap();
        run(&src, &mk(stage, &format!("{n}-b"), 4, 1)).unwrap();
        run(&src, &mk(stage, &format!("{n}-c"), 4, 2)).unwrap();
        let w = |o: &str| tensors(&dir.join(o).join(format!("{key}.safetensors")));
        assert_eq!(w(&format!("{n}-a")), w(&format!("{n}-b")), "{n}: same seed must give the same weights");
        assert_ne!(w(&format!("{n}-a")), w(&format!("{n}-c")), "{n}: another seed must differ");
        // Interrupted after step 2, resumed to 4.
        run(&src, &mk(stage, &format!("{n}-d"), 2, 1)).unwrap();
        let mut r = mk(stage, &format!("{n}-d"), 4, 1);
        r.resume = Some(Resume::Latest);
        run(&src, &r).unwrap();
        assert_eq!(w(&format!("{n}-a")), w(&format!("{n}-d")), "{n}: resumed run differs from the uninterrupted one");
        let la = std::fs::read_to_string(dir.join(format!("{n}-a/loss.jsonl"))).unwrap();
        let ld = std::fs::read_to_string(dir.join(format!("{n}-d/loss.jsonl"))).unwrap();
        let strip = |s: &str| s.lines().map(|l| l.split(",\"seconds\"").next().unwrap().to_string()).collect::<Vec<_>>();
        assert_eq!(strip(&la), strip(&ld), "{n}: loss logs differ");
        // Resuming with other settings is refused, naming what differs.
        let mut bad = mk(stage, &format!("{n}-d"), 6, 1);
        bad.settings.lr = 1e-3;
        bad.resume = Some(Resume::Latest);
        let e = run(&src, &bad).unwrap_err().to_string();
        assert!(e.contains("loop") && e.contains("--steps"), "{e}");
    }
    // Foreign or finished folders are not overwritten.
    std::fs::create_dir_all(dir.join("foreign")).unwrap();
    std::fs::write(dir.join("foreign/notes.txt"), "mine").unwrap();
    let e = run(&src, &mk(Stage::SsVae, "foreign", 2, 1)).unwrap_err().to_string();
    assert!(e.contains("not a recon train output"), "{e}");
    let e = run(&src, &mk(Stage::SsVae, "vae-a", 2, 1)).unwrap_err().to_string();
    assert!(e.contains("--resume"), "{e}");
    let mut nv = mk(Stage::SsFlow, "novae", 2, 1);
    nv.vae = None;
    assert!(run(&src, &nv).unwrap_err().to_string().contains("--vae"));
    let _ = std::fs::remove_dir_all(&dir);
}

/// Write toy samples as a BOP folder (the layout `recon synth` writes) and
/// read it back with `BopSource`.
/// Writes `src` as a BOP dataset under `root` (`models/` in mm, `train/<i>/` holding
/// sample i's views as frames 0, 1); returns the models folder.
fn write_toy_bop(src: &ToySource, root: &Path) -> PathBuf {
    let models = root.join("models");
    std::fs::create_dir_all(&models).unwrap();
    for m in 0..src.num_models() {
        let mesh = src.model(m).unwrap().mesh;
        let mut ply = format!("ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n", mesh.vertices.len(), mesh.faces.len());
        for v in &mesh.vertices {
            ply += &format!("{} {} {}\n", v[0] * 1000.0, v[1] * 1000.0, v[2] * 1000.0);
        }
        for f in &mesh.faces {
            ply += &format!("3 {} {} {}\n", f[0], f[1], f[2]);
        }
        std::fs::write(models.join(format!("obj_{:06}.ply", m + 1)), ply).unwrap();
    }
    // Scene i holds sample i's two views as frames 0 and 1.
    for i in 0..src.num_samples() {
        let s = src.sample(i).unwrap();
        let scene = root.join(format!("train/{i:06}"));
        for sub in ["rgb", "depth", "mask_visib"] {
            std::fs::create_dir_all(scene.join(sub)).unwrap();
        }
        let (mut cams, mut gts, mut infos) = (serde_json::Map::new(), serde_json::Map::new(), serde_json::Map::new());
        for (fi, v) in s.views.iter().enumerate() {
            let f = &v.frame;
            let (w, h) = (f.width as u32, f.height as u32);
            image::RgbImage::from_raw(w, h, f.rgb.clone()).unwrap().save(scene.join(format!("rgb/{fi:06}.png"))).unwrap();
            let d: Vec<u16> = f.depth_m.iter().map(|&z| (z as f64 * 10000.0).round() as u16).collect();
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, d).unwrap().save(scene.join(format!("depth/{fi:06}.png"))).unwrap();
            let m: Vec<u8> = v.mask.iter().map(|&b| if b { 255 } else { 0 }).collect();
            image::GrayImage::from_raw(w, h, m).unwrap().save(scene.join(format!("mask_visib/{fi:06}_000000.png"))).unwrap();
            let k = f.intrinsics;
            cams.insert(
                fi.to_string(),
                serde_json::json!({"cam_K": [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0], "depth_scale": 0.1}),
            );
            let r: Vec<f64> = v.r.iter().flatten().copied().collect();
            gts.insert(fi.to_string(), serde_json::json!([{"cam_R_m2c": r, "cam_t_m2c": v.t.map(|x| x * 1000.0), "obj_id": s.model + 1}]));
            infos.insert(fi.to_string(), serde_json::json!([{"visib_fract": 0.9, "bbox_visib": [0, 0, 10, 10]}]));
        }
        std::fs::write(scene.join("scene_camera.json"), serde_json::Value::Object(cams).to_string()).unwrap();
        std::fs::write(scene.join("scene_gt.json"), serde_json::Value::Object(gts).to_string()).unwrap();
        std::fs::write(scene.join("scene_gt_info.json"), serde_json::Value::Object(infos).to_string()).unwrap();
    }
    models
}

#[test]
fn bop_source_reads_a_bop_folder() {
    let dir = workdir("bop");
    let src =
        ToySource::new(ToyConfig { models: 2, samples: 2, width: 96, height: 72, seed: 3, occluders: false, second_view: true }).unwrap();
    let models = write_toy_bop(&src, &dir.join("data"));
    let bop = BopSource::open(&dir.join("data/train"), &models, &BopOptions::default()).unwrap();
    assert_eq!(bop.num_samples(), 4, "{}", bop.describe());
    for i in 0..src.num_samples() {
        let want = src.sample(i).unwrap();
        // Frame 0 of scene i is BOP sample 2i; its second view is frame 1.
        let got = bop.sample(2 * i).unwrap();
        assert_eq!(got.views.len(), 2);
        assert_eq!(bop.model(got.model).unwrap().key, format!("obj_{:06}", want.model + 1));
        for (g, w) in got.views.iter().zip(&want.views) {
            assert_eq!(g.mask, w.mask);
            assert_eq!(g.frame.rgb, w.frame.rgb);
            for a in 0..3 {
                assert!((g.t[a] - w.t[a]).abs() < 1e-9);
                for b in 0..3 {
                    assert!((g.r[a][b] - w.r[a][b]).abs() < 1e-12);
                }
            }
            let worst = g.frame.depth_m.iter().zip(&w.frame.depth_m).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
            assert!(worst < 6e-5, "depth differs by {worst} m");
        }
        let gm = &bop.model(got.model).unwrap().mesh;
        let wm = &src.model(want.model).unwrap().mesh;
        assert!((gm.vertices[3][1] - wm.vertices[3][1]).abs() < 1e-6);
    }
    // Instances below the visibility threshold are skipped.
    let none = BopSource::open(&dir.join("data/train"), &models, &BopOptions { min_visib_fract: 0.95, second_view: false });
    assert!(none.is_err());
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--resume` with no value continues the newest checkpoint of `--out` (here: none yet,
/// so the run is refused with that reason, not with an argument-parsing error).
#[test]
fn cli_bare_resume_means_latest_checkpoint() {
    let dir = workdir("cli-resume");
    let src =
        ToySource::new(ToyConfig { models: 2, samples: 2, width: 96, height: 72, seed: 3, occluders: false, second_view: true }).unwrap();
    write_toy_bop(&src, &dir.join("data"));
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_recon"))
        .args(["train", "ss-vae", "--data"])
        .arg(dir.join("data"))
        .arg("--out")
        .arg(dir.join("run"))
        .args(["--steps", "1", "--resume"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("--resume: no checkpoint"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
