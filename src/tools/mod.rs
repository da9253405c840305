//! Developer tools: `bench` (kernel, module and end-to-end benchmarks) and
//! `conformance` (every model stage against upstream golden fixtures).

pub mod bench;
pub(crate) mod conformance;
pub use self::bench::{bench_attention, bench_gemm, disc_view, measure_peaks, synthetic_view, BenchReport, MachineInfo};
pub use self::conformance::{run_dirs, run_fixture, Fixture};
