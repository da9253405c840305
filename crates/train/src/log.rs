//! The loss log (`loss.jsonl`: one JSON object per step) and its SVG plot.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::Path;

use recon_core::{Error, Result};

/// One logged step.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LogRecord {
    pub step: usize,
    pub loss: f64,
    /// Named loss terms (`mse`, `mse_pose`, `recon`, `kl`, ...).
    pub terms: BTreeMap<String, f64>,
    /// Other per-step facts (not plotted).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub info: BTreeMap<String, f64>,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    pub lr: f64,
    /// Seconds the step took (data + forward + backward + update).
    pub seconds: f64,
}

/// Read every record of a log (a missing file is an empty log).
pub fn read_log(path: &Path) -> Result<Vec<LogRecord>> {
    if !path.exists() {
        return Ok(Vec::new());
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| serde_json::from_str(l).map_err(|e| Error::input(path.display().to_string(), format!("line {}: {e}", i + 1))))
        .collect()
}

/// Keep the records up to `step` (a resumed run continues from there).
/// Kept lines are copied byte for byte (re-printing parsed floats could
/// change their last digit).
pub fn truncate_log(path: &Path, step: usize) -> Result<()> {
    if !path.exists() {
        return Ok(());
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut kept = String::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        #[derive(serde::Deserialize)]
        struct Step {
            step: usize,
        }
        let s: Step = serde_json::from_str(line).map_err(|e| Error::input(path.display().to_string(), format!("line {}: {e}", i + 1)))?;
        if s.step <= step {
            kept.push_str(line);
            kept.push('\n');
        }
    }
    std::fs::write(path, kept).map_err(|e| Error::io(path, e))
}

pub fn append_log(path: &Path, r: &LogRecord) -> Result<()> {
    let mut f = std::fs::OpenOptions::new().create(true).append(true).open(path).map_err(|e| Error::io(path, e))?;
    let line = serde_json::to_string(r).map_err(|e| Error::msg(e.to_string()))?;
    writeln!(f, "{line}").map_err(|e| Error::io(path, e))
}

/// Running mean over `w` records ending at each index.
fn smooth(v: &[f64], w: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(v.len());
    let mut acc = 0.0;
    for i in 0..v.len() {
        acc += v[i];
        if i >= w {
            acc -= v[i - w];
        }
        out.push(acc / (i + 1).min(w) as f64);
    }
    out
}

/// An SVG line plot of the loss (log scale): every step faint, a running
/// mean bold, one faint line per named term.
pub fn loss_svg(records: &[LogRecord], title: &str) -> String {
    let (w, h, ml, mr, mt, mb) = (720.0, 420.0, 70.0, 20.0, 40.0, 50.0);
    let mut s = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n");
    s += &format!("<text x=\"{}\" y=\"22\" text-anchor=\"middle\" font-size=\"14\">{}</text>\n", w / 2.0, xml_escape(title));
    let pts: Vec<(f64, f64)> = records.iter().filter(|r| r.loss.is_finite() && r.loss > 0.0).map(|r| (r.step as f64, r.loss)).collect();
    if pts.len() < 2 {
        s += &format!("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">not enough steps to plot</text>\n</svg>\n", w / 2.0, h / 2.0);
        return s;
    }
    let mut term_names: Vec<&String> = records.iter().flat_map(|r| r.terms.keys()).collect();
    term_names.sort();
    term_names.dedup();
    let all = pts.iter().map(|p| p.1).chain(records.iter().flat_map(|r| r.terms.values().copied()).filter(|v| v.is_finite() && *v > 0.0));
    let (mut lo, mut hi) = all.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    lo = lo.log10().floor();
    hi = hi.log10().ceil().max(lo + 1.0);
    let (x0, x1) = (pts[0].0, pts[pts.len() - 1].0.max(pts[0].0 + 1.0));
    let px = |x: f64| ml + (x - x0) / (x1 - x0) * (w - ml - mr);
    let py = |y: f64| mt + (hi - y.log10()) / (hi - lo) * (h - mt - mb);
    // Axes and decade grid.
    s += &format!("<line x1=\"{ml}\" y1=\"{}\" x2=\"{}\" y2=\"{}\" stroke=\"black\"/>\n", h - mb, w - mr, h - mb);
    s += &format!("<line x1=\"{ml}\" y1=\"{mt}\" x2=\"{ml}\" y2=\"{}\" stroke=\"black\"/>\n", h - mb);
    let mut d = lo;
    while d <= hi + 1e-9 {
        let y = py(10f64.powf(d));
        s += &format!("<line x1=\"{ml}\" y1=\"{y:.1}\" x2=\"{}\" y2=\"{y:.1}\" stroke=\"#ddd\"/>\n<text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">1e{d}</text>\n", w - mr, ml - 6.0, y + 4.0);
        d += 1.0;
    }
    for i in 0..=4 {
        let x = x0 + (x1 - x0) * i as f64 / 4.0;
        s += &format!("<text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{}</text>\n", px(x), h - mb + 18.0, x.round());
    }
    s += &format!("<text x=\"{}\" y=\"{}\" text-anchor=\"middle\">step</text>\n", (ml + w - mr) / 2.0, h - 10.0);
    let poly = |p: &[(f64, f64)], style: &str| -> String {
        let d: Vec<String> = p.iter().map(|(x, y)| format!("{:.1},{:.1}", px(*x), py(*y))).collect();
        format!("<polyline fill=\"none\" {style} points=\"{}\"/>\n", d.join(" "))
    };
    let palette = ["#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2"];
    for (i, name) in term_names.iter().enumerate() {
        let tp: Vec<(f64, f64)> =
            records.iter().filter_map(|r| r.terms.get(*name).filter(|v| v.is_finite() && **v > 0.0).map(|v| (r.step as f64, *v))).collect();
        let sm = smooth(&tp.iter().map(|p| p.1).collect::<Vec<_>>(), 50);
        let tp: Vec<(f64, f64)> = tp.iter().zip(sm).map(|(p, v)| (p.0, v)).collect();
        if tp.len() >= 2 {
            let c = palette[i % palette.len()];
            s += &poly(&tp, &format!("stroke=\"{c}\" stroke-width=\"1\""));
            s += &format!(
                "<text x=\"{}\" y=\"{}\" fill=\"{c}\">{} (mean of 50)</text>\n",
                w - mr - 150.0,
                mt + 16.0 * (i + 2) as f64,
                xml_escape(name)
            );
        }
    }
    s += &poly(&pts, "stroke=\"#1f77b4\" stroke-opacity=\"0.3\" stroke-width=\"1\"");
    let sm = smooth(&pts.iter().map(|p| p.1).collect::<Vec<_>>(), 50);
    let spts: Vec<(f64, f64)> = pts.iter().zip(sm).map(|(p, v)| (p.0, v)).collect();
    s += &poly(&spts, "stroke=\"#1f77b4\" stroke-width=\"2\"");
    s += &format!("<text x=\"{}\" y=\"{}\" fill=\"#1f77b4\">loss (mean of 50)</text>\n", w - mr - 150.0, mt + 16.0);
    s += "</svg>\n";
    s
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_round_trip_truncate_and_plot() -> Result<()> {
        let dir = recon_testkit::tmp("train-log");
        let p = dir.join("loss.jsonl");
        let _ = std::fs::remove_file(&p);
        for step in 1..=5 {
            let r = LogRecord {
                step,
                loss: 1.0 / step as f64,
                terms: [("mse".to_string(), 0.5 / step as f64)].into(),
                info: Default::default(),
                grad_norm: 1.0,
                lr: 1e-3,
                seconds: 0.1,
            };
            append_log(&p, &r)?;
        }
        assert_eq!(read_log(&p)?.len(), 5);
        truncate_log(&p, 3)?;
        let back = read_log(&p)?;
        assert_eq!(back.iter().map(|r| r.step).collect::<Vec<_>>(), vec![1, 2, 3]);
        let svg = loss_svg(&back, "a <test>");
        assert!(svg.starts_with("<svg") && svg.contains("polyline") && svg.contains("a &lt;test&gt;"));
        assert!(loss_svg(&back[..1], "x").contains("not enough"));
        std::fs::write(&p, "{not json\n").unwrap();
        assert!(read_log(&p).unwrap_err().to_string().contains("line 1"));
        let _ = std::fs::remove_dir_all(&dir);
        Ok(())
    }
}
