//! `recon infer` library path on the shipped YCB-Video sample: real frame,
//! real masks, random tiny weights.
mod common;

use common::{recon_with_env, repo};
use recon::dataset::{FrameOptions, RgbdFrame};
use recon::dataset::{InstanceMap, SkipReason};
use recon::engine::LoadOptions;
use recon::engine::ModelSource;
use recon::engine::{write_outputs, MARKER};
use recon::engine::{Engine, InferSettings};

#[test]
fn sample_frame_reconstructs_in_camera_frame() {
    let frame = RgbdFrame::open(&repo().join("data/sample/000001-color.png"), &FrameOptions::default()).unwrap();
    let map = InstanceMap::open(&repo().join("data/sample/000001-label.png")).unwrap();
    // id 8 (gelatin box) is present; id 99 is not and must be reported, not fatal.
    let (objects, skipped) = map.objects(Some(&[8, 99]));
    assert_eq!(objects.len(), 1);
    assert!(skipped.iter().any(|s| s.reason == SkipReason::IdAbsent));

    let engine =
        Engine::load(&ModelSource::Random { config: Some(repo().join("models/recgen-tiny.json")), seed: 7 }, &LoadOptions::default())
            .unwrap();
    let mut opts = InferSettings::default();
    opts.run.ss_steps = Some(2);
    opts.run.slat_steps = Some(2);
    opts.max_faces = None; // decimating the random model's ~640k faces is slow in test builds
    let t0 = std::time::Instant::now();
    let r = engine.reconstruct(&frame, objects, &opts).unwrap();
    eprintln!("reconstruct: {:.1} s, {:?}", t0.elapsed().as_secs_f64(), r.objects[0].timings);
    assert_eq!(r.objects.len(), 1, "skipped: {:?}", r.skipped);
    let o = &r.objects[0];
    assert!(o.metadata.random_weights);

    // The observed points and the placed object live in the same metric camera frame:
    // the pose translation sits within the object's extent around the observed centroid.
    let n = o.observed_points.len() as f32;
    assert!(n > 100.0);
    let c: Vec<f32> = (0..3).map(|a| o.observed_points.iter().map(|p| p[a]).sum::<f32>() / n).collect();
    let t = o.pose_camera.translation;
    assert!(c[2] > 0.3 && c[2] < 2.0, "observed depth {c:?}");
    let d = ((t[0] - c[0]).powi(2) + (t[1] - c[1]).powi(2) + (t[2] - c[2]).powi(2)).sqrt();
    assert!(d < 0.5, "pose translation {t:?} far from observed centroid {c:?}");
    assert!(o.pose_camera.scale > 0.0 && o.pose_camera.scale.is_finite());
    let mesh = o.mesh_camera.as_ref().expect("mesh");
    assert!(!mesh.faces.is_empty());
    assert!(mesh.vertices.iter().all(|v| v.iter().all(|x| x.is_finite())));

    // Outputs: complete folder with the marker; an unrelated folder is never overwritten.
    let tmp = common::tmp("infer-outputs");
    let out = tmp.join("out");
    let written = write_outputs(&r, &out).unwrap();
    assert!(out.join(MARKER).exists() && out.join("scene.glb").exists() && out.join("observed_points.ply").exists());
    let w = &written[0];
    for p in [Some(&w.pose), w.mesh_glb.as_ref(), w.gaussians_ply.as_ref()].into_iter().flatten() {
        assert!(p.exists(), "{}", p.display());
    }
    let glb = std::fs::read(w.mesh_glb.as_ref().unwrap()).unwrap();
    assert_eq!(&glb[0..4], b"glTF");
    assert_eq!(u32::from_le_bytes(glb[8..12].try_into().unwrap()) as usize, glb.len());
    write_outputs(&r, &out).unwrap(); // replacing an earlier recon output is fine
    let foreign = tmp.join("foreign");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("keep.txt"), "x").unwrap();
    assert!(write_outputs(&r, &foreign).is_err());
    assert!(foreign.join("keep.txt").exists());
    let _ = std::fs::remove_dir_all(&tmp);
}

/// The sample frame, its instance map and the random-weight tiny model, run
/// with one sampler step, `samples` seeds, cross selection and no mesh decoding
/// (the Gaussian centres are scored) to keep the tests fast.
fn one_step_sample_setup(samples: usize) -> (RgbdFrame, InstanceMap, Engine, InferSettings) {
    let frame = RgbdFrame::open(&repo().join("data/sample/000001-color.png"), &FrameOptions::default()).unwrap();
    let map = InstanceMap::open(&repo().join("data/sample/000001-label.png")).unwrap();
    let engine =
        Engine::load(&ModelSource::Random { config: Some(repo().join("models/recgen-tiny.json")), seed: 7 }, &LoadOptions::default())
            .unwrap();
    // These tests are about choosing among every token's pose: the shape fit
    // (which fixes one pose per sample before stage 2) is off.
    let mut opts = InferSettings {
        samples,
        select: recon::engine::SelectMethod::Cross,
        shape_fit: recon::engine::ShapeFit::None,
        ..Default::default()
    };
    opts.run.ss_steps = Some(1);
    opts.run.slat_steps = Some(1);
    opts.run.decode_mesh = false;
    (frame, map, engine, opts)
}

/// Two views (the sample frame twice, the second declared as seen from a
/// camera rotated 0.3 rad about y and shifted), two samples: every
/// candidate and per-view pose must obey the declared relative pose, the
/// winner must have the lowest key, the spread must be that of the
/// per-sample winners, and a rerun must be identical. Mesh decoding is off
/// to keep the test fast: the Gaussian centres are scored instead.
#[test]
fn two_views_and_samples_select_consistently() {
    use recon::engine::{pose_spread, select_best, SelectMethod};
    use recon::engine::{RigidTransform, SecondView};
    use recon::geometry::pose_to_similarity;
    use recon::math::axis_angle;
    let (frame, map, engine, opts) = one_step_sample_setup(2);
    let t = RigidTransform { rotation: axis_angle([0.0, 1.0, 0.0], 0.3), translation: [0.1, 0.0, 0.05], scale: 1.0 };
    let run = |opts: &InferSettings| {
        let (o1, _) = map.objects(Some(&[8]));
        let (o2, _) = map.objects(Some(&[8, 21])); // 21 has no partner in view 1
        engine.reconstruct_two_view(&frame, o1, SecondView { frame: &frame, objects: o2, t_c1_c2: t }, opts).unwrap()
    };
    let r = run(&opts);
    assert_eq!(r.objects.len(), 1, "{:?}", r.skipped);
    assert!(r.notes.iter().any(|n| n.contains("id 21")), "{:?}", r.notes);
    let o = &r.objects[0];
    assert_eq!((o.views.len(), o.candidates.len(), o.samples), (2, 4, 2));
    assert!(o.mesh_camera.is_none() && o.gaussians_camera.as_ref().is_some_and(|g| !g.is_empty()));
    let close = |a: &recon::geometry::Pose, b: &recon::geometry::Pose| {
        let d = (0..3).map(|i| (a.translation[i] - b.translation[i]).abs()).fold(0f32, f32::max)
            + (0..3)
                .flat_map(|i| (0..3).map(move |j| (i, j)))
                .map(|(i, j)| (a.rotation[i][j] - b.rotation[i][j]).abs())
                .fold(0f32, f32::max)
            + (a.scale - b.scale).abs();
        assert!(d < 1e-5, "{a:?} vs {b:?}");
    };
    // The winner has the lowest cross score; its pose is the reported one.
    let scores: Vec<_> = o.candidates.iter().map(|c| c.score.clone()).collect();
    assert_eq!(select_best(SelectMethod::Cross, &scores), Some(o.selection.candidate));
    let best = &o.candidates[o.selection.candidate];
    assert!(scores.iter().all(|s| s.cross() >= best.score.cross()));
    assert!((o.selection.score_m - best.score.cross()).abs() < 1e-12 && o.selection.score_m.is_finite());
    close(&o.pose_camera, &best.pose_camera);
    // Per-view poses: view 1 is the anchor; view 2 sees the pose through T⁻¹.
    close(&o.views[0].pose_selected, &o.pose_camera);
    let in2 = recon::geometry::similarity_to_pose(&t.inverse().compose(&pose_to_similarity(&o.pose_camera)));
    close(&o.views[1].pose_selected, &in2);
    // The selected sample's view-2 token, mapped with T, is its view-2 candidate.
    let c2 = o.candidates.iter().find(|c| c.seed == o.selection.seed && c.view == 2).unwrap();
    close(&recon::geometry::similarity_to_pose(&t.compose(&pose_to_similarity(&o.views[1].pose_own_token.unwrap()))), &c2.pose_camera);
    // Both views' observed points are in the anchor frame.
    assert_eq!(o.observed_points.len(), o.views[0].observed_points + o.views[1].observed_points);
    assert_eq!(o.observed_colors.len(), o.observed_points.len());
    // Spread = that of the per-sample winners.
    let winners: Vec<_> = [0, 2]
        .iter()
        .map(|&f| {
            let i = f + select_best(SelectMethod::Cross, &scores[f..f + 2]).unwrap();
            pose_to_similarity(&o.candidates[i].pose_camera)
        })
        .collect();
    let want = pose_spread(&winners).unwrap();
    let got = o.uncertainty.as_ref().unwrap();
    assert!((got.translation_sd_mm - want.translation_sd_mm).abs() < 1e-6 && (got.rotation_sd_deg - want.rotation_sd_deg).abs() < 1e-4);
    assert!(got.translation_sd_mm > 0.0, "two seeds give two different poses");
    // Determinism.
    let again = run(&opts);
    assert_eq!(again.objects[0].pose_camera, o.pose_camera);
    assert_eq!(again.objects[0].selection.candidate, o.selection.candidate);
    // `first`: view 1's pose, one sample, no spread.
    let first = run(&InferSettings { samples: 1, select: SelectMethod::First, ..opts.clone() });
    let f = &first.objects[0];
    assert_eq!((f.selection.view, f.candidates.len()), (1, 2));
    assert!(f.uncertainty.is_none());
    close(&f.pose_camera, &f.views[0].pose_own_token.unwrap());
}

/// N views through the engine (the sample frame again and again, declared
/// as seen from other cameras): one other view is the two-view run; several
/// run as fused pairs, with the anchor's token as the one candidate and every
/// view's points in the score. Copies of the second view give the two-view
/// run's anchor pose (exactly with round robin); other content changes it; a
/// rerun and another thread count give the same bytes; an unusable view costs
/// that view only; too many views are refused before any work.
#[test]
fn n_views_fuse_pairs_through_the_engine() {
    use recon::engine::{Fusion, RigidTransform, SecondView, SlatFusion, MAX_SECOND_VIEWS};
    use recon::math::axis_angle;
    let (frame, map, engine, opts) = one_step_sample_setup(1);
    let opts = InferSettings { samples: 1, ..opts };
    let cam = |a: f64| RigidTransform { rotation: axis_angle([0.0, 1.0, 0.0], a), translation: [0.1 * a, 0.0, 0.02], scale: 1.0 };
    let others = |n: usize| -> Vec<SecondView> {
        (0..n).map(|i| SecondView { frame: &frame, objects: map.objects(Some(&[8])).0, t_c1_c2: cam(0.2 + 0.1 * i as f64) }).collect()
    };
    let run =
        |n: usize, opts: &InferSettings| engine.reconstruct_views(&frame, map.objects(Some(&[8])).0, others(n), opts, &|_| {}).unwrap();
    // Other content in views 3 and 4: other objects' masks, labelled as object 8.
    let as_8 = |id: u32| {
        let m = map.objects(Some(&[id])).0.remove(0).to_bools();
        vec![recon::dataset::ObjectMask::from_bools(Some(8), format!("{id} as 8"), frame.width, frame.height, &m)]
    };
    let distinct = |opts: &InferSettings| {
        let mut v = others(3);
        (v[1].objects, v[2].objects) = (as_8(14), as_8(21));
        engine.reconstruct_views(&frame, map.objects(Some(&[8])).0, v, opts, &|_| {}).unwrap()
    };
    // One other view: exactly the two-view entry.
    let one = run(1, &opts);
    let two_view = engine.reconstruct_two_view(&frame, map.objects(Some(&[8])).0, others(1).pop().unwrap(), &opts).unwrap();
    let (a, b) = (&one.objects[0], &two_view.objects[0]);
    assert_eq!((a.pose_camera, a.candidates.len()), (b.pose_camera, 2));
    assert_eq!(a.gaussians_camera.as_ref().unwrap().positions, b.gaussians_camera.as_ref().unwrap().positions);
    assert!(a.metadata.fusion.is_none());

    // Three other views, both fusions, stage 2 fused too.
    for (fusion, slat) in [(Fusion::Multidiffusion, SlatFusion::None), (Fusion::Stochastic, SlatFusion::Multidiffusion)] {
        let mut o = opts.clone();
        (o.run.fusion, o.run.slat_fusion) = (fusion, slat);
        // Three steps: round robin gives every pair one.
        o.run.ss_steps = Some(3);
        let r = run(3, &o);
        assert_eq!(r.objects.len(), 1, "{:?}", r.skipped);
        let x = &r.objects[0];
        assert_eq!(x.views.iter().map(|v| v.view).collect::<Vec<_>>(), vec![1, 2, 3, 4]);
        assert_eq!(x.candidates.len(), 1, "the anchor's token is the one candidate");
        assert_eq!((x.selection.view, x.candidates[0].score.per_view_m.len()), (1, 4));
        assert!(x.views[0].pose_own_token.is_some() && x.views[1..].iter().all(|v| v.pose_own_token.is_none()));
        let f = x.metadata.fusion.as_ref().expect("fusion metadata");
        assert_eq!((f.pairs, f.ss, f.slat), (3, fusion, slat));
        assert_eq!(x.metadata.num_views, 4);
        // Copies of view 2: the two-view run's view-1 candidate (round robin: bit for bit).
        let two = run(1, &o);
        let (p, q) = (&x.candidates[0].pose_camera, &two.objects[0].candidates[0].pose_camera);
        match fusion {
            Fusion::Stochastic => assert_eq!(p, q),
            Fusion::Multidiffusion => {
                let d = (0..3).map(|i| (p.translation[i] - q.translation[i]).abs()).fold((p.scale - q.scale).abs(), f32::max);
                assert!(d < 1e-4, "{p:?} vs {q:?}");
            }
        }
        // Other content in the other views changes the result.
        let d = distinct(&o);
        let y = &d.objects[0];
        assert_ne!(y.candidates[0].pose_camera, *q, "{fusion:?}: the other views must change the result");
        // Same bytes with one kernel thread (so on a rerun too).
        let single = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap().install(|| distinct(&o));
        let z = &single.objects[0];
        assert_eq!(z.pose_camera, y.pose_camera, "{fusion:?}");
        assert_eq!(z.gaussians_camera.as_ref().unwrap().positions, y.gaussians_camera.as_ref().unwrap().positions, "{fusion:?}");
        let json = serde_json::to_value(&x.views).unwrap();
        assert!(json[1].get("pose_own_token").is_none() && json[0].get("pose_own_token").is_some());
    }

    // An unusable view (a mask of two pixels) costs that view only.
    let mut bad = others(3);
    let mut mask = bad[1].objects[0].to_bools();
    let keep = mask.iter().position(|&m| m).unwrap();
    for (i, m) in mask.iter_mut().enumerate() {
        *m &= i < keep + 2;
    }
    bad[1].objects = vec![recon::dataset::ObjectMask::from_bools(Some(8), "tiny", frame.width, frame.height, &mask)];
    let r = engine.reconstruct_views(&frame, map.objects(Some(&[8])).0, bad, &opts, &|_| {}).unwrap();
    let x = &r.objects[0];
    assert_eq!(x.views.iter().map(|v| v.view).collect::<Vec<_>>(), vec![1, 2, 4]);
    assert!(x.notes.iter().any(|n| n.contains("view 3") && n.contains("left out")), "{:?}", x.notes);

    // Too many views: refused before any object runs.
    let e = engine.reconstruct_views(&frame, map.objects(Some(&[8])).0, others(MAX_SECOND_VIEWS + 1), &opts, &|_| {}).unwrap_err();
    assert!(e.to_string().contains("views") && e.to_string().contains(&MAX_SECOND_VIEWS.to_string()), "{e}");
    // Masks without ids matched by order: a count mismatch names the view.
    let anon = |n: usize| (0..n).map(|i| recon::dataset::ObjectMask::from_bools(None, format!("m{i}"), 1, 1, &[true])).collect::<Vec<_>>();
    let mut two = others(2);
    two[1].objects = anon(2);
    let e = engine.reconstruct_views(&frame, anon(1), two, &opts, &|_| {}).unwrap_err().to_string();
    assert!(e.contains("view 3"), "{e}");
}

/// The shape fit end to end (random tiny model, sample frame): stage 2 runs on
/// the fitted shell, one pose per sample is kept as the fit saw it, the posed
/// mesh stays out of the observed free space, and the run is deterministic.
#[test]
fn shape_fit_keeps_the_mesh_out_of_observed_free_space() {
    use recon::engine::{ShapeFit, ShapeFitOptions};
    let frame = RgbdFrame::open(&repo().join("data/sample/000001-color.png"), &FrameOptions::default()).unwrap();
    let map = InstanceMap::open(&repo().join("data/sample/000001-label.png")).unwrap();
    let engine =
        Engine::load(&ModelSource::Random { config: Some(repo().join("models/recgen-tiny.json")), seed: 7 }, &LoadOptions::default())
            .unwrap();
    let mut opts = InferSettings { max_faces: None, ..Default::default() };
    opts.run.decode_gaussians = false;
    (opts.run.ss_steps, opts.run.slat_steps) = (Some(1), Some(1));
    let run = |shape_fit: ShapeFit| {
        let (objects, _) = map.objects(Some(&[14]));
        engine.reconstruct(&frame, objects, &InferSettings { shape_fit, ..opts.clone() }).unwrap().objects.remove(0)
    };
    let fitted = run(ShapeFit::Depth);
    let report = fitted.shape_fit.clone().expect("a shape-fit report");
    assert_eq!(fitted.occupied_voxels, report.shell_voxels);
    assert!(report.carved > 0 && report.shell_voxels > 0, "{report:?}");
    assert_eq!(fitted.candidates.len(), 1, "one pose per sample");
    // Mesh vertices more than the margin plus a cell in front of the measured depth.
    let violations = |o: &recon::engine::ObjectResult| {
        let m = o.mesh_camera.as_ref().unwrap();
        let cell = o.pose_camera.scale as f64 / 64.0;
        let k = frame.intrinsics;
        let bad = m
            .vertices
            .iter()
            .filter(|p| {
                let (x, y, z) = (p[0] as f64, p[1] as f64, p[2] as f64);
                let (u, v) = ((k.fx * x / z + k.cx).round(), (k.fy * y / z + k.cy).round());
                if z <= 0.0 || u < 1.0 || v < 1.0 || u >= (frame.width - 1) as f64 || v >= (frame.height - 1) as f64 {
                    return false;
                }
                let d = (0..9)
                    .map(|i| frame.depth_at(u as usize + i % 3 - 1, v as usize + i / 3 - 1) as f64)
                    .filter(|&d| d > 0.0)
                    .fold(f64::INFINITY, f64::min);
                d.is_finite() && z + ShapeFitOptions::default().margin_m + 2.0 * cell < d
            })
            .count();
        bad as f64 / m.vertices.len() as f64
    };
    let with = violations(&fitted);
    let without = violations(&run(ShapeFit::None));
    eprintln!("mesh vertices in observed free space: {:.2} % with the shape fit, {:.2} % without", 100.0 * with, 100.0 * without);
    // The mesh decoder places vertices inside and just around the active cells, so a
    // few can sit a little further out than the cells themselves.
    assert!(with < 0.03 && with < without, "{:.2} % of the fitted mesh lies in observed free space", 100.0 * with);
    let again = run(ShapeFit::Depth);
    assert_eq!((again.pose_camera, again.shape_fit), (fitted.pose_camera, fitted.shape_fit));
}

/// `AlignOptions::depth()` refines every candidate against the depth: the
/// rotation stays the token's, scale and position move, the run is
/// deterministic, and the reported score includes the free-space term.
#[test]
fn depth_pose_fit_refines_scale_and_position_only() {
    use recon::engine::AlignOptions;
    let (frame, map, engine, opts) = one_step_sample_setup(1);
    let run = |align: AlignOptions| {
        let (o1, _) = map.objects(Some(&[8]));
        engine.reconstruct(&frame, o1, &InferSettings { align, ..opts.clone() }).unwrap().objects.remove(0)
    };
    let plain = run(AlignOptions::recgen());
    let fitted = run(AlignOptions::depth());
    let (a, b) = (&plain.candidates[0].pose_camera, &fitted.candidates[0].pose_camera);
    assert_eq!(a.rotation, b.rotation, "the refinement keeps the rotation");
    assert!((a.scale - b.scale).abs() > 1e-6 || (0..3).any(|i| (a.translation[i] - b.translation[i]).abs() > 1e-6), "{a:?} vs {b:?}");
    assert!(fitted.selection.score_m.is_finite());
    assert_eq!(run(AlignOptions::depth()).pose_camera, fitted.pose_camera, "deterministic");
}

#[test]
fn objects_of_two_views_pair_by_id_or_order() {
    use recon::dataset::ObjectMask;
    use recon::engine::match_views;
    let m = |id: Option<u32>, label: &str| ObjectMask::from_bools(id, label, 1, 1, &[true]);
    let (pairs, notes) = match_views(vec![m(Some(3), "a"), m(Some(5), "b")], vec![m(Some(5), "c"), m(Some(9), "d")]).unwrap();
    assert_eq!(pairs.len(), 2);
    assert!(pairs[0].1.is_none());
    assert_eq!(pairs[1].1.as_ref().unwrap().label, "c");
    assert_eq!(notes.len(), 1);
    assert!(notes[0].contains('d'));
    let (pairs, _) = match_views(vec![m(None, "x"), m(None, "y")], vec![m(None, "p"), m(None, "q")]).unwrap();
    assert_eq!(pairs[1].1.as_ref().unwrap().label, "q");
    let e = match_views(vec![m(None, "x")], vec![m(None, "p"), m(None, "q")]).unwrap_err().to_string();
    assert!(e.contains("--masks2") && e.contains("order"), "{e}");
}

/// `recon infer` on the README sample into `out`: the start of the CLI tests' argument lists.
fn sample_infer_args(out: &str) -> [&str; 7] {
    ["infer", "--rgbd", "data/sample/000001-color.png", "--masks", "data/sample/000001-label.png", "--out", out]
}

/// Input errors of the two-view and weights flags stop before any model
/// work, name the flag and leave no output behind.
#[test]
fn cli_rejects_bad_two_view_and_weights_arguments() {
    let tmp = common::tmp("infer-cli");
    let out = tmp.join("out");
    let out_s = out.to_str().unwrap();
    let base = sample_infer_args(out_s);
    let with = |extra: &[&str]| recon_with_env(&[&base[..], extra].concat(), &[]);
    // --view2 needs --masks2 and --rel-pose.
    let o = with(&["--view2", "data/sample/000001-color.png"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--rel-pose"), "{}", String::from_utf8_lossy(&o.stderr));
    // A rel pose that is not a rigid transform.
    let o = with(&[
        "--view2",
        "data/sample/000001-color.png",
        "--masks2",
        "data/sample/000001-label.png",
        "--rel-pose",
        "1,0,0,0,0,1,0,0,0,0,1,0",
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("--rel-pose") && err.contains("16"), "{err}");
    // A manifest name with an empty Hugging Face cache, offline (online it would download).
    let o = recon_with_env(
        &[&base[..], &["--weights", "recgen"]].concat(),
        &[("HF_HOME", tmp.as_path()), ("HF_HUB_OFFLINE", std::path::Path::new("1"))],
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("recon weights fetch --manifest recgen") && err.contains("ss_flow"), "{err}");
    // An unknown precision is refused (bf16/f16 run: tests/pipeline.rs).
    let o = with(&["--dtype", "fp8"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--dtype"), "{}", String::from_utf8_lossy(&o.stderr));
    let o = with(&["--weights", "no-such-thing"]);
    assert!(String::from_utf8_lossy(&o.stderr).contains("not a directory"), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&tmp);
}

/// `--view` files are read and checked before the model loads: a bad field is named with
/// its view number (after --view2's 2), too many views are refused before any file is
/// read, and no output is left behind.
#[test]
fn cli_view_files_are_checked_before_the_model() {
    let tmp = common::tmp("infer-cli-views");
    std::fs::create_dir_all(&tmp).unwrap();
    let out = tmp.join("out");
    let out_s = out.to_str().unwrap();
    let base = sample_infer_args(out_s);
    let with = |extra: &[&str]| recon_with_env(&[&base[..], extra].concat(), &[]);
    let rgb = repo().join("data/sample/000001-color.png");
    let label = repo().join("data/sample/000001-label.png");
    let v = tmp.join("v.json");
    std::fs::write(&v, serde_json::json!({"rgb": rgb, "masks": label}).to_string()).unwrap();
    let v_s = v.to_str().unwrap();
    let o = with(&["--view", v_s]);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success() && err.contains("view 2") && err.contains("v.json") && err.contains("`T_c1_ci`"), "{err}");
    let id = "1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1";
    let o = with(&["--view2", "data/sample/000001-color.png", "--masks2", "data/sample/000001-label.png", "--rel-pose", id, "--view", v_s]);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success() && err.contains("view 3"), "{err}");
    let many: Vec<&str> = (0..17).flat_map(|_| ["--view", "no/such/view.json"]).collect();
    let o = with(&many);
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(!o.status.success() && err.contains("17") && err.contains("16") && !err.contains("no/such"), "{err}");
    let o = with(&["--fusion", "average"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--fusion"));
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&tmp);
}

/// The shipped default (models/recgen-nano/) is a complete trained model:
/// every module labelled trained, its own pose statistics and latent
/// normalisation, within the 30 MB weight budget, and it loads.
#[test]
fn shipped_recgen_nano_is_trained_and_loads() {
    let dir = repo().join("models/recgen-nano");
    let mut bytes = 0u64;
    for key in recon::model::ModuleKey::ALL {
        let p = dir.join(format!("{key}.safetensors"));
        assert!(!recon::weights::is_random_init(&p).unwrap(), "{key} is labelled random");
        bytes += std::fs::metadata(&p).unwrap().len();
    }
    assert!(bytes <= 30 << 20, "{bytes} bytes of weights");
    let arch: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("recgen-nano.json")).unwrap()).unwrap();
    assert_eq!(arch["pose"]["ss_stats"], "pose_stats.json");
    let tiny: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(repo().join("models/recgen-nano.json")).unwrap()).unwrap();
    assert_ne!(arch["slat_normalization"], tiny["slat_normalization"], "the trained folder carries its own latent normalisation");
    let engine =
        Engine::load(&ModelSource::Dir { dir: dir.clone(), config: Some(dir.join("recgen-nano.json")) }, &LoadOptions::default()).unwrap();
    assert!(!engine.pipeline.weights().is_random());
}

/// Objects run at once give what they give one after another, in the same
/// order, and an object that cannot run (a mask of a few pixels, here the
/// second of four) is skipped without losing the others.
#[test]
fn objects_in_parallel_match_one_at_a_time() {
    let (frame, map, engine, opts) = one_step_sample_setup(1);
    let (mut objects, _) = map.objects(None);
    assert!(objects.len() >= 3, "{} objects", objects.len());
    let mut mask = objects[0].to_bools();
    let keep = mask.iter().position(|&m| m).unwrap();
    for (i, m) in mask.iter_mut().enumerate() {
        *m &= i < keep + 3;
    }
    let tiny = recon::dataset::ObjectMask::from_bools(objects[0].id, "tiny", frame.width, frame.height, &mask);
    objects.insert(1, tiny);
    let run = |n: usize| {
        let opts = InferSettings { parallel_objects: std::num::NonZeroUsize::new(n).unwrap(), ..opts.clone() };
        engine.reconstruct(&frame, objects.clone(), &opts).unwrap()
    };
    let (one, many) = (run(1), run(3));
    assert_eq!(one.skipped.len(), 1, "{:?}", one.skipped);
    assert_eq!(one.skipped[0].label, "tiny");
    assert_eq!(one.objects.len(), objects.len() - 1);
    assert_eq!(many.skipped.len(), 1);
    assert_eq!(many.skipped[0].label, "tiny");
    let labels = |r: &recon::engine::FrameResult| r.objects.iter().map(|o| o.label.clone()).collect::<Vec<_>>();
    assert_eq!(labels(&one), labels(&many));
    for (a, b) in one.objects.iter().zip(&many.objects) {
        assert_eq!(a.pose_camera, b.pose_camera, "{}", a.label);
        assert_eq!(a.selection.score_m.to_bits(), b.selection.score_m.to_bits(), "{}", a.label);
        let (ga, gb) = (a.gaussians_camera.as_ref().unwrap(), b.gaussians_camera.as_ref().unwrap());
        assert!(ga.positions == gb.positions && ga.dc == gb.dc, "{}", a.label);
    }
}
