// Where the shared real RGB-D data lives on development and CI machines: test
// support, so its environment variables are read here, never by the library.
// Included by the integration tests (`common::realdata`) and, with
// `include!`, by the library unit tests that use the real frames (so this
// file has no inner attributes or `//!` docs).

/// The shared real-data folder (`realdata/` beside the repository, as on the
/// development machines): `RECON_REALDATA` if set, else
/// `<workspace>/../shared/realdata`, else `/work/shared/realdata`. None when
/// none of them exists.
pub fn shared_realdata() -> Option<std::path::PathBuf> {
    use std::path::{Path, PathBuf};
    // The workspace root: the first folder above the including crate's
    // manifest that holds Cargo.lock.
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).ancestors().find(|p| p.join("Cargo.lock").is_file()).map(Path::to_path_buf);
    let candidates = [
        std::env::var_os("RECON_REALDATA").map(PathBuf::from),
        workspace.map(|w| w.join("../shared/realdata")),
        Some(PathBuf::from("/work/shared/realdata")),
    ];
    candidates.into_iter().flatten().find(|p| p.is_dir())
}

/// One dataset folder of [`shared_realdata`] (e.g. `ycbv_video_oprb`), when present.
pub fn shared_dataset(name: &str) -> Option<std::path::PathBuf> {
    shared_realdata().map(|p| p.join(name)).filter(|p| p.is_dir())
}

/// True when `RECON_REQUIRE_REALDATA=1` (CI): a test that needs the real data
/// must then fail instead of skipping.
pub fn realdata_required() -> bool {
    std::env::var("RECON_REQUIRE_REALDATA").is_ok_and(|v| v == "1")
}

/// [`shared_dataset`] (`name` = None: [`shared_realdata`]), or None with a
/// note on stderr so the test can skip. With `RECON_REQUIRE_REALDATA=1` a
/// missing folder panics instead, failing the test that asked for it (`what`
/// says which test).
pub fn realdata_for_test(name: Option<&str>, what: &str) -> Option<std::path::PathBuf> {
    let found = match name {
        Some(n) => shared_dataset(n),
        None => shared_realdata(),
    };
    if found.is_none() {
        let folder = name.map_or("realdata".to_string(), |n| format!("realdata/{n}"));
        assert!(!realdata_required(), "RECON_REQUIRE_REALDATA=1 but {folder} is missing (set RECON_REALDATA); {what} needs it");
        eprintln!("note: {folder} absent (set RECON_REALDATA); skipping {what}");
    }
    found
}
