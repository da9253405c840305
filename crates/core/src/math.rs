//! The crate's one vocabulary of rigid and similarity transforms, rotations and
//! quaternions, on `[T; 3]` arrays (the layout meshes and point clouds use) with
//! nalgebra behind it where linear algebra is needed. Every layer uses these
//! instead of writing its own `cross` or `compose`.

pub use nalgebra::{Matrix3, Matrix4, SymmetricEigen, Vector3};

use crate::{Error, Result};

/// The scalar types transforms are written for (f32 for assets, f64 for
/// measurement and pose fitting). `Sum` keeps the summation order of the
/// original per-type code, so results are bit-identical to it.
pub trait Real: nalgebra::RealField + Copy + std::iter::Sum + std::fmt::Debug {}
impl<T: nalgebra::RealField + Copy + std::iter::Sum + std::fmt::Debug> Real for T {}

/// `x ↦ s·R·x + t`: a rotation acting on column vectors, a translation and a
/// positive uniform scale. `f64` by default; [`Similarity32`] places assets.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity<T = f64> {
    /// Proper rotation acting on column vectors.
    pub rotation: [[T; 3]; 3],
    /// Translation.
    pub translation: [T; 3],
    /// Uniform scale (> 0).
    pub scale: T,
}

/// The f32 similarity that places decoded meshes and Gaussians.
pub type Similarity32 = Similarity<f32>;

impl<T: Real> Default for Similarity<T> {
    fn default() -> Self {
        Self::identity()
    }
}

impl<T: Real> Similarity<T> {
    /// The identity transform.
    pub fn identity() -> Self {
        let (o, z) = (T::one(), T::zero());
        Similarity { rotation: [[o, z, z], [z, o, z], [z, z, o]], translation: [z; 3], scale: o }
    }

    /// A rigid transform (scale 1); the rotation is not checked.
    pub fn rigid(rotation: [[T; 3]; 3], translation: [T; 3]) -> Self {
        Similarity { rotation, translation, scale: T::one() }
    }

    /// Checks that `rotation` is orthonormal with det +1 (tolerance 1e-3)
    /// and `scale` is positive and finite.
    pub fn new(rotation: [[T; 3]; 3], translation: [T; 3], scale: T) -> Result<Self> {
        if !(scale.is_finite() && scale > T::zero()) || translation.iter().any(|t| !t.is_finite()) {
            return Err(Error::msg(format!("similarity: bad scale {scale:?} or translation {translation:?}")));
        }
        let tol: T = nalgebra::convert(1e-3);
        for i in 0..3 {
            for j in 0..3 {
                let d: T = (0..3).map(|k| rotation[k][i] * rotation[k][j]).sum();
                let want = if i == j { T::one() } else { T::zero() };
                let orthonormal = (d - want).abs() < tol; // false on NaN
                if !orthonormal {
                    return Err(Error::msg(format!("similarity: rotation is not orthonormal: {rotation:?}")));
                }
            }
        }
        if det(&rotation) < T::zero() {
            return Err(Error::msg("similarity: rotation has det -1 (a reflection)"));
        }
        Ok(Similarity { rotation, translation, scale })
    }

    #[inline]
    /// `s·R·p + t`.
    pub fn apply(&self, p: &[T; 3]) -> [T; 3] {
        let r = &self.rotation;
        [0, 1, 2].map(|i| self.scale * (r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2]) + self.translation[i])
    }

    /// The transform of every point.
    pub fn apply_all(&self, pts: &[[T; 3]]) -> Vec<[T; 3]> {
        pts.iter().map(|p| self.apply(p)).collect()
    }

    /// `self ∘ other` (apply `other` first).
    pub fn compose(&self, other: &Similarity<T>) -> Similarity<T> {
        let rotation = matmul(&self.rotation, &other.rotation);
        let translation = self.apply(&other.translation);
        Similarity { rotation, translation, scale: self.scale * other.scale }
    }

    /// The inverse (`s > 0`, `R` a rotation).
    pub fn inverse(&self) -> Similarity<T> {
        let rt: [[T; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| self.rotation[j][i]));
        let s = T::one() / self.scale;
        let t = &self.translation;
        let tt = std::array::from_fn(|i| -s * (rt[i][0] * t[0] + rt[i][1] * t[1] + rt[i][2] * t[2]));
        Similarity { rotation: rt, translation: tt, scale: s }
    }
}

impl Similarity<f32> {
    /// A checked similarity from a (w, x, y, z) quaternion (need not be unit), translation and scale.
    pub fn from_quaternion(q: [f32; 4], translation: [f32; 3], scale: f32) -> Result<Self> {
        Self::new(quat_to_matrix(q), translation, scale)
    }

    /// Unit quaternion (w, x, y, z) of the rotation.
    pub fn quaternion(&self) -> [f32; 4] {
        matrix_to_quat(&self.rotation)
    }
}

/// Rotation matrix from an axis (need not be unit) and an angle in radians (Rodrigues).
pub fn axis_angle(axis: [f64; 3], angle: f64) -> [[f64; 3]; 3] {
    let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
    let (x, y, z) = (axis[0] / n, axis[1] / n, axis[2] / n);
    let (s, c) = angle.sin_cos();
    let v = 1.0 - c;
    [
        [c + x * x * v, x * y * v - z * s, x * z * v + y * s],
        [y * x * v + z * s, c + y * y * v, y * z * v - x * s],
        [z * x * v - y * s, z * y * v + x * s, c + z * z * v],
    ]
}

/// Determinant of a 3×3 matrix.
pub fn det<T: Real>(m: &[[T; 3]; 3]) -> T {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// Matrix product `a·b`.
pub fn matmul<T: Real>(a: &[[T; 3]; 3], b: &[[T; 3]; 3]) -> [[T; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

#[inline]
/// Difference `a − b`.
pub fn sub<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
/// Dot product.
pub fn dot<T: Real>(a: [T; 3], b: [T; 3]) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
/// Euclidean length.
pub fn norm<T: Real>(a: [T; 3]) -> T {
    dot(a, a).sqrt()
}

/// `v / |v|`; the zero vector is returned as it is.
#[inline]
pub fn normalize<T: Real>(v: [T; 3]) -> [T; 3] {
    let n = norm(v);
    if n > T::zero() {
        [v[0] / n, v[1] / n, v[2] / n]
    } else {
        v
    }
}

#[inline]
/// Cross product `a × b`.
pub fn cross<T: Real>(a: [T; 3], b: [T; 3]) -> [T; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
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

/// Unit quaternion in the direction of `q` (identity for the zero quaternion).
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

    fn close(a: &[[f32; 3]; 3], b: &[[f32; 3]; 3], tol: f32) -> bool {
        (0..3).all(|i| (0..3).all(|j| (a[i][j] - b[i][j]).abs() <= tol))
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
    fn rejects_non_rotations() {
        let refl = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]];
        assert!(Similarity::new(refl, [0.0; 3], 1.0).is_err());
        let shear = [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert!(Similarity::new(shear, [0.0; 3], 1.0).is_err());
        assert!(Similarity::new(Similarity::identity().rotation, [0.0; 3], 0.0).is_err());
        assert!(Similarity::new(Similarity::identity().rotation, [f32::NAN, 0.0, 0.0], 1.0).is_err());
    }
}
