//! The sparse tensor: integer voxel coordinates with batch index, plus features.

use crate::{Error, Result};
use candle_core::{DType, Device, Tensor};
use std::ops::Range;

/// A batch of sparse voxel sets: one coordinate row and one feature row per active voxel (TRELLIS `SparseTensor`).
#[derive(Debug, Clone)]
pub struct SparseTensor {
    /// `(batch, x, y, z)` per row; rows of one batch item are contiguous.
    pub coords: Vec<[i32; 4]>,
    /// `[N, C]` features, row i belongs to `coords[i]`.
    pub feats: Tensor,
    /// Number of batch items (items may be empty).
    pub batch_size: usize,
}

impl SparseTensor {
    /// Check that `feats` has one row per coord and batch indices are ascending and `< batch_size`.
    pub fn new(coords: Vec<[i32; 4]>, feats: Tensor, batch_size: usize) -> Result<Self> {
        if feats.dim(0)? != coords.len() {
            return Err(Error::msg(format!("sparse tensor: {} coords but {} feature rows", coords.len(), feats.dim(0)?)));
        }
        let mut last = -1;
        for c in &coords {
            if c[0] < last || c[0] < 0 || c[0] as usize >= batch_size {
                return Err(Error::msg("sparse tensor: batch indices must be contiguous, ascending and < batch_size"));
            }
            last = c[0];
        }
        Ok(Self { coords, feats, batch_size })
    }

    /// Build from an int `[N, 4]` coords tensor and `[N, C]` feats.
    pub fn from_tensors(coords: &Tensor, feats: Tensor) -> Result<Self> {
        let c = coords.to_dtype(DType::I64)?.to_vec2::<i64>()?;
        let coords: Vec<[i32; 4]> = c.iter().map(|r| [r[0] as i32, r[1] as i32, r[2] as i32, r[3] as i32]).collect();
        let batch_size = coords.iter().map(|c| c[0] as usize + 1).max().unwrap_or(0);
        Self::new(coords, feats, batch_size)
    }

    /// Coordinates as an int64 `[N, 4]` tensor.
    pub fn coords_tensor(&self, device: &Device) -> Result<Tensor> {
        let flat: Vec<i64> = self.coords.iter().flat_map(|c| c.iter().map(|&v| v as i64)).collect();
        Ok(Tensor::from_vec(flat, (self.coords.len(), 4), device)?)
    }

    /// Number of rows (active voxels over all batch items).
    pub fn len(&self) -> usize {
        self.coords.len()
    }

    /// Whether there are no rows.
    pub fn is_empty(&self) -> bool {
        self.coords.is_empty()
    }

    /// Same coordinates, new features.
    pub fn with_feats(&self, feats: Tensor) -> Result<Self> {
        Self::new(self.coords.clone(), feats, self.batch_size)
    }

    /// Row range of each batch item.
    pub fn batch_ranges(&self) -> Vec<Range<usize>> {
        let mut ranges = vec![0..0; self.batch_size];
        let mut i = 0;
        while i < self.coords.len() {
            let b = self.coords[i][0] as usize;
            let start = i;
            while i < self.coords.len() && self.coords[i][0] as usize == b {
                i += 1;
            }
            ranges[b] = start..i;
        }
        ranges
    }

    /// Batch index of every row as a u32 tensor `[N]`.
    pub fn batch_index(&self) -> Result<Tensor> {
        let idx: Vec<u32> = self.coords.iter().map(|c| c[0] as u32).collect();
        Ok(Tensor::from_vec(idx, self.coords.len(), self.feats.device())?)
    }

    /// Broadcast a dense per-item tensor `[B, C]` to rows `[N, C]`
    /// (TRELLIS `sparse_batch_broadcast`).
    pub fn batch_broadcast(&self, t: &Tensor) -> Result<Tensor> {
        if t.dim(0)? != self.batch_size {
            return Err(Error::msg(format!("batch broadcast: {} rows for batch size {}", t.dim(0)?, self.batch_size)));
        }
        Ok(t.contiguous()?.index_select(&self.batch_index()?, 0)?)
    }
}
