//! Where an [`Engine`](crate::engine::infer::Engine)'s model comes from: the
//! trained default that ships with recon, a folder, a weights manifest, or
//! random weights. The CLI's `--weights` and `--config` map onto this
//! ([`ModelSource::parse`]), so every front end loads a model the same way.

use crate::weights::manifest::{Manifest, EMBEDDED};
use crate::{Error, Result};
use std::path::{Path, PathBuf};

/// A model: its weights and, where it is not implied, its architecture file.
#[derive(Debug, Clone, PartialEq)]
pub enum ModelSource {
    /// The trained recgen-nano: `models/recgen-nano/` in the working folder
    /// when it holds a complete model (a checkout, possibly retrained), else
    /// the copy compiled into recon (unpacked once under `$RECON_CACHE`,
    /// `$XDG_CACHE_HOME/recon` or `~/.cache/recon`).
    Default,
    /// `<module>.safetensors` per module; the architecture file is the JSON in
    /// the folder holding an `ss_flow` section unless `config` names one
    /// (`models/recgen-tiny.json` when the folder holds none).
    Dir {
        /// The folder holding the weights.
        dir: PathBuf,
        /// The architecture file, when given.
        config: Option<PathBuf>,
    },
    /// A weights manifest (`recgen`, or a manifest file) resolved in the
    /// Hugging Face cache after `recon weights fetch`. The release's own
    /// configs give the module args, latent normalisation, samplers and pose
    /// statistics; the base architecture (`models/recgen-large.json` unless
    /// `config` names one) gives the rest (the image encoder, the pose layout).
    Manifest {
        /// An embedded manifest's name or a manifest file's path, or
        /// `hf:ORG/NAME[@REV]` (see [`ModelSource::parse`]).
        name: String,
        /// The architecture file, when given.
        config: Option<PathBuf>,
        /// The Hugging Face cache (`hub` folder) the files are looked up in.
        cache: PathBuf,
    },
    /// Random weights (`models/recgen-tiny.json` unless `config` names an
    /// architecture): the plumbing is real, the shapes and poses are not.
    Random {
        /// The architecture file, when given.
        config: Option<PathBuf>,
        /// Seed of the random weights.
        seed: u64,
    },
}

impl ModelSource {
    /// From the `--weights` / `weights=` convention: none → the default,
    /// `random`, a folder, a manifest name or file, or `hf:ORG/NAME[@REV]` (a
    /// Hugging Face repo with the RecGen layout, through the same cache: the
    /// embedded manifest of that repo, pins kept at its own revision).
    /// `config` overrides the architecture file; `seed` seeds random weights.
    pub fn parse(weights: Option<&str>, config: Option<&Path>, seed: u64) -> Result<Self> {
        let config = config.map(Path::to_path_buf);
        let Some(w) = weights else {
            return Ok(match config {
                None => ModelSource::Default,
                Some(c) => ModelSource::Dir { dir: default_model_dir()?, config: Some(c) },
            });
        };
        if w == "random" {
            return Ok(ModelSource::Random { config, seed });
        }
        if let Some(spec) = w.strip_prefix("hf:") {
            parse_hf(spec)?;
            return Ok(ModelSource::Manifest { name: w.to_string(), config, cache: crate::weights::fetch::default_hf_cache() });
        }
        let p = Path::new(w);
        if p.is_dir() {
            return Ok(ModelSource::Dir { dir: p.to_path_buf(), config });
        }
        if EMBEDDED.iter().any(|(n, _)| *n == w) || (p.is_file() && Manifest::load(w).is_ok()) {
            return Ok(ModelSource::Manifest { name: w.to_string(), config, cache: crate::weights::fetch::default_hf_cache() });
        }
        let known: Vec<&str> = EMBEDDED.iter().map(|(n, _)| *n).collect();
        Err(Error::input(
            "--weights",
            format!(
                "`{w}`: not a directory, and not `random`, a manifest name ({}), a manifest file or hf:ORG/NAME[@REV]",
                known.join(", ")
            ),
        ))
    }

    /// Load options for `dtype` on this source's architecture (`auto` resolved).
    pub fn load_options(&self, dtype: crate::engine::pipeline::Dtype) -> Result<crate::engine::pipeline::LoadOptions> {
        let arch = crate::model::RecGenConfig::load(&self.architecture()?)?;
        Ok(crate::engine::pipeline::LoadOptions::precision(dtype.resolve(&arch)?))
    }

    /// The architecture file this source is built with.
    pub fn architecture(&self) -> Result<PathBuf> {
        Ok(match self {
            ModelSource::Default => find_architecture(&default_model_dir()?)?,
            // A trained folder carries its architecture file (`recon train slat-flow`).
            ModelSource::Dir { dir, config } => match config {
                Some(c) => c.clone(),
                None => match find_architecture(dir) {
                    Ok(a) => a,
                    Err(_) => shipped_architecture("recgen-tiny.json")?,
                },
            },
            ModelSource::Manifest { config, .. } => match config {
                Some(c) => c.clone(),
                None => shipped_architecture("recgen-large.json")?,
            },
            ModelSource::Random { config, .. } => match config {
                Some(c) => c.clone(),
                None => shipped_architecture("recgen-tiny.json")?,
            },
        })
    }
}

/// The architecture files a source falls back to, with the pose statistics they name,
/// compiled in (crates/core/shipped/ links to models/) so that `--weights recgen` or
/// `random` works outside a checkout too.
const SHIPPED_ARCHITECTURES: [(&str, &str); 4] = [
    ("recgen-large.json", include_str!("../../shipped/recgen-large.json")),
    ("recgen-tiny.json", include_str!("../../shipped/recgen-tiny.json")),
    ("stereo_pose_stats.example.json", include_str!("../../shipped/stereo_pose_stats.example.json")),
    ("slat_pose_stats.example.json", include_str!("../../shipped/slat_pose_stats.example.json")),
];

/// `models/<name>` (one of [`SHIPPED_ARCHITECTURES`]) when the working folder has it (a
/// checkout: the path outputs have always recorded), else the compiled-in copy unpacked under
/// the cache folder (once per content, as the embedded model).
pub fn shipped_architecture(name: &str) -> Result<PathBuf> {
    let local = Path::new("models").join(name);
    if local.is_file() {
        return Ok(local);
    }
    let files: Vec<(&str, &[u8])> = SHIPPED_ARCHITECTURES.iter().map(|(n, text)| (*n, text.as_bytes())).collect();
    Ok(unpack_once(&cache_root(), "models", &files, "recgen-large.json")?.join(name))
}

/// `ORG/NAME[@REV]` of an `hf:` weights argument, checked.
pub fn parse_hf(spec: &str) -> Result<(String, Option<String>)> {
    let (repo, rev) = match spec.split_once('@') {
        Some((r, v)) => (r, Some(v)),
        None => (spec, None),
    };
    let ok = |s: &str| !s.is_empty() && s.chars().all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c));
    match repo.split_once('/') {
        Some((org, name)) if ok(org) && ok(name) && rev.is_none_or(|r| !r.is_empty() && !r.contains(char::is_whitespace)) => {
            Ok((repo.to_string(), rev.map(str::to_string)))
        }
        _ => Err(Error::input("--weights", format!("`hf:{spec}`: expected hf:ORG/NAME or hf:ORG/NAME@REVISION"))),
    }
}

/// The manifest a [`ModelSource::Manifest`] name stands for.
pub fn manifest_of(name: &str) -> Result<Manifest> {
    match name.strip_prefix("hf:") {
        Some(spec) => {
            let (repo, rev) = parse_hf(spec)?;
            Manifest::for_hf_repo(&repo, rev.as_deref())
        }
        None => Manifest::load(name),
    }
}

/// The architecture file of a trained folder: the one JSON holding an `ss_flow` section.
pub fn find_architecture(dir: &Path) -> Result<PathBuf> {
    let mut found = Vec::new();
    for e in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let p = e.map_err(|e| Error::io(dir, e))?.path();
        if p.extension().is_some_and(|x| x == "json") {
            let v: Option<serde_json::Value> = std::fs::read_to_string(&p).ok().and_then(|s| serde_json::from_str(&s).ok());
            if v.is_some_and(|v| v.get(crate::model::key::ModuleKey::SsFlow.name()).is_some()) {
                found.push(p);
            }
        }
    }
    found.sort();
    match found.len() {
        1 => Ok(found.remove(0)),
        0 => Err(Error::input(dir.display().to_string(), "no architecture file (a JSON with an `ss_flow` section); pass --config")),
        _ => Err(Error::input(dir.display().to_string(), format!("several architecture files ({found:?}); pass --config"))),
    }
}

/// The trained recgen-nano, compiled in so that recon has its trained default
/// wherever it runs (the files of models/recgen-nano/ at build time; crates/core/build.rs
/// finds them). Empty in a build from the published package, which cannot carry them.
#[cfg(recon_embedded_nano)]
const EMBEDDED_NANO: &[(&str, &[u8])] = &[
    ("recgen-nano.json", include_bytes!(concat!(env!("RECON_EMBEDDED_NANO_DIR"), "/recgen-nano.json"))),
    ("pose_stats.json", include_bytes!(concat!(env!("RECON_EMBEDDED_NANO_DIR"), "/pose_stats.json"))),
    ("image_cond_model.safetensors", include_bytes!(concat!(env!("RECON_EMBEDDED_NANO_DIR"), "/image_cond_model.safetensors"))),
    ("ss_flow.safetensors", include_bytes!(concat!(env!("RECON_EMBEDDED_NANO_DIR"), "/ss_flow.safetensors"))),
    ("ss_decoder.safetensors", include_bytes!(concat!(env!("RECON_EMBEDDED_NANO_DIR"), "/ss_decoder.safetensors"))),
    ("slat_flow.safetensors", include_bytes!(concat!(env!("RECON_EMBEDDED_NANO_DIR"), "/slat_flow.safetensors"))),
    ("slat_dec_mesh.safetensors", include_bytes!(concat!(env!("RECON_EMBEDDED_NANO_DIR"), "/slat_dec_mesh.safetensors"))),
    ("slat_dec_gs.safetensors", include_bytes!(concat!(env!("RECON_EMBEDDED_NANO_DIR"), "/slat_dec_gs.safetensors"))),
];
#[cfg(not(recon_embedded_nano))]
const EMBEDDED_NANO: &[(&str, &[u8])] = &[];

/// The embedded recgen-nano's content hash (FNV-1a over its file names and bytes, the
/// name of the folder it unpacks to), or `None` when this build carries no model.
pub fn embedded_model_hash() -> Option<u64> {
    // 27 MB byte by byte: once per process.
    static HASH: std::sync::OnceLock<Option<u64>> = std::sync::OnceLock::new();
    *HASH.get_or_init(|| (!EMBEDDED_NANO.is_empty()).then(|| fnv(EMBEDDED_NANO)))
}

/// The default model's folder: models/recgen-nano/ in the working folder when
/// it holds a complete model, else the embedded copy unpacked.
pub fn default_model_dir() -> Result<PathBuf> {
    let local = Path::new("models/recgen-nano");
    if local.join("slat_flow.safetensors").is_file() && local.join("recgen-nano.json").is_file() {
        return Ok(local.to_path_buf());
    }
    embedded_model_in(&cache_root())
}

/// Where the embedded model is unpacked: the applied settings' cache folder
/// (`$RECON_CACHE`, else `$XDG_CACHE_HOME/recon`, else `~/.cache/recon`), else
/// the temporary folder.
fn cache_root() -> PathBuf {
    crate::settings::current().cache_dir.unwrap_or_else(|| std::env::temp_dir().join("recon"))
}

/// The embedded recgen-nano as a folder under `root`: unpacked once per content
/// (the folder name carries a hash of every file), written beside and renamed
/// into place so a half-written copy is never used.
pub fn embedded_model_in(root: &Path) -> Result<PathBuf> {
    if EMBEDDED_NANO.is_empty() {
        return Err(Error::input(
            "--weights",
            "none given, and this recon carries no recgen-nano (a build from the published crate: its 27 MB do not fit \
             a crates.io package); run `recon weights fetch recgen` and pass --weights recgen (or hf:TRI-ML/RecGen), \
             or rebuild from a checkout or with RECON_NANO_DIR set to a recgen-nano folder",
        ));
    }
    unpack_once(root, "recgen-nano", EMBEDDED_NANO, "recgen-nano.json")
}

/// FNV-1a 64 over the files' names and contents, in order.
fn fnv(files: &[(&str, &[u8])]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for (name, bytes) in files {
        for &b in name.as_bytes().iter().chain(bytes.iter()) {
            h = (h ^ b as u64).wrapping_mul(0x100_0000_01b3);
        }
    }
    h
}

/// `files` as the folder `<root>/<stem>-<hash>` (FNV-1a over names and contents: changed
/// files get a new folder), written beside and renamed into place so that a half-written
/// copy is never used; `marker` is the file whose presence means the folder is complete.
fn unpack_once(root: &Path, stem: &str, files: &[(&str, &[u8])], marker: &str) -> Result<PathBuf> {
    let h = fnv(files);
    let dir = root.join(format!("{stem}-{h:016x}"));
    if dir.join(marker).is_file() {
        return Ok(dir);
    }
    let tmp = root.join(format!("{stem}-{h:016x}.partial-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).map_err(|e| {
        Error::input(
            tmp.display().to_string(),
            format!("cannot unpack recon's shipped {stem} files here ({e}); set RECON_CACHE to a writable folder"),
        )
    })?;
    for &(name, bytes) in files {
        std::fs::write(tmp.join(name), bytes).map_err(|e| Error::io(tmp.join(name), e))?;
    }
    match std::fs::rename(&tmp, &dir) {
        Ok(()) => Ok(dir),
        // Another process unpacked it first.
        Err(_) if dir.join(marker).is_file() => {
            let _ = std::fs::remove_dir_all(&tmp);
            Ok(dir)
        }
        Err(e) => Err(Error::io(&dir, e)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn embedded_model_unpacks_the_shipped_files_once() {
        // A checkout's build carries the model (crates/core/build.rs).
        assert_eq!(EMBEDDED_NANO.len(), 8, "the build embedded no recgen-nano");
        let root = crate::util::testing::tmp("embedded");
        let dir = embedded_model_in(&root).unwrap();
        assert_eq!(dir.file_name().unwrap().to_str().unwrap(), format!("recgen-nano-{:016x}", embedded_model_hash().unwrap()));
        let shipped = crate::util::testing::repo().join("models/recgen-nano");
        for (name, _) in EMBEDDED_NANO {
            assert_eq!(std::fs::read(dir.join(name)).unwrap(), std::fs::read(shipped.join(name)).unwrap(), "{name}");
        }
        // Reused, and nothing half-written is left beside it.
        assert_eq!(embedded_model_in(&root).unwrap(), dir);
        let entries: Vec<_> = std::fs::read_dir(&root).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(entries.len(), 1, "{entries:?}");
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn weights_arguments_map_to_sources() {
        assert_eq!(ModelSource::parse(None, None, 1).unwrap(), ModelSource::Default);
        assert_eq!(ModelSource::parse(Some("random"), None, 7).unwrap(), ModelSource::Random { config: None, seed: 7 });
        let tiny = crate::util::testing::repo().join("models/recgen-tiny.json");
        let r = ModelSource::parse(Some("random"), Some(&tiny), 7).unwrap();
        assert_eq!(r.architecture().unwrap(), tiny);
        let dir = crate::util::testing::repo().join("models/recgen-nano");
        let d = ModelSource::parse(dir.to_str(), None, 0).unwrap();
        assert_eq!(d, ModelSource::Dir { dir: dir.clone(), config: None });
        assert_eq!(d.architecture().unwrap(), dir.join("recgen-nano.json"));
        let hf = ModelSource::parse(Some("hf:TRI-ML/RecGen@abc123"), None, 0).unwrap();
        assert!(matches!(&hf, ModelSource::Manifest { name, .. } if name == "hf:TRI-ML/RecGen@abc123"));
        let m = manifest_of("hf:tri-ml/recgen@abc123").unwrap();
        assert_eq!((m.name.as_str(), m.revision()), ("recgen", "abc123"));
        assert!(m.files.iter().all(|f| f.sha256.is_none()), "pins hold at the manifest's own revision only");
        let pinned = manifest_of("hf:TRI-ML/RecGen").unwrap();
        assert!(pinned.files.iter().any(|f| f.sha256.is_some()));
        let mirror = manifest_of("hf:someone/recgen-mirror").unwrap();
        assert_eq!(mirror.repo.as_deref(), Some("someone/recgen-mirror"));
        assert!(mirror.files.iter().any(|f| f.path == "pipeline.json") && mirror.files.iter().all(|f| f.sha256.is_none()));
        for bad in ["hf:", "hf:noslash", "hf:a/b@", "hf:a b/c"] {
            assert!(ModelSource::parse(Some(bad), None, 0).unwrap_err().to_string().contains("hf:ORG/NAME"), "{bad}");
        }
        let e = ModelSource::parse(Some("/no/such/weights"), None, 0).unwrap_err().to_string();
        assert!(e.contains("--weights") && e.contains("/no/such/weights") && e.contains("recgen"), "{e}");
    }
}
