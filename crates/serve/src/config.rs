//! The server's settings ([`ServeConfig`]): what `recon serve`'s flags set.

use crate::error::ServeError;
use recon_core::engine::InferOptions;
use recon_core::settings::Secret;
use std::net::SocketAddr;
use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Default listening address: loopback only.
pub const DEFAULT_BIND: &str = "127.0.0.1:8080";
/// Default jobs computed at once.
pub const DEFAULT_WORKERS: usize = 1;
/// Default jobs waiting (uploads being received count as waiting).
pub const DEFAULT_QUEUE: usize = 16;
/// Default upload limit of one request, MiB.
pub const DEFAULT_MAX_UPLOAD_MB: u64 = 64;
/// Default seconds running jobs get to finish after SIGTERM/SIGINT.
pub const DEFAULT_SHUTDOWN_GRACE_S: u64 = 30;

/// Everything the server runs with. `recon serve`'s flags fill it; tests build it directly.
#[derive(Debug, Clone)]
pub struct ServeConfig {
    /// Address to listen on (`--bind`); port 0 picks a free one.
    pub bind: SocketAddr,
    /// Jobs computed at once (`--workers`), sharing the one loaded model.
    pub workers: NonZeroUsize,
    /// Jobs waiting for a worker (`--queue`); a request beyond it gets 429.
    pub queue: usize,
    /// Folder of the job folders (`--data-dir`): `<data-dir>/jobs/<id>/`.
    pub data_dir: PathBuf,
    /// Finished jobs older than this are deleted (`--keep-hours`); `None` keeps them.
    pub keep: Option<Duration>,
    /// Most bytes one request body may hold (`--max-upload-mb`); more is 413.
    pub max_upload_bytes: u64,
    /// A job running longer is stopped at its next stage boundary and reported
    /// `failed: timeout` (`--job-timeout-s`); `None`: no limit.
    pub job_timeout: Option<Duration>,
    /// The bearer token every route but `/health` requires (`--token-file`, else
    /// `RECON_API_TOKEN`); `None`: no authentication, loopback binds only.
    pub token: Option<Secret>,
    /// The per-frame options a request starts from (the model flags' `--seed`,
    /// `--samples`, …); a request's `options` part overrides them by name. Their
    /// `max_objects` (`--max-objects`) is also the server's ceiling: a request may lower
    /// it, not raise it, and it bounds the binary mask parts of a request.
    pub defaults: InferOptions,
    /// How long running jobs may go on after a shutdown signal before they are stopped
    /// and reported `failed: interrupted`.
    pub shutdown_grace: Duration,
}

impl ServeConfig {
    /// The defaults, with job folders under `data_dir`.
    pub fn new(data_dir: impl Into<PathBuf>) -> Self {
        ServeConfig {
            bind: SocketAddr::from(([127, 0, 0, 1], 8080)),
            workers: NonZeroUsize::MIN,
            queue: DEFAULT_QUEUE,
            data_dir: data_dir.into(),
            keep: None,
            max_upload_bytes: DEFAULT_MAX_UPLOAD_MB << 20,
            job_timeout: None,
            token: None,
            defaults: InferOptions::default(),
            shutdown_grace: Duration::from_secs(DEFAULT_SHUTDOWN_GRACE_S),
        }
    }

    /// Checks the settings before anything starts: the defaults' options are valid, the
    /// limits are positive, and a bind beyond loopback has a token.
    pub fn check(&self) -> Result<(), ServeError> {
        if !self.bind.ip().is_loopback() && self.token.is_none() {
            return Err(ServeError::config(
                "--bind",
                format!(
                    "{} is reachable from other machines; give a token (--token-file or RECON_API_TOKEN) or bind to 127.0.0.1",
                    self.bind
                ),
            ));
        }
        if self.token.as_ref().is_some_and(|t| t.expose().is_empty()) {
            return Err(ServeError::config("--token-file", "the token is empty"));
        }
        if self.max_upload_bytes == 0 {
            return Err(ServeError::config("--max-upload-mb", "must be at least 1"));
        }
        if self.job_timeout.is_some_and(|t| t.is_zero()) {
            return Err(ServeError::config("--job-timeout-s", "must be > 0"));
        }
        self.defaults.validate().map_err(|e| ServeError::config(recon_core::engine::flag(e.option()), e.to_string()))?;
        Ok(())
    }
}

/// Reads a token file: its content without surrounding whitespace; an empty file is an error.
pub fn read_token_file(path: &Path) -> Result<Secret, ServeError> {
    let text = std::fs::read_to_string(path).map_err(|e| ServeError::io(path, e))?;
    let t = text.trim();
    if t.is_empty() {
        return Err(ServeError::config("--token-file", format!("{} is empty", path.display())));
    }
    Ok(Secret::new(t))
}

/// Seconds as a [`Duration`], checked (finite, > 0); `flag` names the setting in the error.
pub fn seconds(v: f64, flag: &str) -> Result<Duration, ServeError> {
    Duration::try_from_secs_f64(v)
        .ok()
        .filter(|d| !d.is_zero())
        .ok_or_else(|| ServeError::config(flag, format!("must be a positive number of seconds, got {v}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_loopback_needs_a_token() {
        let mut c = ServeConfig::new("/tmp/x");
        assert!(c.check().is_ok());
        c.bind = "0.0.0.0:8080".parse().unwrap();
        let e = c.check().unwrap_err().to_string();
        assert!(e.starts_with("--bind: 0.0.0.0:8080") && e.contains("token"), "{e}");
        c.token = Some(Secret::new("t"));
        assert!(c.check().is_ok());
        c.bind = "[::1]:0".parse().unwrap();
        c.token = None;
        assert!(c.check().is_ok());
    }

    #[test]
    fn limits_and_defaults_are_checked() {
        let mut c = ServeConfig::new("/tmp/x");
        c.defaults.samples = 0;
        assert!(c.check().unwrap_err().to_string().contains("--samples"));
        assert!(seconds(-1.0, "--job-timeout-s").is_err());
        assert!(seconds(f64::NAN, "--job-timeout-s").is_err());
        assert_eq!(seconds(1.5, "x").unwrap(), Duration::from_millis(1500));
    }
}
