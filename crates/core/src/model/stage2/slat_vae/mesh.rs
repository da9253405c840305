//! Structured-latent mesh decoder (TRELLIS `SLatMeshDecoder`): the shared
//! trunk, two `SparseSubdivideBlock3d` (each doubles the resolution, so the
//! voxel count grows 8× per block), a linear to the FlexiCubes feature layout
//! (101 channels with colour, else 53), and FlexiCubes at `4·resolution`.
//!
//! Memory: the subdivided tensors are never materialised. Children copy their
//! parent's features, so the first conv of a block gathers straight from the
//! parent rows, the 1×1 skip conv runs at parent level and is broadcast, and
//! every conv works on fixed-size chunks of output rows (im2col per chunk).
//! The full-size tensors that remain are the block outputs themselves.

use crate::mesh::Mesh;
use crate::model::nn::common::linear;
use crate::model::nn::common::Linear;
use crate::model::nn::fast::Compute;
use crate::model::sparse::SparseTensor;
use crate::model::stage2::slat_vae::flexicubes::SparseFeatures2Mesh;
use crate::model::stage2::slat_vae::trunk::{SparseTransformerBase, TrunkArgs, TrunkConfig};
use crate::{Error, Result};
use candle_core::{DType, Module, Tensor};
use candle_nn::VarBuilder;
use recon_kernels::sparse::CoordHash;
use serde::{Deserialize, Serialize};
use std::ops::Range;

/// im2col elements per conv chunk (`rows · 27 · C_in`): bounds scratch memory.
const CONV_CHUNK_ELEMS: usize = 8 << 20;
/// Rows per chunk of the row-wise ops (norms, linears).
const ROW_CHUNK: usize = 1 << 16;

/// Child `ci` of a parent sits at `2·p + (ci>>2 & 1, ci>>1 & 1, ci & 1)`:
/// the order of `nonzero(ones(2,2,2))`, z fastest.
fn child_offset(ci: usize) -> [i32; 3] {
    [(ci >> 2) as i32 & 1, (ci >> 1) as i32 & 1, ci as i32 & 1]
}

/// Coordinates after `SparseSubdivide`: 8 consecutive children per parent.
pub fn subdivide_coords(coords: &[[i32; 4]]) -> Vec<[i32; 4]> {
    let mut out = Vec::with_capacity(coords.len() * 8);
    for c in coords {
        for ci in 0..8 {
            let d = child_offset(ci);
            out.push([c[0], 2 * c[1] + d[0], 2 * c[2] + d[1], 2 * c[3] + d[2]]);
        }
    }
    out
}

/// Neighbourhoods of a subdivided voxel set, derived from the parents'
/// 3×3×3 neighbour table (a child's neighbour lies in a neighbouring parent).
pub struct SubdivGrid {
    n_parent: usize,
    /// `[N_parent · 27]` parent row of each neighbour offset, `u32::MAX` if absent.
    parent_nbr: Vec<u32>,
}

impl SubdivGrid {
    /// The grid of the children of `parents` (coords `(b, x, y, z)`, rows in order).
    pub fn new(parents: &[[i32; 4]]) -> Self {
        let hash = CoordHash::new(parents);
        let mut parent_nbr = vec![u32::MAX; parents.len() * 27];
        for (p, c) in parents.iter().enumerate() {
            for o in 0..27 {
                let d = [(o / 9) as i32 - 1, ((o / 3) % 3) as i32 - 1, (o % 3) as i32 - 1];
                if let Some(r) = hash.get([c[0], c[1] + d[0], c[2] + d[1], c[3] + d[2]]) {
                    parent_nbr[p * 27 + o] = r;
                }
            }
        }
        Self { n_parent: parents.len(), parent_nbr }
    }

    /// Number of child voxels, `8 · N_parent`.
    pub fn num_children(&self) -> usize {
        self.n_parent * 8
    }

    /// Child-row neighbour of child `r` at kernel offset `o = (i·3 + j)·3 + l`
    /// (displacement `(i-1, j-1, l-1)`), if active.
    #[inline]
    fn child_neighbour(&self, r: usize, o: usize) -> Option<usize> {
        let (p, d) = (r / 8, child_offset(r % 8));
        let k = [(o / 9) as i32 - 1, ((o / 3) % 3) as i32 - 1, (o % 3) as i32 - 1];
        let mut po = 0usize;
        let mut ci = 0usize;
        for a in 0..3 {
            let s = d[a] + k[a]; // -1..=2
            po = po * 3 + (s.div_euclid(2) + 1) as usize;
            ci = ci * 2 + s.rem_euclid(2) as usize;
        }
        match self.parent_nbr[p * 27 + po] {
            u32::MAX => None,
            q => Some(q as usize * 8 + ci),
        }
    }
}

/// Submanifold 3×3×3 conv over the subdivided voxels, plain candle ops
/// (differentiable), chunked over output rows.
/// `src` holds parent rows when `src_is_parent` (each child reads its
/// parent's features), else child rows. `w_t` is `[27·C_in, C_out]`.
fn subdiv_conv(grid: &SubdivGrid, src: &Tensor, src_is_parent: bool, w_t: &Tensor, bias: &Tensor) -> Result<Tensor> {
    subdiv_conv_then(grid, src, src_is_parent, w_t, bias, w_t.dim(1)?, &|_, t| Ok(t))
}

/// [`subdiv_conv`] with an epilogue applied to each output chunk (given its
/// child-row offset) before concatenation, so that per-row follow-up ops never
/// need a second full-size tensor. `c_final` is the epilogue's width.
fn subdiv_conv_then(
    grid: &SubdivGrid,
    src: &Tensor,
    src_is_parent: bool,
    w_t: &Tensor,
    bias: &Tensor,
    c_final: usize,
    epilogue: &dyn Fn(usize, Tensor) -> Result<Tensor>,
) -> Result<Tensor> {
    let c_in = src.dim(1)?;
    let n = grid.num_children();
    let rows = ((CONV_CHUNK_ELEMS / (27 * c_in)).max(64) / 8) * 8;
    let mut outs = Vec::with_capacity(n.div_ceil(rows));
    let mut r0 = 0;
    while r0 < n {
        let len = rows.min(n - r0);
        let mut idx = Vec::with_capacity(len * 27);
        let mut mask = Vec::with_capacity(len * 27);
        for r in r0..r0 + len {
            for o in 0..27 {
                match grid.child_neighbour(r, o) {
                    Some(q) => {
                        idx.push(if src_is_parent { (q / 8) as u32 } else { q as u32 });
                        mask.push(1f32);
                    }
                    None => {
                        idx.push(0);
                        mask.push(0f32);
                    }
                }
            }
        }
        let idx = Tensor::from_vec(idx, len * 27, src.device())?;
        let mask = Tensor::from_vec(mask, (len * 27, 1), src.device())?.to_dtype(src.dtype())?;
        let cols = src.index_select(&idx, 0)?.broadcast_mul(&mask)?.reshape((len, 27 * c_in))?;
        outs.push(epilogue(r0, cols.matmul(w_t)?.broadcast_add(bias)?)?);
        r0 += len;
    }
    cat_rows(outs, c_final, src)
}

fn cat_rows(mut outs: Vec<Tensor>, c: usize, like: &Tensor) -> Result<Tensor> {
    match outs.len() {
        0 => Ok(Tensor::zeros((0, c), like.dtype(), like.device())?),
        1 => Ok(outs.pop().unwrap()),
        _ => Ok(Tensor::cat(&outs, 0)?),
    }
}

/// Apply `f` to row chunks of `x` and concatenate.
fn map_rows(x: &Tensor, c_out: usize, f: impl Fn(&Tensor) -> Result<Tensor>) -> Result<Tensor> {
    let n = x.dim(0)?;
    let mut outs = Vec::with_capacity(n.div_ceil(ROW_CHUNK));
    let mut r0 = 0;
    while r0 < n {
        let len = ROW_CHUNK.min(n - r0);
        outs.push(f(&x.narrow(0, r0, len)?)?);
        r0 += len;
    }
    cat_rows(outs, c_out, x)
}

/// `SparseGroupNorm32`: GroupNorm over each batch item's voxels (stats over
/// `C/G` channels × all its rows), eps 1e-5, affine; computed in f32.
#[derive(Debug, Clone)]
pub struct SparseGroupNorm {
    groups: usize,
    weight: Tensor,
    bias: Tensor,
    eps: f64,
}

impl SparseGroupNorm {
    /// `groups` groups over `channels`, affine `weight` and `bias` under `vb`; `channels` must be a multiple of `groups`.
    pub fn new(groups: usize, channels: usize, vb: VarBuilder) -> Result<Self> {
        if groups == 0 || !channels.is_multiple_of(groups) {
            return Err(Error::msg(format!("group norm: {channels} channels not divisible into {groups} groups")));
        }
        Ok(Self { groups, weight: vb.get(channels, "weight")?, bias: vb.get(channels, "bias")?, eps: 1e-5 })
    }

    /// Normalise `x` `[N, C]` per batch range, then apply `SiLU` if `silu`.
    pub fn forward(&self, x: &Tensor, ranges: &[Range<usize>], silu: bool) -> Result<Tensor> {
        let (_, c) = x.dims2()?;
        let (g, cg) = (self.groups, c / self.groups);
        let dtype = x.dtype();
        let x = x.to_dtype(DType::F32)?;
        let mut outs = Vec::new();
        for r in ranges.iter().filter(|r| !r.is_empty()) {
            let xb = x.narrow(0, r.start, r.len())?;
            let count = (r.len() * cg) as f64;
            // Two passes over row chunks: mean, then centred variance.
            let group_sum = |t: &Tensor| -> Result<Tensor> {
                let n = t.dim(0)?;
                Ok(t.reshape((n, g, cg))?.sum(2)?.sum(0)?)
            };
            let mean = (chunked_sum(&xb, g, &group_sum)? / count)?; // [G]
            let mean_c = mean.unsqueeze(1)?.broadcast_as((g, cg))?.reshape(c)?;
            let var = (chunked_sum(&xb, g, &|t: &Tensor| group_sum(&t.broadcast_sub(&mean_c)?.sqr()?))? / count)?;
            let inv = (var + self.eps)?.sqrt()?.recip()?.unsqueeze(1)?.broadcast_as((g, cg))?.reshape(c)?;
            let scale = (inv * &self.weight)?;
            let shift = (&self.bias - (&mean_c * &scale)?)?;
            outs.push(map_rows(&xb, c, |t| {
                let y = t.broadcast_mul(&scale)?.broadcast_add(&shift)?;
                Ok(if silu { y.silu()? } else { y })
            })?);
        }
        Ok(cat_rows(outs, c, &x)?.to_dtype(dtype)?)
    }
}

fn chunked_sum(x: &Tensor, g: usize, f: &dyn Fn(&Tensor) -> Result<Tensor>) -> Result<Tensor> {
    let n = x.dim(0)?;
    let mut acc = Tensor::zeros(g, DType::F32, x.device())?;
    let mut r0 = 0;
    while r0 < n {
        let len = ROW_CHUNK.min(n - r0);
        acc = (acc + f(&x.narrow(0, r0, len)?)?)?;
        r0 += len;
    }
    Ok(acc)
}

/// A submanifold conv's parameters in im2col form.
#[derive(Debug, Clone)]
struct ConvParams {
    /// `[k³·C_in, C_out]` (spconv `[C_out, k, k, k, C_in]`, transposed).
    w_t: Tensor,
    bias: Tensor,
}

impl ConvParams {
    fn new(c_in: usize, c_out: usize, k: usize, vb: VarBuilder) -> Result<Self> {
        let w = vb.get((c_out, k, k, k, c_in), "conv.weight")?;
        let w_t = if k == 1 {
            // spconv's 1×1×1 SubMConv3d multiplies by the weight's memory viewed as
            // [C_in, C_out] (not the transpose of [C_out, C_in]); the released
            // weights were trained that way, and the fixture confirms it.
            w.reshape((c_in, c_out))?
        } else {
            w.reshape((c_out, k * k * k * c_in))?.t()?.contiguous()?
        };
        Ok(Self { w_t, bias: vb.get(c_out, "conv.bias")? })
    }
}

/// `SparseSubdivideBlock3d(C, C_out)`:
/// `out_layers(sub(SiLU(GN(x)))) + skip(sub(x))` with
/// `out_layers = conv3 → GN → SiLU → conv3`, skip a 1×1 conv (or identity).
#[derive(Debug, Clone)]
pub struct SparseSubdivideBlock3d {
    act_norm: SparseGroupNorm,
    conv0: ConvParams,
    out_norm: SparseGroupNorm,
    conv3: ConvParams,
    skip: Option<ConvParams>,
    /// Output channels `C_out`.
    pub out_channels: usize,
}

impl SparseSubdivideBlock3d {
    /// Block `channels → out_channels` with weights under `vb` (`act_layers.0`, `out_layers.{0,1,3}`, `skip_connection`).
    pub fn new(channels: usize, out_channels: usize, vb: VarBuilder) -> Result<Self> {
        let skip =
            if out_channels != channels { Some(ConvParams::new(channels, out_channels, 1, vb.pp("skip_connection"))?) } else { None };
        Ok(Self {
            act_norm: SparseGroupNorm::new(32, channels, vb.pp("act_layers.0"))?,
            conv0: ConvParams::new(channels, out_channels, 3, vb.pp("out_layers.0"))?,
            out_norm: SparseGroupNorm::new(32, out_channels, vb.pp("out_layers.1"))?,
            conv3: ConvParams::new(out_channels, out_channels, 3, vb.pp("out_layers.3"))?,
            skip,
            out_channels,
        })
    }

    /// `x` is the parent tensor; returns the subdivided output (children of
    /// parent `p` at rows `8p..8p+8`, coords from [`subdivide_coords`]).
    pub fn forward(&self, x: &SparseTensor) -> Result<SparseTensor> {
        self.forward_then(x, self.out_channels, &|t| Ok(t))
    }

    /// [`Self::forward`] followed by a row-wise map `post` (output width
    /// `c_post`), applied chunk by chunk so the block output at
    /// `out_channels` is never held in full.
    pub fn forward_then(&self, x: &SparseTensor, c_post: usize, post: &dyn Fn(Tensor) -> Result<Tensor>) -> Result<SparseTensor> {
        let grid = SubdivGrid::new(&x.coords);
        let parent_ranges = x.batch_ranges();
        let child_ranges: Vec<Range<usize>> = parent_ranges.iter().map(|r| r.start * 8..r.end * 8).collect();
        let c = self.out_channels;

        // Nested scopes free each full-size intermediate as soon as it is consumed
        // (shadowed bindings would live to the end of the function).
        let h = {
            let conv_in = self.act_norm.forward(&x.feats, &parent_ranges, true)?;
            let conv_out = subdiv_conv(&grid, &conv_in, true, &self.conv0.w_t, &self.conv0.bias)?;
            drop(conv_in);
            self.out_norm.forward(&conv_out, &child_ranges, true)?
        };
        // Skip at parent level (a 1×1 conv commutes with subdivision), added
        // to each output chunk by broadcasting over the 8 children.
        let skip = match &self.skip {
            Some(p) => map_rows(&x.feats, c, |t| Ok(t.matmul(&p.w_t)?.broadcast_add(&p.bias)?))?,
            None => x.feats.clone(),
        };
        let out = subdiv_conv_then(&grid, &h, false, &self.conv3.w_t, &self.conv3.bias, c_post, &|r0, t| {
            let len = t.dim(0)?; // chunks are multiples of 8 rows, aligned to parents
            let s = skip.narrow(0, r0 / 8, len / 8)?.unsqueeze(1)?.broadcast_as((len / 8, 8, c))?.reshape((len, c))?;
            post((t + s)?)
        })?;
        SparseTensor::new(subdivide_coords(&x.coords), out, x.batch_size)
    }
}

/// Constructor args of `SLatMeshDecoder` (checkpoint `args`): the trunk's
/// plus `resolution` and `representation_config.use_color`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MeshDecoderConfig {
    /// The trunk's args (flattened).
    #[serde(flatten)]
    pub trunk: TrunkArgs,
    /// Side of the latent voxel grid (upstream `resolution`); meshes are extracted at `4·resolution`.
    pub resolution: usize,
    /// Representation settings (upstream `representation_config`; only `use_color` is read).
    #[serde(default)]
    pub representation_config: MeshRepresentationConfig,
}

/// `representation_config` of the mesh decoder; other keys are ignored.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct MeshRepresentationConfig {
    /// Vertex colours as extra FlexiCubes channels.
    #[serde(default)]
    pub use_color: bool,
}

impl MeshDecoderConfig {
    /// Parse the decoder's `args`; errors name `file` and the field.
    pub fn from_json(v: &serde_json::Value, file: &str) -> Result<Self> {
        crate::model::stage2::slat_vae::trunk::from_json_with_trunk(v, file)
    }
}

/// The structured-latent mesh decoder (TRELLIS `SLatMeshDecoder`).
pub struct SLatMeshDecoder {
    /// The sparse transformer trunk.
    pub trunk: SparseTransformerBase,
    /// The two subdivide blocks: `model_channels` → `model_channels / 4` → `model_channels / 8` channels.
    pub upsample: Vec<SparseSubdivideBlock3d>,
    /// Linear from `model_channels / 8` to the FlexiCubes features per cube.
    pub out_layer: Linear,
    /// FlexiCubes extraction at `4·resolution`.
    pub extractor: SparseFeatures2Mesh,
    /// Side of the latent voxel grid.
    pub resolution: usize,
}

impl SLatMeshDecoder {
    /// Built from its config (upstream's args: `resolution`, trunk args,
    /// `representation_config.use_color`).
    pub fn new(args: &MeshDecoderConfig, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let tcfg = TrunkConfig::new(&args.trunk)?;
        let (resolution, use_color) = (args.resolution, args.representation_config.use_color);
        let c = tcfg.model_channels;
        let trunk = SparseTransformerBase::new(&tcfg, vb.clone(), compute)?;
        let upsample = vec![
            SparseSubdivideBlock3d::new(c, c / 4, vb.pp("upsample.0"))?,
            SparseSubdivideBlock3d::new(c / 4, c / 8, vb.pp("upsample.1"))?,
        ];
        let extractor = SparseFeatures2Mesh::new(resolution * 4, use_color);
        let out_layer = linear(c / 8, extractor.channels(), vb.pp("out_layer"), compute)?;
        Ok(Self { trunk, upsample, out_layer, extractor, resolution })
    }

    /// Network part: per-cube FlexiCubes features at `4·resolution`.
    /// `tap(name, tensor)` sees the trunk taps, `upsample.{i}` and `out_layer`.
    pub fn forward_feats(&self, x: &SparseTensor, tap: &mut dyn FnMut(&str, &SparseTensor)) -> Result<SparseTensor> {
        let h = self.trunk.forward_with(x, &mut |name, t| {
            if let Ok(st) = x.with_feats(t.clone()) {
                tap(name, &st)
            }
        })?;
        let mut h = x.with_feats(h)?;
        for (i, blk) in self.upsample.iter().enumerate() {
            h = blk.forward(&h)?;
            tap(&format!("upsample.{i}"), &h);
        }
        let ch = self.extractor.channels();
        let feats = map_rows(&h.feats, ch, |t| Ok(self.out_layer.forward(t)?))?;
        let out = h.with_feats(feats)?;
        drop(h);
        tap("out_layer", &out);
        Ok(out)
    }

    /// Same result as [`Self::forward_feats`] without taps, with the output
    /// layer fused into the last block's chunks (lower peak memory).
    pub fn forward_feats_fused(&self, x: &SparseTensor) -> Result<SparseTensor> {
        let mut h = x.with_feats(self.trunk.forward(x)?)?;
        let last = self.upsample.len() - 1;
        for blk in &self.upsample[..last] {
            h = blk.forward(&h)?;
        }
        self.upsample[last].forward_then(&h, self.extractor.channels(), &|t| Ok(self.out_layer.forward(&t)?))
    }

    /// One mesh per batch item.
    pub fn forward(&self, x: &SparseTensor) -> Result<Vec<Mesh>> {
        let feats = self.forward_feats_fused(x)?;
        self.extractor.extract_sparse(&feats)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn subdivided_conv_matches_sparse_conv_kernel() -> Result<()> {
        use recon_kernels::sparse::{submanifold_conv3d, NeighbourMap};
        let parents: Vec<[i32; 4]> = (0..40).map(|i| [i / 30, (i * 7) % 5, (i * 3) % 4, i % 3]).collect();
        let mut parents = parents;
        parents.sort();
        parents.dedup();
        let (c_in, c_out) = (8, 5);
        let dev = Device::Cpu;
        let children = subdivide_coords(&parents);
        let xc = Tensor::randn(0f32, 1.0, (children.len(), c_in), &dev)?;
        let w = Tensor::randn(0f32, 1.0, (c_out, 3, 3, 3, c_in), &dev)?;
        let b = Tensor::randn(0f32, 1.0, c_out, &dev)?;
        let map = NeighbourMap::submanifold(&children, 3).map_err(Error::msg)?;
        let want = submanifold_conv3d(
            &xc.flatten_all()?.to_vec1::<f32>()?,
            c_in,
            &map,
            &w.flatten_all()?.to_vec1::<f32>()?,
            Some(&b.to_vec1::<f32>()?),
            c_out,
        )
        .map_err(Error::msg)?;
        let w_t = w.reshape((c_out, 27 * c_in))?.t()?.contiguous()?;
        let got = subdiv_conv(&SubdivGrid::new(&parents), &xc, false, &w_t, &b)?.flatten_all()?.to_vec1::<f32>()?;
        let d = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        assert!(d < 1e-4, "subdivide conv vs kernel: {d}");
        Ok(())
    }

    /// Reference submanifold conv over explicit child coordinates (hash lookup per offset).
    fn naive_conv(coords: &[[i32; 4]], x: &[Vec<f32>], w: &[f32], c_in: usize, c_out: usize) -> Vec<Vec<f32>> {
        let hash = CoordHash::new(coords);
        coords
            .iter()
            .map(|c| {
                let mut o = vec![0f32; c_out];
                for k in 0..27 {
                    let d = [(k / 9) as i32 - 1, ((k / 3) % 3) as i32 - 1, (k % 3) as i32 - 1];
                    if let Some(r) = hash.get([c[0], c[1] + d[0], c[2] + d[1], c[3] + d[2]]) {
                        for (co, ov) in o.iter_mut().enumerate() {
                            for ci in 0..c_in {
                                *ov += w[(co * 27 + k) * c_in + ci] * x[r as usize][ci];
                            }
                        }
                    }
                }
                o
            })
            .collect()
    }

    #[test]
    fn subdivided_conv_matches_explicit_subdivision() -> Result<()> {
        let parents: Vec<[i32; 4]> = vec![[0, 0, 0, 0], [0, 1, 0, 0], [0, 1, 1, 0], [0, 3, 2, 1], [0, 2, 2, 1], [1, 0, 0, 0], [1, 0, 0, 1]];
        let (c_in, c_out) = (3, 2);
        let dev = Device::Cpu;
        let xp = Tensor::randn(0f32, 1.0, (parents.len(), c_in), &dev)?;
        let w = Tensor::randn(0f32, 1.0, (c_out, 3, 3, 3, c_in), &dev)?;
        let w_t = w.reshape((c_out, 27 * c_in))?.t()?.contiguous()?;
        let bias = Tensor::zeros(c_out, DType::F32, &dev)?;
        let grid = SubdivGrid::new(&parents);
        let children = subdivide_coords(&parents);
        // Explicit subdivision: each child copies its parent's row.
        let xp_rows = xp.to_vec2::<f32>()?;
        let xc: Vec<Vec<f32>> = (0..children.len()).map(|r| xp_rows[r / 8].clone()).collect();
        let wv = w.flatten_all()?.to_vec1::<f32>()?;
        let want = naive_conv(&children, &xc, &wv, c_in, c_out);
        let got = subdiv_conv(&grid, &xp, true, &w_t, &bias)?.to_vec2::<f32>()?;
        for (g, wnt) in got.iter().zip(&want) {
            for (a, b) in g.iter().zip(wnt) {
                assert!((a - b).abs() < 1e-4, "{a} vs {b}");
            }
        }
        // Child-level source gives the same when the child rows are the copies.
        let xc_t = Tensor::new(xc.concat(), &dev)?.reshape((children.len(), c_in))?;
        let got2 = subdiv_conv(&grid, &xc_t, false, &w_t, &bias)?.to_vec2::<f32>()?;
        assert_eq!(got, got2);
        // Child order: z fastest.
        assert_eq!(children[1], [0, 0, 0, 1]);
        assert_eq!(children[4], [0, 1, 0, 0]);
        Ok(())
    }
}
