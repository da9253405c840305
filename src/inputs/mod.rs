//! Reading user inputs: images, masks, point maps.

pub mod image;
