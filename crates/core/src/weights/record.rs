//! Discovering a module's parameter list without a checkpoint: build the
//! module on a VarBuilder whose backend records every requested name and
//! shape. Two backends: [`Recorder`] hands out zero-cost broadcast zeros (so
//! even the full-size models cost no memory), [`RandomInit`] hands out
//! deterministic random tensors (for `recon weights init`).

use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::VarBuilder;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// Expected name and shape of one parameter.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct TensorSpec {
    /// Parameter name (the dotted VarBuilder path).
    pub name: String,
    /// Parameter shape.
    pub shape: Vec<usize>,
}

type Log = Arc<Mutex<BTreeMap<String, Vec<usize>>>>;

fn record(log: &Log, name: &str, s: &Shape) -> candle_core::Result<()> {
    let mut m = log.lock().map_err(|_| candle_core::Error::Msg("recorder poisoned".into()))?;
    if let Some(prev) = m.get(name) {
        if prev.as_slice() != s.dims() {
            candle_core::bail!("parameter `{name}` requested with shapes {prev:?} and {:?}", s.dims());
        }
    }
    m.insert(name.to_string(), s.dims().to_vec());
    Ok(())
}

/// Records every `get`; returns zeros that are a broadcast of one scalar.
#[derive(Clone, Default)]
pub struct Recorder {
    log: Log,
}

impl Recorder {
    /// An empty recorder.
    pub fn new() -> Self {
        Self::default()
    }
    /// A VarBuilder over this recorder, handing out `dtype` zeros on `dev`.
    pub fn var_builder(&self, dtype: DType, dev: &Device) -> VarBuilder<'static> {
        VarBuilder::from_backend(Box::new(self.clone()), dtype, dev.clone())
    }
    /// Recorded parameters, sorted by name.
    pub fn specs(&self) -> Vec<TensorSpec> {
        let m = self.log.lock().map(|m| m.clone()).unwrap_or_default();
        m.into_iter().map(|(name, shape)| TensorSpec { name, shape }).collect()
    }
}

impl SimpleBackend for Recorder {
    fn get(&self, s: Shape, name: &str, _h: candle_nn::Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        record(&self.log, name, &s)?;
        Tensor::zeros((), dtype, dev)?.broadcast_as(s)
    }
    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("recorder: `{name}` requested without a shape; cannot infer it")
    }
    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

/// The (name, shape) list any module builder requests: run `build` on a
/// recording VarBuilder. Works for modules not in the registry, e.g.
/// `record_with(|vb| SparseStructureDecoder::new(&cfg, vb).map(|_| ()))`.
pub fn record_with<F>(build: F) -> crate::Result<Vec<TensorSpec>>
where
    F: FnOnce(VarBuilder<'static>) -> crate::Result<()>,
{
    let r = Recorder::new();
    build(r.var_builder(DType::F32, &Device::Cpu))?;
    Ok(r.specs())
}

/// splitmix64: a tiny, well-mixed PRNG so values depend only on (seed, name).
fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn fnv1a(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

/// How a parameter is initialised, decided from its name (upstream init
/// schemes are not reproduced: these weights are for plumbing tests only).
pub fn init_rule(name: &str) -> InitRule {
    let last = name.rsplit('.').next().unwrap_or(name);
    let parent = name.rsplit('.').nth(1).unwrap_or("");
    if last == "bias" {
        InitRule::Const(0.0)
    } else if last == "gamma" || last == "lambda1" || (last == "weight" && parent.contains("norm")) {
        InitRule::Const(1.0)
    } else {
        InitRule::Normal(0.02)
    }
}

/// How [`random_values`] fills a parameter ([`init_rule`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum InitRule {
    /// Every value equal to this.
    Const(f32),
    /// Zero-mean normal noise with this standard deviation.
    Normal(f32),
}

/// Deterministic random values for `name` (Box–Muller over splitmix64).
/// Pair j of outputs uses stream draws 2j and 2j+1; splitmix64 can jump to
/// any draw, so large tensors are filled in parallel with the same values.
pub fn random_values(seed: u64, name: &str, n: usize) -> Vec<f32> {
    match init_rule(name) {
        InitRule::Const(c) => vec![c; n],
        InitRule::Normal(std) => {
            use rayon::prelude::*;
            let st0 = seed ^ fnv1a(name);
            let mut out = vec![0f32; n];
            // Chunks of whole pairs; each starts its stream at its first draw.
            const CHUNK: usize = 1 << 16;
            out.par_chunks_mut(CHUNK).enumerate().for_each(|(ci, chunk)| {
                let mut st = st0.wrapping_add(((ci * CHUNK) as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
                for pair in chunk.chunks_mut(2) {
                    let u1 = ((splitmix(&mut st) >> 11) as f64 + 1.0) / (1u64 << 53) as f64;
                    let u2 = (splitmix(&mut st) >> 11) as f64 / (1u64 << 53) as f64;
                    let (z0, z1) = crate::rng::box_muller(u1, u2);
                    pair[0] = z0 as f32 * std;
                    if pair.len() > 1 {
                        pair[1] = z1 as f32 * std;
                    }
                }
            });
            out
        }
    }
}

/// The values [`RandomInit`] hands out for `name` with shape `s`.
pub fn random_tensor_values(seed: u64, name: &str, s: &Shape) -> Vec<f32> {
    // A rank-1 `weight` is a norm scale whatever its module is called
    // (`out_layer.0`, `act_layers.0` are LayerNorm / GroupNorm): 1, so
    // random-weight activations keep their scale.
    if s.rank() == 1 && name.ends_with("weight") {
        vec![1.0; s.elem_count()]
    } else {
        random_values(seed, name, s.elem_count())
    }
}

/// The same values as [`RandomInit`], generated when requested and not kept:
/// building a module on it holds one f32 tensor at a time, so a module built
/// with packed (fast) weights never has its whole f32 copy in memory.
/// `overrides` replace the noise of computed buffers.
#[derive(Clone)]
pub struct RandomStream {
    seed: u64,
    overrides: Arc<BTreeMap<String, Tensor>>,
}

impl RandomStream {
    /// A stream for `seed`; `overrides` give named buffers their values instead of noise.
    pub fn new(seed: u64, overrides: BTreeMap<String, Tensor>) -> Self {
        Self { seed, overrides: Arc::new(overrides) }
    }
    /// An f32 VarBuilder over this stream on `dev`.
    pub fn var_builder(&self, dev: &Device) -> VarBuilder<'static> {
        VarBuilder::from_backend(Box::new(self.clone()), DType::F32, dev.clone())
    }
}

impl SimpleBackend for RandomStream {
    fn get(&self, s: Shape, name: &str, _h: candle_nn::Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        if let Some(t) = self.overrides.get(name) {
            if t.shape() != &s {
                candle_core::bail!("random weights: buffer `{name}` has shape {:?}, requested {:?}", t.dims(), s.dims());
            }
            return t.to_device(dev)?.to_dtype(dtype);
        }
        Tensor::from_vec(random_tensor_values(self.seed, name, &s), s, dev)?.to_dtype(dtype)
    }
    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("random weights: `{name}` requested without a shape; cannot infer it")
    }
    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

/// Records every `get` and returns (and keeps) deterministic random tensors.
#[derive(Clone)]
pub struct RandomInit {
    seed: u64,
    log: Log,
    tensors: Arc<Mutex<BTreeMap<String, Tensor>>>,
}

impl RandomInit {
    /// An initialiser for `seed`, with nothing handed out yet.
    pub fn new(seed: u64) -> Self {
        Self { seed, log: Log::default(), tensors: Default::default() }
    }
    /// An f32 VarBuilder over this initialiser on `dev`.
    pub fn var_builder(&self, dev: &Device) -> VarBuilder<'static> {
        VarBuilder::from_backend(Box::new(self.clone()), DType::F32, dev.clone())
    }
    /// Every tensor handed out, by name.
    pub fn tensors(&self) -> BTreeMap<String, Tensor> {
        self.tensors.lock().map(|m| m.clone()).unwrap_or_default()
    }
}

impl SimpleBackend for RandomInit {
    fn get(&self, s: Shape, name: &str, _h: candle_nn::Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        record(&self.log, name, &s)?;
        let mut m = self.tensors.lock().map_err(|_| candle_core::Error::Msg("init poisoned".into()))?;
        if let Some(t) = m.get(name) {
            return t.to_dtype(dtype);
        }
        let vals = random_tensor_values(self.seed, name, &s);
        let t = Tensor::from_vec(vals, s, dev)?;
        m.insert(name.to_string(), t.clone());
        t.to_dtype(dtype)
    }
    fn get_unchecked(&self, name: &str, _dtype: DType, _dev: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("random init: `{name}` requested without a shape; cannot infer it")
    }
    fn contains_tensor(&self, _name: &str) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_names_and_shapes() {
        let r = Recorder::new();
        let vb = r.var_builder(DType::F32, &Device::Cpu);
        let _ = candle_nn::linear(3, 4, vb.pp("a.fc")).unwrap();
        let _ = vb.get((2, 5), "b").unwrap();
        let specs = r.specs();
        assert_eq!(
            specs,
            vec![
                TensorSpec { name: "a.fc.bias".into(), shape: vec![4] },
                TensorSpec { name: "a.fc.weight".into(), shape: vec![4, 3] },
                TensorSpec { name: "b".into(), shape: vec![2, 5] },
            ]
        );
        // Same name, other shape: an error, not a silent overwrite.
        assert!(vb.get((3, 5), "b").is_err());
        let specs = record_with(|vb| {
            candle_nn::layer_norm(8, 1e-5, vb.pp("ln"))?;
            Ok(())
        })
        .unwrap();
        assert_eq!(specs.iter().map(|s| s.name.as_str()).collect::<Vec<_>>(), vec!["ln.bias", "ln.weight"]);
    }

    /// The parallel fill gives the sequential stream's values.
    #[test]
    fn random_values_match_the_sequential_stream() {
        let n = (1 << 16) * 2 + 7;
        let got = random_values(3, "w.weight", n);
        let mut st = 3 ^ fnv1a("w.weight");
        let mut want = Vec::with_capacity(n);
        while want.len() < n {
            let u1 = ((splitmix(&mut st) >> 11) as f64 + 1.0) / (1u64 << 53) as f64;
            let u2 = (splitmix(&mut st) >> 11) as f64 / (1u64 << 53) as f64;
            let (z0, z1) = crate::rng::box_muller(u1, u2);
            want.push(z0 as f32 * 0.02);
            if want.len() < n {
                want.push(z1 as f32 * 0.02);
            }
        }
        assert_eq!(got, want);
    }

    #[test]
    fn random_init_is_deterministic_and_name_keyed() {
        let a = random_values(7, "x.weight", 1000);
        assert_eq!(a, random_values(7, "x.weight", 1000));
        assert_ne!(a, random_values(8, "x.weight", 1000));
        assert_ne!(a, random_values(7, "y.weight", 1000));
        let std = (a.iter().map(|v| v * v).sum::<f32>() / 1000.0).sqrt();
        assert!((std - 0.02).abs() < 0.003, "std {std}");
        assert_eq!(random_values(7, "blocks.0.norm1.weight", 3), vec![1.0; 3]);
        assert_eq!(random_values(7, "blocks.0.mlp.fc1.bias", 2), vec![0.0; 2]);
    }
}
