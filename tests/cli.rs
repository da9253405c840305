//! The command line's own surface: `-V` / `--version` (build, features and CPU kernels),
//! `recon completions`, `recon man`, and the one line that says the small default model
//! answers when no `--weights` were given.
mod common;

use common::{recon, recon_with_env, repo, tmp};
use std::path::Path;
use std::process::Command;

fn stdout(o: &std::process::Output) -> String {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8(o.stdout.clone()).unwrap()
}

/// The value after `key: ` on the line that starts with it.
fn field<'a>(text: &'a str, key: &str) -> &'a str {
    let prefix = format!("{key}: ");
    text.lines().find_map(|l| l.strip_prefix(prefix.as_str())).unwrap_or_else(|| panic!("no `{key}:` line in\n{text}"))
}

/// `-V` is one line; `--version` adds the commit (a commit of this repository when built
/// from it), the build, recon-core's features, the embedded model and the kernels, which
/// follow RECON_ISA.
#[test]
fn version_reports_build_features_and_kernels() {
    let short = stdout(&recon(&["-V"]));
    assert_eq!(short, format!("recon {}\n", env!("CARGO_PKG_VERSION")));

    let long = stdout(&recon(&["--version"]));
    assert_eq!(long.lines().next(), Some(short.trim_end()), "{long}");
    let commit = field(&long, "commit");
    let git = |args: &[&str]| Command::new("git").args(args).current_dir(repo()).output().ok().filter(|o| o.status.success());
    if git(&["rev-parse", "HEAD"]).is_some() {
        // Built from this checkout: a full hash of one of its commits.
        assert!(commit.len() == 40 && commit.bytes().all(|b| b.is_ascii_hexdigit()), "{commit}");
        assert!(git(&["cat-file", "-e", &format!("{commit}^{{commit}}")]).is_some(), "{commit} is no commit of this repository");
    } else {
        assert!(commit == "unknown" || commit.len() == 40, "{commit}");
    }
    assert!(field(&long, "build").contains(std::env::consts::ARCH), "{long}");
    // The CLI builds recon-core with its clap derives and the hub download.
    let features = field(&long, "features");
    assert!(features.starts_with("recon-core [") && features.contains("hub") && features.contains("clap"), "{features}");
    // A checkout's build embeds the trained default (crates/core/build.rs).
    let model = field(&long, "embedded model");
    let hash = model.strip_prefix("recgen-nano ").unwrap_or_else(|| panic!("{model}"));
    assert!(hash.len() == 16 && hash.bytes().all(|b| b.is_ascii_hexdigit()), "{model}");
    let kernels = field(&long, "cpu kernels");
    let best = kernels.split([',', ' ']).next().unwrap();
    assert!(["portable", "avx2", "avx512", "avx512bf16"].contains(&best), "{kernels}");
    assert!(kernels.contains("this CPU runs: portable") && kernels.contains(best) && kernels.contains("bf16 weights: "), "{kernels}");

    // RECON_ISA caps what runs, and the report says so.
    let o = recon_with_env(&["--version"], &[("RECON_ISA", Path::new("portable"))]);
    let capped = stdout(&o);
    let kernels = field(&capped, "cpu kernels");
    assert!(kernels.starts_with("portable, capped by RECON_ISA=portable"), "{kernels}");
    assert!(kernels.ends_with("bf16 weights: portable (widened to f32 FMA)"), "{kernels}");
    // `-V` stays one line whatever the environment.
    assert_eq!(stdout(&recon_with_env(&["-V"], &[("RECON_ISA", Path::new("portable"))])), short);
}

/// Completion scripts come from the clap definitions: bash's names the real subcommands
/// and flags (nested ones included); zsh and fish work too; an unknown shell is refused.
#[test]
fn completions_name_the_real_commands_and_flags() {
    let bash = stdout(&recon(&["completions", "bash"]));
    assert!(bash.contains("complete -F _recon") && bash.contains("recon"), "{bash}");
    for word in ["infer", "serve", "scene", "weights", "fetch", "completions", "man", "--weights", "--rgbd", "--masks", "--max-faces"] {
        assert!(bash.contains(word), "bash completion lacks {word}");
    }
    for shell in ["zsh", "fish"] {
        let s = stdout(&recon(&["completions", shell]));
        assert!(s.contains("infer") && s.contains("rgbd"), "{shell}");
    }
    let o = recon(&["completions", "tcsh"]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("tcsh"));
}

/// roff requests (lines starting with `.`) used by clap_mangen's pages: a line with any
/// other request is not the roff we expect.
const ROFF_REQUESTS: [&str; 17] =
    [".TH", ".SH", ".SS", ".TP", ".PP", ".IP", ".RS", ".RE", ".B", ".I", ".br", ".sp", ".nf", ".fi", ".ie", ".el", ".\\\""];

/// The page as roff: a `.TH` title first (with recon's version), known requests only, and
/// the NAME section naming the command (`-` escaped there).
fn check_roff(page: &str, name: &str) {
    // Only the quote-string definition (`.ie`/`.el`) and comments come before the title.
    let title = page.lines().find(|l| !l.starts_with(".ie ") && !l.starts_with(".el ") && !l.starts_with(".\\\"")).unwrap_or_default();
    assert!(title.starts_with(&format!(".TH {name} 1")) && title.contains(env!("CARGO_PKG_VERSION")), "{title}");
    for l in page.lines().filter(|l| l.starts_with('.')) {
        let req = l.split_whitespace().next().unwrap();
        assert!(ROFF_REQUESTS.contains(&req), "unexpected roff request {req:?} in {name}'s page: {l}");
    }
    let after_name = page.split(".SH NAME\n").nth(1).unwrap_or_else(|| panic!("{name}: no NAME section\n{page}"));
    let name_line = after_name.lines().next().unwrap();
    assert!(name_line.starts_with(&format!("{} \\- ", name.replace('-', "\\-"))), "{name_line}");
}

/// `recon man` prints recon(1); `--out` writes a page per subcommand. Where groff is
/// installed, it formats the page (UTF-8 input through preconv, `-k`, as man does) with no
/// warning and shows NAME and the commands.
#[test]
fn man_pages_are_roff_with_a_name_section() {
    let page = stdout(&recon(&["man"]));
    check_roff(&page, "recon");
    assert!(page.contains(".SH SUBCOMMANDS") && page.contains("recon\\-infer"), "{page}");

    let dir = tmp("cli-man");
    let o = recon(&["man", "--out", dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(std::fs::read_to_string(dir.join("recon.1")).unwrap(), page);
    let infer = std::fs::read_to_string(dir.join("recon-infer.1")).unwrap();
    check_roff(&infer, "recon-infer");
    assert!(infer.contains("\\-\\-weights") && infer.contains("\\-\\-rgbd"), "{infer}");
    assert!(dir.join("recon-weights-fetch.1").is_file() && dir.join("recon-completions.1").is_file());

    let mut pages: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
    pages.sort();
    assert!(pages.len() >= 15 && pages.iter().all(|p| p.extension().is_some_and(|x| x == "1")), "{pages:?}");
    for p in &pages {
        check_roff(&std::fs::read_to_string(p).unwrap(), p.file_stem().unwrap().to_str().unwrap());
        // -P-cbou: plain text, no overstrike.
        if let Ok(o) = Command::new("groff").args(["-k", "-man", "-Tutf8", "-ww", "-P-cbou"]).arg(p).output() {
            let text = String::from_utf8_lossy(&o.stdout);
            let warnings = String::from_utf8_lossy(&o.stderr);
            assert!(o.status.success() && warnings.trim().is_empty(), "groff on {}: {warnings}", p.display());
            assert!(text.contains("NAME") && text.contains("SYNOPSIS"), "{text}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// The prefix of the line `recon infer` prints when recgen-nano answers by default.
const NOTE: &str = "recon: no --weights given, so recgen-nano answers";

/// The weights' identity as recon defines it (`WeightsSource::sha256`): SHA-256 over
/// `<module> <SHA-256 of its file>` lines in the architecture's module order.
fn weights_sha256(dir: &Path) -> String {
    use recon::weights::hf_cache::sha256_file;
    let arch = recon::model::RecGenConfig::load(&dir.join("recgen-nano.json")).unwrap();
    let lines: String = arch
        .modules()
        .into_iter()
        .map(|(key, _)| format!("{key} {}\n", sha256_file(&dir.join(format!("{key}.safetensors"))).unwrap()))
        .collect();
    let list = tmp("cli-identity").join("lines");
    std::fs::write(&list, lines).unwrap();
    sha256_file(&list).unwrap()
}

/// No `--weights`: one line on stderr says the small default answers and how to load the
/// released weights; with `--weights` there is no such line. Either way every pose.json
/// records the recon version and the model (name, weights' hash), the same for the same
/// checkpoints from another folder.
#[test]
fn infer_says_once_when_the_default_model_answers() {
    let t = tmp("cli-note");
    let run = |extra: &[&str], out: &str| {
        let out = t.join(out);
        let base = ["infer", "--rgbd", "data/sample/000001-color.png", "--masks", "data/sample/000001-label.png", "--objects", "14,21"];
        let fast = ["--steps", "1", "--max-faces", "0", "--out", out.to_str().unwrap()];
        let o = recon_with_env(&[&base[..], &fast[..], extra].concat(), &[("RECON_CACHE", &t.join("cache"))]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let pose = common::read_json(&out.join("id_21/pose.json"));
        (String::from_utf8(o.stderr).unwrap(), pose)
    };
    let (stderr, pose) = run(&[], "default");
    assert_eq!(stderr.matches(NOTE).count(), 1, "{stderr}");
    let line = stderr.lines().find(|l| l.starts_with(NOTE)).unwrap();
    assert!(line.contains("recon weights fetch recgen") && line.contains("--weights hf:TRI-ML/RecGen"), "{line}");
    assert_eq!(pose["recon_version"], env!("CARGO_PKG_VERSION"));
    let nano = repo().join("models/recgen-nano");
    let identity = serde_json::json!({"name": "recgen-nano", "sha256": weights_sha256(&nano)});
    assert_eq!(pose["model_identity"], identity);
    assert_eq!(pose["run"]["weights"]["sha256"], identity["sha256"]);

    // The same checkpoints from another folder: no note, the same identity.
    let copy = t.join("nano-copy");
    std::fs::create_dir_all(&copy).unwrap();
    for e in std::fs::read_dir(&nano).unwrap().flatten().filter(|e| e.path().is_file()) {
        std::fs::copy(e.path(), copy.join(e.file_name())).unwrap();
    }
    let (stderr, pose) = run(&["--weights", copy.to_str().unwrap()], "given");
    assert!(!stderr.contains(NOTE), "{stderr}");
    assert_eq!(pose["model_identity"], identity);
    let _ = std::fs::remove_dir_all(&t);
}

/// Outside a checkout (no models/ in the working folder) a source that names no architecture
/// file takes recon's compiled-in copy: `--weights random` runs recgen-tiny from the cache.
#[test]
fn infer_runs_outside_a_checkout() {
    let t = tmp("cli-outside");
    let sample = repo().join("data/sample");
    let out = t.join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_recon"))
        .args(["infer", "--rgbd"])
        .arg(sample.join("000001-color.png"))
        .arg("--masks")
        .arg(sample.join("000001-label.png"))
        .args(["--objects", "21", "--weights", "random", "--steps", "1", "--max-faces", "0", "--json", "--out"])
        .arg(&out)
        .current_dir(&t)
        .env("RECON_CACHE", t.join("cache"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let config = Path::new(summary["config"].as_str().unwrap());
    assert!(config.starts_with(t.join("cache")) && config.ends_with("recgen-tiny.json"), "{config:?}");
    assert_eq!(std::fs::read(config).unwrap(), std::fs::read(repo().join("models/recgen-tiny.json")).unwrap());
    assert_eq!(summary["model_identity"], serde_json::json!({"name": "recgen-tiny", "sha256": null}));
    assert!(out.join("id_21/pose.json").is_file());
    let _ = std::fs::remove_dir_all(&t);
}
