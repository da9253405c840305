//! Weights manifests (`weights-manifest/*.json`, embedded in the binary):
//! which upstream files the engine uses, where they come from, which module
//! each belongs to, their SHA-256 where pinned, and the exact tensor names and
//! shapes a checkpoint must hold (generated from recon's own modules by
//! `recon weights manifest`, see [`Manifest::with_tensors_from`]).
//!
//! A model loads from a manifest through [`resolve_manifest`]: every file it
//! needs is looked up in the Hugging Face cache ([`crate::weights::hf_cache`]),
//! checked against its pin and tensor list, and the release's own config
//! files give the module args, latent normalisation, sampler settings and
//! pose statistics, as upstream `build_recgen.build` takes them.

use crate::model::config::RecGenConfig;
use crate::model::key::{ModuleKey, ModuleKind};
use crate::weights::hf_cache;
use crate::weights::record::TensorSpec;
use crate::{Error, Result};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Manifests shipped with the crate: (name, JSON text). crates/core/weights-manifest links to the
/// repository's weights-manifest/, so the packaged crate carries the files.
pub const EMBEDDED: &[(&str, &str)] = &[
    ("recgen", include_str!("../../weights-manifest/recgen.json")),
    ("trellis-image-large", include_str!("../../weights-manifest/trellis-image-large.json")),
    ("dinov2-vitl14-reg", include_str!("../../weights-manifest/dinov2-vitl14-reg.json")),
];

/// A weights manifest: the upstream files of one model release, where they come from and what they hold.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// The manifest's name (`recgen`); URL-sourced files are stored under it.
    pub name: String,
    /// `huggingface` (files of `repo` at `revision`) or `url` (each file has its own `url`).
    pub source: String,
    /// Hugging Face repo id (`owner/name`) of a `huggingface` manifest.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub repo: Option<String>,
    /// Repo revision the files are taken from (`main` when absent).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub revision: Option<String>,
    /// Licence of the files, as text.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub licence: Option<String>,
    /// Free-form remarks.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    /// Other manifests (embedded names, or paths relative to this file) whose
    /// files a model from this one also needs (RecGen: the DINOv2 image
    /// encoder): fetched with it and searched first for modules it lacks.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub requires: Vec<String>,
    /// The files.
    pub files: Vec<ManifestFile>,
}

/// One file of a [`Manifest`].
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct ManifestFile {
    /// Path in the repo (for `url` manifests: in the download folder).
    pub path: String,
    /// `safetensors`, `pt`, `json`, ...
    pub kind: String,
    /// Where to download it (`url` manifests).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub url: Option<String>,
    /// SHA-256 of the file (hex): checked by `recon weights verify`, `fetch` and every load.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sha256: Option<String>,
    /// Upstream class the weights belong to.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub module: Option<String>,
    /// Config file (in the same repo) with the module's constructor args.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub config: Option<String>,
    /// What the file is for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub role: Option<String>,
    /// Extra tensors are tolerated (upstream loads with `strict=False`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub allow_unexpected: bool,
    /// Wrapped state-dict key inside a `.pt` file, when known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pt_key: Option<String>,
    /// Not needed by recon: fetched only on request, and absence passes `verify`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub optional: bool,
    /// Why `tensors` is null, or how it was generated.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tensors_note: Option<String>,
    /// Expected tensors (null where the module is not in the crate).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tensors: Option<Vec<TensorSpec>>,
}

impl Manifest {
    /// Parse manifest JSON; errors name `file`.
    pub fn parse(text: &str, file: &str) -> Result<Self> {
        serde_json::from_str(text).map_err(|e| Error::config(file, "manifest", e.to_string()))
    }

    /// An embedded manifest by name, or a manifest JSON file by path.
    pub fn load(name_or_path: &str) -> Result<Self> {
        if let Some((n, text)) = EMBEDDED.iter().find(|(n, _)| *n == name_or_path) {
            return Self::parse(text, &format!("weights-manifest/{n}.json"));
        }
        let p = Path::new(name_or_path);
        if p.exists() {
            let text = std::fs::read_to_string(p).map_err(|e| Error::io(p, e))?;
            return Self::parse(&text, name_or_path);
        }
        let known: Vec<&str> = EMBEDDED.iter().map(|(n, _)| *n).collect();
        Err(Error::input(name_or_path, format!("no such manifest (known: {known:?}, or a path to a manifest .json)")))
    }

    /// Every embedded manifest, parsed.
    pub fn all() -> Result<Vec<Self>> {
        EMBEDDED.iter().map(|(n, t)| Self::parse(t, &format!("weights-manifest/{n}.json"))).collect()
    }

    /// The manifests `requires` names, loaded; `from` is where this manifest
    /// was loaded from (a relative path in `requires` is relative to its folder).
    pub fn required(&self, from: &str) -> Result<Vec<Self>> {
        self.requires
            .iter()
            .map(|r| {
                let embedded = EMBEDDED.iter().any(|(n, _)| n == r);
                let rel = Path::new(from).parent().filter(|_| !embedded && Path::new(r).is_relative() && Path::new(from).is_file());
                match rel {
                    Some(dir) => Self::load(&dir.join(r).display().to_string()),
                    None => Self::load(r),
                }
            })
            .collect()
    }

    /// The revision the files are taken from (`main` when none is pinned).
    pub fn revision(&self) -> &str {
        self.revision.as_deref().unwrap_or("main")
    }

    /// A manifest for `hf:ORG/NAME[@rev]`: the embedded manifest of that repo
    /// (its pins kept only at its own revision), else the RecGen layout read
    /// from that repo (a mirror or fine-tune: no pins, tensor lists kept).
    pub fn for_hf_repo(repo: &str, revision: Option<&str>) -> Result<Self> {
        let known = Self::all()?.into_iter().find(|m| m.repo.as_deref().is_some_and(|r| r.eq_ignore_ascii_case(repo)));
        let mut m = match known {
            Some(m) => m,
            None => {
                let mut m = Self::load("recgen")?;
                m.name = format!("hf:{repo}");
                m.notes.push(format!("RecGen's file layout read from {repo}: no SHA-256 pins"));
                for f in &mut m.files {
                    f.sha256 = None;
                }
                m
            }
        };
        if m.name.starts_with("hf:") {
            m.repo = Some(repo.to_string());
        }
        if let Some(rev) = revision {
            if Some(rev) != m.revision.as_deref() {
                for f in &mut m.files {
                    f.sha256 = None;
                }
                m.revision = Some(rev.to_string());
            }
        }
        Ok(m)
    }

    /// Where the files live under `dir`: `dir` itself, or, when `dir` is a
    /// Hugging Face cache (`…/hub`), the snapshot of this repo/revision
    /// ([`hf_cache::snapshot`]: the pinned commit, a branch through `refs/`,
    /// else `refs/main`), or `recon-url/<name>` for URL-sourced files, where
    /// `fetch` puts them.
    pub fn resolve_dir(&self, dir: &Path) -> PathBuf {
        let url_dir = dir.join("recon-url").join(&self.name);
        if self.source == "url" && url_dir.is_dir() {
            return url_dir;
        }
        if let Some(repo) = &self.repo {
            if let Some(s) = hf_cache::snapshot(dir, repo, self.revision()) {
                return s.dir;
            }
        }
        dir.to_path_buf()
    }

    /// Where a file of this manifest is expected in `cache` (whether or not
    /// it is there). A URL file `recon weights fetch` has not put there is
    /// taken from torch.hub's checkpoint folder when it holds it (a machine
    /// that ran upstream has DINOv2 there).
    pub fn expected_path(&self, cache: &Path, f: &ManifestFile) -> PathBuf {
        match (&self.repo, self.source.as_str()) {
            (_, "url") => {
                let ours = cache.join("recon-url").join(&self.name).join(&f.path);
                let torch =
                    crate::settings::current().torch_checkpoints.map(|d| d.join(&f.path)).filter(|p| !ours.is_file() && p.is_file());
                torch.unwrap_or(ours)
            }
            (Some(repo), _) => match hf_cache::snapshot(cache, repo, self.revision()) {
                Some(s) => s.dir.join(&f.path),
                None => hf_cache::repo_folder(cache, repo).join("snapshots").join(self.revision()).join(&f.path),
            },
            (None, _) => cache.join(&f.path),
        }
    }

    /// Where this manifest's files come from, in words (`repo@revision` or `url`).
    fn origin(&self) -> String {
        match &self.repo {
            Some(r) => format!("{r}@{}", self.revision()),
            None => format!("{} (by URL)", self.name),
        }
    }

    /// This manifest with the tensor list of every weights file whose module
    /// class is one of `arch`'s (equal up to TRELLIS's `Elastic` prefix; any
    /// DINOv2 name for the image encoder), derived from recon's module
    /// builders at `arch`'s sizes: `recon weights manifest NAME --config ARCH`.
    /// Other files keep what they had.
    pub fn with_tensors_from(&self, arch: &RecGenConfig, arch_label: &str) -> Result<Self> {
        let base = |n: &str| n.strip_prefix("Elastic").unwrap_or(n).to_string();
        let mut m = self.clone();
        for f in m.files.iter_mut().filter(|f| is_weights_file(f)) {
            let Some(module) = f.module.clone() else { continue };
            let dino = ModuleKind::of(&module) == Some(ModuleKind::Dinov2);
            let found =
                arch.modules().into_iter().find(|(k, s)| base(&s.name) == base(&module) || (dino && k.kind() == ModuleKind::Dinov2));
            let Some((key, spec)) = found else { continue };
            let label = format!("{arch_label}: {key}");
            f.tensors = Some(crate::weights::registry::expected_tensors(&arch.module_args(key)?, &label)?);
            f.tensors_note = Some(format!(
                "generated by `recon weights manifest {} --config {arch_label}`: the parameters recon's `{key}` module ({}) requests at these sizes, the upstream state-dict names",
                self.name, spec.name
            ));
        }
        Ok(m)
    }

    /// This manifest with the SHA-256 of every file present under `dir` (a
    /// folder, or a Hugging Face cache: then the revision becomes the
    /// snapshot's commit), and the paths of the files not there.
    pub fn with_pins_from(&self, dir: &Path) -> Result<(Self, Vec<String>)> {
        let mut m = self.clone();
        if let Some(s) = m.repo.as_deref().and_then(|r| hf_cache::snapshot(dir, r, self.revision())) {
            m.revision = Some(s.commit);
        }
        let root = self.resolve_dir(dir);
        let mut absent = Vec::new();
        for f in &mut m.files {
            let p = root.join(&f.path);
            if p.is_file() {
                f.sha256 = Some(hf_cache::sha256_file(&p)?);
            } else {
                absent.push(f.path.clone());
            }
        }
        Ok((m, absent))
    }

    /// The manifest as JSON: one line per file, one line per tensor (the
    /// layout of `weights-manifest/*.json`, diff-friendly).
    pub fn to_pretty_json(&self) -> Result<String> {
        let j = |v: &dyn erased::Ser| v.json().map_err(|e| Error::msg(format!("manifest `{}`: {e}", self.name)));
        let mut fields: Vec<(&str, String)> = vec![("name", j(&self.name)?), ("source", j(&self.source)?)];
        for (k, v) in [("repo", &self.repo), ("revision", &self.revision), ("licence", &self.licence)] {
            if let Some(v) = v {
                fields.push((k, j(v)?));
            }
        }
        for (k, list) in [("notes", &self.notes), ("requires", &self.requires)] {
            if !list.is_empty() {
                let rows = list.iter().map(|n| j(n)).collect::<Result<Vec<_>>>()?;
                fields.push((k, format!("[\n    {}\n  ]", rows.join(",\n    "))));
            }
        }
        let mut files = Vec::new();
        for f in &self.files {
            let mut head = f.clone();
            let tensors = head.tensors.take();
            let mut line = j(&head)?;
            if let Some(ts) = tensors {
                line.pop();
                let rows = ts.iter().map(|t| j(t)).collect::<Result<Vec<_>>>()?;
                line.push_str(&format!(",\"tensors\":[\n      {}\n    ]}}", rows.join(",\n      ")));
            }
            files.push(line);
        }
        fields.push(("files", format!("[\n    {}\n  ]", files.join(",\n    "))));
        let body: Vec<String> = fields.into_iter().map(|(k, v)| format!("  \"{k}\": {v}")).collect();
        Ok(format!("{{\n{}\n}}\n", body.join(",\n")))
    }
}

/// Compact JSON of any serialisable value behind one `dyn` type.
mod erased {
    pub trait Ser {
        fn json(&self) -> serde_json::Result<String>;
    }
    impl<T: serde::Serialize> Ser for T {
        fn json(&self) -> serde_json::Result<String> {
            serde_json::to_string(self)
        }
    }
}

/// Checkpoint kinds that hold weights (not configs).
fn is_weights_file(f: &ManifestFile) -> bool {
    matches!(f.kind.as_str(), "safetensors" | "pt" | "pth")
}

/// One file a model load took from a manifest, and what was checked.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ReadFile {
    /// The manifest listing it.
    pub manifest: String,
    /// Its path in the manifest (in the repo).
    pub path: String,
    /// Where it was read.
    pub local: PathBuf,
    /// The pinned SHA-256 the file matched (`None`: the manifest pins none).
    pub sha256: Option<String>,
    /// Tensors checked against the manifest's list (`None`: no list, or not a checkpoint).
    pub tensors: Option<usize>,
    /// What it gave the model: a module key, or the file's role.
    pub used_for: String,
}

/// Downloads files of a manifest into a cache ([`resolve_manifest`]'s `download`; the
/// engine passes the one `recon weights fetch` uses; this module does not import it).
pub type Download<'a> = &'a (dyn Fn(&Manifest, &[&ManifestFile], &Path) -> Result<()> + Sync);

/// [`resolve_manifest`] for an embedded manifest's name or a manifest file.
pub fn resolve_module_files(
    name_or_path: &str,
    config: &RecGenConfig,
    cache: &Path,
    download: Option<Download<'_>>,
) -> Result<WeightFiles> {
    resolve_manifest(&Manifest::load(name_or_path)?, name_or_path, config, cache, download)
}

/// Everything a model needs from the files a manifest lists, as they lie in
/// a Hugging Face cache (`cache`, the `hub` folder; see
/// [`Manifest::resolve_dir`]) after `recon weights fetch`; `from` is where the
/// manifest was loaded from (for relative `requires`).
///
/// Each module of `config` (the base architecture) is matched by class
/// family ([`ModuleKind`]) to a weights file of the manifest, else of the
/// manifests it `requires`, else of the other embedded ones. Every needed
/// file (those checkpoints and the manifest's non-optional config files) must
/// be in the cache, or, given `download` (the engine passes `recon weights
/// fetch`'s) and unless `HF_HUB_OFFLINE` is set, be downloaded into it first
/// (else one error lists every missing file, with the fetch
/// command; under `HF_HUB_OFFLINE` it says nothing is downloaded), match its
/// SHA-256 pin ([`Error::ChecksumMismatch`]) and, for a checkpoint, its tensor
/// list (names and shapes). The architecture is `config` with what the
/// release's own files say put in (see [`release_architecture`]).
pub fn resolve_manifest(
    primary: &Manifest,
    from: &str,
    config: &RecGenConfig,
    cache: &Path,
    download: Option<Download<'_>>,
) -> Result<WeightFiles> {
    use rayon::prelude::*;
    let settings = crate::settings::current();
    let mut search = vec![primary.clone()];
    for m in primary.required(from)?.into_iter().chain(Manifest::all()?) {
        if !search.iter().any(|s| s.name == m.name) {
            search.push(m);
        }
    }
    let find = |kind: ModuleKind| {
        search.iter().find_map(|m| {
            m.files
                .iter()
                .find(|f| is_weights_file(f) && !f.optional && f.module.as_deref().and_then(ModuleKind::of) == Some(kind))
                .map(|f| (m, f))
        })
    };
    // (manifest, file, what it is for, module key)
    let mut need: Vec<(&Manifest, &ManifestFile, String, Option<ModuleKey>)> = Vec::new();
    let mut missing = Vec::new();
    for (key, spec) in config.modules() {
        let Some(kind) = ModuleKind::of(&spec.name) else {
            missing.push(format!("{key}: module class `{}` is unknown", spec.name));
            continue;
        };
        match find(kind) {
            Some((m, f)) => need.push((m, f, key.to_string(), Some(key))),
            None => missing.push(format!("{key}: no manifest lists a {} checkpoint", spec.name)),
        }
    }
    let primary = &search[0];
    for f in primary.files.iter().filter(|f| !f.optional && !is_weights_file(f)) {
        need.push((primary, f, f.role.clone().unwrap_or_else(|| "config".into()), None));
    }
    // Online, what the cache lacks is downloaded first (hf-hub into the same cache, as
    // `recon weights fetch` does; pins are checked below with the rest). A failed download
    // is the error: it names the repo, the file and what to do.
    if let Some(download) = download.filter(|_| !settings.hf_offline && missing.is_empty()) {
        for m in &search {
            let absent: Vec<&ManifestFile> =
                need.iter().filter(|(n, f, ..)| std::ptr::eq(*n, m) && !m.expected_path(cache, f).is_file()).map(|(_, f, ..)| *f).collect();
            if !absent.is_empty() {
                download(m, &absent, cache)?;
            }
        }
    }
    // Missing files, by manifest, with where they were looked for said once.
    let mut fetch = vec![primary.name.clone()];
    for m in &search {
        let mine: Vec<_> = need.iter().filter(|(n, ..)| std::ptr::eq(*n, m)).collect();
        let absent: Vec<String> = mine
            .iter()
            .filter(|(_, f, ..)| !m.expected_path(cache, f).is_file())
            .map(|(_, f, what, key)| match key {
                Some(_) => format!("{what} (`{}`)", f.path),
                None => format!("`{}`", f.path),
            })
            .collect();
        if absent.is_empty() {
            continue;
        }
        let place = match (&m.repo, m.source.as_str()) {
            (_, "url") => format!("{} (or torch.hub's checkpoints folder)", cache.join("recon-url").join(&m.name).display()),
            (Some(repo), _) => match hf_cache::snapshot(cache, repo, m.revision()) {
                Some(s) => s.dir.display().to_string(),
                None => format!("{} (no snapshot of it there)", hf_cache::repo_folder(cache, repo).display()),
            },
            (None, _) => cache.display().to_string(),
        };
        let all = if absent.len() == mine.len() && absent.len() > 1 { "all " } else { "" };
        missing.push(format!("{all}{} of {} in {place}: {}", absent.len(), m.origin(), absent.join(", ")));
        if !fetch.contains(&m.name) {
            fetch.push(m.name.clone());
        }
    }
    if !missing.is_empty() {
        let cmds: Vec<String> = fetch.iter().map(|n| format!("`recon weights fetch --manifest {n}`")).collect();
        let advice = if settings.hf_offline {
            format!(
                "HF_HUB_OFFLINE is set, so nothing is downloaded: run {} where the network is reachable, or point HF_HUB_CACHE / HF_HOME at a cache that holds them",
                cmds.join(" and ")
            )
        } else {
            format!(
                "Download them first with {} (the cache is $HF_HUB_CACHE, else $HF_HOME/hub, else ~/.cache/huggingface/hub)",
                cmds.join(" and ")
            )
        };
        return Err(Error::input(
            cache.display().to_string(),
            format!("weights manifest `{}`: the cache does not hold every file; missing: {}. {advice}", primary.name, missing.join("; ")),
        ));
    }
    // Pins and tensor lists, file by file (hashing the release's gigabytes is
    // the slow part: in parallel).
    let read: Vec<ReadFile> = need
        .par_iter()
        .map(|(m, f, what, _)| -> Result<ReadFile> {
            let local = m.expected_path(cache, f);
            if let Some(pin) = &f.sha256 {
                hf_cache::check_sha256(&local, pin)?;
            }
            let mut tensors = None;
            if let (true, Some(list)) = (is_weights_file(f), &f.tensors) {
                let ck = crate::weights::load::Checkpoint::open(&local, f.pt_key.as_deref())?;
                crate::weights::validate::validate_checkpoint(&ck, list, f.allow_unexpected)?;
                tensors = Some(list.len());
            }
            Ok(ReadFile {
                manifest: m.name.clone(),
                path: f.path.clone(),
                local,
                sha256: f.sha256.clone(),
                tensors,
                used_for: what.clone(),
            })
        })
        .collect::<Result<_>>()?;
    let mut out = WeightFiles { dir: primary.resolve_dir(cache), ..Default::default() };
    for (m, f, _, key) in &need {
        if let Some(k) = key {
            out.modules.insert(*k, m.expected_path(cache, f));
        }
    }
    for f in primary.files.iter().filter(|f| f.kind == "json" && !f.optional) {
        let role = f.role.as_deref().unwrap_or("");
        if !role.contains("pose normaliser statistics") {
            continue;
        }
        let p = primary.expected_path(cache, f);
        if role.contains("stage-1") {
            out.ss_stats = Some(p);
        } else if role.contains("stage-2") {
            out.slat_stats = Some(p);
        }
    }
    let local_of = |path: &str| primary.files.iter().find(|f| f.path == path).map(|f| primary.expected_path(cache, f));
    let sections: Vec<(ModuleKey, PathBuf)> = need
        .iter()
        .filter(|(m, ..)| m.name == primary.name)
        .filter_map(|(_, f, _, key)| Some(((*key)?, local_of(f.config.as_deref()?)?)))
        .collect();
    let pipeline_json = primary.files.iter().find(|f| f.path.rsplit('/').next() == Some("pipeline.json")).and_then(|f| local_of(&f.path));
    let (arch, notes) = release_architecture(config, &sections, pipeline_json.as_deref(), &primary.name)?;
    out.architecture = Some(arch);
    out.notes = notes;
    if let Some(s) = primary.repo.as_deref().and_then(|r| hf_cache::snapshot(cache, r, primary.revision())) {
        if let Some(pinned) = s.instead_of {
            out.notes.insert(
                0,
                format!("{}: revision {pinned} is not in the cache; took the snapshot of refs/main, {}", primary.origin(), s.commit),
            );
        }
    }
    out.read = read;
    Ok(out)
}

/// The module config inside a release config file: a TRELLIS module config
/// (`{"name", "args"}`) or a RecGen training config (`models.<name>` whose
/// class is of `kind`).
fn module_section(v: &serde_json::Value, kind: ModuleKind) -> Option<serde_json::Value> {
    let spec = if v.get("args").is_some() && v.get("name").is_some() {
        v.clone()
    } else {
        v.get("models")?
            .as_object()?
            .values()
            .find(|m| m.get("name").and_then(|n| n.as_str()).and_then(ModuleKind::of) == Some(kind))?
            .clone()
    };
    let (name, args) = (spec.get("name")?.clone(), spec.get("args")?.clone());
    Some(serde_json::json!({"name": name, "args": args}))
}

/// `base` with what the release's own config files say, as upstream's
/// `build_recgen` takes it: each module's section from the config file its
/// checkpoint names (`sections`: TRELLIS `ckpts/*.json`, RecGen
/// `models.denoiser`), the SLat latent normalisation from the stage-2
/// training config (`dataset.args.normalization`), and the sampler settings
/// from `pipeline.json` (`args.{sparse_structure,slat}_sampler`). The image
/// encoder and the pose layout stay `base`'s. Returns the architecture and
/// one note per replaced part.
pub fn release_architecture(
    base: &RecGenConfig,
    sections: &[(ModuleKey, PathBuf)],
    pipeline_json: Option<&Path>,
    manifest: &str,
) -> Result<(RecGenConfig, Vec<String>)> {
    let mut v = serde_json::to_value(base).map_err(|e| Error::msg(format!("architecture {}: {e}", base.name)))?;
    let mut notes = Vec::new();
    for (key, path) in sections {
        let file = path.display().to_string();
        let cfg: serde_json::Value = crate::util::json::read_json(path)?;
        let spec = module_section(&cfg, key.kind()).ok_or_else(|| {
            Error::config(&file, "models", format!("no `{{name, args}}` of a {:?} module (the `{key}` checkpoint's config)", key.kind()))
        })?;
        let name = spec["name"].as_str().unwrap_or("");
        if ModuleKind::of(name) != Some(key.kind()) {
            return Err(Error::config(
                &file,
                "name",
                format!("`{name}` is not a {:?} module (the `{key}` checkpoint's config)", key.kind()),
            ));
        }
        v[key.name()] = spec;
        notes.push(format!("{key}: args from {file}"));
        if *key == ModuleKey::SlatFlow {
            if let Some(n) = cfg.pointer("/dataset/args/normalization").filter(|n| n.is_object()) {
                v["slat_normalization"] = n.clone();
                notes.push(format!("slat_normalization: from {file} (dataset.args.normalization)"));
            }
        }
    }
    if let Some(p) = pipeline_json {
        let pj: serde_json::Value = crate::util::json::read_json(p)?;
        for (ours, theirs) in [("sparse_structure", "sparse_structure_sampler"), ("slat", "slat_sampler")] {
            let Some(s) = pj.pointer(&format!("/args/{theirs}")) else { continue };
            let target = &mut v["samplers"][ours];
            if let Some(n) = s.get("name") {
                target["class"] = n.clone();
            }
            for part in ["params", "args"] {
                for (k, val) in s.get(part).and_then(|x| x.as_object()).into_iter().flatten() {
                    if ["steps", "cfg_strength", "cfg_interval", "rescale_t", "sigma_min"].contains(&k.as_str()) {
                        target[k.as_str()] = val.clone();
                    }
                }
            }
            notes.push(format!("samplers.{ours}: from {} (args.{theirs})", p.display()));
        }
    }
    let label = format!("{} with the release configs of manifest `{manifest}`", base.name);
    let mut arch = RecGenConfig::from_json(&v, &label)?;
    arch.base_dir = base.base_dir.clone();
    Ok((arch, notes))
}

/// Where each module's checkpoint is, for layouts other than
/// `<dir>/<key>.safetensors` (e.g. the upstream files resolved through a
/// weights manifest).
#[derive(Debug, Clone, Default)]
pub struct WeightFiles {
    /// Reported as the weights' origin.
    pub dir: PathBuf,
    /// Module key ([`crate::model::config::RecGenConfig::modules`]) → checkpoint file.
    pub modules: HashMap<crate::model::key::ModuleKey, PathBuf>,
    /// Pose statistics to use instead of the files the architecture names.
    pub ss_stats: Option<PathBuf>,
    /// Likewise for the stage-2 pose statistics (`ss_stats` is stage 1's).
    pub slat_stats: Option<PathBuf>,
    /// The architecture to build instead of the one the caller names (the
    /// base architecture with the release's configs put in).
    pub architecture: Option<RecGenConfig>,
    /// Every manifest file read, with what was checked.
    pub read: Vec<ReadFile>,
    /// What the release's files changed, and any other remark, in words.
    pub notes: Vec<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_manifests_parse() {
        let all = Manifest::all().unwrap();
        assert_eq!(all.len(), EMBEDDED.len());
        for m in &all {
            assert!(!m.files.is_empty(), "{}", m.name);
            for f in &m.files {
                if m.source == "url" {
                    assert!(f.url.is_some(), "{} {}", m.name, f.path);
                }
                assert!(f.tensors.is_some() || f.tensors_note.is_some() || f.kind == "json", "{} {}", m.name, f.path);
            }
        }
    }

    /// The shipped tensor lists are what `recon weights manifest NAME --config
    /// models/recgen-large.json` generates (regenerate them when a module
    /// changes), the pretty form parses back to itself, and the RecGen lists
    /// hold the parameters upstream's module definitions give at the released
    /// sizes (recgen_inference/recgen_modules/models/*.py: spot checks of
    /// each part).
    #[test]
    fn shipped_tensor_lists_are_generated_and_match_upstream() -> Result<()> {
        let arch = RecGenConfig::load(&crate::util::testing::repo().join("models/recgen-large.json"))?;
        for name in ["recgen", "dinov2-vitl14-reg", "trellis-image-large"] {
            let m = Manifest::load(name)?;
            let regen = m.with_tensors_from(&arch, "models/recgen-large.json")?;
            for (a, b) in m.files.iter().zip(&regen.files) {
                assert!(
                    a.tensors == b.tensors,
                    "{name} {}: run `recon weights manifest {name} --out weights-manifest/{name}.json`",
                    a.path
                );
            }
            let text = m.to_pretty_json()?;
            assert_eq!(Manifest::parse(&text, name)?.to_pretty_json()?, text);
        }
        let m = Manifest::load("recgen")?;
        assert_eq!(m.requires, vec!["dinov2-vitl14-reg".to_string()]);
        for f in m.files.iter().filter(|f| !f.optional && f.kind != "json") {
            assert!(f.tensors.as_ref().is_some_and(|t| !t.is_empty()), "{}", f.path);
        }
        let list = |suffix: &str| -> HashMap<String, Vec<usize>> {
            let f = m.files.iter().find(|f| f.path.ends_with(suffix)).expect(suffix);
            f.tensors.iter().flatten().map(|t| (t.name.clone(), t.shape.clone())).collect()
        };
        let ss = list("step0070000.pt");
        for (n, s) in [
            ("pos_emb", vec![4096, 1024]),
            ("input_layer.weight", vec![1024, 8]),
            ("out_layer.weight", vec![8, 1024]),
            ("t_embedder.mlp.0.weight", vec![1024, 256]),
            ("input_layer_pose.weight", vec![1024, 10]),
            ("out_layer_pose.weight", vec![10, 1024]),
            ("pose_token_embedder", vec![2, 1024]),
            ("frame_token_embedder", vec![2, 1024]),
            ("point_embedder.weight", vec![1024, 3, 14, 14]),
            ("mask_embedder.weight", vec![1024, 1, 14, 14]),
            ("blocks.23.self_attn.to_qkv.weight", vec![3072, 1024]),
            ("blocks.23.self_attn.q_rms_norm.gamma", vec![16, 64]),
            ("blocks.0.cross_attn.to_kv.weight", vec![2048, 1024]),
            ("blocks.0.norm2.weight", vec![1024]),
            ("blocks.0.mlp.mlp.2.weight", vec![1024, 4096]),
            ("blocks.0.adaLN_modulation.1.weight", vec![6144, 1024]),
        ] {
            assert_eq!(ss.get(n), Some(&s), "stage 1 `{n}`");
        }
        // LayerNorm32(elementwise_affine=False) norms and the 24 blocks only.
        assert!(!ss.contains_key("blocks.0.norm1.weight") && !ss.keys().any(|k| k.starts_with("blocks.24.")));
        let slat = list("step0075000.pt");
        for (n, s) in [
            ("input_layer.weight", vec![128, 8]),
            ("input_blocks.0.conv1.conv.weight", vec![128, 3, 3, 3, 128]),
            ("input_blocks.1.conv1.conv.weight", vec![1024, 3, 3, 3, 128]),
            ("input_blocks.1.skip_connection.weight", vec![1024, 128]),
            ("input_blocks.1.emb_layers.1.weight", vec![2048, 1024]),
            ("out_blocks.0.norm1.weight", vec![2048]),
            ("out_blocks.0.conv1.conv.weight", vec![128, 3, 3, 3, 2048]),
            ("out_blocks.1.skip_connection.weight", vec![128, 256]),
            ("out_layer.weight", vec![8, 128]),
            ("pose_embedder.weight", vec![1024, 13]),
            ("point_embedder.weight", vec![1024, 3, 14, 14]),
            ("blocks.23.cross_attn.to_out.weight", vec![1024, 1024]),
        ] {
            assert_eq!(slat.get(n), Some(&s), "stage 2 `{n}`");
        }
        // The sinusoidal position embedder holds no parameter; equal-width res blocks skip through Identity.
        assert!(!slat.contains_key("pos_emb") && !slat.contains_key("input_blocks.0.skip_connection.weight"));
        // The TRELLIS decoders (trellis/models/sparse_structure_vae.py, structured_latent_vae/*).
        for (file, n, s) in [
            ("ss_dec_conv3d_16l8_fp16.safetensors", "input_layer.weight", vec![512, 8, 3, 3, 3]),
            ("ss_dec_conv3d_16l8_fp16.safetensors", "middle_block.1.conv2.weight", vec![512, 512, 3, 3, 3]),
            ("ss_dec_conv3d_16l8_fp16.safetensors", "blocks.2.conv.weight", vec![1024, 512, 3, 3, 3]),
            ("ss_dec_conv3d_16l8_fp16.safetensors", "blocks.7.norm2.weight", vec![32]),
            ("ss_dec_conv3d_16l8_fp16.safetensors", "out_layer.2.weight", vec![1, 32, 3, 3, 3]),
            ("m256c_fp16.safetensors", "input_layer.weight", vec![768, 8]),
            ("m256c_fp16.safetensors", "blocks.11.attn.to_qkv.weight", vec![2304, 768]),
            ("m256c_fp16.safetensors", "upsample.0.act_layers.0.weight", vec![768]),
            ("m256c_fp16.safetensors", "upsample.0.out_layers.0.conv.weight", vec![192, 3, 3, 3, 768]),
            ("m256c_fp16.safetensors", "upsample.0.skip_connection.conv.weight", vec![192, 1, 1, 1, 768]),
            ("m256c_fp16.safetensors", "upsample.1.out_layers.3.conv.weight", vec![96, 3, 3, 3, 96]),
            ("m256c_fp16.safetensors", "out_layer.weight", vec![101, 96]),
            ("gs32_fp16.safetensors", "out_layer.weight", vec![448, 768]),
            ("gs32_fp16.safetensors", "offset_perturbation", vec![32, 3]),
            ("gs32_fp16.safetensors", "blocks.0.mlp.mlp.0.weight", vec![3072, 768]),
        ] {
            assert_eq!(list(file).get(n), Some(&s), "{file} `{n}`");
        }
        // LayerNorm32(elementwise_affine=False) in the decoders' transformer blocks.
        assert!(!list("gs32_fp16.safetensors").contains_key("blocks.0.norm1.weight"));
        Ok(())
    }

    #[test]
    fn dinov2_manifest_matches_the_model() {
        let m = Manifest::load("dinov2-vitl14-reg").unwrap();
        let f = &m.files[0];
        let cfg = crate::model::config::ModuleArgs::Dinov2(crate::model::stage1::dinov2::Dinov2Config::vitl14_reg());
        let want = crate::weights::registry::expected_tensors(&cfg, "vitl14").unwrap();
        assert_eq!(f.tensors.as_ref().unwrap(), &want);
        // 24 blocks × 14 tensors + cls, pos, registers, mask, patch w/b, norm w/b.
        assert_eq!(want.len(), 24 * 14 + 8);
        let params: usize = want.iter().map(|s| s.shape.iter().product::<usize>()).sum();
        // spec §10: 304.37 M weights (+1024 for the unused mask_token).
        assert_eq!(params, 304_372_736);
    }
}
