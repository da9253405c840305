//! Sparse voxel tensors (TRELLIS `SparseTensor`): integer coordinates
//! `(batch, x, y, z)` with each batch item's rows contiguous, plus features.

pub mod attention;
pub mod conv;
pub mod spatial;
mod tensor;
pub mod windowed;

pub use attention::{varlen_attention, varlen_attention_with};
pub use conv::{neighbour_map, SparseConv3d};
pub use spatial::{sparse_downsample, sparse_upsample, DownsampleCache};
pub use tensor::SparseTensor;
