//! End to end on random tiny weights (`models/recgen-tiny.json`): synthetic
//! inputs (smooth random image, disc mask, sphere-cap pointmap) → pose,
//! occupancy, mesh, Gaussians → GLB + splat PLY re-read and checked;
//! determinism; two-view conditioning; loading the same weights from files.

mod common;

use candle_core::{Device, Tensor};
use common::{tiny_config, tmp};
use recon::engine::{Fusion, SlatFusion, MAX_SECOND_VIEWS};
use recon::engine::{LoadOptions, ObjectInputs, ObjectReconstruction, Pipeline, RunOptions, Stages, ViewInput, Weights, WeightsSource};
use recon::export::{save_glb, Axes, GlbOptions};
use recon::rng::SeededRng;
use std::path::{Path, PathBuf};

/// One synthetic view of side `s`: a smooth random RGB image (a few random
/// sinusoids, ImageNet-normalised), a disc mask, and the pointmap of a sphere
/// cap seen head-on inside the disc (zeros outside). `shift` moves the disc.
fn view(s: usize, seed: u64, shift: f32) -> ViewInput {
    let mut rng = SeededRng::new(seed);
    #[allow(clippy::approx_constant)] // 6.28: test data, about a turn
    let waves: Vec<[f32; 4]> =
        (0..4).map(|_| [rng.normal() as f32 * 4.0, rng.normal() as f32 * 4.0, rng.uniform() as f32 * 6.28, rng.uniform() as f32]).collect();
    let (mean, std) = ([0.485f32, 0.456, 0.406], [0.229f32, 0.224, 0.225]);
    recon::tools::disc_view(s, shift, |u, v, ch| {
        let val: f32 =
            waves.iter().enumerate().map(|(i, w)| 0.25 * (w[0] * u + w[1] * v + w[2] + (i + ch) as f32).sin() * w[3]).sum::<f32>() + 0.5;
        (val.clamp(0.0, 1.0) - mean[ch]) / std[ch]
    })
}

fn all_finite3(v: &[[f32; 3]]) -> bool {
    v.iter().flatten().all(|x| x.is_finite())
}

fn check_result(out: &ObjectReconstruction) {
    assert!(!out.coords.is_empty());
    let r = out.ss_resolution as i32;
    assert!(out.coords.iter().flatten().all(|&c| (0..r).contains(&c)));
    let mesh = out.mesh.as_ref().expect("mesh decoded");
    mesh.validate().unwrap();
    assert!(!mesh.faces.is_empty(), "random tiny weights gave an empty mesh");
    assert!(all_finite3(&mesh.vertices));
    assert!(mesh.vertices.iter().flatten().all(|x| x.abs() <= 0.6), "mesh leaves the object cube");
    let attrs = mesh.vertex_attrs.as_ref().expect("vertex colours");
    assert!(attrs.iter().flatten().all(|x| (0.0..=1.0).contains(x)));
    let g = out.gaussians.as_ref().expect("gaussians decoded");
    g.validate().unwrap();
    assert_eq!(g.len(), out.coords.len() * 4, "num_gaussians = 4 per voxel");
    assert!(all_finite3(&g.positions) && all_finite3(&g.scales) && all_finite3(&g.dc));
    assert!(g.opacities.iter().all(|o| *o > 0.0 && *o < 1.0));
    assert!(g.scales.iter().flatten().all(|s| *s > 0.0));
    // Pose: a proper rotation, finite translation, positive scale.
    let p = &out.pose;
    assert_eq!(p.per_token.len(), 2);
    assert_eq!(p.per_token[0], p.pose);
    let rm = p.pose.rotation;
    for i in 0..3 {
        for j in 0..3 {
            let d: f32 = (0..3).map(|k| rm[k][i] * rm[k][j]).sum();
            assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-4);
        }
    }
    assert!(p.pose.translation.iter().all(|t| t.is_finite()) && p.pose.scale > 0.0);
    assert!(p.tokens_10d.iter().flatten().chain(p.slat_tokens_13d.iter().flatten()).all(|x| x.is_finite()));
    assert!(out.metadata.random_weights);
    let t = &out.timings;
    assert!(t.total > 0.0 && t.ss_sampling > 0.0 && t.slat_sampling > 0.0 && t.mesh_decoder > 0.0);
}

fn same(a: &ObjectReconstruction, b: &ObjectReconstruction) -> bool {
    a.coords == b.coords && a.pose == b.pose && a.mesh == b.mesh && a.gaussians == b.gaussians
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes(b[i..i + 4].try_into().unwrap())
}

/// Re-read a GLB: header, JSON chunk, accessor counts against the mesh.
fn check_glb(path: &Path, n_vertices: usize, n_faces: usize) {
    let b = std::fs::read(path).unwrap();
    assert_eq!(&b[0..4], b"glTF");
    assert_eq!(u32_at(&b, 4), 2);
    assert_eq!(u32_at(&b, 8) as usize, b.len());
    let json_len = u32_at(&b, 12) as usize;
    assert_eq!(&b[16..20], b"JSON");
    let j: serde_json::Value = serde_json::from_slice(&b[20..20 + json_len]).unwrap();
    let bin_hdr = 20 + json_len;
    assert_eq!(&b[bin_hdr + 4..bin_hdr + 8], b"BIN\0");
    assert_eq!(u32_at(&b, bin_hdr) as usize, b.len() - bin_hdr - 8);
    let prim = &j["meshes"][0]["primitives"][0];
    let count = |acc: &serde_json::Value| j["accessors"][acc.as_u64().unwrap() as usize]["count"].as_u64().unwrap() as usize;
    assert_eq!(count(&prim["attributes"]["POSITION"]), n_vertices);
    assert_eq!(count(&prim["attributes"]["COLOR_0"]), n_vertices);
    assert_eq!(count(&prim["indices"]), 3 * n_faces);
}

/// Re-read a 3DGS PLY: header vertex count and body size.
fn check_splat_ply(path: &Path, n: usize) {
    let b = std::fs::read(path).unwrap();
    let end = b.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    let head = std::str::from_utf8(&b[..end]).unwrap();
    assert!(head.starts_with("ply\nformat binary_little_endian 1.0\n"));
    assert!(head.contains(&format!("element vertex {n}\n")));
    assert_eq!(head.matches("property float").count(), 17);
    assert_eq!(b.len() - end, n * 17 * 4);
}

#[test]
fn tiny_pipeline_end_to_end() {
    let p = Pipeline::load(&tiny_config(), Weights::Random(0), Stages::All, &LoadOptions::default()).unwrap();
    assert!(matches!(p.weights(), WeightsSource::Random { seed: 0 }));
    let s = p.image_size();
    let one = ObjectInputs { views: vec![view(s, 1, 0.0)] };
    let opts = RunOptions { seed: 7, ..Default::default() };
    let out = p.run(&one, &opts).unwrap();
    check_result(&out);
    eprintln!(
        "tiny single view: {} voxels, {} vertices, {} faces, {} gaussians; timings {:?}",
        out.coords.len(),
        out.mesh.as_ref().unwrap().vertices.len(),
        out.mesh.as_ref().unwrap().faces.len(),
        out.gaussians.as_ref().unwrap().len(),
        out.timings
    );

    // Exports re-read with matching counts.
    let dir = tmp("export");
    let mesh = out.mesh.as_ref().unwrap();
    let glb = dir.join("object.glb");
    save_glb(mesh, &glb, &GlbOptions::default()).unwrap();
    check_glb(&glb, mesh.vertices.len(), mesh.faces.len());
    let ply = dir.join("object_splat.ply");
    recon::export::save_splat_ply(out.gaussians.as_ref().unwrap(), &ply, Axes::YUp).unwrap();
    check_splat_ply(&ply, out.gaussians.as_ref().unwrap().len());
    let _ = std::fs::remove_dir_all(&dir);

    // Same seed → bit-identical; another seed → different.
    let again = p.run(&one, &opts).unwrap();
    assert!(same(&out, &again), "same seed gave different outputs");
    let other = p.run(&one, &RunOptions { seed: 8, decode_mesh: false, ..Default::default() }).unwrap();
    assert_ne!(other.pose.tokens_10d, out.pose.tokens_10d);
    assert!(other.mesh.is_none() && other.gaussians.is_some());

    // Two views: frame-token conditioning in stage 1, concatenated views in stage 2.
    let two = ObjectInputs { views: vec![view(s, 1, 0.0), view(s, 2, 0.08)] };
    let out2 = p.run(&two, &opts).unwrap();
    check_result(&out2);
    assert_eq!(out2.metadata.num_views, 2);
    assert_ne!(out2.pose.tokens_10d, out.pose.tokens_10d, "the second view must change the result");

    // Bad inputs are errors, not panics (more views than pose tokens run as
    // fused pairs: tests below).
    let mut bad = view(s, 1, 0.0);
    bad.mask = Tensor::zeros((1, 1, s + 14, s + 14), candle_core::DType::F32, &Device::Cpu).unwrap();
    assert!(p.run(&ObjectInputs { views: vec![bad] }, &opts).is_err());
    assert!(p.run(&one, &RunOptions { ss_steps: Some(0), ..Default::default() }).is_err());
}

/// `recon weights init --config` layout → `Pipeline::load` gives the same
/// model as `Pipeline::random`; a wrong file is named with tensor and shapes.
#[test]
fn load_from_initialised_files() {
    let dir = tmp("load");
    // `recon weights init --config <architecture>` goes through write_random_init.
    assert_eq!(recon::weights::write_random_init(&tiny_config(), &dir, 5).unwrap(), dir);
    let files: Vec<PathBuf> = recon::model::ModuleKey::ALL.iter().map(|k| dir.join(format!("{k}.safetensors"))).collect();
    assert!(dir.join("stereo_pose_stats.example.json").exists() && dir.join("slat_pose_stats.example.json").exists());
    for f in &files {
        assert!(recon::weights::is_random_init(f).unwrap());
    }
    let cfg = dir.join("recgen-tiny.json");
    // Stage 1 only keeps this test short; stage 2 loads through the same code.
    let loaded = Pipeline::load(&cfg, Weights::Dir(&dir), Stages::SparseStructure, &LoadOptions::default()).unwrap();
    assert!(loaded.weights().is_random());
    let random = Pipeline::load(&tiny_config(), Weights::Random(5), Stages::SparseStructure, &LoadOptions::default()).unwrap();
    let one = ObjectInputs { views: vec![view(loaded.image_size(), 3, 0.0)] };
    let opts = RunOptions { seed: 1, stage1_only: true, ..Default::default() };
    let a = loaded.run(&one, &opts).unwrap();
    let b = random.run(&one, &opts).unwrap();
    assert!(!a.coords.is_empty() && a.mesh.is_none());
    assert_eq!(a.coords, b.coords);
    assert_eq!(a.pose, b.pose);
    assert!(Pipeline::load(&cfg, Weights::Dir(&dir), Stages::All, &LoadOptions::default()).is_ok());

    // A wrong checkpoint fails before building, naming the tensor.
    std::fs::copy(dir.join("ss_decoder.safetensors"), dir.join("ss_flow.safetensors")).unwrap();
    let err = Pipeline::load(&cfg, Weights::Dir(&dir), Stages::SparseStructure, &LoadOptions::default())
        .err()
        .expect("wrong checkpoint accepted")
        .to_string();
    assert!(err.contains("ss_flow.safetensors") && err.contains("blocks.0"), "{err}");
    std::fs::remove_file(dir.join("ss_flow.safetensors")).unwrap();
    let err =
        Pipeline::load(&cfg, Weights::Dir(&dir), Stages::All, &LoadOptions::default()).err().expect("missing file accepted").to_string();
    assert!(err.contains("ss_flow.safetensors"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Building each module per stage gives bit-identical results to resident
/// modules; the plain (candle) and fast f32 paths agree; bf16/f16 run; the
/// peak memory of each stage is reported.
#[test]
fn load_options_precision_and_per_stage() {
    use recon::engine::LoadOptions;
    use recon::model::{Compute, Precision};
    let staged_opts = LoadOptions { per_stage: true, ..Default::default() };
    let resident = Pipeline::load(&tiny_config(), Weights::Random(2), Stages::All, &LoadOptions::default()).unwrap();
    let staged = Pipeline::load(&tiny_config(), Weights::Random(2), Stages::All, &staged_opts).unwrap();
    let one = ObjectInputs { views: vec![view(resident.image_size(), 1, 0.0)] };
    let opts = RunOptions { seed: 3, ss_steps: Some(3), slat_steps: Some(2), measure_memory: true, ..Default::default() };
    let a = resident.run(&one, &opts).unwrap();
    let b = staged.run(&one, &opts).unwrap();
    assert!(same(&a, &b), "per-stage building changed the result");
    assert!(b.timings.loading > 0.0 && a.timings.loading == 0.0);
    if std::path::Path::new("/proc/self/status").exists() {
        let m = b.memory.as_ref().unwrap();
        for (name, v) in [
            ("encoder", m.image_encoder),
            ("ss flow", m.ss_flow),
            ("ss dec", m.ss_decoder),
            ("slat flow", m.slat_flow),
            ("mesh", m.mesh_decoder),
        ] {
            assert!(v.is_some_and(|x| x > 0.0), "{name}: no peak RSS");
        }
    }
    assert!(a.memory.is_some() && resident.run(&one, &RunOptions { measure_memory: false, ..opts.clone() }).unwrap().memory.is_none());

    // Plain candle path vs fast f32 kernels: same occupancy and pose up to float rounding.
    let s1 = RunOptions { seed: 3, ss_steps: Some(3), stage1_only: true, ..Default::default() };
    let plain = Pipeline::load(
        &tiny_config(),
        Weights::Random(2),
        Stages::SparseStructure,
        &LoadOptions { compute: Compute::Plain, per_stage: false },
    )
    .unwrap();
    let p = plain.run(&one, &s1).unwrap();
    let f = resident.run(&one, &s1).unwrap();
    let d = p.pose.tokens_10d.iter().flatten().zip(f.pose.tokens_10d.iter().flatten()).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
    assert!(d < 1e-3, "plain vs fast pose tokens differ by {d}");
    assert_eq!(p.coords, f.coords);
    for precision in [Precision::Bf16, Precision::F16] {
        let q = Pipeline::load(&tiny_config(), Weights::Random(2), Stages::SparseStructure, &LoadOptions::precision(precision)).unwrap();
        assert_eq!(q.load_options().compute.fast_parts().unwrap().0, precision);
        let r = q.run(&one, &s1).unwrap();
        assert!(r.pose.tokens_10d.iter().flatten().all(|v| v.is_finite()) && !r.coords.is_empty());
    }
}

/// Pair fusion (RecGen `run_pointmap_many_views`) on the tiny model: N
/// copies of the second view fused by the mean are the two-view run up to
/// float rounding, and round robin is it exactly; round robin's step 0 takes
/// pair 1 (so with one step the fused run is the (anchor, view 2) run, bit
/// for bit); stage-2 fusion runs its own pose passes and changes the result;
/// the same seed gives the same bytes; too many views are refused.
#[test]
fn fused_pairs_match_the_two_view_run() {
    let p = Pipeline::load(&tiny_config(), Weights::Random(0), Stages::All, &LoadOptions::default()).unwrap();
    let s = p.image_size();
    let (a, b, c) = (view(s, 1, 0.0), view(s, 2, 0.08), view(s, 3, -0.05));
    let inputs = |vs: &[&ViewInput]| ObjectInputs { views: vs.iter().map(|v| (*v).clone()).collect() };
    let opts = RunOptions { seed: 5, ss_steps: Some(3), slat_steps: Some(2), decode_mesh: false, ..Default::default() };
    let two = p.run(&inputs(&[&a, &b]), &opts).unwrap();
    assert!(two.metadata.fusion.is_none() && two.pose.view_tokens == 2);

    // Round robin over copies: bit-identical, stage 2 included.
    let rr = RunOptions { fusion: Fusion::Stochastic, ..opts.clone() };
    let copies = p.run(&inputs(&[&a, &b, &b, &b]), &rr).unwrap();
    // (Everything but `view_tokens`: the fused run's other tokens are not views' own.)
    assert!(copies.coords == two.coords && copies.pose.per_token == two.pose.per_token && copies.pose.tokens_10d == two.pose.tokens_10d);
    assert!(copies.pose.slat_tokens_13d == two.pose.slat_tokens_13d && copies.gaussians == two.gaussians, "round robin over copies");
    assert_eq!(copies.pose.view_tokens, 1);
    let f = copies.metadata.fusion.as_ref().unwrap();
    assert_eq!((f.pairs, f.ss, f.slat), (3, Fusion::Stochastic, SlatFusion::None));
    // The mean over copies: the same up to float rounding (stage 1 only, where it acts).
    let s1 = RunOptions { stage1_only: true, ..opts.clone() };
    let two1 = p.run(&inputs(&[&a, &b]), &s1).unwrap();
    let mean = p.run(&inputs(&[&a, &b, &b, &b]), &s1).unwrap();
    let d =
        mean.pose.tokens_10d.iter().flatten().zip(two1.pose.tokens_10d.iter().flatten()).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max);
    assert!(d < 1e-4, "mean over copies: tokens differ by {d}");
    assert_eq!(mean.coords, two1.coords);

    // Round robin takes pair (step mod N): one step uses pair 1 alone.
    let one_step = RunOptions { ss_steps: Some(1), stage1_only: true, fusion: Fusion::Stochastic, ..opts.clone() };
    let abc = p.run(&inputs(&[&a, &b, &c]), &one_step).unwrap();
    let acb = p.run(&inputs(&[&a, &c, &b]), &one_step).unwrap();
    assert_eq!(abc.pose.tokens_10d, p.run(&inputs(&[&a, &b]), &one_step).unwrap().pose.tokens_10d);
    assert_eq!(acb.pose.tokens_10d, p.run(&inputs(&[&a, &c]), &one_step).unwrap().pose.tokens_10d);
    assert_ne!(abc.pose.tokens_10d, acb.pose.tokens_10d);
    // Two steps: pair 1 then pair 2, which is neither pair alone.
    let two_steps = RunOptions { ss_steps: Some(2), ..one_step.clone() };
    let abc2 = p.run(&inputs(&[&a, &b, &c]), &two_steps).unwrap();
    assert_ne!(abc2.pose.tokens_10d, p.run(&inputs(&[&a, &b]), &two_steps).unwrap().pose.tokens_10d);
    assert_ne!(abc2.pose.tokens_10d, p.run(&inputs(&[&a, &c]), &two_steps).unwrap().pose.tokens_10d);

    // Three distinct views, both stage-2 fusions: deterministic, and stage-2
    // fusion (with its own pose passes) changes stage 2 only.
    let three = inputs(&[&a, &b, &c]);
    let md = p.run(&three, &opts).unwrap();
    assert!(same(&md, &p.run(&three, &opts).unwrap()), "same seed, same bytes");
    for slat in [SlatFusion::Multidiffusion, SlatFusion::Stochastic] {
        let fused2 = p.run(&three, &RunOptions { slat_fusion: slat, ..opts.clone() }).unwrap();
        assert_eq!((&fused2.pose, &fused2.coords), (&md.pose, &md.coords), "{slat:?}: stage 1 is the same");
        assert_ne!(fused2.gaussians, md.gaussians, "{slat:?}");
        assert_eq!(fused2.metadata.fusion.as_ref().unwrap().slat, slat);
    }

    // Too many views are refused, naming the limit.
    let many: Vec<&ViewInput> = std::iter::once(&a).chain(std::iter::repeat_n(&b, MAX_SECOND_VIEWS + 1)).collect();
    let e = p.run(&inputs(&many), &s1).unwrap_err().to_string();
    assert!(e.contains(&MAX_SECOND_VIEWS.to_string()) && e.contains("views"), "{e}");
}
