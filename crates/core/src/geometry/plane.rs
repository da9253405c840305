//! Support plane from an observed point map: RANSAC (MSAC scoring) for a
//! robust first guess, then least-squares refinement (total least squares:
//! the smallest principal axis of the inliers), and the world frame it
//! defines (gravity −z, plane at z = 0).

use crate::math::Similarity32;
use crate::math::{cross, dot, norm, sub};
use crate::rng::SeededRng;
use crate::{Error, Result};
use serde::Serialize;

/// Plane `normal · x + offset = 0` with a unit normal.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Plane {
    /// Unit normal.
    pub normal: [f64; 3],
    /// Offset along the normal (`−normal · x` for any point `x` on the plane).
    pub offset: f64,
}

impl Plane {
    /// Signed distance of `p` from the plane (positive on the normal's side).
    pub fn signed_distance(&self, p: &[f64; 3]) -> f64 {
        dot(self.normal, *p) + self.offset
    }

    /// The same plane with the normal pointing to the side of `viewpoint`.
    pub fn facing(self, viewpoint: &[f64; 3]) -> Plane {
        if self.signed_distance(viewpoint) < 0.0 {
            Plane { normal: self.normal.map(|x| -x), offset: -self.offset }
        } else {
            self
        }
    }
}

#[derive(Debug, Clone)]
/// Settings of [`fit_plane`].
pub struct PlaneFitOptions {
    /// Inlier distance (metres).
    pub threshold_m: f64,
    /// Upper bound on RANSAC hypotheses (fewer when the inlier ratio allows).
    pub max_iterations: usize,
    /// Least-squares refit / inlier reselection rounds.
    pub refine_rounds: usize,
    /// Points used for hypothesis scoring (a seeded subset when there are more).
    pub max_score_points: usize,
    /// A plane explaining fewer of the points than this fails.
    pub min_inlier_fraction: f64,
    /// Seed of the RANSAC hypotheses and the scoring subset.
    pub seed: u64,
}

impl Default for PlaneFitOptions {
    fn default() -> Self {
        Self { threshold_m: 0.01, max_iterations: 1000, refine_rounds: 6, max_score_points: 20_000, min_inlier_fraction: 0.1, seed: 0 }
    }
}

/// Result of [`fit_plane`]; residuals are point-to-plane distances of the
/// final inliers.
#[derive(Debug, Clone, Serialize)]
pub struct PlaneFit {
    /// The fitted plane.
    pub plane: Plane,
    /// Points given.
    pub points: usize,
    /// Final inliers.
    pub inliers: usize,
    /// `inliers / points`.
    pub inlier_fraction: f64,
    /// RANSAC inlier distance used (metres).
    pub threshold_m: f64,
    /// Final inlier band after refinement.
    pub band_m: f64,
    /// Root-mean-square inlier residual (metres).
    pub rms_residual_m: f64,
    /// Median absolute inlier residual (metres).
    pub median_abs_residual_m: f64,
    /// RANSAC hypotheses tried.
    pub ransac_iterations: usize,
}

/// Fit the dominant plane of `points` (non-finite and all-zero points, i.e.
/// invalid depth, are ignored). Deterministic for a given seed.
pub fn fit_plane(points: &[[f64; 3]], opts: &PlaneFitOptions) -> Result<PlaneFit> {
    let pts: Vec<[f64; 3]> = points.iter().copied().filter(|p| p.iter().all(|x| x.is_finite()) && p.iter().any(|&x| x != 0.0)).collect();
    if pts.len() < 3 {
        return Err(Error::input("support plane", format!("need at least 3 valid points, got {}", pts.len())));
    }
    if !(opts.threshold_m.is_finite() && opts.threshold_m > 0.0) {
        return Err(Error::input("support plane", format!("inlier threshold must be positive, got {}", opts.threshold_m)));
    }
    let mut rng = SeededRng::new(opts.seed);
    let score_set: Vec<[f64; 3]> = if pts.len() > opts.max_score_points {
        (0..opts.max_score_points).map(|_| pts[(rng.next_u64() % pts.len() as u64) as usize]).collect()
    } else {
        pts.clone()
    };
    let t2 = opts.threshold_m * opts.threshold_m;
    // MSAC: truncated quadratic loss, better conditioned than inlier counts.
    let cost = |pl: &Plane| -> f64 { score_set.iter().map(|p| pl.signed_distance(p).powi(2).min(t2)).sum() };
    let mut best: Option<(f64, Plane)> = None;
    let mut needed = opts.max_iterations;
    let mut it = 0;
    while it < needed.min(opts.max_iterations) {
        it += 1;
        let s = [0, 1, 2].map(|_| score_set[(rng.next_u64() % score_set.len() as u64) as usize]);
        let Some(pl) = plane_through(&s) else { continue };
        let c = cost(&pl);
        if best.as_ref().is_none_or(|(bc, _)| c < *bc) {
            best = Some((c, pl));
            // Adaptive stop: enough samples for 99.9% confidence of one all-inlier draw.
            let w = score_set.iter().filter(|p| pl.signed_distance(p).abs() <= opts.threshold_m).count() as f64 / score_set.len() as f64;
            let p_good = w.powi(3).clamp(1e-9, 1.0 - 1e-12);
            needed = ((1e-3f64).ln() / (1.0 - p_good).ln()).ceil().max(20.0) as usize;
        }
    }
    let Some((_, mut plane)) = best else {
        return Err(Error::input("support plane", "all sampled point triples are collinear"));
    };
    // Refinement: least squares on the inliers, then the inlier band shrinks
    // to 3× the residual (floor: a tenth of the RANSAC threshold) so points of
    // objects standing on the plane stop pulling it up.
    let mut band = opts.threshold_m;
    let mut inliers: Vec<[f64; 3]> = pts.iter().copied().filter(|p| plane.signed_distance(p).abs() <= band).collect();
    for _ in 0..opts.refine_rounds.max(1) {
        if inliers.len() < 3 {
            break;
        }
        plane = least_squares_plane(&inliers).unwrap_or(plane);
        let rms = (inliers.iter().map(|p| plane.signed_distance(p).powi(2)).sum::<f64>() / inliers.len() as f64).sqrt();
        band = (3.0 * rms).clamp(0.1 * opts.threshold_m, opts.threshold_m);
        inliers = pts.iter().copied().filter(|p| plane.signed_distance(p).abs() <= band).collect();
    }
    let frac = inliers.len() as f64 / pts.len() as f64;
    if inliers.len() < 3 || frac < opts.min_inlier_fraction {
        return Err(Error::input(
            "support plane",
            format!(
                "no dominant plane: best plane explains {:.1}% of {} points within {} m (need {:.0}%)",
                100.0 * frac,
                pts.len(),
                opts.threshold_m,
                100.0 * opts.min_inlier_fraction
            ),
        ));
    }
    let mut abs: Vec<f64> = inliers.iter().map(|p| plane.signed_distance(p).abs()).collect();
    let rms = (abs.iter().map(|d| d * d).sum::<f64>() / abs.len() as f64).sqrt();
    abs.sort_by(f64::total_cmp);
    Ok(PlaneFit {
        plane,
        points: pts.len(),
        inliers: inliers.len(),
        inlier_fraction: frac,
        threshold_m: opts.threshold_m,
        band_m: band,
        rms_residual_m: rms,
        median_abs_residual_m: abs[abs.len() / 2],
        ransac_iterations: it,
    })
}

fn plane_through(p: &[[f64; 3]; 3]) -> Option<Plane> {
    let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
    let len = norm(n);
    let scale = norm(sub(p[1], p[0])).max(norm(sub(p[2], p[0])));
    if !(len > 1e-9 * scale * scale) {
        return None;
    }
    let n = n.map(|x| x / len);
    Some(Plane { normal: n, offset: -dot(n, p[0]) })
}

/// Total-least-squares plane: through the centroid, normal = eigenvector of
/// the smallest eigenvalue of the scatter matrix.
pub fn least_squares_plane(pts: &[[f64; 3]]) -> Option<Plane> {
    if pts.len() < 3 {
        return None;
    }
    let n = pts.len() as f64;
    let c = [0, 1, 2].map(|k| pts.iter().map(|p| p[k]).sum::<f64>() / n);
    let mut m = nalgebra::Matrix3::<f64>::zeros();
    for p in pts {
        let d = nalgebra::Vector3::new(p[0] - c[0], p[1] - c[1], p[2] - c[2]);
        m += d * d.transpose();
    }
    let e = m.symmetric_eigen();
    let (i, _) = e.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let v = e.eigenvectors.column(i);
    let normal = [v[0], v[1], v[2]];
    let len = norm(normal);
    if !(len > 0.0) {
        return None;
    }
    let normal = normal.map(|x| x / len);
    Some(Plane { normal, offset: -dot(normal, c) })
}

/// `T_world←camera` for a support plane given in the camera frame: world z
/// is the plane normal pointing to the camera (gravity −z), the plane is
/// z = 0, the origin is where the optical axis meets the plane (the foot of
/// the camera centre when the axis grazes it), and world x is the camera x
/// axis projected onto the plane.
pub fn world_from_camera(plane_camera: &Plane) -> Result<Similarity32> {
    let pl = plane_camera.facing(&[0.0; 3]);
    let n = pl.normal;
    if pl.signed_distance(&[0.0; 3]) <= 1e-6 {
        return Err(Error::input("support plane", "the camera centre lies on the support plane"));
    }
    // Optical axis t·(0,0,1) meets the plane at t = −offset/n_z when it hits it in front.
    let origin = if n[2] < -0.1 { [0.0, 0.0, -pl.offset / n[2]] } else { n.map(|x| -pl.offset * x) };
    let mut x = [1.0, 0.0, 0.0];
    let mut xp = sub(x, n.map(|v| v * dot(x, n)));
    if norm(xp) < 0.1 {
        x = [0.0, 0.0, 1.0];
        xp = sub(x, n.map(|v| v * dot(x, n)));
    }
    let xw = xp.map(|v| v / norm(xp));
    let yw = cross(n, xw);
    // Rows are the world axes in camera coordinates: p_w = R (p_c − origin).
    let r = [xw, yw, n];
    let t = [0, 1, 2].map(|i| -dot(r[i], origin));
    Similarity32::new(r.map(|row| row.map(|v| v as f32)), t.map(|v| v as f32), 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tilted table seen from a camera at the origin, a box and a
    /// cylinder standing on it, uniform outliers, Gaussian depth noise.
    fn planted(seed: u64, noise: f64) -> (Plane, Vec<[f64; 3]>) {
        let mut rng = SeededRng::new(seed);
        let n = {
            let v = [0.05, -0.8, -0.6];
            let l = norm(v);
            v.map(|x| x / l)
        };
        let plane = Plane { normal: n, offset: 0.9 }; // camera 0.9 m above
        let u = {
            let a = cross(n, [1.0, 0.0, 0.0]);
            a.map(|x| x / norm(a))
        };
        let w = cross(n, u);
        let foot = n.map(|x| -0.9 * x);
        let at = |a: f64, b: f64, h: f64| [0, 1, 2].map(|k| foot[k] + a * u[k] + b * w[k] + h * n[k]);
        let mut pts = Vec::new();
        for _ in 0..6000 {
            let (a, b) = (rng.uniform() * 1.2 - 0.6, rng.uniform() * 1.2 - 0.6);
            pts.push(at(a, b, noise * rng.normal()));
        }
        // Objects: a 10 cm box and a cylinder standing on the plane (points on their sides and tops).
        for _ in 0..1500 {
            let (a, b, h) = (rng.uniform() * 0.1 + 0.1, rng.uniform() * 0.1 - 0.2, rng.uniform() * 0.1 + 0.002);
            pts.push(at(a, b, h));
        }
        for _ in 0..1500 {
            let th = rng.uniform() * std::f64::consts::TAU;
            let h = rng.uniform() * 0.15 + 0.003;
            pts.push(at(-0.2 + 0.04 * th.cos(), 0.1 + 0.04 * th.sin(), h));
        }
        // 20% gross outliers and invalid (zero) depth.
        for _ in 0..2000 {
            pts.push([rng.uniform() * 2.0 - 1.0, rng.uniform() * 2.0 - 1.0, rng.uniform() * 2.0]);
        }
        pts.extend(std::iter::repeat_n([0.0; 3], 500));
        (plane, pts)
    }

    #[test]
    fn recovers_planted_plane_among_objects_and_outliers() {
        let (truth, pts) = planted(7, 0.002);
        let fit = fit_plane(&pts, &PlaneFitOptions::default()).unwrap();
        let pl = fit.plane.facing(&[0.0; 3]);
        let angle = dot(pl.normal, truth.normal).clamp(-1.0, 1.0).acos().to_degrees();
        assert!(angle < 0.3, "normal off by {angle}°");
        assert!((pl.offset - truth.offset).abs() < 1e-3, "offset {} vs {}", pl.offset, truth.offset);
        // Residual is the noise level (σ = 2 mm; the 1 cm threshold truncates little).
        assert!((0.0015..0.0025).contains(&fit.rms_residual_m), "rms {}", fit.rms_residual_m);
        assert_eq!(fit.points, pts.len() - 500);
        // Plane points within 3σ plus the few object points that low.
        assert!(fit.inliers >= 5900 && fit.inliers < 6000 + 200, "inliers {}", fit.inliers);
        // Same seed, same answer.
        let again = fit_plane(&pts, &PlaneFitOptions::default()).unwrap();
        assert_eq!(again.plane, fit.plane);
    }

    #[test]
    fn world_frame_puts_plane_at_z0_with_gravity_down() {
        let (truth, pts) = planted(3, 0.0);
        let fit = fit_plane(&pts, &PlaneFitOptions::default()).unwrap();
        // Noise-free: the band shrinks below the objects' lowest points (2 mm);
        // a stray outlier or two may remain inside the final 1 mm band.
        assert!(fit.median_abs_residual_m < 1e-6 && fit.rms_residual_m < 5e-5 && fit.band_m <= 0.001 + 1e-12, "{fit:?}");
        let tw = world_from_camera(&fit.plane).unwrap();
        // Every exact plane point maps to z = 0; the camera is above (z > 0).
        for p in pts.iter().filter(|p| truth.signed_distance(p).abs() < 1e-9).take(200) {
            let q = tw.apply(&p.map(|x| x as f32));
            assert!(q[2].abs() < 1e-5, "{q:?}");
        }
        let cam = tw.apply(&[0.0; 3]);
        assert!((cam[2] - 0.9).abs() < 1e-4, "camera height {}", cam[2]);
        // A point 10 cm above the plane (towards the camera) has z = 0.1.
        let above = [0, 1, 2].map(|k| (-0.9 * truth.normal[k] + 0.1 * truth.normal[k]) as f32);
        assert!((tw.apply(&above)[2] - 0.1).abs() < 1e-5);
    }

    #[test]
    fn too_few_points_or_no_plane_is_an_error() {
        assert!(fit_plane(&[[0.0; 3]; 10], &PlaneFitOptions::default()).is_err());
        let mut rng = SeededRng::new(1);
        let cloud: Vec<[f64; 3]> = (0..3000).map(|_| [rng.uniform(), rng.uniform(), rng.uniform() + 1.0]).collect();
        let e = fit_plane(&cloud, &PlaneFitOptions { threshold_m: 0.002, min_inlier_fraction: 0.3, ..Default::default() })
            .unwrap_err()
            .to_string();
        assert!(e.contains("no dominant plane"), "{e}");
    }
}
