//! Dense 3D building blocks of the sparse-structure VAE (TRELLIS
//! `modules/spatial.py`, `modules/norm.py`): `Conv3d`, `ChannelLayerNorm32`
//! and `pixel_shuffle_3d`.
//!
//! Each has two paths: candle ops (differentiable, for training and as the
//! reference) and the hand-written kernels of `recon_kernels::conv3d`
//! working on a [`Volume`] (inference). Tests check that both agree.
//!
//! The differentiable convolution is [`conv3d_trainable`]: a candle custom op
//! whose forward and input gradient run the fast kernel and whose weight
//! gradient is one GEMM per kernel tap. The plain-ops composition
//! [`conv3d_candle`] (2D convolutions over depth slices) is its reference;
//! its backward goes through candle's CPU `conv_transpose2d`, a direct loop
//! too slow to train with, which is why the custom op exists. Tests check values and gradients
//! of the two agree.

use crate::{Error, Result};

/// Normalisation of the 3D-conv VAE blocks (`norm_type`): TRELLIS offers
/// `layer` (ChannelLayerNorm32) and `group`; the released models use `layer`,
/// the only one here.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum NormType {
    /// Channel LayerNorm (`layer`, TRELLIS `ChannelLayerNorm32`), see [`ChannelLayerNorm`].
    #[default]
    Layer,
    /// GroupNorm (`group`); parsed, but the SS VAE configs refuse it.
    Group,
}
use crate::model::nn::fast::{Compute, Isa, Precision};
use candle_core::{CpuStorage, DType, Device, Layout, Shape, Storage, Tensor};
use candle_nn::VarBuilder;
use recon_kernels::conv3d as k;
use recon_kernels::gemm::WeightFormat;

/// An NCDHW `f32` volume in a plain buffer, the currency of the fast path.
#[derive(Debug, Clone)]
pub struct Volume {
    /// The values, row-major in `dims` order (`B·C·D·H·W` of them).
    pub data: Vec<f32>,
    /// `[B, C, D, H, W]`
    pub dims: [usize; 5],
}

impl Volume {
    /// Copy a `[B, C, D, H, W]` tensor (any device and dtype) into an f32 CPU volume.
    pub fn from_tensor(t: &Tensor) -> Result<Self> {
        let (b, c, d, h, w) = t.dims5()?;
        let data = t.to_device(&Device::Cpu)?.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
        Ok(Volume { data, dims: [b, c, d, h, w] })
    }
    /// The volume as a `[B, C, D, H, W]` f32 CPU tensor (a copy).
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

/// Stride-1 3D convolution plus bias (`x` `[B, Cin, D, H, W]`, `w`
/// `[Cout, Cin, k, k, k]`, `b` `[Cout]`, f32 on the CPU), differentiable in
/// all three (module docs).
pub fn conv3d_trainable(x: &Tensor, w: &Tensor, b: &Tensor, pad: usize) -> Result<Tensor> {
    let (_, cin, ..) = x.dims5()?;
    let (cout, wcin, kd, kh, kw) = w.dims5()?;
    if wcin != cin || kd != kh || kd != kw || pad >= kd || b.dims() != [cout] {
        return Err(Error::msg(format!("conv3d: weight {:?}, bias {:?} (pad {pad}) do not fit input {:?}", w.dims(), b.dims(), x.dims())));
    }
    if !x.device().is_cpu() || x.dtype() != DType::F32 || w.dtype() != DType::F32 || b.dtype() != DType::F32 {
        return conv3d_candle(x, w, Some(b), pad);
    }
    Ok(x.contiguous()?.apply_op3(&w.contiguous()?, &b.contiguous()?, Conv3dOp { pad })?)
}

struct Conv3dOp {
    pad: usize,
}

fn conv3d_raw(
    x: &[f32],
    xd: &[usize],
    w: &[f32],
    wd: &[usize],
    bias: Option<&[f32]>,
    pad: usize,
) -> candle_core::Result<(Vec<f32>, [usize; 5])> {
    let s = k::Conv3dShape { batch: xd[0], cin: xd[1], cout: wd[0], d: xd[2], h: xd[3], w: xd[4], k: wd[2], pad };
    let (od, oh, ow) = s.out_dims().ok_or_else(|| candle_core::Error::Msg(format!("conv3d: kernel does not fit input {xd:?}")))?;
    let mut out = vec![0f32; s.output_len()];
    k::conv3d(x, &s, w, bias, &mut out, false).map_err(candle_core::Error::Msg)?;
    Ok((out, [xd[0], wd[0], od, oh, ow]))
}

fn f32_contiguous<'a>(s: &'a CpuStorage, l: &Layout) -> candle_core::Result<&'a [f32]> {
    let CpuStorage::F32(v) = s else { candle_core::bail!("dense3d op: f32 only") };
    let (a, b) = l.contiguous_offsets().ok_or_else(|| candle_core::Error::Msg("dense3d op: input must be contiguous".into()))?;
    Ok(&v[a..b])
}

/// Contiguous f32 values of a tensor (a copy).
fn values(t: &Tensor) -> candle_core::Result<Vec<f32>> {
    t.flatten_all()?.to_vec1::<f32>()
}

impl candle_core::CustomOp3 for Conv3dOp {
    fn name(&self) -> &'static str {
        "recon-conv3d"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let bias = f32_contiguous(s3, l3)?;
        let (out, dims) = conv3d_raw(f32_contiguous(s1, l1)?, l1.dims(), f32_contiguous(s2, l2)?, l2.dims(), Some(bias), self.pad)?;
        Ok((CpuStorage::F32(out), Shape::from_dims(&dims)))
    }

    /// `dx = conv3d(g, flip(w)ᵀ, k−1−pad)` (fast kernel); `dw[:, :, tap] =
    /// g · shift_tap(x_pad)ᵀ`, one GEMM per tap; `db = Σ g`.
    fn bwd(
        &self,
        x: &Tensor,
        w: &Tensor,
        _b: &Tensor,
        _res: &Tensor,
        g: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        use rayon::prelude::*;
        let (cout, cin, kk, ..) = w.dims5()?;
        let (bsz, _, d, h, wd) = x.dims5()?;
        let (_, _, od, oh, ow) = g.dims5()?;
        let gv = values(g)?;
        // Input gradient: full correlation with the flipped, transposed kernel.
        let wv = values(w)?;
        let k3 = kk * kk * kk;
        let mut wt = vec![0f32; wv.len()];
        for co in 0..cout {
            for ci in 0..cin {
                for t in 0..k3 {
                    wt[(ci * cout + co) * k3 + (k3 - 1 - t)] = wv[(co * cin + ci) * k3 + t];
                }
            }
        }
        let (dx, dims) = conv3d_raw(&gv, &[bsz, cout, od, oh, ow], &wt, &[cin, cout, kk, kk, kk], None, kk - 1 - self.pad)?;
        if dims != [bsz, cin, d, h, wd] {
            candle_core::bail!("conv3d backward: input gradient {dims:?} does not match input {:?}", x.dims());
        }
        let dx = Tensor::from_vec(dx, (bsz, cin, d, h, wd), x.device())?;
        // Bias gradient: per output channel, the sum over batch and positions.
        let np = od * oh * ow;
        let db: Vec<f32> = (0..cout).map(|co| (0..bsz).map(|b| gv[(b * cout + co) * np..][..np].iter().sum::<f32>()).sum()).collect();
        let db = Tensor::from_vec(db, cout, x.device())?;
        // Weight gradient: G [Cout, B·P] times the tap-shifted input [Cin, B·P]ᵀ.
        let mut g2 = vec![0f32; cout * bsz * np];
        for co in 0..cout {
            for b in 0..bsz {
                g2[(co * bsz + b) * np..][..np].copy_from_slice(&gv[(b * cout + co) * np..][..np]);
            }
        }
        let g2 = Tensor::from_vec(g2, (cout, bsz * np), x.device())?;
        let xv = values(x)?;
        let p = self.pad as isize;
        let mut taps = Vec::with_capacity(k3);
        for a in 0..kk as isize {
            for bb in 0..kk as isize {
                for c in 0..kk as isize {
                    // xs[ci, b, z, y, ·] = x[b, ci, z+a−p, y+bb−p, ·+c−p] (0 outside).
                    let mut xs = vec![0f32; cin * bsz * np];
                    xs.par_chunks_mut(np).enumerate().for_each(|(row, dst)| {
                        let (ci, b) = (row / bsz, row % bsz);
                        let src = &xv[(b * cin + ci) * d * h * wd..][..d * h * wd];
                        for z in 0..od {
                            let sz = z as isize + a - p;
                            if sz < 0 || sz >= d as isize {
                                continue;
                            }
                            for y in 0..oh {
                                let sy = y as isize + bb - p;
                                if sy < 0 || sy >= h as isize {
                                    continue;
                                }
                                let srow = &src[(sz as usize * h + sy as usize) * wd..][..wd];
                                let drow = &mut dst[(z * oh + y) * ow..][..ow];
                                // Output x reads input x + c − p: copy the in-range run.
                                let lo = (p - c).max(0) as usize;
                                let hi = ((wd as isize + p - c).min(ow as isize)).max(0) as usize;
                                if lo < hi {
                                    let s0 = (lo as isize + c - p) as usize;
                                    drow[lo..hi].copy_from_slice(&srow[s0..s0 + hi - lo]);
                                }
                            }
                        }
                    });
                    let xs = Tensor::from_vec(xs, (cin, bsz * np), x.device())?;
                    taps.push(g2.matmul(&xs.t()?)?);
                }
            }
        }
        let dw = Tensor::stack(&taps, 2)?.reshape((cout, cin, kk, kk, kk))?;
        Ok((Some(dx), Some(dw), Some(db)))
    }
}

/// `nn.Conv3d(cin, cout, k, padding=pad)` with bias (`{prefix}.weight`, `{prefix}.bias`).
///
/// The fast path takes the precision of the `compute` it is built with (f32
/// for [`Compute::Plain`]). It matters for the wide
/// Winograd layers (`recon_kernels::conv3d::conv3d_winograd`): at bf16 their
/// transformed weights (transformed in f32, rounded once) and activations are
/// rounded to bf16, products accumulated in f32, as torch's bf16 autocast
/// does. f16 computes as f32: the transformed weights are made per call, so
/// f16 storage would save no resident memory. Narrow layers (im2col) and the
/// differentiable path are f32 in every mode.
#[derive(Debug, Clone)]
pub struct Conv3d {
    weight: Tensor,
    bias: Tensor,
    cin: usize,
    cout: usize,
    k: usize,
    pad: usize,
    format: WeightFormat,
    isa: Isa,
}

impl Conv3d {
    /// Load `{prefix}.weight` `[cout, cin, k, k, k]` and `{prefix}.bias` `[cout]`; zero padding `pad` on every side.
    pub fn new(cin: usize, cout: usize, k: usize, pad: usize, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let weight = vb.get((cout, cin, k, k, k), "weight")?;
        let bias = vb.get(cout, "bias")?;
        let (format, isa) = match compute.fast_parts() {
            Some((Precision::Bf16, isa)) => (WeightFormat::Bf16, isa),
            Some((_, isa)) => (WeightFormat::F32, isa),
            None => (WeightFormat::F32, Isa::best()),
        };
        Ok(Self { weight, bias, cin, cout, k, pad, format, isa })
    }

    /// Storage format of the Winograd layers' transformed weights.
    pub fn weight_format(&self) -> WeightFormat {
        self.format
    }

    /// Differentiable path (`conv3d_trainable`).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        conv3d_trainable(x, &self.weight, &self.bias, self.pad)
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
            with_f32_slice(&self.bias, |bias| k::conv3d_with(&x.data, &s, wt, Some(bias), &mut out.data, accumulate, self.format, self.isa))
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
    /// Load `{prefix}.weight` and `{prefix}.bias`, both `[channels]`.
    pub fn new(channels: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self { weight: vb.get(channels, "weight")?, bias: vb.get(channels, "bias")?, channels, eps: 1e-5 })
    }

    /// Differentiable path: the fast kernel forward, a hand-written backward
    /// (`channel_layer_norm_trainable`).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        channel_layer_norm_trainable(x, &self.weight, &self.bias, self.eps)
    }

    /// The plain-ops composition (reference for tests).
    pub fn forward_plain(&self, x: &Tensor) -> Result<Tensor> {
        channel_layer_norm_plain(x, &self.weight, &self.bias, self.eps)
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

/// LayerNorm over dim 1 of `[B, C, …]` with affine `weight`/`bias` `[C]`,
/// in plain candle ops.
pub fn channel_layer_norm_plain(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    let x = x.to_dtype(DType::F32)?;
    let mean = x.mean_keepdim(1)?;
    let xc = x.broadcast_sub(&mean)?;
    let var = xc.sqr()?.mean_keepdim(1)?;
    let y = xc.broadcast_div(&(var + eps)?.sqrt()?)?;
    let mut shape = vec![1; x.rank()];
    shape[1] = weight.elem_count();
    Ok(y.broadcast_mul(&weight.reshape(shape.clone())?)?.broadcast_add(&bias.reshape(shape)?)?)
}

/// [`channel_layer_norm_plain`] as one custom op: forward by the fast
/// kernel, backward hand-written (candle's generic backward of the
/// composition reduces over strided dims, which dominated training time).
pub fn channel_layer_norm_trainable(x: &Tensor, weight: &Tensor, bias: &Tensor, eps: f64) -> Result<Tensor> {
    if !x.device().is_cpu() || x.dtype() != DType::F32 || x.rank() < 2 {
        return channel_layer_norm_plain(x, weight, bias, eps);
    }
    Ok(x.contiguous()?.apply_op3(&weight.contiguous()?, &bias.contiguous()?, ChannelLnOp { eps: eps as f32 })?)
}

struct ChannelLnOp {
    eps: f32,
}

impl candle_core::CustomOp3 for ChannelLnOp {
    fn name(&self) -> &'static str {
        "recon-channel-layer-norm"
    }

    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> candle_core::Result<(CpuStorage, Shape)> {
        let dims = l1.dims();
        let (b, c) = (dims[0], dims[1]);
        let n: usize = dims[2..].iter().product();
        let x = f32_contiguous(s1, l1)?;
        let mut out = vec![0f32; x.len()];
        k::channel_layer_norm(x, (b, c, n), f32_contiguous(s2, l2)?, f32_contiguous(s3, l3)?, self.eps, false, &mut out)
            .map_err(candle_core::Error::Msg)?;
        Ok((CpuStorage::F32(out), Shape::from_dims(dims)))
    }

    /// With `x̂ = (x − μ)·r` and `u = g·γ` per position:
    /// `dx = r·(u − mean_c u − x̂·mean_c(u·x̂))`, `dγ = Σ g·x̂`, `dβ = Σ g`
    /// (sums over batch and positions, accumulated per block in a fixed
    /// order, so the result does not depend on thread scheduling).
    fn bwd(
        &self,
        x: &Tensor,
        gamma: &Tensor,
        _beta: &Tensor,
        _res: &Tensor,
        g: &Tensor,
    ) -> candle_core::Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        use rayon::prelude::*;
        let dims = x.dims().to_vec();
        let (bsz, c) = (dims[0], dims[1]);
        let n: usize = dims[2..].iter().product();
        let (xv, gv, gam) = (values(x)?, values(g)?, values(gamma)?);
        const BLK: usize = 256;
        let nblk = n.div_ceil(BLK);
        let eps = self.eps;
        let parts: Vec<(Vec<f32>, Vec<f32>, Vec<f32>)> = (0..bsz * nblk)
            .into_par_iter()
            .map(|job| {
                let (b, p0) = (job / nblk, (job % nblk) * BLK);
                let len = BLK.min(n - p0);
                let (xb, gb) = (&xv[b * c * n..][..c * n], &gv[b * c * n..][..c * n]);
                fn row(v: &[f32], ci: usize, n: usize, p0: usize, len: usize) -> &[f32] {
                    &v[ci * n + p0..][..len]
                }
                let mut mean = vec![0f32; len];
                for ci in 0..c {
                    mean.iter_mut().zip(row(xb, ci, n, p0, len)).for_each(|(m, v)| *m += v);
                }
                mean.iter_mut().for_each(|m| *m /= c as f32);
                let mut r = vec![0f32; len];
                for ci in 0..c {
                    r.iter_mut().zip(row(xb, ci, n, p0, len).iter().zip(&mean)).for_each(|(s, (v, m))| *s += (v - m) * (v - m));
                }
                r.iter_mut().for_each(|s| *s = 1.0 / (*s / c as f32 + eps).sqrt());
                let (mut m1, mut m2) = (vec![0f32; len], vec![0f32; len]);
                let (mut dgam, mut dbet) = (vec![0f32; c], vec![0f32; c]);
                for ci in 0..c {
                    let (xr, gr) = (row(xb, ci, n, p0, len), row(gb, ci, n, p0, len));
                    for i in 0..len {
                        let xh = (xr[i] - mean[i]) * r[i];
                        let u = gr[i] * gam[ci];
                        m1[i] += u;
                        m2[i] += u * xh;
                        dgam[ci] += gr[i] * xh;
                        dbet[ci] += gr[i];
                    }
                }
                let mut dx = vec![0f32; c * len];
                for ci in 0..c {
                    let (xr, gr) = (row(xb, ci, n, p0, len), row(gb, ci, n, p0, len));
                    for i in 0..len {
                        let xh = (xr[i] - mean[i]) * r[i];
                        dx[ci * len + i] = r[i] * (gr[i] * gam[ci] - m1[i] / c as f32 - xh * m2[i] / c as f32);
                    }
                }
                (dx, dgam, dbet)
            })
            .collect();
        let mut dx = vec![0f32; xv.len()];
        let (mut dgam, mut dbet) = (vec![0f32; c], vec![0f32; c]);
        for (job, (px, pg, pb)) in parts.iter().enumerate() {
            let (b, p0) = (job / nblk, (job % nblk) * BLK);
            let len = BLK.min(n - p0);
            for ci in 0..c {
                dx[b * c * n + ci * n + p0..][..len].copy_from_slice(&px[ci * len..][..len]);
                dgam[ci] += pg[ci];
                dbet[ci] += pb[ci];
            }
        }
        let dev = x.device();
        Ok((Some(Tensor::from_vec(dx, dims, dev)?), Some(Tensor::from_vec(dgam, c, dev)?), Some(Tensor::from_vec(dbet, c, dev)?)))
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
    use crate::util::max_abs_diff;
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
            let conv = Conv3d::new(cin, cout, kk, pad, VarBuilder::from_tensors(ws, DType::F32, &Device::Cpu), Compute::Plain).unwrap();
            let fast = conv.forward_fast(&Volume::from_tensor(&x).unwrap(), None).unwrap().to_tensor().unwrap();
            assert!(max_abs_diff(&fast, &want).unwrap() < 1e-5, "fast path, case {i}");
            assert!(max_abs_diff(&conv.forward(&x).unwrap(), &fast).unwrap() < 1e-5);
        }
    }

    /// A `Conv3d` built with a bf16 compute runs its Winograd layers on bf16
    /// operands: within 1 % (relative L2) of the f32 reference, but not f32.
    #[test]
    fn conv3d_takes_the_build_precision() {
        let (cin, cout) = (64, 66);
        let x = rand(&[2, cin, 3, 4, 5], 90);
        let wt = (rand(&[cout, cin, 3, 3, 3], 91) * 0.1).unwrap();
        let b = rand(&[cout], 92);
        let want = conv_ref(&x, &wt, &b, 1).flatten_all().unwrap().to_vec1::<f32>().unwrap();
        let mut ws = HashMap::new();
        ws.insert("weight".to_string(), wt);
        ws.insert("bias".to_string(), b);
        let vb = VarBuilder::from_tensors(ws, DType::F32, &Device::Cpu);
        let vx = Volume::from_tensor(&x).unwrap();
        for (precision, format) in
            [(Precision::F32, WeightFormat::F32), (Precision::Bf16, WeightFormat::Bf16), (Precision::F16, WeightFormat::F32)]
        {
            let conv = Conv3d::new(cin, cout, 3, 1, vb.clone(), Compute::fast(precision)).unwrap();
            assert_eq!(conv.weight_format(), format);
            let got = conv.forward_fast(&vx, None).unwrap().data;
            let num: f64 = got.iter().zip(&want).map(|(a, b)| ((a - b) as f64).powi(2)).sum();
            let den: f64 = want.iter().map(|b| (*b as f64).powi(2)).sum();
            let rel = (num / den).sqrt();
            match format {
                WeightFormat::Bf16 => assert!(rel > 1e-5 && rel < 1e-2, "{precision}: relative error {rel}"),
                _ => assert!(rel < 1e-5, "{precision}: relative error {rel}"),
            }
        }
        // Plain: f32.
        assert_eq!(Conv3d::new(cin, cout, 3, 1, vb, Compute::Plain).unwrap().weight_format(), WeightFormat::F32);
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

    /// The custom-op convolution equals the plain-ops one in value and in
    /// both gradients (Winograd and im2col widths, k = 3 and k = 1).
    #[test]
    fn trainable_conv3d_matches_plain_ops_values_and_gradients() {
        for (i, &(bsz, cin, cout, d, h, w, kk, pad)) in
            [(2, 3, 5, 4, 5, 3, 3, 1), (1, 16, 16, 4, 4, 4, 3, 1), (2, 4, 3, 3, 2, 4, 1, 0), (1, 2, 2, 4, 4, 4, 3, 0)].iter().enumerate()
        {
            let x = candle_core::Var::from_tensor(&rand(&[bsz, cin, d, h, w], 40 + i as u64)).unwrap();
            let wt = candle_core::Var::from_tensor(&rand(&[cout, cin, kk, kk, kk], 50 + i as u64)).unwrap();
            let probe = rand(&[bsz, cout, d + 2 * pad + 1 - kk, h + 2 * pad + 1 - kk, w + 2 * pad + 1 - kk], 60 + i as u64);
            let b = candle_core::Var::from_tensor(&rand(&[cout], 70 + i as u64)).unwrap();
            let fast = conv3d_trainable(x.as_tensor(), wt.as_tensor(), b.as_tensor(), pad).unwrap();
            let plain = conv3d_candle(x.as_tensor(), wt.as_tensor(), Some(b.as_tensor()), pad).unwrap();
            assert!(max_abs_diff(&fast, &plain).unwrap() < 1e-4, "case {i}: values");
            let gf = (fast * &probe).unwrap().sum_all().unwrap().backward().unwrap();
            let gp = (plain * &probe).unwrap().sum_all().unwrap().backward().unwrap();
            for (name, v) in [("x", &x), ("w", &wt), ("b", &b)] {
                let d = max_abs_diff(gf.get(v).unwrap(), gp.get(v).unwrap()).unwrap();
                assert!(d < 1e-4, "case {i}: gradient wrt {name} differs by {d}");
            }
        }
    }

    /// The custom-op channel LayerNorm equals the plain-ops one in value and
    /// in the gradients of input, weight and bias.
    #[test]
    fn trainable_channel_layer_norm_matches_plain_ops() {
        let x = candle_core::Var::from_tensor(&(rand(&[2, 5, 3, 4, 300], 80) * 3.0).unwrap()).unwrap();
        let w = candle_core::Var::from_tensor(&(rand(&[5], 81) + 1.0).unwrap()).unwrap();
        let b = candle_core::Var::from_tensor(&rand(&[5], 82)).unwrap();
        let probe = rand(&[2, 5, 3, 4, 300], 83);
        let fast = channel_layer_norm_trainable(x.as_tensor(), w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
        let plain = channel_layer_norm_plain(x.as_tensor(), w.as_tensor(), b.as_tensor(), 1e-5).unwrap();
        assert!(max_abs_diff(&fast, &plain).unwrap() < 1e-5);
        let gf = (fast * &probe).unwrap().sum_all().unwrap().backward().unwrap();
        let gp = (plain * &probe).unwrap().sum_all().unwrap().backward().unwrap();
        for (name, v) in [("x", &x), ("w", &w), ("b", &b)] {
            // Relative to the gradient's size: w and b sum 7200 terms.
            let (a, p) = (gf.get(v).unwrap(), gp.get(v).unwrap());
            let scale = p.abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap().max(1.0);
            let d = max_abs_diff(a, p).unwrap() / scale as f64;
            assert!(d < 1e-5, "gradient wrt {name} differs by {d} (relative)");
        }
    }

    #[test]
    fn channel_layer_norm_paths_agree() {
        let x = rand(&[2, 5, 3, 4, 2], 3);
        let mut ws = HashMap::new();
        ws.insert("weight".to_string(), (rand(&[5], 4) + 1.0).unwrap());
        ws.insert("bias".to_string(), rand(&[5], 5));
        let ln = ChannelLayerNorm::new(5, VarBuilder::from_tensors(ws, DType::F32, &Device::Cpu)).unwrap();
        let a = ln.forward_plain(&x).unwrap();
        assert!(max_abs_diff(&a, &ln.forward(&x).unwrap()).unwrap() < 1e-5);
        let vx = Volume::from_tensor(&x).unwrap();
        let b = ln.forward_fast(&vx, false).unwrap().to_tensor().unwrap();
        assert!(max_abs_diff(&a, &b).unwrap() < 1e-5);
        let c = ln.forward_fast(&vx, true).unwrap().to_tensor().unwrap();
        assert!(max_abs_diff(&candle_nn::ops::silu(&a).unwrap(), &c).unwrap() < 1e-5);
        // Normalised over channels: per-position mean of (y - bias)/weight is ~0.
        let plain = crate::model::nn::common::layer_norm_plain(&x.permute((0, 2, 3, 4, 1)).unwrap(), 1e-5).unwrap();
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
        let want = x.get(1).unwrap().get((8 + 4) + 1).unwrap().get(1).unwrap().get(1).unwrap().get(0).unwrap().to_scalar::<f32>().unwrap();
        assert_eq!(v, want);
        let fast = pixel_shuffle_3d_fast(&Volume::from_tensor(&x).unwrap()).unwrap().to_tensor().unwrap();
        assert_eq!(max_abs_diff(&y, &fast).unwrap(), 0.0);
    }
}
