//! Structured logs: one JSON object per line on stderr (`event`: `listening`, `request`,
//! `job`, `recovered`, `shutdown`, …), with the Unix time in `ts`.

use std::io::Write;

/// Seconds since the Unix epoch.
pub(crate) fn now_unix() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

/// Writes one log line: `fields` (a JSON object) with `ts` and `event` added first.
pub(crate) fn log(event: &str, fields: serde_json::Value) {
    let mut line = serde_json::Map::new();
    line.insert("ts".into(), serde_json::json!((now_unix() * 1e3).round() / 1e3));
    line.insert("event".into(), serde_json::json!(event));
    if let serde_json::Value::Object(m) = fields {
        line.extend(m);
    }
    let text = serde_json::Value::Object(line).to_string();
    // A closed stderr must not take the server down.
    let _ = writeln!(std::io::stderr().lock(), "{text}");
}

/// Peak resident memory of the process so far, MiB (VmHWM), rounded to 0.1.
pub(crate) fn peak_mib() -> Option<f64> {
    recon_core::util::peak_rss_mib().map(|m| (m * 10.0).round() / 10.0)
}

/// Resident memory now, bytes (VmRSS of /proc/self/status).
pub(crate) fn rss_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse::<u64>().ok().map(|k| k << 10)
}
