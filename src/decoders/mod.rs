//! decoders
pub mod gaussian;
pub mod trunk;
