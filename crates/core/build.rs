//! Finds the trained recgen-nano to compile into recon-core (`engine::source`).
//!
//! Its 27 MB do not fit a crates.io package (10 MB), so the packaged crate does not carry
//! them: a build from a checkout embeds `models/recgen-nano/` of the repository; a build
//! from the published package embeds nothing unless `RECON_NANO_DIR` names a folder holding
//! the model's files (then `recon infer` without `--weights` says how to get weights).

use std::path::{Path, PathBuf};

/// The files `engine::source::EMBEDDED_NANO` includes, every one required.
const FILES: [&str; 8] = [
    "recgen-nano.json",
    "pose_stats.json",
    "image_cond_model.safetensors",
    "ss_flow.safetensors",
    "ss_decoder.safetensors",
    "slat_flow.safetensors",
    "slat_dec_mesh.safetensors",
    "slat_dec_gs.safetensors",
];

fn main() {
    println!("cargo::rustc-check-cfg=cfg(recon_embedded_nano)");
    println!("cargo::rerun-if-env-changed=RECON_NANO_DIR");
    let manifest = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR"));
    let dir = match std::env::var_os("RECON_NANO_DIR") {
        Some(d) => {
            let d = PathBuf::from(d);
            if let Some(missing) = FILES.iter().find(|f| !d.join(f).is_file()) {
                panic!("RECON_NANO_DIR={}: no {missing} there (a recgen-nano folder holds {FILES:?})", d.display());
            }
            Some(d)
        }
        // An unpacked package (it holds Cargo.toml.orig) is no checkout: whatever lies two
        // folders up is not this crate's repository.
        None if manifest.join("Cargo.toml.orig").exists() => None,
        None => Some(manifest.join("../../models/recgen-nano")).filter(|d| FILES.iter().all(|f| d.join(f).is_file())),
    };
    let Some(dir) = dir else {
        return;
    };
    let dir = dir.canonicalize().unwrap_or(dir);
    for f in FILES {
        println!("cargo::rerun-if-changed={}", dir.join(f).display());
    }
    println!("cargo::rustc-cfg=recon_embedded_nano");
    println!("cargo::rustc-env=RECON_EMBEDDED_NANO_DIR={}", path_str(&dir));
}

fn path_str(p: &Path) -> String {
    p.to_str().unwrap_or_else(|| panic!("{}: the recgen-nano folder's path must be UTF-8 to embed it", p.display())).to_string()
}
