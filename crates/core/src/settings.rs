//! Process settings from the environment, read once at the program's edge.
//!
//! [`Settings::from_env`] is the one place recon reads environment variables.
//! A program (the `recon` CLI, the Python module) calls it once at start and
//! [`Settings::apply`]s the result: that sets the kernels' instruction-set cap
//! and bf16 choice and makes the values the library asks for
//! ([`current`]). Library code never reads the environment itself; a program
//! that never applies settings gets [`Settings::NONE`] (no overrides: the
//! CPU's best kernels, the machine's memory, the temporary folder as cache).
//!
//! | Variable | Meaning | Default | Read where |
//! |---|---|---|---|
//! | `RECON_ISA` | Caps the kernels' instruction set: `portable`, `avx2`, `avx512` or `avx512bf16` | the best the CPU runs | `Settings::from_env` → `recon_kernels::isa::set_cap` |
//! | `RECON_BF16_DOT` | `on`/`off`: whether bf16 weights use `vdpbf16ps` (AVX512-BF16) instead of f32 FMA | measured once per process | `Settings::from_env` → `recon_kernels::peak::set_bf16_dot` |
//! | `RECON_MEMORY_LIMIT_MB` | Caps the memory budget (MiB) that model loads are checked against | the machine's `MemTotal` | `Settings::from_env` → `util::limits::memory_budget_bytes` |
//! | `RECON_CACHE` | Folder the embedded recgen-nano is unpacked to | `$XDG_CACHE_HOME/recon` | `Settings::from_env` → `engine::source` |
//! | `XDG_CACHE_HOME` | Cache base when `RECON_CACHE` is unset (`<it>/recon`) | `$HOME/.cache` | `Settings::from_env` |
//! | `HOME` | Home folder: `~/.cache/recon`, `~/.cache/huggingface/hub` | none (then: the temporary folder for recon's cache, `./.cache/huggingface/hub`) | `Settings::from_env` |
//! | `HF_HOME` | Hugging Face root: the hub cache is `$HF_HOME/hub`, the login token `$HF_HOME/token` | `$HOME/.cache/huggingface` | `Settings::from_env` → `weights::hf_cache` |
//! | `HF_HUB_CACHE` | The Hugging Face hub cache itself (`models--ORG--NAME/…`); wins over `HF_HOME` | `$HF_HOME/hub` | `Settings::from_env` → `weights::hf_cache` |
//! | `HF_HUB_OFFLINE` | `1`/`true`/`yes`/`on`: never use the network; checkpoints come from the cache only | off | `Settings::from_env` → `weights::fetch` |
//! | `HF_TOKEN` | Hugging Face access token for downloads (gated or private repos) | the login token file `$HF_HOME/token` | `Settings::from_env` → `weights::fetch` |
//! | `HF_ENDPOINT` | Hugging Face hub address for downloads | `https://huggingface.co` | `Settings::from_env` → `weights::fetch` |
//! | `TORCH_HOME` | PyTorch's cache: a torch.hub checkpoint (DINOv2) already under `$TORCH_HOME/hub/checkpoints` is used instead of downloading it | `$XDG_CACHE_HOME/torch`, else `$HOME/.cache/torch` | `Settings::from_env` → `weights::manifest`, `weights::fetch` |
//! | `RECON_API_TOKEN` | Bearer token `recon serve` requires on every route but `/health` (`--token-file` wins) | none: no token (then `recon serve` binds to loopback only) | `Settings::from_env` → `recon-serve`'s configuration |
//! | `RECON_MALLOC` | `system` turns off the large-buffer cache of the global allocator | cache on | the allocator itself (`util::buffer_cache`), at its first large allocation: it can run before `main` |
//!
//! An empty value counts as unset. A value that does not parse is an error
//! naming the variable ([`SettingsError`]), not silently ignored.

use std::ffi::OsString;
use std::path::PathBuf;
use std::sync::RwLock;

use recon_kernels::isa::Isa;

/// The variables [`Settings::from_env`] reads, with their meaning (the table
/// of the module docs, for `--help` texts and checks).
pub const VARIABLES: &[(&str, &str)] = &[
    ("RECON_ISA", "caps the kernels' instruction set: portable, avx2, avx512 or avx512bf16"),
    ("RECON_BF16_DOT", "on/off: whether bf16 weights use vdpbf16ps instead of f32 FMA (default: measured)"),
    ("RECON_MEMORY_LIMIT_MB", "caps the memory budget, in MiB (default: the machine's MemTotal)"),
    ("RECON_CACHE", "folder the embedded model is unpacked to (default: $XDG_CACHE_HOME/recon)"),
    ("XDG_CACHE_HOME", "cache base when RECON_CACHE is unset (default: $HOME/.cache)"),
    ("HOME", "home folder, for ~/.cache/recon and ~/.cache/huggingface/hub"),
    ("HF_HOME", "Hugging Face root: hub cache $HF_HOME/hub, login token $HF_HOME/token (default: $HOME/.cache/huggingface)"),
    ("HF_HUB_CACHE", "the Hugging Face hub cache itself (default: $HF_HOME/hub)"),
    ("HF_HUB_OFFLINE", "1/true/yes/on: no network; checkpoints from the Hugging Face cache only (default: off)"),
    ("HF_TOKEN", "Hugging Face access token for downloads (default: the token file $HF_HOME/token)"),
    ("HF_ENDPOINT", "Hugging Face hub address for downloads (default: https://huggingface.co)"),
    ("TORCH_HOME", "PyTorch cache: torch.hub checkpoints under $TORCH_HOME/hub/checkpoints are used (default: $XDG_CACHE_HOME/torch)"),
    ("RECON_API_TOKEN", "bearer token recon serve requires on every route but /health (--token-file wins)"),
];

/// A variable whose value does not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("environment variable {name}={value:?}: {expected}")]
pub struct SettingsError {
    /// The variable's name.
    pub name: &'static str,
    /// Its value as set.
    pub value: String,
    /// What the value should be.
    pub expected: &'static str,
}

/// Everything recon takes from the environment (see the module docs).
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Settings {
    /// `RECON_ISA`: the most specialised kernel family used.
    pub isa_cap: Option<Isa>,
    /// `RECON_BF16_DOT`: forces (`Some(true)`) or forbids `vdpbf16ps`; `None` measures.
    pub bf16_dot: Option<bool>,
    /// `RECON_MEMORY_LIMIT_MB`, in bytes.
    pub memory_limit: Option<u64>,
    /// Where the embedded model is unpacked: `RECON_CACHE`, else
    /// `XDG_CACHE_HOME/recon`, else `HOME/.cache/recon`.
    pub cache_dir: Option<PathBuf>,
    /// The Hugging Face hub cache: `HF_HUB_CACHE`, else `HF_HOME/hub`, else `HOME/.cache/huggingface/hub`.
    pub hf_cache: Option<PathBuf>,
    /// The Hugging Face root (`HF_HOME`, else `HOME/.cache/huggingface`): where the login token file is.
    pub hf_home: Option<PathBuf>,
    /// `HF_HUB_OFFLINE`: checkpoints come from the cache only, nothing is downloaded.
    pub hf_offline: bool,
    /// `HF_TOKEN`: the Hugging Face access token (else the login token file under `hf_home`).
    pub hf_token: Option<Secret>,
    /// `HF_ENDPOINT`: the hub's address for downloads (else `https://huggingface.co`).
    pub hf_endpoint: Option<String>,
    /// torch.hub's checkpoint folder: `TORCH_HOME/hub/checkpoints`, else
    /// `XDG_CACHE_HOME/torch/hub/checkpoints`, else `HOME/.cache/torch/hub/checkpoints`.
    pub torch_checkpoints: Option<PathBuf>,
    /// `RECON_API_TOKEN`: the bearer token `recon serve` requires (`--token-file` wins).
    pub api_token: Option<Secret>,
}

/// A secret value (an API token): compared and used, never shown by `Debug`.
#[derive(Clone, PartialEq, Eq)]
pub struct Secret(String);

impl Secret {
    /// Wraps a secret.
    pub fn new(value: impl Into<String>) -> Self {
        Secret(value.into())
    }

    /// The secret itself (to compare or send, never to log).
    pub fn expose(&self) -> &str {
        &self.0
    }
}

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Secret(***)")
    }
}

static APPLIED: RwLock<Settings> = RwLock::new(Settings::NONE);

/// The settings last [applied](Settings::apply) in this process
/// ([`Settings::NONE`] before any).
pub fn current() -> Settings {
    APPLIED.read().unwrap_or_else(|e| e.into_inner()).clone()
}

impl Settings {
    /// No overrides.
    pub const NONE: Settings = Settings {
        isa_cap: None,
        bf16_dot: None,
        memory_limit: None,
        cache_dir: None,
        hf_cache: None,
        hf_home: None,
        hf_offline: false,
        hf_token: None,
        hf_endpoint: None,
        torch_checkpoints: None,
        api_token: None,
    };

    /// Read the process environment: the one place recon does.
    pub fn from_env() -> Result<Self, SettingsError> {
        Self::from_lookup(|name| std::env::var_os(name))
    }

    /// Parse the variables from `lookup` (name → value; the process
    /// environment in [`Settings::from_env`], a map in tests).
    pub fn from_lookup(lookup: impl Fn(&str) -> Option<OsString>) -> Result<Self, SettingsError> {
        // Path variables keep non-UTF-8 values; an empty one counts as unset.
        let path = |name: &str| lookup(name).filter(|v| !v.is_empty()).map(PathBuf::from);
        let text = |name: &'static str| -> Result<Option<String>, SettingsError> {
            match lookup(name) {
                None => Ok(None),
                Some(v) => match v.into_string() {
                    Ok(s) if s.trim().is_empty() => Ok(None),
                    Ok(s) => Ok(Some(s)),
                    Err(v) => Err(SettingsError { name, value: v.to_string_lossy().into_owned(), expected: "not valid UTF-8" }),
                },
            }
        };
        let bad = |name: &'static str, value: &str, expected: &'static str| SettingsError { name, value: value.to_string(), expected };

        let isa_cap = match text("RECON_ISA")? {
            None => None,
            Some(v) => Some(Isa::parse(&v).ok_or_else(|| bad("RECON_ISA", &v, "expected portable, avx2, avx512 or avx512bf16"))?),
        };
        let bf16_dot = match text("RECON_BF16_DOT")? {
            None => None,
            Some(v) => match v.trim() {
                "on" => Some(true),
                "off" => Some(false),
                _ => return Err(bad("RECON_BF16_DOT", &v, "expected on or off")),
            },
        };
        let memory_limit = match text("RECON_MEMORY_LIMIT_MB")? {
            None => None,
            Some(v) => {
                let mb = v.trim().parse::<u64>().map_err(|_| bad("RECON_MEMORY_LIMIT_MB", &v, "expected a whole number of MiB"))?;
                Some(mb.checked_mul(1 << 20).ok_or_else(|| bad("RECON_MEMORY_LIMIT_MB", &v, "too large"))?)
            }
        };
        let home = path("HOME");
        // torch.hub's rule: TORCH_HOME, else XDG_CACHE_HOME/torch, else ~/.cache/torch.
        let torch_checkpoints = path("TORCH_HOME")
            .or_else(|| path("XDG_CACHE_HOME").map(|p| p.join("torch")))
            .or_else(|| home.as_ref().map(|p| p.join(".cache/torch")))
            .map(|t| t.join("hub").join("checkpoints"));
        let cache_dir = path("RECON_CACHE")
            .or_else(|| path("XDG_CACHE_HOME").map(|p| p.join("recon")))
            .or_else(|| home.as_ref().map(|p| p.join(".cache/recon")));
        // huggingface_hub's rules: HF_HUB_CACHE, else HF_HOME/hub, else the home folder's.
        let hf_home = path("HF_HOME").or_else(|| home.map(|h| h.join(".cache").join("huggingface")));
        let hf_cache = path("HF_HUB_CACHE").or_else(|| hf_home.as_ref().map(|h| h.join("hub")));
        let hf_offline = match text("HF_HUB_OFFLINE")? {
            None => false,
            Some(v) => match v.trim().to_ascii_lowercase().as_str() {
                "1" | "true" | "yes" | "on" => true,
                "0" | "false" | "no" | "off" => false,
                _ => return Err(bad("HF_HUB_OFFLINE", &v, "expected 1, true, yes, on or 0, false, no, off")),
            },
        };
        let hf_token = text("HF_TOKEN")?.map(|t| Secret::new(t.trim()));
        let hf_endpoint = text("HF_ENDPOINT")?.map(|e| e.trim().trim_end_matches('/').to_string());
        // Surrounding whitespace (a trailing newline from `$(cat file)`) is not part of a token.
        let api_token = text("RECON_API_TOKEN")?.map(|t| Secret::new(t.trim()));
        Ok(Settings {
            isa_cap,
            bf16_dot,
            memory_limit,
            cache_dir,
            hf_cache,
            hf_home,
            hf_offline,
            hf_token,
            hf_endpoint,
            torch_checkpoints,
            api_token,
        })
    }

    /// Make these the process's settings: the kernels' instruction-set cap
    /// and bf16 choice, and what [`current`] returns. Call once at start,
    /// before any model is built (the kernels fix their bf16 choice at the
    /// first bf16 build).
    pub fn apply(&self) {
        recon_kernels::isa::set_cap(self.isa_cap);
        recon_kernels::peak::set_bf16_dot(self.bf16_dot);
        *APPLIED.write().unwrap_or_else(|e| e.into_inner()) = self.clone();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    fn parse(vars: &[(&str, &str)]) -> Result<Settings, SettingsError> {
        let map: HashMap<String, OsString> = vars.iter().map(|(k, v)| (k.to_string(), OsString::from(v))).collect();
        Settings::from_lookup(|k| map.get(k).cloned())
    }

    #[test]
    fn parses_every_variable() {
        assert_eq!(parse(&[]).unwrap(), Settings::NONE);
        let s = parse(&[
            ("RECON_ISA", " AVX512 "),
            ("RECON_BF16_DOT", "off"),
            ("RECON_MEMORY_LIMIT_MB", "100"),
            ("XDG_CACHE_HOME", "/x"),
            ("HOME", "/h"),
        ])
        .unwrap();
        assert_eq!(s.isa_cap, Some(Isa::Avx512));
        assert_eq!(s.bf16_dot, Some(false));
        assert_eq!(s.memory_limit, Some(100 << 20));
        assert_eq!(s.cache_dir, Some(PathBuf::from("/x/recon")));
        assert_eq!(s.hf_cache, Some(PathBuf::from("/h/.cache/huggingface/hub")));
        assert_eq!(s.torch_checkpoints, Some(PathBuf::from("/x/torch/hub/checkpoints")));
        assert_eq!(parse(&[("TORCH_HOME", "/t"), ("HOME", "/h")]).unwrap().torch_checkpoints, Some(PathBuf::from("/t/hub/checkpoints")));
        let s = parse(&[("RECON_CACHE", "/c"), ("XDG_CACHE_HOME", "/x"), ("HF_HOME", "/hf"), ("HOME", "/h")]).unwrap();
        assert_eq!(s.cache_dir, Some(PathBuf::from("/c")));
        assert_eq!(s.hf_cache, Some(PathBuf::from("/hf/hub")));
        assert_eq!(s.hf_home, Some(PathBuf::from("/hf")));
        assert!(!s.hf_offline);
        // HF_HUB_CACHE wins over HF_HOME for the cache; the token file stays under HF_HOME.
        let s = parse(&[("HF_HUB_CACHE", "/hc"), ("HF_HOME", "/hf"), ("HF_HUB_OFFLINE", "1"), ("HF_TOKEN", "hf_x\n")]).unwrap();
        assert_eq!((s.hf_cache, s.hf_home), (Some(PathBuf::from("/hc")), Some(PathBuf::from("/hf"))));
        assert!(s.hf_offline);
        assert_eq!(s.hf_token.as_ref().map(Secret::expose), Some("hf_x"));
        assert!(!parse(&[("HF_HUB_OFFLINE", "False")]).unwrap().hf_offline);
        assert_eq!(parse(&[("HF_ENDPOINT", "http://h:1/")]).unwrap().hf_endpoint.as_deref(), Some("http://h:1"));
        let s = parse(&[("RECON_API_TOKEN", " tok3n\n")]).unwrap();
        assert_eq!(s.api_token.as_ref().map(Secret::expose), Some("tok3n"));
        assert_eq!(format!("{:?}", s.api_token), "Some(Secret(***))");
        // Empty counts as unset.
        let s = parse(&[("RECON_ISA", ""), ("RECON_CACHE", ""), ("HOME", "/h")]).unwrap();
        assert_eq!(s.isa_cap, None);
        assert_eq!(s.cache_dir, Some(PathBuf::from("/h/.cache/recon")));
    }

    #[test]
    fn rejects_a_bad_value_naming_the_variable() {
        let e = parse(&[("RECON_MEMORY_LIMIT_MB", "lots")]).unwrap_err();
        assert_eq!(e.name, "RECON_MEMORY_LIMIT_MB");
        let msg = e.to_string();
        assert!(msg.contains("RECON_MEMORY_LIMIT_MB") && msg.contains("lots") && msg.contains("whole number"), "{msg}");
        let e = parse(&[("RECON_ISA", "sse2")]).unwrap_err();
        assert!(e.to_string().contains("RECON_ISA") && e.to_string().contains("avx512bf16"), "{e}");
        let e = parse(&[("HF_HUB_OFFLINE", "maybe")]).unwrap_err();
        assert!(e.to_string().contains("HF_HUB_OFFLINE") && e.to_string().contains("maybe"), "{e}");
        let e = parse(&[("RECON_BF16_DOT", "yes")]).unwrap_err();
        assert!(e.to_string().contains("RECON_BF16_DOT") && e.to_string().contains("on or off"), "{e}");
    }

    #[test]
    fn every_variable_read_is_documented() {
        let names: Vec<&str> = VARIABLES.iter().map(|(n, _)| *n).collect();
        let seen = std::cell::RefCell::new(Vec::new());
        Settings::from_lookup(|k| {
            seen.borrow_mut().push(k.to_string());
            None
        })
        .unwrap();
        for k in seen.borrow().iter() {
            assert!(names.contains(&k.as_str()), "{k} is read but not in VARIABLES");
        }
        for n in &names {
            assert!(seen.borrow().iter().any(|k| k == n), "{n} is listed but never read");
            assert!(include_str!("settings.rs").contains(&format!("| `{n}` |")), "{n} missing from the module docs' table");
        }
    }
}
