//! The `recon` binary: one file per subcommand under src/cli/.
use clap::{Parser, Subcommand};

mod cli;

#[derive(Parser)]
#[command(name = "recon", version, about = "RGB-D frames + masks → simulation-ready posed 3D objects")]
struct Cli {
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Run conformance fixture directories (config.json + data.safetensors) and report max abs error per output.
    Conformance {
        /// Fixture directories.
        #[arg(required = true)]
        dirs: Vec<std::path::PathBuf>,
    },
    /// Reconstruct every masked object of an RGB-D frame: posed mesh, Gaussians and pose per object.
    Infer(cli::infer::InferArgs),
    /// Measured vs simulated: find what the simulation gets wrong, name the cause, extend the sensor model.
    Audit {
        #[command(subcommand)]
        cmd: cli::audit::AuditCmd,
    },
    /// Checkpoints: download, verify, random-initialise.
    Weights {
        #[command(subcommand)]
        cmd: cli::weights::WeightsCmd,
    },
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let ok = match cli.cmd {
        Cmd::Conformance { dirs } => recon::conformance::run_dirs(&dirs, &mut std::io::stdout())?,
        Cmd::Weights { cmd } => cli::weights::run(cmd)?,
        Cmd::Infer(a) => cli::infer::run(a)?,
        Cmd::Audit { cmd } => cli::audit::run(cmd)?,
    };
    if !ok {
        std::process::exit(1);
    }
    Ok(())
}
