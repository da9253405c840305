//! Reading user inputs: images, masks, point maps.

pub mod image;
pub mod matv5;
pub mod frame;
pub mod masks;
