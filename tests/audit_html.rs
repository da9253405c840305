//! `recon audit`'s HTML report, opened in a real headless browser (Chromium).
//!
//! A small `recon synth` dataset with a bias planted linear in image u is audited and its
//! outputs written; the page must reference only files that exist, show the findings,
//! mechanism, before/after and maps sections, and, loaded in Chromium, raise no error and display every
//! image. A page with a broken image is checked the same way and must be caught, so the browser
//! check can fail. Without a browser the browser part is skipped (with a message), unless
//! `RECON_REQUIRE_BROWSER=1` (CI) makes that a failure. `RECON_CHROMIUM` names the binary.
mod common;

use common::tmp;
use recon::audit::{audit_depth_frames, collect, residual_table, write_outputs, DepthOptions, MechanismOptions, SearchOptions};
use recon::sensor::{Covariate, Effect, Form, SensorModel, Target};
use recon::synth::{generate, SynthOptions};
use std::path::{Path, PathBuf};
use std::process::Command;

fn chromium() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("RECON_CHROMIUM") {
        return Some(PathBuf::from(p));
    }
    ["chromium", "chromium-browser", "google-chrome", "google-chrome-stable"]
        .iter()
        .find_map(|name| std::env::var_os("PATH")?.to_str()?.split(':').map(|d| Path::new(d).join(name)).find(|p| p.is_file()))
}

/// Loads `page` (a copy with a checking script injected first in <head>) and returns what the
/// script saw after the load event: JS/resource errors, images and whether each rendered,
/// tables and findings rows.
fn browser_check(browser: &Path, page: &Path) -> serde_json::Value {
    let html = std::fs::read_to_string(page).unwrap();
    let script = r#"<script>
window.__errors = [];
window.addEventListener('error', e => { __errors.push(e.message || ('resource: ' + ((e.target && (e.target.src || e.target.href)) || '?'))); }, true);
window.addEventListener('load', () => {
  const imgs = [...document.images];
  const out = document.createElement('pre');
  out.id = 'recon-check';
  out.textContent = JSON.stringify({
    errors: __errors,
    images: imgs.length,
    broken: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).map(i => i.getAttribute('src')),
    tables: [...document.querySelectorAll('table')].map(t => t.id),
    findings_rows: document.querySelectorAll('#findings tbody tr').length,
  });
  document.body.appendChild(out);
});
</script>"#;
    let checked = page.with_file_name("check.html");
    std::fs::write(&checked, html.replacen("<head>", &format!("<head>{script}"), 1)).unwrap();
    let profile = page.with_file_name("chromium-profile");
    let out = Command::new(browser)
        .args([
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-dev-shm-usage",
            "--no-first-run",
            "--allow-file-access-from-files",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(["--virtual-time-budget=10000", "--dump-dom"])
        .arg(format!("file://{}", checked.display()))
        .output()
        .expect("running the browser");
    let dom = String::from_utf8_lossy(&out.stdout);
    let start = dom.find("<pre id=\"recon-check\">").unwrap_or_else(|| {
        panic!("no check result in the browser's DOM (exit {:?}); stderr:\n{}", out.status, String::from_utf8_lossy(&out.stderr))
    });
    let rest = &dom[start + "<pre id=\"recon-check\">".len()..];
    let text = &rest[..rest.find("</pre>").unwrap()];
    let text = text.replace("&quot;", "\"").replace("&lt;", "<").replace("&gt;", ">").replace("&amp;", "&");
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("check result {text}: {e}"))
}

#[test]
fn html_report_loads_in_a_browser_with_its_tables_plots_and_maps() {
    let dir = tmp("audit-html");
    let data = dir.join("data");
    let audited = SensorModel::stereo_default();
    let mut truth = audited.clone();
    // 9.6 mm across the 160-px image, well above this sensor's noise; 12 frames, so the
    // sign-flip test over held-out frames can reach the default alpha.
    truth.effects.push(Effect { target: Target::Bias, covariate: Covariate::U, form: Form::Linear { slope: 6e-5 }, by: None, cause: None });
    let opts = SynthOptions { scenes: 4, views: 3, seed: 7, width: 160, height: 120, parts: false, sensor: truth };
    generate(&data, &opts, &|| {}).unwrap();
    let col = collect(&data, &audited, &DepthOptions { max_pixels_per_frame: 1200, seed: 0, max_frames: None }).unwrap();
    let table = residual_table(&audited, &col.pixels, "planted u bias");
    let opts = SearchOptions::default();
    let mut audit = audit_depth_frames(&table, &opts, &audited, &col.sims, &MechanismOptions::from_search(&opts)).unwrap();
    assert!(
        audit.report.findings.iter().any(|f| f.target == "bias" && f.covariate == "u"),
        "the planted bias ~ u is not among the findings:\n{}",
        audit.report.summary()
    );
    let out = dir.join("out");
    write_outputs(&mut audit, &out, None).unwrap();
    let page = out.join("report.html");
    let html = std::fs::read_to_string(&page).unwrap();

    // Every file the page links exists in the output folder; the sections are there.
    let mut linked = vec![];
    for attr in ["src=\"", "href=\""] {
        for (i, _) in html.match_indices(attr) {
            let rest = &html[i + attr.len()..];
            linked.push(rest[..rest.find('"').unwrap()].to_string());
        }
    }
    assert!(linked.iter().any(|l| l.starts_with("maps/")), "no residual map linked");
    assert!(linked.iter().any(|l| l.starts_with("plots/partial")), "no partial-residual plot linked");
    for l in &linked {
        assert!(out.join(l).is_file(), "report.html links {l}, which is not in {}", out.display());
    }
    for id in ["summary", "findings", "mechanism-verdict", "mechanism-comparison", "before-after", "maps", "plots"] {
        assert!(html.contains(&format!("id=\"{id}\"")), "report.html lacks #{id}");
    }

    let Some(browser) = chromium() else {
        assert!(
            std::env::var("RECON_REQUIRE_BROWSER").as_deref() != Ok("1"),
            "RECON_REQUIRE_BROWSER=1 but no chromium / google-chrome on PATH (or RECON_CHROMIUM)"
        );
        eprintln!("skipping the browser check: no chromium / google-chrome on PATH");
        return;
    };
    let seen = browser_check(&browser, &page);
    assert_eq!(seen["errors"], serde_json::json!([]), "errors while loading report.html: {seen}");
    assert_eq!(seen["broken"], serde_json::json!([]), "images that did not render: {seen}");
    assert_eq!(seen["images"].as_u64().unwrap() as usize, linked.iter().filter(|l| l.ends_with(".png") || l.ends_with(".svg")).count());
    assert_eq!(seen["findings_rows"].as_u64().unwrap() as usize, audit.report.findings.len(), "{seen}");
    let tables: Vec<&str> = seen["tables"].as_array().unwrap().iter().filter_map(|t| t.as_str()).collect();
    for t in ["findings", "mechanism-comparison", "before-after"] {
        assert!(tables.contains(&t), "table #{t} not in the loaded page: {seen}");
    }

    // The same check on a page with one missing image must report it.
    let broken = out.join("broken.html");
    std::fs::write(&broken, html.replacen("src=\"maps/", "src=\"maps/missing-", 1)).unwrap();
    let seen = browser_check(&browser, &broken);
    assert_eq!(seen["broken"].as_array().map(|b| b.len()), Some(1), "the broken image was not caught: {seen}");
    let _ = std::fs::remove_dir_all(&dir);
}
