//! What `recon --version` reports, and `recon completions` / `recon man`: shell completions
//! and manual pages generated from the same clap definitions as the command line.
use std::io::Write;
use std::path::PathBuf;

/// The git commit the binary was built from (root build.rs: `git rev-parse HEAD`, or the
/// packaged crate's `.cargo_vcs_info.json`), else `unknown`.
pub const COMMIT: &str = env!("RECON_GIT_COMMIT");

/// The lines `recon --version` prints after `recon <version>`: commit, build, cargo
/// features, embedded model, and the CPU kernels in use (after `RECON_ISA` /
/// `RECON_BF16_DOT` are applied). `-V` prints the first line only.
pub fn long_version() -> String {
    use recon_kernels::isa::{cap, Isa};
    let model = match recon::engine::embedded_model_hash() {
        Some(h) => format!("recgen-nano {h:016x}"),
        None => "none (pass --weights)".to_string(),
    };
    let best = Isa::best();
    let supported: Vec<&str> = Isa::all_supported().into_iter().map(Isa::name).collect();
    let bf16 = recon_kernels::peak::bf16_isa();
    let bf16_how = if bf16 == Isa::Avx512Bf16 { "vdpbf16ps" } else { "widened to f32 FMA" };
    let capped = cap().map_or(String::new(), |c| format!(", capped by RECON_ISA={}", c.name()));
    let features = recon_core::FEATURES;
    format!(
        "{version}\ncommit: {COMMIT}\nbuild: {target}, {profile} profile\nfeatures: recon-core [{features}]\nembedded model: {model}\ncpu kernels: {best}{capped} (this CPU runs: {supported}); bf16 weights: {bf16} ({bf16_how})",
        version = env!("CARGO_PKG_VERSION"),
        target = env!("RECON_BUILD_TARGET"),
        profile = env!("RECON_BUILD_PROFILE"),
        features = features.join(", "),
        best = best.name(),
        supported = supported.join(", "),
        bf16 = bf16.name(),
    )
}

/// `recon completions SHELL`: the completion script on stdout.
#[derive(clap::Args)]
pub struct CompletionsArgs {
    /// The shell: bash, zsh, fish, elvish or powershell.
    #[arg(value_enum)]
    shell: clap_complete::Shell,
}

/// `recon man`: the manual page of `recon` on stdout, or with `--out` one page per command.
#[derive(clap::Args)]
pub struct ManArgs {
    /// Write `recon.1` and one page per subcommand (`recon-infer.1`, …) into this folder
    /// (created if missing) instead of printing `recon.1`.
    #[arg(long)]
    out: Option<PathBuf>,
}

pub fn completions(a: CompletionsArgs, mut cmd: clap::Command) -> anyhow::Result<bool> {
    clap_complete::generate(a.shell, &mut cmd, "recon", &mut std::io::stdout());
    Ok(true)
}

pub fn man(a: ManArgs, cmd: clap::Command) -> anyhow::Result<bool> {
    use anyhow::Context;
    match a.out {
        Some(dir) => {
            std::fs::create_dir_all(&dir).with_context(|| format!("--out {}", dir.display()))?;
            let mut cmd = cmd.disable_help_subcommand(true);
            cmd.build();
            write_pages(cmd, &dir).with_context(|| format!("writing manual pages into {}", dir.display()))?;
            eprintln!("wrote manual pages into {}", dir.display());
        }
        None => {
            let mut page = Vec::new();
            // As `--out` renders it: no `help` subcommand (it has no page of its own).
            clap_mangen::Man::new(cmd.disable_help_subcommand(true)).render(&mut page)?;
            std::io::stdout().write_all(&page)?;
        }
    }
    Ok(true)
}

/// `cmd`'s page and its subcommands' (`recon-weights-fetch.1`, …) into `dir`, as
/// `clap_mangen::generate_to` writes them but with recon's version in every page's title.
fn write_pages(cmd: clap::Command, dir: &std::path::Path) -> std::io::Result<()> {
    for sub in cmd.get_subcommands().filter(|s| !s.is_hide_set()).cloned() {
        write_pages(sub, dir)?;
    }
    clap_mangen::Man::new(cmd.version(env!("CARGO_PKG_VERSION"))).generate_to(dir)?;
    Ok(())
}
