//! The exact shortcuts of a guided sampler step (issue 37 §1) at full size:
//! the flows of models/recgen-large.json on random weights, one guided step
//! (condition + all-zero `neg_cond`) on the run's prepared conditions with
//! the shortcuts against the same step computed in full, in f32 and bf16.
//! The tiny models' unit tests check the same in CI; at full size it takes
//! minutes in a release build, so it is ignored:
//! `cargo test --release --test shortcuts_fullsize -- --ignored --nocapture`
mod common;

use recon::model::{Compute, ModuleKey, Precision};
use recon::tools::bench::bench_guided;

/// The unconditional half may move by float rounding only (the constant
/// context's output row is `to_out(v)` instead of a uniform average of
/// equal value rows); so may the SLat flow's conditional half (its input
/// stage runs once for both halves, and a lone item's sparse convolutions
/// round differently than a batch of two).
const MAX_REL: f64 = 1e-6;

#[test]
#[ignore]
fn full_size_guided_step_with_shortcuts_matches_full_computation() {
    let config = common::repo().join("models/recgen-large.json");
    let computes = [Compute::fast(Precision::F32), Compute::fast(Precision::Bf16)];
    let rows = bench_guided(&config, &[ModuleKey::SsFlow, ModuleKey::SlatFlow], &computes, 1, true, |r| {
        eprintln!(
            "{:<9} {:<24} cond max rel {:.2e} ({} bits), uncond max rel {:.2e} | full {:.1} s, prepared + shortcuts {:.1} s (+ {:.1} s once per run) | {}",
            r.module,
            r.precision,
            r.max_rel_cond,
            if r.cond_same_bits { "same" } else { "different" },
            r.max_rel_uncond,
            r.full_seconds,
            r.step_seconds,
            r.prepare_seconds,
            r.input
        )
    })
    .unwrap();
    assert_eq!(rows.len(), 4, "ss_flow and slat_flow in f32 and bf16");
    for r in &rows {
        let what = format!("{} {}", r.module, r.precision);
        assert!(r.max_rel_uncond <= MAX_REL, "{what}: unconditional half {:.2e} from the full computation", r.max_rel_uncond);
        if r.module == ModuleKey::SsFlow.name() {
            // Keys and values prepared once per run are the same computation.
            assert!(r.cond_same_bits && r.max_rel_cond == 0.0, "{what}: conditional half changed ({:.2e})", r.max_rel_cond);
        } else {
            assert!(r.max_rel_cond <= MAX_REL, "{what}: conditional half {:.2e} from the full computation", r.max_rel_cond);
        }
    }
}
