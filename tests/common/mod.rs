//! Helpers the integration tests share (each test file is its own crate and
//! includes this module with `mod common;`).
// Every test crate uses a different subset of these.
#![allow(dead_code, unused_imports)]

pub mod realdata;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub use recon_testkit::{repo, tmp};

/// The tiny architecture every plumbing test runs.
pub fn tiny_config() -> PathBuf {
    repo().join("models/recgen-tiny.json")
}

/// Run the `recon` binary built for these tests, from the repository root.
pub fn recon(args: &[&str]) -> Output {
    recon_with_env(args, &[])
}

/// [`recon`] with extra environment variables.
pub fn recon_with_env(args: &[&str], env: &[(&str, &Path)]) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_recon"));
    c.args(args).current_dir(repo());
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().expect("running recon")
}

/// A JSON file, parsed.
pub fn read_json(p: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}
