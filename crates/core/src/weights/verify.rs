//! `recon weights verify DIR`: check that a directory holds a manifest's
//! files and that every checkpoint with a known tensor list matches it.

use crate::model::config::ModuleArgs;
use crate::weights::load::Checkpoint;
use crate::weights::manifest::Manifest;
use crate::weights::registry::{expected_tensors, ModuleConfig, ModuleKind};
use crate::weights::validate::compare;
use crate::Result;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

/// One row of `recon weights verify`: a manifest file and what its check found.
#[derive(Debug, Clone, PartialEq)]
pub struct VerifyRow {
    /// The file's path in the manifest.
    pub file: String,
    /// Whether the file exists.
    pub present: bool,
    /// File size in bytes (0 when absent).
    pub bytes: u64,
    /// `None` when no tensor list is known for the file.
    pub tensors: Option<(usize, usize)>, // (matched, expected)
    /// Whether the file passes (an absent optional file does).
    pub ok: bool,
    /// What the check found, in words.
    pub detail: String,
}

/// Check every manifest file under `dir` (or the HF-cache snapshot in it).
pub fn verify_dir(m: &Manifest, dir: &Path) -> Result<Vec<VerifyRow>> {
    let root = m.resolve_dir(dir);
    let mut rows = Vec::new();
    for f in &m.files {
        let mut p = root.join(&f.path);
        if !p.exists() && m.source == "url" {
            p = m.expected_path(dir, f); // e.g. torch.hub's own copy
        }
        let meta = std::fs::metadata(&p).ok();
        let mut row = VerifyRow {
            file: f.path.clone(),
            present: meta.is_some(),
            bytes: meta.map(|m| m.len()).unwrap_or(0),
            tensors: None,
            ok: false,
            detail: String::new(),
        };
        if !row.present {
            row.ok = f.optional;
            row.detail = if f.optional { "absent (optional)".into() } else { "MISSING".into() };
            rows.push(row);
            continue;
        }
        // A pinned SHA-256 is checked whatever the kind.
        let sha = f.sha256.as_ref().map(|pin| match crate::weights::hf_cache::sha256_file(&p) {
            Ok(h) if h.eq_ignore_ascii_case(pin.trim()) => Ok(()),
            Ok(h) => Err(format!("SHA-256 MISMATCH: {h}, the manifest pins {pin}")),
            Err(e) => Err(format!("cannot hash: {e}")),
        });
        // Without a stored list, derive one from the module's config file
        // when the registry knows the module.
        let derived = match (&f.tensors, &f.module, &f.config) {
            (None, Some(module), Some(cfg)) => derive_expected(module, &root.join(cfg)),
            _ => None,
        };
        match f.tensors.as_ref().or(derived.as_ref()) {
            None => {
                row.ok = true;
                row.detail = match f.kind.as_str() {
                    "json" => match crate::util::json::read_json::<serde_json::Value>(&p) {
                        Ok(_) => "present (valid JSON)".into(),
                        Err(e) => {
                            row.ok = false;
                            format!("invalid: {e}")
                        }
                    },
                    _ => "present (no tensor list: module not in the crate)".into(),
                };
            }
            Some(expected) => match Checkpoint::open(&p, f.pt_key.as_deref()) {
                Err(e) => row.detail = format!("cannot open: {e}"),
                Ok(ck) => {
                    let found: BTreeMap<String, Vec<usize>> = ck.tensors().into_iter().map(|(k, v)| (k, v.shape)).collect();
                    let r = compare(expected, &found, f.allow_unexpected);
                    row.tensors = Some((r.matched, expected.len()));
                    row.ok = r.is_ok();
                    row.detail = if r.is_ok() {
                        let extra = found.len().saturating_sub(r.matched);
                        if extra > 0 {
                            format!("ok ({extra} extra tensors tolerated)")
                        } else {
                            "ok".into()
                        }
                    } else {
                        let mut parts = Vec::new();
                        if let Some(s) = r.missing.first() {
                            parts.push(format!("{} missing (first `{}` {:?})", r.missing.len(), s.name, s.shape));
                        }
                        if let Some((n, got, want)) = r.mismatched.first() {
                            parts.push(format!("{} wrong shape (first `{n}` {got:?} vs {want:?})", r.mismatched.len()));
                        }
                        if let Some(n) = r.unexpected.first() {
                            parts.push(format!("{} unexpected (first `{n}`)", r.unexpected.len()));
                        }
                        parts.join("; ")
                    };
                }
            },
        }
        match sha {
            Some(Err(msg)) => {
                row.ok = false;
                row.detail = format!("{msg}; {}", row.detail);
            }
            Some(Ok(())) => row.detail.push_str(", sha256 ok"),
            None => {}
        }
        rows.push(row);
    }
    Ok(rows)
}

/// Expected tensors of `module` from its config file: a module config
/// (`{"name", "args"}`) or a training config whose `models` map holds an
/// entry for a known class. `None` when the file is absent or not usable.
fn derive_expected(module: &str, config: &Path) -> Option<Vec<crate::weights::record::TensorSpec>> {
    ModuleKind::of(module)?;
    let v: serde_json::Value = crate::util::json::read_json(config).ok()?;
    let spec = if v.get("args").is_some() {
        v
    } else {
        v.get("models")?.as_object()?.values().find(|m| m.get("name").and_then(|n| n.as_str()).and_then(ModuleKind::of).is_some())?.clone()
    };
    let cfg: ModuleConfig = serde_json::from_value(spec).ok()?;
    let file = config.display().to_string();
    expected_tensors(&ModuleArgs::from_spec(&cfg, &file).ok()?, &file).ok()
}

/// Write `rows` as the verify table, headed by the manifest and its folder, to `out` (write errors ignored).
pub fn print_table(m: &Manifest, dir: &Path, rows: &[VerifyRow], out: &mut dyn Write) {
    let _ = writeln!(out, "manifest {} ({}) in {}", m.name, m.repo.as_deref().unwrap_or(&m.source), m.resolve_dir(dir).display());
    let _ = writeln!(out, "{:<70} {:>14} {:>13}  {:<4}  detail", "file", "bytes", "tensors", "ok");
    for r in rows {
        let t = r.tensors.map(|(a, b)| format!("{a}/{b}")).unwrap_or_else(|| "-".into());
        let _ = writeln!(out, "{:<70} {:>14} {:>13}  {:<4}  {}", r.file, r.bytes, t, if r.ok { "OK" } else { "FAIL" }, r.detail);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A manifest entry without a stored tensor list is checked against the
    /// list its module config implies.
    #[test]
    fn tensor_list_derived_from_module_config() -> Result<()> {
        let dir = crate::util::testing::tmp("verify-derive");
        let cfg = serde_json::json!({"name": "SparseStructureDecoder", "args": {
            "out_channels": 1, "latent_channels": 4, "num_res_blocks": 1, "num_res_blocks_middle": 1, "channels": [16, 8]}});
        let cfg_path = dir.join("ss_dec.json");
        std::fs::write(&cfg_path, cfg.to_string()).map_err(|e| crate::Error::io(&cfg_path, e))?;
        crate::weights::init::write_random_init(&cfg_path, &dir, 1)?;
        let m = Manifest::parse(
            r#"{"name": "t", "source": "url", "files": [{"path": "ss_dec.safetensors", "kind": "safetensors",
                "url": "x", "module": "SparseStructureDecoder", "config": "ss_dec.json", "tensors_note": "derived"}]}"#,
            "t",
        )?;
        let rows = verify_dir(&m, &dir)?;
        let (matched, want) = rows[0].tensors.expect("derived tensor list");
        assert!(rows[0].ok && matched == want && want > 10, "{:?}", rows[0]);
        // A checkpoint of another shape fails.
        let other = serde_json::json!({"name": "SparseStructureDecoder", "args": {
            "out_channels": 1, "latent_channels": 4, "num_res_blocks": 1, "num_res_blocks_middle": 1, "channels": [8, 8]}});
        std::fs::write(&cfg_path, other.to_string()).map_err(|e| crate::Error::io(&cfg_path, e))?;
        let rows = verify_dir(&m, &dir)?;
        assert!(!rows[0].ok && rows[0].detail.contains("wrong shape"), "{:?}", rows[0]);
        let _ = std::fs::remove_dir_all(&dir);
        Ok(())
    }
}
