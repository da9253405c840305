//! Weights manifests (`weights-manifest/*.json`, embedded in the binary):
//! which upstream files the engine uses, where they come from, which module
//! each belongs to, and — where the module exists in this crate — the exact
//! tensor names and shapes a checkpoint must hold.

use crate::weights::record::TensorSpec;
use crate::{Error, Result};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// Manifests shipped with the crate: (name, JSON text).
pub const EMBEDDED: &[(&str, &str)] = &[
    ("recgen", include_str!("../../../../weights-manifest/recgen.json")),
    ("trellis-image-large", include_str!("../../../../weights-manifest/trellis-image-large.json")),
    ("dinov2-vitl14-reg", include_str!("../../../../weights-manifest/dinov2-vitl14-reg.json")),
];

/// A weights manifest: the upstream files of one model release, where they come from and what they hold.
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
pub struct Manifest {
    /// The manifest's name (`recgen`); URL-sourced files are stored under it.
    pub name: String,
    /// `huggingface` (files of `repo` at `revision`) or `url` (each file has its own `url`).
    pub source: String,
    /// Hugging Face repo id (`owner/name`) of a `huggingface` manifest.
    #[serde(default)]
    pub repo: Option<String>,
    /// Repo revision the files are taken from (`main` when absent).
    #[serde(default)]
    pub revision: Option<String>,
    /// Licence of the files, as text.
    #[serde(default)]
    pub licence: Option<String>,
    /// Free-form remarks.
    #[serde(default)]
    pub notes: Vec<String>,
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
    #[serde(default)]
    pub url: Option<String>,
    /// SHA-256 of the file (hex), as recorded; recon does not check it.
    #[serde(default)]
    pub sha256: Option<String>,
    /// Upstream class the weights belong to.
    #[serde(default)]
    pub module: Option<String>,
    /// Config file (in the same repo) with the module's constructor args.
    #[serde(default)]
    pub config: Option<String>,
    /// What the file is for.
    #[serde(default)]
    pub role: Option<String>,
    /// Upstream loads with `strict=False`: extra tensors are tolerated.
    #[serde(default)]
    pub allow_unexpected: bool,
    /// Wrapped state-dict key inside a `.pt` file, when known.
    #[serde(default)]
    pub pt_key: Option<String>,
    /// Expected tensors (null where the module is not in the crate yet).
    #[serde(default)]
    pub tensors: Option<Vec<TensorSpec>>,
    /// Why `tensors` is null, or how it was generated.
    #[serde(default)]
    pub tensors_note: Option<String>,
    /// Not needed by recon: fetched only on request, and absence passes `verify`.
    #[serde(default)]
    pub optional: bool,
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

    /// Where the files live under `dir`: `dir` itself, or, when `dir` is a
    /// Hugging Face cache (`…/hub`), the snapshot of this repo/revision (or
    /// `recon-url/<name>` for URL-sourced files, where `fetch` puts them).
    pub fn resolve_dir(&self, dir: &Path) -> PathBuf {
        let url_dir = dir.join("recon-url").join(&self.name);
        if self.source == "url" && url_dir.is_dir() {
            return url_dir;
        }
        if let (Some(repo), Some(rev)) = (&self.repo, &self.revision) {
            let snap = dir.join(format!("models--{}", repo.replace('/', "--"))).join("snapshots").join(rev);
            if snap.is_dir() {
                return snap;
            }
            let snaps = dir.join(format!("models--{}", repo.replace('/', "--"))).join("snapshots");
            if let Ok(rd) = std::fs::read_dir(&snaps) {
                if let Some(first) = rd.flatten().map(|e| e.path()).find(|p| p.is_dir()) {
                    return first;
                }
            }
        }
        dir.to_path_buf()
    }
}

/// Checkpoint kinds that hold weights (not configs).
fn is_weights_file(f: &ManifestFile) -> bool {
    matches!(f.kind.as_str(), "safetensors" | "pt" | "pth")
}

/// The checkpoint of every module of an architecture, from the files a
/// manifest lists, as they lie in a Hugging Face cache (`cache`, the `hub`
/// folder; see [`Manifest::resolve_dir`]) after `recon weights fetch`.
///
/// Each module is matched by class family ([`ModuleKind`](crate::weights::registry::ModuleKind)) to a weights
/// file of the named manifest; a family the manifest does not list at all
/// (RecGen ships no DINOv2) is taken from the other embedded manifests. The
/// manifest's pose-statistics files (role "stage-1/stage-2 pose normaliser
/// statistics"), when present, replace the architecture's. Missing files are
/// one error listing every path looked at.
pub fn resolve_module_files(name_or_path: &str, config: &crate::model::config::RecGenConfig, cache: &Path) -> Result<WeightFiles> {
    use crate::weights::registry::ModuleKind;
    let primary = Manifest::load(name_or_path)?;
    let others: Vec<Manifest> = Manifest::all()?.into_iter().filter(|m| m.name != primary.name).collect();
    let lists = |m: &Manifest, kind: ModuleKind| -> Option<ManifestFile> {
        m.files.iter().find(|f| is_weights_file(f) && !f.optional && f.module.as_deref().and_then(ModuleKind::of) == Some(kind)).cloned()
    };
    let mut out = WeightFiles { dir: primary.resolve_dir(cache), ..Default::default() };
    let mut missing = Vec::new();
    let mut fetch = vec![primary.name.clone()];
    for (key, spec) in config.modules() {
        let Some(kind) = ModuleKind::of(&spec.name) else {
            missing.push(format!("{key}: module class `{}` is unknown", spec.name));
            continue;
        };
        let found = lists(&primary, kind).map(|f| (&primary, f)).or_else(|| others.iter().find_map(|m| lists(m, kind).map(|f| (m, f))));
        let Some((m, f)) = found else {
            missing.push(format!("{key}: no manifest lists a {} checkpoint", spec.name));
            continue;
        };
        let path = m.resolve_dir(cache).join(&f.path);
        if path.is_file() {
            out.modules.insert(key, path);
        } else {
            missing.push(format!("{key}: {}", path.display()));
            if !fetch.contains(&m.name) {
                fetch.push(m.name.clone());
            }
        }
    }
    if !missing.is_empty() {
        let cmds: Vec<String> = fetch.iter().map(|n| format!("`recon weights fetch --manifest {n}`")).collect();
        return Err(Error::input(
            cache.display().to_string(),
            format!(
                "weights manifest `{}`: the cache does not hold every checkpoint; missing: {}. Download them first with {} (the cache is $HF_HOME/hub, else ~/.cache/huggingface/hub)",
                primary.name,
                missing.join("; "),
                cmds.join(" and ")
            ),
        ));
    }
    let dir = primary.resolve_dir(cache);
    for f in primary.files.iter().filter(|f| f.kind == "json") {
        let role = f.role.as_deref().unwrap_or("");
        if !role.contains("pose normaliser statistics") {
            continue;
        }
        let p = dir.join(&f.path);
        if !p.is_file() {
            continue;
        }
        if role.contains("stage-1") {
            out.ss_stats = Some(p);
        } else if role.contains("stage-2") {
            out.slat_stats = Some(p);
        }
    }
    Ok(out)
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
