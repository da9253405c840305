//! Conformance against upstream golden fixtures.
//!
//! A fixture directory holds `config.json` (which upstream module ran, its
//! constructor `args`, tolerances) and `data.safetensors` (weights under the
//! upstream names plus `input.*`, `output.*`, `intermediate.*`, `time.*`).
//! `run_dirs` dispatches on the config's `module` field, builds the module
//! from its `args`, and compares every output. The test suite and the
//! `recon conformance` command share this code.

mod dinov2;
mod fixture;
mod flexicubes;
mod slat_dec;
mod slat_flow;
mod ss_decoder;
mod ss_flow;

pub use fixture::{Check, Fixture};

use crate::model::Compute;
use crate::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Run one fixture directory with its modules built on `compute`, and
/// return its checks.
pub fn run_fixture(dir: &Path, compute: Compute) -> Result<Vec<Check>> {
    let fx = Fixture::load(dir)?;
    let module = fx.module().to_string();
    let first = module.split_whitespace().next().unwrap_or("");
    match first {
        m if m.starts_with("Dinov2") => dinov2::run(&fx, compute),
        "SparseFeatures2Mesh" => flexicubes::run(&fx),
        "SLatGaussianDecoder" => slat_dec::run_gs(&fx, compute),
        "SLatMeshDecoder" => slat_dec::run_mesh(&fx, compute),
        "SLatFlowModel" => slat_flow::run(&fx, compute),
        "SparseStructureDecoder" => ss_decoder::run(&fx, compute),
        "SparseStructureFlowModel" => ss_flow::run_model(&fx, compute),
        "FlowEulerGuidanceIntervalSampler" => ss_flow::run_sampler(&fx, compute),
        _ => Err(Error::config(
            dir.join("config.json").display().to_string(),
            "module",
            format!("no conformance runner for module `{module}`"),
        )),
    }
}

/// Run every directory, print one line per output, return true when all pass.
pub fn run_dirs(dirs: &[PathBuf], out: &mut dyn Write) -> Result<bool> {
    let mut all_ok = true;
    for dir in dirs {
        let name = dir.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
        match run_fixture(dir, Compute::Plain) {
            Ok(checks) => {
                for c in &checks {
                    let _ = writeln!(
                        out,
                        "{:<40} {:<36} max_abs {:>10.3e}  tol {:>8.1e}  {}{}",
                        name,
                        c.output,
                        c.max_abs,
                        c.tol,
                        if c.pass { "PASS" } else { "FAIL" },
                        c.note.as_deref().map(|n| format!("  ({n})")).unwrap_or_default()
                    );
                    all_ok &= c.pass;
                }
                if checks.is_empty() {
                    let _ = writeln!(out, "{name:<40} no outputs checked  FAIL");
                    all_ok = false;
                }
            }
            Err(e) => {
                let _ = writeln!(out, "{name:<40} ERROR {e}");
                all_ok = false;
            }
        }
    }
    Ok(all_ok)
}
