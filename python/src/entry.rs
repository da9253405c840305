//! `python -m recon_rgbd …`: the `recon` binary's `infer`, `scene`, `serve`, `synth`, `eval` and
//! `weights` commands from the wheel, which carries no binary. The argument structs and `run`
//! functions are the CLI's own files (src/cli/, compiled into the extension by lib.rs), so the
//! flags, defaults, messages, outputs and exit codes are the binary's.
//! `info()`: what this build is and what it runs on.

use crate::cli;
use clap::{Parser, Subcommand};
use pyo3::prelude::*;
use pyo3::types::PyDict;

#[derive(Parser)]
#[command(
    name = "python -m recon_rgbd",
    version,
    about = "RGB-D frames + masks → simulation-ready posed 3D objects (the recon CLI's commands that a wheel carries)"
)]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Reconstruct every masked object of an RGB-D frame: posed mesh, Gaussians and pose per object.
    Infer(cli::infer::InferArgs),
    /// Posed meshes (a scene file or a recon infer output) → settled, simulator-ready scene: URDF, MJCF, USD, GLB.
    Scene(cli::scene::SceneArgs),
    /// Serve the engine over HTTP: POST a frame and masks, get poses and the files `infer` writes (docs/serve.md).
    Serve(cli::serve::ServeArgs),
    /// Synthetic occluded RGB-D scenes with exact ground truth, in the BOP format.
    Synth(cli::synth::SynthArgs),
    /// Score predictions (or the `observed` baseline) against a BOP or YCB-Video dataset.
    Eval(cli::eval::EvalArgs),
    /// Checkpoints: download, verify, random-initialise.
    Weights {
        #[command(subcommand)]
        cmd: cli::weights::WeightsCmd,
    },
}

/// Runs `argv` (program name first) as the `recon` binary would and returns its exit status:
/// 0 done, 1 error (printed as the binary prints it), 2 or 3 from `infer` (README: exit codes),
/// 2 for a usage error. The GIL is released while the command runs.
#[pyfunction]
pub fn cli_main(py: Python<'_>, argv: Vec<String>) -> i32 {
    let cli = match Cli::try_parse_from(&argv) {
        Ok(c) => c,
        Err(e) => {
            // --help and --version print to stdout and exit 0; usage errors print to stderr.
            let _ = e.print();
            return e.exit_code();
        }
    };
    let run = || -> anyhow::Result<i32> {
        let ok = match cli.cmd {
            Cmd::Infer(a) => return cli::infer::run(a),
            Cmd::Scene(a) => cli::scene::run(a)?,
            Cmd::Serve(a) => cli::serve::run(a)?,
            Cmd::Synth(a) => cli::synth::run(a)?,
            Cmd::Eval(a) => cli::eval::run(a)?,
            Cmd::Weights { cmd } => cli::weights::run(cmd)?,
        };
        Ok(if ok { 0 } else { 1 })
    };
    match py.detach(run) {
        Ok(code) => code,
        Err(e) => {
            // As a Rust `main` returning an error prints it (the binary's format).
            eprintln!("Error: {e:?}");
            1
        }
    }
}

/// This build and the machine it runs on: version, git commit (when built from a git
/// checkout), Cargo features, target, the instruction sets recon's kernels detect and use
/// (the machine line of `recon bench`), threads, allocator.
#[pyfunction]
pub fn info(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let m = recon::tools::bench::MachineInfo::detect();
    let d = PyDict::new(py);
    d.set_item("version", env!("CARGO_PKG_VERSION"))?;
    d.set_item("commit", option_env!("RECON_GIT_COMMIT"))?;
    d.set_item("features", FEATURES.to_vec())?;
    d.set_item("profile", if cfg!(debug_assertions) { "dev" } else { "release" })?;
    d.set_item("target", format!("{}-{}", std::env::consts::ARCH, std::env::consts::OS))?;
    d.set_item("cpu", m.cpu)?;
    d.set_item("isa", m.best_isa)?;
    d.set_item("bf16_isa", m.bf16_isa)?;
    d.set_item("supported_isas", m.supported_isas)?;
    d.set_item("threads", m.threads)?;
    d.set_item("allocator", m.allocator)?;
    d.set_item("default_model", "recgen-nano (embedded)")?;
    Ok(d)
}

/// The optional parts this extension is built with: `hub` (Hugging Face download, through the
/// `recon` crate's default features) and the `recon` commands `python -m recon_rgbd` runs.
const FEATURES: [&str; 2] = ["hub", "cli"];
