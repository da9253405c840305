//! Submanifold sparse 3D convolution (TRELLIS `SparseConv3d` over spconv's
//! `SubMConv3d`). Weights keep spconv's stored layout `[C_out, k, k, k, C_in]`
//! under `{prefix}.conv.weight` / `{prefix}.conv.bias`; kernel index (i, j, l)
//! reads the neighbour at `(x+i-k/2, y+j-k/2, z+l-k/2)` (see
//! `recon_kernels::sparse` for the full convention).
//!
//! Two paths with identical maths:
//! - [`SparseConv3d::forward`]: the hand-written multi-threaded kernel (inference only); a
//!   layer built with fast compute packs its weight once at load time and runs recon's GEMM
//!   kernels in the layer's precision, a plain one the f32 reference kernel;
//! - [`SparseConv3d::forward_differentiable`]: candle ops (index_select gather,
//!   matmul, index_add scatter), so gradients flow to feats and weights.

use super::tensor::SparseTensor;
use crate::model::nn::fast::Compute;
use crate::util::profile;
use crate::{Error, Result};
use candle_core::{DType, Tensor};
use candle_nn::VarBuilder;
use recon_kernels::isa::Isa;
use recon_kernels::sparse::{NeighbourMap, PackedSparseWeight};

/// Build the submanifold neighbour map of `x`'s coordinates.
pub fn neighbour_map(x: &SparseTensor, kernel_size: usize) -> Result<NeighbourMap> {
    profile::timed(profile::Kind::SparseIndex, || 0, || NeighbourMap::submanifold(&x.coords, kernel_size).map_err(Error::msg))
}

/// Submanifold sparse 3D convolution with odd kernel size k: outputs only at the input's active voxels.
#[derive(Debug, Clone)]
pub struct SparseConv3d {
    /// `[C_out, k, k, k, C_in]`.
    pub weight: Tensor,
    /// `[C_out]`, if any.
    pub bias: Option<Tensor>,
    /// Input channels `C_in`.
    pub in_channels: usize,
    /// Output channels `C_out`.
    pub out_channels: usize,
    /// Kernel side k (odd).
    pub kernel_size: usize,
    // Host copies for the fast kernel, made once at load time: the packed taps
    // with their ISA (fast compute), else the f32 weight as stored.
    weight_host: Vec<f32>,
    packed: Option<(PackedSparseWeight, Isa)>,
    bias_host: Option<Vec<f32>>,
}

impl SparseConv3d {
    /// Load `{vb}.conv.weight` `[C_out, k, k, k, C_in]` and `{vb}.conv.bias`;
    /// fast `compute` packs the weight for its precision and ISA.
    pub fn new(in_channels: usize, out_channels: usize, kernel_size: usize, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let vb = vb.pp("conv");
        let k = kernel_size;
        let weight = vb.get((out_channels, k, k, k, in_channels), "weight")?;
        let bias = Some(vb.get(out_channels, "bias")?);
        let mut conv = Self::from_tensors(weight, bias)?;
        if let Some((precision, isa)) = compute.fast_parts() {
            let w = std::mem::take(&mut conv.weight_host);
            let packed =
                PackedSparseWeight::new(&w, out_channels, k * k * k, in_channels, precision.weight_format()).map_err(Error::msg)?;
            conv.packed = Some((packed, isa));
        }
        Ok(conv)
    }

    /// From a weight `[C_out, k, k, k, C_in]` and optional bias `[C_out]`.
    pub fn from_tensors(weight: Tensor, bias: Option<Tensor>) -> Result<Self> {
        let dims = weight.dims().to_vec();
        if dims.len() != 5 || dims[1] != dims[2] || dims[2] != dims[3] || dims[1].is_multiple_of(2) {
            return Err(Error::msg(format!("sparse conv weight must be [C_out, k, k, k, C_in] with odd k, got {dims:?}")));
        }
        let weight_host = weight.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        let bias_host = match &bias {
            Some(b) => Some(b.to_dtype(DType::F32)?.to_vec1::<f32>()?),
            None => None,
        };
        Ok(Self { in_channels: dims[4], out_channels: dims[0], kernel_size: dims[1], weight, bias, weight_host, packed: None, bias_host })
    }

    fn check_input(&self, x: &SparseTensor, map: &NeighbourMap) -> Result<()> {
        let c = x.feats.dim(1)?;
        if c != self.in_channels {
            return Err(Error::msg(format!("sparse conv: input has {c} channels, expected {}", self.in_channels)));
        }
        if map.num_rows != x.len() || map.kernel_size != self.kernel_size {
            return Err(Error::msg("sparse conv: neighbour map was built for other coordinates or kernel size"));
        }
        Ok(())
    }

    /// Fast path; builds the neighbour map.
    pub fn forward(&self, x: &SparseTensor) -> Result<SparseTensor> {
        let map = neighbour_map(x, self.kernel_size)?;
        self.forward_with_map(x, &map)
    }

    /// Fast path with a precomputed neighbour map of `x`'s coordinates.
    pub fn forward_with_map(&self, x: &SparseTensor, map: &NeighbourMap) -> Result<SparseTensor> {
        self.check_input(x, map)?;
        let dtype = x.feats.dtype();
        let feats = x.feats.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        let flops = || 2 * (map.pairs.iter().map(Vec::len).sum::<usize>() * self.in_channels * self.out_channels) as u64;
        let out = profile::timed(profile::Kind::SparseConv, flops, || match &self.packed {
            Some((w, isa)) => recon_kernels::sparse::submanifold_conv3d_packed(*isa, &feats, map, w, self.bias_host.as_deref()),
            None => recon_kernels::sparse::submanifold_conv3d(
                &feats,
                self.in_channels,
                map,
                &self.weight_host,
                self.bias_host.as_deref(),
                self.out_channels,
            ),
        })
        .map_err(Error::msg)?;
        let out = Tensor::from_vec(out, (x.len(), self.out_channels), x.feats.device())?.to_dtype(dtype)?;
        x.with_feats(out)
    }

    /// Differentiable path (plain candle ops) with a precomputed neighbour map.
    pub fn forward_differentiable(&self, x: &SparseTensor, map: &NeighbourMap) -> Result<SparseTensor> {
        self.check_input(x, map)?;
        let dev = x.feats.device();
        let kv = map.kernel_volume();
        let w = self.weight.to_dtype(x.feats.dtype())?.reshape((self.out_channels, kv, self.in_channels))?;
        let mut out = Tensor::zeros((x.len(), self.out_channels), x.feats.dtype(), dev)?;
        for (o, pairs) in map.pairs.iter().enumerate() {
            if pairs.is_empty() {
                continue;
            }
            let dst: Vec<u32> = pairs.iter().map(|p| p.0).collect();
            let src: Vec<u32> = pairs.iter().map(|p| p.1).collect();
            let dst = Tensor::from_vec(dst, pairs.len(), dev)?;
            let src = Tensor::from_vec(src, pairs.len(), dev)?;
            let wo = w.narrow(1, o, 1)?.squeeze(1)?.t()?; // [C_in, C_out]
            let contrib = x.feats.index_select(&src, 0)?.matmul(&wo)?;
            out = out.index_add(&dst, &contrib, 0)?;
        }
        if let Some(b) = &self.bias {
            out = out.broadcast_add(&b.to_dtype(out.dtype())?)?;
        }
        x.with_feats(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    fn random_sparse(n_side: i32, keep_every: usize) -> SparseTensor {
        let mut coords = Vec::new();
        let mut i = 0usize;
        for b in 0..2 {
            for x in 0..n_side {
                for y in 0..n_side {
                    for z in 0..n_side {
                        i += 1;
                        if !(i * 7919).is_multiple_of(keep_every) {
                            coords.push([b, x, y, z]);
                        }
                    }
                }
            }
        }
        let feats = Tensor::randn(0f32, 1.0, (coords.len(), 5), &Device::Cpu).unwrap();
        SparseTensor::new(coords, feats, 2).unwrap()
    }

    #[test]
    fn fast_and_differentiable_paths_agree() -> Result<()> {
        let x = random_sparse(6, 3);
        for k in [1usize, 3] {
            let w = Tensor::randn(0f32, 0.3, (7, k, k, k, 5), &Device::Cpu)?;
            let b = Tensor::randn(0f32, 0.3, 7, &Device::Cpu)?;
            let conv = SparseConv3d::from_tensors(w, Some(b))?;
            let map = neighbour_map(&x, k)?;
            let fast = conv.forward_with_map(&x, &map)?;
            let slow = conv.forward_differentiable(&x, &map)?;
            let d = crate::util::max_abs_diff(&fast.feats, &slow.feats)?;
            assert!(d < 1e-5, "k={k}: fast vs differentiable differ by {d}");
            assert_eq!(fast.coords, x.coords);
        }
        Ok(())
    }

    #[test]
    fn packed_fast_layers_agree_with_the_plain_layer() -> Result<()> {
        use crate::model::nn::fast::Precision;
        let x = random_sparse(6, 3);
        let w = Tensor::randn(0f32, 0.3, (7, 3, 3, 3, 5), &Device::Cpu)?;
        let b = Tensor::randn(0f32, 0.3, 7, &Device::Cpu)?;
        let tensors = std::collections::HashMap::from([("conv.weight".to_string(), w.clone()), ("conv.bias".to_string(), b.clone())]);
        let vb = VarBuilder::from_tensors(tensors, DType::F32, &Device::Cpu);
        let map = neighbour_map(&x, 3)?;
        let want = SparseConv3d::from_tensors(w, Some(b))?.forward_with_map(&x, &map)?;
        let scale = want.feats.abs()?.max_all()?.to_scalar::<f32>()?;
        for (precision, tol) in [(Precision::F32, 1e-5), (Precision::Bf16, 2e-2)] {
            let conv = SparseConv3d::new(5, 7, 3, vb.clone(), Compute::fast(precision))?;
            assert!(conv.packed.as_ref().is_some_and(|(p, _)| p.format() == precision.weight_format()));
            let got = conv.forward_with_map(&x, &map)?;
            let d = crate::util::max_abs_diff(&got.feats, &want.feats)?;
            assert!(d <= (tol * scale) as f64, "{precision}: packed layer differs by {d} (scale {scale})");
        }
        assert!(SparseConv3d::new(5, 7, 3, vb, Compute::Plain)?.packed.is_none());
        Ok(())
    }

    #[test]
    fn differentiable_path_has_gradients() -> Result<()> {
        let x = random_sparse(4, 2);
        let w = Var::from_tensor(&Tensor::randn(0f32, 0.3, (3, 3, 3, 3, 5), &Device::Cpu)?)?;
        let conv = SparseConv3d::from_tensors(w.as_tensor().clone(), None)?;
        let map = neighbour_map(&x, 3)?;
        let y = conv.forward_differentiable(&x, &map)?;
        let grads = y.feats.sqr()?.sum_all()?.backward()?;
        let g = grads.get(w.as_tensor()).expect("weight gradient");
        assert!(g.abs()?.sum_all()?.to_scalar::<f32>()? > 0.0);
        Ok(())
    }

    #[test]
    fn rejects_wrong_channels() -> Result<()> {
        let x = random_sparse(3, 2);
        let conv = SparseConv3d::from_tensors(Tensor::zeros((2, 3, 3, 3, 4), DType::F32, &Device::Cpu)?, None)?;
        assert!(conv.forward(&x).is_err());
        Ok(())
    }
}
