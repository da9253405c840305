//! DINOv2 ViT with register tokens (`dinov2_vitl14_reg`), the image encoder
//! of TRELLIS and RecGen. Parameters use the torch.hub checkpoint names
//! (`cls_token`, `pos_embed`, `register_tokens`, `patch_embed.proj`,
//! `blocks.{i}.*`, `norm`), so `dinov2_vitl14_reg4_pretrain.pth` maps 1:1.
//!
//! Token layout: `[cls, reg_0..reg_{R-1}, patches]`. The position embedding
//! covers cls + patches and is added *before* the registers are inserted, so
//! registers carry no position.

use crate::model::nn::common::{attention, layer_norm_plain, linear, LayerNorm, Linear};
use crate::model::nn::fast::{self, Activation, AttnLayout, AttnSegment, Compute};
use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2d, Conv2dConfig, VarBuilder};
use serde::{Deserialize, Serialize};

/// Hyper-parameters of a DINOv2 ViT with registers.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dinov2Config {
    /// Token width D (hub `embed_dim`, HF `hidden_size`).
    pub embed_dim: usize,
    /// Number of transformer blocks (hub `depth`, HF `num_hidden_layers`).
    pub depth: usize,
    /// Attention heads (hub `num_heads`, HF `num_attention_heads`).
    pub num_heads: usize,
    /// MLP hidden width as a multiple of D (`mlp_ratio`).
    pub mlp_ratio: f64,
    /// Patch side in pixels (`patch_size`).
    pub patch_size: usize,
    /// Image side the position embedding was trained for (518 for the hub models).
    pub img_size: usize,
    /// Register tokens R (`num_register_tokens`).
    pub num_register_tokens: usize,
    /// Image channels (hub `in_chans`, HF `num_channels`; default 3).
    #[serde(default = "default_in_chans")]
    pub in_chans: usize,
    /// Epsilon of every LayerNorm (`layer_norm_eps`; default 1e-6).
    #[serde(default = "default_eps")]
    pub layer_norm_eps: f64,
}

fn default_in_chans() -> usize {
    3
}
fn default_eps() -> f64 {
    1e-6
}

/// The HF `Dinov2WithRegistersConfig` fields this port reads (others, such
/// as `layerscale_value`, are ignored).
#[derive(Debug, Clone, Deserialize)]
struct Dinov2HfConfig {
    hidden_size: usize,
    num_hidden_layers: usize,
    num_attention_heads: usize,
    #[serde(default)]
    mlp_ratio: Option<f64>,
    patch_size: usize,
    image_size: usize,
    num_register_tokens: usize,
    #[serde(default)]
    num_channels: Option<usize>,
    #[serde(default)]
    layer_norm_eps: Option<f64>,
    #[serde(default)]
    use_swiglu_ffn: Option<bool>,
    #[serde(default)]
    hidden_act: Option<String>,
    #[serde(default)]
    qkv_bias: Option<bool>,
}

impl Dinov2Config {
    /// `dinov2_vitl14_reg` as loaded by TRELLIS/RecGen.
    pub fn vitl14_reg() -> Self {
        Self {
            embed_dim: 1024,
            depth: 24,
            num_heads: 16,
            mlp_ratio: 4.0,
            patch_size: 14,
            img_size: 518,
            num_register_tokens: 4,
            in_chans: 3,
            layer_norm_eps: 1e-6,
        }
    }

    /// DINOv2 args in either form: hub (`embed_dim`, `depth`, ...) or HF
    /// `Dinov2WithRegistersConfig` (`hidden_size`, `num_hidden_layers`, ...,
    /// as in the architecture file and the conformance fixture), then
    /// validated; errors name `file` and the field.
    pub fn from_json(v: &serde_json::Value, file: &str) -> crate::Result<Self> {
        let cfg = if v.get("hidden_size").is_some() {
            Self::from_hf(crate::util::json::from_value(v, file)?, file)?
        } else {
            crate::util::json::from_value(v, file)?
        };
        cfg.validate(file)?;
        Ok(cfg)
    }

    /// Only the variant used upstream is supported (GELU MLP, qkv bias, layer scale).
    fn from_hf(hf: Dinov2HfConfig, file: &str) -> crate::Result<Self> {
        if hf.use_swiglu_ffn == Some(true) {
            return Err(crate::Error::config(file, "use_swiglu_ffn", "SwiGLU FFN is not supported (vitl14 uses an MLP)"));
        }
        if let Some(act) = hf.hidden_act.filter(|a| a != "gelu") {
            return Err(crate::Error::config(file, "hidden_act", format!("only exact `gelu` is supported, got `{act}`")));
        }
        if hf.qkv_bias == Some(false) {
            return Err(crate::Error::config(file, "qkv_bias", "qkv without bias is not supported"));
        }
        Ok(Self {
            embed_dim: hf.hidden_size,
            depth: hf.num_hidden_layers,
            num_heads: hf.num_attention_heads,
            mlp_ratio: hf.mlp_ratio.unwrap_or(4.0),
            patch_size: hf.patch_size,
            img_size: hf.image_size,
            num_register_tokens: hf.num_register_tokens,
            in_chans: hf.num_channels.unwrap_or(3),
            layer_norm_eps: hf.layer_norm_eps.unwrap_or(1e-6),
        })
    }

    /// Check that `embed_dim` is a multiple of `num_heads` and `img_size` of `patch_size`; errors name `file`.
    pub fn validate(&self, file: &str) -> crate::Result<()> {
        if self.num_heads == 0 || !self.embed_dim.is_multiple_of(self.num_heads) {
            return Err(crate::Error::config(file, "num_heads", "embed_dim must be a positive multiple of num_heads"));
        }
        if self.patch_size == 0 || !self.img_size.is_multiple_of(self.patch_size) {
            return Err(crate::Error::config(file, "img_size", "must be a multiple of patch_size"));
        }
        Ok(())
    }

    /// Patches per side at `img_size`.
    pub fn grid(&self) -> usize {
        self.img_size / self.patch_size
    }
    /// MLP hidden width, `embed_dim · mlp_ratio` (truncated).
    pub fn mlp_hidden(&self) -> usize {
        (self.embed_dim as f64 * self.mlp_ratio) as usize
    }
    /// Tokens before the patch tokens: cls + registers.
    pub fn num_prefix_tokens(&self) -> usize {
        1 + self.num_register_tokens
    }
}

#[derive(Debug, Clone)]
struct Attention {
    qkv: Linear,
    proj: Linear,
    heads: usize,
    compute: Compute,
}

impl Attention {
    fn new(dim: usize, heads: usize, vb: VarBuilder, compute: Compute) -> Result<Self> {
        Ok(Self { qkv: linear(dim, 3 * dim, vb.pp("qkv"), compute)?, proj: linear(dim, dim, vb.pp("proj"), compute)?, heads, compute })
    }
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, n, c) = x.dims3()?;
        let d = c / self.heads;
        if let (Some((precision, isa)), Some(qkv_l)) = (self.compute.fast_parts(), self.qkv.fast()) {
            // Fused kernels reading q, k, v in place from the qkv rows.
            let qkv = fast::with_f32(x, |xs| qkv_l.forward_slice(xs, b * n, Activation::None))?;
            let lay = |off| AttnLayout::new(3 * c, off);
            let segs: Vec<AttnSegment> = (0..b).map(|i| AttnSegment { q: i * n..(i + 1) * n, kv: i * n..(i + 1) * n }).collect();
            let o = fast::attention_rows(isa, precision, self.heads, d, (&qkv, lay(0)), (&qkv, lay(c)), (&qkv, lay(2 * c)), b * n, &segs)?;
            return self.proj.forward(&Tensor::from_vec(o, (b, n, c), x.device())?);
        }
        // qkv is laid out [q | k | v], each split into heads.
        let qkv = self.qkv.forward(x)?.reshape((b, n, 3, self.heads, d))?.permute((2, 0, 3, 1, 4))?;
        let (q, k, v) = (qkv.get(0)?, qkv.get(1)?, qkv.get(2)?);
        let o = attention(&q, &k, &v)?; // [B, H, N, d]
        self.proj.forward(&o.transpose(1, 2)?.reshape((b, n, c))?)
    }
}

#[derive(Debug, Clone)]
struct Mlp {
    fc1: Linear,
    fc2: Linear,
}

impl Mlp {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        // nn.GELU() default: exact erf form (not the tanh approximation).
        self.fc2.forward(&self.fc1.forward_act(x, Activation::GeluErf)?)
    }
}

#[derive(Debug, Clone)]
struct Block {
    norm1: LayerNorm,
    attn: Attention,
    ls1: Tensor,
    norm2: LayerNorm,
    mlp: Mlp,
    ls2: Tensor,
    compute: Compute,
}

impl Block {
    fn new(cfg: &Dinov2Config, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let d = cfg.embed_dim;
        let h = cfg.mlp_hidden();
        Ok(Self {
            norm1: LayerNorm::new(d, cfg.layer_norm_eps, vb.pp("norm1"), compute)?,
            attn: Attention::new(d, cfg.num_heads, vb.pp("attn"), compute)?,
            ls1: vb.pp("ls1").get(d, "gamma")?,
            norm2: LayerNorm::new(d, cfg.layer_norm_eps, vb.pp("norm2"), compute)?,
            mlp: Mlp { fc1: linear(d, h, vb.pp("mlp.fc1"), compute)?, fc2: linear(h, d, vb.pp("mlp.fc2"), compute)? },
            ls2: vb.pp("ls2").get(d, "gamma")?,
            compute,
        })
    }
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if self.compute.is_fast() {
            let x = fast::gated_residual(x, &self.attn.forward(&self.norm1.forward(x)?)?, Some(&self.ls1))?;
            return fast::gated_residual(&x, &self.mlp.forward(&self.norm2.forward(&x)?)?, Some(&self.ls2));
        }
        let x = (x + self.attn.forward(&self.norm1.forward(x)?)?.broadcast_mul(&self.ls1)?)?;
        &x + self.mlp.forward(&self.norm2.forward(&x)?)?.broadcast_mul(&self.ls2)?
    }
}

/// Everything one forward pass produces.
#[derive(Debug, Clone)]
pub struct Dinov2Output {
    /// Tokens entering the first block: `[B, 1+R+P, D]`.
    pub embeddings: Tensor,
    /// Output of the last block, before the final norm.
    pub x_prenorm: Tensor,
    /// After the final affine LayerNorm.
    pub last_hidden_state: Tensor,
}

/// DINOv2 ViT with register tokens (torch.hub `DinoVisionTransformer`).
#[derive(Debug, Clone)]
pub struct Dinov2 {
    /// The hyper-parameters it was built with.
    pub cfg: Dinov2Config,
    cls_token: Tensor,
    pos_embed: Tensor,
    register_tokens: Option<Tensor>,
    patch_embed: Conv2d,
    blocks: Vec<Block>,
    norm: LayerNorm,
}

impl Dinov2 {
    /// Build from a VarBuilder rooted at the hub checkpoint's top level.
    pub fn new(cfg: &Dinov2Config, vb: VarBuilder, compute: Compute) -> Result<Self> {
        let d = cfg.embed_dim;
        let g = cfg.grid();
        let cls_token = vb.get((1, 1, d), "cls_token")?;
        let pos_embed = vb.get((1, 1 + g * g, d), "pos_embed")?;
        let register_tokens =
            if cfg.num_register_tokens > 0 { Some(vb.get((1, cfg.num_register_tokens, d), "register_tokens")?) } else { None };
        // Part of the checkpoint (used only for masked-image training); requested so
        // strict validation accepts the hub file.
        let _mask_token = vb.get((1, d), "mask_token")?;
        let conv_cfg = Conv2dConfig { stride: cfg.patch_size, ..Default::default() };
        let patch_embed = candle_nn::conv2d(cfg.in_chans, d, cfg.patch_size, conv_cfg, vb.pp("patch_embed.proj"))?;
        let blocks = (0..cfg.depth).map(|i| Block::new(cfg, vb.pp(format!("blocks.{i}")), compute)).collect::<Result<Vec<_>>>()?;
        let norm = LayerNorm::new(d, cfg.layer_norm_eps, vb.pp("norm"), compute)?;
        Ok(Self { cfg: cfg.clone(), cls_token, pos_embed, register_tokens, patch_embed, blocks, norm })
    }

    /// Position embedding for a `gh × gw` patch grid. Upstream interpolates
    /// (bicubic, antialiased) when the grid differs from the trained one; that
    /// path is not ported, so other grids are rejected instead of silently
    /// giving different features.
    fn pos_embed_for(&self, gh: usize, gw: usize) -> Result<Tensor> {
        let g = self.cfg.grid();
        if gh == g && gw == g {
            Ok(self.pos_embed.clone())
        } else {
            candle_core::bail!(
                "dinov2: image gives a {gh}x{gw} patch grid but the position embedding is for {g}x{g} \
                 (image side {}); resize the image to {}x{} (pos-embed interpolation is not implemented)",
                self.cfg.img_size,
                self.cfg.img_size,
                self.cfg.img_size
            )
        }
    }

    /// Patch embedding + cls + position + registers: `[B, 1+R+P, D]`.
    pub fn embed(&self, pixel_values: &Tensor) -> Result<Tensor> {
        let (b, _c, h, w) = pixel_values.dims4()?;
        let p = self.cfg.patch_size;
        if h % p != 0 || w % p != 0 {
            candle_core::bail!("dinov2: image size {h}x{w} is not a multiple of the patch size {p}");
        }
        let d = self.cfg.embed_dim;
        let x = self.patch_embed.forward(pixel_values)?; // [B, D, gh, gw]
        let (gh, gw) = (x.dim(2)?, x.dim(3)?);
        let x = x.flatten_from(2)?.transpose(1, 2)?; // row-major patches
        let cls = self.cls_token.broadcast_as((b, 1, d))?;
        let x = Tensor::cat(&[&cls, &x], 1)?.broadcast_add(&self.pos_embed_for(gh, gw)?)?;
        match &self.register_tokens {
            Some(reg) => {
                let r = reg.dim(1)?;
                let reg = reg.broadcast_as((b, r, d))?;
                let n = x.dim(1)?;
                Tensor::cat(&[&x.narrow(1, 0, 1)?, &reg, &x.narrow(1, 1, n - 1)?], 1)
            }
            None => Ok(x),
        }
    }

    /// Full forward (`forward_features` with `is_training=True` upstream).
    pub fn forward(&self, pixel_values: &Tensor) -> Result<Dinov2Output> {
        let embeddings = self.embed(pixel_values)?;
        let mut x = embeddings.clone();
        for blk in &self.blocks {
            x = blk.forward(&x)?;
        }
        let last_hidden_state = self.norm.forward(&x)?;
        Ok(Dinov2Output { embeddings, x_prenorm: x, last_hidden_state })
    }

    /// TRELLIS conditioning: `[B, 1+R+P, D]`.
    pub fn trellis_cond(&self, pixel_values: &Tensor) -> Result<Tensor> {
        trellis_cond(&self.forward(pixel_values)?.x_prenorm)
    }

    /// RecGen conditioning (patch tokens only): `[B, P, D]`.
    pub fn recgen_cond(&self, pixel_values: &Tensor) -> Result<Tensor> {
        recgen_cond(&self.forward(pixel_values)?.x_prenorm, self.cfg.num_prefix_tokens())
    }
}

/// TRELLIS: `F.layer_norm(x_prenorm, (D,))` without affine, default eps 1e-5, over all tokens.
pub fn trellis_cond(x_prenorm: &Tensor) -> Result<Tensor> {
    layer_norm_plain(x_prenorm, 1e-5)
}

/// RecGen: the TRELLIS conditioning with the `num_prefix` (cls + registers) tokens dropped.
pub fn recgen_cond(x_prenorm: &Tensor, num_prefix: usize) -> Result<Tensor> {
    let c = trellis_cond(x_prenorm)?;
    let n = c.dim(1)?;
    if n < num_prefix {
        candle_core::bail!("recgen_cond: {n} tokens, fewer than the {num_prefix} prefix tokens");
    }
    c.narrow(1, num_prefix, n - num_prefix)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use candle_nn::VarMap;

    fn tiny() -> Dinov2Config {
        Dinov2Config {
            embed_dim: 16,
            depth: 1,
            num_heads: 2,
            mlp_ratio: 2.0,
            patch_size: 14,
            img_size: 28,
            num_register_tokens: 4,
            in_chans: 3,
            layer_norm_eps: 1e-6,
        }
    }

    #[test]
    fn token_layout_and_conds() -> Result<()> {
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
        let cfg = tiny();
        let m = Dinov2::new(&cfg, vb, Compute::Plain)?;
        let img = Tensor::randn(0f32, 1.0, (2, 3, 28, 28), &dev)?;
        let out = m.forward(&img)?;
        assert_eq!(out.x_prenorm.dims(), &[2, 1 + 4 + 4, 16]);
        // Registers sit at positions 1..5 and carry no position embedding.
        let reg = out.embeddings.narrow(1, 1, 4)?;
        let want = m.register_tokens.as_ref().unwrap().broadcast_as((2, 4, 16))?;
        assert_eq!(crate::util::max_abs_diff(&reg, &want.contiguous()?).unwrap(), 0.0);
        let c = recgen_cond(&out.x_prenorm, cfg.num_prefix_tokens())?;
        assert_eq!(c.dims(), &[2, 4, 16]);
        let t = trellis_cond(&out.x_prenorm)?.narrow(1, 5, 4)?;
        assert_eq!(crate::util::max_abs_diff(&c, &t).unwrap(), 0.0);
        // A different grid is refused, not silently mis-embedded.
        assert!(m.forward(&Tensor::zeros((1, 3, 42, 42), DType::F32, &dev)?).is_err());
        Ok(())
    }

    /// DINOv2 on the fast kernels (erf GELU fused into fc1, flash attention on
    /// the qkv rows) matches the plain model.
    #[test]
    fn fast_model_matches_plain() -> crate::Result<()> {
        use crate::model::nn::fast::Precision;
        let dev = Device::Cpu;
        let vm = VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
        let cfg = Dinov2Config { embed_dim: 32, depth: 2, ..tiny() };
        let plain = Dinov2::new(&cfg, vb.clone(), Compute::Plain)?;
        let mut rng = crate::rng::SeededRng::new(5);
        for (_, var) in vm.data().lock().unwrap().iter() {
            var.set(&((rng.randn(var.dims(), &dev)? * 0.1)? + 0.02)?)?;
        }
        let fast = Dinov2::new(&cfg, vb, Compute::fast(Precision::F32))?;
        assert!(fast.blocks[0].attn.qkv.fast().is_some() && fast.blocks[0].compute.is_fast());
        let img = rng.randn(&[2, 3, 28, 28], &dev)?;
        let a = plain.forward(&img)?.x_prenorm;
        let b = fast.forward(&img)?.x_prenorm;
        let d = crate::util::max_abs_diff(&a, &b).unwrap();
        assert!(d < 1e-4, "diff {d}");
        Ok(())
    }

    #[test]
    fn vitl_preset_matches_spec() {
        let c = Dinov2Config::vitl14_reg();
        assert_eq!((c.grid(), c.mlp_hidden(), c.num_prefix_tokens()), (37, 4096, 5));
    }
}
