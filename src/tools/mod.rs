//! Developer tools: [`bench`] (kernel, module and end-to-end benchmarks) and
//! [`conformance`] (every model stage against upstream golden fixtures).

pub mod bench;
pub mod conformance;
