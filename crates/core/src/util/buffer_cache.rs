//! A global allocator that reuses large buffers by size.
//!
//! A full-size transformer block allocates the same few large activations
//! (33.5 MB rows, 100 MB q/k/v, …) in every block and every sampler step.
//! glibc serves each one above 32 MiB with a fresh mapping, faulted in and
//! zeroed page by page (CPU time in the kernel on every step; docs/performance.md);
//! keeping freed memory in glibc's heap instead avoids that but fragments
//! the heap, raising peak resident memory by ~15 % of the live data.
//!
//! [`LargeBufferCache`] gives every buffer of at least [`LARGE_BYTES`] its
//! own mapping and, when it is freed, keeps the mapping for the next request
//! of exactly the same page-rounded size (which the next block makes). Kept
//! buffers are unmapped, oldest first, beyond [`CACHE_BYTES`], when their
//! size has not recurred for a while, and to pay for a new mapping; all are
//! released by [`release_cached_buffers`] at stage boundaries. Smaller
//! buffers go to the system allocator unchanged.
//!
//! `RECON_MALLOC=system` in the environment turns the cache off (read once,
//! at the first large request, so a buffer is always freed the way it was
//! allocated).

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::UnsafeCell;
use std::sync::atomic::{AtomicBool, AtomicU8, AtomicUsize, Ordering};

/// Smallest buffer served by the cache.
pub const LARGE_BYTES: usize = 16 << 20;
/// Most bytes of freed buffers kept for reuse.
pub const CACHE_BYTES: usize = 384 << 20;
/// A kept buffer not reused within this many later large requests is
/// unmapped: its size is not recurring (a model's build temporaries), and
/// holding it would only add to resident memory. A transformer block makes
/// about 20 large requests, so its sizes recur well within this.
const STALE_AFTER: usize = 24;
const SLOTS: usize = 64;
const PAGE: usize = 4096;

/// Install with `#[global_allocator] static A: LargeBufferCache = LargeBufferCache;`.
pub struct LargeBufferCache;

#[derive(Clone, Copy)]
struct Slot {
    addr: usize,
    bytes: usize,
    /// SERVED when it was kept (its age in large requests).
    kept_at: usize,
}

const EMPTY: Slot = Slot { addr: 0, bytes: 0, kept_at: 0 };

struct Kept {
    /// Oldest first.
    slots: [Slot; SLOTS],
    len: usize,
    bytes: usize,
}

/// The kept buffers behind a spin lock: critical sections are a scan of at
/// most `SLOTS` entries, and unlike a `Mutex` the lock can be taken and
/// released around `fork` (a child forked while another thread held it would
/// otherwise wait forever on its first large buffer).
struct Locked(UnsafeCell<Kept>);
// SAFETY: the cell is only reached through `kept()`, which holds LOCK.
unsafe impl Sync for Locked {}
static KEPT: Locked = Locked(UnsafeCell::new(Kept { slots: [EMPTY; SLOTS], len: 0, bytes: 0 }));
static LOCK: AtomicBool = AtomicBool::new(false);

fn lock() {
    let mut spins = 0u32;
    while LOCK.compare_exchange_weak(false, true, Ordering::Acquire, Ordering::Relaxed).is_err() {
        spins += 1;
        if spins < 64 {
            std::hint::spin_loop();
        } else {
            std::thread::yield_now();
        }
    }
}

fn unlock() {
    LOCK.store(false, Ordering::Release);
}

struct KeptGuard;

impl std::ops::Deref for KeptGuard {
    type Target = Kept;
    fn deref(&self) -> &Kept {
        // SAFETY: LOCK is held for the guard's lifetime.
        unsafe { &*KEPT.0.get() }
    }
}

impl std::ops::DerefMut for KeptGuard {
    fn deref_mut(&mut self) -> &mut Kept {
        // SAFETY: LOCK is held for the guard's lifetime, and there is one guard.
        unsafe { &mut *KEPT.0.get() }
    }
}

impl Drop for KeptGuard {
    fn drop(&mut self) {
        unlock();
    }
}

#[cfg(target_os = "linux")]
fn hold_lock_across_fork() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    extern "C" fn prepare() {
        lock();
    }
    extern "C" fn release() {
        unlock();
    }
    // SAFETY: registers plain functions that take and release the spin lock.
    ONCE.call_once(|| unsafe {
        libc::pthread_atfork(Some(prepare), Some(release), Some(release));
    });
}

const UNDECIDED: u8 = 0;
const ON: u8 = 1;
const OFF: u8 = 2;
static MODE: AtomicU8 = AtomicU8::new(UNDECIDED);
/// Large requests served so far (kept or new), for [`buffer_cache_active`].
static SERVED: AtomicUsize = AtomicUsize::new(0);

fn cache_on() -> bool {
    match MODE.load(Ordering::Acquire) {
        ON => true,
        OFF => false,
        _ => {
            let off = system_requested();
            // The first decision wins, so every thread sees one mode for good.
            let _ = MODE.compare_exchange(UNDECIDED, if off { OFF } else { ON }, Ordering::AcqRel, Ordering::Acquire);
            MODE.load(Ordering::Acquire) == ON
        }
    }
}

/// `RECON_MALLOC=system`, read without allocating (we are inside the allocator).
/// The one variable read outside `crate::settings::Settings::from_env`: the
/// global allocator serves allocations made before `main` (and, in the Python
/// module, before its init), so its mode cannot wait for settings to be
/// applied. It is listed in the settings table.
fn system_requested() -> bool {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: getenv with a NUL-terminated name; the result is read-only and
        // NUL-terminated, compared before any other environment access.
        let v = unsafe { libc::getenv(c"RECON_MALLOC".as_ptr()) };
        !v.is_null() && unsafe { std::ffi::CStr::from_ptr(v) }.to_bytes() == b"system"
    }
    #[cfg(not(target_os = "linux"))]
    true
}

fn large(layout: &Layout) -> bool {
    layout.size() >= LARGE_BYTES && layout.align() <= PAGE && cache_on()
}

fn rounded(size: usize) -> usize {
    size.div_ceil(PAGE) * PAGE
}

fn kept() -> KeptGuard {
    #[cfg(target_os = "linux")]
    hold_lock_across_fork();
    lock();
    KeptGuard
}

#[cfg(target_os = "linux")]
fn map(bytes: usize) -> *mut u8 {
    // SAFETY: a fresh private anonymous mapping; failure is reported as null.
    let p = unsafe {
        libc::mmap(std::ptr::null_mut(), bytes, libc::PROT_READ | libc::PROT_WRITE, libc::MAP_PRIVATE | libc::MAP_ANONYMOUS, -1, 0)
    };
    if p == libc::MAP_FAILED {
        std::ptr::null_mut()
    } else {
        p as *mut u8
    }
}

#[cfg(target_os = "linux")]
fn unmap(addr: usize, bytes: usize) {
    // SAFETY: a whole mapping made by `map` and no longer handed out.
    unsafe { libc::munmap(addr as *mut libc::c_void, bytes) };
}

// Off Linux the cache is never on (`system_requested`), so these are not reached.
#[cfg(not(target_os = "linux"))]
fn map(_bytes: usize) -> *mut u8 {
    std::ptr::null_mut()
}
#[cfg(not(target_os = "linux"))]
fn unmap(_addr: usize, _bytes: usize) {}

/// A kept buffer of exactly `bytes`, or a new mapping; `fresh` says whether
/// its memory is known to be zero.
fn take(bytes: usize) -> (*mut u8, bool) {
    let served = SERVED.fetch_add(1, Ordering::Relaxed) + 1;
    let mut evicted = Evicted::default();
    let found = {
        let mut k = kept();
        let found = k.slots[..k.len].iter().position(|s| s.bytes == bytes).map(|i| k.remove(i).addr);
        k.evict(&mut evicted, |s| s.kept_at + STALE_AFTER < served);
        if found.is_none() {
            // A new mapping is paid for with kept ones (oldest first): when the
            // sizes change (a sampler's guided steps give way to unguided
            // ones, a decoder moves to the next resolution) the old sizes'
            // buffers would otherwise sit beside the new ones until stale.
            let mut need = bytes;
            k.evict(&mut evicted, |s| {
                let go = need > 0;
                need = need.saturating_sub(s.bytes);
                go
            });
        }
        found
    };
    evicted.unmap();
    match found {
        Some(addr) => (addr as *mut u8, false),
        None => (map(bytes), true),
    }
}

fn give_back(addr: usize, bytes: usize) {
    if bytes > CACHE_BYTES {
        unmap(addr, bytes);
        return;
    }
    let served = SERVED.load(Ordering::Relaxed);
    let mut evicted = Evicted::default();
    {
        let mut k = kept();
        // Oldest first, until the new one fits.
        let mut need = (k.len + 1).saturating_sub(SLOTS);
        let mut over = (k.bytes + bytes).saturating_sub(CACHE_BYTES);
        k.evict(&mut evicted, |s| {
            let go = need > 0 || over > 0;
            if go {
                need = need.saturating_sub(1);
                over = over.saturating_sub(s.bytes);
            }
            go
        });
        let len = k.len;
        k.slots[len] = Slot { addr, bytes, kept_at: served };
        k.len += 1;
        k.bytes += bytes;
    }
    evicted.unmap();
}

impl Kept {
    fn remove(&mut self, i: usize) -> Slot {
        let s = self.slots[i];
        let len = self.len;
        self.slots.copy_within(i + 1..len, i);
        self.len -= 1;
        self.bytes -= s.bytes;
        s
    }

    /// Remove the slots `go` picks (visited oldest first) into `out`.
    fn evict(&mut self, out: &mut Evicted, mut go: impl FnMut(&Slot) -> bool) {
        let mut i = 0;
        while i < self.len {
            if go(&self.slots[i]) {
                out.list[out.len] = self.remove(i);
                out.len += 1;
            } else {
                i += 1;
            }
        }
    }
}

/// Mappings to unmap once the lock is released (other threads' requests
/// need not wait on the system calls).
struct Evicted {
    list: [Slot; SLOTS],
    len: usize,
}

impl Default for Evicted {
    fn default() -> Self {
        Self { list: [EMPTY; SLOTS], len: 0 }
    }
}

impl Evicted {
    fn unmap(&self) {
        for s in &self.list[..self.len] {
            unmap(s.addr, s.bytes);
        }
    }
}

/// Unmap every kept buffer (stage boundaries, so one stage's buffers do
/// not count in the next one's resident memory). Returns the bytes released.
pub fn release_cached_buffers() -> usize {
    let mut evicted = Evicted::default();
    kept().evict(&mut evicted, |_| true);
    evicted.unmap();
    evicted.list[..evicted.len].iter().map(|s| s.bytes).sum()
}

/// Bytes of freed large buffers kept for reuse now.
pub fn cached_buffer_bytes() -> usize {
    kept().bytes
}

/// Whether the process's large buffers go through the cache: the global
/// allocator is [`LargeBufferCache`] and `RECON_MALLOC=system` is not set.
/// Probes with one large allocation.
pub fn buffer_cache_active() -> bool {
    let before = SERVED.load(Ordering::Relaxed);
    drop(std::hint::black_box(vec![0u8; LARGE_BYTES]));
    SERVED.load(Ordering::Relaxed) > before
}

// SAFETY: large buffers are whole private mappings owned by exactly one
// allocation at a time (handed out once, kept only after being freed); all
// other requests are forwarded to `System` with their own layouts, and
// `large` gives the same answer for a layout at allocation and at free.
unsafe impl GlobalAlloc for LargeBufferCache {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if large(&layout) {
            return take(rounded(layout.size())).0;
        }
        System.alloc(layout)
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if large(&layout) {
            let (p, fresh) = take(rounded(layout.size()));
            if !p.is_null() && !fresh {
                std::ptr::write_bytes(p, 0, layout.size());
            }
            return p;
        }
        System.alloc_zeroed(layout)
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if large(&layout) {
            give_back(ptr as usize, rounded(layout.size()));
            return;
        }
        System.dealloc(ptr, layout)
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let new_layout = Layout::from_size_align_unchecked(new_size, layout.align());
        if !large(&layout) && !large(&new_layout) {
            return System.realloc(ptr, layout, new_size);
        }
        if large(&layout) && large(&new_layout) && rounded(layout.size()) == rounded(new_size) {
            return ptr;
        }
        let new = self.alloc(new_layout);
        if !new.is_null() {
            std::ptr::copy_nonoverlapping(ptr, new, layout.size().min(new_size));
            self.dealloc(ptr, layout);
        }
        new
    }
}
