//! RecGen conditioning embedders shared by both stages (RecGen
//! `SparseStructurePoseFlowModel` and `SLatCondFlowModel`):
//!
//! - `point_embedder`: Conv2d(3→C, k14, s14) over the XYZ pointmap;
//! - `mask_embedder`: Conv2d(1→C, k14, s14) over the object mask;
//! - `frame_token_embedder`: a `[2, C]` parameter added to the patch tokens of
//!   view 0 / view 1 (stage 1 only).
//!
//! The 14×14/stride-14 convolutions see exactly one DINOv2 patch each, so their
//! flattened `[B, h·w, C]` output (row-major over the patch grid) adds 1:1 to
//! the DINOv2 patch tokens (CLS and register tokens stripped).

use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};

/// Patch size of the DINOv2 backbone the embedders align with.
pub const PATCH: usize = 14;

/// A Conv2d(k=14, s=14) turning an image-like input into patch tokens.
#[derive(Debug, Clone)]
pub struct PatchEmbedder {
    conv: Conv2d,
    in_channels: usize,
    out_channels: usize,
}

impl PatchEmbedder {
    fn new(in_channels: usize, out_channels: usize, vb: VarBuilder) -> Result<Self> {
        let cfg = Conv2dConfig { stride: PATCH, ..Default::default() };
        let conv = candle_nn::conv2d(in_channels, out_channels, PATCH, cfg, vb)?;
        Ok(Self { conv, in_channels, out_channels })
    }

    /// `x` `[B, Cin, H, W]` (H, W multiples of 14) → tokens `[B, (H/14)·(W/14), C]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (_, c, h, w) = x.dims4()?;
        if c != self.in_channels || h % PATCH != 0 || w % PATCH != 0 {
            candle_core::bail!("patch embedder: expected [B, {}, 14·h, 14·w], got {:?}", self.in_channels, x.dims());
        }
        let f = self.conv.forward(x)?; // [B, C, h, w]
        f.flatten_from(2)?.transpose(1, 2)?.contiguous()
    }

    /// Token width C.
    pub fn out_channels(&self) -> usize {
        self.out_channels
    }
}

/// The point-map and mask embedder settings both flow transformers share (RecGen
/// `SparseStructureFlowModel` and `SLatCondFlowModel` args, flattened into each config).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CondEmbedderConfig {
    /// Whether the point-map embedder adds its tokens to the condition.
    #[serde(default)]
    pub use_point_embedder: bool,
    /// Width of the point-map embedder's tokens.
    #[serde(default = "default_embed_channels")]
    pub point_embedder_out_channels: usize,
    /// Whether the mask embedder adds its tokens to the condition.
    #[serde(default)]
    pub use_mask_embedder: bool,
    /// Width of the mask embedder's tokens.
    #[serde(default = "default_embed_channels")]
    pub mask_embedder_out_channels: usize,
}

fn default_embed_channels() -> usize {
    1024
}

/// `point_embedder`: Conv2d(3→C, 14/14) over the normalised pointmap.
#[derive(Debug, Clone)]
pub struct PointmapEmbedder(pub PatchEmbedder);

impl PointmapEmbedder {
    /// `vb` is the model root; weights are `point_embedder.{weight,bias}`.
    pub fn new(out_channels: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self(PatchEmbedder::new(3, out_channels, vb.pp("point_embedder"))?))
    }
    /// `[B, 3, H, W]` → `[B, (H/14)(W/14), C]`.
    pub fn forward(&self, pointmap: &Tensor) -> Result<Tensor> {
        self.0.forward(pointmap)
    }
}

/// `mask_embedder`: Conv2d(1→C, 14/14) over the {0,1} mask.
#[derive(Debug, Clone)]
pub struct MaskEmbedder(pub PatchEmbedder);

impl MaskEmbedder {
    /// `vb` is the model root; weights are `mask_embedder.{weight,bias}`.
    pub fn new(out_channels: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self(PatchEmbedder::new(1, out_channels, vb.pp("mask_embedder"))?))
    }
    /// `[B, 1, H, W]` → `[B, (H/14)(W/14), C]`.
    pub fn forward(&self, mask: &Tensor) -> Result<Tensor> {
        self.0.forward(mask)
    }
}

/// `frame_token_embedder`: learned `[2, C]` view-type embedding (a bare
/// parameter, so the checkpoint name has no `.weight` suffix).
#[derive(Debug, Clone)]
pub struct FrameTokenEmbedder {
    weight: Tensor,
}

impl FrameTokenEmbedder {
    /// `vb` is the model root; the `[2, channels]` parameter is `frame_token_embedder`.
    pub fn new(channels: usize, vb: VarBuilder) -> Result<Self> {
        Ok(Self { weight: vb.get((2, channels), "frame_token_embedder")? })
    }

    /// `views` `[B, F, N, C]` with F ≤ 2 → `[B, F·N, C]`, view f gets row f added.
    pub fn forward(&self, views: &Tensor) -> Result<Tensor> {
        let (b, f, n, c) = views.dims4()?;
        if f > self.weight.dim(0)? {
            candle_core::bail!("frame token embedder: {f} views but only {} frame embeddings", self.weight.dim(0)?);
        }
        let e = self.weight.narrow(0, 0, f)?.reshape((1, f, 1, c))?;
        views.broadcast_add(&e)?.reshape((b, f * n, c))
    }
}

/// One view's conditioning inputs.
#[derive(Debug, Clone)]
pub struct ViewInputs {
    /// DINOv2 patch tokens after the final LayerNorm, CLS/registers stripped: `[B, N, C]`.
    pub patch_tokens: Tensor,
    /// Normalised pointmap `[B, 3, H, W]`, H = W = 14·√N.
    pub pointmap: Option<Tensor>,
    /// Mask `[B, 1, H, W]` in {0, 1}.
    pub mask: Option<Tensor>,
}

/// The embedders a model owns (any may be absent).
#[derive(Debug, Clone, Copy, Default)]
pub struct CondEmbedders<'a> {
    /// Point-map embedder, if the model has one.
    pub point: Option<&'a PointmapEmbedder>,
    /// Mask embedder, if the model has one.
    pub mask: Option<&'a MaskEmbedder>,
    /// Frame-token embedder, if the model has one.
    pub frame: Option<&'a FrameTokenEmbedder>,
}

/// Build `(cond, neg_cond)` as RecGen's `get_cond` / `get_cond_multiview` do:
/// 1. patch tokens of every view; with ≥ 2 views and a frame embedder, add the
///    per-view frame embedding; concatenate views along the sequence;
/// 2. `neg_cond` = zeros of that shape, taken *before* step 3 (and without the
///    frame embeddings' effect, since it is zeros);
/// 3. add the concatenated pointmap features and mask features (only when the
///    inputs are given).
///
/// A pointmap or mask given to a model without the matching embedder is an error.
pub fn build_condition(views: &[ViewInputs], emb: CondEmbedders) -> Result<(Tensor, Tensor)> {
    if views.is_empty() {
        candle_core::bail!("build_condition: no views");
    }
    let tokens: Vec<Tensor> = views.iter().map(|v| v.patch_tokens.clone()).collect();
    let mut cond = match (views.len() > 1, emb.frame) {
        (true, Some(frame)) => frame.forward(&Tensor::stack(&tokens, 1)?)?,
        _ => Tensor::cat(&tokens, 1)?,
    };
    let neg = cond.zeros_like()?;
    // Upstream adds pointmap features only if every view has one (a list is
    // passed or not); a partial set would misalign with the token sequence.
    let n_pm = views.iter().filter(|v| v.pointmap.is_some()).count();
    if n_pm > 0 {
        let Some(pe) = emb.point else { candle_core::bail!("pointmap given but the model has no point_embedder") };
        if n_pm != views.len() {
            candle_core::bail!("pointmap given for {n_pm} of {} views; give all or none", views.len());
        }
        let feats: Vec<Tensor> = views.iter().map(|v| pe.forward(v.pointmap.as_ref().unwrap())).collect::<Result<_>>()?;
        cond = cond.add(&Tensor::cat(&feats, 1)?)?;
    }
    let n_m = views.iter().filter(|v| v.mask.is_some()).count();
    if n_m > 0 {
        let Some(me) = emb.mask else { candle_core::bail!("mask given but the model has no mask_embedder") };
        if n_m != views.len() {
            candle_core::bail!("mask given for {n_m} of {} views; give all or none", views.len());
        }
        let feats: Vec<Tensor> = views.iter().map(|v| me.forward(v.mask.as_ref().unwrap())).collect::<Result<_>>()?;
        cond = cond.add(&Tensor::cat(&feats, 1)?)?;
    }
    Ok((cond, neg))
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use std::collections::HashMap;

    fn vb_with(ts: Vec<(&str, Tensor)>) -> VarBuilder<'static> {
        let m: HashMap<String, Tensor> = ts.into_iter().map(|(k, v)| (k.to_string(), v)).collect();
        VarBuilder::from_tensors(m, DType::F32, &Device::Cpu)
    }

    #[test]
    fn pointmap_tokens_align_with_patch_grid() -> Result<()> {
        let dev = Device::Cpu;
        let c = 8;
        let (gh, gw) = (3usize, 4usize); // patch grid 3×4 → image 42×56
        let w = Tensor::randn(0f32, 1.0, (c, 3, PATCH, PATCH), &dev)?;
        let b = Tensor::randn(0f32, 1.0, c, &dev)?;
        let pe = PointmapEmbedder::new(c, vb_with(vec![("point_embedder.weight", w), ("point_embedder.bias", b.clone())]))?;
        let (r, col) = (2usize, 1usize);
        let mut img = vec![0f32; 3 * gh * PATCH * gw * PATCH];
        for ch in 0..3 {
            for y in r * PATCH..(r + 1) * PATCH {
                for x in col * PATCH..(col + 1) * PATCH {
                    img[(ch * gh * PATCH + y) * gw * PATCH + x] = 1.0 + (x + y + ch) as f32 * 0.01;
                }
            }
        }
        let img = Tensor::from_vec(img, (1, 3, gh * PATCH, gw * PATCH), &dev)?;
        let tok = pe.forward(&img)?;
        assert_eq!(tok.dims(), &[1, gh * gw, c]);
        let diff = tok.squeeze(0)?.broadcast_sub(&b)?.abs()?.max(1)?.to_vec1::<f32>()?;
        for (i, d) in diff.iter().enumerate() {
            if i == r * gw + col {
                assert!(*d > 1e-3, "token {i} should carry the patch signal");
            } else {
                assert!(*d < 1e-6, "token {i} should be bias only, diff {d}");
            }
        }
        Ok(())
    }

    #[test]
    fn mask_tokens_align_with_patch_grid() -> Result<()> {
        let dev = Device::Cpu;
        let c = 4;
        let w = Tensor::randn(0f32, 1.0, (c, 1, PATCH, PATCH), &dev)?;
        let b = Tensor::zeros(c, DType::F32, &dev)?;
        let me = MaskEmbedder::new(c, vb_with(vec![("mask_embedder.weight", w), ("mask_embedder.bias", b)]))?;
        let mut m = vec![0f32; 28 * 28];
        m[14 * 28 + 20] = 1.0; // row 14 (patch row 1), col 20 (patch col 1)
        let m = Tensor::from_vec(m, (1, 1, 28, 28), &dev)?;
        let tok = me.forward(&m)?.squeeze(0)?.abs()?.max(1)?.to_vec1::<f32>()?;
        assert_eq!(tok.len(), 4);
        assert!(tok[3] > 0.0 && tok[0] == 0.0 && tok[1] == 0.0 && tok[2] == 0.0);
        Ok(())
    }

    #[test]
    fn condition_two_views_adds_frames_and_zero_negative() -> Result<()> {
        let dev = Device::Cpu;
        let c = 4;
        let frame = Tensor::new(&[[1f32, 1., 1., 1.], [2., 2., 2., 2.]], &dev)?;
        let fe = FrameTokenEmbedder::new(c, vb_with(vec![("frame_token_embedder", frame)]))?;
        let v0 = Tensor::zeros((1, 3, c), DType::F32, &dev)?;
        let v1 = Tensor::ones((1, 3, c), DType::F32, &dev)?;
        let views =
            vec![ViewInputs { patch_tokens: v0, pointmap: None, mask: None }, ViewInputs { patch_tokens: v1, pointmap: None, mask: None }];
        let (cond, neg) = build_condition(&views, CondEmbedders { frame: Some(&fe), ..Default::default() })?;
        assert_eq!(cond.dims(), &[1, 6, c]);
        let v = cond.squeeze(0)?.to_vec2::<f32>()?;
        assert_eq!(v[0], vec![1.0; 4]);
        assert_eq!(v[5], vec![3.0; 4]);
        assert_eq!(neg.dims(), &[1, 6, c]);
        assert_eq!(neg.abs()?.sum_all()?.to_scalar::<f32>()?, 0.0);
        // A single view gets no frame embedding.
        let (cond1, _) = build_condition(&views[1..], CondEmbedders { frame: Some(&fe), ..Default::default() })?;
        assert_eq!(cond1.squeeze(0)?.to_vec2::<f32>()?[0], vec![1.0; 4]);
        // Pointmap without an embedder is rejected.
        let bad = vec![ViewInputs {
            patch_tokens: Tensor::zeros((1, 1, c), DType::F32, &dev)?,
            pointmap: Some(Tensor::zeros((1, 3, 14, 14), DType::F32, &dev)?),
            mask: None,
        }];
        assert!(build_condition(&bad, CondEmbedders::default()).is_err());
        Ok(())
    }
}
