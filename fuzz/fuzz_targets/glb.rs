#![no_main]
use recon::tools::fuzz::{run, Target};

libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    let t = Target::from_name("glb").expect("target name");
    // Errors are the expected outcome for most inputs; a panic, a hang or an
    // allocation over libFuzzer's -malloc_limit_mb is a finding.
    let _ = run(t, data);
});
