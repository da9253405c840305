//! `recon serve`: the engine behind an HTTP API (crates/serve; docs/serve.md). Flags →
//! `recon_serve::ServeConfig`, the model loaded once, then the library runs the server.
use crate::cli::model_args::ModelArgs;
use std::net::SocketAddr;
use std::num::NonZeroUsize;
use std::path::PathBuf;

#[derive(clap::Args)]
pub struct ServeArgs {
    /// Address to listen on. A non-loopback address needs a token (--token-file or
    /// RECON_API_TOKEN); port 0 picks a free port (printed at start).
    #[arg(long, default_value = recon_serve::DEFAULT_BIND)]
    bind: SocketAddr,
    /// The model, and the per-frame options a request starts from (its `options` part
    /// overrides them by name).
    #[command(flatten)]
    model: ModelArgs,
    /// Threads of the model's kernels (default: all cores), shared by the workers.
    #[arg(long)]
    threads: Option<usize>,
    /// Jobs computed at once; they share the one loaded model.
    #[arg(long, default_value_t = NonZeroUsize::new(recon_serve::DEFAULT_WORKERS).unwrap_or(NonZeroUsize::MIN))]
    workers: NonZeroUsize,
    /// Jobs waiting for a worker (uploads in progress count); beyond it requests get 429.
    #[arg(long, default_value_t = recon_serve::DEFAULT_QUEUE)]
    queue: usize,
    /// Folder of the job folders (inputs, state, outputs): `<data-dir>/jobs/<id>/`.
    #[arg(long, default_value = "recon-serve-data")]
    data_dir: PathBuf,
    /// Delete finished jobs older than this many hours (default: keep them).
    #[arg(long)]
    keep_hours: Option<f64>,
    /// Largest request body, MiB; more is answered 413.
    #[arg(long, default_value_t = recon_serve::DEFAULT_MAX_UPLOAD_MB)]
    max_upload_mb: u64,
    /// Stop a job running longer than this (at its next stage boundary): failed, timeout.
    #[arg(long)]
    job_timeout_s: Option<f64>,
    /// File holding the bearer token every route but /health requires (wins over
    /// RECON_API_TOKEN).
    #[arg(long)]
    token_file: Option<PathBuf>,
    /// Seconds running jobs may go on after SIGTERM/SIGINT before they are stopped.
    #[arg(long, default_value_t = recon_serve::DEFAULT_SHUTDOWN_GRACE_S as f64)]
    shutdown_grace_s: f64,
}

pub fn run(a: ServeArgs) -> anyhow::Result<bool> {
    use anyhow::Context;
    use recon::engine::Engine;
    let token = match &a.token_file {
        Some(p) => Some(recon_serve::read_token_file(p)?),
        None => recon::settings::current().api_token,
    };
    let mut cfg = recon_serve::ServeConfig::new(&a.data_dir);
    cfg.bind = a.bind;
    cfg.workers = a.workers;
    cfg.queue = a.queue;
    cfg.keep = a.keep_hours.map(|h| recon_serve::seconds(h * 3600.0, "--keep-hours")).transpose()?;
    cfg.max_upload_bytes = a.max_upload_mb.checked_mul(1 << 20).context("--max-upload-mb is too large")?;
    cfg.job_timeout = a.job_timeout_s.map(|s| recon_serve::seconds(s, "--job-timeout-s")).transpose()?;
    cfg.token = token;
    cfg.defaults = a.model.infer.clone();
    cfg.shutdown_grace =
        std::time::Duration::try_from_secs_f64(a.shutdown_grace_s).map_err(|_| anyhow::anyhow!("--shutdown-grace-s must be >= 0"))?;
    // Refused before the model is loaded (a non-loopback bind without a token, bad limits).
    cfg.check()?;
    if let Some(n) = a.threads {
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global().context("--threads")?;
    }
    let source = a.model.source()?;
    a.model.note_default_model();
    let load = a.model.load_options(&source)?;
    let engine = Engine::load(&source, &load)?;
    if engine.pipeline.weights().is_random() {
        eprintln!(
            "NOTE: serving {} with RANDOM weights (seed {}). The plumbing is real; the shapes and poses are not meaningful.",
            source.architecture()?.display(),
            a.model.infer.seed
        );
    }
    recon_serve::run(cfg, std::sync::Arc::new(engine), |addr| {
        use std::io::Write;
        println!("recon serve: listening on http://{addr}");
        let _ = std::io::stdout().flush();
    })?;
    Ok(true)
}
