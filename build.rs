//! Build facts `recon --version` prints: the git commit, the target and the profile.
//!
//! The commit comes from `git rev-parse HEAD` in a checkout; in a source package (which
//! holds Cargo.toml.orig) from the `.cargo_vcs_info.json` cargo writes into it; else it
//! is `unknown`.

use std::path::Path;
use std::process::Command;

fn main() {
    let dir = std::env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR");
    let dir = Path::new(&dir);
    let commit = if dir.join("Cargo.toml.orig").exists() { packaged_commit(dir) } else { git_commit(dir) };
    println!("cargo::rustc-env=RECON_GIT_COMMIT={}", commit.unwrap_or_else(|| "unknown".to_string()));
    println!("cargo::rustc-env=RECON_BUILD_TARGET={}", std::env::var("TARGET").unwrap_or_default());
    println!("cargo::rustc-env=RECON_BUILD_PROFILE={}", std::env::var("PROFILE").unwrap_or_default());
    println!("cargo::rerun-if-changed=build.rs");
}

/// HEAD's commit, and the files whose change moves it (so a new commit rebuilds).
fn git_commit(dir: &Path) -> Option<String> {
    let git = |args: &[&str]| -> Option<String> {
        let o = Command::new("git").args(args).current_dir(dir).output().ok()?;
        o.status.success().then(|| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    let commit = git(&["rev-parse", "HEAD"])?;
    let mut watch = vec!["HEAD".to_string(), "packed-refs".to_string()];
    watch.extend(git(&["symbolic-ref", "-q", "HEAD"]));
    for w in watch {
        // `--path-format=absolute`: a worktree's HEAD lives outside `dir`.
        if let Some(p) = git(&["rev-parse", "--path-format=absolute", "--git-path", &w]).filter(|p| Path::new(p).exists()) {
            println!("cargo::rerun-if-changed={p}");
        }
    }
    Some(commit).filter(|c| c.len() >= 40 && c.bytes().all(|b| b.is_ascii_hexdigit()))
}

/// `git.sha1` of the package's `.cargo_vcs_info.json` (`cargo package` writes it).
fn packaged_commit(dir: &Path) -> Option<String> {
    let text = std::fs::read_to_string(dir.join(".cargo_vcs_info.json")).ok()?;
    let at = text.find("\"sha1\"")?;
    let rest = &text[at + 6..];
    let start = rest.find('"')? + 1;
    let sha: String = rest[start..].chars().take_while(|c| c.is_ascii_hexdigit()).collect();
    (sha.len() == 40).then_some(sha)
}
