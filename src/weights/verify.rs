//! `recon weights verify DIR`: check that a directory holds a manifest's
//! files and that every checkpoint with a known tensor list matches it.

use super::load::Checkpoint;
use super::manifest::Manifest;
use super::validate::compare;
use crate::Result;
use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

#[derive(Debug, Clone, PartialEq)]
pub struct VerifyRow {
    pub file: String,
    pub present: bool,
    pub bytes: u64,
    /// `None` when no tensor list is known for the file.
    pub tensors: Option<(usize, usize)>, // (matched, expected)
    pub ok: bool,
    pub detail: String,
}

/// Check every manifest file under `dir` (or the HF-cache snapshot in it).
pub fn verify_dir(m: &Manifest, dir: &Path) -> Result<Vec<VerifyRow>> {
    let root = m.resolve_dir(dir);
    let mut rows = Vec::new();
    for f in &m.files {
        let p = root.join(&f.path);
        let meta = std::fs::metadata(&p).ok();
        let mut row = VerifyRow { file: f.path.clone(), present: meta.is_some(), bytes: meta.map(|m| m.len()).unwrap_or(0), tensors: None, ok: false, detail: String::new() };
        if !row.present {
            row.ok = f.optional;
            row.detail = if f.optional { "absent (optional)".into() } else { "MISSING".into() };
            rows.push(row);
            continue;
        }
        match &f.tensors {
            None => {
                row.ok = true;
                row.detail = match f.kind.as_str() {
                    "json" => match crate::config::read_json::<serde_json::Value>(&p) {
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
                        if extra > 0 { format!("ok ({extra} extra tensors tolerated)") } else { "ok".into() }
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
        rows.push(row);
    }
    Ok(rows)
}

pub fn print_table(m: &Manifest, dir: &Path, rows: &[VerifyRow], out: &mut dyn Write) {
    let _ = writeln!(out, "manifest {} ({}) in {}", m.name, m.repo.as_deref().unwrap_or(&m.source), m.resolve_dir(dir).display());
    let _ = writeln!(out, "{:<70} {:>14} {:>13}  {:<4}  detail", "file", "bytes", "tensors", "ok");
    for r in rows {
        let t = r.tensors.map(|(a, b)| format!("{a}/{b}")).unwrap_or_else(|| "-".into());
        let _ = writeln!(out, "{:<70} {:>14} {:>13}  {:<4}  {}", r.file, r.bytes, t, if r.ok { "OK" } else { "FAIL" }, r.detail);
    }
}
