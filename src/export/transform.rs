//! Similarity transforms `p ↦ s·R·p + t` for placing decoded objects (unit
//! cube, z up) in the camera/world frame, applied to meshes and Gaussians.

use super::splat::Gaussians;
use crate::decoders::Mesh;
use crate::{Error, Result};

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    /// Proper rotation acting on column vectors.
    pub rotation: [[f32; 3]; 3],
    pub translation: [f32; 3],
    pub scale: f32,
}

impl Default for Similarity {
    fn default() -> Self {
        Self::identity()
    }
}

impl Similarity {
    pub fn identity() -> Self {
        Similarity { rotation: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], translation: [0.0; 3], scale: 1.0 }
    }

    /// Checks that `rotation` is orthonormal with det +1 (tolerance 1e-3)
    /// and `scale` is positive and finite.
    pub fn new(rotation: [[f32; 3]; 3], translation: [f32; 3], scale: f32) -> Result<Self> {
        if !(scale.is_finite() && scale > 0.0) || translation.iter().any(|t| !t.is_finite()) {
            return Err(Error::msg(format!("similarity: bad scale {scale} or translation {translation:?}")));
        }
        for i in 0..3 {
            for j in 0..3 {
                let d: f32 = (0..3).map(|k| rotation[k][i] * rotation[k][j]).sum();
                let want = if i == j { 1.0 } else { 0.0 };
                let orthonormal = (d - want).abs() < 1e-3; // false on NaN
                if !orthonormal {
                    return Err(Error::msg(format!("similarity: rotation is not orthonormal: {rotation:?}")));
                }
            }
        }
        if det(&rotation) < 0.0 {
            return Err(Error::msg("similarity: rotation has det -1 (a reflection)"));
        }
        Ok(Similarity { rotation, translation, scale })
    }

    pub fn from_quaternion(q: [f32; 4], translation: [f32; 3], scale: f32) -> Result<Self> {
        Self::new(quat_to_matrix(q), translation, scale)
    }

    /// `self ∘ other` (apply `other` first).
    pub fn compose(&self, other: &Similarity) -> Similarity {
        let r = matmul(&self.rotation, &other.rotation);
        let t = self.apply_point(other.translation);
        Similarity { rotation: r, translation: t, scale: self.scale * other.scale }
    }

    pub fn apply_point(&self, p: [f32; 3]) -> [f32; 3] {
        let r = &self.rotation;
        [0, 1, 2].map(|i| self.scale * (r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2]) + self.translation[i])
    }

    /// Unit quaternion (w, x, y, z) of the rotation.
    pub fn quaternion(&self) -> [f32; 4] {
        matrix_to_quat(&self.rotation)
    }

    pub fn apply_mesh(&self, mesh: &Mesh) -> Mesh {
        Mesh {
            vertices: mesh.vertices.iter().map(|&v| self.apply_point(v)).collect(),
            faces: mesh.faces.clone(),
            vertex_attrs: mesh.vertex_attrs.clone(),
        }
    }

    /// Positions mapped, scales ×s, rotations pre-multiplied by R
    /// (covariance R·Σ·Rᵀ·s²); opacity and colour unchanged (SH degree 0
    /// is view independent).
    pub fn apply_gaussians(&self, g: &Gaussians) -> Gaussians {
        let q = self.quaternion();
        Gaussians {
            positions: g.positions.iter().map(|&p| self.apply_point(p)).collect(),
            scales: g.scales.iter().map(|s| s.map(|x| x * self.scale)).collect(),
            rotations: g.rotations.iter().map(|&r| normalize_quat(quat_mul(q, r))).collect(),
            opacities: g.opacities.clone(),
            dc: g.dc.clone(),
        }
    }
}

/// A mesh stretched along the axes of its own frame, `x ↦ diag(k)·x`.
pub fn stretch_mesh(mesh: &Mesh, k: [f64; 3]) -> Mesh {
    let k = k.map(|x| x as f32);
    Mesh { vertices: mesh.vertices.iter().map(|v| [v[0] * k[0], v[1] * k[1], v[2] * k[2]]).collect(), faces: mesh.faces.clone(), vertex_attrs: mesh.vertex_attrs.clone() }
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

fn det(m: &[[f32; 3]; 3]) -> f32 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

pub fn matmul(a: &[[f32; 3]; 3], b: &[[f32; 3]; 3]) -> [[f32; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

/// Hamilton product of (w, x, y, z) quaternions.
pub fn quat_mul(a: [f32; 4], b: [f32; 4]) -> [f32; 4] {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

pub fn normalize_quat(q: [f32; 4]) -> [f32; 4] {
    let n = q.iter().map(|x| x * x).sum::<f32>().sqrt();
    if n > 0.0 {
        q.map(|x| x / n)
    } else {
        [1.0, 0.0, 0.0, 0.0]
    }
}

/// Rotation matrix of a (not necessarily unit) quaternion (w, x, y, z).
pub fn quat_to_matrix(q: [f32; 4]) -> [[f32; 3]; 3] {
    let [w, x, y, z] = normalize_quat(q);
    [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ]
}

/// Quaternion (w ≥ 0) of a rotation matrix (Shepperd's method, stable near 180°).
pub fn matrix_to_quat(m: &[[f32; 3]; 3]) -> [f32; 4] {
    let m = m.map(|r| r.map(|x| x as f64));
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [0.25 * s, (m[2][1] - m[1][2]) / s, (m[0][2] - m[2][0]) / s, (m[1][0] - m[0][1]) / s]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [(m[2][1] - m[1][2]) / s, 0.25 * s, (m[0][1] + m[1][0]) / s, (m[0][2] + m[2][0]) / s]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [(m[0][2] - m[2][0]) / s, (m[0][1] + m[1][0]) / s, 0.25 * s, (m[1][2] + m[2][1]) / s]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [(m[1][0] - m[0][1]) / s, (m[0][2] + m[2][0]) / s, (m[1][2] + m[2][1]) / s, 0.25 * s]
    };
    let q = if q[0] < 0.0 { q.map(|x| -x) } else { q };
    normalize_quat(q.map(|x| x as f32))
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let g = Gaussians { positions: vec![[0.1, -0.2, 0.3]], scales: vec![[0.03, 0.01, 0.02]], rotations: vec![q], opacities: vec![0.5], dc: vec![[0.0; 3]] };
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
    fn quaternion_matrix_round_trip_including_half_turns() {
        let qs = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
            [0.3, -0.5, 0.7, 0.2],
            [0.01, 0.6, -0.6, 0.5],
        ];
        for q in qs {
            let q = normalize_quat(q);
            let back = matrix_to_quat(&quat_to_matrix(q));
            let same = (0..4).all(|k| (back[k] - q[k]).abs() < 1e-5) || (0..4).all(|k| (back[k] + q[k]).abs() < 1e-5);
            assert!(same, "{q:?} -> {back:?}");
        }
        // Hamilton product matches matrix product.
        let (a, b) = (normalize_quat([0.3, -0.5, 0.7, 0.2]), normalize_quat([0.9, 0.1, -0.2, 0.4]));
        assert!(close(&quat_to_matrix(quat_mul(a, b)), &matmul(&quat_to_matrix(a), &quat_to_matrix(b)), 1e-5));
    }

    #[test]
    fn gaussians_transform_like_their_covariance() {
        let t = Similarity::from_quaternion([0.2, 0.4, -0.1, 0.8], [0.5, -1.0, 2.0], 1.7).unwrap();
        let g = Gaussians {
            positions: vec![[0.1, 0.2, -0.3]],
            scales: vec![[0.01, 0.02, 0.05]],
            rotations: vec![normalize_quat([0.7, 0.1, 0.5, -0.3])],
            opacities: vec![0.4],
            dc: vec![[0.1, 0.2, 0.3]],
        };
        let h = t.apply_gaussians(&g);
        assert_eq!(h.positions[0], t.apply_point(g.positions[0]));
        let r = t.rotation;
        let sigma = covariance(g.rotations[0], g.scales[0]);
        let rs = matmul(&r, &sigma);
        let want: [[f32; 3]; 3] =
            std::array::from_fn(|i| std::array::from_fn(|j| t.scale * t.scale * (0..3).map(|k| rs[i][k] * r[j][k]).sum::<f32>()));
        let got = covariance(h.rotations[0], h.scales[0]);
        assert!(close(&got, &want, 1e-7), "{got:?} vs {want:?}");
        assert_eq!(h.opacities, g.opacities);
    }

    #[test]
    fn mesh_transform_rotates_normals_and_composes() {
        let t = Similarity::from_quaternion([0.5, 0.5, 0.5, 0.5], [1.0, 2.0, 3.0], 2.0).unwrap();
        let mesh = crate::export::tests::tetrahedron();
        let m2 = t.apply_mesh(&mesh);
        for (n0, n1) in mesh.face_normals().iter().zip(m2.face_normals()) {
            let rn = [0, 1, 2].map(|i| (0..3).map(|k| t.rotation[i][k] * n0[k]).sum::<f32>());
            assert!((0..3).all(|k| (rn[k] - n1[k]).abs() < 1e-5));
        }
        let u = Similarity::from_quaternion([0.9, -0.2, 0.1, 0.3], [0.0, -1.0, 0.5], 0.5).unwrap();
        let p = [0.3, -0.2, 0.9];
        let a = t.compose(&u).apply_point(p);
        let b = t.apply_point(u.apply_point(p));
        assert!((0..3).all(|k| (a[k] - b[k]).abs() < 1e-5));
    }

    #[test]
    fn rejects_non_rotations() {
        let refl = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
        assert!(Similarity::new(refl, [0.0; 3], 1.0).is_err());
        let shear = [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(Similarity::new(shear, [0.0; 3], 1.0).is_err());
        assert!(Similarity::new(Similarity::identity().rotation, [0.0; 3], 0.0).is_err());
        assert!(Similarity::new(Similarity::identity().rotation, [f32::NAN, 0.0, 0.0], 1.0).is_err());
    }
}
