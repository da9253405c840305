//! `recon weights`: fetch, verify, random-initialise checkpoints.
use anyhow::Context;
use clap::Subcommand;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum WeightsCmd {
    /// Download a manifest's files, and those of the manifests it requires (`recon weights
    /// fetch recgen`: the RecGen release and the DINOv2 encoder), into the Hugging Face cache;
    /// files already there are kept, pinned SHA-256 checked. HF_TOKEN, HF_ENDPOINT and
    /// HF_HUB_OFFLINE apply.
    Fetch {
        /// Manifest name (recgen, trellis-image-large, dinov2-vitl14-reg) or path; default: all.
        #[arg(value_name = "MANIFEST", conflicts_with = "manifest")]
        name: Option<String>,
        /// The same as the positional MANIFEST.
        #[arg(long)]
        manifest: Option<String>,
        /// Cache directory (default: $HF_HUB_CACHE, else $HF_HOME/hub, else ~/.cache/huggingface/hub).
        #[arg(long)]
        cache: Option<PathBuf>,
        /// Also download files marked optional.
        #[arg(long)]
        with_optional: bool,
    },
    /// Check a directory (or HF cache) against a manifest: files present, SHA-256 pins, tensor
    /// names and shapes.
    Verify {
        /// Folder or Hugging Face cache (default: the cache, as for fetch).
        dir: Option<PathBuf>,
        /// Manifest name or path, with the manifests it requires; default: all.
        #[arg(long)]
        manifest: Option<String>,
    },
    /// Print a manifest with its checkpoints' tensor lists regenerated from recon's modules at
    /// an architecture's sizes (and, with --pin, the SHA-256 of the files in a folder or cache):
    /// how weights-manifest/*.json are made.
    Manifest {
        /// Manifest name or path.
        name: String,
        /// Architecture file giving the module sizes.
        #[arg(long, default_value = "models/recgen-large.json")]
        config: PathBuf,
        /// Folder or Hugging Face cache holding the files: record their SHA-256 (and the snapshot's commit).
        #[arg(long)]
        pin: Option<PathBuf>,
        /// Write here instead of stdout.
        #[arg(long)]
        out: Option<PathBuf>,
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
        /// `pt`: a torch zip archive of the state dict, as `torch.save` writes it (the format of
        /// RecGen's released denoisers), labelled by an extra archive record torch does not read
        #[arg(long, value_enum, default_value = "safetensors")]
        format: recon::weights::InitFormat,
    },
    /// Print the tensor names and shapes a module config expects (JSON).
    Expected {
        #[arg(long)]
        config: PathBuf,
    },
}

/// The named manifest and those it requires, or every embedded one.
fn manifests(name: &Option<String>) -> anyhow::Result<Vec<recon::weights::Manifest>> {
    use recon::weights::Manifest;
    Ok(match name {
        Some(n) => {
            let m = Manifest::load(n)?;
            let mut all = vec![m.clone()];
            all.extend(m.required(n)?);
            all
        }
        None => Manifest::all()?,
    })
}

pub fn run(cmd: WeightsCmd) -> anyhow::Result<bool> {
    match cmd {
        WeightsCmd::Fetch { name, manifest, cache, with_optional } => {
            for m in manifests(&name.or(manifest))? {
                let paths = recon::weights::fetch(&m, cache.as_deref(), with_optional)?;
                for p in paths {
                    println!("{}", p.display());
                }
            }
            Ok(true)
        }
        WeightsCmd::Verify { dir, manifest } => {
            let dir = dir.unwrap_or_else(recon::weights::hf_cache::default_cache);
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
        WeightsCmd::Manifest { name, config, pin, out } => {
            let arch = recon::model::RecGenConfig::load(&config)?;
            let mut m = recon::weights::Manifest::load(&name)?.with_tensors_from(&arch, &config.display().to_string())?;
            if let Some(dir) = pin {
                let (pinned, absent) = m.with_pins_from(&dir)?;
                for a in absent {
                    eprintln!("not pinned (absent from {}): {a}", dir.display());
                }
                m = pinned;
            }
            let text = m.to_pretty_json()?;
            match out {
                Some(p) => std::fs::write(&p, text).with_context(|| format!("writing {}", p.display()))?,
                None => print!("{text}"),
            }
            Ok(true)
        }
        WeightsCmd::Init { config, out, seed, format } => {
            let p = recon::weights::write_random_init_as(&config, &out, seed, format)?;
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
