//! Conditional flow matching (TRELLIS `trainers/flow_matching`, RecGen's
//! pose extension), in the conventions [`recon_core::model::sampler`] integrates:
//!
//! - `x_t = (1 − t)·x₀ + (σ + (1 − σ)·t)·ε`, t = 0 data, t = 1 noise;
//! - target velocity `v = (1 − σ)·ε − x₀` (= dx_t/dt for σ = 0), so the
//!   sampler's step `x ← x − (t − t_prev)·v` walks from noise to data;
//! - the model sees `1000·t`;
//! - t is drawn logit-normal, `t = sigmoid(N(mean, std))` (TRELLIS stage 1:
//!   mean 1, std 1);
//! - RecGen: pose tokens are noised with the *same* t and their own noise,
//!   and regressed with the same target; loss
//!   `mse(v, v̂) + α·mse_pose` with α = 0.01, the pose error averaged over
//!   the supervised tokens only (`_pose_loss_mask`);
//! - classifier-free guidance dropout: with probability `p_uncond` (0.1) a
//!   sample's whole condition (image tokens + point-map + mask embeddings)
//!   is replaced by zeros, the `neg_cond` the sampler uses (RecGen's
//!   coordinated `_shared_cfg_mask` mode). Its pose loss is kept, as RecGen
//!   does, so the unconditional model also predicts pose.

use candle_core::{DType, Tensor};

use recon_core::rng::SeededRng;
use recon_core::{Error, Result};

/// Flow-matching hyper-parameters (upstream defaults in [`Default`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FlowMatching {
    /// Smallest noise scale σ_min of the interpolation path.
    pub sigma_min: f64,
    /// Logit-normal time distribution.
    pub t_mean: f64,
    /// Standard deviation of the logit-normal time distribution.
    pub t_std: f64,
    /// Probability of dropping the condition (CFG training).
    pub p_uncond: f64,
    /// Weight α of the pose velocity loss.
    pub pose_alpha: f64,
}

impl Default for FlowMatching {
    fn default() -> Self {
        Self { sigma_min: 1e-5, t_mean: 1.0, t_std: 1.0, p_uncond: 0.1, pose_alpha: 0.01 }
    }
}

impl FlowMatching {
    /// `n` times in (0, 1).
    pub fn sample_t(&self, rng: &mut SeededRng, n: usize) -> Vec<f32> {
        (0..n).map(|_| (1.0 / (1.0 + (-(rng.normal() * self.t_std + self.t_mean)).exp())) as f32).collect()
    }

    /// `x_t` for per-sample times `t` (`[B]`, broadcast over the other dims).
    pub fn diffuse(&self, x0: &Tensor, t: &Tensor, noise: &Tensor) -> Result<Tensor> {
        let t = per_sample(t, x0.rank())?;
        let a = t.affine(-1.0, 1.0)?;
        let s = t.affine(1.0 - self.sigma_min, self.sigma_min)?;
        Ok((x0.broadcast_mul(&a)? + noise.broadcast_mul(&s)?)?)
    }

    /// Target velocity `(1 − σ)·ε − x₀`.
    pub fn target(&self, x0: &Tensor, noise: &Tensor) -> Result<Tensor> {
        Ok(((noise * (1.0 - self.sigma_min))? - x0)?)
    }

    /// Per-sample CFG drop decisions.
    pub fn drop_mask(&self, rng: &mut SeededRng, n: usize) -> Vec<bool> {
        (0..n).map(|_| rng.uniform() < self.p_uncond).collect()
    }
}

/// `[B]` → `[B, 1, …, 1]` of rank `rank`.
fn per_sample(t: &Tensor, rank: usize) -> Result<Tensor> {
    let b = t.dim(0)?;
    let mut shape = vec![b];
    shape.extend(std::iter::repeat_n(1, rank.saturating_sub(1)));
    Ok(t.reshape(shape)?)
}

/// Zero the condition of dropped samples: `cond` `[B, L, C]`.
pub fn drop_condition(cond: &Tensor, drop: &[bool]) -> Result<Tensor> {
    let b = cond.dim(0)?;
    if drop.len() != b {
        return Err(Error::msg(format!("cfg dropout: {} decisions for a batch of {b}", drop.len())));
    }
    if !drop.iter().any(|&d| d) {
        return Ok(cond.clone());
    }
    let keep: Vec<f32> = drop.iter().map(|&d| if d { 0.0 } else { 1.0 }).collect();
    let keep = Tensor::from_vec(keep, (b, 1, 1), cond.device())?.to_dtype(cond.dtype())?;
    Ok(cond.broadcast_mul(&keep)?)
}

/// Mean squared error over the supervised pose tokens: `pred`, `target`
/// `[B, K, P]`, `mask` `[B, K]` in {0, 1}: `Σ mask·(p − y)² / max(Σ mask, 1) / P`.
pub fn masked_pose_mse(pred: &Tensor, target: &Tensor, mask: &Tensor) -> Result<Tensor> {
    let p = pred.dim(2)?;
    let err = (pred - target)?.sqr()?.broadcast_mul(&mask.unsqueeze(2)?)?.sum_all()?;
    let n = mask.sum_all()?.to_dtype(DType::F32)?.to_scalar::<f32>()?.max(1.0);
    Ok((err / (n as f64 * p as f64))?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::AdamW;
    use candle_core::Device;
    use candle_core::Var;
    use recon_core::model::sampler::{FlowEulerGuidanceIntervalSampler, FnVelocity, SamplerSettings};

    #[test]
    fn diffuse_and_target_follow_trellis() -> Result<()> {
        let fm = FlowMatching { sigma_min: 0.1, ..Default::default() };
        let x0 = Tensor::new(&[[1f32, 2.0], [3.0, 4.0]], &Device::Cpu)?;
        let eps = Tensor::new(&[[0.5f32, -1.0], [2.0, 0.0]], &Device::Cpu)?;
        let t = Tensor::new(&[0.0f32, 0.5], &Device::Cpu)?;
        let xt = fm.diffuse(&x0, &t, &eps)?.to_vec2::<f32>()?;
        // t = 0: x0 + σ·ε; t = 0.5: 0.5·x0 + (0.1 + 0.9·0.5)·ε.
        assert!((xt[0][0] - (1.0 + 0.05)).abs() < 1e-6 && (xt[0][1] - (2.0 - 0.1)).abs() < 1e-6);
        assert!((xt[1][0] - (1.5 + 0.55 * 2.0)).abs() < 1e-6 && (xt[1][1] - 2.0).abs() < 1e-6);
        let v = fm.target(&x0, &eps)?.to_vec2::<f32>()?;
        assert!((v[0][0] - (0.45 - 1.0)).abs() < 1e-6);
        // Time samples are in (0, 1) with median sigmoid(mean).
        let mut rng = SeededRng::new(1);
        let mut ts = fm.sample_t(&mut rng, 4001);
        assert!(ts.iter().all(|&t| t > 0.0 && t < 1.0));
        ts.sort_by(|a, b| a.total_cmp(b));
        assert!((ts[2000] - 1.0 / (1.0 + (-1f32).exp())).abs() < 0.02, "median {}", ts[2000]);
        Ok(())
    }

    #[test]
    fn condition_dropout_and_masked_pose_loss() -> Result<()> {
        let dev = Device::Cpu;
        let cond = Tensor::ones((3, 2, 4), DType::F32, &dev)?;
        let d = drop_condition(&cond, &[false, true, false])?;
        let s = d.sum_keepdim(2)?.sum_keepdim(1)?.flatten_all()?.to_vec1::<f32>()?;
        assert_eq!(s, vec![8.0, 0.0, 8.0]);
        assert!(drop_condition(&cond, &[true]).is_err());
        let n = FlowMatching::default().drop_mask(&mut SeededRng::new(3), 10000).iter().filter(|&&b| b).count();
        assert!((900..1100).contains(&n), "{n} drops in 10000");
        // Token 1 of sample 0 is unsupervised: its error does not count.
        let pred = Tensor::new(&[[[1f32, 1.0], [100.0, 100.0]], [[0.0, 0.0], [2.0, 0.0]]], &dev)?;
        let target = Tensor::zeros((2, 2, 2), DType::F32, &dev)?;
        let mask = Tensor::new(&[[1f32, 0.0], [1.0, 1.0]], &dev)?;
        let l = masked_pose_mse(&pred, &target, &mask)?.to_scalar::<f32>()?;
        assert!((l - (1.0 + 1.0 + 0.0 + 4.0) / 3.0 / 2.0).abs() < 1e-6, "{l}");
        Ok(())
    }

    /// End-to-end check of the conventions: a model trained with this
    /// objective on a 2-D Gaussian, then integrated by the inference sampler
    /// from noise, reproduces the Gaussian. (A sign or time-scale mismatch
    /// between training and sampling sends the samples elsewhere.)
    #[test]
    fn trained_velocity_is_sampled_back_to_the_data_distribution() -> Result<()> {
        let dev = Device::Cpu;
        let (mu, sd) = ([2.0f32, -1.0], [0.5f32, 0.2]);
        // Exact velocity of a Gaussian is affine in x for each t:
        // v = a(t)·x + b(t); a, b come from a small MLP of t.
        let mut rng = SeededRng::new(5);
        let init = |r: &mut SeededRng, shape: &[usize], std: f64| -> Result<Var> { Ok(Var::from_tensor(&(r.randn(shape, &dev)? * std)?)?) };
        let w1 = init(&mut rng, &[16, 32], 0.3)?;
        let b1 = init(&mut rng, &[32], 0.0)?;
        let w2 = init(&mut rng, &[32, 4], 0.0)?;
        let b2 = init(&mut rng, &[4], 0.0)?;
        let vars: Vec<(String, Var)> =
            [("w1", &w1), ("b1", &b1), ("w2", &w2), ("b2", &b2)].iter().map(|(n, v)| (n.to_string(), (*v).clone())).collect();
        let model = |x: &Tensor, t_model: &Tensor| -> Result<Tensor> {
            let t = (t_model / 1000.0)?;
            let feats = recon_core::model::nn::common::TimestepEmbedder::sinusoidal(&(t * 10.0)?, 16)?;
            let h = feats.matmul(w1.as_tensor())?.broadcast_add(b1.as_tensor())?.silu()?;
            let ab = h.matmul(w2.as_tensor())?.broadcast_add(b2.as_tensor())?; // [B, 4]
            let a = (ab.narrow(1, 0, 2)? - 1.0)?;
            Ok(((x * a)? + ab.narrow(1, 2, 2)?)?)
        };
        let fm = FlowMatching { t_mean: 0.0, ..Default::default() };
        let mut opt = AdamW::new(&vars, candle_nn::ParamsAdamW { lr: 1e-2, weight_decay: 0.0, ..Default::default() })?;
        let b = 256;
        for _ in 0..400 {
            let z = rng.randn(&[b, 2], &dev)?;
            let x0 = z.broadcast_mul(&Tensor::new(&sd, &dev)?)?.broadcast_add(&Tensor::new(&mu, &dev)?)?;
            let eps = rng.randn(&[b, 2], &dev)?;
            let t = Tensor::from_vec(fm.sample_t(&mut rng, b), b, &dev)?;
            let xt = fm.diffuse(&x0, &t, &eps)?;
            let loss = (model(&xt, &(&t * 1000.0)?)? - fm.target(&x0, &eps)?)?.sqr()?.mean_all()?;
            opt.step(&loss.backward()?)?;
        }
        let sampler =
            FlowEulerGuidanceIntervalSampler::new(SamplerSettings { steps: 50, rescale_t: 1.0, cfg_strength: 0.0, ..Default::default() });
        let vm = FnVelocity(|s: &[Tensor], t_model: f32, _c: &Tensor| -> Result<Vec<Tensor>> {
            let t = Tensor::full(t_model, s[0].dim(0)?, &dev)?;
            Ok(vec![model(&s[0], &t)?])
        });
        let n = 4000;
        let out = sampler.sample(&vm, vec![rng.randn(&[n, 2], &dev)?], &Tensor::zeros(1, DType::F32, &dev)?, None)?;
        let v = out[0].to_vec2::<f32>()?;
        for a in 0..2 {
            let m = v.iter().map(|r| r[a] as f64).sum::<f64>() / n as f64;
            let s = (v.iter().map(|r| (r[a] as f64 - m).powi(2)).sum::<f64>() / n as f64).sqrt();
            assert!((m - mu[a] as f64).abs() < 0.1, "axis {a}: mean {m} vs {}", mu[a]);
            assert!((s / sd[a] as f64 - 1.0).abs() < 0.25, "axis {a}: std {s} vs {}", sd[a]);
        }
        Ok(())
    }
}
