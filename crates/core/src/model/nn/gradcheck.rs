//! Gradient checks for tests: the analytic directional derivative of a loss
//! against its central finite difference.

use candle_core::{Tensor, Var};

use crate::rng::SeededRng;
use crate::{Error, Result};

/// Every variable of a `VarMap`, sorted by name.
pub fn sorted_vars(vm: &candle_nn::VarMap) -> Vec<(String, Var)> {
    let mut vars: Vec<(String, Var)> = vm.data().lock().expect("varmap").iter().map(|(k, v)| (k.clone(), v.clone())).collect();
    vars.sort_by(|a, b| a.0.cmp(&b.0));
    vars
}

/// Check `d/dε loss(θ + ε·u)` at 0 for a random unit direction `u` over
/// every variable of `vars`: backprop's `⟨∇loss, u⟩` must equal
/// `(loss(θ + h·u) − loss(θ − h·u)) / 2h` within `rel_tol`. Also fails when
/// a variable not named in `unused` gets no gradient at all (a layer that
/// is not trainable). Returns (analytic, numeric).
pub fn directional_check(
    vars: &[(String, Var)],
    unused: &[&str],
    loss: impl Fn() -> Result<Tensor>,
    seed: u64,
    rel_tol: f64,
) -> Result<(f64, f64)> {
    let l0 = loss()?;
    let grads = l0.backward()?;
    let missing: Vec<&str> =
        vars.iter().filter(|(n, v)| grads.get(v).is_none() && !unused.contains(&n.as_str())).map(|(n, _)| n.as_str()).collect();
    if !missing.is_empty() {
        return Err(Error::msg(format!("no gradient reaches {missing:?}")));
    }
    let mut rng = SeededRng::new(seed);
    let dirs: Vec<Tensor> = vars.iter().map(|(_, v)| rng.randn(v.dims(), v.device())).collect::<Result<_>>()?;
    let norm = dirs.iter().map(|d| Ok(d.sqr()?.sum_all()?.to_scalar::<f32>()? as f64)).sum::<Result<f64>>()?.sqrt();
    let mut analytic = 0.0;
    for ((_, v), d) in vars.iter().zip(&dirs) {
        if let Some(g) = grads.get(v) {
            analytic += (g * d)?.sum_all()?.to_scalar::<f32>()? as f64 / norm;
        }
    }
    let h = 1e-2;
    let orig: Vec<Tensor> = vars.iter().map(|(_, v)| v.as_tensor().copy()).collect::<candle_core::Result<_>>()?;
    let at = |s: f64| -> Result<f64> {
        for (((_, v), d), o) in vars.iter().zip(&dirs).zip(&orig) {
            v.set(&(o + (d * (s * h / norm))?)?)?;
        }
        Ok(loss()?.to_scalar::<f32>()? as f64)
    };
    let (lp, lm) = (at(1.0)?, at(-1.0)?);
    for ((_, v), o) in vars.iter().zip(&orig) {
        v.set(o)?;
    }
    let numeric = (lp - lm) / (2.0 * h);
    if analytic.abs() < 1e-6 {
        return Err(Error::msg(format!("directional derivative {analytic:e} is ~0: the check would prove nothing")));
    }
    let err = (numeric - analytic).abs();
    if err > rel_tol * analytic.abs().max(numeric.abs()).max(1e-3) {
        return Err(Error::msg(format!("directional derivative: backprop {analytic:.6e}, finite difference {numeric:.6e}")));
    }
    Ok((analytic, numeric))
}
