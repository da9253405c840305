//! Depth audit: pixels of GT objects → residual table against a sensor model.
use super::table::{Column, ResidualTable};
use crate::sensor::{Base, Covariate, PixelCovariates, SensorModel, Target};

/// One compared pixel: its covariates (after the model's edge fattening, as the
/// simulator evaluates them; `depth` = simulated z) and the measured depth in metres
/// (0 or non-finite = missing).
#[derive(Clone, Copy, Debug)]
pub struct PixelSample {
    pub cov: PixelCovariates,
    pub measured: f64,
}

/// Spread of the disparity quantisation in z at depth z (uniform rounding: step²/12).
pub fn quantisation_sd(model: &SensorModel, z: f64) -> f64 {
    match &model.base {
        Base::Stereo { focal_px, baseline_m, subpixel, .. } if *subpixel > 0.0 => z * z * subpixel / (focal_px * baseline_m) / 12f64.sqrt(),
        _ => 0.0,
    }
}

/// Builds the residual table of `pixels` against `model`: simulated = depth + the
/// model's bias, the model's sd floor (base ⊕ quantisation) and its existing noise and
/// dropout effects as offsets, so the search looks for what the model lacks. Pixels
/// the model declares out of range are left out. Units are frames (`cov.frame`).
pub fn residual_table(model: &SensorModel, pixels: &[PixelSample], source: &str) -> ResidualTable {
    let mut t = ResidualTable { source: source.to_string(), value_unit: "m".into(), ..Default::default() };
    let mut frames: Vec<i64> = pixels.iter().map(|p| p.cov.frame).collect();
    frames.sort_unstable();
    frames.dedup();
    t.unit_names = frames.iter().map(|f| f.to_string()).collect();
    let mut cols: Vec<Vec<f64>> = vec![vec![]; Covariate::ALL.len()];
    for p in pixels {
        let c = &p.cov;
        let z = c.depth;
        if !(z > 0.0) || (model.min_depth_m > 0.0 && z < model.min_depth_m) || (model.max_depth_m > 0.0 && z > model.max_depth_m) {
            continue;
        }
        t.measured.push(if p.measured.is_finite() && p.measured > 0.0 { p.measured } else { f64::NAN });
        t.simulated.push(z + model.bias(c));
        let b = model.base_sd(z);
        let q = quantisation_sd(model, z);
        t.sd_floor.push((b * b + q * q).sqrt());
        t.sd_offset.push(model.effects.iter().filter(|e| e.target == Target::Noise).map(|e| e.eval(c)).sum());
        t.p_offset.push(model.effects.iter().filter(|e| e.target == Target::Dropout).map(|e| e.eval(c)).sum());
        t.unit.push(frames.binary_search(&c.frame).expect("frame listed"));
        for (k, cv) in Covariate::ALL.iter().enumerate() {
            cols[k].push(c.get(*cv));
        }
    }
    for (k, cv) in Covariate::ALL.iter().enumerate() {
        let values = std::mem::take(&mut cols[k]);
        t.columns.push(if cv.is_categorical() { Column::categorical(cv.name(), values) } else { Column::numeric(cv.name(), values) });
    }
    t
}
