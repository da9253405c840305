//! The architecture files a wheel carries. `weights="random"`, a manifest name and `hf:` read
//! their architecture from `models/recgen-{tiny,large}.json` in the working folder (a
//! checkout's); a wheel installed elsewhere has no such folder, so the extension embeds those
//! files (and the pose statistics they name) and unpacks them once into recon's cache folder
//! when the working folder lacks them.

use recon::engine::ModelSource;
use std::path::{Path, PathBuf};

const FILES: [(&str, &str); 4] = [
    ("recgen-large.json", include_str!("../../models/recgen-large.json")),
    ("recgen-tiny.json", include_str!("../../models/recgen-tiny.json")),
    ("stereo_pose_stats.example.json", include_str!("../../models/stereo_pose_stats.example.json")),
    ("slat_pose_stats.example.json", include_str!("../../models/slat_pose_stats.example.json")),
];

/// `source` with its architecture file made explicit where it would be read from a
/// `models/` folder that the working folder does not have: the embedded copy, unpacked.
/// Every other source is returned as it is.
pub fn with_embedded_architecture(source: ModelSource) -> recon::Result<ModelSource> {
    let default = match &source {
        ModelSource::Random { config: None, .. } | ModelSource::Manifest { config: None, .. } => source.architecture()?,
        _ => return Ok(source),
    };
    let Some(name) = default.strip_prefix("models").ok().and_then(|f| f.to_str()).filter(|_| !default.is_file()) else {
        return Ok(source);
    };
    if !FILES.iter().any(|(f, _)| *f == name) {
        return Ok(source);
    }
    let config = Some(unpacked(&cache_root())?.join(name));
    Ok(match source {
        ModelSource::Random { seed, .. } => ModelSource::Random { config, seed },
        ModelSource::Manifest { name, cache, .. } => ModelSource::Manifest { name, config, cache },
        other => other,
    })
}

/// recon's cache folder (`$RECON_CACHE`, `$XDG_CACHE_HOME/recon`, `~/.cache/recon`), else
/// the temporary folder: where the embedded recgen-nano is unpacked too.
fn cache_root() -> PathBuf {
    recon::settings::current().cache_dir.unwrap_or_else(|| std::env::temp_dir().join("recon"))
}

/// The files under `root/architectures-<hash>/`, written beside and renamed into place so
/// that a half-written copy is never read (several processes may start at once).
fn unpacked(root: &Path) -> recon::Result<PathBuf> {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for (name, text) in FILES {
        for &b in name.as_bytes().iter().chain(text.as_bytes()) {
            h = (h ^ b as u64).wrapping_mul(0x100_0000_01b3);
        }
    }
    let dir = root.join(format!("architectures-{h:016x}"));
    if dir.join(FILES[0].0).is_file() {
        return Ok(dir);
    }
    let tmp = root.join(format!("architectures-{h:016x}.partial-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).map_err(|e| recon::Error::io(&tmp, e))?;
    for (name, text) in FILES {
        std::fs::write(tmp.join(name), text).map_err(|e| recon::Error::io(tmp.join(name), e))?;
    }
    match std::fs::rename(&tmp, &dir) {
        Ok(()) => Ok(dir),
        Err(_) if dir.join(FILES[0].0).is_file() => {
            let _ = std::fs::remove_dir_all(&tmp);
            Ok(dir)
        }
        Err(e) => Err(recon::Error::io(&dir, e)),
    }
}
