//! Predicted poses between RecGen's normalised point-map frame and the
//! metric camera frame.
//!
//! **What the pose means.** Stage 1 predicts (after de-normalising the pose
//! tokens with the pose stats) a rotation `R`, translation `t` and isotropic
//! scale `s` that place the decoded object — the TRELLIS canonical frame in
//! which the voxel grid, the mesh and the Gaussians come out, `[-0.5, 0.5]³`,
//! z up, exactly as the decoders emit it — into the normalised point-map
//! frame of [`super::pointmap`]: `x_n = s·R·x_canonical + t`. RecGen applies
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

use super::pointmap::{Normaliser, NORMALISED_CENTRE};
use super::pose::Pose;
use crate::export::transform::Similarity;
use crate::Result;

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
pub fn canonical_to_camera(p: &Pose, n: &Normaliser) -> Result<Similarity> {
    let c = pose_to_camera(p, n);
    Similarity::new(c.rotation, c.translation, c.scale)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::pose::rotation_from_6d;
    use crate::model::sampler::SeededRng;

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
            let xn = Similarity::new(p.rotation, p.translation, p.scale).unwrap().apply_point(x);
            let want = n.to_camera([xn[0] as f64, xn[1] as f64, xn[2] as f64]);
            let got = sim.apply_point(x);
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
