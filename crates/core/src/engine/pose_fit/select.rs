//! Pose selection among several predictions (RecGen appendix B).
//!
//! **Selection** ([`SelectMethod`]): each view's predicted pose is a
//! candidate (and each sample's, with several seeds).
//! - `single`: every candidate is scored in its own view only;
//! - `cross`: every candidate is scored in every view, the other views'
//!   points brought into its frame with the relative camera pose, and the
//!   per-view scores are averaged (views count equally whatever their point
//!   counts); with one view this equals `single`;
//! - `first`: only the first (anchor) view's poses are candidates, scored in
//!   that view (with one sample there is nothing to choose).
//!
//! The lowest score wins; ties go to the earliest candidate (sample order,
//! then view order), so the choice is deterministic.

use crate::engine::pose_fit::score::CandidateScore;
use crate::math::Similarity;
use crate::spatial::{dist2, P3};
use serde::Serialize;

/// Which candidates compete and how they are scored (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum SelectMethod {
    /// Only the first (anchor) view's candidates compete, each scored in that view.
    First,
    /// Every candidate competes, scored in its own view only.
    Single,
    /// Every candidate competes, scored by its mean score over all views.
    #[default]
    Cross,
}

impl SelectMethod {
    /// The method's name on the command line and in JSON (`cross`).
    pub fn name(self) -> &'static str {
        match self {
            SelectMethod::First => "first",
            SelectMethod::Single => "single",
            SelectMethod::Cross => "cross",
        }
    }

    /// The selection key of a candidate predicted for view `own_view`
    /// (`None`: not a candidate under this method).
    pub fn key(self, s: &CandidateScore) -> Option<f64> {
        match self {
            SelectMethod::First => (s.own_view == 0).then(|| s.single()),
            SelectMethod::Single => Some(s.single()),
            SelectMethod::Cross => Some(s.cross()),
        }
    }
}

/// Index of the winning candidate: lowest key, ties to the first; NaN keys
/// and non-candidates never win. `None` when nothing is eligible.
pub fn select_best(method: SelectMethod, scores: &[CandidateScore]) -> Option<usize> {
    let mut best: Option<(usize, f64)> = None;
    for (i, s) in scores.iter().enumerate() {
        let Some(k) = method.key(s).filter(|k| !k.is_nan()) else { continue };
        if best.is_none_or(|(_, b)| k < b) {
            best = Some((i, k));
        }
    }
    best.map(|b| b.0)
}

/// Spread of several pose estimates of one object (the `--samples` uncertainty).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PoseSpread {
    /// Poses the spread is taken over.
    pub samples: usize,
    /// `sqrt(Σ|t_i − t̄|² / (n−1))`, millimetres.
    pub translation_sd_mm: f64,
    /// `sqrt(Σ θ_i² / (n−1))` with `θ_i` the geodesic angle from the chordal
    /// mean rotation, degrees.
    pub rotation_sd_deg: f64,
    /// Sample standard deviation of the scale over its mean.
    pub scale_sd_rel: f64,
}

/// Spread of `poses` (metres); `None` for fewer than two.
pub fn pose_spread(poses: &[Similarity]) -> Option<PoseSpread> {
    let n = poses.len();
    if n < 2 {
        return None;
    }
    let nf = n as f64;
    let tm: P3 = std::array::from_fn(|a| poses.iter().map(|p| p.translation[a]).sum::<f64>() / nf);
    let t_ss: f64 = poses.iter().map(|p| dist2(&p.translation, &tm)).sum();
    let rm = mean_rotation(poses.iter().map(|p| p.rotation));
    let ang_ss: f64 = poses.iter().map(|p| geodesic_angle(&rm, &p.rotation).powi(2)).sum();
    let sm = poses.iter().map(|p| p.scale).sum::<f64>() / nf;
    let s_ss: f64 = poses.iter().map(|p| (p.scale - sm).powi(2)).sum();
    Some(PoseSpread {
        samples: n,
        translation_sd_mm: (t_ss / (nf - 1.0)).sqrt() * 1e3,
        rotation_sd_deg: (ang_ss / (nf - 1.0)).sqrt().to_degrees(),
        scale_sd_rel: (s_ss / (nf - 1.0)).sqrt() / sm,
    })
}

/// Chordal L2 mean: the rotation nearest (Frobenius) to the sum of the matrices.
pub fn mean_rotation(rs: impl Iterator<Item = [[f64; 3]; 3]>) -> [[f64; 3]; 3] {
    let mut m = nalgebra::Matrix3::<f64>::zeros();
    for r in rs {
        m += nalgebra::Matrix3::from_fn(|i, j| r[i][j]);
    }
    let svd = m.svd(true, true);
    let (Some(mut u), Some(vt)) = (svd.u, svd.v_t) else { return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]] };
    if (u * vt).determinant() < 0.0 {
        // The smallest singular value is last (nalgebra sorts them descending).
        u.column_mut(2).neg_mut();
    }
    let r = u * vt;
    std::array::from_fn(|i| std::array::from_fn(|j| r[(i, j)]))
}

/// Angle (radians) of `aᵀ·b`.
pub fn geodesic_angle(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> f64 {
    let tr: f64 = (0..3).map(|i| (0..3).map(|k| a[k][i] * b[k][i]).sum::<f64>()).sum();
    ((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}
