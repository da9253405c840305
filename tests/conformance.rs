//! Every vendored upstream fixture must reproduce within its stated tolerance.
use std::path::PathBuf;

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/conformance").join(name)
}

fn assert_fixture(name: &str) {
    let checks = recon::conformance::run_fixture(&fixture(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
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
