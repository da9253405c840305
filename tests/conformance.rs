//! Every vendored upstream fixture must reproduce within its stated tolerance.
use std::path::PathBuf;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/conformance").join(name)
}

fn assert_fixture(name: &str) {
    let checks = recon::tools::run_fixture(&fixture(name), recon::model::Compute::Plain).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert!(!checks.is_empty(), "{name}: no outputs checked");
    for c in &checks {
        eprintln!("{name}: {} max_abs {:.3e} tol {:.1e}", c.output, c.max_abs, c.tol);
        assert!(c.pass, "{name}: {} max_abs {:.3e} exceeds tol {:.1e}", c.output, c.max_abs, c.tol);
    }
}

macro_rules! fixture_tests {
    ($($test:ident => $dir:literal),* $(,)?) => {
        $( #[test] fn $test() { assert_fixture($dir); } )*
    };
}

fixture_tests! {
    dinov2_reg_cond => "dinov2_reg_cond",
    ss_flow_base => "ss_flow_base",
    ss_flow_imglarge => "ss_flow_imglarge",
    ss_flow_sharemod_qknorm_cross => "ss_flow_sharemod_qknorm_cross",
    ss_sampler_interval_cfg => "ss_sampler_interval_cfg",
    ss_sampler_interval_cfg_norescale => "ss_sampler_interval_cfg_norescale",
    ss_decoder => "ss_decoder",
    slat_flow => "slat_flow",
    slat_dec_mesh => "slat_dec_mesh",
    slat_dec_gs => "slat_dec_gs",
    flexicubes_sphere_r16 => "flexicubes_sphere_r16",
    flexicubes_box_r16_color => "flexicubes_box_r16_color",
}

/// The same fixtures with every layer built on the fast inference kernels in
/// f32 (packed GEMM, flash attention, fused norms): within the same tolerances.
fn assert_fixture_fast(name: &str) {
    use recon::model::{Compute, Precision};
    let checks =
        recon::tools::run_fixture(&fixture(name), Compute::fast(Precision::F32)).unwrap_or_else(|e| panic!("{name} (fast f32): {e}"));
    assert!(!checks.is_empty(), "{name}: no outputs checked");
    for c in &checks {
        eprintln!("{name} fast f32: {} max_abs {:.3e} tol {:.1e}", c.output, c.max_abs, c.tol);
        assert!(c.pass, "{name} fast f32: {} max_abs {:.3e} exceeds tol {:.1e}", c.output, c.max_abs, c.tol);
    }
}

macro_rules! fast_fixture_tests {
    ($($test:ident => $dir:literal),* $(,)?) => {
        $( #[test] fn $test() { assert_fixture_fast($dir); } )*
    };
}

fast_fixture_tests! {
    fast_dinov2_reg_cond => "dinov2_reg_cond",
    fast_ss_flow_base => "ss_flow_base",
    fast_ss_flow_imglarge => "ss_flow_imglarge",
    fast_ss_flow_sharemod_qknorm_cross => "ss_flow_sharemod_qknorm_cross",
    fast_ss_sampler_interval_cfg => "ss_sampler_interval_cfg",
    fast_slat_flow => "slat_flow",
    fast_slat_dec_mesh => "slat_dec_mesh",
    fast_slat_dec_gs => "slat_dec_gs",
}

/// bf16 error budget against the f32 upstream outputs: every output's max
/// abs error within 3% of that output's largest magnitude (bf16 keeps 8
/// mantissa bits, 0.4% per rounding; a few roundings accumulate per layer).
fn assert_fixture_bf16(name: &str) {
    use recon::model::{Compute, Precision};
    let dir = fixture(name);
    let fx = recon::tools::Fixture::load(&dir).unwrap();
    let checks = recon::tools::run_fixture(&dir, Compute::fast(Precision::Bf16)).unwrap_or_else(|e| panic!("{name} (bf16): {e}"));
    let mut checked = 0;
    for c in &checks {
        let Ok(want) = fx.tensor(&c.output) else { continue };
        let scale = want
            .to_dtype(candle_core::DType::F32)
            .unwrap()
            .abs()
            .unwrap()
            .flatten_all()
            .unwrap()
            .max(0)
            .unwrap()
            .to_scalar::<f32>()
            .unwrap() as f64;
        let rel = c.max_abs / scale.max(1e-12);
        eprintln!("{name} bf16: {} max_abs {:.3e} (max |ref| {scale:.3e}, rel {rel:.2e})", c.output, c.max_abs);
        assert!(
            rel <= 0.01 || c.max_abs <= c.tol,
            "{name} bf16: {} max_abs {:.3e} is {rel:.2e} of max |ref| {scale:.3e}",
            c.output,
            c.max_abs
        );
        checked += 1;
    }
    assert!(checked > 0, "{name}: no outputs checked");
}

#[test]
fn bf16_within_budget_on_transformer_fixtures() {
    for name in ["dinov2_reg_cond", "ss_flow_imglarge", "slat_flow", "slat_dec_gs"] {
        assert_fixture_bf16(name);
    }
}
