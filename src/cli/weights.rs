//! `recon weights`: fetch, verify, random-initialise checkpoints.
use clap::Subcommand;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum WeightsCmd {
    /// Download a manifest's files (Hugging Face files into the standard HF cache).
    Fetch {
        /// Manifest name (recgen, trellis-image-large, dinov2-vitl14-reg) or path; default: all.
        #[arg(long)]
        manifest: Option<String>,
        /// Cache directory (default: $HF_HOME/hub or ~/.cache/huggingface/hub).
        #[arg(long)]
        cache: Option<PathBuf>,
        /// Also download files marked optional.
        #[arg(long)]
        with_optional: bool,
    },
    /// Check a directory (or HF cache) against a manifest: files present, tensor names and shapes.
    Verify {
        dir: PathBuf,
        /// Manifest name or path; default: all.
        #[arg(long)]
        manifest: Option<String>,
    },
    /// Write random-initialised weights (labelled recon.random_init=true) for a module config.
    Init {
        /// Module config JSON ({"name": ClassName, "args": {...}}), e.g. models/dinov2_tiny.json.
        #[arg(long)]
        config: PathBuf,
        #[arg(long)]
        out: PathBuf,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Print the tensor names and shapes a module config expects (JSON).
    Expected {
        #[arg(long)]
        config: PathBuf,
    },
}

fn manifests(name: &Option<String>) -> anyhow::Result<Vec<recon::weights::Manifest>> {
    use recon::weights::Manifest;
    Ok(match name {
        Some(n) => vec![Manifest::load(n)?],
        None => Manifest::all()?,
    })
}

pub fn run(cmd: WeightsCmd) -> anyhow::Result<bool> {
    match cmd {
        WeightsCmd::Fetch { manifest, cache, with_optional } => {
            for m in manifests(&manifest)? {
                let paths = recon::weights::fetch(&m, cache.as_deref(), with_optional)?;
                for p in paths {
                    println!("{}", p.display());
                }
            }
            Ok(true)
        }
        WeightsCmd::Verify { dir, manifest } => {
            if !dir.is_dir() {
                anyhow::bail!("{}: not a directory", dir.display());
            }
            let mut ok = true;
            for m in manifests(&manifest)? {
                let rows = recon::weights::verify_dir(&m, &dir)?;
                recon::weights::print_table(&m, &dir, &rows, &mut std::io::stdout());
                ok &= rows.iter().all(|r| r.ok);
            }
            Ok(ok)
        }
        WeightsCmd::Init { config, out, seed } => {
            let p = recon::weights::write_random_init(&config, &out, seed)?;
            println!("wrote {} (RANDOM weights, recon.random_init=true, seed {seed})", p.display());
            Ok(true)
        }
        WeightsCmd::Expected { config } => {
            let file = config.display().to_string();
            let cfg = recon::model::ModuleArgs::from_spec(&recon::weights::ModuleConfig::read(&config)?, &file)?;
            let specs = recon::weights::expected_tensors(&cfg, &file)?;
            println!("{}", serde_json::to_string(&specs)?);
            Ok(true)
        }
    }
}
