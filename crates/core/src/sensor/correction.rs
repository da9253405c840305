//! Depth correction: undoing fitted sensor mechanisms on a measured depth image.
//!
//! `recon audit depth` fits [`Mechanism`]s to measured-vs-simulated depth and writes the
//! invertible ones as a [`DepthCorrection`] (`depth_correction.json`). Applying it
//! ([`DepthCorrection::apply`]) maps a measured depth image back to what the ideal,
//! registered camera would have measured:
//!
//! - geometric mechanisms (`registration`, `extrinsic_rotation`, `radial_distortion`):
//!   the forward model says pixel s of the depth image holds the surface at position
//!   p(s) (distortion, then rotation, then the registration shift; as in
//!   [`expect`](super::expect)). The corrected depth at pixel q is the measured depth at
//!   s = p⁻¹(q) (found by fixed-point iteration, sampled bilinearly where its four
//!   neighbours are one surface, else the nearest reading), times the rotation's depth
//!   factor at s;
//! - value mechanisms (`depth_scale`, `depth_offset`, `drift`): z = (m − offset) / gain
//!   with gain = 1 + scale + scale_per_frame·f and offset = offset_m + offset_m_per_frame·f
//!   at frame index f.
//!
//! Noise, dropout and edge effects cannot be undone on one image (a missing or mixed
//! reading holds no trace of the surface behind it); the file lists them under
//! `not_corrected` with the reason.
use super::mechanism::{geometric_chain, Mechanism, Pinhole};
use crate::dataset::frame::RgbdFrame;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Version of the depth correction file format.
pub const CORRECTION_VERSION: u32 = 1;

/// Kinds a depth correction can undo.
pub const INVERTIBLE: [&str; 6] = ["registration", "extrinsic_rotation", "depth_scale", "depth_offset", "radial_distortion", "drift"];

/// Why a mechanism kind cannot be undone on a depth image (None: it can).
pub fn not_invertible_reason(kind: &str) -> Option<&'static str> {
    Some(match kind {
        "edge_fattening" => {
            "edge effect: a fattened edge pixel holds the nearer surface's depth, and the surface behind it is not in the image"
        }
        "mixed_pixels" => {
            "edge effect: a mixed pixel's weight is random per pixel, so the surface's own depth cannot be recovered from one reading"
        }
        "occlusion_shadow" => "missing returns in the projector's shadow: a missing reading cannot be restored",
        "range_noise" => "random noise with zero mean: nothing to subtract",
        "grazing_dropout" | "dark_dropout" => "missing returns: a missing reading cannot be restored",
        "material_group" => "its bias applies to surfaces by colour intensity and its noise is random; not undone on the depth image",
        _ => return None,
    })
}

/// A fitted mechanism the correction does not undo, and why.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NotCorrected {
    /// The fitted mechanism (sensor-JSON form).
    pub fitted: Mechanism,
    /// Why it is not undone.
    pub reason: String,
}

/// The correction file (`depth_correction.json`; module docs).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct DepthCorrection {
    /// File format version ([`CORRECTION_VERSION`]).
    pub version: u32,
    /// Where the parameters come from (free text: the audited dataset).
    #[serde(default)]
    pub source: String,
    /// Invertible mechanisms with their fitted parameters (sensor-JSON form), undone in
    /// the reverse order of the forward model whatever their order here.
    pub corrections: Vec<Mechanism>,
    /// Fitted mechanisms that are not undone, with the reason.
    #[serde(default)]
    pub not_corrected: Vec<NotCorrected>,
    /// Remarks (e.g. a correction whose mechanism the audit found ambiguous).
    #[serde(default)]
    pub notes: Vec<String>,
}

const FIELDS: [&str; 5] = ["version", "source", "corrections", "not_corrected", "notes"];

impl DepthCorrection {
    /// The correction for `fitted` mechanisms (e.g. the audit's `mechanisms.fitted`): the
    /// invertible ones are corrected, the others listed with their reason.
    pub fn from_fitted(fitted: &[Mechanism], source: &str) -> Self {
        let mut c = DepthCorrection {
            version: CORRECTION_VERSION,
            source: source.into(),
            corrections: vec![],
            not_corrected: vec![],
            notes: vec![],
        };
        for m in fitted {
            match not_invertible_reason(m.name()) {
                None => c.corrections.push(m.clone()),
                Some(r) => c.not_corrected.push(NotCorrected { fitted: m.clone(), reason: r.into() }),
            }
        }
        c
    }

    /// Parses and validates a correction from JSON text; `file` names it in errors, which
    /// name the field (`corrections[1].du_px`) and what was expected.
    pub fn from_json_str(s: &str, file: &str) -> Result<Self> {
        let v: serde_json::Value = serde_json::from_str(s).map_err(|e| Error::config(file, "(json)", e.to_string()))?;
        let obj = v.as_object().ok_or_else(|| Error::config(file, "(json)", "expected a JSON object"))?;
        if let Some(k) = obj.keys().find(|k| !FIELDS.contains(&k.as_str())) {
            return Err(Error::config(file, k, format!("unknown field; expected one of {}", FIELDS.join(", "))));
        }
        match obj.get("version").map(|v| v.as_u64()) {
            Some(Some(x)) if x == CORRECTION_VERSION as u64 => {}
            Some(_) => return Err(Error::config(file, "version", format!("expected {CORRECTION_VERSION}, got {}", obj["version"]))),
            None => return Err(Error::config(file, "version", format!("missing; expected {CORRECTION_VERSION}"))),
        }
        let arr = |key: &str, required: bool| -> Result<Vec<serde_json::Value>> {
            match obj.get(key) {
                Some(serde_json::Value::Array(a)) => Ok(a.clone()),
                Some(_) => Err(Error::config(file, key, "expected an array")),
                None if required => Err(Error::config(file, key, "missing; expected an array of mechanisms (may be empty)")),
                None => Ok(vec![]),
            }
        };
        let mut c = DepthCorrection {
            version: CORRECTION_VERSION,
            source: match obj.get("source") {
                None => String::new(),
                Some(serde_json::Value::String(s)) => s.clone(),
                Some(_) => return Err(Error::config(file, "source", "expected a string")),
            },
            corrections: vec![],
            not_corrected: vec![],
            notes: vec![],
        };
        for (i, m) in arr("corrections", true)?.into_iter().enumerate() {
            let field = format!("corrections[{i}]");
            let m: Mechanism = serde_json::from_value(m).map_err(|e| Error::config(file, &field, e.to_string()))?;
            if let Some(r) = not_invertible_reason(m.name()) {
                return Err(Error::config(
                    file,
                    format!("{field}.mechanism"),
                    format!("{} cannot be corrected ({r}); expected one of {}", m.name(), INVERTIBLE.join(", ")),
                ));
            }
            if let Err((f, msg)) = m.check() {
                return Err(Error::config(file, format!("{field}.{f}"), msg));
            }
            if c.corrections.iter().any(|o| o.name() == m.name()) {
                return Err(Error::config(file, &field, format!("{} is listed twice; give each mechanism once", m.name())));
            }
            c.corrections.push(m);
        }
        for (i, n) in arr("not_corrected", false)?.into_iter().enumerate() {
            let n: NotCorrected =
                serde_json::from_value(n).map_err(|e| Error::config(file, format!("not_corrected[{i}]"), e.to_string()))?;
            c.not_corrected.push(n);
        }
        for (i, n) in arr("notes", false)?.into_iter().enumerate() {
            match n {
                serde_json::Value::String(s) => c.notes.push(s),
                _ => return Err(Error::config(file, format!("notes[{i}]"), "expected a string")),
            }
        }
        Ok(c)
    }

    /// Reads and validates a correction file.
    pub fn load(path: &Path) -> Result<Self> {
        let s = std::fs::read_to_string(path).map_err(|e| Error::Io { path: path.to_path_buf(), source: e })?;
        Self::from_json_str(&s, &path.display().to_string())
    }

    /// Writes the correction as pretty JSON.
    pub fn save(&self, path: &Path) -> Result<()> {
        let s = serde_json::to_string_pretty(self).expect("depth correction serialises");
        std::fs::write(path, s).map_err(|e| Error::Io { path: path.to_path_buf(), source: e })
    }

    /// Whether applying it changes nothing (no correction listed).
    pub fn is_identity(&self) -> bool {
        self.corrections.is_empty()
    }

    /// Whether it depends on the frame index (a drift correction).
    pub fn uses_frame_index(&self) -> bool {
        self.corrections.iter().any(|m| matches!(m, Mechanism::Drift { .. }))
    }

    /// One line: what it corrects and what not.
    pub fn describe(&self) -> String {
        let names = |v: Vec<&str>| if v.is_empty() { "nothing".to_string() } else { v.join(", ") };
        format!(
            "corrects {}; not corrected: {}",
            names(self.corrections.iter().map(|m| m.name()).collect()),
            names(self.not_corrected.iter().map(|n| n.fitted.name()).collect())
        )
    }

    /// Position p(s) that pixel s = (x, y) of the measured depth image sees, and the
    /// rotation's depth factor there (the forward model's geometric chain).
    fn forward(&self, k: Pinhole, x: f64, y: f64) -> Option<(f64, f64, f64)> {
        geometric_chain(&self.corrections, k, x, y)
    }

    /// (gain, offset) of the value mechanisms at frame index `frame`.
    fn gain_offset(&self, frame: i64) -> (f64, f64) {
        let (mut g, mut o) = (1.0, 0.0);
        for m in &self.corrections {
            match *m {
                Mechanism::DepthScale { scale } => g += scale,
                Mechanism::DepthOffset { offset_m } => o += offset_m,
                Mechanism::Drift { offset_m_per_frame, scale_per_frame } => {
                    g += scale_per_frame * frame as f64;
                    o += offset_m_per_frame * frame as f64;
                }
                _ => {}
            }
        }
        (g, o)
    }

    /// The corrected depth image (metres, row-major `width × height`, 0 or non-finite:
    /// no reading) of a measured one taken with intrinsics `k` at frame index `frame`
    /// (module docs). Pixels whose source falls off the image or on no reading get 0.
    pub fn apply(&self, depth: &[f32], width: usize, height: usize, k: Pinhole, frame: i64) -> Vec<f32> {
        assert_eq!(depth.len(), width * height, "depth must be width × height");
        if self.is_identity() {
            return depth.to_vec();
        }
        let geometric = self.corrections.iter().any(|m| {
            matches!(m, Mechanism::Registration { .. } | Mechanism::ExtrinsicRotation { .. } | Mechanism::RadialDistortion { .. })
        });
        let (gain, offset) = self.gain_offset(frame);
        let valid = |z: f32| z.is_finite() && z > 0.0;
        let value = |m: f64, zfac: f64| -> f32 {
            let z = (m - offset) / gain / zfac;
            if z > 0.0 && z.is_finite() {
                z as f32
            } else {
                0.0
            }
        };
        let mut out = vec![0.0f32; width * height];
        for y in 0..height {
            for x in 0..width {
                let i = y * width + x;
                if !geometric {
                    if valid(depth[i]) {
                        out[i] = value(depth[i] as f64, 1.0);
                    }
                    continue;
                }
                // s with p(s) = q: fixed-point iteration from q (p is close to the identity).
                let (qx, qy) = (x as f64, y as f64);
                let (mut sx, mut sy) = (qx, qy);
                let mut zfac = 1.0;
                let mut ok = false;
                for _ in 0..20 {
                    let Some((px, py, zf)) = self.forward(k, sx, sy) else { break };
                    zfac = zf;
                    let (ex, ey) = (qx - px, qy - py);
                    sx += ex;
                    sy += ey;
                    if ex.abs() < 1e-4 && ey.abs() < 1e-4 {
                        ok = true;
                        break;
                    }
                }
                if !ok {
                    continue;
                }
                if let Some(m) = sample(depth, width, height, sx, sy) {
                    out[i] = value(m, zfac);
                }
            }
        }
        out
    }

    /// [`Self::apply`] to a frame's depth, with its intrinsics.
    pub fn apply_to_frame(&self, frame: &mut RgbdFrame, index: i64) {
        let k = frame.intrinsics;
        let pin = Pinhole { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
        frame.depth_m = self.apply(&frame.depth_m, frame.width, frame.height, pin, index);
    }
}

/// The measured depth at a real-valued position: bilinear where the four neighbours are
/// valid readings of one surface (within 2 % of each other), else the nearest pixel's
/// reading. None: off the image or no reading.
fn sample(d: &[f32], w: usize, h: usize, x: f64, y: f64) -> Option<f64> {
    if !(x > -0.5 && y > -0.5 && x < w as f64 - 0.5 && y < h as f64 - 0.5) {
        return None;
    }
    let ok = |z: f32| z.is_finite() && z > 0.0;
    let near = d[(y.round() as usize).min(h - 1) * w + (x.round() as usize).min(w - 1)];
    let (x0, y0) = (x.floor().max(0.0), y.floor().max(0.0));
    let (x0u, y0u) = ((x0 as usize).min(w - 1), (y0 as usize).min(h - 1));
    let (x1u, y1u) = ((x0u + 1).min(w - 1), (y0u + 1).min(h - 1));
    let q = [d[y0u * w + x0u], d[y0u * w + x1u], d[y1u * w + x0u], d[y1u * w + x1u]];
    if q.iter().all(|&z| ok(z)) {
        let (lo, hi) = q.iter().fold((f64::INFINITY, 0.0f64), |(a, b), &v| (a.min(v as f64), b.max(v as f64)));
        if hi - lo <= 0.02 * lo {
            let (ax, ay) = ((x - x0).clamp(0.0, 1.0), (y - y0).clamp(0.0, 1.0));
            let q = q.map(|v| v as f64);
            return Some((1.0 - ay) * ((1.0 - ax) * q[0] + ax * q[1]) + ay * ((1.0 - ax) * q[2] + ax * q[3]));
        }
    }
    ok(near).then_some(near as f64)
}

#[cfg(test)]
mod tests {
    use super::super::{PixelCovariates, SensorModel, MECHANISM_NAMES};
    use super::*;

    /// A table-top-like frame: a tilted plane with a smooth bump, 160×120.
    fn clean(w: usize, h: usize) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                let r2 = (x - 90.0).powi(2) + (y - 50.0).powi(2);
                (0.9 + 0.002 * x + 0.001 * y - 0.08 * (-r2 / (2.0 * 18.0f64.powi(2))).exp()) as f32
            })
            .collect()
    }

    /// Measured depth of `clean` under `mechs` (ideal sensor: no noise, no dropout).
    fn plant(mechs: &[Mechanism], d: &[f32], w: usize, h: usize, k: Pinhole, frame: i64) -> Vec<f32> {
        let covs: Vec<PixelCovariates> = (0..w * h)
            .map(|i| PixelCovariates {
                depth: d[i] as f64,
                u: (i % w) as f64,
                v: (i / w) as f64,
                frame,
                intensity: 0.5,
                ..Default::default()
            })
            .collect();
        let mut m = SensorModel::ideal();
        m.mechanisms = mechs.to_vec();
        m.apply_frame(&covs, w, h, k, 1)
    }

    /// Median and 95th percentile of |a − b| over the interior (a margin of 12 px).
    fn err(a: &[f32], b: &[f32], w: usize, h: usize) -> (f64, f64) {
        let mut e: Vec<f64> = (0..w * h)
            .filter(|i| (12..w - 12).contains(&(i % w)) && (12..h - 12).contains(&(i / w)))
            .map(|i| if a[i] > 0.0 && b[i] > 0.0 { (a[i] - b[i]).abs() as f64 } else { 1.0 })
            .collect();
        e.sort_by(|x, y| x.total_cmp(y));
        (e[e.len() / 2], e[e.len() * 95 / 100])
    }

    #[test]
    fn correcting_a_planted_frame_gives_back_the_clean_depth() {
        let (w, h) = (160, 120);
        let k = Pinhole { fx: 150.0, fy: 150.0, cx: 79.5, cy: 59.5 };
        let d = clean(w, h);
        let cases: Vec<Vec<Mechanism>> = vec![
            vec![Mechanism::Registration { du_px: 1.6, dv_px: -0.7 }],
            vec![Mechanism::ExtrinsicRotation { rx_deg: 0.0, ry_deg: 0.0, rz_deg: 2.0 }],
            vec![Mechanism::DepthScale { scale: 0.02 }, Mechanism::DepthOffset { offset_m: -0.006 }],
            vec![Mechanism::RadialDistortion { k1: 0.2, k2: 0.0 }],
            vec![Mechanism::Drift { offset_m_per_frame: 0.0005, scale_per_frame: 0.001 }],
            vec![
                Mechanism::RadialDistortion { k1: -0.15, k2: 0.0 },
                Mechanism::Registration { du_px: -2.2, dv_px: 1.0 },
                Mechanism::ExtrinsicRotation { rx_deg: 0.3, ry_deg: -0.2, rz_deg: -1.5 },
                Mechanism::DepthScale { scale: -0.015 },
                Mechanism::Drift { offset_m_per_frame: -0.0004, scale_per_frame: 0.0 },
            ],
        ];
        let frame = 6;
        for mechs in cases {
            let measured = plant(&mechs, &d, w, h, k, frame);
            let before = err(&measured, &d, w, h);
            let corr = DepthCorrection::from_fitted(&mechs, "test");
            assert_eq!(corr.corrections.len(), mechs.len());
            let fixed = corr.apply(&measured, w, h, k, frame);
            let after = err(&fixed, &d, w, h);
            // The planted error is mm-sized; corrected, what remains is interpolation.
            assert!(before.0 > 1e-3, "{mechs:?}: planted error only {before:?}");
            assert!(after.0 < 5e-5 && after.1 < 2e-4, "{mechs:?}: corrected error {after:?} (before {before:?})");
            // The wrong frame index leaves a drift error.
            if corr.uses_frame_index() {
                let wrong = err(&corr.apply(&measured, w, h, k, 0), &d, w, h);
                assert!(wrong.0 > 1e-3, "{wrong:?}");
            }
        }
    }

    #[test]
    fn noise_dropout_and_edges_are_listed_not_corrected() {
        for n in MECHANISM_NAMES {
            let m = Mechanism::neutral(n).unwrap();
            assert_eq!(INVERTIBLE.contains(&n), not_invertible_reason(n).is_none(), "{n}");
            let c = DepthCorrection::from_fitted(&[m], "x");
            assert_eq!(c.corrections.len() + c.not_corrected.len(), 1);
        }
        let c = DepthCorrection::from_fitted(&[Mechanism::RangeNoise { coefficient: 0.01 }], "x");
        assert!(c.is_identity() && c.not_corrected[0].reason.contains("noise"));
        let d = vec![1.0f32, 0.0, 2.0, f32::NAN];
        let k = Pinhole { fx: 1.0, fy: 1.0, cx: 0.5, cy: 0.5 };
        assert_eq!(c.apply(&d, 2, 2, k, 0)[..3], d[..3]);
    }

    #[test]
    fn bad_files_name_the_file_and_the_field() {
        let ok = DepthCorrection::from_fitted(
            &[Mechanism::Registration { du_px: 1.0, dv_px: 0.0 }, Mechanism::RangeNoise { coefficient: 0.01 }],
            "audit",
        );
        let text = serde_json::to_string(&ok).unwrap();
        assert_eq!(DepthCorrection::from_json_str(&text, "c.json").unwrap(), ok);
        let bad = |s: &str| DepthCorrection::from_json_str(s, "c.json").unwrap_err().to_string();
        let e = bad(&text.replace("\"version\":1", "\"version\":2"));
        assert!(e.contains("c.json") && e.contains("version") && e.contains("expected 1"), "{e}");
        let e = bad(&text.replace("\"du_px\":1.0", "\"du_px\":9.0"));
        assert!(e.contains("corrections[0].du_px") && e.contains("[-4, 4]"), "{e}");
        let e = bad(r#"{"version":1,"corrections":[{"mechanism":"range_noise","coefficient":0.01}]}"#);
        assert!(e.contains("corrections[0].mechanism") && e.contains("cannot be corrected"), "{e}");
        let e = bad(r#"{"version":1,"corrections":[{"mechanism":"registration","du":1}]}"#);
        assert!(e.contains("corrections[0]") && e.contains("du"), "{e}");
        let e = bad(r#"{"version":1}"#);
        assert!(e.contains("corrections") && e.contains("missing"), "{e}");
        let e = bad(r#"{"version":1,"corrections":[],"extra":0}"#);
        assert!(e.contains("extra") && e.contains("unknown field"), "{e}");
        let e = bad("[1, 2");
        assert!(e.contains("c.json"), "{e}");
    }
}
