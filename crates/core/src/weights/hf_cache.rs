//! The Hugging Face hub cache as `huggingface_hub` (Python) and `hf-hub`
//! (Rust) lay it out, read without either:
//!
//! ```text
//! <cache>/models--ORG--NAME/blobs/<sha256 or git sha1>          file contents
//! <cache>/models--ORG--NAME/snapshots/<commit>/<path in repo>   symlinks into blobs/ (or copies)
//! <cache>/models--ORG--NAME/refs/<branch>                       the commit a branch was at
//! ```
//!
//! `<cache>` is `$HF_HUB_CACHE`, else `$HF_HOME/hub`, else
//! `~/.cache/huggingface/hub` ([`default_cache`], from the applied
//! [settings](crate::settings)). A revision is a commit (its snapshot folder)
//! or a branch/tag (its `refs/` file names the commit). hf-hub 0.4 looks a
//! file up through `refs/<revision>` only, which misses a commit pinned by
//! revision in a cache Python filled (Python writes no ref for a commit), so
//! recon resolves the snapshot itself.
//!
//! Also here: SHA-256 of files, checked against a manifest's pins.

use crate::{Error, Result};
use std::io::Read;
use std::path::{Path, PathBuf};

/// The applied settings' hub cache: `$HF_HUB_CACHE`, else `$HF_HOME/hub`,
/// else `~/.cache/huggingface/hub`; `./.cache/huggingface/hub` without a home folder.
pub fn default_cache() -> PathBuf {
    crate::settings::current().hf_cache.unwrap_or_else(|| PathBuf::from(".").join(".cache").join("huggingface").join("hub"))
}

/// `<cache>/models--ORG--NAME`.
pub fn repo_folder(cache: &Path, repo: &str) -> PathBuf {
    cache.join(format!("models--{}", repo.replace('/', "--")))
}

/// True for a full git commit id (40 hex digits).
pub fn is_commit(rev: &str) -> bool {
    rev.len() == 40 && rev.bytes().all(|b| b.is_ascii_hexdigit())
}

/// The commit a branch or tag points to in the cache (`refs/<rev>`).
fn read_ref(repo_dir: &Path, rev: &str) -> Option<String> {
    let text = std::fs::read_to_string(repo_dir.join("refs").join(rev)).ok()?;
    let c = text.trim();
    (!c.is_empty()).then(|| c.to_string())
}

/// A snapshot of a repo in the cache.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// `<cache>/models--ORG--NAME/snapshots/<commit>`.
    pub dir: PathBuf,
    /// The commit.
    pub commit: String,
    /// The revision asked for, when the snapshot is another one (the pinned
    /// commit is absent and `main` was taken instead).
    pub instead_of: Option<String>,
}

/// The snapshot of `repo` at `revision` (a commit, or a branch/tag through
/// `refs/`). When a pinned commit is absent but `refs/main` names a snapshot,
/// that one is taken (`instead_of` says so): a cache filled by upstream's own
/// `hf_hub_download` holds the branch head, and the manifest's SHA-256 pins
/// decide whether its files are the pinned ones.
pub fn snapshot(cache: &Path, repo: &str, revision: &str) -> Option<Snapshot> {
    let dir = repo_folder(cache, repo);
    let at = |commit: String| {
        let d = dir.join("snapshots").join(&commit);
        d.is_dir().then_some((d, commit))
    };
    // A snapshot folder named by the revision itself (a commit), else the ref.
    if let Some((d, commit)) = at(revision.to_string()).or_else(|| read_ref(&dir, revision).and_then(at)) {
        return Some(Snapshot { dir: d, commit, instead_of: None });
    }
    if revision != "main" {
        if let Some((d, commit)) = read_ref(&dir, "main").and_then(at) {
            return Some(Snapshot { dir: d, commit, instead_of: Some(revision.to_string()) });
        }
    }
    None
}

/// Where `path` of `repo` at `revision` is in the cache, or an error naming
/// the repo, revision, file and cache. `offline` (`HF_HUB_OFFLINE`) only
/// changes the advice.
pub fn cached_file(cache: &Path, repo: &str, revision: &str, path: &str, offline: bool) -> Result<PathBuf> {
    if let Some(s) = snapshot(cache, repo, revision) {
        let p = s.dir.join(path);
        if p.is_file() {
            return Ok(p);
        }
    }
    Err(cache_miss(cache, repo, revision, path, offline))
}

/// The error for a file the cache lacks.
pub fn cache_miss(cache: &Path, repo: &str, revision: &str, path: &str, offline: bool) -> Error {
    let how = if offline {
        "HF_HUB_OFFLINE is set, so nothing is downloaded: fetch it where the network is reachable (`recon weights fetch`) and copy the cache, or point HF_HUB_CACHE / HF_HOME at a cache that holds it"
    } else {
        "download it with `recon weights fetch`"
    };
    Error::input(
        repo_folder(cache, repo).display().to_string(),
        format!("Hugging Face repo `{repo}` (revision {revision}): file `{path}` is not in the cache {}; {how}", cache.display()),
    )
}

/// SHA-256 of a file's contents, lower-case hex.
pub fn sha256_file(path: &Path) -> Result<String> {
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut ctx = ring::digest::Context::new(&ring::digest::SHA256);
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(|e| Error::io(path, e))?;
        if n == 0 {
            break;
        }
        ctx.update(&buf[..n]);
    }
    Ok(ctx.finish().as_ref().iter().map(|b| format!("{b:02x}")).collect())
}

/// Check `path` against a pinned SHA-256 (hex, any case): a mismatch is
/// [`Error::ChecksumMismatch`] naming the file and both hashes.
pub fn check_sha256(path: &Path, expected: &str) -> Result<()> {
    let actual = sha256_file(path)?;
    if actual.eq_ignore_ascii_case(expected.trim()) {
        Ok(())
    } else {
        Err(Error::ChecksumMismatch { file: path.display().to_string(), expected: expected.trim().to_ascii_lowercase(), actual })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sha256_of_known_contents() -> Result<()> {
        let dir = crate::util::testing::tmp("sha256");
        let p = dir.join("abc");
        std::fs::write(&p, b"abc").map_err(|e| Error::io(&p, e))?;
        let abc = "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad";
        assert_eq!(sha256_file(&p)?, abc);
        check_sha256(&p, &abc.to_ascii_uppercase())?;
        let e = check_sha256(&p, &"0".repeat(64)).unwrap_err().to_string();
        assert!(e.contains(&p.display().to_string()) && e.contains(abc) && e.contains(&"0".repeat(64)), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
        Ok(())
    }

    /// Commit snapshots, branch refs, and the `main` fallback for an absent pin.
    #[test]
    fn snapshots_resolve_by_commit_ref_or_main() {
        let cache = crate::util::testing::tmp("hf-snapshots");
        let (c1, c2) = ("a".repeat(40), "b".repeat(40));
        let repo = repo_folder(&cache, "org/m");
        assert!(repo.ends_with("models--org--m"));
        for c in [&c1, &c2] {
            std::fs::create_dir_all(repo.join("snapshots").join(c)).unwrap();
        }
        std::fs::write(repo.join("snapshots").join(&c2).join("f.json"), "{}").unwrap();
        assert!(snapshot(&cache, "org/m", &c1).is_some_and(|s| s.commit == c1 && s.instead_of.is_none()));
        assert!(snapshot(&cache, "org/m", "main").is_none());
        std::fs::create_dir_all(repo.join("refs")).unwrap();
        std::fs::write(repo.join("refs/main"), format!("{c2}\n")).unwrap();
        assert!(snapshot(&cache, "org/m", "main").is_some_and(|s| s.commit == c2));
        let other = "c".repeat(40);
        let s = snapshot(&cache, "org/m", &other).unwrap();
        assert_eq!((s.commit.as_str(), s.instead_of.as_deref()), (c2.as_str(), Some(other.as_str())));
        assert!(cached_file(&cache, "org/m", "main", "f.json", false).unwrap().ends_with("f.json"));
        let e = cached_file(&cache, "org/m", "main", "g.bin", true).unwrap_err().to_string();
        assert!(e.contains("org/m") && e.contains("g.bin") && e.contains("HF_HUB_OFFLINE"), "{e}");
        assert!(snapshot(&cache, "org/none", "main").is_none());
        let _ = std::fs::remove_dir_all(&cache);
    }
}
