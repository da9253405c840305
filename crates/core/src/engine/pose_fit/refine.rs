//! Depth consistency of a posed mesh: the free-space term of the pose score,
//! and a refinement of a predicted pose's scale and translation against the
//! observed depth.
//!
//! **Why.** The RecGen score ([`crate::engine::pose_fit::score`]) is one-sided: it measures
//! how far the *observed* points are from the mesh. A mesh larger than the
//! object can still pass through every observed point, so the score does not
//! penalise oversized predictions, and best-of-N selection with it drifts
//! towards them. The depth image says more than the object's points: every
//! pixel with a valid reading is a ray that is empty up to that depth. A
//! posed mesh whose surface lies in front of the observed depth (by more than
//! the sensor noise) contradicts the measurement, whatever object the pixel
//! belongs to: an oversized mesh spills past its mask onto the background
//! behind it and is caught there, while growing behind an occluder (where
//! the object may really continue) costs nothing.
//!
//! **Free-space term** ([`free_space`]): surface samples of the posed mesh
//! are projected into the view; where the pixel has a valid depth `d`, the
//! violation is `clamp(d − margin − z, 0, cap)`. The depth used is the
//! minimum over the pixel's 3×3 neighbourhood, so that a true surface point
//! on the silhouette, which may round onto a background pixel, is not
//! counted. The term is the trimmed mean of the violations over the samples
//! that land on valid pixels (samples off the image or on holes say nothing).
//! The view score becomes `fit + weight · free_space` (metres).
//!
//! **Refinement** ([`refine_pose`]): the predicted rotation is kept and a
//! uniform scale about the predicted centre plus a translation are fitted,
//! `x ↦ e^δ (x − c) + c + s·Δ`, by Nelder–Mead on the cross-view score with
//! the free-space term (subsampled points). The pose token's scale and
//! position are the least certain parts of a prediction; the depth pins the
//! visible surface, and the free-space term stops the fit from sliding the
//! mesh along the viewing rays while growing it. Behind an occluder neither
//! term sees the object, so a small prior `refine_prior · s · δ²` keeps the
//! model's scale where the depth is silent. With `refine_stretch` the scale
//! is fitted per axis of the object frame (the mesh's proportions), which
//! the depth constrains across the rays but not along them.

use crate::engine::pose_fit::free_space::ViewPoints;
use crate::engine::pose_fit::options::AlignOptions;
use crate::engine::pose_fit::score::Surface;
use crate::math::Similarity;

/// Nelder–Mead minimisation of `f` from `x0` with initial steps `step`
/// (deterministic; at most `max_evals` evaluations). Returns the best point and value.
pub fn nelder_mead<const N: usize>(
    f: &dyn Fn(&[f64; N]) -> f64,
    x0: [f64; N],
    step: [f64; N],
    max_evals: usize,
    tol: f64,
) -> ([f64; N], f64) {
    let mut simplex: Vec<([f64; N], f64)> = Vec::with_capacity(N + 1);
    simplex.push((x0, f(&x0)));
    for i in 0..N {
        let mut x = x0;
        x[i] += step[i];
        simplex.push((x, f(&x)));
    }
    let mut evals = N + 1;
    let lerp = |a: &[f64; N], b: &[f64; N], t: f64| -> [f64; N] { std::array::from_fn(|i| a[i] + t * (b[i] - a[i])) };
    while evals < max_evals {
        simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
        if (simplex[N].1 - simplex[0].1).abs() <= tol {
            break;
        }
        let centroid: [f64; N] = std::array::from_fn(|i| simplex[..N].iter().map(|p| p.0[i]).sum::<f64>() / N as f64);
        let worst = simplex[N];
        let xr = lerp(&centroid, &worst.0, -1.0);
        let fr = f(&xr);
        evals += 1;
        if fr < simplex[0].1 {
            let xe = lerp(&centroid, &worst.0, -2.0);
            let fe = f(&xe);
            evals += 1;
            simplex[N] = if fe < fr { (xe, fe) } else { (xr, fr) };
        } else if fr < simplex[N - 1].1 {
            simplex[N] = (xr, fr);
        } else {
            let (xc, fc) = if fr < worst.1 {
                let x = lerp(&centroid, &worst.0, -0.5);
                (x, f(&x))
            } else {
                let x = lerp(&centroid, &worst.0, 0.5);
                (x, f(&x))
            };
            evals += 1;
            if fc < worst.1.min(fr) {
                simplex[N] = (xc, fc);
            } else {
                // Shrink towards the best vertex.
                let best = simplex[0].0;
                for p in simplex.iter_mut().skip(1) {
                    p.0 = lerp(&best, &p.0, 0.5);
                    p.1 = f(&p.0);
                }
                evals += N;
            }
        }
    }
    simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
    simplex[0]
}

/// The pose `x ↦ e^δ (x − c) + c + s·Δ` applied after `pose` (c its translation).
pub fn adjust(pose: &Similarity, delta_log_scale: f64, shift: [f64; 3]) -> Similarity {
    let k = delta_log_scale.exp();
    let c = pose.translation;
    let t = std::array::from_fn(|i| c[i] + pose.scale * shift[i]);
    Similarity { rotation: pose.rotation, translation: t, scale: pose.scale * k }
}

/// What a refinement did.
#[derive(Debug, Clone, Copy)]
pub struct Refined {
    /// The refined pose (surface → anchor camera); the start when nothing improved.
    pub pose: Similarity,
    /// Per-axis stretch of the object frame (`[1, 1, 1]` unless
    /// `refine_stretch`): the mesh is `diag(stretch)·x` before `pose`.
    pub stretch: [f64; 3],
    /// Objective before the refinement (subsampled cross score, metres).
    pub before_m: f64,
    /// Objective after it (equal to `before_m` when nothing improved).
    pub after_m: f64,
}

/// Refines the scale and translation of `pose` (surface → anchor) against
/// every view's points and depth (module docs); with `refine_stretch`, the
/// scale is per axis of the object frame. The result is never worse than
/// the start on the objective.
pub fn refine_pose(surface: &Surface, pose: &Similarity, views: &[ViewPoints], opts: &AlignOptions) -> Refined {
    let sub = AlignOptions { max_points: opts.refine_points, ..*opts };
    let samples = surface.samples(opts.refine_points);
    // x = [log scale per axis (one shared unless stretching), shift]: scale
    // changes are bounded to ×/÷ 2 and shifts to one object size.
    let split = |x: &[f64; 6]| -> (f64, [f64; 3]) {
        if opts.refine_stretch {
            let m = (x[0] + x[1] + x[2]) / 3.0;
            (m, [x[0] - m, x[1] - m, x[2] - m])
        } else {
            (x[0], [0.0; 3])
        }
    };
    let objective = |x: &[f64; 6]| -> f64 {
        let n = if opts.refine_stretch { 3 } else { 1 };
        if x[..n].iter().any(|v| v.abs() > std::f64::consts::LN_2) || x[3..].iter().any(|v| v.abs() > 1.0) {
            return f64::INFINITY;
        }
        let (m, a) = split(x);
        let p = adjust(pose, m, [x[3], x[4], x[5]]);
        let per: Vec<f64> =
            views.iter().map(|v| crate::engine::pose_fit::score::view_score_stretched(surface, &samples, &p, a, v, &sub)).collect();
        let prior = opts.refine_prior * pose.scale * x[..n].iter().map(|v| v * v).sum::<f64>();
        per.iter().sum::<f64>() / per.len().max(1) as f64 + prior
    };
    let before = objective(&[0.0; 6]);
    let unchanged = Refined { pose: *pose, stretch: [1.0; 3], before_m: before, after_m: before };
    if !before.is_finite() || views.is_empty() {
        return unchanged;
    }
    let x = if opts.refine_stretch {
        nelder_mead(&objective, [0.0; 6], [0.08, 0.08, 0.08, 0.05, 0.05, 0.05], opts.refine_evals, 1e-6)
    } else {
        // Four free parameters: the shared log scale and the shift.
        let f4 = |y: &[f64; 4]| objective(&[y[0], 0.0, 0.0, y[1], y[2], y[3]]);
        let (y, v) = nelder_mead(&f4, [0.0; 4], [0.08, 0.05, 0.05, 0.05], opts.refine_evals, 1e-6);
        ([y[0], 0.0, 0.0, y[1], y[2], y[3]], v)
    };
    let (x, after) = x;
    if after < before {
        let (m, a) = split(&x);
        Refined { pose: adjust(pose, m, [x[3], x[4], x[5]]), stretch: a.map(f64::exp), before_m: before, after_m: after }
    } else {
        unchanged
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::frame::Intrinsics;
    use crate::engine::pose_fit::free_space::{free_space, DepthView};
    use crate::engine::pose_fit::score::view_score;
    use crate::math::axis_angle;
    use crate::mesh::primitives::cuboid;
    use crate::spatial::P3;

    const K: Intrinsics = Intrinsics { fx: 500.0, fy: 500.0, cx: 160.0, cy: 120.0 };
    const W: usize = 320;
    const H: usize = 240;

    /// Depth image of a wall at `wall` m with the posed box in front of it,
    /// ray-cast exactly (slab test), and the box's visible points.
    fn render(h: [f64; 3], pose: &Similarity, wall: f64) -> (Vec<f32>, Vec<P3>) {
        let inv = pose.inverse();
        let mut depth = vec![wall as f32; W * H];
        let mut pts = Vec::new();
        for v in 0..H {
            for u in 0..W {
                let dir = [(u as f64 - K.cx) / K.fx, (v as f64 - K.cy) / K.fy, 1.0];
                // Ray in the box frame: o + t·d.
                let o = inv.apply(&[0.0; 3]);
                let e = inv.apply(&dir);
                let d: P3 = std::array::from_fn(|i| e[i] - o[i]);
                let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
                for a in 0..3 {
                    let (lo, hi) = ((-h[a] - o[a]) / d[a], (h[a] - o[a]) / d[a]);
                    t0 = t0.max(lo.min(hi));
                    t1 = t1.min(lo.max(hi));
                }
                if t0 <= t1 && t0 > 0.0 && t0 < wall {
                    depth[v * W + u] = t0 as f32;
                    pts.push([dir[0] * t0, dir[1] * t0, t0]);
                }
            }
        }
        (depth, pts)
    }

    fn setup(truth: &Similarity) -> (Surface, ViewPoints) {
        let h = [0.5, 0.3, 0.2];
        let (depth, pts) = render(h, truth, 1.2);
        let view = ViewPoints { points: pts, to_anchor: Similarity::identity(), depth: DepthView::new(&depth, W, H, K) };
        (Surface::new(cuboid(h), 20_000, 4).unwrap(), view)
    }

    fn truth() -> Similarity {
        Similarity { rotation: axis_angle([0.3, 1.0, 0.1], 0.6), translation: [0.02, -0.01, 0.8], scale: 0.15 }
    }

    /// The true pose has (almost) no free-space violation; a 30 % larger box
    /// pushed back so that its front still passes through the observed
    /// points fits about as well one-sidedly, but spills onto the wall.
    #[test]
    fn free_space_catches_an_oversized_mesh_the_fit_term_misses() {
        let t = truth();
        let (surface, view) = setup(&t);
        let samples = surface.samples(4000);
        let opts = AlignOptions::default();
        let fs_true = free_space(&samples, &t, &view, &opts);
        assert!(fs_true < 1e-4, "true pose violates free space by {fs_true} m");
        let big = adjust(&t, 0.3f64.ln_1p(), [0.0, 0.0, 0.3 * 0.2]);
        let fs_big = free_space(&samples, &big, &view, &opts);
        assert!(fs_big > 0.01, "oversized mesh: {fs_big} m");
        // Without the depth the term is silent.
        let bare = ViewPoints { depth: None, ..view.clone() };
        assert_eq!(free_space(&samples, &big, &bare, &opts), 0.0);
        // The combined score prefers the truth by a wide margin.
        let with = AlignOptions { free_space_weight: 1.0, ..opts };
        assert!(view_score(&surface, &big, &view, &with) > view_score(&surface, &t, &view, &with) + 0.005);
    }

    /// From a pose 25 % too large and 1.5 cm off, the refinement recovers the
    /// true scale to 5 % and the centre to 5 mm.
    #[test]
    fn refinement_recovers_scale_and_position() {
        let t = truth();
        let (surface, view) = setup(&t);
        let start = adjust(&t, 0.25f64.ln_1p(), [0.1, -0.05, 0.05]);
        let opts = AlignOptions { free_space_weight: 1.0, ..AlignOptions::default() };
        let r = refine_pose(&surface, &start, std::slice::from_ref(&view), &opts);
        let ds = r.pose.scale / t.scale;
        let dt = ((0..3).map(|i| (r.pose.translation[i] - t.translation[i]).powi(2)).sum::<f64>()).sqrt();
        println!("scale ratio {ds:.3}, centre error {:.1} mm, objective {:.2} → {:.2} mm", dt * 1e3, r.before_m * 1e3, r.after_m * 1e3);
        assert!(r.after_m < r.before_m);
        assert!((ds - 1.0).abs() < 0.05, "scale ratio {ds}");
        assert!(dt < 0.005, "centre error {dt} m");
    }

    /// The scale prior holds the scale where it pays more than the fit gains:
    /// a heavy prior keeps the start's scale (the shift still fits), the
    /// default one lets the depth correct a 25 % error.
    #[test]
    fn scale_prior_weighs_against_the_fit() {
        let t = truth();
        let (surface, view) = setup(&t);
        let start = adjust(&t, 0.25f64.ln_1p(), [0.0; 3]);
        let heavy = AlignOptions { refine_prior: 100.0, ..AlignOptions::depth() };
        let r = refine_pose(&surface, &start, std::slice::from_ref(&view), &heavy);
        assert!((r.pose.scale / start.scale - 1.0).abs() < 0.01, "heavy prior: scale ratio {}", r.pose.scale / start.scale);
        assert!(r.after_m < r.before_m);
        let r = refine_pose(&surface, &start, std::slice::from_ref(&view), &AlignOptions::depth());
        assert!((r.pose.scale / t.scale - 1.0).abs() < 0.05, "default prior: scale ratio {}", r.pose.scale / t.scale);
    }

    /// A predicted box of the wrong proportions (30 % too long along its x,
    /// 20 % too thin along z): the uniform fit cannot correct them, the
    /// per-axis stretch brings the visible proportions back.
    #[test]
    fn stretch_refinement_corrects_proportions() {
        let t = truth();
        let h = [0.5, 0.3, 0.2];
        let (depth, pts) = render(h, &t, 1.2);
        let view = ViewPoints { points: pts, to_anchor: Similarity::identity(), depth: DepthView::new(&depth, W, H, K) };
        let wrong = [0.5 * 1.3, 0.3, 0.2 * 0.8];
        let surface = Surface::new(cuboid(wrong), 20_000, 4).unwrap();
        let uniform = AlignOptions { free_space_weight: 1.0, ..AlignOptions::default() };
        let stretch = AlignOptions { refine_stretch: true, refine_evals: 320, ..uniform };
        let ru = refine_pose(&surface, &t, std::slice::from_ref(&view), &uniform);
        let rs = refine_pose(&surface, &t, std::slice::from_ref(&view), &stretch);
        assert_eq!(ru.stretch, [1.0; 3]);
        // Fitted half-extents (true-pose units) per axis, and their worst relative error.
        let ext = |r: &Refined| -> [f64; 3] { std::array::from_fn(|i| wrong[i] * r.stretch[i] * r.pose.scale / t.scale) };
        let err = |e: [f64; 3]| (0..3).map(|i| (e[i] / h[i] - 1.0).abs()).fold(0.0, f64::max);
        let (eu, es) = (ext(&ru), ext(&rs));
        println!(
            "uniform {eu:.3?} ({:.3}), stretch {es:.3?} ({:.3}); objective {:.2} / {:.2} mm",
            err(eu),
            err(es),
            ru.after_m * 1e3,
            rs.after_m * 1e3
        );
        assert!(rs.after_m < ru.after_m, "the stretch fit ends no better than the uniform one");
        assert!(err(es) < 0.1 && err(es) < 0.5 * err(eu), "proportions: uniform {eu:?}, stretch {es:?}");
    }

    #[test]
    fn nelder_mead_finds_a_quadratic_minimum() {
        let f = |x: &[f64; 2]| (x[0] - 1.0).powi(2) + 3.0 * (x[1] + 0.5).powi(2);
        let (x, v) = nelder_mead(&f, [0.0, 0.0], [0.5, 0.5], 400, 1e-14);
        assert!((x[0] - 1.0).abs() < 1e-4 && (x[1] + 0.5).abs() < 1e-4 && v < 1e-8, "{x:?} {v}");
    }

    #[test]
    fn min_filter_ignores_holes_and_reaches_one_pixel() {
        let mut d = vec![2.0f32; 9];
        d[4] = 0.0; // hole in the centre
        d[0] = 1.0;
        let k = Intrinsics { fx: 1.0, fy: 1.0, cx: 1.0, cy: 1.0 };
        let dv = DepthView::new(&d, 3, 3, k).unwrap();
        assert_eq!(dv.depth_at(&[0.0, 0.0, 1.0]), Some(1.0)); // centre: neighbour (0,0) is nearest
        assert_eq!(dv.depth_at(&[1.0, 1.0, 1.0]), Some(2.0)); // corner (2,2)
        assert_eq!(dv.depth_at(&[5.0, 0.0, 1.0]), None); // off the image
        assert_eq!(dv.depth_at(&[0.0, 0.0, -1.0]), None); // behind
        assert!(DepthView::new(&d, 4, 3, k).is_none());
    }
}
