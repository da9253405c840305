//! RecGen object pose: rotation + translation + isotropic scale, with the
//! 6D / 9D rotation encodings and z-score normalisation the models use.
//!
//! Layouts (RecGen `recgen_modules/utils/pose_utils.py`):
//! - 10-D (stage 1, `6d_translation_scale`): `[r6 (6), t (3), s]`, where
//!   `r6 = [r11, r21, r31, r12, r22, r32]` = the first two **columns** of R.
//! - 13-D (stage 2, `9d_translation_scale`): `[r9 (9), t (3), s]`.
//! - Decoding 6D: Gram–Schmidt `b1 = n(a1)`, `b2 = n(a2 − (b1·a2) b1)`,
//!   `b3 = b1 × b2`, `R = [b1 b2 b3]` as columns.
//!
//! **9-D ordering (spec §12 q4).** Two conventions exist upstream:
//! - The training data / `parse_pose_output` treat r9 as R flattened
//!   **row-major** (`reshape(3, 3)`). The released stats confirm it:
//!   `9d_rotation.mean = [m0, m3, ·, m1, m4, ·, m2, m5, ·]` in terms of the 6D
//!   mean `m`, i.e. `r9[3i + j] = R[i][j]` with r6 holding columns.
//! - `RecGenPipeline._convert_pose_representation`, which turns the stage-1
//!   pose into the stage-2 pose token at inference, concatenates the columns
//!   `[b1, b2, b3]` = R flattened column-major (= Rᵀ row-major), and then
//!   normalises that with the row-major stats.
//!
//! The released model was evaluated through the pipeline, so
//! [`NineDLayout::PipelineColumns`] is the default used for stage 2; the
//! row-major layout is available for training-data compatibility.

use std::path::Path;

use candle_core::{Device, Tensor};
use serde::Deserialize;

use crate::math::Similarity;
use crate::{Error, Result};

/// Row-major 3×3 matrix: `m[row][col]`.
pub type Mat3 = [[f32; 3]; 3];

/// An object pose: `x_world = scale · R · x_object + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation, row-major.
    pub rotation: Mat3,
    /// Translation.
    pub translation: [f32; 3],
    /// Uniform scale.
    pub scale: f32,
}

/// How a rotation is flattened into 9 numbers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NineDLayout {
    /// `[b1, b2, b3]` columns concatenated, as the released inference pipeline does.
    PipelineColumns,
    /// R row-major, as the training data and `parse_pose_output` do.
    RowMajor,
}

/// The layout of a pose vector (RecGen `pose_representation`): rotation, then
/// translation (3) and scale (1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, Deserialize)]
#[allow(clippy::enum_variant_names)] // the upstream names: rotation form + translation + scale
pub enum PoseRepresentation {
    #[serde(rename = "quaternion_translation_scale")]
    /// Quaternion (4), translation (3), scale (1).
    QuaternionTranslationScale,
    #[serde(rename = "6d_translation_scale")]
    /// 6D rotation (two columns), translation, scale.
    SixDTranslationScale,
    #[serde(rename = "9d_translation_scale")]
    /// 9D rotation (the full matrix), translation, scale.
    NineDTranslationScale,
}

impl PoseRepresentation {
    /// Width of a pose vector.
    pub fn channels(self) -> usize {
        match self {
            PoseRepresentation::QuaternionTranslationScale => 8,
            PoseRepresentation::SixDTranslationScale => 10,
            PoseRepresentation::NineDTranslationScale => 13,
        }
    }
}

// Upstream F.normalize clamps the norm at 1e-12.
const NORM_EPS: f64 = 1e-12;

fn normalize(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(NORM_EPS);
    [v[0] / n, v[1] / n, v[2] / n]
}

fn gram_schmidt(r6: &[f32; 6]) -> [[f64; 3]; 3] {
    let a1 = [r6[0] as f64, r6[1] as f64, r6[2] as f64];
    let a2 = [r6[3] as f64, r6[4] as f64, r6[5] as f64];
    let b1 = normalize(a1);
    let d = b1[0] * a2[0] + b1[1] * a2[1] + b1[2] * a2[2];
    let b2 = normalize([a2[0] - d * b1[0], a2[1] - d * b1[1], a2[2] - d * b1[2]]);
    let b3 = [b1[1] * b2[2] - b1[2] * b2[1], b1[2] * b2[0] - b1[0] * b2[2], b1[0] * b2[1] - b1[1] * b2[0]];
    [b1, b2, b3]
}

/// 6D → rotation matrix by Gram–Schmidt (columns b1, b2, b3).
pub fn rotation_from_6d(r6: &[f32; 6]) -> Mat3 {
    let b = gram_schmidt(r6);
    let mut r = [[0f32; 3]; 3];
    for (col, bc) in b.iter().enumerate() {
        for row in 0..3 {
            r[row][col] = bc[row] as f32;
        }
    }
    r
}

/// Rotation → 6D `[r11, r21, r31, r12, r22, r32]` (first two columns).
pub fn rotation_to_6d(r: &Mat3) -> [f32; 6] {
    [r[0][0], r[1][0], r[2][0], r[0][1], r[1][1], r[2][1]]
}

/// 6D → 9D as the released pipeline's `_convert_pose_representation`:
/// Gram–Schmidt, then `[b1, b2, b3]` concatenated (R column-major).
pub fn six_d_to_nine_d_pipeline(r6: &[f32; 6]) -> [f32; 9] {
    let b = gram_schmidt(r6);
    let mut out = [0f32; 9];
    for (i, v) in b.iter().flatten().enumerate() {
        out[i] = *v as f32;
    }
    out
}

/// Rotation → 9D in the given layout.
pub fn rotation_to_9d(r: &Mat3, layout: NineDLayout) -> [f32; 9] {
    let mut out = [0f32; 9];
    for i in 0..3 {
        for j in 0..3 {
            match layout {
                NineDLayout::RowMajor => out[3 * i + j] = r[i][j],
                NineDLayout::PipelineColumns => out[3 * j + i] = r[i][j],
            }
        }
    }
    out
}

/// 9D → matrix (inverse of [`rotation_to_9d`]; no re-orthonormalisation,
/// like upstream `parse_pose_output`).
pub fn rotation_from_9d(r9: &[f32; 9], layout: NineDLayout) -> Mat3 {
    let mut r = [[0f32; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            r[i][j] = match layout {
                NineDLayout::RowMajor => r9[3 * i + j],
                NineDLayout::PipelineColumns => r9[3 * j + i],
            };
        }
    }
    r
}

impl Pose {
    /// From a denormalised 10-D vector `[r6, t, s]`.
    pub fn from_10d(v: &[f32; 10]) -> Self {
        let r6 = [v[0], v[1], v[2], v[3], v[4], v[5]];
        Pose { rotation: rotation_from_6d(&r6), translation: [v[6], v[7], v[8]], scale: v[9] }
    }

    /// To a 10-D vector `[r6, t, s]`.
    pub fn to_10d(&self) -> [f32; 10] {
        let r6 = rotation_to_6d(&self.rotation);
        let t = self.translation;
        [r6[0], r6[1], r6[2], r6[3], r6[4], r6[5], t[0], t[1], t[2], self.scale]
    }

    /// To a 13-D vector `[r9, t, s]`.
    pub fn to_13d(&self, layout: NineDLayout) -> [f32; 13] {
        let r9 = rotation_to_9d(&self.rotation, layout);
        let mut out = [0f32; 13];
        out[..9].copy_from_slice(&r9);
        out[9..12].copy_from_slice(&self.translation);
        out[12] = self.scale;
        out
    }

    /// From a 13-D vector `[r9, t, s]`.
    pub fn from_13d(v: &[f32; 13], layout: NineDLayout) -> Self {
        let mut r9 = [0f32; 9];
        r9.copy_from_slice(&v[..9]);
        Pose { rotation: rotation_from_9d(&r9, layout), translation: [v[9], v[10], v[11]], scale: v[12] }
    }

    /// 4×4 row-major similarity transform `[s·R | t; 0 0 0 1]`.
    pub fn matrix(&self) -> [[f32; 4]; 4] {
        let mut m = [[0f32; 4]; 4];
        for i in 0..3 {
            for j in 0..3 {
                m[i][j] = self.scale * self.rotation[i][j];
            }
            m[i][3] = self.translation[i];
        }
        m[3][3] = 1.0;
        m
    }
}

#[derive(Debug, Clone, Deserialize)]
struct MeanStd<const N: usize> {
    #[serde(with = "serde_arrays_or_vec")]
    mean: [f64; N],
    #[serde(with = "serde_arrays_or_vec")]
    std: [f64; N],
}

#[derive(Debug, Clone, Deserialize)]
struct ScalarMeanStd {
    mean: f64,
    std: f64,
}

#[derive(Debug, Clone, Deserialize)]
struct GlobalStats {
    #[serde(rename = "6d_rotation")]
    rot6d: MeanStd<6>,
    #[serde(rename = "9d_rotation", default)]
    rot9d: Option<MeanStd<9>>,
    translation: MeanStd<3>,
    scale: ScalarMeanStd,
}

/// Fixed-size arrays from JSON lists (serde only derives arrays up to 32 via
/// tuples; a length check gives a clear error).
mod serde_arrays_or_vec {
    use serde::{Deserialize, Deserializer};
    pub fn deserialize<'de, D: Deserializer<'de>, const N: usize>(d: D) -> Result<[f64; N], D::Error> {
        let v = Vec::<f64>::deserialize(d)?;
        v.clone().try_into().map_err(|_| serde::de::Error::custom(format!("expected {N} numbers, got {}", v.len())))
    }
}

/// Z-score pose statistics (RecGen `PoseNormalizer`), read from a JSON file in
/// the format of `stereo_pose_stats.json` / `slat_pose_stats.json`
/// (`global_statistics.{6d_rotation, 9d_rotation, translation, scale}` with
/// `mean`/`std`; the wrapper object is optional).
#[derive(Debug, Clone)]
pub struct PoseStats {
    stats: GlobalStats,
}

impl PoseStats {
    /// Reads the statistics from a JSON file.
    pub fn from_json_file(path: &Path) -> Result<Self> {
        let v: serde_json::Value = crate::util::json::read_json(path)?;
        Self::from_json(&v, &path.display().to_string())
    }

    /// The statistics from parsed JSON; `file` names it in errors.
    pub fn from_json(v: &serde_json::Value, file: &str) -> Result<Self> {
        let g = v.get("global_statistics").unwrap_or(v);
        let stats: GlobalStats = serde_json::from_value(g.clone()).map_err(|e| Error::config(file, "global_statistics", e.to_string()))?;
        let mut stds: Vec<f64> = stats.rot6d.std.to_vec();
        stds.extend(stats.translation.std);
        stds.push(stats.scale.std);
        if let Some(r9) = &stats.rot9d {
            stds.extend(r9.std);
        }
        if stds.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(Error::config(file, "std", "every std must be a positive finite number"));
        }
        Ok(Self { stats })
    }

    fn rot9d(&self) -> Result<&MeanStd<9>> {
        self.stats.rot9d.as_ref().ok_or_else(|| Error::msg("pose stats: no `9d_rotation` entry for a 13-D pose"))
    }

    /// Mean and std of each component of the 10-D or 13-D layout.
    fn mean_std(&self, dim: usize) -> Result<(Vec<f64>, Vec<f64>)> {
        let (mut m, mut s): (Vec<f64>, Vec<f64>) = match dim {
            10 => (self.stats.rot6d.mean.to_vec(), self.stats.rot6d.std.to_vec()),
            13 => {
                let r = self.rot9d()?;
                (r.mean.to_vec(), r.std.to_vec())
            }
            _ => return Err(Error::msg(format!("pose stats: unsupported pose width {dim} (10 or 13)"))),
        };
        m.extend(self.stats.translation.mean);
        s.extend(self.stats.translation.std);
        m.push(self.stats.scale.mean);
        s.push(self.stats.scale.std);
        Ok((m, s))
    }

    /// `(x − mean) / std` per component, for 10-D or 13-D vectors.
    pub fn normalize(&self, v: &[f32]) -> Result<Vec<f32>> {
        let (m, s) = self.mean_std(v.len())?;
        Ok(v.iter().zip(m.iter().zip(&s)).map(|(&x, (m, s))| ((x as f64 - m) / s) as f32).collect())
    }

    /// `x·std + mean` per component; the scale is clamped to ≥ 1e-6 as upstream.
    pub fn denormalize(&self, v: &[f32]) -> Result<Vec<f32>> {
        let (m, s) = self.mean_std(v.len())?;
        let mut out: Vec<f32> = v.iter().zip(m.iter().zip(&s)).map(|(&x, (m, s))| (x as f64 * s + m) as f32).collect();
        if let Some(last) = out.last_mut() {
            *last = last.max(1e-6);
        }
        Ok(out)
    }

    /// Decode a normalised 10-D model output into a pose.
    pub fn decode_10d(&self, v: &[f32]) -> Result<Pose> {
        let d = self.denormalize(v)?;
        let a: [f32; 10] = d.try_into().map_err(|_| Error::msg("pose: expected 10 values"))?;
        Ok(Pose::from_10d(&a))
    }
}

/// Stage-1 → stage-2 pose tokens, as `RecGenPipeline._prepare_pose_for_slat`:
/// normalised 10-D `[B, K, 10]` (or `[B, 10]`) → denormalise with the stage-1
/// stats → Gram–Schmidt 6D → 9D (`layout`) → normalise with the stage-2 stats
/// → `[B, K, 13]` (or `[B, 13]`).
pub fn ss_pose_to_slat_pose(pose: &Tensor, ss: &PoseStats, slat: &PoseStats, layout: NineDLayout) -> Result<Tensor> {
    let dims = pose.dims().to_vec();
    if dims.last() != Some(&10) || !(dims.len() == 2 || dims.len() == 3) {
        return Err(Error::msg(format!("pose: expected [B, K, 10] or [B, 10], got {dims:?}")));
    }
    let rows = pose.flatten_to(dims.len() - 2)?.to_dtype(candle_core::DType::F32)?.to_vec2::<f32>()?;
    let mut out = Vec::with_capacity(rows.len() * 13);
    for r in rows {
        let d = ss.denormalize(&r)?;
        let r6 = [d[0], d[1], d[2], d[3], d[4], d[5]];
        let r9 = match layout {
            NineDLayout::PipelineColumns => six_d_to_nine_d_pipeline(&r6),
            NineDLayout::RowMajor => rotation_to_9d(&rotation_from_6d(&r6), NineDLayout::RowMajor),
        };
        let mut v13 = r9.to_vec();
        v13.extend_from_slice(&d[6..10]);
        out.extend(slat.normalize(&v13)?);
    }
    let mut shape = dims;
    *shape.last_mut().unwrap() = 13;
    Ok(Tensor::from_vec(out, shape, &Device::Cpu)?.to_device(pose.device())?)
}

/// A pose as an f64 similarity.
pub fn pose_to_similarity(p: &Pose) -> Similarity {
    Similarity {
        rotation: p.rotation.map(|row| row.map(|x| x as f64)),
        translation: p.translation.map(|x| x as f64),
        scale: p.scale as f64,
    }
}

/// The [`Pose`] of a similarity (rounded to f32).
pub fn similarity_to_pose(s: &Similarity) -> Pose {
    Pose { rotation: s.rotation.map(|row| row.map(|x| x as f32)), translation: s.translation.map(|x| x as f32), scale: s.scale as f32 }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SeededRng;

    fn det(r: &Mat3) -> f32 {
        r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
            + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0])
    }

    fn rand6(rng: &mut SeededRng) -> [f32; 6] {
        std::array::from_fn(|_| rng.normal() as f32)
    }

    #[test]
    fn gram_schmidt_is_orthonormal_and_roundtrips() {
        let mut rng = SeededRng::new(11);
        for _ in 0..200 {
            let r = rotation_from_6d(&rand6(&mut rng));
            for i in 0..3 {
                for j in 0..3 {
                    let dot: f32 = (0..3).map(|k| r[k][i] * r[k][j]).sum();
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((dot - want).abs() < 1e-5, "RᵀR[{i}][{j}] = {dot}");
                }
            }
            assert!((det(&r) - 1.0).abs() < 1e-5);
            let back = rotation_from_6d(&rotation_to_6d(&r));
            for i in 0..3 {
                for j in 0..3 {
                    assert!((back[i][j] - r[i][j]).abs() < 1e-5);
                }
            }
        }
        // The first column is a1's direction.
        let r = rotation_from_6d(&[2.0, 0.0, 0.0, 1.0, 3.0, 0.0]);
        assert_eq!([r[0][0], r[1][0], r[2][0]], [1.0, 0.0, 0.0]);
        assert_eq!([r[0][1], r[1][1], r[2][1]], [0.0, 1.0, 0.0]);
        assert_eq!([r[0][2], r[1][2], r[2][2]], [0.0, 0.0, 1.0]);
    }

    #[test]
    fn nine_d_layouts() {
        // A rotation about z by 90°: columns (0,1,0), (−1,0,0), (0,0,1).
        let r: Mat3 = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let r6 = rotation_to_6d(&r);
        assert_eq!(r6, [0.0, 1.0, 0.0, -1.0, 0.0, 0.0]);
        // Pipeline: columns b1, b2, b3 concatenated.
        assert_eq!(six_d_to_nine_d_pipeline(&r6), [0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        assert_eq!(rotation_to_9d(&r, NineDLayout::PipelineColumns), six_d_to_nine_d_pipeline(&r6));
        // Row-major: rows of R.
        assert_eq!(rotation_to_9d(&r, NineDLayout::RowMajor), [0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
        for l in [NineDLayout::RowMajor, NineDLayout::PipelineColumns] {
            assert_eq!(rotation_from_9d(&rotation_to_9d(&r, l), l), r);
        }
        let p = Pose { rotation: r, translation: [1.0, 2.0, 3.0], scale: 0.5 };
        let v = p.to_13d(NineDLayout::RowMajor);
        assert_eq!(&v[9..], &[1.0, 2.0, 3.0, 0.5]);
        assert_eq!(Pose::from_13d(&v, NineDLayout::RowMajor), p);
        assert_eq!(Pose::from_10d(&p.to_10d()), p);
    }

    fn example_stats(name: &str) -> PoseStats {
        let path = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../..")).join("models").join(name);
        PoseStats::from_json_file(&path).unwrap()
    }

    #[test]
    fn normalisation_roundtrips_with_shipped_stats() {
        let ss = example_stats("stereo_pose_stats.example.json");
        let slat = example_stats("slat_pose_stats.example.json");
        let mut rng = SeededRng::new(5);
        for _ in 0..20 {
            let v10: Vec<f32> = (0..10).map(|i| rng.normal() as f32 + if i == 9 { 3.0 } else { 0.0 }).collect();
            let back = ss.denormalize(&ss.normalize(&v10).unwrap()).unwrap();
            for (a, b) in v10.iter().zip(&back) {
                assert!((a - b).abs() < 1e-5);
            }
            let v13: Vec<f32> = (0..13).map(|i| rng.normal() as f32 + if i == 12 { 3.0 } else { 0.0 }).collect();
            let back = slat.denormalize(&slat.normalize(&v13).unwrap()).unwrap();
            for (a, b) in v13.iter().zip(&back) {
                assert!((a - b).abs() < 1e-5);
            }
        }
        // The mean pose normalises to zeros.
        let mean = ss.denormalize(&[0.0; 10]).unwrap();
        assert!(ss.normalize(&mean).unwrap().iter().all(|v| v.abs() < 1e-6));
        assert!(ss.normalize(&[0.0; 7]).is_err());
        // The shipped stats encode r9 row-major relative to r6 columns (module docs).
        let (m6, _) = ss.mean_std(10).unwrap();
        let (m9, _) = ss.mean_std(13).unwrap();
        for (i9, i6) in [(0, 0), (1, 3), (3, 1), (4, 4), (6, 2), (7, 5)] {
            assert!((m9[i9] - m6[i6]).abs() < 1e-12);
        }
    }

    #[test]
    fn stage1_to_stage2_pose_tokens() -> Result<()> {
        let ss = example_stats("stereo_pose_stats.example.json");
        let slat = example_stats("slat_pose_stats.example.json");
        let r: Mat3 = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let p = Pose { rotation: r, translation: [0.5, 0.4, 0.7], scale: 1.1 };
        let n10 = ss.normalize(&p.to_10d())?;
        let t = Tensor::from_vec([n10.clone(), n10].concat(), (1, 2, 10), &Device::Cpu)?;
        let out = ss_pose_to_slat_pose(&t, &ss, &slat, NineDLayout::PipelineColumns)?;
        assert_eq!(out.dims(), &[1, 2, 13]);
        let row = out.flatten_all()?.to_vec1::<f32>()?;
        let d = slat.denormalize(&row[..13])?;
        let want = p.to_13d(NineDLayout::PipelineColumns);
        for (a, b) in d.iter().zip(&want) {
            assert!((a - b).abs() < 1e-5, "{d:?} vs {want:?}");
        }
        Ok(())
    }

    #[test]
    fn bad_stats_are_rejected() {
        let v = serde_json::json!({"6d_rotation": {"mean": [0,0,0,0,0,0], "std": [1,1,1,1,1,0]},
            "translation": {"mean": [0,0,0], "std": [1,1,1]}, "scale": {"mean": 1, "std": 1}});
        assert!(PoseStats::from_json(&v, "t").is_err());
        let v = serde_json::json!({"6d_rotation": {"mean": [0,0,0], "std": [1,1,1]},
            "translation": {"mean": [0,0,0], "std": [1,1,1]}, "scale": {"mean": 1, "std": 1}});
        assert!(PoseStats::from_json(&v, "t").is_err());
    }
}
