//! Helpers shared by the benchmarks in `benches/`.

/// Peak resident memory of this process (VmHWM of /proc/self/status) in MiB;
/// `None` where the file is not available (non-Linux).
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Reset the peak-RSS high-water mark (Linux `clear_refs` 5), so the next
/// reading covers only what follows; a no-op where unsupported.
pub fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}
