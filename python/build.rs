//! Records the git commit the extension is built from (`recon_rgbd.info()["commit"]`), when it
//! is built from a git checkout with git on the PATH; a build from the sdist has none.
use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    out.status.success().then(|| String::from_utf8_lossy(&out.stdout).trim().to_string()).filter(|s| !s.is_empty())
}

fn main() {
    if let Some(commit) = git(&["rev-parse", "HEAD"]) {
        println!("cargo:rustc-env=RECON_GIT_COMMIT={commit}");
        // Rebuilt when HEAD moves: HEAD itself (a branch switch) and the branch it points to (a commit).
        for p in [
            git(&["rev-parse", "--git-path", "HEAD"]),
            git(&["symbolic-ref", "-q", "HEAD"]).and_then(|r| git(&["rev-parse", "--git-path", &r])),
        ]
        .into_iter()
        .flatten()
        {
            println!("cargo:rerun-if-changed={p}");
        }
    }
}
