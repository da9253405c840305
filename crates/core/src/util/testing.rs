//! Temporary folders for tests: the one helper every test of the workspace
//! uses (recon-core's unit tests here, the other crates' through recon-testkit).

use std::path::PathBuf;

/// The workspace root (models/, data/sample/, tests/fixtures/).
pub fn repo() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../.."))
}

/// A fresh, empty folder under the system temp dir, unique to this process
/// and `tag` (what was there from an earlier run is removed first). Tags must
/// differ between the tests of one test binary.
pub fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("recon-test-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}
