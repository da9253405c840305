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
/// memory is first handed back to the OS (kept large buffers, and glibc's
/// `malloc_trim`): otherwise memory freed by an earlier stage stays resident
/// and the new mark starts from it.
pub fn reset_peak_rss() {
    super::buffer_cache::release_cached_buffers();
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

/// Keep large freed buffers in the heap for reuse instead of returning them
/// to the OS (glibc `mallopt`: mmap and trim thresholds at 1 GiB). By
/// default glibc serves every buffer above 32 MiB, such as one activation of
/// a full-size transformer block, with fresh pages that are faulted in and
/// zeroed on each allocation, kernel time on every step
/// (docs/performance.md). The cost is a few percent more peak
/// resident memory (freed holes are reused, not unmapped). Returns whether
/// the allocator took both settings; `false` (and nothing changed) off glibc.
pub fn keep_freed_memory() -> bool {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn mallopt(param: i32, value: i32) -> i32;
        }
        const M_TRIM_THRESHOLD: i32 = -1;
        const M_MMAP_THRESHOLD: i32 = -3;
        // SAFETY: mallopt only changes allocator thresholds; called before any
        // worker threads exist, and valid at any time in glibc anyway.
        let ok = unsafe { mallopt(M_MMAP_THRESHOLD, 1 << 30) == 1 && mallopt(M_TRIM_THRESHOLD, 1 << 30) == 1 };
        KEPT.store(ok, std::sync::atomic::Ordering::Relaxed);
        ok
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    false
}

static KEPT: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Whether [`keep_freed_memory`] is in effect in this process (reports
/// record it: it changes both time and peak memory).
pub fn freed_memory_kept() -> bool {
    KEPT.load(std::sync::atomic::Ordering::Relaxed)
}
