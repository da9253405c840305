//! `LargeBufferCache`, the CLI's global allocator: a large buffer freed and
//! allocated again at the same size reuses its pages (no page faults), comes
//! back zeroed when asked, does not creep in resident memory over repeated
//! transformer-like blocks, and drops sizes that stop recurring.
//! Its own binary without the test harness: page faults and resident memory
//! are per process, so no other test may run meanwhile.

#[global_allocator]
static ALLOC: recon::util::LargeBufferCache = recon::util::LargeBufferCache;

const MIB: usize = 1 << 20;

/// Minor page faults of this process so far (field 10 of /proc/self/stat).
#[cfg(target_os = "linux")]
fn minor_faults() -> u64 {
    let s = std::fs::read_to_string("/proc/self/stat").expect("/proc/self/stat");
    let after = s.rsplit(')').next().unwrap();
    after.split_whitespace().nth(7).unwrap().parse().unwrap()
}

/// Anonymous resident memory (RssAnon of /proc/self/status) in bytes.
#[cfg(target_os = "linux")]
fn rss_anon() -> usize {
    let s = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let line = s.lines().find(|l| l.starts_with("RssAnon:")).expect("RssAnon");
    line.split_whitespace().nth(1).unwrap().parse::<usize>().unwrap() * 1024
}

/// Allocate `bytes`, write every page, return a checksum so nothing is elided.
fn touch(bytes: usize) -> u64 {
    let mut v = vec![0u8; bytes];
    for i in (0..v.len()).step_by(4096) {
        v[i] = 1;
    }
    std::hint::black_box(&v);
    v.iter().step_by(4096).map(|&b| b as u64).sum()
}

#[cfg(not(target_os = "linux"))]
fn main() {
    assert!(!recon::util::buffer_cache_active(), "the cache is Linux-only");
    println!("allocator: not Linux, the cache is off");
}

#[cfg(target_os = "linux")]
fn main() {
    use recon::util::{buffer_cache_active, cached_buffer_bytes, release_cached_buffers};
    if std::env::var_os("RECON_MALLOC").is_some_and(|v| v == "system") {
        assert!(!buffer_cache_active(), "RECON_MALLOC=system must turn the cache off");
        println!("allocator: RECON_MALLOC=system, cache off");
        return;
    }
    assert!(buffer_cache_active());

    // 1. Reuse: a fresh 64 MiB buffer faults its pages in; the same size again does not.
    release_cached_buffers();
    let f0 = minor_faults();
    touch(64 * MIB);
    let fresh = minor_faults() - f0;
    // One fault per 4 KiB page, or per 2 MiB where transparent huge pages are always on.
    assert!(fresh >= 16, "a fresh 64 MiB mapping should fault, saw {fresh} faults");
    assert!(cached_buffer_bytes() >= 64 * MIB, "the freed buffer is kept");
    let f1 = minor_faults();
    touch(64 * MIB);
    let reused = minor_faults() - f1;
    assert!(reused < fresh / 10, "reused buffer: {reused} faults vs {fresh} fresh");

    // 2. Zeroed on reuse: `vec![0; n]` over a kept buffer that held data.
    let mut v = vec![7u8; 48 * MIB];
    v[48 * MIB - 1] = 9;
    drop(std::hint::black_box(v));
    let z = vec![0u8; 48 * MIB];
    assert!(z.iter().all(|&b| b == 0), "a reused buffer must come back zeroed");
    drop(z);

    // 3. Growth across the threshold keeps the contents.
    let mut g: Vec<u32> = (0..1000).collect();
    g.resize(5 * MIB, 5);
    g.truncate(1000);
    g.shrink_to_fit();
    assert!(g.iter().enumerate().all(|(i, &x)| x == i as u32));
    let mut g: Vec<u32> = (0..(2 * MIB as u32)).collect();
    g.extend(std::iter::repeat_n(1, 6 * MIB));
    assert_eq!(g[2 * MIB - 1], 2 * MIB as u32 - 1);
    drop(g);

    // 4. Steady state: a block-like pattern (one residual stream, mixed
    //    short-lived sizes, all served by the cache) repeated does not grow
    //    resident memory.
    release_cached_buffers();
    let block = |x: Vec<f32>| -> Vec<f32> {
        let n = x.len();
        let h: Vec<f32> = x.iter().map(|v| v * 0.5).collect();
        let qkv = vec![1f32; 3 * n];
        let packs = vec![2u32; n + n / 20];
        let o: Vec<f32> = h.iter().zip(&qkv).map(|(a, b)| a + b).collect();
        drop((qkv, packs, h));
        let kv = vec![0.5f32; n + n / 3];
        let x1: Vec<f32> = x.iter().zip(&o).zip(&kv).map(|((a, b), c)| a + b * c).collect();
        drop((o, kv, x));
        let hidden = vec![0.25f32; n];
        x1.iter().zip(&hidden).map(|(a, b)| a - b).collect()
    };
    let n = 20 * MIB / 4;
    let mut x = vec![0f32; n];
    for _ in 0..3 {
        x = block(x);
    }
    let settled = rss_anon();
    for _ in 0..30 {
        x = block(x);
    }
    let after = rss_anon();
    assert!(after <= settled + 4 * MIB, "resident memory crept over 30 blocks: {} → {} MiB", settled / MIB, after / MIB);
    drop(x);

    // 5. When the sizes change, new buffers are paid for with kept ones:
    //    resident memory after the switch stays within the old sizes' peak.
    release_cached_buffers();
    let phase = |mib: usize, rounds: usize| {
        for _ in 0..rounds {
            let a: Vec<Vec<u8>> = (0..4).map(|i| vec![1u8; (mib + i) * MIB]).collect();
            drop(std::hint::black_box(a));
        }
    };
    phase(40, 3);
    let big = rss_anon();
    phase(20, 3);
    let small = rss_anon();
    assert!(small <= big + 4 * MIB, "switching sizes grew resident memory: {} → {} MiB", big / MIB, small / MIB);

    // 6. A size that stops recurring is unmapped after later large requests.
    release_cached_buffers();
    drop(std::hint::black_box(vec![1u8; 40 * MIB]));
    assert!(cached_buffer_bytes() >= 40 * MIB);
    for _ in 0..100 {
        drop(std::hint::black_box(vec![1u8; 17 * MIB]));
    }
    assert!(cached_buffer_bytes() < 40 * MIB, "a stale 40 MiB buffer is still kept ({} MiB kept)", cached_buffer_bytes() / MIB);
    let released = release_cached_buffers();
    assert_eq!(cached_buffer_bytes(), 0);
    assert!(released >= 17 * MIB);

    // 7. fork while other threads hold the cache's lock in a tight loop: every
    //    child can still allocate a large buffer (the lock is taken around fork).
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let churn: Vec<_> = (0..2)
        .map(|_| {
            let stop = stop.clone();
            std::thread::spawn(move || {
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    drop(std::hint::black_box(Vec::<u8>::with_capacity(17 * MIB)));
                }
            })
        })
        .collect();
    let forks = 100;
    for _ in 0..forks {
        // SAFETY: the child only allocates, frees and exits.
        let pid = unsafe { libc::fork() };
        assert!(pid >= 0, "fork failed");
        if pid == 0 {
            let v = vec![0u8; 18 * MIB];
            let code = if v[18 * MIB - 1] == 0 { 0 } else { 3 };
            drop(v);
            // SAFETY: leave the child without running the parent's exit handlers.
            unsafe { libc::_exit(code) };
        }
        let t = std::time::Instant::now();
        loop {
            let mut status = 0;
            // SAFETY: waits on our own child.
            let r = unsafe { libc::waitpid(pid, &mut status, libc::WNOHANG) };
            if r == pid {
                assert!(libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0, "child exited with {status}");
                break;
            }
            if t.elapsed() > std::time::Duration::from_secs(20) {
                // SAFETY: our own child.
                unsafe { libc::kill(pid, libc::SIGKILL) };
                panic!("a child forked while the cache's lock was held never got a large buffer");
            }
            std::thread::sleep(std::time::Duration::from_millis(1));
        }
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    churn.into_iter().for_each(|t| t.join().unwrap());

    println!(
        "allocator: {forks} forks under contention, every child allocated; 64 MiB reallocated: {fresh} page faults fresh, {reused} reused; 30 blocks: resident {} → {} MiB",
        settled / MIB,
        after / MIB
    );
}
