//! Peak resident memory, for the per-stage figures of `recon infer` and the benches.

/// Peak resident memory of this process (VmHWM of /proc/self/status) in MiB;
/// `None` where the file is not available (non-Linux).
pub fn peak_rss_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Reset the peak-RSS high-water mark (Linux `clear_refs` 5), so the next
/// reading covers only what follows; a no-op where unsupported. Free heap
/// memory is first handed back to the OS (glibc `malloc_trim`): otherwise
/// memory freed by an earlier stage stays resident and the new mark starts
/// from it.
pub fn reset_peak_rss() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn malloc_trim(pad: usize) -> i32;
        }
        // SAFETY: glibc's malloc_trim only releases free memory; always safe to call.
        unsafe {
            malloc_trim(0);
        }
    }
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}
