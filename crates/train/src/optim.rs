//! AdamW and gradient clipping.
//!
//! The update is candle-nn's `AdamW` operation for operation (a test checks
//! the two give bit-identical parameters), but candle-nn keeps its moments
//! and step counter private, so a checkpoint could not restore them and a
//! resumed run would diverge. This one exposes its state.

use std::collections::BTreeMap;

use candle_core::backprop::GradStore;
use candle_core::{Tensor, Var};
use candle_nn::ParamsAdamW;

use recon_core::{Error, Result};

/// AdamW over a fixed, ordered list of named variables.
pub struct AdamW {
    /// Learning rate, betas, epsilon and weight decay.
    pub params: ParamsAdamW,
    /// Steps taken (bias correction uses it).
    pub step_t: usize,
    vars: Vec<(String, Var, Var, Var)>, // name, θ, m, v
}

impl AdamW {
    /// An optimiser over `vars` (in this order), with zeroed moments.
    pub fn new(vars: &[(String, Var)], params: ParamsAdamW) -> Result<Self> {
        let vars = vars
            .iter()
            .map(|(n, v)| {
                Ok((n.clone(), v.clone(), Var::zeros(v.shape(), v.dtype(), v.device())?, Var::zeros(v.shape(), v.dtype(), v.device())?))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { params, step_t: 0, vars })
    }

    /// One update from `grads` (variables without a gradient are left alone,
    /// their moments too, as in candle-nn).
    pub fn step(&mut self, grads: &GradStore) -> Result<()> {
        self.step_t += 1;
        let p = &self.params;
        let (lr, beta1, beta2) = (p.lr, p.beta1, p.beta2);
        let lr_lambda = lr * p.weight_decay;
        let scale_m = 1f64 / (1f64 - beta1.powi(self.step_t as i32));
        let scale_v = 1f64 / (1f64 - beta2.powi(self.step_t as i32));
        for (_, theta, m, v) in &self.vars {
            if let Some(g) = grads.get(theta) {
                let next_m = ((m.as_tensor() * beta1)? + (g * (1.0 - beta1))?)?;
                let next_v = ((v.as_tensor() * beta2)? + (g.sqr()? * (1.0 - beta2))?)?;
                let m_hat = (&next_m * scale_m)?;
                let v_hat = (&next_v * scale_v)?;
                let next_theta = (theta.as_tensor() * (1f64 - lr_lambda))?;
                let adjusted = (m_hat / (v_hat.sqrt()? + p.eps)?)?;
                let next_theta = (next_theta - (adjusted * lr)?)?;
                m.set(&next_m)?;
                v.set(&next_v)?;
                theta.set(&next_theta)?;
            }
        }
        Ok(())
    }

    /// Moments as `{name}.m` / `{name}.v` tensors (copies).
    pub fn state_tensors(&self) -> Result<BTreeMap<String, Tensor>> {
        let mut out = BTreeMap::new();
        for (n, _, m, v) in &self.vars {
            out.insert(format!("{n}.m"), m.as_tensor().copy()?.detach());
            out.insert(format!("{n}.v"), v.as_tensor().copy()?.detach());
        }
        Ok(out)
    }

    /// Restore moments saved by [`Self::state_tensors`] and the step count.
    pub fn load_state(&mut self, state: &BTreeMap<String, Tensor>, step_t: usize, file: &str) -> Result<()> {
        for (n, theta, m, v) in &self.vars {
            for (suffix, var) in [("m", m), ("v", v)] {
                let key = format!("{n}.{suffix}");
                let t = state.get(&key).ok_or_else(|| Error::MissingTensor {
                    file: file.into(),
                    name: key.clone(),
                    expected: theta.dims().to_vec(),
                })?;
                if t.dims() != theta.dims() {
                    return Err(Error::ShapeMismatch {
                        file: file.into(),
                        name: key,
                        found: t.dims().to_vec(),
                        expected: theta.dims().to_vec(),
                    });
                }
                var.set(t)?;
            }
        }
        self.step_t = step_t;
        Ok(())
    }
}

/// Global L2 norm of the gradients of `vars` (summed in the given order, so
/// it is reproducible), and, when it exceeds `max_norm`, every gradient
/// scaled by `max_norm / norm` in place. Returns the norm before clipping.
pub fn clip_grad_norm(grads: &mut GradStore, vars: &[(String, Var)], max_norm: Option<f64>) -> Result<f64> {
    let mut sq = 0f64;
    for (_, v) in vars {
        if let Some(g) = grads.get(v) {
            sq += g.sqr()?.sum_all()?.to_dtype(candle_core::DType::F64)?.to_scalar::<f64>()?;
        }
    }
    let norm = sq.sqrt();
    if !norm.is_finite() {
        return Err(Error::msg(format!("gradient norm is {norm}: the loss diverged (lower --lr or check the data)")));
    }
    if let Some(max) = max_norm {
        if norm > max {
            let s = max / norm;
            for (_, v) in vars {
                if let Some(g) = grads.remove(v) {
                    grads.insert(v, (g * s)?);
                }
            }
        }
    }
    Ok(norm)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;
    use candle_nn::Optimizer;
    use recon_core::rng::SeededRng;

    fn problem(seed: u64) -> Result<(Vec<(String, Var)>, Tensor)> {
        let mut rng = SeededRng::new(seed);
        let a = Var::from_tensor(&rng.randn(&[4, 3], &Device::Cpu)?)?;
        let b = Var::from_tensor(&rng.randn(&[3], &Device::Cpu)?)?;
        let x = rng.randn(&[5, 4], &Device::Cpu)?;
        Ok((vec![("a".into(), a), ("b".into(), b)], x))
    }

    fn loss(vars: &[(String, Var)], x: &Tensor) -> Result<Tensor> {
        let y = x.matmul(vars[0].1.as_tensor())?.broadcast_add(vars[1].1.as_tensor())?;
        Ok((y.sin()? * 3.0)?.sqr()?.mean_all()?)
    }

    #[test]
    fn matches_candle_nn_adamw_bit_for_bit() -> Result<()> {
        let params = ParamsAdamW { lr: 0.05, weight_decay: 0.1, ..Default::default() };
        let (ours, x) = problem(1)?;
        let (theirs, _) = problem(1)?;
        let mut opt = AdamW::new(&ours, params.clone())?;
        let mut reference = candle_nn::AdamW::new(theirs.iter().map(|(_, v)| v.clone()).collect(), params)?;
        for _ in 0..5 {
            opt.step(&loss(&ours, &x)?.backward()?)?;
            reference.step(&loss(&theirs, &x)?.backward()?)?;
        }
        for ((_, a), (_, b)) in ours.iter().zip(&theirs) {
            assert_eq!(a.as_tensor().flatten_all()?.to_vec1::<f32>()?, b.as_tensor().flatten_all()?.to_vec1::<f32>()?);
        }
        Ok(())
    }

    #[test]
    fn state_round_trip_continues_identically() -> Result<()> {
        let params = ParamsAdamW { lr: 0.05, ..Default::default() };
        let (va, x) = problem(2)?;
        let mut a = AdamW::new(&va, params.clone())?;
        for _ in 0..3 {
            a.step(&loss(&va, &x)?.backward()?)?;
        }
        // Copy parameters and optimizer state into a fresh optimizer.
        let vb: Vec<(String, Var)> =
            va.iter().map(|(n, v)| Ok((n.clone(), Var::from_tensor(&v.as_tensor().copy()?)?))).collect::<Result<_>>()?;
        let mut b = AdamW::new(&vb, params)?;
        b.load_state(&a.state_tensors()?, a.step_t, "mem")?;
        for _ in 0..3 {
            a.step(&loss(&va, &x)?.backward()?)?;
            b.step(&loss(&vb, &x)?.backward()?)?;
        }
        for ((_, p), (_, q)) in va.iter().zip(&vb) {
            assert_eq!(p.as_tensor().flatten_all()?.to_vec1::<f32>()?, q.as_tensor().flatten_all()?.to_vec1::<f32>()?);
        }
        assert!(b.load_state(&BTreeMap::new(), 0, "empty").is_err());
        Ok(())
    }

    #[test]
    fn clipping_scales_to_max_norm() -> Result<()> {
        let (v, x) = problem(3)?;
        let mut g = loss(&v, &x)?.backward()?;
        let n0 = clip_grad_norm(&mut g, &v, None)?;
        assert!(n0 > 0.5, "{n0}");
        let n1 = clip_grad_norm(&mut g, &v, Some(0.5))?;
        assert_eq!(n0, n1);
        let after = clip_grad_norm(&mut g, &v, None)?;
        assert!((after - 0.5).abs() < 1e-5, "{after}");
        Ok(())
    }
}
