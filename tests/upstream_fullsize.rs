//! recon on checkpoints stored the way the released ones are (fp16
//! safetensors + `{name, args}` JSON under `ckpts/`, released file names),
//! written by upstream PyTorch through `benches/upstream/harness.py --save`,
//! against upstream's outputs on the same inputs.
//!
//! The tiny fixture runs in CI. The full-size check needs the harness's
//! output (a TRELLIS checkout and torch), so it is ignored:
//! `python3 benches/upstream/harness.py --trellis /path/to/TRELLIS --save /tmp/fullsize`
//! (`--dinov2 /path/to/dinov2 --modules ss_flow,ss_decoder,dinov2` adds DINOv2 ViT-L/14-reg)
//! `RECON_UPSTREAM_DIR=/tmp/fullsize cargo test --release --test upstream_fullsize -- --ignored`
//!
//! The stage-2 sparse modules (RecGen's SLat flow as released: `.pt` + `slat_config.json`;
//! TRELLIS's SLat Gaussian decoder: `ckpts/` fp16 safetensors) come from
//! `benches/upstream/sparse_fullsize.py --save DIR --trellis T --recgen R --modules slat_flow,slat_dec_gs`,
//! which also runs upstream in float64; `RECON_UPSTREAM_SPARSE_DIR=DIR` runs the ignored
//! `full_size_sparse_modules_match_upstream_float64`.
mod common;

use recon::model::{Compute, Precision};
use recon::tools::upstream::{check_released, check_sparse, ReleasedRow};
use std::path::Path;

/// f32 on the stored fp16 values against upstream f32 on the same values:
/// only summation order differs, so well inside one fp16 rounding (2⁻¹¹).
const F32_MAX_REL: f64 = 1.0 / 2048.0;
/// recon bf16 against upstream f32 (mean relative error): the 1 % bf16
/// budget of the README, or 1.5× upstream's own bf16 autocast error where
/// upstream itself exceeds 1 % (its bf16 SS decoder: 1.03e-2); and never
/// worse than twice upstream's own.
const BF16_MEAN_REL: f64 = 0.01;
const BF16_VS_UPSTREAM_BF16: f64 = 1.5;

/// DINOv2 (fp32 weights) in f32 against upstream's float64 run: no farther than this
/// multiple of upstream f32's own distance from float64 (issue 36: full-size activations
/// make a fixed absolute tolerance meaningless), with a floor for tiny models where
/// upstream's own distance is at rounding level.
const F32_VS_F64_MULTIPLE: f64 = 4.0;
const F32_VS_F64_FLOOR: f64 = 1e-5;

fn check(dir: &Path) -> Vec<ReleasedRow> {
    let rows = check_released(dir, &[Compute::fast(Precision::F32), Compute::fast(Precision::Bf16)]).unwrap();
    for r in &rows {
        eprintln!("{:<11} {:<28} vs {:<24} max rel {:.2e} mean rel {:.2e}", r.module, r.compute, r.reference, r.max_rel, r.mean_rel);
    }
    if rows.iter().any(|r| r.module == "dinov2") {
        let get = |compute: &str, reference: &str| {
            rows.iter()
                .find(|r| r.module == "dinov2" && r.compute.starts_with(compute) && r.reference == reference)
                .unwrap_or_else(|| panic!("dinov2: no row {compute} vs {reference}"))
        };
        let ours = get("fast f32", "upstream f64");
        let theirs = get("upstream f32", "upstream f64");
        for (what, a, b) in [("max", ours.max_rel, theirs.max_rel), ("mean", ours.mean_rel, theirs.mean_rel)] {
            let budget = (F32_VS_F64_MULTIPLE * b).max(F32_VS_F64_FLOOR);
            assert!(a <= budget, "dinov2 f32 vs float64: {what} rel {a:.2e} > {budget:.2e} (upstream f32's own: {b:.2e})");
        }
        let bf16 = get("fast bf16", "upstream f32");
        let theirs = get("upstream bf16 autocast", "upstream f32");
        let budget = BF16_MEAN_REL.max(BF16_VS_UPSTREAM_BF16 * theirs.mean_rel);
        assert!(bf16.mean_rel <= budget, "dinov2 bf16: mean rel {:.2e} > {budget:.2e}", bf16.mean_rel);
    }
    let released: Vec<&str> = ["ss_flow", "ss_decoder"].into_iter().filter(|m| rows.iter().any(|r| r.module == *m)).collect();
    for module in released {
        let get = |compute: &str, reference: &str| {
            rows.iter()
                .find(|r| r.module == module && r.compute.starts_with(compute) && r.reference == reference)
                .unwrap_or_else(|| panic!("{module}: no row {compute} vs {reference}"))
        };
        let f32 = get("fast f32", "upstream f32");
        assert!(f32.max_rel <= F32_MAX_REL, "{module} f32: max rel {:.2e} > {F32_MAX_REL:.2e}", f32.max_rel);
        let bf16 = get("fast bf16", "upstream f32");
        let theirs = get("upstream bf16 autocast", "upstream f32");
        let budget = BF16_MEAN_REL.max(BF16_VS_UPSTREAM_BF16 * theirs.mean_rel);
        assert!(bf16.mean_rel <= budget, "{module} bf16: mean rel {:.2e} > {budget:.2e}", bf16.mean_rel);
        assert!(
            bf16.mean_rel <= 2.0 * theirs.mean_rel.max(F32_MAX_REL),
            "{module} bf16: mean rel {:.2e}, upstream's own bf16 {:.2e}",
            bf16.mean_rel,
            theirs.mean_rel
        );
    }
    rows
}

#[test]
fn tiny_released_layout_loads_unchanged_and_matches_upstream() {
    let rows = check(&common::repo().join("tests/fixtures/upstream_tiny"));
    assert!(rows.iter().any(|r| r.module == "ss_flow") && rows.iter().any(|r| r.module == "ss_decoder"));
}

/// DINOv2 stored as torch.hub stores it (a `torch.save` state dict under the hub's file
/// name), read by recon's own `.pth` reader, against upstream's f32 and float64 runs.
#[test]
fn tiny_dinov2_hub_checkpoint_matches_upstream() {
    let rows = check(&common::repo().join("tests/fixtures/upstream_tiny_dinov2"));
    assert!(rows.iter().any(|r| r.module == "dinov2" && r.reference == "upstream f64"), "{rows:?}");
}

/// A config that does not describe the stored tensors is refused by the
/// strict loader, naming the file and the tensor.
#[test]
fn a_checkpoint_that_does_not_match_its_config_is_refused() {
    let src = common::repo().join("tests/fixtures/upstream_tiny");
    let dir = common::tmp("upstream_tiny_bad");
    std::fs::create_dir_all(dir.join("ckpts")).unwrap();
    for f in ["reference.safetensors", "ckpts/ss_flow_img_dit_L_16l8_fp16.safetensors"] {
        std::fs::copy(src.join(f), dir.join(f)).unwrap();
    }
    let json = std::fs::read_to_string(src.join("ckpts/ss_flow_img_dit_L_16l8_fp16.json")).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&json).unwrap();
    v["args"]["num_blocks"] = serde_json::json!(3);
    std::fs::write(dir.join("ckpts/ss_flow_img_dit_L_16l8_fp16.json"), v.to_string()).unwrap();
    let err = check_released(&dir, &[Compute::fast(Precision::F32)]).unwrap_err().to_string();
    assert!(err.contains("ss_flow_img_dit_L_16l8_fp16.safetensors") && err.contains("blocks.2"), "{err}");
}

#[test]
#[ignore]
fn full_size_released_layout_matches_upstream() {
    let dir =
        std::env::var("RECON_UPSTREAM_DIR").expect("set RECON_UPSTREAM_DIR to a folder written by benches/upstream/harness.py --save");
    let rows = check(Path::new(&dir));
    assert!(rows.iter().any(|r| r.module == "ss_flow" || r.module == "dinov2"), "no full-size module in {dir}");
}

/// recon f32 against upstream's float64 run, for every output of every sparse module found:
/// no farther than `F32_VS_F64_MULTIPLE` × upstream f32's own distance from float64 (floor
/// `F32_VS_F64_FLOOR`), for the max and the mean relative error.
fn check_sparse_dir(dir: &Path) -> Vec<ReleasedRow> {
    let rows = check_sparse(dir, &[Compute::fast(Precision::F32)]).unwrap();
    for r in &rows {
        eprintln!(
            "{:<15} {:<28} vs {:<13} max rel {:.2e} mean rel {:.2e} ({:.1} s)",
            r.module, r.compute, r.reference, r.max_rel, r.mean_rel, r.forward_seconds
        );
    }
    let mut modules: Vec<&str> = rows.iter().map(|r| r.module.as_str()).collect();
    modules.dedup();
    for module in modules {
        let get = |compute: &str, reference: &str| {
            rows.iter()
                .find(|r| r.module == module && r.compute.starts_with(compute) && r.reference == reference)
                .unwrap_or_else(|| panic!("{module}: no row {compute} vs {reference}"))
        };
        let ours = get("fast f32", "upstream f64");
        let theirs = get("upstream f32", "upstream f64");
        for (what, a, b) in [("max", ours.max_rel, theirs.max_rel), ("mean", ours.mean_rel, theirs.mean_rel)] {
            let budget = (F32_VS_F64_MULTIPLE * b).max(F32_VS_F64_FLOOR);
            assert!(a <= budget, "{module} f32 vs float64: {what} rel {a:.2e} > {budget:.2e} (upstream f32's own: {b:.2e})");
        }
    }
    rows
}

/// RecGen's stage-2 flow stored as released (a `torch.save` state dict and `slat_config.json`),
/// read by recon's `.pt` reader, its condition (point-map, mask and pose embedders) and
/// velocity, and TRELLIS's SLat Gaussian decoder (`ckpts/`, fp16 safetensors), its out-layer
/// features and Gaussians, against upstream's f32 and float64 runs.
#[test]
fn tiny_stage2_release_matches_upstream_float64() {
    let rows = check_sparse_dir(&common::repo().join("tests/fixtures/upstream_tiny_slat"));
    for m in ["slat_flow", "slat_flow.cond", "slat_dec_gs.feats", "slat_dec_gs.xyz", "slat_dec_gs.opacity"] {
        assert!(rows.iter().any(|r| r.module == m && r.reference == "upstream f64"), "{m}: {rows:?}");
    }
}

/// A stage-2 config whose args do not describe the stored tensors is refused by the strict
/// loader, naming the `.pt` file and the tensor.
#[test]
fn a_slat_flow_pt_that_does_not_match_its_config_is_refused() {
    let src = common::repo().join("tests/fixtures/upstream_tiny_slat");
    let dir = common::tmp("upstream_tiny_slat_bad");
    std::fs::create_dir_all(&dir).unwrap();
    for f in ["sparse_reference.safetensors", "slat_denoiser_ema0.9999_step0075000.pt"] {
        std::fs::copy(src.join(f), dir.join(f)).unwrap();
    }
    let mut v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(src.join("slat_config.json")).unwrap()).unwrap();
    v["models"]["denoiser"]["args"]["num_blocks"] = serde_json::json!(3);
    std::fs::write(dir.join("slat_config.json"), v.to_string()).unwrap();
    let err = check_sparse(&dir, &[Compute::fast(Precision::F32)]).unwrap_err().to_string();
    assert!(err.contains("slat_denoiser_ema0.9999_step0075000.pt") && err.contains("blocks.2"), "{err}");
}

#[test]
#[ignore]
fn full_size_sparse_modules_match_upstream_float64() {
    let dir = std::env::var("RECON_UPSTREAM_SPARSE_DIR")
        .expect("set RECON_UPSTREAM_SPARSE_DIR to a folder written by benches/upstream/sparse_fullsize.py --save");
    let rows = check_sparse_dir(Path::new(&dir));
    assert!(rows.iter().any(|r| r.module == "slat_flow" || r.module.starts_with("slat_dec")), "no sparse module in {dir}");
}
