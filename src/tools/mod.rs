//! Developer tools: `bench` (kernel, module and end-to-end benchmarks),
//! `upstream` (recon against upstream PyTorch on the same machine),
//! `conformance` (every model stage against upstream golden fixtures) and
//! `fuzz` (one target per parser, for cargo-fuzz and the bounded test pass).

pub mod bench;
pub(crate) mod conformance;
pub mod fuzz;
pub mod upstream;
pub use self::bench::{bench_attention, bench_gemm, disc_view, measure_peaks, synthetic_view, BenchReport, MachineInfo};
pub use self::conformance::{run_dirs, run_fixture, Fixture};
