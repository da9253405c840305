//! The `recon` binary: one file per subcommand under src/cli/.
use clap::{CommandFactory, FromArgMatches, Parser, Subcommand};

mod cli;

/// Large activations reuse freed buffers of the same size (see
/// `LargeBufferCache`); `RECON_MALLOC=system` turns that off.
#[global_allocator]
static ALLOC: recon::util::LargeBufferCache = recon::util::LargeBufferCache;

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
    /// Score predictions (or the `observed` baseline) against a BOP or YCB-Video dataset: occlusion-binned table, report JSON, SVG plot.
    Eval(cli::eval::EvalArgs),
    /// Reconstruct every masked object of an RGB-D frame: posed mesh, Gaussians and pose per object.
    Infer(cli::infer::InferArgs),
    /// Benchmarks: kernel GFLOP/s vs measured peak, per-module time and memory at full size, precision errors, end to end, shape fit, synth, training steps.
    Bench(cli::bench::BenchArgs),
    /// Train a stage-1 model (SS VAE, SS flow with pose tokens) on BOP-format synthetic data.
    Train(cli::train::TrainArgs),
    /// Serve the engine over HTTP: POST a frame and masks, get poses and the files `infer` writes (docs/serve.md).
    Serve(cli::serve::ServeArgs),
    /// Synthetic occluded RGB-D scenes with exact ground truth, in the BOP format.
    Synth(cli::synth::SynthArgs),
    /// Posed meshes (a scene file or a recon infer output) → settled, simulator-ready scene: URDF, MJCF, USD, GLB.
    Scene(cli::scene::SceneArgs),
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
    /// Shell completion script for bash, zsh, fish, elvish or powershell, on stdout.
    Completions(cli::meta::CompletionsArgs),
    /// Manual page (roff) of recon on stdout, or every command's into a folder.
    Man(cli::meta::ManArgs),
}

fn main() -> anyhow::Result<()> {
    // The environment is read here, once (see `recon::settings` for the list); applied
    // before parsing so that `--version` reports the kernels RECON_ISA leaves, its error
    // reported after so that `--help` works whatever the environment holds.
    let settings = recon::settings::Settings::from_env();
    if let Ok(s) = &settings {
        s.apply();
    }
    let mut command = Cli::command();
    // `-V` stays one line; `--version` adds the build and CPU facts (measured, so only then).
    if std::env::args_os().skip(1).take_while(|a| a != "--").any(|a| a == "--version") {
        command = command.long_version(Box::leak(cli::meta::long_version().into_boxed_str()) as &str);
    }
    let cli = Cli::from_arg_matches_mut(&mut command.get_matches()).unwrap_or_else(|e| e.exit());
    settings?;
    let ok = match cli.cmd {
        Cmd::Completions(a) => cli::meta::completions(a, Cli::command())?,
        Cmd::Man(a) => cli::meta::man(a, Cli::command())?,
        Cmd::Conformance { dirs } => recon::tools::run_dirs(&dirs, &mut std::io::stdout())?,
        Cmd::Weights { cmd } => cli::weights::run(cmd)?,
        Cmd::Eval(a) => cli::eval::run(a)?,
        Cmd::Infer(a) => match cli::infer::run(a)? {
            cli::infer::EXIT_ALL => true,
            code => std::process::exit(code),
        },
        Cmd::Bench(a) => cli::bench::run(a)?,
        Cmd::Train(a) => cli::train::run(a)?,
        Cmd::Synth(a) => cli::synth::run(a)?,
        Cmd::Scene(a) => cli::scene::run(a)?,
        Cmd::Serve(a) => cli::serve::run(a)?,
        Cmd::Audit { cmd } => cli::audit::run(cmd)?,
    };
    if !ok {
        std::process::exit(1);
    }
    Ok(())
}
