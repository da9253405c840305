//! Depth sensor models: what a camera does to the true depth.
//!
//! One type serves both directions: `recon synth` *simulates* measured depth from
//! rendered depth with it, and `recon audit` *fits* it to measured data (and writes
//! an extended model back). Every effect the audit can find (bias, noise or dropout
//! as a function of one pixel covariate, optionally times a second one) is an
//! [`Effect`] here, so an audited model is directly usable for simulation and its
//! bias terms can be inverted when preprocessing real input ([`SensorModel::correct`]).
//!
//! Per pixel with covariates `c` and true z-depth `z` (metres), the model says
//! ```text
//! measured = z + bias(c) + sd(c)·N(0,1)      with probability 1 − p_missing(c), else missing (0)
//! bias(c)      = bias_m + Σ_{bias effects} f(c)
//! sd(c)        = max(0, sqrt(base_sd(z)² + noise_m²) + Σ_{noise effects} f(c))
//! p_missing(c) = clamp(dropout + Σ_{dropout effects} f(c), 0, 1)
//! ```
//! `base_sd` is 0 (ideal), constant (gaussian) or grows with z² (stereo: disparity noise).
//! The stereo kind also quantises disparity and fattens foreground edges (pixels within
//! `edge_fattening_px` of a depth discontinuity take the nearer depth).
//!
//! Physical mechanisms (registration shift, lens distortion, drift, edge effects, …;
//! [`Mechanism`]) act on whole frames: [`SensorModel::apply_frame`]. A model without
//! any behaves exactly as before. The invertible ones, fitted by `recon audit`, are
//! undone on measured depth by a [`DepthCorrection`].

mod correction;
mod mechanism;
pub use self::correction::{not_invertible_reason, DepthCorrection, NotCorrected, CORRECTION_VERSION, INVERTIBLE};
pub use self::mechanism::{expect, Expect, Mechanism, Param, Pinhole, SimFrame, MECHANISM_NAMES};

use crate::rng::SeededRng;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// Version of the sensor model file format.
pub const VERSION: u32 = 1;

/// The per-pixel quantities effects can depend on. Names are the audit's column names.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
pub enum Covariate {
    /// Simulated z-depth along the optical axis, metres.
    Depth,
    /// Distance from the principal point / image half-diagonal.
    Radius,
    /// Angle between the viewing ray and the hit face normal, degrees.
    Incidence,
    /// Pixels to the nearest discontinuity of the simulated depth.
    EdgeDistance,
    /// Luminance 0.299R+0.587G+0.114B of the RGB pixel, 0–1.
    Intensity,
    /// Object id (categorical).
    Object,
    /// Frame index.
    Frame,
    /// Pixel column (0 at the left).
    U,
    /// Pixel row (0 at the top).
    V,
}

impl Covariate {
    /// Every covariate, in declaration order.
    pub const ALL: [Covariate; 9] = [
        Covariate::Depth,
        Covariate::Radius,
        Covariate::Incidence,
        Covariate::EdgeDistance,
        Covariate::Intensity,
        Covariate::Object,
        Covariate::Frame,
        Covariate::U,
        Covariate::V,
    ];
    /// Snake-case name (the audit's column name).
    pub fn name(self) -> &'static str {
        match self {
            Covariate::Depth => "depth",
            Covariate::Radius => "radius",
            Covariate::Incidence => "incidence",
            Covariate::EdgeDistance => "edge_distance",
            Covariate::Intensity => "intensity",
            Covariate::Object => "object",
            Covariate::Frame => "frame",
            Covariate::U => "u",
            Covariate::V => "v",
        }
    }
    /// The covariate named `s`.
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL.iter().copied().find(|c| c.name() == s)
    }
    /// Categorical covariates take the `group` form; the others the numeric forms.
    pub fn is_categorical(self) -> bool {
        matches!(self, Covariate::Object)
    }
}

/// Covariate values of one pixel.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq)]
pub struct PixelCovariates {
    /// Simulated z-depth, metres.
    pub depth: f64,
    /// Distance from the principal point over the image half-diagonal.
    pub radius: f64,
    /// Angle between the viewing ray and the surface normal, degrees.
    pub incidence: f64,
    /// Pixels to the nearest depth discontinuity.
    pub edge_distance: f64,
    /// Luminance of the RGB pixel, 0–1.
    pub intensity: f64,
    /// Object id (-1: background).
    pub object: i64,
    /// Frame index.
    pub frame: i64,
    /// Pixel column.
    pub u: f64,
    /// Pixel row.
    pub v: f64,
}

impl PixelCovariates {
    /// The value of covariate `c` (categorical ones as numbers).
    pub fn get(&self, c: Covariate) -> f64 {
        match c {
            Covariate::Depth => self.depth,
            Covariate::Radius => self.radius,
            Covariate::Incidence => self.incidence,
            Covariate::EdgeDistance => self.edge_distance,
            Covariate::Intensity => self.intensity,
            Covariate::Object => self.object as f64,
            Covariate::Frame => self.frame as f64,
            Covariate::U => self.u,
            Covariate::V => self.v,
        }
    }
}

/// What an effect changes.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    /// Mean of measured − simulated depth, metres.
    Bias,
    /// Standard deviation of the residual, metres.
    Noise,
    /// Probability of a missing return.
    Dropout,
}

impl Target {
    /// Snake-case name (`bias`, `noise`, `dropout`).
    pub fn name(self) -> &'static str {
        match self {
            Target::Bias => "bias",
            Target::Noise => "noise",
            Target::Dropout => "dropout",
        }
    }
}

/// Shape of an effect in its covariate `x`. The global terms absorb constants, so the
/// numeric forms have no intercept.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(tag = "form", rename_all = "snake_case")]
pub enum Form {
    /// `slope·x`
    Linear {
        /// Change per unit of the covariate.
        slope: f64,
    },
    /// `linear·x + quadratic·x²`
    Quadratic {
        /// Coefficient of `x`.
        linear: f64,
        /// Coefficient of `x²`.
        quadratic: f64,
    },
    /// `delta` where `x > threshold`, else 0.
    Step {
        /// Where the step is.
        threshold: f64,
        /// Value above the threshold.
        delta: f64,
    },
    /// A value per category (key: the category as an integer string); unlisted ones 0.
    Group {
        /// Value per category.
        values: BTreeMap<String, f64>,
    },
}

impl Form {
    /// Snake-case name (`linear`, `quadratic`, `step`, `group`).
    pub fn name(&self) -> &'static str {
        match self {
            Form::Linear { .. } => "linear",
            Form::Quadratic { .. } => "quadratic",
            Form::Step { .. } => "step",
            Form::Group { .. } => "group",
        }
    }
    /// The form's value at `x`.
    pub fn eval(&self, x: f64) -> f64 {
        match self {
            Form::Linear { slope } => slope * x,
            Form::Quadratic { linear, quadratic } => linear * x + quadratic * x * x,
            Form::Step { threshold, delta } => {
                if x > *threshold {
                    *delta
                } else {
                    0.0
                }
            }
            Form::Group { values } => values.get(&format!("{}", x.round() as i64)).copied().unwrap_or(0.0),
        }
    }
}

/// One term: `target += form(covariate) [· by]`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Effect {
    /// What the effect changes.
    pub target: Target,
    /// The covariate it depends on.
    pub covariate: Covariate,
    #[serde(flatten)]
    /// Its shape in the covariate.
    pub form: Form,
    /// Interaction: the term is multiplied by this second covariate's value.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub by: Option<Covariate>,
    /// Free text: what the term means physically (written by the audit).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cause: Option<String>,
}

impl Effect {
    /// The effect's value at a pixel (times the `by` covariate when set).
    pub fn eval(&self, c: &PixelCovariates) -> f64 {
        let f = self.form.eval(c.get(self.covariate));
        match self.by {
            Some(b) => f * c.get(b),
            None => f,
        }
    }
}

/// The noise floor of the sensor type.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Base {
    /// Exact depth.
    Ideal,
    /// Constant standard deviation.
    Gaussian {
        /// Standard deviation in metres.
        sigma_m: f64,
    },
    /// Stereo / structured light: z = f·B/d, disparity noise `disparity_sigma_px` so
    /// sd(z) = z²·σ_d/(f·B); disparity quantised to `subpixel` px (0 = off).
    Stereo {
        /// Focal length in pixels.
        focal_px: f64,
        /// Stereo baseline in metres.
        baseline_m: f64,
        /// Disparity noise standard deviation in pixels.
        disparity_sigma_px: f64,
        #[serde(default)]
        /// Disparity quantisation step in pixels (0: off).
        subpixel: f64,
    },
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
/// A depth sensor model (module docs): base noise, global terms and effects.
pub struct SensorModel {
    /// File format version ([`VERSION`]).
    pub version: u32,
    #[serde(default)]
    /// Free-text name.
    pub name: String,
    /// Noise floor of the sensor type.
    pub base: Base,
    /// Global bias, metres.
    #[serde(default)]
    pub bias_m: f64,
    /// Global extra noise sd, metres (added in quadrature to the base).
    #[serde(default)]
    pub noise_m: f64,
    /// Global missing-return probability.
    #[serde(default)]
    pub dropout: f64,
    /// Pixels within this distance of a depth discontinuity take the nearer depth.
    #[serde(default)]
    pub edge_fattening_px: f64,
    /// Valid range; returns outside it are missing. 0 = no limit.
    #[serde(default)]
    pub min_depth_m: f64,
    #[serde(default)]
    /// Farthest valid return in metres (0: no limit).
    pub max_depth_m: f64,
    #[serde(default)]
    /// Covariate-dependent effects (bias, noise, dropout).
    pub effects: Vec<Effect>,
    /// Physical mechanisms acting on whole frames ([`Mechanism`]); at most one of each kind.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub mechanisms: Vec<Mechanism>,
}

impl Default for SensorModel {
    fn default() -> Self {
        SensorModel::ideal()
    }
}

impl SensorModel {
    /// Exact depth: no noise, bias or dropout.
    pub fn ideal() -> Self {
        SensorModel {
            version: VERSION,
            name: "ideal".into(),
            base: Base::Ideal,
            bias_m: 0.0,
            noise_m: 0.0,
            dropout: 0.0,
            edge_fattening_px: 0.0,
            min_depth_m: 0.0,
            max_depth_m: 0.0,
            effects: vec![],
            mechanisms: vec![],
        }
    }

    /// A consumer RGB-D camera in the spirit of a RealSense D4xx / Kinect-style sensor.
    pub fn stereo_default() -> Self {
        SensorModel {
            name: "stereo".into(),
            base: Base::Stereo { focal_px: 600.0, baseline_m: 0.05, disparity_sigma_px: 0.08, subpixel: 1.0 / 16.0 },
            dropout: 0.01,
            edge_fattening_px: 1.5,
            min_depth_m: 0.2,
            max_depth_m: 6.0,
            ..SensorModel::ideal()
        }
    }

    /// Parses and validates a model from JSON text; `file` names it in errors.
    pub fn from_json_str(s: &str, file: &str) -> Result<Self> {
        let m: SensorModel = serde_json::from_str(s).map_err(|e| Error::config(file, "(json)", e.to_string()))?;
        m.validate(file)?;
        Ok(m)
    }

    /// Reads and validates a model from a JSON file.
    pub fn load(path: &Path) -> Result<Self> {
        let s = std::fs::read_to_string(path).map_err(|e| Error::Io { path: path.to_path_buf(), source: e })?;
        Self::from_json_str(&s, &path.display().to_string())
    }

    /// Writes the model as pretty JSON.
    pub fn save(&self, path: &Path) -> Result<()> {
        let s = serde_json::to_string_pretty(self).expect("sensor model serialises");
        std::fs::write(path, s).map_err(|e| Error::Io { path: path.to_path_buf(), source: e })
    }

    /// Checks the version, ranges and effect forms; `file` names the model in errors.
    pub fn validate(&self, file: &str) -> Result<()> {
        let bad = |field: &str, msg: String| Err(Error::config(file, field, msg));
        if self.version != VERSION {
            return bad("version", format!("expected {VERSION}, got {}", self.version));
        }
        let finite_nonneg = |v: f64| v.is_finite() && v >= 0.0;
        if !self.bias_m.is_finite() {
            return bad("bias_m", "expected a finite number".into());
        }
        for (f, v) in [
            ("noise_m", self.noise_m),
            ("edge_fattening_px", self.edge_fattening_px),
            ("min_depth_m", self.min_depth_m),
            ("max_depth_m", self.max_depth_m),
        ] {
            if !finite_nonneg(v) {
                return bad(f, format!("expected a finite number ≥ 0, got {v}"));
            }
        }
        if !(0.0..=1.0).contains(&self.dropout) {
            return bad("dropout", format!("expected a probability in [0, 1], got {}", self.dropout));
        }
        match &self.base {
            Base::Ideal => {}
            Base::Gaussian { sigma_m } => {
                if !finite_nonneg(*sigma_m) {
                    return bad("base.sigma_m", format!("expected ≥ 0, got {sigma_m}"));
                }
            }
            Base::Stereo { focal_px, baseline_m, disparity_sigma_px, subpixel } => {
                if !(*focal_px > 0.0 && *baseline_m > 0.0) {
                    return bad("base", "stereo needs focal_px > 0 and baseline_m > 0".into());
                }
                if !finite_nonneg(*disparity_sigma_px) || !finite_nonneg(*subpixel) {
                    return bad("base", "stereo disparity_sigma_px and subpixel must be ≥ 0".into());
                }
            }
        }
        for (i, e) in self.effects.iter().enumerate() {
            let ok = match &e.form {
                Form::Linear { slope } => slope.is_finite(),
                Form::Quadratic { linear, quadratic } => linear.is_finite() && quadratic.is_finite(),
                Form::Step { threshold, delta } => threshold.is_finite() && delta.is_finite(),
                Form::Group { values } => values.iter().all(|(k, v)| k.parse::<i64>().is_ok() && v.is_finite()),
            };
            if !ok {
                return bad(&format!("effects[{i}]"), "parameters must be finite; group keys integer strings".into());
            }
            if e.covariate.is_categorical() != matches!(e.form, Form::Group { .. }) {
                return bad(
                    &format!("effects[{i}]"),
                    format!(
                        "covariate {} takes {} form",
                        e.covariate.name(),
                        if e.covariate.is_categorical() { "the group" } else { "a numeric (linear/quadratic/step)" }
                    ),
                );
            }
        }
        for (i, m) in self.mechanisms.iter().enumerate() {
            if let Err((field, msg)) = m.check() {
                return bad(&format!("mechanisms[{i}].{field}"), msg);
            }
            if self.mechanisms[..i].iter().any(|o| o.name() == m.name()) {
                return bad(&format!("mechanisms[{i}]"), format!("{} is listed twice; give each mechanism once", m.name()));
            }
        }
        Ok(())
    }

    /// Standard deviation of the sensor-type noise floor at true depth z.
    pub fn base_sd(&self, z: f64) -> f64 {
        match &self.base {
            Base::Ideal => 0.0,
            Base::Gaussian { sigma_m } => *sigma_m,
            Base::Stereo { focal_px, baseline_m, disparity_sigma_px, .. } => z * z * disparity_sigma_px / (focal_px * baseline_m),
        }
    }

    fn sum(&self, t: Target, c: &PixelCovariates) -> f64 {
        self.effects.iter().filter(|e| e.target == t).map(|e| e.eval(c)).sum()
    }

    /// Expected bias (measured − true depth) at a pixel, metres.
    pub fn bias(&self, c: &PixelCovariates) -> f64 {
        self.bias_m + self.sum(Target::Bias, c)
    }

    /// Noise standard deviation at a pixel, metres.
    pub fn sd(&self, c: &PixelCovariates) -> f64 {
        let b = self.base_sd(c.depth);
        ((b * b + self.noise_m * self.noise_m).sqrt() + self.sum(Target::Noise, c)).max(0.0)
    }

    /// Probability that the pixel's return is missing.
    pub fn p_missing(&self, c: &PixelCovariates) -> f64 {
        (self.dropout + self.sum(Target::Dropout, c)).clamp(0.0, 1.0)
    }

    /// Quantise a depth through the stereo disparity grid (identity for other kinds).
    pub fn quantise(&self, z: f64) -> f64 {
        match &self.base {
            Base::Stereo { focal_px, baseline_m, subpixel, .. } if *subpixel > 0.0 && z > 0.0 => {
                let fb = focal_px * baseline_m;
                let d = ((fb / z) / subpixel).round().max(1.0) * subpixel;
                fb / d
            }
            _ => z,
        }
    }

    /// Measured depth for one pixel (0 = missing). `c.depth` is the true depth.
    pub fn sample(&self, c: &PixelCovariates, rng: &mut SeededRng) -> f64 {
        let z = c.depth;
        if !(z > 0.0) {
            return 0.0;
        }
        if (self.min_depth_m > 0.0 && z < self.min_depth_m) || (self.max_depth_m > 0.0 && z > self.max_depth_m) {
            return 0.0;
        }
        // Draw both variates unconditionally so the stream does not depend on the branch.
        let u = rng.uniform();
        let n = rng.normal();
        if u < self.p_missing(c) {
            return 0.0;
        }
        let m = self.quantise(z + self.bias(c) + self.sd(c) * n);
        if m > 0.0 {
            m
        } else {
            0.0
        }
    }

    /// Remove the modelled bias from a measured depth (the inverse used on real input).
    pub fn correct(&self, measured: f64, c: &PixelCovariates) -> f64 {
        if measured > 0.0 {
            measured - self.bias(c)
        } else {
            measured
        }
    }

    /// Apply to a whole rendered frame. `covs[i].depth` is the true depth of pixel i
    /// (0 = no surface); row-major `width × height`. Edge fattening first (a stereo
    /// matcher's window bleeds the foreground), then per-pixel sampling.
    pub fn apply(&self, covs: &[PixelCovariates], width: usize, height: usize, seed: u64) -> Vec<f32> {
        let fattened = self.fattened(covs, width, height);
        let mut rng = SeededRng::new(seed);
        fattened.iter().map(|c| self.sample(c, &mut rng) as f32).collect()
    }

    /// [`Self::apply`] with the model's [`Mechanism`]s, which need the frame's
    /// intrinsics. Without mechanisms this is `apply`, bit for bit. With them: the
    /// model's own edge fattening, then the mechanisms' forward model ([`expect`]); each
    /// pixel draws a uniform (dropout), a normal (noise) and a uniform (mixed-pixel
    /// weight), and takes its other covariates from the surface point it sees.
    pub fn apply_frame(&self, covs: &[PixelCovariates], width: usize, height: usize, k: Pinhole, seed: u64) -> Vec<f32> {
        if self.mechanisms.is_empty() {
            return self.apply(covs, width, height, seed);
        }
        let fattened = self.fattened(covs, width, height);
        let frame = sim_frame(&fattened, width, height, k);
        let all: Vec<usize> = (0..width * height).collect();
        let ex = expect(&self.mechanisms, &frame, &all);
        let mut rng = SeededRng::new(seed);
        ex.iter()
            .enumerate()
            .map(|(i, e)| {
                let (u, n, w) = (rng.uniform(), rng.normal(), rng.uniform());
                let Some(src) = e.src else { return 0.0 };
                let mut z = e.z;
                if e.other > 0.0 {
                    z += w * (e.other - z);
                }
                if !(z > 0.0) || e.shadow {
                    return 0.0;
                }
                if (self.min_depth_m > 0.0 && z < self.min_depth_m) || (self.max_depth_m > 0.0 && z > self.max_depth_m) {
                    return 0.0;
                }
                let c = PixelCovariates { depth: z, u: covs[i].u, v: covs[i].v, frame: covs[i].frame, ..fattened[src] };
                if u < (self.p_missing(&c) + e.p).clamp(0.0, 1.0) {
                    return 0.0;
                }
                let sd = (self.sd(&c).powi(2) + e.var).sqrt();
                let m = self.quantise(e.gain * (z + self.bias(&c)) + e.offset + sd * n);
                if m > 0.0 {
                    m as f32
                } else {
                    0.0
                }
            })
            .collect()
    }

    /// The covariates the per-pixel model sees after edge fattening (what [`Self::apply`]
    /// samples from): the audit evaluates the model's expectation on exactly these.
    pub fn fattened(&self, covs: &[PixelCovariates], width: usize, height: usize) -> Vec<PixelCovariates> {
        assert_eq!(covs.len(), width * height, "covariates must be width × height");
        if self.edge_fattening_px > 0.0 {
            fatten_edges(covs, width, height, self.edge_fattening_px)
        } else {
            covs.to_vec()
        }
    }
}

/// The mechanisms' view of a frame from its per-pixel covariates.
pub fn sim_frame(covs: &[PixelCovariates], width: usize, height: usize, k: Pinhole) -> SimFrame {
    SimFrame {
        width,
        height,
        k,
        frame: covs.first().map(|c| c.frame).unwrap_or(0),
        depth: covs.iter().map(|c| c.depth as f32).collect(),
        incidence: covs.iter().map(|c| c.incidence as f32).collect(),
        intensity: covs.iter().map(|c| c.intensity as f32).collect(),
    }
}

/// Pixels within `r` px of a nearer neighbour whose depth is much smaller (a
/// discontinuity > 2 % of depth) take that nearer depth, keeping their other covariates.
fn fatten_edges(covs: &[PixelCovariates], w: usize, h: usize, r: f64) -> Vec<PixelCovariates> {
    let ri = r.ceil() as isize;
    let mut out = covs.to_vec();
    for y in 0..h as isize {
        for x in 0..w as isize {
            let i = (y as usize) * w + x as usize;
            let z = covs[i].depth;
            let mut best = if z > 0.0 { z } else { f64::INFINITY };
            for dy in -ri..=ri {
                for dx in -ri..=ri {
                    if ((dx * dx + dy * dy) as f64) > r * r {
                        continue;
                    }
                    let (xx, yy) = (x + dx, y + dy);
                    if xx < 0 || yy < 0 || xx >= w as isize || yy >= h as isize {
                        continue;
                    }
                    let zn = covs[(yy as usize) * w + xx as usize].depth;
                    if zn > 0.0 && zn < best && (!(z > 0.0) || z - zn > 0.02 * z) {
                        best = zn;
                    }
                }
            }
            if best.is_finite() && best != z {
                out[i].depth = best;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn px(depth: f64) -> PixelCovariates {
        PixelCovariates { depth, ..Default::default() }
    }

    #[test]
    fn json_round_trip_and_validation() {
        let mut m = SensorModel::stereo_default();
        m.effects.push(Effect {
            target: Target::Dropout,
            covariate: Covariate::Incidence,
            form: Form::Step { threshold: 70.0, delta: 0.8 },
            by: None,
            cause: None,
        });
        m.effects.push(Effect {
            target: Target::Bias,
            covariate: Covariate::Object,
            form: Form::Group { values: [("3".to_string(), 0.004)].into_iter().collect() },
            by: None,
            cause: Some("dark material".into()),
        });
        let s = serde_json::to_string(&m).unwrap();
        assert!(s.contains("\"form\":\"step\"") && s.contains("\"kind\":\"stereo\""));
        let back = SensorModel::from_json_str(&s, "t.json").unwrap();
        assert_eq!(back, m);
        // A numeric form on a categorical covariate is refused, naming the field.
        let bad = s.replace("\"covariate\":\"object\"", "\"covariate\":\"depth\"");
        let e = SensorModel::from_json_str(&bad, "t.json").unwrap_err().to_string();
        assert!(e.contains("effects[1]") && e.contains("t.json"), "{e}");
        let e = SensorModel::from_json_str(&s.replace("\"version\":1", "\"version\":7"), "t.json").unwrap_err().to_string();
        assert!(e.contains("version"), "{e}");
    }

    #[test]
    fn mechanisms_validate_naming_the_field_and_shift_the_frame() {
        let m = SensorModel::from_json_str(
            r#"{"version":1,"base":{"kind":"ideal"},"mechanisms":[{"mechanism":"depth_scale","scale":0.3}]}"#,
            "s.json",
        );
        let e = m.unwrap_err().to_string();
        assert!(e.contains("mechanisms[0].scale") && e.contains("[-0.05, 0.05]") && e.contains("s.json"), "{e}");
        let e = SensorModel::from_json_str(r#"{"version":1,"base":{"kind":"ideal"},"mechanisms":[{"mechanism":"warp"}]}"#, "s.json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("warp"), "{e}");
        // No mechanism: apply_frame is apply; the JSON has no `mechanisms` key.
        let (w, h) = (12, 6);
        let covs: Vec<PixelCovariates> = (0..w * h)
            .map(|i| PixelCovariates { depth: 1.0 + 0.01 * (i % w) as f64, u: (i % w) as f64, v: (i / w) as f64, ..Default::default() })
            .collect();
        let k = Pinhole { fx: 20.0, fy: 20.0, cx: 5.5, cy: 2.5 };
        let mut m = SensorModel::stereo_default();
        assert_eq!(m.apply_frame(&covs, w, h, k, 9), m.apply(&covs, w, h, 9));
        assert!(!serde_json::to_string(&m).unwrap().contains("mechanisms"));
        // A registration shift of 2 px: pixel u sees the surface of u − 2.
        let mut ideal = SensorModel::ideal();
        ideal.mechanisms.push(Mechanism::Registration { du_px: 2.0, dv_px: 0.0 });
        let out = ideal.apply_frame(&covs, w, h, k, 9);
        assert_eq!(out[3 * w + 1], 0.0);
        assert!((out[3 * w + 7] as f64 - covs[3 * w + 5].depth).abs() < 1e-6);
        m.mechanisms = ideal.mechanisms.clone();
        m.mechanisms.push(Mechanism::Registration { du_px: 1.0, dv_px: 0.0 });
        let e = m.validate("s.json").unwrap_err().to_string();
        assert!(e.contains("mechanisms[1]") && e.contains("twice"), "{e}");
    }

    #[test]
    fn stereo_noise_grows_with_range_squared() {
        let m = SensorModel::stereo_default();
        let r = m.base_sd(2.0) / m.base_sd(1.0);
        assert!((r - 4.0).abs() < 1e-12);
        // Empirical sd matches the model at 1.5 m (no quantisation, no dropout).
        let mut m = m;
        if let Base::Stereo { subpixel, .. } = &mut m.base {
            *subpixel = 0.0;
        }
        m.dropout = 0.0;
        let mut rng = SeededRng::new(3);
        let xs: Vec<f64> = (0..20000).map(|_| m.sample(&px(1.5), &mut rng) - 1.5).collect();
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        let sd = (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / xs.len() as f64).sqrt();
        assert!(mean.abs() < 3.0 * m.base_sd(1.5) / (xs.len() as f64).sqrt() + 1e-9, "mean {mean}");
        assert!((sd / m.base_sd(1.5) - 1.0).abs() < 0.03, "sd {sd} vs {}", m.base_sd(1.5));
    }

    #[test]
    fn effects_change_bias_and_dropout() {
        let mut m = SensorModel::ideal();
        m.effects.push(Effect {
            target: Target::Bias,
            covariate: Covariate::Radius,
            form: Form::Quadratic { linear: 0.0, quadratic: 0.01 },
            by: None,
            cause: None,
        });
        m.effects.push(Effect {
            target: Target::Dropout,
            covariate: Covariate::Incidence,
            form: Form::Step { threshold: 60.0, delta: 1.0 },
            by: None,
            cause: None,
        });
        let mut rng = SeededRng::new(0);
        let c = PixelCovariates { depth: 1.0, radius: 0.5, incidence: 30.0, ..Default::default() };
        assert!((m.sample(&c, &mut rng) - 1.0025).abs() < 1e-12);
        assert!((m.correct(1.0025, &c) - 1.0).abs() < 1e-12);
        let grazing = PixelCovariates { incidence: 75.0, ..c };
        assert_eq!(m.sample(&grazing, &mut rng), 0.0);
    }

    #[test]
    fn apply_is_deterministic_and_fattens_foreground() {
        let (w, h) = (8, 4);
        // Left half near (1 m), right half far (2 m).
        let covs: Vec<PixelCovariates> = (0..w * h).map(|i| px(if i % w < 4 { 1.0 } else { 2.0 })).collect();
        let mut m = SensorModel::ideal();
        m.edge_fattening_px = 1.0;
        let a = m.apply(&covs, w, h, 5);
        assert_eq!(a, m.apply(&covs, w, h, 5));
        for y in 0..h {
            assert_eq!(a[y * w + 4], 1.0, "edge pixel takes the foreground depth");
            assert_eq!(a[y * w + 5], 2.0);
        }
    }
}
