//! Dense 3D building blocks of the sparse-structure VAE (TRELLIS
//! `modules/spatial.py`, `modules/norm.py`): `Conv3d`, `ChannelLayerNorm32`
//! and `pixel_shuffle_3d`.
//!
//! Each has two paths: plain candle ops (differentiable, for training and as
//! the reference) and the hand-written kernels of `recon_kernels::conv3d`
//! working on a [`Volume`] (inference). Tests check that both agree.

use crate::{Error, Result};
use candle_core::{DType, Device, Storage, Tensor};
use candle_nn::VarBuilder;
use recon_kernels::conv3d as k;

/// An NCDHW `f32` volume in a plain buffer, the currency of the fast path.
#[derive(Debug, Clone)]
pub struct Volume {
    pub data: Vec<f32>,
    /// `[B, C, D, H, W]`
    pub dims: [usize; 5],
}

impl Volume {
    pub fn from_tensor(t: &Tensor) -> Result<Self> {
        let (b, c, d, h, w) = t.dims5()?;
        let data = t.to_device(&Device::Cpu)?.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        Ok(Volume { data, dims: [b, c, d, h, w] })
    }
    pub fn to_tensor(&self) -> Result<Tensor> {
        Ok(Tensor::from_slice(&self.data, &self.dims[..], &Device::Cpu)?)
    }
    /// Flattened spatial size `D·H·W`.
    pub fn positions(&self) -> usize {
        self.dims[2] * self.dims[3] * self.dims[4]
    }
}

/// Run `f` on the contiguous f32 CPU data of `t` without copying when
/// possible (large conv weights are borrowed in place, not duplicated).
pub fn with_f32_slice<R>(t: &Tensor, f: impl FnOnce(&[f32]) -> R) -> Result<R> {
    if t.device().is_cpu() && t.dtype() == DType::F32 {
        let (storage, layout) = t.storage_and_layout();
        if let (Storage::Cpu(cpu), Some((start, end))) = (&*storage, layout.contiguous_offsets()) {
            return Ok(f(&cpu.as_slice::<f32>()?[start..end]));
        }
    }
    let v = t.to_device(&Device::Cpu)?.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    Ok(f(&v))
}

/// Stride-1 3D convolution with candle ops (differentiable): the depth taps
/// become a sum of 2D convolutions over depth slices folded into the batch.
/// `x` `[B, Cin, D, H, W]`, `w` `[Cout, Cin, k, k, k]`, `b` `[Cout]`.
pub fn conv3d_candle(x: &Tensor, w: &Tensor, b: Option<&Tensor>, pad: usize) -> Result<Tensor> {
    let (bsz, cin, d, _h, _w) = x.dims5()?;
    let (cout, wcin, kd, kh, kw) = w.dims5()?;
    if wcin != cin || kd != kh || kd != kw {
        return Err(Error::msg(format!("conv3d: weight {:?} does not fit input {:?}", w.dims(), x.dims())));
    }
    let do_ = (d + 2 * pad + 1).checked_sub(kd).filter(|&n| n > 0).ok_or_else(|| Error::msg("conv3d: kernel larger than padded input"))?;
    // [B, D+2p, Cin, H, W]: depth next to batch so a depth window folds into it.
    let xt = x.pad_with_zeros(2, pad, pad)?.permute((0, 2, 1, 3, 4))?;
    let mut acc: Option<Tensor> = None;
    for t in 0..kd {
        let (_, _, _, h, wd) = xt.dims5()?;
        let slab = xt.narrow(1, t, do_)?.contiguous()?.reshape((bsz * do_, cin, h, wd))?;
        let wt = w.narrow(2, t, 1)?.squeeze(2)?.contiguous()?;
        let y = slab.conv2d(&wt, pad, 1, 1, 1)?;
        acc = Some(match acc {
            None => y,
            Some(a) => (a + y)?,
        });
    }
    let y = acc.ok_or_else(|| Error::msg("conv3d: empty kernel"))?;
    let (_, _, ho, wo) = y.dims4()?;
    let y = y.reshape((bsz, do_, cout, ho, wo))?.permute((0, 2, 1, 3, 4))?.contiguous()?;
    Ok(match b {
        Some(b) => y.broadcast_add(&b.reshape((1, cout, 1, 1, 1))?)?,
        None => y,
    })
}

/// `nn.Conv3d(cin, cout, k, padding=pad)` with bias (`{prefix}.weight`, `{prefix}.bias`).
#[derive(Debug, Clone)]
pub struct Conv3d {
    weight: Tensor,
    bias: Tensor,
    cin: usize,
    cout: usize,
    k: usize,
    pad: usize,
}

impl Conv3d {
    pub fn new(cin: usize, cout: usize, k: usize, pad: usize, vb: VarBuilder) -> Result<Self> {
        let weight = vb.get((cout, cin, k, k, k), "weight")?;
        let bias = vb.get(cout, "bias")?;
        Ok(Self { weight, bias, cin, cout, k, pad })
    }

    /// Differentiable candle-ops path.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        conv3d_candle(x, &self.weight, Some(&self.bias), self.pad)
    }

    /// Fast path. With `residual`, the result is added onto it in place
    /// (`residual + conv(x)`) and that buffer is returned.
    pub fn forward_fast(&self, x: &Volume, residual: Option<Volume>) -> Result<Volume> {
        let [batch, cin, d, h, w] = x.dims;
        if cin != self.cin {
            return Err(Error::msg(format!("conv3d: input has {cin} channels, layer expects {}", self.cin)));
        }
        let s = k::Conv3dShape { batch, cin, cout: self.cout, d, h, w, k: self.k, pad: self.pad };
        let (od, oh, ow) = s.out_dims().ok_or_else(|| Error::msg(format!("conv3d: kernel does not fit input {:?}", x.dims)))?;
        let dims = [batch, self.cout, od, oh, ow];
        let (mut out, accumulate) = match residual {
            Some(r) if r.dims == dims => (r, true),
            Some(r) => return Err(Error::msg(format!("conv3d: residual {:?} does not match output {dims:?}", r.dims))),
            None => (Volume { data: vec![0.0; s.output_len()], dims }, false),
        };
        with_f32_slice(&self.weight, |wt| {
            with_f32_slice(&self.bias, |bias| k::conv3d(&x.data, &s, wt, Some(bias), &mut out.data, accumulate))
        })??
        .map_err(Error::msg)?;
        Ok(out)
    }
}

/// `ChannelLayerNorm32`: LayerNorm over the channel dim of NCDHW, eps 1e-5, affine.
#[derive(Debug, Clone)]
pub struct ChannelLayerNorm {
    weight: Tensor,
    bias: Tensor,
    channels: usize,
    eps: f64,
}

impl ChannelLayerNorm {
    pub fn new(channels: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self { weight: vb.get(channels, "weight")?, bias: vb.get(channels, "bias")?, channels, eps: 1e-5 })
    }

    /// Differentiable path: channels-last, LayerNorm, back.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let xl = x.permute((0, 2, 3, 4, 1))?;
        let y = crate::model::common::layer_norm_plain(&xl, self.eps)?.broadcast_mul(&self.weight)?.broadcast_add(&self.bias)?;
        Ok(y.permute((0, 4, 1, 2, 3))?.contiguous()?)
    }

    /// Fast path, optionally fused with the SiLU that always follows it in the decoder.
    pub fn forward_fast(&self, x: &Volume, silu: bool) -> Result<Volume> {
        let [b, c, ..] = x.dims;
        if c != self.channels {
            return Err(Error::msg(format!("channel layer norm: input has {c} channels, layer expects {}", self.channels)));
        }
        let mut out = vec![0.0; x.data.len()];
        with_f32_slice(&self.weight, |g| {
            with_f32_slice(&self.bias, |be| k::channel_layer_norm(&x.data, (b, c, x.positions()), g, be, self.eps as f32, silu, &mut out))
        })??
        .map_err(Error::msg)?;
        Ok(Volume { data: out, dims: x.dims })
    }
}

/// `pixel_shuffle_3d(x, 2)` with candle ops: `[B, C·8, D, H, W]` → `[B, C, 2D, 2H, 2W]`,
/// channel `c·8 + (a·4 + b·2 + e)` going to sub-voxel offset `(a, b, e)`.
pub fn pixel_shuffle_3d(x: &Tensor) -> Result<Tensor> {
    let (b, c8, d, h, w) = x.dims5()?;
    if c8 % 8 != 0 {
        return Err(Error::msg(format!("pixel_shuffle_3d: {c8} channels is not a multiple of 8")));
    }
    let c = c8 / 8;
    let y = x.reshape(vec![b, c, 2, 2, 2, d, h, w])?.permute(vec![0, 1, 5, 2, 6, 3, 7, 4])?.contiguous()?;
    Ok(y.reshape((b, c, 2 * d, 2 * h, 2 * w))?)
}

/// Fast path of [`pixel_shuffle_3d`].
pub fn pixel_shuffle_3d_fast(x: &Volume) -> Result<Volume> {
    let [b, c8, d, h, w] = x.dims;
    let mut out = vec![0.0; x.data.len()];
    k::pixel_shuffle_3d(&x.data, (b, c8, d, h, w), &mut out).map_err(Error::msg)?;
    Ok(Volume { data: out, dims: [b, c8 / 8, 2 * d, 2 * h, 2 * w] })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::conformance::max_abs_diff;
    use std::collections::HashMap;

    fn rand(shape: &[usize], seed: u64) -> Tensor {
        let n: usize = shape.iter().product();
        let mut s = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let v: Vec<f32> = (0..n)
            .map(|_| {
                s ^= s << 13;
                s ^= s >> 7;
                s ^= s << 17;
                ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
            })
            .collect();
        Tensor::from_vec(v, shape, &Device::Cpu).unwrap()
    }

    /// Direct loop reference for the candle path.
    fn conv_ref(x: &Tensor, w: &Tensor, b: &Tensor, pad: usize) -> Tensor {
        let (bsz, cin, d, h, wd) = x.dims5().unwrap();
        let (cout, _, kk, _, _) = w.dims5().unwrap();
        let s = k::Conv3dShape { batch: bsz, cin, cout, d, h, w: wd, k: kk, pad };
        let (od, oh, ow) = s.out_dims().unwrap();
        let mut out = vec![0.0; s.output_len()];
        let xv = x.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let wv = w.flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let bv = b.to_vec1::<f32>().unwrap();
        k::conv3d_reference(&xv, &s, &wv, Some(&bv), &mut out).unwrap();
        Tensor::from_vec(out, (bsz, cout, od, oh, ow), &Device::Cpu).unwrap()
    }

    #[test]
    fn conv3d_candle_and_fast_paths_agree_with_reference() {
        for (i, &(bsz, cin, cout, d, h, w, kk, pad)) in
            [(2, 3, 5, 4, 5, 6, 3, 1), (1, 7, 2, 3, 3, 5, 3, 1), (2, 2, 3, 5, 4, 4, 1, 0), (1, 4, 3, 5, 6, 4, 3, 0)].iter().enumerate()
        {
            let x = rand(&[bsz, cin, d, h, w], 10 + i as u64);
            let wt = rand(&[cout, cin, kk, kk, kk], 20 + i as u64);
            let b = rand(&[cout], 30 + i as u64);
            let want = conv_ref(&x, &wt, &b, pad);
            let got_candle = conv3d_candle(&x, &wt, Some(&b), pad).unwrap();
            assert!(max_abs_diff(&got_candle, &want).unwrap() < 1e-5, "candle path, case {i}");
            let mut ws = HashMap::new();
            ws.insert("weight".to_string(), wt.clone());
            ws.insert("bias".to_string(), b.clone());
            let conv = Conv3d::new(cin, cout, kk, pad, VarBuilder::from_tensors(ws, DType::F32, &Device::Cpu)).unwrap();
            let fast = conv.forward_fast(&Volume::from_tensor(&x).unwrap(), None).unwrap().to_tensor().unwrap();
            assert!(max_abs_diff(&fast, &want).unwrap() < 1e-5, "fast path, case {i}");
            assert!(max_abs_diff(&conv.forward(&x).unwrap(), &fast).unwrap() < 1e-5);
        }
    }

    #[test]
    fn conv3d_candle_path_is_differentiable() {
        let x = rand(&[1, 2, 3, 3, 3], 1);
        let w = candle_core::Var::from_tensor(&rand(&[2, 2, 3, 3, 3], 2)).unwrap();
        let y = conv3d_candle(&x, w.as_tensor(), None, 1).unwrap();
        let grads = y.sum_all().unwrap().backward().unwrap();
        let g = grads.get(w.as_tensor()).expect("weight gradient");
        // d(sum y)/dw[co, ci, kd, kh, kw] = sum of x over the shifted window: the centre tap sees all of x.
        let centre = g.get(0).unwrap().get(0).unwrap().get(1).unwrap().get(1).unwrap().get(1).unwrap().to_scalar::<f32>().unwrap();
        let xs = x.get(0).unwrap().get(0).unwrap().sum_all().unwrap().to_scalar::<f32>().unwrap();
        assert!((centre - xs).abs() < 1e-5, "{centre} vs {xs}");
    }

    #[test]
    fn channel_layer_norm_paths_agree() {
        let x = rand(&[2, 5, 3, 4, 2], 3);
        let mut ws = HashMap::new();
        ws.insert("weight".to_string(), (rand(&[5], 4) + 1.0).unwrap());
        ws.insert("bias".to_string(), rand(&[5], 5));
        let ln = ChannelLayerNorm::new(5, VarBuilder::from_tensors(ws, DType::F32, &Device::Cpu)).unwrap();
        let a = ln.forward(&x).unwrap();
        let vx = Volume::from_tensor(&x).unwrap();
        let b = ln.forward_fast(&vx, false).unwrap().to_tensor().unwrap();
        assert!(max_abs_diff(&a, &b).unwrap() < 1e-5);
        let c = ln.forward_fast(&vx, true).unwrap().to_tensor().unwrap();
        assert!(max_abs_diff(&candle_nn::ops::silu(&a).unwrap(), &c).unwrap() < 1e-5);
        // Normalised over channels: per-position mean of (y - bias)/weight is ~0.
        let plain = crate::model::common::layer_norm_plain(&x.permute((0, 2, 3, 4, 1)).unwrap(), 1e-5).unwrap();
        let m = plain.mean_keepdim(4).unwrap().abs().unwrap().max_keepdim(0).unwrap().flatten_all().unwrap().max(0).unwrap();
        assert!(m.to_scalar::<f32>().unwrap() < 1e-5);
    }

    #[test]
    fn pixel_shuffle_paths_agree_and_follow_upstream_indexing() {
        let (b, c, d, h, w) = (2, 2, 2, 3, 2);
        let x = Tensor::arange(0f32, (b * c * 8 * d * h * w) as f32, &Device::Cpu).unwrap().reshape((b, c * 8, d, h, w)).unwrap();
        let y = pixel_shuffle_3d(&x).unwrap();
        assert_eq!(y.dims(), &[b, c, 2 * d, 2 * h, 2 * w]);
        // Output voxel (z, y, x) = (2d+a, 2h+b, 2w+e) reads channel c*8 + a*4 + b*2 + e.
        let v = y.get(1).unwrap().get(1).unwrap().get(3).unwrap().get(2).unwrap().get(1).unwrap().to_scalar::<f32>().unwrap();
        let want = x.get(1).unwrap().get(8 + 4 + 0 + 1).unwrap().get(1).unwrap().get(1).unwrap().get(0).unwrap().to_scalar::<f32>().unwrap();
        assert_eq!(v, want);
        let fast = pixel_shuffle_3d_fast(&Volume::from_tensor(&x).unwrap()).unwrap().to_tensor().unwrap();
        assert_eq!(max_abs_diff(&y, &fast).unwrap(), 0.0);
    }
}
