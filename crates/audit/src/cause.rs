//! Physical interpretation of a finding, in words. Depth-sensor covariates get the
//! usual suspects of RGB-D cameras; other tables get a neutral description.
use recon_core::sensor::{Form, Target};

/// How a form varies over the observed covariate range `[lo, hi]`: the change from lo
/// to hi and whether it is monotone.
fn span(form: &Form, lo: f64, hi: f64) -> (f64, bool) {
    let n = 32;
    let ys: Vec<f64> = (0..=n).map(|i| form.eval(lo + (hi - lo) * i as f64 / n as f64)).collect();
    let inc = ys.windows(2).all(|w| w[1] >= w[0] - 1e-15);
    let dec = ys.windows(2).all(|w| w[1] <= w[0] + 1e-15);
    (ys[n] - ys[0], inc || dec)
}

fn amount(target: Target, v: f64, unit: &str) -> String {
    match target {
        Target::Dropout => format!("{:+.1} percentage points", 100.0 * v),
        _ if unit == "m" => format!("{:+.2} mm", 1000.0 * v),
        _ => format!("{v:+.4} {unit}").trim_end().to_string(),
    }
}

fn what(target: Target) -> &'static str {
    match target {
        Target::Bias => "bias (mean of measured − simulated)",
        Target::Noise => "noise (spread)",
        Target::Dropout => "missing-return rate",
    }
}

/// One sentence: what changes, by how much, along what, and the likely physical cause.
/// `range` is the covariate's observed [lo, hi]; `unit` the residual's unit ("m" for depth).
pub fn describe(
    target: Target,
    covariate: &str,
    form: &Form,
    by: Option<&str>,
    range: (f64, f64),
    unit: &str,
    depth_sensor: bool,
) -> String {
    let (lo, hi) = range;
    let shape = match form {
        Form::Step { threshold, delta } => {
            format!("{} changes by {} where {covariate} > {}", what(target), amount(target, *delta, unit), fmt_num(*threshold))
        }
        Form::Group { values } => {
            let (mut mn, mut mx) = (0.0f64, 0.0f64);
            for v in values.values() {
                mn = mn.min(*v);
                mx = mx.max(*v);
            }
            format!(
                "{} differs between {covariate} values (spread {} across {} groups)",
                what(target),
                amount(target, mx - mn, unit).trim_start_matches('+'),
                values.len() + 1
            )
        }
        _ => {
            let (d, mono) = span(form, lo, hi);
            let kind = if matches!(form, Form::Quadratic { .. }) {
                if mono {
                    "curving"
                } else {
                    "non-monotone (quadratic)"
                }
            } else {
                "linearly"
            };
            format!(
                "{} {} {} with {covariate}: {} from {covariate} = {} to {}",
                what(target),
                if d >= 0.0 { "grows" } else { "falls" },
                kind,
                amount(target, d, unit),
                fmt_num(lo),
                fmt_num(hi)
            )
        }
    };
    let shape = match by {
        Some(b) => format!("{shape}, scaled by {b} (interaction)"),
        None => shape,
    };
    if !depth_sensor {
        return format!("{shape}.");
    }
    let rising = match form {
        Form::Step { delta, .. } => *delta > 0.0,
        Form::Group { .. } => true,
        _ => span(form, lo, hi).0 > 0.0,
    };
    let quad = matches!(form, Form::Quadratic { .. });
    let why = match (target, covariate) {
        (Target::Noise, "depth") if quad => "noise grows with range² — disparity noise/quantisation of a stereo or structured-light sensor (σ_z = z²·σ_d/(f·B))",
        (Target::Noise, "depth") if rising => "noise grows with range — disparity noise of a stereo/structured-light sensor (σ_z ∝ z²; a linear term is its first-order form) or multipath in time-of-flight",
        (Target::Bias, "depth") => "range-dependent bias — depth-scale error of the sensor calibration (baseline or focal length of the IR pair), or temperature drift of the projector",
        (Target::Dropout, "depth") if rising => "returns missing at long range — too little projected pattern or signal comes back",
        (Target::Dropout, "depth") => "returns missing at short range — closer than the sensor's minimum distance (pattern defocus, disparity beyond the search range)",
        (Target::Bias, "radius") | (Target::Bias, "u") | (Target::Bias, "v") => "depth warps away from the image centre — unmodelled lens distortion of the IR camera/projector or depth-to-colour registration error (the GT uses the plain pinhole)",
        (Target::Noise, "radius") | (Target::Noise, "u") | (Target::Noise, "v") => "noise grows towards the image border — lens distortion and vignetting of the IR camera degrade matching off-axis",
        (Target::Dropout, "radius") | (Target::Dropout, "u") | (Target::Dropout, "v") => "returns missing towards the border — the projector's pattern does not cover the whole field of view (or IR vignetting)",
        (Target::Dropout, "incidence") => "returns missing at grazing incidence — slanted surfaces reflect too little of the projected pattern back",
        (Target::Noise, "incidence") => "noise grows at grazing incidence — the matching window spans a range of depths on slanted surfaces",
        (Target::Bias, "incidence") => "bias on slanted surfaces — the matching window averages over a depth slope (foreshortening)",
        (_, "edge_distance") => "errors near depth discontinuities — mixed pixels and edge fattening of the stereo matching window, projector shadows at occluding edges",
        (Target::Dropout, "intensity") => "returns missing on dark surfaces — low IR albedo returns too little pattern",
        (Target::Noise, "intensity") => "noise depends on surface brightness — low-albedo (dark) surfaces give weaker pattern contrast",
        (Target::Bias, "intensity") => "bias depends on surface brightness — albedo-dependent matching/subsurface effects, or the IR-colour registration at texture edges",
        (_, "object") => "object-specific — the material (dark, specular, translucent) of some objects, or an error in their GT pose/model",
        (_, "frame") => "drift over the sequence — sensor warm-up/temperature, or a GT camera-pose drift",
        _ => "an unmodelled sensor effect",
    };
    format!("{shape}: {why}.")
}

fn fmt_num(x: f64) -> String {
    if x != 0.0 && (x.abs() >= 1e4 || x.abs() < 1e-3) {
        format!("{x:.3e}")
    } else {
        format!("{x:.3}").trim_end_matches('0').trim_end_matches('.').to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn causes_name_the_physics() {
        let s = describe(Target::Dropout, "incidence", &Form::Step { threshold: 70.0, delta: 0.8 }, None, (0.0, 89.0), "m", true);
        assert!(s.contains("incidence > 70") && s.contains("+80.0 percentage points") && s.contains("grazing"), "{s}");
        let s = describe(Target::Noise, "depth", &Form::Quadratic { linear: 0.0, quadratic: 0.002 }, None, (0.5, 1.5), "m", true);
        assert!(s.contains("range²") && s.contains("+4.00 mm"), "{s}");
        let s = describe(Target::Bias, "mass", &Form::Linear { slope: -0.1 }, None, (0.0, 2.0), "kg", false);
        assert!(s.contains("falls linearly") && s.contains("-0.2000 kg") && !s.contains("sensor"), "{s}");
    }
}
