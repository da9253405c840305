//! `keep_freed_memory` (the CLI's default): a large buffer freed and then
//! allocated again is served from the heap, not from freshly faulted pages.
//! Its own binary without the test harness: the check must run on the main
//! thread (glibc serves other threads' large buffers from mmap whatever the
//! thresholds), with no other test faulting pages meanwhile.

/// Minor page faults of this process so far (field 10 of /proc/self/stat).
fn minor_faults() -> u64 {
    let s = std::fs::read_to_string("/proc/self/stat").expect("/proc/self/stat");
    let after = s.rsplit(')').next().unwrap();
    after.split_whitespace().nth(7).unwrap().parse().unwrap()
}

fn touch(mib: usize) -> u64 {
    let mut v = vec![0u8; mib << 20];
    for i in (0..v.len()).step_by(4096) {
        v[i] = 1;
    }
    std::hint::black_box(&v);
    v.iter().step_by(4096).map(|&b| b as u64).sum()
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn main() {
    println!("allocator: not glibc on Linux, nothing to check");
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn main() {
    // glibc's defaults: a 64 MiB buffer is mmapped, so every allocation faults in all its pages.
    touch(64);
    let f0 = minor_faults();
    touch(64);
    let default_faults = minor_faults() - f0;
    // One fault per 4 KiB page, or per 2 MiB where transparent huge pages are always on.
    assert!(default_faults >= 16, "expected glibc to fault in a fresh 64 MiB buffer, saw {default_faults} faults");

    assert!(recon::util::keep_freed_memory(), "glibc refused the thresholds");
    assert!(recon::util::freed_memory_kept());
    touch(64);
    let f1 = minor_faults();
    touch(64);
    let kept_faults = minor_faults() - f1;
    assert!(kept_faults < default_faults / 10, "kept heap: {kept_faults} faults vs {default_faults} with glibc's defaults");
    println!("allocator: 64 MiB reallocated: {default_faults} page faults with glibc's defaults, {kept_faults} with freed memory kept");
}
