//! The seeded generator every module draws from: model noise, synthetic
//! scenes, sensor noise, surface sampling and RANSAC alike.

use crate::Result;
use candle_core::{DType, Device, Tensor};

/// Two independent standard normals from two uniforms in (0, 1] and [0, 1)
/// (Box–Muller): `(r·cos a, r·sin a)` with `r = √(−2 ln u1)`, `a = 2π·u2`.
/// Every generator of the crate goes through this one arithmetic, so a value
/// drawn from the same uniforms is the same bits wherever it is drawn.
#[inline]
pub fn box_muller(u1: f64, u2: f64) -> (f64, f64) {
    let r = (-2.0 * u1.ln()).sqrt();
    let a = std::f64::consts::TAU * u2;
    (r * a.cos(), r * a.sin())
}

/// Deterministic standard-normal noise from a 64-bit seed (xoshiro256++
/// seeded by SplitMix64, Box–Muller). candle's CPU `randn` is not seedable, and
/// a fixed seed must give identical samples on every run and platform.
#[derive(Debug, Clone)]
pub struct SeededRng {
    s: [u64; 4],
    spare: Option<f64>,
}

impl SeededRng {
    /// A generator seeded from `seed` (SplitMix64 expansion).
    pub fn new(seed: u64) -> Self {
        let mut z = seed;
        let mut next = || {
            z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut x = z;
            x = (x ^ (x >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            x = (x ^ (x >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            x ^ (x >> 31)
        };
        Self { s: [next(), next(), next(), next()], spare: None }
    }

    /// The generator's full state (xoshiro words, cached Box–Muller value as
    /// f64 bits), for checkpoints; [`Self::from_state`] continues the stream.
    pub fn state(&self) -> ([u64; 4], Option<u64>) {
        (self.s, self.spare.map(f64::to_bits))
    }

    /// A generator continuing from a saved [`Self::state`].
    pub fn from_state(s: [u64; 4], spare_bits: Option<u64>) -> Self {
        Self { s, spare: spare_bits.map(f64::from_bits) }
    }

    /// Next 64 random bits (xoshiro256++).
    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[0].wrapping_add(s[3]).rotate_left(23).wrapping_add(s[0]);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in (0, 1) (never exactly 0, so the log in Box–Muller is finite).
    pub fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) * (1.0 / (1u64 << 53) as f64)
    }

    /// A standard-normal sample (Box–Muller, the second value cached).
    pub fn normal(&mut self) -> f64 {
        if let Some(v) = self.spare.take() {
            return v;
        }
        let (z0, z1) = box_muller(self.uniform(), self.uniform());
        self.spare = Some(z1);
        z0
    }

    /// An f32 tensor of standard-normal values.
    pub fn randn(&mut self, shape: &[usize], device: &Device) -> Result<Tensor> {
        let n: usize = shape.iter().product();
        let v: Vec<f32> = (0..n).map(|_| self.normal() as f32).collect();
        Ok(Tensor::from_vec(v, shape, device)?.to_dtype(DType::F32)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeded_noise_is_deterministic_and_standard() -> Result<()> {
        let dev = Device::Cpu;
        let a = SeededRng::new(42).randn(&[10000], &dev)?.to_vec1::<f32>()?;
        let b = SeededRng::new(42).randn(&[10000], &dev)?.to_vec1::<f32>()?;
        let c = SeededRng::new(43).randn(&[10000], &dev)?.to_vec1::<f32>()?;
        assert_eq!(a, b);
        assert_ne!(a, c);
        // A restored state continues the stream exactly (also mid Box–Muller pair).
        let mut r = SeededRng::new(9);
        r.normal();
        let (s, spare) = r.state();
        let mut q = SeededRng::from_state(s, spare);
        assert_eq!((0..5).map(|_| r.normal()).collect::<Vec<_>>(), (0..5).map(|_| q.normal()).collect::<Vec<_>>());
        let mean = a.iter().map(|&v| v as f64).sum::<f64>() / a.len() as f64;
        let var = a.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / a.len() as f64;
        assert!(mean.abs() < 0.05 && (var - 1.0).abs() < 0.05, "mean {mean} var {var}");
        Ok(())
    }

    /// `box_muller` is the arithmetic the generators spelled out before it
    /// existed (with 2π as `TAU` and as `2.0 * PI`), bit for bit.
    #[test]
    fn box_muller_keeps_the_written_out_bits() {
        let mut r = SeededRng::new(5);
        for _ in 0..1000 {
            let (u1, u2) = (r.uniform(), r.uniform());
            let (z0, z1) = box_muller(u1, u2);
            let rad = (-2.0 * u1.ln()).sqrt();
            assert_eq!(z0.to_bits(), (rad * (std::f64::consts::TAU * u2).cos()).to_bits());
            assert_eq!(z1.to_bits(), (rad * (2.0 * std::f64::consts::PI * u2).sin()).to_bits());
        }
        // The pair's second value is the generator's next draw.
        let (mut a, mut b) = (SeededRng::new(8), SeededRng::new(8));
        let want = box_muller(b.uniform(), b.uniform());
        assert_eq!((a.normal().to_bits(), a.normal().to_bits()), (want.0.to_bits(), want.1.to_bits()));
    }
}
