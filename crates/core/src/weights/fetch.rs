//! `recon weights fetch`: download a manifest's files. Hugging Face files go
//! into the standard hub cache ([`crate::weights::hf_cache`]: `$HF_HUB_CACHE`,
//! else `$HF_HOME/hub`, or `--cache`) through `hf-hub`'s client, configured
//! from the applied [settings](crate::settings) (`HF_TOKEN` or the login token
//! file, `HF_ENDPOINT`) rather than its own environment reading; files already
//! in the cache are not downloaded again, and under `HF_HUB_OFFLINE` nothing
//! is. URL-sourced files (the torch.hub DINOv2 checkpoint) are downloaded with
//! `ureq` into `<cache>/recon-url/<manifest>/`. Every file with a pinned
//! SHA-256 is checked once it is in place.

use crate::weights::hf_cache;
use crate::weights::manifest::{Manifest, ManifestFile};
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// Download every non-optional file (and optional ones when `with_optional`)
/// that the cache does not hold yet, and check the pinned SHA-256 of each.
/// Returns the local paths. The first failure aborts with a message naming
/// the repo, revision and file.
pub fn fetch(m: &Manifest, cache: Option<&Path>, with_optional: bool) -> Result<Vec<PathBuf>> {
    let files: Vec<&ManifestFile> = m.files.iter().filter(|f| with_optional || !f.optional).collect();
    let cache = cache.map(Path::to_path_buf).unwrap_or_else(default_hf_cache);
    let out = get_files(m, &files, &cache, crate::settings::current().hf_offline)?;
    for (f, p) in files.iter().zip(&out) {
        if let Some(pin) = &f.sha256 {
            hf_cache::check_sha256(p, pin)?;
        }
    }
    Ok(out)
}

/// `files` of `m` in `cache`: those there as they are, the others downloaded
/// (never under `offline`: then the first one missing is the error). Pins are
/// the caller's to check.
pub(crate) fn get_files(m: &Manifest, files: &[&ManifestFile], cache: &Path, offline: bool) -> Result<Vec<PathBuf>> {
    match m.source.as_str() {
        "huggingface" => fetch_hf(m, files, cache, offline),
        "url" => {
            let base = cache.join("recon-url").join(&m.name);
            std::fs::create_dir_all(&base).map_err(|e| Error::io(&base, e))?;
            let mut out = Vec::new();
            for f in files {
                let url = f.url.as_ref().ok_or_else(|| Error::config(&m.name, "url", format!("file `{}` has no url", f.path)))?;
                let dest = m.expected_path(cache, f);
                if !dest.exists() {
                    if offline {
                        return Err(Error::input(
                            dest.display().to_string(),
                            format!(
                                "manifest `{}`: `{}` is not there and HF_HUB_OFFLINE is set, so it is not downloaded from {url}",
                                m.name, f.path
                            ),
                        ));
                    }
                    download_url(url, &dest).map_err(|e| {
                        Error::msg(format!(
                            "manifest `{}`: cannot download `{}`: {e}. Check network access, or place the file at {}",
                            m.name,
                            f.path,
                            dest.display()
                        ))
                    })?;
                }
                out.push(dest);
            }
            Ok(out)
        }
        other => Err(Error::config(&m.name, "source", format!("unknown source `{other}`"))),
    }
}

/// The Hugging Face files of `m`: those in the cache as they are, the others
/// through hf-hub's client (never under `offline`).
fn fetch_hf(m: &Manifest, files: &[&ManifestFile], cache: &Path, offline: bool) -> Result<Vec<PathBuf>> {
    let repo = m.repo.clone().ok_or_else(|| Error::config(&m.name, "repo", "missing for a huggingface manifest"))?;
    let rev = m.revision().to_string();
    let mut out = Vec::new();
    let mut client = None;
    for f in files {
        // The pinned snapshot, a ref, or refs/main: hf-hub itself only looks through refs/<revision>.
        if let Ok(p) = hf_cache::cached_file(cache, &repo, &rev, &f.path, offline) {
            out.push(p);
            continue;
        }
        if offline {
            return Err(hf_cache::cache_miss(cache, &repo, &rev, &f.path, true));
        }
        if client.is_none() {
            client = Some(hf_client(cache)?);
        }
        let api = client.as_ref().ok_or_else(|| Error::msg("hf-hub client"))?;
        out.push(download_hf(api, &repo, &rev, &f.path)?);
    }
    Ok(out)
}

#[cfg(feature = "hub")]
type Client = hf_hub::api::sync::Api;
#[cfg(not(feature = "hub"))]
type Client = ();

/// hf-hub's client on `cache`, with the settings' token and endpoint (hf-hub's
/// `from_env` would read `HF_HOME`/`HF_ENDPOINT` itself, and knows neither
/// `HF_HUB_CACHE` nor `HF_TOKEN`).
#[cfg(feature = "hub")]
fn hf_client(cache: &Path) -> Result<Client> {
    use hf_hub::api::sync::ApiBuilder;
    let s = crate::settings::current();
    let token = s.hf_token.map(|t| t.expose().to_string()).or_else(|| {
        // The login token file (`huggingface-cli login`), as hf-hub and huggingface_hub read it.
        let f = s.hf_home.as_ref()?.join("token");
        std::fs::read_to_string(f).ok().map(|t| t.trim().to_string()).filter(|t| !t.is_empty())
    });
    let mut b = ApiBuilder::from_cache(hf_hub::Cache::new(cache.to_path_buf())).with_progress(true).with_token(token);
    if let Some(e) = s.hf_endpoint {
        b = b.with_endpoint(e);
    }
    b.build().map_err(|e| Error::msg(format!("hf-hub: cannot set up the client: {e}")))
}

#[cfg(feature = "hub")]
fn download_hf(api: &Client, repo: &str, rev: &str, path: &str) -> Result<PathBuf> {
    use hf_hub::{Repo, RepoType};
    let r = api.repo(Repo::with_revision(repo.to_string(), RepoType::Model, rev.to_string()));
    r.download(path).map_err(|e| {
        let status = match &e {
            hf_hub::api::sync::ApiError::RequestError(r) => match r.as_ref() {
                ureq::Error::Status(code, _) => Some(*code),
                _ => None,
            },
            _ => None,
        };
        Error::msg(format!(
            "cannot download `{path}` from Hugging Face repo `{repo}` (revision {rev}): {e}. {}",
            download_advice(repo, status)
        ))
    })
}

/// What to do about a failed download, by the HTTP status the hub answered.
#[cfg_attr(not(feature = "hub"), allow(dead_code))]
fn download_advice(repo: &str, status: Option<u16>) -> String {
    let token = crate::settings::current().hf_token.is_some();
    match status {
        Some(401) if !token => format!(
            "The hub wants a token: `{repo}` is gated or private. Set HF_TOKEN (or run `huggingface-cli login`) with an account that was granted access"
        ),
        Some(401 | 403) => format!(
            "The hub refused the token: `{repo}` is gated or private and this account has no access yet. Request access on the repo's page, then retry"
        ),
        Some(404) => format!("The hub has no such file: check the repo name `{repo}`, the revision and the path (a manifest of another release?)"),
        Some(code) => format!("The hub answered HTTP {code}; retry later, or check HF_ENDPOINT and the proxy"),
        None => "Check network access (HF_ENDPOINT, proxy) and that the file exists; gated repos need HF_TOKEN".to_string(),
    }
}

#[cfg(not(feature = "hub"))]
fn hf_client(_: &Path) -> Result<Client> {
    Ok(())
}

#[cfg(not(feature = "hub"))]
fn download_hf(_: &Client, repo: &str, _: &str, path: &str) -> Result<PathBuf> {
    Err(Error::msg(format!(
        "`{path}` of `{repo}` is not in the Hugging Face cache, and this build of recon-core has no `hub` feature, \
         so it cannot download it; place the files in a folder and load it, or build with `--features hub`"
    )))
}

/// The applied settings' Hugging Face hub cache ([`hf_cache::default_cache`]).
pub fn default_hf_cache() -> PathBuf {
    hf_cache::default_cache()
}

#[cfg(feature = "hub")]
fn download_url(url: &str, dest: &Path) -> Result<()> {
    let tmp = dest.with_extension("part");
    let resp = ureq::get(url).call().map_err(|e| Error::msg(format!("request to {url} failed: {e}")))?;
    let len = resp.header("content-length").and_then(|l| l.parse::<u64>().ok());
    // The same bar hf-hub draws for hub files (hidden when stderr is not a terminal).
    let bar = indicatif::ProgressBar::new(len.unwrap_or(0));
    if let Ok(style) =
        indicatif::ProgressStyle::with_template("{msg} [{elapsed_precise}] [{wide_bar}] {bytes}/{total_bytes} {bytes_per_sec} ({eta})")
    {
        bar.set_style(style);
    }
    bar.set_message(dest.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default());
    let mut reader = bar.wrap_read(resp.into_reader());
    let mut f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let n = std::io::copy(&mut reader, &mut f).map_err(|e| Error::msg(format!("download of {url} interrupted: {e}")))?;
    bar.finish_and_clear();
    if len.is_some_and(|l| l != n) {
        return Err(Error::msg(format!("download of {url} ended after {n} of {} bytes", len.unwrap_or(0))));
    }
    std::fs::rename(&tmp, dest).map_err(|e| Error::io(dest, e))?;
    Ok(())
}

#[cfg(not(feature = "hub"))]
fn download_url(url: &str, _: &Path) -> Result<()> {
    Err(Error::msg(format!("this build of recon-core has no `hub` feature, so it cannot download {url}")))
}

#[cfg(test)]
mod tests {
    /// The hub's answer decides the advice: a token for 401, access for 403, the name for 404.
    #[test]
    fn download_advice_by_status() {
        let a = |s| super::download_advice("TRI-ML/RecGen", s);
        assert!(a(Some(401)).contains("Set HF_TOKEN") && a(Some(401)).contains("gated or private"), "{}", a(Some(401)));
        assert!(a(Some(403)).contains("Request access"), "{}", a(Some(403)));
        assert!(a(Some(404)).contains("check the repo name `TRI-ML/RecGen`"), "{}", a(Some(404)));
        assert!(a(Some(503)).contains("HTTP 503") && a(None).contains("network"));
    }
}
