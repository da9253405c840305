//! The per-frame options are defined once (`recon::engine::InferOptions`), and so are
//! `recon scene`'s (`recon::sim::SceneOptions`): the CLI's flags (`recon infer --help`,
//! `recon eval --help`, `recon scene --help`), Python's keywords (the type stub
//! python/recon_rgbd/__init__.pyi) and the docs' table (docs/options.md) must agree with them on
//! every name and default. `RECON_BLESS=1 cargo test --test options` rewrites the table.
mod common;

use common::repo;
use recon::engine::InferOptions;
use recon::sim::SceneOptions;
use serde_json::Value;

/// `(name, default)` of every option, in `--help` order.
fn defaults() -> Vec<(&'static str, Value)> {
    let v = serde_json::to_value(InferOptions::default()).unwrap();
    let m = v.as_object().unwrap();
    assert_eq!(m.len(), InferOptions::NAMES.len(), "InferOptions::NAMES misses a field: {:?}", m.keys());
    InferOptions::NAMES.iter().map(|n| (*n, m.get(*n).unwrap_or_else(|| panic!("no field `{n}`")).clone())).collect()
}

/// `(name, default)` of every `recon scene` option, in `--help` order.
fn scene_defaults() -> Vec<(&'static str, Value)> {
    let v = serde_json::to_value(SceneOptions::default()).unwrap();
    let m = v.as_object().unwrap();
    assert_eq!(m.len(), SceneOptions::NAMES.len(), "SceneOptions::NAMES misses a field: {:?}", m.keys());
    SceneOptions::NAMES.iter().map(|n| (*n, m[*n].clone())).collect()
}

#[test]
fn scene_names_are_the_fields_and_the_flags() {
    let cmd = <SceneOptions as clap::Args>::augment_args(clap::Command::new("scene"));
    let ids: Vec<String> = cmd.get_arguments().map(|a| a.get_id().to_string()).collect();
    assert_eq!(ids, SceneOptions::NAMES);
}

fn flag(name: &str) -> String {
    format!("--{}", name.replace('_', "-"))
}

/// The default as clap prints it (`[default: …]`), `None` without one; a pair of numbers
/// (`clamp_range`) as `LOW,HIGH`.
fn cli_default(v: &Value) -> Option<String> {
    match v {
        Value::Null => None,
        Value::String(s) => Some(s.clone()),
        Value::Array(a) => {
            Some(a.iter().map(|x| x.as_f64().map_or_else(|| x.to_string(), |f| f.to_string())).collect::<Vec<_>>().join(","))
        }
        v => Some(v.to_string()),
    }
}

/// The options clap derives from the struct: their ids in order.
fn clap_args() -> clap::Command {
    <InferOptions as clap::Args>::augment_args(clap::Command::new("options"))
}

#[test]
fn names_are_the_fields_and_the_flags() {
    let ids: Vec<String> = clap_args().get_arguments().map(|a| a.get_id().to_string()).collect();
    let names: Vec<&str> = defaults().iter().map(|(n, _)| *n).collect();
    assert_eq!(ids, names);
    for a in clap_args().get_arguments() {
        assert_eq!(a.get_long().map(|l| format!("--{l}")), Some(flag(a.get_id().as_str())));
    }
}

/// The block of `--help` describing `flag` (its line up to the next flag's).
fn help_block<'a>(help: &'a str, flag: &str) -> Option<&'a str> {
    let start = help.find(&format!("      {flag} <")).or_else(|| help.find(&format!("      {flag}\n")))?;
    let rest = &help[start..];
    let end = rest[1..].find("\n      -").or_else(|| rest[1..].find("\n  -")).map_or(rest.len(), |e| e + 1);
    Some(&rest[..end])
}

/// Whether clap's `[default: …]` text shows the library's default: equal text, or equal
/// numbers (clap prints `10` for 10.0, and an f32's JSON form is its f64 widening).
fn same_default(shown: Option<&str>, library: Option<&str>) -> bool {
    match (shown, library) {
        (Some(a), Some(b)) => a == b || matches!((a.parse::<f64>(), b.parse::<f64>()), (Ok(x), Ok(y)) if same_number(x, y)),
        (a, b) => a == b,
    }
}

/// Equal as f32 (the options hold f32 and f64 values).
fn same_number(x: f64, y: f64) -> bool {
    (x - y).abs() <= 1e-6 * x.abs().max(y.abs())
}

/// `recon <cmd> --help` shows every option of `defaults` under its flag with its default.
fn check_cli(cmd: &[&str], defaults: &[(&'static str, Value)]) {
    let mut args = cmd.to_vec();
    args.push("--help");
    let out = common::recon(&args);
    assert!(out.status.success(), "recon {cmd:?} --help");
    let help = String::from_utf8(out.stdout).unwrap();
    for (name, v) in defaults {
        let f = flag(name);
        let block = help_block(&help, &f).unwrap_or_else(|| panic!("recon {cmd:?} --help has no {f}"));
        let shown = block.find("[default: ").map(|i| {
            let s = &block[i + "[default: ".len()..];
            s[..s.find(']').unwrap()].to_string()
        });
        assert!(same_default(shown.as_deref(), cli_default(v).as_deref()), "recon {cmd:?} {f}: default {shown:?}, the library's {v}");
    }
}

#[test]
fn cli_flags_have_the_library_names_and_defaults() {
    for cmd in ["infer", "eval"] {
        check_cli(&[cmd], &defaults());
    }
    check_cli(&["scene"], &scene_defaults());
}

/// A Python literal of the stub as JSON (`None`, `"x"`, `200_000`, `0.02`, `True`, `(-2.0, 3.0)`).
fn py_literal(s: &str) -> Value {
    match s {
        s if s.len() >= 2 && (s.starts_with('(') || s.starts_with('[')) => {
            Value::Array(s[1..s.len() - 1].split(',').map(str::trim).filter(|x| !x.is_empty()).map(py_literal).collect())
        }
        "None" => Value::Null,
        "True" => Value::Bool(true),
        "False" => Value::Bool(false),
        s if s.starts_with('"') => Value::String(s.trim_matches('"').to_string()),
        s => {
            let n = s.replace('_', "");
            n.parse::<u64>().map(Value::from).unwrap_or_else(|_| Value::from(n.parse::<f64>().unwrap()))
        }
    }
}

/// The stub's `func` signature has every option of `defaults` as a keyword with its default.
fn check_stub(func: &str, defaults: &[(&'static str, Value)]) {
    let stub = std::fs::read_to_string(repo().join("python/recon_rgbd/__init__.pyi")).unwrap();
    let start = stub.find(func).unwrap_or_else(|| panic!("stub: no {func}"));
    let sig = &stub[start..start + stub[start..].find(") ->").unwrap()];
    for (name, v) in defaults {
        let line = sig
            .lines()
            .map(str::trim)
            .find(|l| l.starts_with(&format!("{name}:")))
            .unwrap_or_else(|| panic!("stub {func}…): no keyword `{name}`"));
        let default = line.split(" = ").nth(1).unwrap_or_else(|| panic!("stub {func}…): `{name}` has no default"));
        let got = py_literal(default.trim_end_matches(','));
        let same = match (&got, v) {
            (Value::Number(a), Value::Number(b)) => same_number(a.as_f64().unwrap(), b.as_f64().unwrap()),
            (a, b) => a == b,
        };
        assert!(same, "stub {func}…): `{name}` defaults to {got}, the library to {v}");
    }
}

#[test]
fn python_stub_has_the_library_names_and_defaults() {
    for func in ["def reconstruct(", "def reconstruct_files(", "def eval("] {
        check_stub(func, &defaults());
    }
    check_stub("def scene(", &scene_defaults());
}

/// One markdown table row per option of `cmd` (help text from the struct's docs).
fn table_rows(cmd: clap::Command, defaults: Vec<(&'static str, Value)>, null: &str) -> String {
    let mut s = String::from("| Option | Flag | Default | Meaning |\n|---|---|---|---|\n");
    for ((name, v), arg) in defaults.into_iter().zip(cmd.get_arguments()) {
        // The default as `--help` shows it (an f32's JSON form is its f64 widening).
        let shown: Vec<String> = arg.get_default_values().iter().map(|d| d.to_string_lossy().into_owned()).collect();
        let default = match (&v, shown.first()) {
            (Value::Null, _) => null.to_string(),
            (_, Some(d)) => format!("`{d}`"),
            (v, None) => format!("`{v}`"),
        };
        let mut help = arg.get_help().map(|h| h.to_string()).unwrap_or_default();
        let values: Vec<String> = arg.get_possible_values().iter().map(|p| format!("`{}`", p.get_name())).collect();
        if !values.is_empty() {
            help = format!("{help}; one of {}", values.join(", "));
        }
        s += &format!("| `{name}` | `{}` | {default} | {} |\n", flag(name), help.replace('|', "\\|").replace('\n', " "));
    }
    s
}

/// docs/options.md: the options tables, generated from the structs.
fn options_table() -> String {
    let mut s = String::from(
        "# Options\n\n\
         <!-- Generated by tests/options.rs from recon::engine::InferOptions and recon::sim::SceneOptions; \
         `RECON_BLESS=1 cargo test --test options` rewrites it. -->\n\n\
         ## Per-frame options\n\n\
         The options of `recon infer` and `recon eval --method recgen` (flags), of\n\
         `Engine.reconstruct`, `Engine.reconstruct_files` and `recon_rgbd.eval` (keywords; defaults:\n\
         `recon_rgbd.infer_defaults()`) and of JSON (keys): one name per setting, the flag's with `_`.\n\n",
    );
    s += &table_rows(clap_args(), defaults(), "(the model config's)");
    s += "\n## Scene options\n\n\
          The options of `recon scene` (flags) and `recon_rgbd.scene` (keywords): one name per setting,\n\
          the flag's with `_`. The inputs (`--input`, `--frame`, `--out`, `--variations`, …) are\n\
          listed by `recon scene --help`.\n\n";
    s += &table_rows(<SceneOptions as clap::Args>::augment_args(clap::Command::new("scene")), scene_defaults(), "none");
    s
}

#[test]
fn docs_table_is_current() {
    let path = repo().join("docs/options.md");
    let table = options_table();
    if std::env::var_os("RECON_BLESS").is_some() {
        std::fs::write(&path, &table).unwrap();
    }
    let on_disk = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(on_disk == table, "docs/options.md is stale: run `RECON_BLESS=1 cargo test --test options`\n{table}");
}
