//! Predicted poses between RecGen's normalised point-map frame and the
//! metric camera frame.
//!
//! **What the pose means.** Stage 1 predicts (after de-normalising the pose
//! tokens with the pose stats) a rotation `R`, translation `t` and isotropic
//! scale `s` that place the decoded object — the TRELLIS canonical frame in
//! which the voxel grid, the mesh and the Gaussians come out, `[-0.5, 0.5]³`,
//! z up, exactly as the decoders emit it — into the normalised point-map
//! frame of [`crate::geometry::pointmap`]: `x_n = s·R·x_canonical + t`. RecGen applies
//! the pose matrix directly to the raw decoder mesh (`inference.py`,
//! `_build_result_from_outputs`) and documents the canonical → camera map as
//! `inv(cam2ncam) @ pose` applied to the Gaussians in their canonical frame
//! (`posthoc_color.calibrate_asset`), so **no axis change** (such as GLB's
//! z-up → y-up) sits between the decoder output and the pose. A y-up export
//! rotation, if wanted, belongs after the objects are placed, not here.
//!
//! **Back to metres.** With the normaliser `x_n = (x − c)/d + 0.5`
//! (`c` = median centre, `d` = diameter in metres):
//! `x = (x_n − 0.5)·d + c`, hence the camera-frame pose is
//! `R_cam = R`, `t_cam = (t − 0.5)·d + c`, `s_cam = s·d`.
//! (RecGen's mesh path does the same: apply the pose, subtract
//! `cam2ncam`'s translation `0.5 − c/d`, divide by `1/d`.) Note the 0.5
//! offset: the normalised frame is centred at `(0.5, 0.5, 0.5)`, not at 0,
//! which matches the stage-1 pose stats (translation mean ≈ (0.50, 0.49, 0.66)).

use crate::geometry::pointmap::{Normaliser, NORMALISED_CENTRE};
use crate::geometry::pose::Pose;
use crate::math::{Similarity, Similarity32};
use crate::{Error, Result};
use std::path::Path;

/// Normalised-frame pose → camera-frame pose (metres).
pub fn pose_to_camera(p: &Pose, n: &Normaliser) -> Pose {
    let t = std::array::from_fn(|a| ((p.translation[a] as f64 - NORMALISED_CENTRE) * n.diameter + n.centre[a]) as f32);
    Pose { rotation: p.rotation, translation: t, scale: (p.scale as f64 * n.diameter) as f32 }
}

/// Camera-frame pose (metres) → normalised-frame pose (inverse of
/// [`pose_to_camera`]); used to express ground truth in the model's frame.
pub fn pose_to_normalised(p: &Pose, n: &Normaliser) -> Pose {
    let t = std::array::from_fn(|a| ((p.translation[a] as f64 - n.centre[a]) / n.diameter + NORMALISED_CENTRE) as f32);
    Pose { rotation: p.rotation, translation: t, scale: (p.scale as f64 / n.diameter) as f32 }
}

/// The similarity placing canonical decoder output (mesh vertices, Gaussian
/// centres/scales/rotations) in the metric camera frame, from the predicted
/// normalised-frame pose: RecGen's `inv(cam2ncam) @ pose_matrix`.
/// Fails when the rotation is not proper or the scale not positive.
pub fn canonical_to_camera(p: &Pose, n: &Normaliser) -> Result<Similarity32> {
    let c = pose_to_camera(p, n);
    Similarity32::new(c.rotation, c.translation, c.scale)
}

/// The relative camera pose `T_c1_c2` (camera 2 → camera 1: `x₁ = R·x₂ + t`,
/// metres) from `--rel-pose`: 16 numbers of the 4×4 matrix, row-major,
/// separated by commas or spaces, or a JSON file holding `"T_c1_c2"` (4×4
/// rows or 16 numbers). The rotation must be proper and orthonormal to 1e-3.
pub fn parse_rel_pose(arg: &str) -> Result<Similarity> {
    let path = Path::new(arg);
    let (nums, file): (Vec<f64>, String) = if path.is_file() {
        let file = path.display().to_string();
        let v: serde_json::Value = crate::util::json::read_json(path)?;
        let m =
            v.get("T_c1_c2").ok_or_else(|| Error::config(&file, "T_c1_c2", "missing: expected the 4×4 camera-2-to-camera-1 transform"))?;
        let mut flat = Vec::new();
        fn walk(v: &serde_json::Value, out: &mut Vec<f64>) -> bool {
            match v {
                serde_json::Value::Array(a) => a.iter().all(|x| walk(x, out)),
                serde_json::Value::Number(n) => n.as_f64().map(|x| out.push(x)).is_some(),
                _ => false,
            }
        }
        if !walk(m, &mut flat) {
            return Err(Error::config(&file, "T_c1_c2", "must hold only numbers (4×4 rows or 16 numbers)"));
        }
        (flat, file)
    } else {
        let parts: Vec<&str> = arg.split(|c: char| c == ',' || c.is_whitespace()).filter(|s| !s.is_empty()).collect();
        let nums: std::result::Result<Vec<f64>, _> = parts.iter().map(|s| s.parse::<f64>()).collect();
        let nums = nums.map_err(|_| {
            Error::input("--rel-pose", format!("`{arg}` is neither a file nor 16 numbers (4×4 row-major camera-2-to-camera-1 transform)"))
        })?;
        (nums, "--rel-pose".to_string())
    };
    rel_pose_from_numbers(&nums, &file, "T_c1_c2")
}

/// A relative camera pose from the 16 numbers of its 4×4 matrix, row-major,
/// checked as [`parse_rel_pose`] checks it; errors name `file` and the
/// matrix's `name` (`T_c1_c2`).
pub fn rel_pose_from_numbers(nums: &[f64], file: &str, name: &str) -> Result<Similarity> {
    if nums.len() != 16 || nums.iter().any(|x| !x.is_finite()) {
        return Err(Error::input(file, format!("{name} needs 16 finite numbers (4×4, row-major), got {}", nums.len())));
    }
    let m = |i: usize, j: usize| nums[4 * i + j];
    if (m(3, 0).abs() + m(3, 1).abs() + m(3, 2).abs() + (m(3, 3) - 1.0).abs()) > 1e-6 {
        return Err(Error::input(file, format!("{name}: the last row must be 0 0 0 1 (a rigid transform)")));
    }
    let r: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| m(i, j)));
    let mut err: f64 = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            let d: f64 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
            err = err.max((d - if i == j { 1.0 } else { 0.0 }).abs());
        }
    }
    let det = nalgebra::Matrix3::from_fn(|i, j| r[i][j]).determinant();
    if err > 1e-3 || det <= 0.0 {
        return Err(Error::input(file, format!("{name}: the 3×3 block is not a rotation (|RᵀR − I| = {err:.2e}, det = {det:.4})")));
    }
    Ok(Similarity::rigid(r, [m(0, 3), m(1, 3), m(2, 3)]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose::rotation_from_6d;
    use crate::rng::SeededRng;

    #[test]
    fn round_trip_is_exact_on_dyadic_values() {
        // Dyadic numbers make every step exact in f32/f64.
        let n = Normaliser { centre: [0.25, -0.125, 0.75], diameter: 0.5 };
        let r = rotation_from_6d(&[0.0, 1.0, 0.0, -1.0, 0.0, 0.0]);
        let p = Pose { rotation: r, translation: [0.5, 0.375, 0.625], scale: 1.25 };
        let c = pose_to_camera(&p, &n);
        assert_eq!(c.translation, [0.25, -0.1875, 0.8125]);
        assert_eq!(c.scale, 0.625);
        assert_eq!(pose_to_normalised(&c, &n), p);
    }

    #[test]
    fn round_trip_and_point_consistency() {
        let mut rng = SeededRng::new(3);
        for _ in 0..100 {
            let n = Normaliser {
                centre: [rng.normal() * 0.2, rng.normal() * 0.2, 0.8 + rng.normal().abs()],
                diameter: 0.05 + rng.normal().abs() * 0.3,
            };
            let r6: [f32; 6] = std::array::from_fn(|_| rng.normal() as f32);
            let p = Pose {
                rotation: rotation_from_6d(&r6),
                translation: std::array::from_fn(|_| 0.5 + 0.1 * rng.normal() as f32),
                scale: 1.0 + 0.3 * rng.normal().abs() as f32,
            };
            let back = pose_to_normalised(&pose_to_camera(&p, &n), &n);
            // Camera translations are stored in f32 (metres): one ulp there is
            // ulp/d in normalised units.
            let tol = 4.0 * f32::EPSILON as f64 * (1.0 + n.centre[2].abs()) / n.diameter + 1e-6;
            for a in 0..3 {
                assert!(((back.translation[a] - p.translation[a]).abs() as f64) < tol);
            }
            assert!((back.scale - p.scale).abs() < 1e-6 * p.scale);
            assert_eq!(back.rotation, p.rotation);
            // Placing a canonical point via the camera similarity equals placing
            // it in the normalised frame and un-normalising it.
            let sim = canonical_to_camera(&p, &n).unwrap();
            let x = [0.3f32, -0.2, 0.45];
            let xn = Similarity32::new(p.rotation, p.translation, p.scale).unwrap().apply(&x);
            let want = n.to_camera([xn[0] as f64, xn[1] as f64, xn[2] as f64]);
            let got = sim.apply(&x);
            for a in 0..3 {
                assert!((got[a] as f64 - want[a]).abs() < 1e-5, "{got:?} vs {want:?}");
            }
        }
        // A reflection is refused.
        let n = Normaliser { centre: [0.0; 3], diameter: 1.0 };
        let bad = Pose { rotation: [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], translation: [0.0; 3], scale: 1.0 };
        assert!(canonical_to_camera(&bad, &n).is_err());
    }
}
