//! Sparse voxel tensors (TRELLIS `SparseTensor`): integer coordinates
//! `(batch, x, y, z)` with each batch item's rows contiguous, plus features.

pub(crate) mod attention;
pub(crate) mod conv;
pub(crate) mod spatial;
mod tensor;
pub(crate) mod windowed;

pub use attention::{varlen_attention, varlen_attention_with};
pub use conv::{neighbour_map, SparseConv3d};
pub use spatial::{sparse_downsample, sparse_upsample, DownsampleCache};
pub use tensor::SparseTensor;
