//! File routes' paths: a request's path may only name a regular file inside its job's
//! folder (no `..`, no absolute path, no symbolic link anywhere on the way).

use std::path::{Path, PathBuf};

/// The file `rel` (`/`-separated, as in the URL) names under `root`, or `None` when it
/// would leave `root`, passes a symbolic link, or is not a regular file.
pub fn resolve(root: &Path, rel: &str) -> Option<PathBuf> {
    if rel.is_empty() || rel.contains(['\0', '\\']) {
        return None;
    }
    if std::fs::symlink_metadata(root).ok()?.file_type().is_symlink() {
        return None;
    }
    let mut p = root.to_path_buf();
    for comp in rel.split('/') {
        if comp.is_empty() || comp == "." || comp == ".." || comp.contains(':') {
            return None;
        }
        p.push(comp);
        let md = std::fs::symlink_metadata(&p).ok()?;
        if md.file_type().is_symlink() {
            return None;
        }
    }
    std::fs::symlink_metadata(&p).ok()?.file_type().is_file().then_some(p)
}

/// Every regular file under `root`, as `/`-separated relative paths, sorted; symbolic
/// links are left out (and not followed).
pub fn list_files(root: &Path) -> Vec<String> {
    fn walk(dir: &Path, prefix: &str, out: &mut Vec<String>, depth: usize) {
        let Ok(rd) = std::fs::read_dir(dir) else { return };
        let mut entries: Vec<_> = rd.flatten().collect();
        entries.sort_by_key(|e| e.file_name());
        for e in entries {
            let Ok(ft) = e.file_type() else { continue };
            let name = e.file_name().to_string_lossy().to_string();
            let rel = if prefix.is_empty() { name.clone() } else { format!("{prefix}/{name}") };
            if ft.is_file() {
                out.push(rel);
            } else if ft.is_dir() && depth < 8 {
                walk(&e.path(), &rel, out, depth + 1);
            }
        }
    }
    let mut out = Vec::new();
    walk(root, "", &mut out, 0);
    out
}

/// The content type of a served file, by extension.
pub fn content_type(path: &Path) -> &'static str {
    match path.extension().and_then(|e| e.to_str()).unwrap_or("") {
        "json" => "application/json",
        "glb" => "model/gltf-binary",
        "png" => "image/png",
        "usda" | "urdf" | "xml" | "mjcf" | "txt" => "text/plain; charset=utf-8",
        _ => "application/octet-stream",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_stay_inside_and_skip_links() {
        let d = recon_testkit::tmp("serve-paths");
        let root = d.join("out");
        std::fs::create_dir_all(root.join("a")).unwrap();
        std::fs::write(root.join("a/x.json"), "{}").unwrap();
        std::fs::write(d.join("secret"), "s").unwrap();
        std::os::unix::fs::symlink(d.join("secret"), root.join("link")).unwrap();
        std::os::unix::fs::symlink(&d, root.join("dirlink")).unwrap();
        assert_eq!(resolve(&root, "a/x.json"), Some(root.join("a/x.json")));
        for bad in ["", "a", "../secret", "a/../../secret", "/etc/passwd", "link", "dirlink/secret", "a//x.json", "./a/x.json", "a\\x.json"]
        {
            assert_eq!(resolve(&root, bad), None, "{bad}");
        }
        assert_eq!(list_files(&root), vec!["a/x.json".to_string()]);
        let _ = std::fs::remove_dir_all(&d);
    }
}
