//! Where the shared real RGB-D data lives on development and CI machines.

/// The shared real-data folder (`realdata/` beside the repository, as on the
/// development machines), for tests and examples that use the real frames:
/// `RECON_REALDATA` if set, else `<repo>/../shared/realdata`, else
/// `/work/shared/realdata`. None when none of them exists.
pub fn shared_realdata() -> Option<std::path::PathBuf> {
    use std::path::PathBuf;
    let candidates = [
        std::env::var_os("RECON_REALDATA").map(PathBuf::from),
        Some(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/realdata")),
        Some(PathBuf::from("/work/shared/realdata")),
    ];
    candidates.into_iter().flatten().find(|p| p.is_dir())
}

/// One dataset folder of [`shared_realdata`] (e.g. `ycbv_video_oprb`), when present.
pub fn shared_dataset(name: &str) -> Option<std::path::PathBuf> {
    shared_realdata().map(|p| p.join(name)).filter(|p| p.is_dir())
}
