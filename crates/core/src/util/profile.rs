//! Opt-in time and FLOP accounting of the inference kernels, for
//! `recon bench --sections stage2`: where a forward spends its time (GEMM,
//! attention, sparse convolution, sparse indexing, norms; the rest is glue)
//! and how many floating-point operations the kernels were asked for,
//! counted from the operand shapes at each call.
//!
//! Off by default: each instrumented call then costs one relaxed atomic
//! load. On, kind times are exclusive (a kind timed inside another, e.g. a
//! GEMM inside a timed conv, is subtracted from the outer one) and regions
//! (parts of a model's forward) are inclusive. Only the calls made on the
//! thread that turned profiling on are recorded (the kernels parallelise
//! inside the timed call and return before it ends), so other threads'
//! work does not leak in. Counters are process-wide: profile one forward at
//! a time, from one thread.

use std::cell::{Cell, RefCell};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Instant;

/// What a timed call does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Packed GEMMs (every fast linear layer).
    Gemm = 0,
    /// Fused (flash) attention.
    Attention = 1,
    /// Submanifold sparse convolutions.
    SparseConv = 2,
    /// Sparse indexing: neighbour maps, down- and upsampling.
    SparseIndex = 3,
    /// LayerNorm (fused or plain) and QK RMS norms.
    Norm = 4,
}

/// A part of a model's forward, timed inclusively.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Region {
    /// The sparse io stages (SLat flow input and output blocks).
    IoBlocks = 0,
    /// The transformer blocks.
    Transformer = 1,
}

const KINDS: usize = 5;
const REGIONS: usize = 2;

static ENABLED: AtomicBool = AtomicBool::new(false);
static KIND_NS: [AtomicU64; KINDS] = [const { AtomicU64::new(0) }; KINDS];
static KIND_FLOPS: [AtomicU64; KINDS] = [const { AtomicU64::new(0) }; KINDS];
static KIND_CALLS: [AtomicU64; KINDS] = [const { AtomicU64::new(0) }; KINDS];
static REGION_NS: [AtomicU64; REGIONS] = [const { AtomicU64::new(0) }; REGIONS];
static REGION_FLOPS: [AtomicU64; REGIONS] = [const { AtomicU64::new(0) }; REGIONS];

thread_local! {
    /// Nanoseconds of timed kinds nested in each open kind scope.
    static NESTED: RefCell<Vec<u64>> = const { RefCell::new(Vec::new()) };
    /// Whether this thread turned profiling on.
    static RECORDING: Cell<bool> = const { Cell::new(false) };
}

/// Whether profiling is on for calls made on this thread.
#[inline]
pub fn enabled() -> bool {
    ENABLED.load(Ordering::Relaxed) && RECORDING.with(Cell::get)
}

/// Turn profiling on or off for the calls made on this thread (the counters
/// are kept; see [`reset`]).
pub fn set_enabled(on: bool) {
    RECORDING.with(|r| r.set(on));
    ENABLED.store(on, Ordering::Relaxed);
}

/// Zero every counter.
pub fn reset() {
    for a in KIND_NS.iter().chain(&KIND_FLOPS).chain(&KIND_CALLS).chain(&REGION_NS).chain(&REGION_FLOPS) {
        a.store(0, Ordering::Relaxed);
    }
}

/// Run `f` as a call of `kind` doing `flops` floating-point operations
/// (recorded only when profiling is on; `flops` is then evaluated).
#[inline]
pub fn timed<R>(kind: Kind, flops: impl FnOnce() -> u64, f: impl FnOnce() -> R) -> R {
    if !enabled() {
        return f();
    }
    NESTED.with(|n| n.borrow_mut().push(0));
    let t = Instant::now();
    let r = f();
    let ns = t.elapsed().as_nanos() as u64;
    let nested = NESTED.with(|n| {
        let mut n = n.borrow_mut();
        let nested = n.pop().unwrap_or(0);
        if let Some(parent) = n.last_mut() {
            *parent += ns;
        }
        nested
    });
    let k = kind as usize;
    KIND_NS[k].fetch_add(ns.saturating_sub(nested), Ordering::Relaxed);
    KIND_FLOPS[k].fetch_add(flops(), Ordering::Relaxed);
    KIND_CALLS[k].fetch_add(1, Ordering::Relaxed);
    r
}

fn all_flops() -> u64 {
    KIND_FLOPS.iter().map(|a| a.load(Ordering::Relaxed)).sum()
}

/// Run `f` as (part of) `region`: its time and the FLOPs of the kinds
/// timed inside it (regions are entered from one thread at a time).
#[inline]
pub fn region<R>(region: Region, f: impl FnOnce() -> R) -> R {
    if !enabled() {
        return f();
    }
    let flops = all_flops();
    let t = Instant::now();
    let r = f();
    REGION_NS[region as usize].fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
    REGION_FLOPS[region as usize].fetch_add(all_flops().saturating_sub(flops), Ordering::Relaxed);
    r
}

/// One kind's totals.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct KindTotals {
    /// Exclusive seconds.
    pub seconds: f64,
    /// Floating-point operations (a multiply-add counts 2).
    pub flops: f64,
    /// Timed calls.
    pub calls: u64,
}

/// Everything recorded since the last [`reset`].
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Profile {
    /// [`Kind::Gemm`].
    pub gemm: KindTotals,
    /// [`Kind::Attention`].
    pub attention: KindTotals,
    /// [`Kind::SparseConv`].
    pub sparse_conv: KindTotals,
    /// [`Kind::SparseIndex`].
    pub sparse_index: KindTotals,
    /// [`Kind::Norm`].
    pub norm: KindTotals,
    /// Inclusive seconds in the sparse io blocks.
    pub io_blocks_seconds: f64,
    /// FLOPs in the sparse io blocks.
    pub io_blocks_flops: f64,
    /// Inclusive seconds in the transformer blocks.
    pub transformer_seconds: f64,
    /// FLOPs in the transformer blocks.
    pub transformer_flops: f64,
}

impl Profile {
    /// Seconds of all kinds together (the rest of a forward is glue).
    pub fn kernel_seconds(&self) -> f64 {
        self.kinds().iter().map(|k| k.seconds).sum()
    }

    /// FLOPs of all kinds together.
    pub fn flops(&self) -> f64 {
        self.kinds().iter().map(|k| k.flops).sum()
    }

    fn kinds(&self) -> [KindTotals; KINDS] {
        [self.gemm, self.attention, self.sparse_conv, self.sparse_index, self.norm]
    }
}

/// The counters now.
pub fn snapshot() -> Profile {
    let kind = |k: Kind| KindTotals {
        seconds: KIND_NS[k as usize].load(Ordering::Relaxed) as f64 * 1e-9,
        flops: KIND_FLOPS[k as usize].load(Ordering::Relaxed) as f64,
        calls: KIND_CALLS[k as usize].load(Ordering::Relaxed),
    };
    Profile {
        gemm: kind(Kind::Gemm),
        attention: kind(Kind::Attention),
        sparse_conv: kind(Kind::SparseConv),
        sparse_index: kind(Kind::SparseIndex),
        norm: kind(Kind::Norm),
        io_blocks_seconds: REGION_NS[Region::IoBlocks as usize].load(Ordering::Relaxed) as f64 * 1e-9,
        io_blocks_flops: REGION_FLOPS[Region::IoBlocks as usize].load(Ordering::Relaxed) as f64,
        transformer_seconds: REGION_NS[Region::Transformer as usize].load(Ordering::Relaxed) as f64 * 1e-9,
        transformer_flops: REGION_FLOPS[Region::Transformer as usize].load(Ordering::Relaxed) as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Off: nothing is recorded; on: nested kinds are exclusive, FLOPs and
    /// calls add up. (The only test touching the process-wide counters.)
    #[test]
    fn records_only_when_on_and_nested_time_is_exclusive() {
        reset();
        assert_eq!(timed(Kind::Gemm, || 10, || 3), 3);
        assert_eq!(snapshot(), Profile::default());
        set_enabled(true);
        let spin = |ms: u64| {
            let t = Instant::now();
            while t.elapsed().as_millis() < ms as u128 {}
        };
        region(Region::IoBlocks, || {
            timed(
                Kind::SparseConv,
                || 100,
                || {
                    spin(20);
                    timed(Kind::Gemm, || 7, || spin(30));
                },
            )
        });
        // Another thread's calls are not recorded.
        std::thread::spawn(|| timed(Kind::Attention, || 5, || ())).join().unwrap();
        set_enabled(false);
        let p = snapshot();
        reset();
        assert_eq!((p.gemm.calls, p.sparse_conv.calls, p.gemm.flops, p.sparse_conv.flops, p.attention.calls), (1, 1, 7.0, 100.0, 0));
        assert!(p.gemm.seconds >= 0.03 && p.sparse_conv.seconds >= 0.02, "{p:?}");
        // Exclusive kinds never add up to more than the region around them.
        assert!(p.io_blocks_seconds >= p.kernel_seconds() && p.transformer_seconds == 0.0, "nested time counted twice: {p:?}");
        assert_eq!((p.flops(), p.io_blocks_flops, p.transformer_flops), (107.0, 107.0, 0.0));
    }
}
