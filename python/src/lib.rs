//! `recon_rgbd._recon`: the Python extension module of recon. Every function here calls the
//! library function its CLI command calls (`recon infer` → [`recon::engine::Engine`] and
//! [`recon::engine::write_outputs`], `recon synth` → [`recon::synth::generate`], …), with
//! numpy arrays in and out and the GIL released while recon computes. The pure-Python
//! package around it (`python/recon_rgbd/`) adds `recon_rgbd.ray` and the type stubs.

use pyo3::prelude::*;

/// recon's large buffers are reused by size, as in the `recon` CLI
/// (`recon::util::LargeBufferCache`; `RECON_MALLOC=system` turns it off).
/// It serves this extension's Rust allocations only, not Python's.
#[global_allocator]
static ALLOC: recon::util::LargeBufferCache = recon::util::LargeBufferCache;

mod convert;
mod engine;
mod entry;
mod errors;
mod tools;

/// The `recon` binary's own subcommand files, compiled in for `python -m recon_rgbd`
/// (`entry::cli_main`): one definition of each command's flags and behaviour. Only the
/// commands a wheel runs are listed (not bench, train, audit, conformance).
#[path = "../../src/cli"]
#[allow(dead_code, reason = "items the binary uses and python -m recon_rgbd does not")]
mod cli {
    pub mod eval;
    pub mod infer;
    pub mod model_args;
    pub mod scene;
    pub mod serve;
    pub mod synth;
    pub mod weights;
}

#[pymodule]
fn _recon(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    // The environment is read here, once, at import (see `recon::settings`).
    recon::settings::Settings::from_env().map_err(|e| errors::ConfigError::new_err(e.to_string()))?.apply();
    m.add("ReconError", py.get_type::<errors::ReconError>())?;
    m.add("InputError", py.get_type::<errors::InputError>())?;
    m.add("WeightsError", py.get_type::<errors::WeightsError>())?;
    m.add("ConfigError", py.get_type::<errors::ConfigError>())?;
    m.add("DefaultModelWarning", py.get_type::<errors::DefaultModelWarning>())?;
    m.add_class::<engine::Engine>()?;
    m.add_class::<engine::Object>()?;
    m.add_class::<engine::Mesh>()?;
    m.add_class::<engine::Gaussians>()?;
    m.add_function(wrap_pyfunction!(engine::infer_defaults, m)?)?;
    m.add_function(wrap_pyfunction!(tools::load_frame, m)?)?;
    m.add_function(wrap_pyfunction!(tools::load_masks, m)?)?;
    m.add_function(wrap_pyfunction!(tools::scene, m)?)?;
    m.add_function(wrap_pyfunction!(tools::synth, m)?)?;
    m.add_function(wrap_pyfunction!(tools::synth_begin, m)?)?;
    m.add_function(wrap_pyfunction!(tools::synth_plan, m)?)?;
    m.add_function(wrap_pyfunction!(tools::synth_shard, m)?)?;
    m.add_function(wrap_pyfunction!(tools::synth_finish, m)?)?;
    m.add_function(wrap_pyfunction!(tools::eval, m)?)?;
    m.add_function(wrap_pyfunction!(tools::audit_depth, m)?)?;
    m.add_function(wrap_pyfunction!(tools::dataset_frames, m)?)?;
    m.add_function(wrap_pyfunction!(tools::keep_freed_memory, m)?)?;
    m.add_function(wrap_pyfunction!(entry::cli_main, m)?)?;
    m.add_function(wrap_pyfunction!(entry::info, m)?)?;
    m.add("OUTPUT_MARKER", recon::engine::MARKER)?;
    m.add("STAGE_COLUMNS", recon::engine::STAGE_COLUMNS.to_vec())?;
    m.add("MAX_SECOND_VIEWS", recon::engine::MAX_SECOND_VIEWS)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
