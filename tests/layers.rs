//! The layer rule of `docs/ARCHITECTURE.md`, read from the source.
//!
//! - Between crates: each crate of the workspace depends only on the crates
//!   listed before it in [`CRATES`] (the compiler then refuses any other import).
//! - Inside `recon-core`: every `crate::…` / `super::…` / `self::…` path in
//!   `crates/core/src/` (tests inside the library included) may only name its own
//!   top-level module or one listed below it in [`LAYERS`].
//! - In every crate the files import each other without a circle (test modules
//!   left out of the circle check: a test may use a sibling's helpers).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The workspace's crates, bottom first, with their folders (the order of `docs/ARCHITECTURE.md`).
const CRATES: &[(&str, &str)] = &[
    ("recon-kernels", "crates/kernels"),
    ("recon-core", "crates/core"),
    ("recon-testkit", "crates/testkit"),
    ("recon-synth", "crates/synth"),
    ("recon-eval", "crates/eval"),
    ("recon-sim", "crates/sim"),
    ("recon-audit", "crates/audit"),
    ("recon-train", "crates/train"),
    ("recon-serve", "crates/serve"),
    ("recon", "."),
    ("recon-python", "python"),
];

/// Top-level modules of `recon-core`, bottom first (the order of `docs/ARCHITECTURE.md`).
const LAYERS: &[&str] = &[
    "error",
    "settings",
    "math",
    "rng",
    "util",
    "spatial",
    "mesh",
    "gaussians",
    "dataset",
    "sensor",
    "render",
    "export",
    "geometry",
    "model",
    "weights",
    "engine",
];

/// A source file of the library: its module path and its code, with comments
/// removed and test modules split off.
struct Source {
    module: Vec<String>,
    code: String,
    test_code: String,
    /// Child modules declared with `mod name;`.
    children: BTreeSet<String>,
}

fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn core_dir() -> PathBuf {
    workspace().join("crates/core/src")
}

fn rs_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rs_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

fn module_of(rel: &Path) -> Vec<String> {
    let mut parts: Vec<String> = rel.with_extension("").iter().map(|s| s.to_string_lossy().into_owned()).collect();
    if parts.last().is_some_and(|l| l == "mod" || l == "lib") {
        parts.pop();
    }
    parts
}

/// Drops `//` comments (doc comments included) and string literals, which may
/// mention paths without importing them.
fn strip(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        let mut in_str = false;
        let mut prev = ' ';
        let mut chars = line.chars().peekable();
        while let Some(c) = chars.next() {
            if !in_str && c == '/' && chars.peek() == Some(&'/') {
                break;
            }
            // Char literals such as '{' or '"' are dropped whole.
            if !in_str && c == '\'' {
                let ahead: Vec<char> = chars.clone().take(3).collect();
                let len = match ahead.as_slice() {
                    ['\\', _, '\'', ..] => Some(3),
                    [_, '\'', ..] => Some(2),
                    _ => None,
                };
                if let Some(n) = len {
                    for _ in 0..n {
                        chars.next();
                    }
                    prev = '\'';
                    continue;
                }
            }
            if c == '"' && prev != '\\' && prev != '\'' {
                in_str = !in_str;
                prev = c;
                continue;
            }
            if !in_str {
                out.push(c);
            }
            prev = c;
        }
        out.push('\n');
    }
    out
}

/// Splits `#[cfg(test)] mod … { … }` blocks off the code.
fn split_tests(code: &str) -> (String, String) {
    let (mut main, mut tests) = (String::new(), String::new());
    let mut rest = code;
    // Test-only code: `#[cfg(test)]` (the fixtures other crates' tests share are ordinary,
    // doc-hidden modules and obey the layers like any code).
    while let Some(i) = ["#[cfg(test)]"].iter().filter_map(|m| rest.find(m)).min() {
        main.push_str(&rest[..i]);
        let after = &rest[i..];
        let open = after.find(['{', ';']).unwrap_or(after.len() - 1);
        if after.as_bytes()[open] == b';' {
            // `#[cfg(test)] use …;` or `mod x;`
            tests.push_str(&after[..=open]);
            rest = &after[open + 1..];
            continue;
        }
        let mut depth = 0usize;
        let mut end = after.len();
        for (k, ch) in after.char_indices().skip(open) {
            match ch {
                '{' => depth += 1,
                '}' => {
                    depth -= 1;
                    if depth == 0 {
                        end = k + 1;
                        break;
                    }
                }
                _ => {}
            }
        }
        tests.push_str(&after[..end]);
        rest = &after[end..];
    }
    main.push_str(rest);
    (main, tests)
}

fn read_sources(root: &Path) -> BTreeMap<Vec<String>, Source> {
    let mut files = Vec::new();
    rs_files(root, &mut files);
    let mut out = BTreeMap::new();
    for f in files {
        let rel = f.strip_prefix(root).unwrap().to_path_buf();
        // The binary (`main.rs`, `cli/`) is a separate crate on top of the library.
        if rel.starts_with("cli") || rel == Path::new("main.rs") {
            continue;
        }
        let (code, test_code) = split_tests(&strip(&std::fs::read_to_string(&f).unwrap()));
        let children = code
            .lines()
            .filter_map(|l| {
                let l = l.trim();
                let l = l.strip_prefix("pub ").unwrap_or(l);
                let l = l.strip_prefix("pub(crate) ").unwrap_or(l);
                l.strip_prefix("mod ").and_then(|r| r.strip_suffix(';')).map(str::to_string)
            })
            .collect();
        out.insert(module_of(&rel), Source { module: module_of(&rel), code, test_code, children });
    }
    out
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// Every path the code names from a root (`crate::`, `super::`, or a child
/// module of a `mod.rs`), as absolute module paths (a trailing item name
/// included; brace groups expanded one level).
fn paths(src: &Source, code: &str) -> Vec<Vec<String>> {
    let mut out = Vec::new();
    let bytes: Vec<char> = code.chars().collect();
    let text: String = bytes.iter().collect();
    let mut i = 0;
    while i < bytes.len() {
        if i > 0 && (is_ident(bytes[i - 1]) || bytes[i - 1] == ':') {
            i += 1;
            continue;
        }
        let rest: String = bytes[i..bytes.len().min(i + 7)].iter().collect();
        let (mut base, start) = if rest.starts_with("crate::") {
            (Vec::new(), i + 7)
        } else if rest.starts_with("self::") {
            (src.module.clone(), i + 6)
        } else if rest.starts_with("super::") {
            let mut j = i;
            let mut base = src.module.clone();
            while text[char_offset(&text, j)..].starts_with("super::") {
                base.pop();
                j += 7;
            }
            (base, j)
        } else {
            // A child module named at the start of a path (`use child::Item` in a mod.rs).
            let word: String = bytes[i..].iter().take_while(|c| is_ident(**c)).collect();
            let after = i + word.chars().count();
            if !word.is_empty() && src.children.contains(&word) && text[char_offset(&text, after)..].starts_with("::") {
                (src.module.clone(), i)
            } else {
                i += 1;
                continue;
            }
        };
        // Read `a::b::c` or `a::b::{x, y::z}`.
        let mut j = start;
        let mut segs = Vec::new();
        loop {
            let w: String = bytes[j..].iter().take_while(|c| is_ident(**c)).collect();
            if w.is_empty() {
                break;
            }
            j += w.chars().count();
            segs.push(w);
            if text[char_offset(&text, j)..].starts_with("::") {
                j += 2;
            } else {
                break;
            }
        }
        base.extend(segs);
        if j < bytes.len() && bytes[j] == '{' {
            let close = bytes[j..].iter().position(|c| *c == '}').map(|k| j + k).unwrap_or(bytes.len());
            let inner: String = bytes[j + 1..close].iter().collect();
            for item in inner.split(',') {
                let item = item.trim().split(" as ").next().unwrap_or("").trim();
                if item.is_empty() || item == "self" {
                    out.push(base.clone());
                    continue;
                }
                let mut p = base.clone();
                p.extend(item.split("::").map(|s| s.trim().to_string()).filter(|s| !s.is_empty() && !s.contains('{')));
                out.push(p);
            }
            i = close;
        } else {
            out.push(base);
            i = j;
        }
    }
    out
}

fn char_offset(text: &str, chars: usize) -> usize {
    text.char_indices().nth(chars).map(|(b, _)| b).unwrap_or(text.len())
}

/// The file a path lands in: its longest prefix that is a module.
fn resolve(sources: &BTreeMap<Vec<String>, Source>, path: &[String]) -> Option<Vec<String>> {
    (0..=path.len()).rev().map(|n| path[..n].to_vec()).find(|p| sources.contains_key(p))
}

fn rank(top: &str) -> Option<usize> {
    LAYERS.iter().position(|l| *l == top)
}

#[test]
fn every_top_level_module_has_a_layer() {
    let sources = read_sources(&core_dir());
    let tops: BTreeSet<String> = sources.keys().filter_map(|m| m.first().cloned()).collect();
    let missing: Vec<&String> = tops.iter().filter(|t| rank(t).is_none()).collect();
    assert!(missing.is_empty(), "modules without a layer in LAYERS (and docs/ARCHITECTURE.md): {missing:?}");
}

#[test]
fn no_module_imports_a_layer_above_it() {
    let sources = read_sources(&core_dir());
    let mut upward = Vec::new();
    for src in sources.values() {
        let Some(from) = src.module.first() else { continue };
        let Some(rf) = rank(from) else { continue };
        for (code, kind) in [(&src.code, ""), (&src.test_code, " (in its tests)")] {
            for p in paths(src, code) {
                let Some(to) = p.first() else { continue };
                if let Some(rt) = rank(to) {
                    if rt > rf {
                        upward.push(format!("{} -> {}{kind}", src.module.join("::"), p.join("::")));
                    }
                }
            }
        }
    }
    upward.sort();
    upward.dedup();
    assert!(upward.is_empty(), "{} upward import(s):\n{}", upward.len(), upward.join("\n"));
}

#[test]
fn files_import_each_other_without_circles() {
    let mut circles = Vec::new();
    for (name, dir) in CRATES {
        for c in circles_in(&read_sources(&workspace().join(dir).join("src"))) {
            let c = format!("{name}: {c}");
            if !KNOWN_CIRCLES.contains(&c.as_str()) {
                circles.push(c);
            }
        }
    }
    assert!(circles.is_empty(), "{} import circle(s):\n{}", circles.len(), circles.join("\n"));
}

/// Each crate's `recon-*` dependencies come before it in [`CRATES`].
#[test]
fn crates_depend_only_on_crates_below_them() {
    let mut upward = Vec::new();
    for (i, (name, dir)) in CRATES.iter().enumerate() {
        let manifest = std::fs::read_to_string(workspace().join(dir).join("Cargo.toml")).unwrap();
        // Dependencies are the `recon-…` keys at the start of a line in a dependencies table.
        let mut in_deps = false;
        for line in manifest.lines() {
            let l = line.trim();
            if l.starts_with('[') {
                in_deps = l.ends_with("dependencies]");
                continue;
            }
            let Some(dep) = l.split(['=', '.', ' ']).next().filter(|d| in_deps && d.starts_with("recon")) else { continue };
            match CRATES.iter().position(|(n, _)| *n == dep) {
                Some(j) if j < i => {}
                Some(_) => upward.push(format!("{name} -> {dep}")),
                None => upward.push(format!("{name} -> {dep} (not in CRATES)")),
            }
        }
    }
    assert!(upward.is_empty(), "crate dependencies out of order:\n{}", upward.join("\n"));
}

/// Circles that predate the check of every crate, each with its reason; any other fails.
/// - `conv3d` and its `winograd` submodule share the tile helpers both ways (recon-kernels).
const KNOWN_CIRCLES: &[&str] = &["recon-kernels: conv3d -> conv3d::winograd -> conv3d"];

/// The import circles among one crate's files. The crate root is left out: it declares the
/// modules and re-exports names (`Error`, `Result`, `Engine`, the prelude), and every file names
/// `crate::Error` through it, which is not a dependency of one file on another.
fn circles_in(sources: &BTreeMap<Vec<String>, Source>) -> Vec<String> {
    let mut edges: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    for src in sources.values().filter(|s| !s.module.is_empty()) {
        for p in paths(src, &src.code) {
            if let Some(to) = resolve(sources, &p) {
                if to != src.module && !to.is_empty() {
                    edges.entry(src.module.clone()).or_default().insert(to);
                }
            }
        }
    }
    // Depth-first search for a back edge; report the circle it closes.
    let mut state: BTreeMap<Vec<String>, u8> = BTreeMap::new();
    let mut stack: Vec<Vec<String>> = Vec::new();
    let mut circles = Vec::new();
    fn visit(
        n: &Vec<String>,
        edges: &BTreeMap<Vec<String>, BTreeSet<Vec<String>>>,
        state: &mut BTreeMap<Vec<String>, u8>,
        stack: &mut Vec<Vec<String>>,
        circles: &mut Vec<String>,
    ) {
        state.insert(n.clone(), 1);
        stack.push(n.clone());
        for m in edges.get(n).into_iter().flatten() {
            match state.get(m).copied().unwrap_or(0) {
                0 => visit(m, edges, state, stack, circles),
                1 => {
                    let at = stack.iter().position(|s| s == m).unwrap();
                    let names: Vec<String> =
                        stack[at..].iter().chain([m]).map(|s| if s.is_empty() { "lib".into() } else { s.join("::") }).collect();
                    circles.push(names.join(" -> "));
                }
                _ => {}
            }
        }
        stack.pop();
        state.insert(n.clone(), 2);
    }
    for n in sources.keys() {
        if state.get(n).copied().unwrap_or(0) == 0 {
            visit(n, &edges, &mut state, &mut stack, &mut circles);
        }
    }
    circles
}

/// The checker itself: a planted upward import and a planted circle are found.
#[test]
fn the_checker_sees_planted_violations() {
    let src = Source {
        module: vec!["mesh".into(), "post".into()],
        code: "use crate::engine::infer::{Engine, output::x};\nuse super::trimesh::TriMesh;\nfn f() { crate::math::cross(a, b); }\npub use self::inner::Item;\n".into(),
        test_code: String::new(),
        children: BTreeSet::new(),
    };
    let p = paths(&src, &src.code);
    let s: Vec<String> = p.iter().map(|p| p.join("::")).collect();
    assert_eq!(
        s,
        ["engine::infer::Engine", "engine::infer::output::x", "mesh::trimesh::TriMesh", "math::cross", "mesh::post::inner::Item"]
    );
    assert!(rank("engine").unwrap() > rank("mesh").unwrap());
    let (main, tests) = split_tests("fn a() {}\n#[cfg(test)]\nmod tests {\n    fn b() { if x { } }\n}\nfn c() {}\n");
    assert!(main.contains("fn a") && main.contains("fn c") && !main.contains("fn b"));
    assert!(tests.contains("fn b"));
    assert_eq!(strip("let x = \"crate::a\"; // crate::b\ncrate::c"), "let x = ; \ncrate::c\n");
    assert_eq!(strip("if c == '{' || c == '\\'' { x::<'a> }"), "if c ==  || c ==  { x::<'a> }\n");
}

/// A minimal engine build (`recon-core` without default features) brings no CLI, download,
/// physics or progress-bar dependency: those are optional features of `recon-core` or
/// dependencies of the crates above it.
#[test]
fn the_engine_crate_keeps_optional_weight_optional() {
    let manifest = std::fs::read_to_string(workspace().join("crates/core/Cargo.toml")).unwrap();
    let deps: Vec<&str> = manifest
        .split("[dependencies]")
        .nth(1)
        .unwrap()
        .split("\n[")
        .next()
        .unwrap()
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .collect();
    let dep = |name: &str| deps.iter().find(|l| l.split(['=', '.', ' ']).next() == Some(name)).copied();
    for heavy in ["rapier3d", "anyhow"] {
        assert!(dep(heavy).is_none(), "recon-core must not depend on {heavy}");
    }
    // indicatif: the download's progress bar, part of the `hub` feature.
    for optional in ["hf-hub", "ureq", "clap", "indicatif"] {
        let line = dep(optional).unwrap_or_else(|| panic!("recon-core lists {optional}"));
        assert!(line.contains("optional = true"), "{optional} must be optional in recon-core: {line}");
    }
    assert!(manifest.contains("default = [\"hub\"]"), "the hub download is the one default feature");
}
