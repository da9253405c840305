//! What RecGen's `recgen_inference` returns and writes (issue 36 §4), and its preprocessing
//! knobs as options (§6), on random tiny weights: the object-frame and camera-frame
//! assets agree through the pose, RecGen's pose fields through `cam2ncam`, the files of its
//! `save` sit beside recon's own; each knob changes what it should.
mod common;

use candle_core::{Device, Tensor};
use common::{repo, tiny_config, tmp};
use recon::dataset::{FrameOptions, InstanceMap, Intrinsics, ObjectMask, RgbdFrame};
use recon::engine::{
    write_outputs, write_outputs_with, ClampRange, Engine, InferOptions, LoadOptions, ModelSource, ObjectInputs, OutputOptions, Pipeline,
    RunOptions, Stages, ViewInput, Weights, RECGEN_FILES,
};
use recon::geometry::prepare_frame_objects;
use recon::math::Similarity32;

fn apply4(m: &[[f64; 4]; 4], p: [f32; 3]) -> [f64; 3] {
    std::array::from_fn(|i| (0..3).map(|k| m[i][k] * p[k] as f64).sum::<f64>() + m[i][3])
}

/// Largest coordinate difference, relative to the larger magnitude (at least 1).
fn max_rel(a: &[[f32; 3]], b: &[[f64; 3]]) -> f64 {
    assert_eq!(a.len(), b.len());
    a.iter().zip(b).flat_map(|(x, y)| (0..3).map(move |k| (x[k] as f64 - y[k]).abs() / y[k].abs().max(1.0))).fold(0.0, f64::max)
}

/// The same JSON, numbers equal to 1e-12 (JSON text need not round-trip the last bit).
fn close_json(a: &serde_json::Value, b: &serde_json::Value) {
    use serde_json::Value;
    match (a, b) {
        (Value::Number(x), Value::Number(y)) => {
            let (x, y) = (x.as_f64().unwrap(), y.as_f64().unwrap());
            assert!((x - y).abs() <= 1e-12 * x.abs().max(1.0), "{x} vs {y}");
        }
        (Value::Array(x), Value::Array(y)) => {
            assert_eq!(x.len(), y.len());
            x.iter().zip(y).for_each(|(x, y)| close_json(x, y));
        }
        (Value::Object(x), Value::Object(y)) => {
            assert_eq!(x.len(), y.len());
            x.iter().for_each(|(k, v)| close_json(v, &y[k]));
        }
        _ => assert_eq!(a, b),
    }
}

/// The float rows of a binary splat PLY written by recon (17 floats per Gaussian).
fn splat_rows(bytes: &[u8]) -> Vec<[f32; 17]> {
    let end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    bytes[end..].chunks_exact(68).map(|r| std::array::from_fn(|k| f32::from_le_bytes(r[4 * k..4 * k + 4].try_into().unwrap()))).collect()
}

/// The sample frame's gelatin box (id 8) on the random tiny model, with the defaults but one
/// sampler step: the objects of both frames, RecGen's fields and files.
#[test]
fn result_fields_and_files_agree_through_the_pose() {
    let frame = RgbdFrame::open(&repo().join("data/sample/000001-color.png"), &FrameOptions::default()).unwrap();
    let (objects, _) = InstanceMap::open(&repo().join("data/sample/000001-label.png")).unwrap().objects(Some(&[8]));
    let engine = Engine::load(&ModelSource::Random { config: Some(tiny_config()), seed: 7 }, &LoadOptions::default()).unwrap();
    let settings = InferOptions { steps: Some(1), ..Default::default() }.settings().unwrap();
    let r = engine.reconstruct(&frame, objects, &settings).unwrap();
    assert_eq!(r.objects.len(), 1, "{:?}", r.skipped);
    let o = &r.objects[0];
    assert_eq!((r.image.width, r.image.height, r.image.intrinsics), (frame.width, frame.height, frame.intrinsics));
    assert_eq!(r.image.rgb, frame.rgb);
    assert_eq!(serde_json::to_value(r.pose_representation).unwrap(), "6d_translation_scale");

    // The object-frame assets placed by the camera pose are the camera-frame ones, exactly.
    let p = &o.pose_camera;
    let place = Similarity32::new(p.rotation, p.translation, p.scale).unwrap();
    let (mo, mc) = (o.mesh_object.as_ref().expect("object-frame mesh"), o.mesh_camera.as_ref().expect("camera-frame mesh"));
    assert!(!mo.faces.is_empty());
    assert_eq!(&place.apply_mesh(mo), mc);
    assert!(mo.vertices.iter().flatten().all(|x| x.abs() <= 1.0), "the object frame is the canonical cube");
    let (go, gc) = (o.gaussians_object.as_ref().expect("object-frame Gaussians"), o.gaussians_camera.as_ref().unwrap());
    assert!(!go.is_empty());
    assert_eq!(&place.apply_gaussians(go), gc);

    // RecGen's form: inv(cam2ncam) · pose_matrix places the raw mesh (f64 against f32).
    let rp = o.recgen_pose();
    let m = rp.camera_matrix();
    assert!(max_rel(&mc.vertices, &mo.vertices.iter().map(|v| apply4(&m, *v)).collect::<Vec<_>>()) < 1e-5);
    assert!(max_rel(&gc.positions, &go.positions.iter().map(|v| apply4(&m, *v)).collect::<Vec<_>>()) < 1e-5);
    // pose_matrix = cam2ncam · camera pose, and cam2ncam is view 1's normaliser.
    let v1 = &o.views[0];
    let s = 1.0 / v1.normaliser_diameter_m;
    for i in 0..3 {
        assert_eq!(rp.cam2ncam[i][i], s);
        assert!((rp.cam2ncam[i][3] - (0.5 - v1.normaliser_centre_m[i] * s)).abs() < 1e-12);
        assert!((rp.pose.translation[i] - ((p.translation[i] as f64 - v1.normaliser_centre_m[i]) * s + 0.5)).abs() < 1e-9);
    }
    assert!((rp.pose.scale - p.scale as f64 * s).abs() < 1e-9);

    // The files: recon's, and RecGen's beside them.
    let dir = tmp("recgen-files");
    let out = dir.join("out");
    // By default only recon's own files.
    let plain = dir.join("plain");
    let written = write_outputs(&r, &plain).unwrap();
    let obj = written[0].pose.parent().unwrap().to_path_buf();
    for f in RECGEN_FILES {
        assert!(!obj.join(f).exists(), "{f} written without recgen_files");
    }
    let written = write_outputs_with(&r, &out, &OutputOptions { recgen_files: true }).unwrap();
    let obj = written[0].pose.parent().unwrap().to_path_buf();
    for f in RECGEN_FILES.iter().chain(&["pose.json", "mesh.glb", "mesh.ply", "gaussians.ply"]) {
        assert!(obj.join(f).is_file(), "{f} missing");
    }
    // The index keeps its earlier form (no new keys).
    let index = common::read_json(&out.join("recon-output.json"));
    let keys: Vec<&str> = index["objects"][0].as_object().unwrap().keys().map(String::as_str).collect();
    assert_eq!(keys, ["gaussians_ply", "mesh_glb", "mesh_ply", "object", "pose"]); // (serde_json's map sorts)
                                                                                   // metadata.json: upstream's keys in its order, the values above.
    let text = std::fs::read_to_string(obj.join("metadata.json")).unwrap();
    let meta: serde_json::Value = serde_json::from_str(&text).unwrap();
    let keys: Vec<&str> = meta.as_object().unwrap().keys().map(String::as_str).collect();
    let mut order: Vec<(usize, &str)> = keys.iter().map(|k| (text.find(&format!("\"{k}\"")).unwrap(), *k)).collect();
    order.sort();
    assert_eq!(
        order.iter().map(|x| x.1).collect::<Vec<_>>(),
        ["pose_matrix", "pose_quat", "pose", "cam2ncam", "pose_representation", "intrinsics"]
    );
    let pose_keys: Vec<&str> = meta["pose"].as_object().unwrap().keys().map(String::as_str).collect();
    assert_eq!(pose_keys.len(), 4);
    for k in ["quaternion", "translation", "scale", "rotation_matrix"] {
        assert!(pose_keys.contains(&k), "{k}");
    }
    close_json(&meta["pose_matrix"], &serde_json::json!(rp.pose_matrix));
    close_json(&meta["pose_quat"], &serde_json::json!(rp.pose_quat));
    close_json(&meta["pose"], &serde_json::json!(rp.pose));
    close_json(&meta["cam2ncam"], &serde_json::json!(rp.cam2ncam));
    assert_eq!(meta["pose_representation"], "6d_translation_scale");
    let k = frame.intrinsics;
    close_json(&meta["intrinsics"], &serde_json::json!([[k.fx, 0.0, k.cx], [0.0, k.fy, k.cy], [0.0, 0.0, 1.0]]));
    // The splats: the camera frame's is recon's gaussians.ply; the object frame's holds
    // the object-frame centres.
    assert_eq!(std::fs::read(obj.join("posed_gaussian.ply")).unwrap(), std::fs::read(obj.join("gaussians.ply")).unwrap());
    let rows = splat_rows(&std::fs::read(obj.join("gaussian.ply")).unwrap());
    assert_eq!(rows.len(), go.len());
    assert!(rows.iter().zip(&go.positions).all(|(r, p)| r[..3] == p[..]));
    // The OBJ meshes: one `v` line per vertex, in the two frames.
    for (name, mesh) in [("mesh.obj", mo), ("posed_mesh.obj", mc)] {
        let text = std::fs::read_to_string(obj.join(name)).unwrap();
        let v: Vec<[f32; 3]> = text
            .lines()
            .filter(|l| l.starts_with("v "))
            .map(|l| {
                let x: Vec<f32> = l.split_whitespace().skip(1).take(3).map(|t| t.parse().unwrap()).collect();
                [x[0], x[1], x[2]]
            })
            .collect();
        assert_eq!(v, mesh.vertices, "{name}");
    }
    // The overlay: the input's size; the input off the object, changed where it projects.
    let ov = image::open(obj.join("overlay.png")).unwrap().to_rgb8();
    assert_eq!((ov.width() as usize, ov.height() as usize), (frame.width, frame.height));
    let changed = ov.as_raw().iter().zip(&frame.rgb).filter(|(a, b)| a != b).count();
    assert!(changed > 100, "the mesh changed {changed} bytes of the overlay");
    assert_eq!(&ov.as_raw()[..30], &frame.rgb[..30], "the top-left corner is far from the object");
    let _ = std::fs::remove_dir_all(&dir);
}

/// A 64×48 frame looking at a plane at 1 m through a 20×16 mask, with a few far
/// outliers (5 m) inside the mask.
fn plane_frame() -> (RgbdFrame, ObjectMask, usize) {
    let (w, h) = (64, 48);
    let mut depth = vec![1.0f32; w * h];
    let mut mask = vec![false; w * h];
    for y in 16..32 {
        for x in 22..42 {
            mask[y * w + x] = true;
        }
    }
    // Inside the default eroded mask (x 24..40, y 18..30: 192 pixels), 3 outliers (< 2 %).
    for (x, y) in [(30, 22), (33, 25), (36, 28)] {
        depth[y * w + x] = 5.0;
    }
    let rgb = (0..w * h * 3).map(|i| (i % 200) as u8).collect();
    let f = RgbdFrame::from_buffers(w, h, rgb, depth, Intrinsics::new(60.0, 60.0, 31.5, 23.5).unwrap(), "plane").unwrap();
    (f, ObjectMask::from_bools(Some(1), "plane", w, h, &mask), 20 * 16)
}

/// Each preprocessing knob through the one options path: InferOptions → settings → the
/// prepared view.
#[test]
fn preprocessing_knobs_change_what_they_should() {
    let (frame, mask, area) = plane_frame();
    let prepare = |o: InferOptions| {
        let s = o.settings().unwrap();
        let (mut p, skips) = prepare_frame_objects(&frame, vec![mask.clone()], 28, 10, &s.prepare, &Device::Cpu);
        assert!(skips.is_empty(), "{skips:?}");
        p.pop().unwrap().view
    };
    let eroded = |v: &recon::geometry::pointmap::PreparedView| v.mask_full.iter().filter(|&&m| m).count();
    // Erosion: a k×k kernel takes (k − 1)/2 pixels off each side per pass.
    let d = prepare(InferOptions::default());
    assert_eq!(eroded(&d), (20 - 4) * (16 - 4));
    let k7 = prepare(InferOptions { mask_erosion_kernel_size: 7, ..Default::default() });
    assert_eq!(eroded(&k7), (20 - 6) * (16 - 6));
    let twice = prepare(InferOptions { mask_erosion_kernel_size: 3, mask_erosion_iterations: 2, ..Default::default() });
    assert_eq!(eroded(&twice), (20 - 4) * (16 - 4));
    let off = prepare(InferOptions { mask_erosion_enabled: false, ..Default::default() });
    assert_eq!(eroded(&off), area);
    let none = prepare(InferOptions { mask_erosion_iterations: 0, ..Default::default() });
    assert_eq!(eroded(&none), area);
    // The quantile drop: with 0 the far outliers size the unit cube; at the default they
    // are dropped and the plane's own extent (about 0.27 m across) does.
    assert!(d.normaliser.diameter < 0.5, "{}", d.normaliser.diameter);
    let keep = prepare(InferOptions { quantile_drop_threshold: 0.0, ..Default::default() });
    assert!(keep.normaliser.diameter > 7.0, "{}", keep.normaliser.diameter);
    // The clamp: every value of the point map in the range, the range reached.
    let values = |v: &recon::geometry::pointmap::PreparedView| v.pointmap.flatten_all().unwrap().to_vec1::<f32>().unwrap();
    let narrow = values(&prepare(InferOptions { clamp_range: ClampRange { low: 0.45, high: 0.55 }, ..Default::default() }));
    assert!(narrow.iter().all(|x| (0.45..=0.55).contains(x)));
    assert!(narrow.contains(&0.45) && narrow.contains(&0.55));
    let wide = values(&d);
    assert!(wide.iter().any(|&x| !(0.45..=0.55).contains(&x)));
}

/// `use_pointmap = false` leaves the point map out of the condition, as upstream's
/// `pointmap=None`: the run no longer depends on it (and did with it).
#[test]
fn without_the_pointmap_the_run_ignores_it() {
    let p = Pipeline::load(&tiny_config(), Weights::Random(0), Stages::All, &LoadOptions::default()).unwrap();
    let s = p.image_size();
    let v = recon::tools::disc_view(s, 0.0, |u, v, ch| (u + v + ch as f32 * 0.1) - 0.5);
    let flat = ViewInput { pointmap: Tensor::zeros((1, 3, s, s), candle_core::DType::F32, &Device::Cpu).unwrap(), ..v.clone() };
    let run = |view: &ViewInput, use_pointmap: bool| {
        let opts = RunOptions { seed: 3, ss_steps: Some(2), stage1_only: true, use_pointmap, ..Default::default() };
        p.run(&ObjectInputs { views: vec![view.clone()] }, &opts).unwrap()
    };
    let (a, b) = (run(&v, true), run(&flat, true));
    assert_ne!(a.pose.tokens_10d, b.pose.tokens_10d, "with the point map, the point map matters");
    let (a, b) = (run(&v, false), run(&flat, false));
    assert_eq!((a.pose.tokens_10d, a.coords), (b.pose.tokens_10d, b.coords));
    assert!(!a.metadata.use_pointmap);
    // The record: absent from the JSON when the point map was used (earlier outputs).
    let with = serde_json::to_value(&run(&v, true).metadata).unwrap();
    assert!(with.get("use_pointmap").is_none());
    assert_eq!(serde_json::to_value(&a.metadata).unwrap()["use_pointmap"], false);
}

/// Without refinement or shape fit, one view, recon's `pose_matrix` is the model's own pose
/// token in the normalised frame, as upstream's `parse_pose` gives it (to f32 rounding).
#[test]
fn unrefined_pose_matrix_is_the_models_token() {
    use recon::engine::{PoseFit, ShapeFit};
    let frame = RgbdFrame::open(&repo().join("data/sample/000001-color.png"), &FrameOptions::default()).unwrap();
    let (objects, _) = InstanceMap::open(&repo().join("data/sample/000001-label.png")).unwrap().objects(Some(&[8]));
    let engine = Engine::load(&ModelSource::Random { config: Some(tiny_config()), seed: 7 }, &LoadOptions::default()).unwrap();
    let o = InferOptions { steps: Some(1), pose_fit: PoseFit::Recgen, shape_fit: ShapeFit::None, ..Default::default() };
    let mut settings = o.settings().unwrap();
    settings.run.decode_mesh = false; // the random decoder's mesh is large; the Gaussians score
    let r = engine.reconstruct(&frame, objects, &settings).unwrap();
    let o = &r.objects[0];
    assert_eq!(o.selection.view, 1);
    let (token, rp) = (&o.pose_normalised, o.recgen_pose());
    for i in 0..3 {
        for j in 0..3 {
            assert_eq!(rp.pose.rotation_matrix[i][j], token.rotation[i][j] as f64);
        }
        assert!(
            (rp.pose.translation[i] - token.translation[i] as f64).abs() < 1e-5,
            "{:?} vs {:?}",
            rp.pose.translation,
            token.translation
        );
    }
    assert!((rp.pose.scale / token.scale as f64 - 1.0).abs() < 1e-5);
}
