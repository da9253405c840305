//! Real RGB-D data: loading the three curated datasets, and the coordinate
//! plumbing proof on YCB-Video ground truth.
//!
//! The datasets live in ../shared/realdata (not in the repository; see
//! `common::realdata::shared_realdata`); tests
//! that need them print a note and return when the folder is absent, or fail
//! with `RECON_REQUIRE_REALDATA=1` (which `.ci/run` sets). The one YCB-Video frame shipped in `data/sample/`
//! is always tested.
#![allow(clippy::needless_range_loop)] // 3×3 index loops read as the maths does

mod common;

use common::{repo, tmp};
use std::path::{Path, PathBuf};

use recon::dataset::MatFile;
use recon::dataset::{validate_objects, InstanceMap, MaskOptions};
use recon::dataset::{FrameOptions, RgbdFrame};
use recon::geometry::{canonical_to_camera, pose_to_camera, pose_to_normalised};
use recon::geometry::{object_points, prepare_object, Normaliser};
use recon::geometry::{Pose, PoseStats};
use recon::math::Similarity32;

fn realdata() -> Option<PathBuf> {
    common::realdata::realdata_for_test(None, "this real-data test")
}

fn check_ycb_frame(color: &Path) {
    let f = RgbdFrame::open(color, &FrameOptions::default()).unwrap();
    assert_eq!((f.width, f.height), (640, 480));
    let k = f.intrinsics;
    assert!((k.fx - 1066.778).abs() < 1e-3 && (k.fy - 1067.487).abs() < 1e-3, "{k:?}");
    assert!((k.cx - 312.9869).abs() < 1e-3 && (k.cy - 241.3109).abs() < 1e-3, "{k:?}");
    assert!((f.depth_scale_m - 1e-4).abs() < 1e-12, "factor_depth 10000 → 1e-4 m per unit");
    let med = f.median_valid_depth().unwrap();
    // README: "depth at the median pixel is about 0.6 to 1.2 m"; the median
    // over all valid pixels of sequence 0001 is 1.225 m, hence the margin.
    assert!((0.55..=1.3).contains(&med), "median depth {med} m");
    assert!(f.intrinsics_source.ends_with("-meta.mat"), "{}", f.intrinsics_source);
    let meta =
        MatFile::open(&color.with_file_name(color.file_name().unwrap().to_str().unwrap().replace("-color.png", "-meta.mat"))).unwrap();
    let cls = meta.get("cls_indexes").unwrap();
    let poses = meta.get("poses").unwrap();
    assert_eq!(poses.dims[..2], [3, 4]);
    assert_eq!(poses.dims.get(2).copied().unwrap_or(1), cls.len());
    println!("{}: median depth {med:.3} m, valid {:.1}%, {} objects", color.display(), f.valid_fraction() * 100.0, cls.len());
}

#[test]
fn ycb_sample_frame_in_repo_loads() {
    check_ycb_frame(&repo().join("data/sample/000001-color.png"));
}

#[test]
fn ycb_video_frames_load() {
    let Some(root) = realdata() else { return };
    for seq in ["0000", "0001", "0002"] {
        for i in 1..=5 {
            check_ycb_frame(&root.join(format!("ycbv_video_oprb/{seq}/{i:06}-color.png")));
        }
    }
}

#[test]
fn linemod_frame_loads() {
    let Some(root) = realdata() else { return };
    let f = RgbdFrame::open(&root.join("lm_benchvise_sam6d/rgb.png"), &FrameOptions::default()).unwrap();
    assert_eq!((f.width, f.height), (640, 480));
    let k = f.intrinsics;
    assert_eq!((k.fx, k.fy, k.cx, k.cy), (572.4114, 573.57043, 325.2611, 242.04899));
    assert_eq!(f.depth_scale_m, 0.001); // BOP depth_scale 1.0 = 1 mm per unit
    let med = f.median_valid_depth().unwrap();
    assert!((1.0..1.25).contains(&med), "README: median about 1.12 m, got {med}");
    let invalid = 1.0 - f.valid_fraction();
    assert!((0.02..0.10).contains(&invalid), "README: about 5% invalid, got {invalid}");
    println!("LINEMOD: median {med:.3} m, invalid {:.1}%", invalid * 100.0);
}

#[test]
fn realsense_frames_load() {
    let Some(root) = realdata() else { return };
    for i in 0..5 {
        let f = RgbdFrame::open(&root.join(format!("realsense_ycb_posecnn_pytorch/{i:06}-color.png")), &FrameOptions::default()).unwrap();
        let k = f.intrinsics;
        assert!((k.fx - 618.0173).abs() < 1e-3 && (k.fy - 618.0034).abs() < 1e-3, "{k:?}");
        assert!((k.cx - 312.3770).abs() < 1e-3 && (k.cy - 232.3753).abs() < 1e-3, "{k:?}");
        assert_eq!(f.depth_scale_m, 0.001);
        assert!(f.intrinsics_source.ends_with("meta.yml"));
        let med = f.median_valid_depth().unwrap();
        assert!((0.6..0.85).contains(&med), "README: median 0.69–0.77 m, got {med}");
        let invalid = 1.0 - f.valid_fraction();
        assert!((0.05..0.35).contains(&invalid), "README: about 17% invalid, got {invalid}");
        println!("RealSense {i}: median {med:.3} m, invalid {:.1}%", invalid * 100.0);
    }
}

const YCB_NAMES: [&str; 21] = [
    "002_master_chef_can",
    "003_cracker_box",
    "004_sugar_box",
    "005_tomato_soup_can",
    "006_mustard_bottle",
    "007_tuna_fish_can",
    "008_pudding_box",
    "009_gelatin_box",
    "010_potted_meat_can",
    "011_banana",
    "019_pitcher_base",
    "021_bleach_cleanser",
    "024_bowl",
    "025_mug",
    "035_power_drill",
    "036_wood_block",
    "037_scissors",
    "040_large_marker",
    "051_large_clamp",
    "052_extra_large_clamp",
    "061_foam_brick",
];

fn read_xyz(p: &Path) -> Vec<[f64; 3]> {
    std::fs::read_to_string(p)
        .unwrap()
        .lines()
        .filter_map(|l| {
            let v: Vec<f64> = l.split_whitespace().filter_map(|s| s.parse().ok()).collect();
            (v.len() >= 3).then(|| [v[0], v[1], v[2]])
        })
        .collect()
}

/// Nearest-point distances through a uniform grid (exact: falls back to a
/// full scan when the 27 neighbouring cells hold nothing closer than a cell).
struct Grid {
    cell: f64,
    map: std::collections::HashMap<[i64; 3], Vec<[f64; 3]>>,
    all: Vec<[f64; 3]>,
}

impl Grid {
    fn new(pts: &[[f64; 3]], cell: f64) -> Self {
        let mut map: std::collections::HashMap<[i64; 3], Vec<[f64; 3]>> = Default::default();
        for p in pts {
            map.entry(p.map(|v| (v / cell).floor() as i64)).or_default().push(*p);
        }
        Grid { cell, map, all: pts.to_vec() }
    }
    fn nearest(&self, q: [f64; 3]) -> f64 {
        let c = q.map(|v| (v / self.cell).floor() as i64);
        let d2 = |p: &[f64; 3]| (p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2);
        let mut best = f64::INFINITY;
        for dx in -1..=1 {
            for dy in -1..=1 {
                for dz in -1..=1 {
                    if let Some(v) = self.map.get(&[c[0] + dx, c[1] + dy, c[2] + dz]) {
                        for p in v {
                            best = best.min(d2(p));
                        }
                    }
                }
            }
        }
        if best.sqrt() > self.cell {
            best = self.all.iter().map(d2).fold(f64::INFINITY, f64::min);
        }
        best.sqrt()
    }
}

fn stats(mut v: Vec<f64>) -> (f64, f64) {
    let mean = v.iter().sum::<f64>() / v.len() as f64;
    v.sort_by(|a, b| a.total_cmp(b));
    (mean, v[v.len() / 2])
}

/// Ground truth through the exact code path predictions take:
/// GT object→camera pose → normalised frame (forward, with the normaliser of
/// OUR preprocessing of that object's mask + depth) → back to the camera via
/// `canonical_to_camera` → place the model points → distance from the
/// observed (eroded-mask, valid-depth) points to the nearest placed point.
#[test]
fn ycb_gt_pose_survives_normalised_frame_round_trip() {
    let Some(root) = realdata() else { return };
    let ycb = root.join("ycbv_video_oprb");
    let stats_ss = PoseStats::from_json_file(&repo().join("models/stereo_pose_stats.example.json")).unwrap();
    let mut rows = Vec::new();
    let mut worst_plumbing = 0f64;
    println!(
        "{:<6} {:<6} {:<20} {:>6} {:>7} {:>7} {:>7} {:>7} {:>7} | {:>21} {:>5} {:>6}",
        "seq", "frame", "object", "pts", "mean", "median", "<1cm%", "spacing", "no+0.5", "cube t_n", "s_n", "max|z|"
    );
    for seq in ["0000", "0001", "0002"] {
        for i in 1..=5 {
            let color = ycb.join(format!("{seq}/{i:06}-color.png"));
            let frame = RgbdFrame::open(&color, &FrameOptions::default()).unwrap();
            let meta = MatFile::open(&ycb.join(format!("{seq}/{i:06}-meta.mat"))).unwrap();
            let cls = meta.get("cls_indexes").unwrap().data.clone();
            let poses = meta.get("poses").unwrap();
            let labels = InstanceMap::open(&ycb.join(format!("{seq}/{i:06}-label.png"))).unwrap();
            let ids: Vec<u32> = cls.iter().map(|&c| c as u32).collect();
            let (objs, skips) = labels.objects(Some(&ids));
            assert!(skips.is_empty(), "{skips:?}");
            let (valid, skips) = validate_objects(&frame, objs, &MaskOptions::default());
            assert!(skips.is_empty(), "{skips:?}");
            for obj in valid {
                let id = obj.mask.id.unwrap();
                let k = ids.iter().position(|&c| c == id).unwrap();
                let name = YCB_NAMES[id as usize - 1];
                let r: [[f32; 3]; 3] = std::array::from_fn(|a| std::array::from_fn(|b| poses.at(&[a, b, k]).unwrap() as f32));
                let t: [f32; 3] = std::array::from_fn(|a| poses.at(&[a, 3, k]).unwrap() as f32);
                let gt = Pose { rotation: r, translation: t, scale: 1.0 };

                // Our preprocessing of this object (full size, as inference does).
                let view = prepare_object(&frame, &obj.mask.to_bools(), 518).unwrap();
                let nz: Normaliser = view.normaliser;
                assert_eq!(view.pointmap.dims(), &[1, 3, 518, 518]);

                // Forward to the normalised frame, then back along the prediction path.
                let pose_n = pose_to_normalised(&gt, &nz);
                let place = canonical_to_camera(&pose_n, &nz).unwrap();
                let back = pose_to_camera(&pose_n, &nz);
                let model = read_xyz(&ycb.join(format!("models_points_xyz/{name}/points.xyz")));
                let direct = Similarity32::new(r, t, 1.0).unwrap();
                let placed: Vec<[f64; 3]> = model
                    .iter()
                    .map(|p| {
                        let x = [p[0] as f32, p[1] as f32, p[2] as f32];
                        let a = place.apply(&x);
                        let b = direct.apply(&x);
                        for c in 0..3 {
                            worst_plumbing = worst_plumbing.max((a[c] - b[c]).abs() as f64);
                        }
                        [a[0] as f64, a[1] as f64, a[2] as f64]
                    })
                    .collect();
                for c in 0..3 {
                    worst_plumbing = worst_plumbing.max((back.translation[c] - t[c]).abs() as f64);
                }

                // Observed points: the same set that entered the statistics.
                let (obs, _) = object_points(&frame, &obj.mask.to_bools(), Some(Default::default())).unwrap();
                assert_eq!(obs.len(), view.num_points);
                let grid = Grid::new(&placed, 0.02);
                let d: Vec<f64> = obs.iter().map(|&q| grid.nearest(q)).collect();
                let within = d.iter().filter(|&&x| x < 0.01).count() as f64 / d.len() as f64;
                let (mean, med) = stats(d);

                // Control: dropping the 0.5 offset of the normalised frame
                // (t·d + c) must visibly break the placement.
                let wrong_t: [f32; 3] = std::array::from_fn(|a| (pose_n.translation[a] as f64 * nz.diameter + nz.centre[a]) as f32);
                let wrong = Similarity32::new(r, wrong_t, (pose_n.scale as f64 * nz.diameter) as f32).unwrap();
                let wrong_pts: Vec<[f64; 3]> =
                    model.iter().map(|p| wrong.apply(&[p[0] as f32, p[1] as f32, p[2] as f32]).map(|v| v as f64)).collect();
                let wgrid = Grid::new(&wrong_pts, 0.02);
                let (wrong_mean, _) = stats(obs.iter().step_by(7).map(|&q| wgrid.nearest(q)).collect());

                // Model sampling: mean distance between neighbouring model points.
                let mgrid = Grid::new(&model, 0.02);
                let spacing = model
                    .iter()
                    .step_by(5)
                    .map(|p| {
                        let mut best = f64::INFINITY;
                        for q in &mgrid.all {
                            let dd = ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt();
                            if dd > 0.0 {
                                best = best.min(dd);
                            }
                        }
                        best
                    })
                    .sum::<f64>()
                    / model.iter().step_by(5).count() as f64;

                // The TRELLIS-canonical unit cube of this object (bbox centred,
                // longest side 1) in the normalised frame, compared with the
                // stage-1 pose stats: translation and scale should be typical.
                let lo: [f64; 3] = std::array::from_fn(|a| model.iter().map(|p| p[a]).fold(f64::INFINITY, f64::min));
                let hi: [f64; 3] = std::array::from_fn(|a| model.iter().map(|p| p[a]).fold(f64::NEG_INFINITY, f64::max));
                let side = (0..3).map(|a| hi[a] - lo[a]).fold(0.0, f64::max);
                let bc: [f32; 3] = std::array::from_fn(|a| ((lo[a] + hi[a]) / 2.0) as f32);
                let cube_t = direct.apply(&bc);
                let cube_n = pose_to_normalised(&Pose { rotation: r, translation: cube_t, scale: side as f32 }, &nz);
                let z = stats_ss.normalize(&cube_n.to_10d()).unwrap();
                let max_z = z[6..].iter().fold(0f32, |m, v| m.max(v.abs()));

                println!(
                    "{seq:<6} {i:06} {name:<20} {:>6} {:>5.2}mm {:>5.2}mm {:>6.1}% {:>5.2}mm {:>5.0}mm | ({:.2}, {:.2}, {:.2}) {:>5.2} {:>6.2}",
                    obs.len(),
                    mean * 1e3,
                    med * 1e3,
                    within * 100.0,
                    spacing * 1e3,
                    wrong_mean * 1e3,
                    cube_n.translation[0],
                    cube_n.translation[1],
                    cube_n.translation[2],
                    cube_n.scale,
                    max_z
                );
                rows.push((name, mean, med, wrong_mean, max_z));
            }
        }
    }
    println!("max |round-trip placement − direct GT placement| = {:.3e} m", worst_plumbing);
    assert!(worst_plumbing < 2e-6, "plumbing error {worst_plumbing} m");
    assert_eq!(rows.len(), 3 * 5 + 4 * 5 + 6 * 5);
    for (name, mean, med, wrong, _) in &rows {
        assert!(*med < 0.008, "{name}: median distance {med} m is above sensor-noise level");
        assert!(*mean < 0.015, "{name}: mean distance {mean} m");
        assert!(*wrong > 3.0 * mean, "{name}: the control placement should be far off, got {wrong} m vs {mean} m");
    }
    // The unit-cube poses are typical of the stage-1 training distribution
    // (|z-score| of t and s); partly occluded objects (the mug) sit further
    // out because their visible part sets the normaliser.
    let mut zs: Vec<f32> = rows.iter().map(|r| r.4).collect();
    zs.sort_by(|a, b| a.total_cmp(b));
    assert!(zs[zs.len() / 2] < 2.0, "median |z| {}", zs[zs.len() / 2]);
}

/// Invariants of the prepared tensors on the frame shipped in the repository
/// (always runs): the normalised object points have their per-axis median at
/// 0.5 and a 5–95 % spread of their norms of exactly 0.5 (the diameter is
/// twice that spread), the tensors have the pipeline's shapes, and every
/// object of the label map is prepared.
#[test]
fn sample_frame_objects_prepare_with_recgen_invariants() {
    use recon::geometry::{prepare_frame_objects, PrepareOptions};
    let dir = repo().join("data/sample");
    let frame = RgbdFrame::open(&dir.join("000001-color.png"), &FrameOptions::default()).unwrap();
    let (objs, skips) = InstanceMap::open(&dir.join("000001-label.png")).unwrap().objects(None);
    assert!(skips.is_empty());
    assert_eq!(objs.iter().map(|o| o.id.unwrap()).collect::<Vec<_>>(), vec![8, 14, 21]);
    let s = 112; // small S keeps the test fast; the geometry does not depend on S
    let (prepared, skips) = prepare_frame_objects(&frame, objs, s, 100, &PrepareOptions::default(), &candle_core::Device::Cpu);
    assert!(skips.is_empty(), "{skips:?}");
    assert_eq!(prepared.len(), 3);
    for p in &prepared {
        let v = &p.view;
        assert_eq!(v.pixel_values.dims(), &[1, 3, s, s]);
        assert_eq!(v.pointmap.dims(), &[1, 3, s, s]);
        assert_eq!(v.mask.dims(), &[1, 1, s, s]);
        let (pts, _) = object_points(&frame, &p.object.to_bools(), Some(Default::default())).unwrap();
        let q: Vec<[f64; 3]> = pts.iter().map(|&x| v.normaliser.to_normalised(x)).collect();
        let mut norms: Vec<f64> = q.iter().map(|x| ((x[0] - 0.5).powi(2) + (x[1] - 0.5).powi(2) + (x[2] - 0.5).powi(2)).sqrt()).collect();
        norms.sort_by(|a, b| a.total_cmp(b));
        let qt = |f: f64| {
            let pos = f * (norms.len() - 1) as f64;
            let lo = pos.floor() as usize;
            norms[lo] + (norms[(lo + 1).min(norms.len() - 1)] - norms[lo]) * (pos - lo as f64)
        };
        assert!((qt(0.95) - qt(0.05) - 0.5).abs() < 1e-9, "spread {}", qt(0.95) - qt(0.05));
        for a in 0..3 {
            let mut c: Vec<f64> = q.iter().map(|x| x[a]).collect();
            c.sort_by(|x, y| x.total_cmp(y));
            let n = c.len();
            let med = if n % 2 == 1 { c[n / 2] } else { 0.5 * (c[n / 2 - 1] + c[n / 2]) };
            assert!((med - 0.5).abs() < 1e-9);
        }
        let pm = v.pointmap.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(pm.iter().all(|x| x.is_finite() && (-2.0..=3.0).contains(x)));
        let mk = v.mask.sum_all().unwrap().to_scalar::<f32>().unwrap();
        assert!(mk > 100.0, "{mk}");
        let px = v.pixel_values.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        assert!(px.iter().all(|x| x.is_finite() && x.abs() < 3.0));
        println!(
            "{}: {} points, centre {:?} m, diameter {:.4} m, crop {:?}",
            p.object.label,
            v.num_points,
            v.normaliser.centre.map(|c| (c * 1e4).round() / 1e4),
            v.normaliser.diameter,
            v.crop
        );
    }
}

// ---------------------------------------------------------------------------
// `recon infer` end to end on the three real datasets (random tiny weights).

/// Run `recon infer … --json` and return the parsed summary.
fn run_infer(args: &[String]) -> serde_json::Value {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_recon"))
        .arg("infer")
        .args(args)
        .args(["--steps", "1", "--json", "--weights", "random", "--colour", "texture"])
        .current_dir(repo())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    // 0: every object written; 3: some were skipped (listed in the summary), the rest written.
    assert!(matches!(out.status.code(), Some(0 | 3)), "recon infer {args:?} failed ({:?}):\n{err}", out.status.code());
    assert!(err.contains("RANDOM weights"), "the random-weights notice is missing: {err}");
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| panic!("--json output: {e}\n{}", String::from_utf8_lossy(&out.stdout)))
}

/// A GLB file: header, JSON chunk and BIN chunk in place; returns the JSON.
fn check_glb(path: &Path) -> serde_json::Value {
    let b = std::fs::read(path).unwrap();
    let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap()) as usize;
    assert_eq!(&b[0..4], b"glTF", "{}", path.display());
    assert_eq!(u32_at(4), 2);
    assert_eq!(u32_at(8), b.len());
    let jlen = u32_at(12);
    assert_eq!(&b[16..20], b"JSON");
    let doc: serde_json::Value = serde_json::from_slice(&b[20..20 + jlen]).unwrap();
    assert_eq!(&b[20 + jlen + 4..20 + jlen + 8], b"BIN\0");
    assert_eq!(20 + jlen + 8 + u32_at(20 + jlen), b.len());
    assert_eq!(doc["asset"]["version"], "2.0");
    doc
}

/// Every file of a `recon infer` output folder, and the summary's fields.
fn check_infer_outputs(summary: &serde_json::Value, views: usize) {
    let out = PathBuf::from(summary["out"].as_str().unwrap());
    assert!(out.join("recon-output.json").is_file());
    let objects = summary["objects"].as_array().unwrap();
    assert!(!objects.is_empty(), "no object reconstructed: {summary}");
    assert_eq!(summary["views"], views);
    for k in ["encoder", "ss_sampling", "ss_decoder", "shape_fit", "slat_sampling", "mesh", "gaussians", "decimate", "select", "total"] {
        assert!(summary["stage_totals_s"][k].as_f64().is_some(), "stage_totals_s.{k}");
    }
    assert!(summary["stage_totals_s"]["total"].as_f64().unwrap() > 0.0);
    for o in objects {
        let files = &o["files"];
        let pose: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(files["pose"].as_str().unwrap()).unwrap()).unwrap();
        // Rotation (proper, orthonormal), translation in metres, scale, sampler settings and seed.
        let r: Vec<Vec<f64>> = serde_json::from_value(pose["rotation"].clone()).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                let d: f64 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
                assert!((d - if i == j { 1.0 } else { 0.0 }).abs() < 1e-4, "{r:?}");
            }
        }
        let t: Vec<f64> = serde_json::from_value(pose["translation_m"].clone()).unwrap();
        assert!(t.len() == 3 && t.iter().all(|x| x.is_finite()));
        assert!(pose["scale_m"].as_f64().unwrap() > 0.0);
        assert!(pose["frame"].as_str().unwrap().contains("camera"));
        assert!(
            pose["run"]["seed"].as_u64().is_some() && pose["run"]["ss_sampler"]["steps"] == 1 && pose["run"]["slat_sampler"]["steps"] == 1
        );
        assert_eq!(pose["run"]["random_weights"], true);
        assert!(pose["selection"]["method"].is_string() && pose["selection"]["score_m"].as_f64().unwrap().is_finite());
        let pv = pose["views"].as_array().unwrap();
        assert_eq!(pv.len(), views);
        // The predicted object sits where its points were observed (random weights: within its
        // own extent). That is the token's pose: the depth fit (`--pose-fit depth`, the default)
        // then moves it to wherever the random mesh best meets the depth, by at most √3 of its
        // scale (the refinement's bound).
        let c: Vec<f64> = serde_json::from_value(pv[0]["normaliser_centre_m"].clone()).unwrap();
        let tok: Vec<f64> = serde_json::from_value(pv[0]["pose_own_token"]["translation"].clone()).unwrap();
        let dist = |a: &[f64], b: &[f64]| ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        assert!(
            dist(&tok, &c) < 0.5 * pv[0]["normaliser_diameter_m"].as_f64().unwrap() + 0.05,
            "token translation {tok:?} vs observed centre {c:?}"
        );
        if views == 1 {
            let s_tok = pv[0]["pose_own_token"]["scale"].as_f64().unwrap();
            assert!(dist(&t, &tok) <= 3f64.sqrt() * s_tok * 1.0001 + 1e-6, "refined {t:?} vs token {tok:?} (scale {s_tok})");
            let ratio = pose["scale_m"].as_f64().unwrap() / s_tok;
            assert!((0.5 - 1e-6..=2.0 + 1e-6).contains(&ratio), "refined scale ratio {ratio}");
        }
        assert!(o["stage_seconds"]["total"].as_f64().unwrap() > 0.0);
        let mesh = check_glb(Path::new(files["mesh_glb"].as_str().unwrap()));
        // `--colour texture`: UVs and an embedded PNG, baked from the photo.
        let attrs = &mesh["meshes"][0]["primitives"][0]["attributes"];
        assert!(attrs.get("POSITION").is_some() && attrs.get("TEXCOORD_0").is_some() && attrs.get("COLOR_0").is_none());
        assert_eq!(mesh["images"][0]["mimeType"], "image/png");
        assert!(pose["texture"]["texels_from_views"].as_u64().unwrap() > 0, "no texel seen by the photo: {}", pose["texture"]);
        let ply = std::fs::read(files["gaussians_ply"].as_str().unwrap()).unwrap();
        assert!(ply.starts_with(b"ply\n"));
    }
    let scene = check_glb(&out.join("scene.glb"));
    let meshes = scene["meshes"].as_array().unwrap();
    assert_eq!(meshes.len(), 2 * objects.len(), "one mesh and one observed cloud per object");
    let points: Vec<&serde_json::Value> = meshes.iter().filter(|m| m["primitives"][0]["mode"] == 0).collect();
    assert_eq!(points.len(), objects.len());
    for p in points {
        let acc = &scene["accessors"][p["primitives"][0]["attributes"]["POSITION"].as_u64().unwrap() as usize];
        assert!(acc["count"].as_u64().unwrap() > 100);
    }
    println!("{}: {}", out.display(), serde_json::to_string(&summary["stage_totals_s"]).unwrap());
}

/// YCB-Video: the label map is the instance mask; the face budget is applied.
#[test]
fn infer_cli_ycb_video() {
    let Some(root) = realdata() else { return };
    let d = root.join("ycbv_video_oprb/0000");
    let tmp = tmp("ycb");
    let s = |p: PathBuf| p.to_string_lossy().to_string();
    let summary = run_infer(&[
        "--rgbd".into(),
        s(d.join("000001-color.png")),
        "--masks".into(),
        s(d.join("000001-label.png")),
        "--objects".into(),
        "21".into(),
        "--max-faces".into(),
        "600000".into(),
        "--out".into(),
        s(tmp.join("out")),
    ]);
    check_infer_outputs(&summary, 1);
    let o = &summary["objects"][0];
    let (faces, decoded) = (o["faces"].as_u64().unwrap(), o["faces_decoded"].as_u64().unwrap());
    assert!(faces <= 600_000 && (decoded <= 600_000 || faces < decoded), "{faces} of {decoded}");
    let _ = std::fs::remove_dir_all(&tmp);
}

/// LINEMOD ships no mask: a depth-based one for the watering can (pixels of
/// a box around it standing ≥ 15 mm in front of the board, the board depth
/// taken per row just left and right of the box).
#[test]
fn infer_cli_linemod_with_depth_mask() {
    let Some(root) = realdata() else { return };
    let d = root.join("lm_benchvise_sam6d");
    let frame = RgbdFrame::open(&d.join("rgb.png"), &FrameOptions::default()).unwrap();
    let (w, h) = (frame.width, frame.height);
    let (x0, x1, y0, y1) = (370, 440, 225, 315);
    let mut mask = image::GrayImage::new(w as u32, h as u32);
    let mut n = 0;
    for y in y0..y1 {
        let mut side: Vec<f32> = (x0 - 8..x0).chain(x1..x1 + 8).map(|x| frame.depth_m[y * w + x]).filter(|z| *z > 0.0).collect();
        side.sort_by(|a, b| a.total_cmp(b));
        let board = side[side.len() / 2];
        for x in x0..x1 {
            let z = frame.depth_m[y * w + x];
            if z > 0.0 && z < board - 0.015 {
                mask.put_pixel(x as u32, y as u32, image::Luma([255]));
                n += 1;
            }
        }
    }
    assert!(n > 2000, "{n} mask pixels");
    let tmp = tmp("lm");
    mask.save(tmp.join("can-mask.png")).unwrap();
    let s = |p: PathBuf| p.to_string_lossy().to_string();
    let summary = run_infer(&[
        "--rgbd".into(),
        s(d.join("rgb.png")),
        "--masks".into(),
        s(tmp.join("can-mask.png")),
        "--max-faces".into(),
        "0".into(),
        "--out".into(),
        s(tmp.join("out")),
    ]);
    check_infer_outputs(&summary, 1);
    let _ = std::fs::remove_dir_all(&tmp);
}

/// RealSense: PoseCNN's predicted label map (not ground truth) as the instance mask.
#[test]
fn infer_cli_realsense_with_posecnn_labels() {
    let Some(root) = realdata() else { return };
    let d = root.join("realsense_ycb_posecnn_pytorch");
    let mat = MatFile::open(&d.join("posecnn_predictions/000000-color.png.mat")).unwrap();
    let labels = mat.get("labels").unwrap();
    assert_eq!(labels.dims, vec![480, 640]);
    let mut img = image::GrayImage::new(640, 480);
    for y in 0..480 {
        for x in 0..640 {
            img.put_pixel(x as u32, y as u32, image::Luma([labels.at(&[y, x]).unwrap() as u8]));
        }
    }
    let tmp = tmp("rs");
    img.save(tmp.join("labels.png")).unwrap();
    let s = |p: PathBuf| p.to_string_lossy().to_string();
    // Class 5 = mustard bottle (README).
    let summary = run_infer(&[
        "--rgbd".into(),
        s(d.join("000000-color.png")),
        "--masks".into(),
        s(tmp.join("labels.png")),
        "--objects".into(),
        "5".into(),
        "--max-faces".into(),
        "0".into(),
        "--out".into(),
        s(tmp.join("out")),
    ]);
    check_infer_outputs(&summary, 1);
    let _ = std::fs::remove_dir_all(&tmp);
}

/// 4×4 GT object-to-camera pose of the object at column `k` of a YCB meta file.
fn ycb_gt(meta: &MatFile, k: usize) -> [[f64; 4]; 4] {
    let p = meta.get("poses").unwrap();
    let mut m = [[0.0; 4]; 4];
    for a in 0..3 {
        for b in 0..4 {
            m[a][b] = if p.dims.len() == 3 { p.at(&[a, b, k]).unwrap() } else { p.at(&[a, b]).unwrap() };
        }
    }
    m[3][3] = 1.0;
    m
}

fn mat4_mul(a: &[[f64; 4]; 4], b: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..4).map(|k| a[i][k] * b[k][j]).sum()))
}

fn rigid_inv(a: &[[f64; 4]; 4]) -> [[f64; 4]; 4] {
    let mut m = [[0.0; 4]; 4];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = a[j][i];
        }
        m[i][3] = -(0..3).map(|k| a[k][i] * a[k][3]).sum::<f64>();
    }
    m[3][3] = 1.0;
    m
}

/// `T_c1_c2 = T_c1_obj · T_c2_obj⁻¹` from the GT poses of object column `k`.
fn ycb_rel_pose(seq: &Path, f1: usize, f2: usize, k: usize) -> [[f64; 4]; 4] {
    let m1 = MatFile::open(&seq.join(format!("{f1:06}-meta.mat"))).unwrap();
    let m2 = MatFile::open(&seq.join(format!("{f2:06}-meta.mat"))).unwrap();
    mat4_mul(&ycb_gt(&m1, k), &rigid_inv(&ycb_gt(&m2, k)))
}

/// Two YCB-Video frames of one sequence with the relative camera pose from
/// their GT object poses (written as a `T_c1_c2` JSON file).
#[test]
fn infer_cli_two_view_ycb_video() {
    let Some(root) = realdata() else { return };
    let d = root.join("ycbv_video_oprb/0000");
    let tmp = tmp("ycb2");
    let rel = ycb_rel_pose(&d, 1, 5, 0);
    std::fs::write(tmp.join("rel.json"), serde_json::json!({ "T_c1_c2": rel }).to_string()).unwrap();
    let s = |p: PathBuf| p.to_string_lossy().to_string();
    let summary = run_infer(&[
        "--rgbd".into(),
        s(d.join("000001-color.png")),
        "--masks".into(),
        s(d.join("000001-label.png")),
        "--view2".into(),
        s(d.join("000005-color.png")),
        "--masks2".into(),
        s(d.join("000005-label.png")),
        "--rel-pose".into(),
        s(tmp.join("rel.json")),
        "--objects".into(),
        "8".into(),
        "--select".into(),
        "cross".into(),
        "--max-faces".into(),
        "0".into(),
        "--out".into(),
        s(tmp.join("out")),
    ]);
    check_infer_outputs(&summary, 2);
    let o = &summary["objects"][0];
    let views = o["views"].as_array().unwrap();
    assert!(views[1]["frame"].as_str().unwrap().ends_with("000005-color.png"));
    // The selected pose seen from camera 2, mapped with T_c1_c2, is the reported camera-1 pose.
    let p2 = &views[1]["pose_selected"];
    let t2: Vec<f64> = serde_json::from_value(p2["translation"].clone()).unwrap();
    let t1: Vec<f64> = serde_json::from_value(o["translation_m"].clone()).unwrap();
    for a in 0..3 {
        let mapped = (0..3).map(|b| rel[a][b] * t2[b]).sum::<f64>() + rel[a][3];
        assert!((mapped - t1[a]).abs() < 1e-5, "{mapped} vs {}", t1[a]);
    }
    let pose: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(o["files"]["pose"].as_str().unwrap()).unwrap()).unwrap();
    // The shape fit (default) fixes one pose per sample before stage 2; it used both views.
    assert_eq!(pose["candidates"].as_array().unwrap().len(), 1);
    assert!(pose["shape_fit"]["shell_voxels"].as_u64().unwrap() > 0);
    assert_eq!(pose["run"]["num_views"], 2);
    let _ = std::fs::remove_dir_all(&tmp);
}

/// Pose scoring on real depth: the BOP meshes of the master chef can and the
/// cracker box (YCB-Video 0001), placed at their GT poses through the same
/// normalised-frame → camera-frame code path as predictions, against the
/// observed points of frame 1 (`single`) and of frames 1 and 5 (`cross`, via
/// the GT relative pose); a pose 1 cm / 5° off must score clearly worse.
#[test]
fn alignment_scores_gt_meshes_on_real_depth() {
    use recon::dataset::read_ply;
    use recon::engine::{score_candidate, AlignOptions, Surface, ViewPoints};
    use recon::geometry::pose_to_similarity;
    use recon::math::{axis_angle, Similarity as Sim64};
    let Some(root) = realdata() else { return };
    let ycb = root.join("ycbv_video_oprb");
    let seq = ycb.join("0001");
    let opts = AlignOptions::default();
    let load = |f: usize| {
        let frame = RgbdFrame::open(&seq.join(format!("{f:06}-color.png")), &FrameOptions::default()).unwrap();
        let labels = InstanceMap::open(&seq.join(format!("{f:06}-label.png"))).unwrap();
        (frame, labels, MatFile::open(&seq.join(format!("{f:06}-meta.mat"))).unwrap())
    };
    let (f1, l1, m1) = load(1);
    let (f5, l5, _) = load(5);
    let cls: Vec<u32> = m1.get("cls_indexes").unwrap().data.iter().map(|&c| c as u32).collect();
    // (class id, BOP model, README offset x_bop_mm = 1000·x_ycbv_m + offset)
    for (id, ply, off) in [(1u32, "obj_000001.ply", [1.39, -0.45, 3.60]), (2, "obj_000002.ply", [0.61, 1.76, 4.77])] {
        let k = cls.iter().position(|&c| c == id).unwrap();
        let mut mesh = read_ply(&ycb.join("models_bop_ply_recentred").join(ply)).unwrap();
        for v in mesh.vertices.iter_mut() {
            *v = std::array::from_fn(|a| (v[a] - off[a]) / 1000.0);
        }
        let surface = Surface::new(mesh, 50_000, 0).unwrap();
        let pts = |f: &RgbdFrame, l: &InstanceMap| {
            let (o, _) = l.objects(Some(&[id]));
            object_points(f, &o[0].to_bools(), Some(Default::default())).unwrap().0
        };
        let (p1, p5) = (pts(&f1, &l1), pts(&f5, &l5));
        let g = ycb_gt(&m1, k);
        let gt = Pose {
            rotation: std::array::from_fn(|a| std::array::from_fn(|b| g[a][b] as f32)),
            translation: std::array::from_fn(|a| g[a][3] as f32),
            scale: 1.0,
        };
        // Through the prediction path: normalised frame of OUR preprocessing, back to the camera.
        let nz = Normaliser::fit(&p1, 0.05).unwrap();
        let placed = pose_to_similarity(&pose_to_camera(&pose_to_normalised(&gt, &nz), &nz));
        let rel = ycb_rel_pose(&seq, 1, 5, k);
        let to1 = Sim64 {
            rotation: std::array::from_fn(|a| std::array::from_fn(|b| rel[a][b])),
            translation: [rel[0][3], rel[1][3], rel[2][3]],
            scale: 1.0,
        };
        let views =
            [ViewPoints { points: p1, to_anchor: Sim64::identity(), depth: None }, ViewPoints { points: p5, to_anchor: to1, depth: None }];
        let good = score_candidate(&surface, &placed, 0, &views, &opts);
        let off_pose = Sim64 { translation: [placed.translation[0] + 0.01, placed.translation[1], placed.translation[2]], ..placed }
            .compose(&Sim64 { rotation: axis_angle([0.0, 0.0, 1.0], 5f64.to_radians()), translation: [0.0; 3], scale: 1.0 });
        let bad = score_candidate(&surface, &off_pose, 0, &views, &opts);
        println!(
            "{ply} (id {id}): GT pose trimmed-mean distance view 1 {:.2} mm, view 5 {:.2} mm, cross {:.2} mm; 1 cm/5° off: single {:.2} mm, cross {:.2} mm",
            good.per_view_m[0] * 1e3,
            good.per_view_m[1] * 1e3,
            good.cross() * 1e3,
            bad.single() * 1e3,
            bad.cross() * 1e3
        );
        assert!(good.single() < 0.006 && good.cross() < 0.006, "{good:?}");
        assert!(bad.single() > 1.5 * good.single() && bad.cross() > 1.5 * good.cross(), "{bad:?} vs {good:?}");
    }
}
