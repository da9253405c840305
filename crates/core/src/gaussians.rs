//! 3D Gaussians (activated values) in one frame: what the SLat Gaussian
//! decoder returns, what transforms place and what the splat writer saves.

use crate::math::{matrix_to_quat, normalize_quat, quat_mul, quat_to_matrix, Similarity32};
use crate::{Error, Result};

/// Zeroth-order SH basis constant: RGB = C0·dc + 0.5.
pub const SH_C0: f32 = 0.282_094_79;

/// Activated Gaussians in one frame. The SLat Gaussian decoder returns this
/// type directly (`decoders::gaussian::GaussianModel::to_gaussians`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Gaussians {
    /// Centres.
    pub positions: Vec<[f32; 3]>,
    /// Standard deviations along the local axes (linear, > 0).
    pub scales: Vec<[f32; 3]>,
    /// Unit quaternions (w, x, y, z).
    pub rotations: Vec<[f32; 4]>,
    /// In (0, 1).
    pub opacities: Vec<f32>,
    /// SH degree-0 coefficients; RGB = 0.28209479·dc + 0.5.
    pub dc: Vec<[f32; 3]>,
}

impl Gaussians {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.positions.len()
    }

    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.positions.is_empty()
    }

    /// Checks that every field has one entry per Gaussian.
    pub fn validate(&self) -> Result<()> {
        let n = self.positions.len();
        if [self.scales.len(), self.rotations.len(), self.opacities.len(), self.dc.len()].iter().any(|&l| l != n) {
            return Err(Error::msg("gaussians: field lengths differ"));
        }
        Ok(())
    }

    /// Base colour of splat `i`: `C0·dc + 0.5`, clamped at 0 like the rasteriser.
    pub fn rgb(&self, i: usize) -> [f32; 3] {
        let d = self.dc[i];
        [0, 1, 2].map(|c| (SH_C0 * d[c] + 0.5).max(0.0))
    }

    /// Concatenate (e.g. several objects placed in one scene).
    pub fn extend(&mut self, other: &Gaussians) {
        self.positions.extend_from_slice(&other.positions);
        self.scales.extend_from_slice(&other.scales);
        self.rotations.extend_from_slice(&other.rotations);
        self.opacities.extend_from_slice(&other.opacities);
        self.dc.extend_from_slice(&other.dc);
    }
}

impl Similarity32 {
    /// Positions mapped, scales ×s, rotations pre-multiplied by R
    /// (covariance R·Σ·Rᵀ·s²); opacity and colour unchanged (SH degree 0
    /// is view independent).
    pub fn apply_gaussians(&self, g: &Gaussians) -> Gaussians {
        let q = self.quaternion();
        Gaussians {
            positions: g.positions.iter().map(|&p| self.apply(&p)).collect(),
            scales: g.scales.iter().map(|s| s.map(|x| x * self.scale)).collect(),
            rotations: g.rotations.iter().map(|&r| normalize_quat(quat_mul(q, r))).collect(),
            opacities: g.opacities.clone(),
            dc: g.dc.clone(),
        }
    }
}

/// Gaussians stretched by `S = diag(k)` in their own frame: centres `S·x`,
/// covariances `S·Σ·S` (re-factored into scales and a rotation).
pub fn stretch_gaussians(g: &Gaussians, k: [f64; 3]) -> Gaussians {
    let kf = k.map(|x| x as f32);
    let s = nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(k[0], k[1], k[2]));
    let (scales, rotations) = g
        .scales
        .iter()
        .zip(&g.rotations)
        .map(|(sc, q)| {
            let r = quat_to_matrix(*q);
            let r = nalgebra::Matrix3::from_fn(|i, j| r[i][j] as f64);
            let d = nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(sc[0] as f64, sc[1] as f64, sc[2] as f64).map(|x| x * x));
            let cov = s * r * d * r.transpose() * s;
            let e = nalgebra::SymmetricEigen::new(cov);
            let mut v = e.eigenvectors;
            if v.determinant() < 0.0 {
                v.set_column(2, &(-v.column(2)));
            }
            let m: [[f32; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| v[(i, j)] as f32));
            (std::array::from_fn(|i| e.eigenvalues[i].max(0.0).sqrt() as f32), matrix_to_quat(&m))
        })
        .unzip();
    Gaussians {
        positions: g.positions.iter().map(|p| [p[0] * kf[0], p[1] * kf[1], p[2] * kf[2]]).collect(),
        scales,
        rotations,
        opacities: g.opacities.clone(),
        dc: g.dc.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::matmul;
    use crate::mesh::{stretch_mesh, Mesh};

    fn covariance(q: [f32; 4], s: [f32; 3]) -> [[f32; 3]; 3] {
        let r = quat_to_matrix(q);
        std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| r[i][k] * s[k] * s[k] * r[j][k]).sum()))
    }

    fn close(a: &[[f32; 3]; 3], b: &[[f32; 3]; 3], tol: f32) -> bool {
        (0..3).all(|i| (0..3).all(|j| (a[i][j] - b[i][j]).abs() <= tol))
    }

    /// The stretched covariance, rebuilt from the new scales and rotation, is `S·Σ·S`.
    #[test]
    fn stretched_gaussians_have_the_stretched_covariance() {
        let q = normalize_quat([0.9, 0.2, -0.3, 0.25]);
        let g = Gaussians {
            positions: vec![[0.1, -0.2, 0.3]],
            scales: vec![[0.03, 0.01, 0.02]],
            rotations: vec![q],
            opacities: vec![0.5],
            dc: vec![[0.0; 3]],
        };
        let k = [1.6, 0.7, 1.1];
        let cov = |s: [f32; 3], q: [f32; 4]| -> [[f64; 3]; 3] {
            let r = quat_to_matrix(q);
            std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|a| r[i][a] as f64 * r[j][a] as f64 * (s[a] as f64).powi(2)).sum()))
        };
        let c0 = cov(g.scales[0], q);
        let out = stretch_gaussians(&g, k);
        let c1 = cov(out.scales[0], out.rotations[0]);
        for i in 0..3 {
            for j in 0..3 {
                assert!((c1[i][j] - k[i] * k[j] * c0[i][j]).abs() < 1e-8, "cov[{i}][{j}] {} vs {}", c1[i][j], k[i] * k[j] * c0[i][j]);
            }
            assert!((out.positions[0][i] - g.positions[0][i] * k[i] as f32).abs() < 1e-7);
        }
        let m = stretch_mesh(&Mesh { vertices: vec![[1.0, 2.0, 3.0]], faces: vec![], vertex_attrs: Default::default() }, k);
        assert!(m.vertices[0].iter().zip([1.6, 1.4, 3.3]).all(|(a, b)| (a - b).abs() < 1e-6), "{:?}", m.vertices[0]);
    }

    #[test]
    fn gaussians_transform_like_their_covariance() {
        let t = Similarity32::from_quaternion([0.2, 0.4, -0.1, 0.8], [0.5, -1.0, 2.0], 1.7).unwrap();
        let g = Gaussians {
            positions: vec![[0.1, 0.2, -0.3]],
            scales: vec![[0.01, 0.02, 0.05]],
            rotations: vec![normalize_quat([0.7, 0.1, 0.5, -0.3])],
            opacities: vec![0.4],
            dc: vec![[0.1, 0.2, 0.3]],
        };
        let h = t.apply_gaussians(&g);
        assert_eq!(h.positions[0], t.apply(&g.positions[0]));
        let r = t.rotation;
        let sigma = covariance(g.rotations[0], g.scales[0]);
        let rs = matmul(&r, &sigma);
        let want: [[f32; 3]; 3] =
            std::array::from_fn(|i| std::array::from_fn(|j| t.scale * t.scale * (0..3).map(|k| rs[i][k] * r[j][k]).sum::<f32>()));
        let got = covariance(h.rotations[0], h.scales[0]);
        assert!(close(&got, &want, 1e-7), "{got:?} vs {want:?}");
        assert_eq!(h.opacities, g.opacities);
    }
}
