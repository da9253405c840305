//! The bounded fuzz pass on the stable toolchain: every parser target of
//! `recon::tools::fuzz` runs on its seed corpus (`fuzz/corpus/<target>/`,
//! regressions from the coverage-guided runs included) and then on
//! deterministic mutations of it for `RECON_FUZZ_SECONDS` per target
//! (default 2; `.ci/run` sets 20). Required, per input: no panic, no hang
//! (no input may take 60 s), and no more bytes live at once on the parsing
//! thread than `recon::tools::fuzz::alloc_bound` (measured by the counting
//! allocator below). The long coverage-guided runs use cargo-fuzz (`fuzz/`,
//! README "Hostile inputs").

mod common;

use recon::tools::fuzz::{alloc_bound, corpus, mutate, run, Target};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// Counts the bytes each thread holds and its peak since the last reset.
struct Counting;

thread_local! {
    static LIVE: Cell<isize> = const { Cell::new(0) };
    static PEAK: Cell<isize> = const { Cell::new(0) };
}

fn add(n: isize) {
    // try_with: the allocator also runs while thread-locals are torn down.
    let _ = LIVE.try_with(|l| {
        let v = l.get() + n;
        l.set(v);
        let _ = PEAK.try_with(|p| p.set(p.get().max(v)));
    });
}

// SAFETY: forwards to the system allocator; the bookkeeping does not allocate.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        add(l.size() as isize);
        System.alloc(l)
    }
    unsafe fn alloc_zeroed(&self, l: Layout) -> *mut u8 {
        add(l.size() as isize);
        System.alloc_zeroed(l)
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        add(-(l.size() as isize));
        System.dealloc(p, l)
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, new: usize) -> *mut u8 {
        add(new as isize - l.size() as isize);
        System.realloc(p, l, new)
    }
}

#[global_allocator]
static ALLOC: Counting = Counting;

/// Peak bytes held above the starting level while `f` runs on this thread.
fn peak_during<R>(f: impl FnOnce() -> R) -> (R, usize) {
    let base = LIVE.with(Cell::get);
    PEAK.with(|p| p.set(base));
    let r = f();
    let peak = PEAK.with(Cell::get);
    (r, (peak - base).max(0) as usize)
}

#[derive(Default, Debug)]
struct Tally {
    execs: usize,
    ok: usize,
    errors: usize,
    max_alloc: usize,
    slowest_ms: u128,
}

fn budget() -> Duration {
    let s = std::env::var("RECON_FUZZ_SECONDS").ok().and_then(|v| v.parse::<f64>().ok()).unwrap_or(2.0);
    Duration::from_secs_f64(s.max(0.0))
}

/// Run one input; a panic or an allocation over the bound is returned as a finding.
fn one(t: Target, data: &[u8], tally: &mut Tally) -> Result<(), String> {
    let start = Instant::now();
    let (r, peak) = peak_during(|| std::panic::catch_unwind(|| run(t, data)));
    tally.execs += 1;
    tally.slowest_ms = tally.slowest_ms.max(start.elapsed().as_millis());
    tally.max_alloc = tally.max_alloc.max(peak);
    match r {
        Err(p) => {
            let msg = p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string())).unwrap_or_default();
            return Err(format!("panic: {msg}"));
        }
        Ok(Ok(())) => tally.ok += 1,
        Ok(Err(e)) => {
            // Errors must say something (they name the file the user gave).
            if e.to_string().trim().is_empty() {
                return Err("an error with an empty message".into());
            }
            tally.errors += 1
        }
    }
    if peak > alloc_bound(data.len()) {
        return Err(format!("{peak} bytes live at once, over the bound of {}", alloc_bound(data.len())));
    }
    Ok(())
}

fn fuzz_target(t: Target) {
    let dir = common::repo().join("fuzz/corpus").join(t.name());
    let seeds = corpus(&dir).unwrap();
    assert!(!seeds.is_empty(), "no seed corpus in {}", dir.display());
    let budget = budget();
    let (tx, rx) = mpsc::channel::<String>();
    // The work runs on its own thread so a hang is seen (and reported) here.
    let worker = std::thread::spawn(move || {
        let mut tally = Tally::default();
        let found = |what: &str, data: &[u8], why: String| {
            let out = common::tmp(&format!("fuzz-finding-{}", t.name())).join("input");
            std::fs::write(&out, data).unwrap();
            panic!("{}: {what}: {why} (input saved to {})", t.name(), out.display());
        };
        for (i, s) in seeds.iter().enumerate() {
            let _ = tx.send(format!("seed {i}"));
            if let Err(why) = one(t, s, &mut tally) {
                found(&format!("seed {i}"), s, why);
            }
        }
        let start = Instant::now();
        let mut i = 0u64;
        // At least 200 mutations whatever the machine's speed.
        while i < 200 || start.elapsed() < budget {
            let data = mutate(&seeds, i, t.is_text());
            let _ = tx.send(format!("mutation {i}"));
            if let Err(why) = one(t, &data, &mut tally) {
                found(&format!("mutation {i}"), &data, why);
            }
            i += 1;
        }
        tally
    });
    let mut last = String::from("start");
    loop {
        match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(m) => last = m,
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
            Err(mpsc::RecvTimeoutError::Timeout) => panic!("{}: hang: {last} ran for over 60 s", t.name()),
        }
    }
    let tally = worker.join().unwrap_or_else(|p| std::panic::resume_unwind(p));
    eprintln!(
        "fuzz {}: {} executions ({} accepted, {} refused), 0 panics, 0 hangs, max {:.1} MiB live, slowest input {} ms",
        t.name(),
        tally.execs,
        tally.ok,
        tally.errors,
        tally.max_alloc as f64 / (1 << 20) as f64,
        tally.slowest_ms
    );
    // The corpus seeds are valid files (regressions aside): the pass must
    // have exercised the accepting path, not only early refusals.
    assert!(tally.ok > 0, "{}: no input parsed at all; the seeds are broken", t.name());
}

macro_rules! targets {
    ($($name:ident => $t:expr),* $(,)?) => {
        $(#[test] fn $name() { fuzz_target($t); })*

        /// Every target has a test here (a new target cannot be left out).
        #[test]
        fn every_target_is_fuzzed() {
            let tested = [$($t),*];
            for t in Target::ALL {
                assert!(tested.contains(&t), "{} has no test in tests/fuzz_parsers.rs", t.name());
                assert_eq!(Target::from_name(t.name()), Some(t));
                assert!(common::repo().join("fuzz/fuzz_targets").join(format!("{}.rs", t.name())).is_file(), "{} has no cargo-fuzz target", t.name());
            }
        }
    };
}

targets! {
    safetensors => Target::Safetensors,
    pt => Target::Pt,
    matv5 => Target::MatV5,
    ply => Target::Ply,
    scene_json => Target::SceneJson,
    bop_scene_gt => Target::BopSceneGt,
    bop_scene_camera => Target::BopSceneCamera,
    bop_models_info => Target::BopModelsInfo,
    architecture => Target::Architecture,
    sensor => Target::Sensor,
    materials => Target::Materials,
    predictions => Target::Predictions,
    variation_spec => Target::VariationSpec,
    intrinsics_json => Target::IntrinsicsJson,
    intrinsics_yaml => Target::IntrinsicsYaml,
    obj => Target::Obj,
    glb => Target::Glb,
    asset_physics => Target::AssetPhysics,
}
