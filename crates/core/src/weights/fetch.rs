//! `recon weights fetch`: download a manifest's files. Hugging Face files go
//! through `hf-hub` into the standard HF cache (`$HF_HOME/hub`, or `--cache`);
//! URL-sourced files (the torch.hub DINOv2 checkpoint) are downloaded with
//! `ureq` into `<cache>/recon-url/<manifest>/`.

use crate::weights::manifest::Manifest;
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// Download every non-optional file (and optional ones when `with_optional`).
/// Returns the local paths. The first failure aborts with a message naming
/// the repo, revision and file.
pub fn fetch(m: &Manifest, cache: Option<&Path>, with_optional: bool) -> Result<Vec<PathBuf>> {
    let files: Vec<_> = m.files.iter().filter(|f| with_optional || !f.optional).collect();
    let mut out = Vec::new();
    match m.source.as_str() {
        "huggingface" => out.extend(fetch_hf(m, &files, cache)?),
        "url" => {
            let base = cache.map(Path::to_path_buf).unwrap_or_else(default_hf_cache).join("recon-url").join(&m.name);
            std::fs::create_dir_all(&base).map_err(|e| Error::io(&base, e))?;
            for f in files {
                let url = f.url.as_ref().ok_or_else(|| Error::config(&m.name, "url", format!("file `{}` has no url", f.path)))?;
                let dest = base.join(&f.path);
                if !dest.exists() {
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
        }
        other => return Err(Error::config(&m.name, "source", format!("unknown source `{other}`"))),
    }
    Ok(out)
}

/// The Hugging Face files of `m` through hf-hub's client and cache.
#[cfg(feature = "hub")]
fn fetch_hf(m: &Manifest, files: &[&crate::weights::manifest::ManifestFile], cache: Option<&Path>) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();

    use hf_hub::api::sync::ApiBuilder;
    use hf_hub::{Repo, RepoType};
    let repo = m.repo.clone().ok_or_else(|| Error::config(&m.name, "repo", "missing for a huggingface manifest"))?;
    let rev = m.revision.clone().unwrap_or_else(|| "main".into());
    let mut b = ApiBuilder::from_env().with_progress(true);
    if let Some(c) = cache {
        b = b.with_cache_dir(c.to_path_buf());
    }
    let api = b.build().map_err(|e| Error::msg(format!("hf-hub: cannot set up the client: {e}")))?;
    let r = api.repo(Repo::with_revision(repo.clone(), RepoType::Model, rev.clone()));
    for f in files {
        let p = r.get(&f.path).map_err(|e| {
            Error::msg(format!(
                "cannot download `{}` from Hugging Face repo `{repo}` (revision {rev}): {e}. \
                         Check network access (HF_ENDPOINT, proxy) and that the file exists; \
                         gated repos need HF_TOKEN",
                f.path
            ))
        })?;
        out.push(p);
    }
    Ok(out)
}

#[cfg(not(feature = "hub"))]
fn fetch_hf(m: &Manifest, _: &[&crate::weights::manifest::ManifestFile], _: Option<&Path>) -> Result<Vec<PathBuf>> {
    Err(Error::msg(format!(
        "manifest `{}`: this build of recon-core has no `hub` feature, so it cannot download from Hugging Face; \
         place the files in a folder and load it, or build with `--features hub`",
        m.name
    )))
}

/// The applied settings' Hugging Face cache: `$HF_HOME/hub`, else
/// `~/.cache/huggingface/hub` (hf-hub's own default); `./.cache/huggingface/hub`
/// without a home folder.
pub fn default_hf_cache() -> PathBuf {
    crate::settings::current().hf_cache.unwrap_or_else(|| PathBuf::from(".").join(".cache").join("huggingface").join("hub"))
}

#[cfg(feature = "hub")]
fn download_url(url: &str, dest: &Path) -> Result<()> {
    let tmp = dest.with_extension("part");
    let resp = ureq::get(url).call().map_err(|e| Error::msg(format!("request to {url} failed: {e}")))?;
    let mut reader = resp.into_reader();
    let mut f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    std::io::copy(&mut reader, &mut f).map_err(|e| Error::msg(format!("download of {url} interrupted: {e}")))?;
    std::fs::rename(&tmp, dest).map_err(|e| Error::io(dest, e))?;
    Ok(())
}

#[cfg(not(feature = "hub"))]
fn download_url(url: &str, _: &Path) -> Result<()> {
    Err(Error::msg(format!("this build of recon-core has no `hub` feature, so it cannot download {url}")))
}
