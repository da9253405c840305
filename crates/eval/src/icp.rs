//! Point-to-point ICP (Besl & McKay) with the closed-form Umeyama step, rigid or with a
//! uniform scale.

use nalgebra::{Matrix3, Vector3};
use recon_core::math::Similarity;
use recon_core::spatial::{KdTree, P3};

#[derive(Debug, Clone, Copy)]
pub struct IcpOptions {
    pub max_iters: usize,
    /// Stop when the mean correspondence distance improves by less than this fraction.
    pub rel_tol: f64,
    /// Estimate a uniform scale as well (similarity ICP).
    pub with_scale: bool,
    /// Start by moving the source centroid onto the target centroid.
    pub init_centroids: bool,
}

impl Default for IcpOptions {
    fn default() -> Self {
        IcpOptions { max_iters: 60, rel_tol: 1e-6, with_scale: false, init_centroids: true }
    }
}

#[derive(Debug, Clone)]
/// Outcome of an ICP alignment.
pub struct IcpResult {
    /// Maps source points onto the target.
    pub transform: Similarity,
    /// Mean source→target nearest distance after the final transform.
    pub mean_dist: f64,
    /// Iterations run.
    pub iters: usize,
    /// Whether the mean distance stopped changing (relative tolerance) before the iteration limit.
    pub converged: bool,
}

/// Least-squares similarity (or rigid) transform mapping `src[i]` onto `dst[i]` (Umeyama 1991).
pub fn umeyama(src: &[P3], dst: &[P3], with_scale: bool) -> Similarity {
    let n = src.len().min(dst.len());
    if n == 0 {
        return Similarity::identity();
    }
    let v = |p: &P3| Vector3::new(p[0], p[1], p[2]);
    let ms = src[..n].iter().fold(Vector3::zeros(), |a, p| a + v(p)) / n as f64;
    let md = dst[..n].iter().fold(Vector3::zeros(), |a, p| a + v(p)) / n as f64;
    let mut cov = Matrix3::zeros();
    let mut var_s = 0.0;
    for i in 0..n {
        let (a, b) = (v(&src[i]) - ms, v(&dst[i]) - md);
        cov += b * a.transpose();
        var_s += a.norm_squared();
    }
    cov /= n as f64;
    var_s /= n as f64;
    let svd = cov.svd(true, true);
    let (u, vt) = match (svd.u, svd.v_t) {
        (Some(u), Some(vt)) => (u, vt),
        _ => return Similarity::identity(),
    };
    // Reflection guard: force det(R) = +1.
    let mut d = Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * vt;
    let s = if with_scale && var_s > 0.0 { (svd.singular_values.component_mul(&d.diagonal())).sum() / var_s } else { 1.0 };
    let t = md - s * r * ms;
    let mut rr = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            rr[i][j] = r[(i, j)];
        }
    }
    Similarity { rotation: rr, translation: [t[0], t[1], t[2]], scale: s }
}

/// Aligns `source` onto `target` by point-to-point ICP. Returns the transform to apply to
/// the source. Correspondences: nearest target point of each source point (k-d tree).
pub fn icp(source: &[P3], target: &[P3], opts: &IcpOptions) -> IcpResult {
    let tree = KdTree::new(target);
    let mut tf = Similarity::identity();
    if source.is_empty() || target.is_empty() {
        return IcpResult { transform: tf, mean_dist: f64::INFINITY, iters: 0, converged: false };
    }
    if opts.init_centroids {
        let c = |s: &[P3]| {
            let n = s.len() as f64;
            let m = s.iter().fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]]);
            [m[0] / n, m[1] / n, m[2] / n]
        };
        let (cs, ct) = (c(source), c(target));
        tf.translation = [ct[0] - cs[0], ct[1] - cs[1], ct[2] - cs[2]];
    }
    let mut cur = tf.apply_all(source);
    let mut prev = f64::INFINITY;
    let mut converged = false;
    let mut iters = 0;
    for it in 0..opts.max_iters {
        iters = it + 1;
        let nn = tree.nearest_all(&cur);
        let mean = nn.iter().map(|x| x.1).sum::<f64>() / nn.len() as f64;
        if mean <= 1e-15 || (prev.is_finite() && (prev - mean).abs() <= opts.rel_tol * prev) {
            converged = true;
            break;
        }
        prev = mean;
        let dst: Vec<P3> = nn.iter().map(|&(i, _)| target[i]).collect();
        let step = umeyama(&cur, &dst, opts.with_scale);
        tf = step.compose(&tf);
        cur = tf.apply_all(source);
    }
    let mean_dist = tree.nearest_dists(&cur).iter().sum::<f64>() / cur.len() as f64;
    IcpResult { transform: tf, mean_dist, iters, converged }
}

#[cfg(test)]
mod tests {
    use super::*;
    use recon_core::math::axis_angle;
    use recon_core::rng::SeededRng;

    #[test]
    fn umeyama_recovers_similarity() {
        let mut rng = SeededRng::new(11);
        let src: Vec<P3> = (0..50).map(|_| [rng.normal(), rng.normal(), rng.normal()]).collect();
        let tf = Similarity { rotation: axis_angle([1.0, 2.0, -0.5], 1.1), translation: [0.3, -2.0, 5.0], scale: 1.7 };
        let dst = tf.apply_all(&src);
        let est = umeyama(&src, &dst, true);
        assert!((est.scale - 1.7).abs() < 1e-10);
        for i in 0..3 {
            assert!((est.translation[i] - tf.translation[i]).abs() < 1e-9);
            for j in 0..3 {
                assert!((est.rotation[i][j] - tf.rotation[i][j]).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn icp_aligns_moved_cloud() {
        let mut rng = SeededRng::new(5);
        // Anisotropic blob so the alignment is unique.
        let src: Vec<P3> = (0..4000).map(|_| [rng.normal() * 0.1, rng.normal() * 0.05, rng.normal() * 0.02]).collect();
        let tf = Similarity::rigid(axis_angle([0.2, 1.0, 0.3], 0.25), [0.02, -0.01, 0.03]);
        let dst = tf.apply_all(&src);
        let res = icp(&src, &dst, &IcpOptions::default());
        assert!(res.converged);
        assert!(res.mean_dist < 1e-8, "{res:?}");
    }
}
