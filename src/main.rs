use clap::{Parser, Subcommand};

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
}

fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    match cli.cmd {
        Cmd::Conformance { dirs } => {
            let ok = recon::conformance::run_dirs(&dirs, &mut std::io::stdout())?;
            if !ok {
                std::process::exit(1);
            }
        }
    }
    Ok(())
}
