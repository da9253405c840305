//! Physical sensor mechanisms: parametric forward models of measured depth (and missing
//! returns) given the simulated frame.
//!
//! An [`Effect`](super) is a function of one pixel covariate; a mechanism is what the
//! camera physically does, and usually shows in several covariates at once (a
//! registration shift shows as bias against u, v, incidence and edge distance). Each
//! [`Mechanism`] has named parameters with a prior range ([`Mechanism::prior`]), which
//! is both the range a sensor JSON may set and the range `recon audit` searches.
//!
//! The forward model ([`expect`]) maps a simulated frame ([`SimFrame`]: z-depth,
//! intrinsics, incidence, intensity, frame index) to, per pixel, what the camera sees
//! ([`Expect`]): which surface point (geometric mechanisms warp the sampling position:
//! radial distortion, then the rotation between depth and colour cameras, then the
//! registration shift), whether an edge effect replaces or mixes its depth, whether the
//! projector's shadow hides it, and the value, noise and dropout terms. The sensor model
//! samples measured depth from it (`SensorModel::apply_frame`); the audit evaluates its
//! likelihood. No mechanism: the sensor model's per-pixel path, bit for bit.
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics of the simulated frame (pixels).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub struct Pinhole {
    /// Focal length along x.
    pub fx: f64,
    /// Focal length along y.
    pub fy: f64,
    /// Principal point x.
    pub cx: f64,
    /// Principal point y.
    pub cy: f64,
}

/// A simulated frame, row-major `width × height`.
#[derive(Clone, Debug)]
pub struct SimFrame {
    /// Image width.
    pub width: usize,
    /// Image height.
    pub height: usize,
    /// Intrinsics of the (colour) camera the simulation is rendered for.
    pub k: Pinhole,
    /// Frame index (drift).
    pub frame: i64,
    /// Simulated z-depth in metres (0: no surface).
    pub depth: Vec<f32>,
    /// Angle between the viewing ray and the surface normal, degrees.
    pub incidence: Vec<f32>,
    /// Luminance 0–1 of the colour pixel.
    pub intensity: Vec<f32>,
}

/// What a depth camera does to the simulated depth (module docs). Serialised with a
/// `mechanism` tag, e.g. `{"mechanism": "registration", "du_px": 1.5, "dv_px": -0.5}`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(tag = "mechanism", rename_all = "snake_case", deny_unknown_fields)]
pub enum Mechanism {
    /// Depth image shifted against the colour image: the depth stored at pixel (u, v)
    /// is the surface at (u − du, v − dv).
    Registration {
        /// Shift along u, pixels.
        du_px: f64,
        /// Shift along v, pixels.
        dv_px: f64,
    },
    /// Small rotation of the depth camera against the colour camera (x, y, z axes of
    /// the camera frame). About x and y it is, to first order, a registration shift
    /// (du ≈ fx·ry); the audit fits the roll about the optical axis (`rz_deg`).
    ExtrinsicRotation {
        /// Rotation about the camera x axis, degrees.
        #[serde(default)]
        rx_deg: f64,
        /// Rotation about the camera y axis, degrees.
        #[serde(default)]
        ry_deg: f64,
        /// Rotation about the optical axis, degrees.
        #[serde(default)]
        rz_deg: f64,
    },
    /// measured = z·(1 + scale): a baseline or focal calibration error.
    DepthScale {
        /// Relative scale error.
        scale: f64,
    },
    /// measured = z + offset_m.
    DepthOffset {
        /// Offset in metres.
        offset_m: f64,
    },
    /// Uncorrected radial distortion of the depth camera: the depth at normalised
    /// position x is the surface at x·(1 + k1·r² + k2·r⁴).
    RadialDistortion {
        /// r² coefficient.
        k1: f64,
        /// r⁴ coefficient.
        #[serde(default)]
        k2: f64,
    },
    /// Warm-up drift, linear in the frame index f: measured = z·(1 + scale·f) + offset·f.
    Drift {
        /// Offset per frame, metres.
        #[serde(default)]
        offset_m_per_frame: f64,
        /// Relative scale per frame.
        #[serde(default)]
        scale_per_frame: f64,
    },
    /// Pixels within `band_px` of a nearer surface (a discontinuity over 2 % of depth)
    /// take its depth: the matching window bleeds the foreground.
    EdgeFattening {
        /// Band width, pixels.
        band_px: f64,
    },
    /// Pixels within `band_px` of a discontinuity return a mix w·z_other + (1 − w)·z,
    /// w ~ U(0, 1): mean halfway, sd |Δz|/√12.
    MixedPixels {
        /// Band width, pixels.
        band_px: f64,
    },
    /// Structured light / stereo occlusion shadow: a pixel is missing when a nearer
    /// surface within the disparity difference lies on the projector's side of it
    /// (sign of `baseline_m`: + looks to larger u), i.e. at k px with
    /// k ≤ fx·|B|·(1/z_near − 1/z).
    OcclusionShadow {
        /// Signed projector baseline along x, metres.
        baseline_m: f64,
    },
    /// Disparity noise: extra sd = coefficient·z² (metres; coefficient in 1/m).
    RangeNoise {
        /// sd at 1 m, metres.
        coefficient: f64,
    },
    /// Missing returns at grazing incidence: p += rate·clamp((θ − onset)/(90° − onset), 0, 1).
    GrazingDropout {
        /// Where dropout starts, degrees.
        onset_deg: f64,
        /// Missing probability at 90°.
        rate: f64,
    },
    /// Missing returns on dark (low-albedo) surfaces: p += rate·clamp((below − I)/below, 0, 1).
    DarkDropout {
        /// Intensity below which returns drop.
        below: f64,
        /// Missing probability at intensity 0.
        rate: f64,
    },
    /// A material group (dark surfaces, intensity below `intensity_below`) with its own
    /// bias and extra noise.
    MaterialGroup {
        /// The group: intensity below this.
        intensity_below: f64,
        /// Bias of the group, metres.
        bias_m: f64,
        /// Extra noise sd of the group, metres.
        noise_m: f64,
    },
}

/// The names of every mechanism kind, in declaration order.
pub const MECHANISM_NAMES: [&str; 13] = [
    "registration",
    "extrinsic_rotation",
    "depth_scale",
    "depth_offset",
    "radial_distortion",
    "drift",
    "edge_fattening",
    "mixed_pixels",
    "occlusion_shadow",
    "range_noise",
    "grazing_dropout",
    "dark_dropout",
    "material_group",
];

/// One parameter of a mechanism: name and prior range.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Param {
    /// Field name in the sensor JSON.
    pub name: &'static str,
    /// Lowest value of the prior.
    pub lo: f64,
    /// Highest value of the prior.
    pub hi: f64,
}

// A macro, not a const fn: struct literals of constants are promoted to 'static.
macro_rules! p {
    ($name:expr, $lo:expr, $hi:expr) => {
        Param { name: $name, lo: $lo, hi: $hi }
    };
}

impl Mechanism {
    /// The mechanism of kind `name` with every parameter at its neutral value (no effect).
    pub fn neutral(name: &str) -> Option<Mechanism> {
        use Mechanism::*;
        Some(match name {
            "registration" => Registration { du_px: 0.0, dv_px: 0.0 },
            "extrinsic_rotation" => ExtrinsicRotation { rx_deg: 0.0, ry_deg: 0.0, rz_deg: 0.0 },
            "depth_scale" => DepthScale { scale: 0.0 },
            "depth_offset" => DepthOffset { offset_m: 0.0 },
            "radial_distortion" => RadialDistortion { k1: 0.0, k2: 0.0 },
            "drift" => Drift { offset_m_per_frame: 0.0, scale_per_frame: 0.0 },
            "edge_fattening" => EdgeFattening { band_px: 0.0 },
            "mixed_pixels" => MixedPixels { band_px: 0.0 },
            "occlusion_shadow" => OcclusionShadow { baseline_m: 0.0 },
            "range_noise" => RangeNoise { coefficient: 0.0 },
            "grazing_dropout" => GrazingDropout { onset_deg: 90.0, rate: 0.0 },
            "dark_dropout" => DarkDropout { below: 0.02, rate: 0.0 },
            "material_group" => MaterialGroup { intensity_below: 0.02, bias_m: 0.0, noise_m: 0.0 },
            _ => return None,
        })
    }

    /// Snake-case kind name (the JSON tag).
    pub fn name(&self) -> &'static str {
        use Mechanism::*;
        match self {
            Registration { .. } => "registration",
            ExtrinsicRotation { .. } => "extrinsic_rotation",
            DepthScale { .. } => "depth_scale",
            DepthOffset { .. } => "depth_offset",
            RadialDistortion { .. } => "radial_distortion",
            Drift { .. } => "drift",
            EdgeFattening { .. } => "edge_fattening",
            MixedPixels { .. } => "mixed_pixels",
            OcclusionShadow { .. } => "occlusion_shadow",
            RangeNoise { .. } => "range_noise",
            GrazingDropout { .. } => "grazing_dropout",
            DarkDropout { .. } => "dark_dropout",
            MaterialGroup { .. } => "material_group",
        }
    }

    /// Every parameter with its prior range, in [`Self::values`] order.
    pub fn prior(&self) -> &'static [Param] {
        use Mechanism::*;
        match self {
            Registration { .. } => &[p!("du_px", -4.0, 4.0), p!("dv_px", -4.0, 4.0)],
            ExtrinsicRotation { .. } => &[p!("rx_deg", -1.0, 1.0), p!("ry_deg", -1.0, 1.0), p!("rz_deg", -3.0, 3.0)],
            DepthScale { .. } => &[p!("scale", -0.05, 0.05)],
            DepthOffset { .. } => &[p!("offset_m", -0.02, 0.02)],
            RadialDistortion { .. } => &[p!("k1", -0.3, 0.3), p!("k2", -0.1, 0.1)],
            Drift { .. } => &[p!("offset_m_per_frame", -0.002, 0.002), p!("scale_per_frame", -0.002, 0.002)],
            EdgeFattening { .. } => &[p!("band_px", 0.0, 5.0)],
            MixedPixels { .. } => &[p!("band_px", 0.0, 4.0)],
            OcclusionShadow { .. } => &[p!("baseline_m", -0.15, 0.15)],
            RangeNoise { .. } => &[p!("coefficient", 0.0, 0.02)],
            GrazingDropout { .. } => &[p!("onset_deg", 30.0, 90.0), p!("rate", 0.0, 1.0)],
            DarkDropout { .. } => &[p!("below", 0.02, 0.6), p!("rate", 0.0, 1.0)],
            MaterialGroup { .. } => &[p!("intensity_below", 0.02, 0.6), p!("bias_m", -0.02, 0.02), p!("noise_m", 0.0, 0.02)],
        }
    }

    /// Parameter values in [`Self::prior`] order.
    pub fn values(&self) -> Vec<f64> {
        use Mechanism::*;
        match *self {
            Registration { du_px, dv_px } => vec![du_px, dv_px],
            ExtrinsicRotation { rx_deg, ry_deg, rz_deg } => vec![rx_deg, ry_deg, rz_deg],
            DepthScale { scale } => vec![scale],
            DepthOffset { offset_m } => vec![offset_m],
            RadialDistortion { k1, k2 } => vec![k1, k2],
            Drift { offset_m_per_frame, scale_per_frame } => vec![offset_m_per_frame, scale_per_frame],
            EdgeFattening { band_px } | MixedPixels { band_px } => vec![band_px],
            OcclusionShadow { baseline_m } => vec![baseline_m],
            RangeNoise { coefficient } => vec![coefficient],
            GrazingDropout { onset_deg, rate } => vec![onset_deg, rate],
            DarkDropout { below, rate } => vec![below, rate],
            MaterialGroup { intensity_below, bias_m, noise_m } => vec![intensity_below, bias_m, noise_m],
        }
    }

    /// The same kind with parameters `v` (in [`Self::prior`] order; missing ones keep theirs).
    pub fn with_values(&self, v: &[f64]) -> Mechanism {
        use Mechanism::*;
        let mut cur = self.values();
        for (c, x) in cur.iter_mut().zip(v) {
            *c = *x;
        }
        let c = &cur;
        match self {
            Registration { .. } => Registration { du_px: c[0], dv_px: c[1] },
            ExtrinsicRotation { .. } => ExtrinsicRotation { rx_deg: c[0], ry_deg: c[1], rz_deg: c[2] },
            DepthScale { .. } => DepthScale { scale: c[0] },
            DepthOffset { .. } => DepthOffset { offset_m: c[0] },
            RadialDistortion { .. } => RadialDistortion { k1: c[0], k2: c[1] },
            Drift { .. } => Drift { offset_m_per_frame: c[0], scale_per_frame: c[1] },
            EdgeFattening { .. } => EdgeFattening { band_px: c[0] },
            MixedPixels { .. } => MixedPixels { band_px: c[0] },
            OcclusionShadow { .. } => OcclusionShadow { baseline_m: c[0] },
            RangeNoise { .. } => RangeNoise { coefficient: c[0] },
            GrazingDropout { .. } => GrazingDropout { onset_deg: c[0], rate: c[1] },
            DarkDropout { .. } => DarkDropout { below: c[0], rate: c[1] },
            MaterialGroup { .. } => MaterialGroup { intensity_below: c[0], bias_m: c[1], noise_m: c[2] },
        }
    }

    /// Checks every parameter is finite and inside its prior range. Err: (field, message).
    pub fn check(&self) -> Result<(), (String, String)> {
        for (par, v) in self.prior().iter().zip(self.values()) {
            if !(v.is_finite() && v >= par.lo && v <= par.hi) {
                return Err((
                    par.name.to_string(),
                    format!("expected a number in [{}, {}] (the prior of {}), got {v}", par.lo, par.hi, self.name()),
                ));
            }
        }
        Ok(())
    }

    fn is_geometric(&self) -> bool {
        matches!(self, Mechanism::Registration { .. } | Mechanism::ExtrinsicRotation { .. } | Mechanism::RadialDistortion { .. })
    }
}

/// What the camera sees at one pixel under a list of mechanisms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Expect {
    /// Pixel whose simulated surface is seen (its incidence and intensity apply); None:
    /// off the image.
    pub src: Option<usize>,
    /// Depth of the seen surface, metres (0: no surface in the simulation).
    pub z: f64,
    /// Mixed pixel: the other surface's depth (0: not mixed). With `z`, the return is
    /// z + w·(other − z), w ~ U(0, 1).
    pub other: f64,
    /// Mixed with a surface the simulation does not have (its depth is unknown).
    pub unknown: bool,
    /// In the projector's shadow: no return.
    pub shadow: bool,
    /// Multiplicative factor on the depth (1 + scale + drift).
    pub gain: f64,
    /// Added to the depth after the gain, metres.
    pub offset: f64,
    /// Extra variance, m² (in quadrature with the sensor model's sd).
    pub var: f64,
    /// Added missing probability.
    pub p: f64,
}

/// The simulated depth at a real-valued position: bilinear where the four neighbours
/// are one smooth surface (within 2 % of each other), else the nearest pixel's depth.
/// Returns (depth, nearest pixel); None off the image.
fn sample_depth(f: &SimFrame, x: f64, y: f64) -> Option<(f64, usize)> {
    let (w, h) = (f.width as f64, f.height as f64);
    if !(x > -0.5 && y > -0.5 && x < w - 0.5 && y < h - 0.5) {
        return None;
    }
    let near = (y.round() as usize).min(f.height - 1) * f.width + (x.round() as usize).min(f.width - 1);
    let (x0, y0) = (x.floor().max(0.0), y.floor().max(0.0));
    let (x0u, y0u) = ((x0 as usize).min(f.width - 1), (y0 as usize).min(f.height - 1));
    let (x1u, y1u) = ((x0u + 1).min(f.width - 1), (y0u + 1).min(f.height - 1));
    let d = |xx: usize, yy: usize| f.depth[yy * f.width + xx] as f64;
    let q = [d(x0u, y0u), d(x1u, y0u), d(x0u, y1u), d(x1u, y1u)];
    let (lo, hi) = q.iter().fold((f64::INFINITY, 0.0f64), |(a, b), &v| (a.min(v), b.max(v)));
    if lo > 0.0 && hi - lo <= 0.02 * lo {
        let (ax, ay) = ((x - x0).clamp(0.0, 1.0), (y - y0).clamp(0.0, 1.0));
        let z = (1.0 - ay) * ((1.0 - ax) * q[0] + ax * q[1]) + ay * ((1.0 - ax) * q[2] + ax * q[3]);
        Some((z, near))
    } else {
        Some((f.depth[near] as f64, near))
    }
}

/// The geometric chain for integer pixel (u, v): (depth seen, source pixel).
fn seen(mechs: &[Mechanism], f: &SimFrame, u: usize, v: usize) -> (f64, Option<usize>) {
    if !mechs.iter().any(|m| m.is_geometric()) {
        let i = v * f.width + u;
        return (f.depth[i] as f64, Some(i));
    }
    let Some((x, y, zfac)) = geometric_chain(mechs, f.k, u as f64, v as f64) else {
        return (0.0, None);
    };
    match sample_depth(f, x, y) {
        Some((z, src)) => (if z > 0.0 { z * zfac } else { 0.0 }, Some(src)),
        None => (0.0, None),
    }
}

/// The geometric mechanisms (radial distortion, extrinsic rotation, registration) for the
/// depth image's point (x, y): the point of the simulated image it sees and the rotation's
/// depth factor; None where the rotated ray does not point forward. The forward model and
/// the depth correction share it, so the correction inverts exactly what is simulated.
pub(crate) fn geometric_chain(mechs: &[Mechanism], k: Pinhole, x: f64, y: f64) -> Option<(f64, f64, f64)> {
    let (mut xn, mut yn) = ((x - k.cx) / k.fx, (y - k.cy) / k.fy);
    let mut zfac = 1.0;
    let (mut du, mut dv) = (0.0, 0.0);
    for m in mechs {
        if let Mechanism::RadialDistortion { k1, k2 } = *m {
            let r2 = xn * xn + yn * yn;
            let s = 1.0 + k1 * r2 + k2 * r2 * r2;
            xn *= s;
            yn *= s;
        }
    }
    for m in mechs {
        if let Mechanism::ExtrinsicRotation { rx_deg, ry_deg, rz_deg } = *m {
            // Ray of the depth camera in the colour camera's frame: d_c = Rᵀ·d_d,
            // R = Rz·Ry·Rx; the depth camera's z of the hit point is z_c / d_c.z.
            let (a, b, c) = (rx_deg.to_radians(), ry_deg.to_radians(), rz_deg.to_radians());
            let (sa, ca, sb, cb, sc, cc) = (a.sin(), a.cos(), b.sin(), b.cos(), c.sin(), c.cos());
            let r = [
                [cc * cb, cc * sb * sa - sc * ca, cc * sb * ca + sc * sa],
                [sc * cb, sc * sb * sa + cc * ca, sc * sb * ca - cc * sa],
                [-sb, cb * sa, cb * ca],
            ];
            let dd = [xn, yn, 1.0];
            let dc: [f64; 3] = [0, 1, 2].map(|j| (0..3).map(|i| r[i][j] * dd[i]).sum::<f64>());
            if !(dc[2] > 1e-6) {
                return None;
            }
            xn = dc[0] / dc[2];
            yn = dc[1] / dc[2];
            zfac /= dc[2];
        }
        if let Mechanism::Registration { du_px, dv_px } = *m {
            du += du_px;
            dv += dv_px;
        }
    }
    Some((k.fx * xn + k.cx - du, k.fy * yn + k.cy - dv, zfac))
}

/// Offsets within a disc of radius r (dx² + dy² ≤ r², not the centre), nearest first
/// (ties in raster order).
fn disc(r: f64) -> Vec<(isize, isize)> {
    let ri = r.floor() as isize;
    let mut out: Vec<(isize, isize)> = vec![];
    for dy in -ri..=ri {
        for dx in -ri..=ri {
            if (dx, dy) != (0, 0) && ((dx * dx + dy * dy) as f64) <= r * r {
                out.push((dx, dy));
            }
        }
    }
    out.sort_by_key(|&(dx, dy)| dx * dx + dy * dy);
    out
}

/// The forward model at `pixels` (indices into the frame). Deterministic; mixed pixels
/// and noise are drawn by the caller.
pub fn expect(mechs: &[Mechanism], f: &SimFrame, pixels: &[usize]) -> Vec<Expect> {
    let (w, h) = (f.width as isize, f.height as isize);
    let fatten = mechs.iter().find_map(|m| if let Mechanism::EdgeFattening { band_px } = *m { Some(band_px) } else { None });
    let mixed = mechs.iter().find_map(|m| if let Mechanism::MixedPixels { band_px } = *m { Some(band_px) } else { None });
    let shadow = mechs.iter().find_map(|m| if let Mechanism::OcclusionShadow { baseline_m } = *m { Some(baseline_m) } else { None });
    let fat_disc = fatten.filter(|&b| b >= 1.0).map(disc).unwrap_or_default();
    let mix_disc = mixed.filter(|&b| b >= 1.0).map(disc).unwrap_or_default();
    let geometric = mechs.iter().any(|m| m.is_geometric());
    let at = |x: isize, y: isize| -> f64 {
        if x < 0 || y < 0 || x >= w || y >= h {
            return 0.0;
        }
        if geometric {
            seen(mechs, f, x as usize, y as usize).0
        } else {
            f.depth[y as usize * f.width + x as usize] as f64
        }
    };
    // The seen depth after edge fattening (what the mixed-pixel and shadow tests compare).
    let fattened = |x: isize, y: isize| -> f64 {
        let z = at(x, y);
        let mut best = if z > 0.0 { z } else { f64::INFINITY };
        for &(dx, dy) in &fat_disc {
            let zn = at(x + dx, y + dy);
            if zn > 0.0 && zn < best && (!(z > 0.0) || z - zn > 0.02 * z) {
                best = zn;
            }
        }
        if best.is_finite() {
            best
        } else {
            z
        }
    };
    pixels
        .iter()
        .map(|&i| {
            let (u, v) = ((i % f.width) as isize, (i / f.width) as isize);
            let (_, src) = seen(mechs, f, u as usize, v as usize);
            let z = fattened(u, v);
            let mut e = Expect { src, z, other: 0.0, unknown: false, shadow: false, gain: 1.0, offset: 0.0, var: 0.0, p: 0.0 };
            if z > 0.0 && !mix_disc.is_empty() {
                for &(dx, dy) in &mix_disc {
                    let (x, y) = (u + dx, v + dy);
                    if x < 0 || y < 0 || x >= w || y >= h {
                        continue;
                    }
                    let zn = fattened(x, y);
                    if !(zn > 0.0) {
                        e.unknown = true;
                        break;
                    }
                    if (zn - z).abs() > 0.02 * z {
                        e.other = zn;
                        break;
                    }
                }
            }
            if let Some(b) = shadow.filter(|b| *b != 0.0) {
                if z > 0.0 {
                    let s = if b > 0.0 { 1 } else { -1 };
                    let fb = f.k.fx * b.abs();
                    // The widest shadow any nearer surface (≥ 5 cm away from the camera) can cast.
                    let kmax = (fb * (1.0 / 0.05 - 1.0 / z)).ceil().clamp(0.0, 64.0) as isize;
                    for kk in 1..=kmax {
                        let zn = fattened(u + s * kk, v);
                        if zn > 0.0 && zn < z && (kk as f64) <= fb * (1.0 / zn - 1.0 / z) {
                            e.shadow = true;
                            break;
                        }
                    }
                }
            }
            let (inc, inten) = match src {
                Some(j) => (f.incidence[j] as f64, f.intensity[j] as f64),
                None => (0.0, 1.0),
            };
            for m in mechs {
                match *m {
                    Mechanism::DepthScale { scale } => e.gain += scale,
                    Mechanism::DepthOffset { offset_m } => e.offset += offset_m,
                    Mechanism::Drift { offset_m_per_frame, scale_per_frame } => {
                        e.gain += scale_per_frame * f.frame as f64;
                        e.offset += offset_m_per_frame * f.frame as f64;
                    }
                    Mechanism::RangeNoise { coefficient } => {
                        let sd = coefficient * z * z;
                        e.var += sd * sd;
                    }
                    Mechanism::GrazingDropout { onset_deg, rate } if onset_deg < 90.0 => {
                        e.p += rate * ((inc - onset_deg) / (90.0 - onset_deg)).clamp(0.0, 1.0);
                    }
                    Mechanism::DarkDropout { below, rate } if below > 0.0 => {
                        e.p += rate * ((below - inten) / below).clamp(0.0, 1.0);
                    }
                    Mechanism::MaterialGroup { intensity_below, bias_m, noise_m } if inten < intensity_below => {
                        e.offset += bias_m;
                        e.var += noise_m * noise_m;
                    }
                    _ => {}
                }
            }
            e
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(w: usize, h: usize, depth: impl Fn(usize, usize) -> f32) -> SimFrame {
        let mut d = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                d[y * w + x] = depth(x, y);
            }
        }
        SimFrame {
            width: w,
            height: h,
            k: Pinhole { fx: 50.0, fy: 50.0, cx: (w as f64 - 1.0) / 2.0, cy: (h as f64 - 1.0) / 2.0 },
            frame: 3,
            depth: d,
            incidence: vec![80.0; w * h],
            intensity: vec![0.1; w * h],
        }
    }

    #[test]
    fn registration_shifts_and_values_compose() {
        let f = frame(16, 8, |x, _| 1.0 + 0.01 * x as f32);
        let all: Vec<usize> = (0..16 * 8).collect();
        let m = [Mechanism::Registration { du_px: 2.0, dv_px: 0.0 }, Mechanism::DepthScale { scale: 0.01 }];
        let e = expect(&m, &f, &all);
        // Pixel (5, 3) sees the surface at (3, 3).
        let p = 3 * 16 + 5;
        assert_eq!(e[p].src, Some(3 * 16 + 3));
        assert!((e[p].z - 1.03).abs() < 1e-6 && (e[p].gain - 1.01).abs() < 1e-12);
        // Off the image on the left.
        assert_eq!(e[3 * 16].src, None);
        let d = expect(
            &[
                Mechanism::Drift { offset_m_per_frame: 0.001, scale_per_frame: 0.0 },
                Mechanism::GrazingDropout { onset_deg: 70.0, rate: 0.6 },
            ],
            &f,
            &[p],
        );
        assert!((d[0].offset - 0.003).abs() < 1e-12 && (d[0].p - 0.3).abs() < 1e-12);
    }

    #[test]
    fn edge_fattening_mixing_and_shadow_act_on_the_right_side() {
        // Near block (0.5 m) on columns 6..10 in front of a 1 m wall.
        let f = frame(16, 4, |x, _| if (6..10).contains(&x) { 0.5 } else { 1.0 });
        let row: Vec<usize> = (16..32).collect();
        let fat = expect(&[Mechanism::EdgeFattening { band_px: 1.0 }], &f, &row);
        assert_eq!(fat[5].z, 0.5);
        assert_eq!(fat[4].z, 1.0);
        let mix = expect(&[Mechanism::MixedPixels { band_px: 1.0 }], &f, &row);
        assert_eq!((mix[5].other, mix[6].other, mix[7].other), (0.5, 1.0, 0.0));
        // fx·B·(1/0.5 − 1/1) = 50·0.04·1 = 2 px of shadow, left of the block for B > 0.
        let sh = expect(&[Mechanism::OcclusionShadow { baseline_m: 0.04 }], &f, &row);
        let shadowed: Vec<usize> = (0..16).filter(|&x| sh[x].shadow).collect();
        assert_eq!(shadowed, vec![4, 5]);
        let sh = expect(&[Mechanism::OcclusionShadow { baseline_m: -0.04 }], &f, &row);
        let shadowed: Vec<usize> = (0..16).filter(|&x| sh[x].shadow).collect();
        assert_eq!(shadowed, vec![10, 11]);
    }

    #[test]
    fn json_names_the_mechanism_and_priors_bound_parameters() {
        let m = Mechanism::Registration { du_px: 1.5, dv_px: -0.5 };
        let s = serde_json::to_string(&m).unwrap();
        assert_eq!(s, r#"{"mechanism":"registration","du_px":1.5,"dv_px":-0.5}"#);
        assert_eq!(serde_json::from_str::<Mechanism>(&s).unwrap(), m);
        assert!(serde_json::from_str::<Mechanism>(r#"{"mechanism":"registration","du":1}"#).is_err());
        let (field, msg) = Mechanism::DepthScale { scale: 0.2 }.check().unwrap_err();
        assert_eq!(field, "scale");
        assert!(msg.contains("[-0.05, 0.05]"), "{msg}");
        for n in MECHANISM_NAMES {
            let m = Mechanism::neutral(n).unwrap();
            assert_eq!(m.name(), n);
            assert_eq!(m.prior().len(), m.values().len());
            assert_eq!(m.with_values(&m.values()), m);
            m.check().unwrap();
        }
    }
}
