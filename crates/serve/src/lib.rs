//! `recon serve`: the engine behind an HTTP API, for pipelines in any language.
//!
//! A client posts an RGB-D frame (or two) and its object masks as multipart parts to
//! `POST /v1/reconstruct`; the server runs `recon infer` on it with the model it loaded
//! once, and answers per object the metric pose, its score and stage times, and the URLs
//! of the files `recon infer` writes (byte for byte the CLI's). Jobs can also be queued
//! (`?wait=false`), polled, cancelled, archived, and turned into sim-ready scenes
//! (`recon scene`). The routes are [`ROUTES`]; `docs/serve.md` is the user's guide.
//!
//! What it promises: a full queue answers 429 with `Retry-After`; an upload over the limit
//! 413; every input `recon infer` refuses is refused, before it is queued, as a 4xx
//! naming the part and field with the CLI's message; each job lives in its own folder
//! with its state written atomically, so a restart after a crash serves finished jobs
//! byte-identical and reports interrupted ones (see [`jobs`]); SIGTERM/SIGINT shut down
//! gracefully; a `wait=true` client that disconnects cancels its job; a bearer token is
//! required off loopback.
//!
//! ```no_run
//! use std::sync::Arc;
//! use recon_core::engine::{Engine, LoadOptions, ModelSource};
//! # fn main() -> Result<(), recon_serve::ServeError> {
//! let engine = Arc::new(Engine::load(&ModelSource::Default, &LoadOptions::default())?);
//! let cfg = recon_serve::ServeConfig::new("recon-serve-data");
//! recon_serve::run(cfg, engine, |addr| println!("listening on http://{addr}"))
//! # }
//! ```
#![warn(missing_docs)]

mod api;
mod config;
mod error;
pub mod inputs;
pub mod jobs;
mod log;
mod metrics;
mod openapi;
mod paths;

pub use api::{run, start, RunningServer};
pub use config::{
    read_token_file, seconds, ServeConfig, DEFAULT_BIND, DEFAULT_MAX_UPLOAD_MB, DEFAULT_QUEUE, DEFAULT_SHUTDOWN_GRACE_S, DEFAULT_WORKERS,
};
pub use error::{ApiError, ServeError};
pub use metrics::Metrics;
pub use openapi::{axum_path, openapi, Route, ROUTES};
pub use paths::resolve as resolve_job_file;
