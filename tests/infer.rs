//! `recon infer` library path on the shipped YCB-Video sample: real frame,
//! real masks, random tiny weights.
use recon::infer::{write_outputs, Engine, InferOptions, MARKER};
use recon::inputs::frame::{FrameOptions, RgbdFrame};
use recon::inputs::masks::{InstanceMap, SkipReason};
use std::path::PathBuf;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn sample_frame_reconstructs_in_camera_frame() {
    let frame = RgbdFrame::open(&root().join("data/sample/000001-color.png"), &FrameOptions::default()).unwrap();
    let map = InstanceMap::open(&root().join("data/sample/000001-label.png")).unwrap();
    // id 8 (gelatin box) is present; id 99 is not and must be reported, not fatal.
    let (objects, skipped) = map.objects(Some(&[8, 99]));
    assert_eq!(objects.len(), 1);
    assert!(skipped.iter().any(|s| s.reason == SkipReason::IdAbsent));

    let engine = Engine::random(&root().join("models/recgen-tiny.json"), 7).unwrap();
    let mut opts = InferOptions::default();
    opts.run.ss_steps = Some(2);
    opts.run.slat_steps = Some(2);
    let r = engine.reconstruct(&frame, objects, &opts).unwrap();
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
    let tmp = std::env::temp_dir().join(format!("recon-infer-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
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
