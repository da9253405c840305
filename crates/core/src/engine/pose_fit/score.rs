//! How well a posed mesh explains the observed depth (RecGen appendix B).
//!
//! **Score.** A candidate pose places the decoded mesh in metric camera
//! space; its score in one view is the *trimmed mean* of the distances from
//! that view's observed object points (eroded mask, valid depth, metres) to
//! the posed mesh surface, dropping the largest [`AlignOptions::trim`]
//! (10 %) of the distances so that mask bleeding, flying pixels and the
//! unobserved back of the object do not dominate. Lower is better.
//!
//! Distances are to the surface, not to vertices: the mesh is densely
//! sampled once in its canonical frame ([`Surface`]), the nearest sample is
//! found with the k-d tree of [`crate::spatial`], and the distance is
//! refined to the exact point-to-triangle distance of that sample's face
//! (never larger than the sample distance, never smaller than the true one).
//! Placing the mesh by a similarity `x ↦ s·R·x + t` scales distances by `s`,
//! so the points are mapped into the canonical frame instead of re-sampling
//! the mesh for every candidate. Without a mesh (mesh decoding off) a point
//! set such as the Gaussian centres stands in ([`Surface::from_points`]).
//!
use crate::engine::pose_fit::free_space::{free_space, ViewPoints};
use crate::engine::pose_fit::options::{AlignOptions, FREE_SPACE_SAMPLES};
use crate::math::Similarity;
use crate::mesh::trimesh::TriMesh;
use crate::spatial::{dist2, KdTree, P3};
use crate::util::trimmed_mean;
use crate::{Error, Result};
use rayon::prelude::*;
use serde::Serialize;

/// Closest point to `p` on triangle `abc` (Ericson, *Real-Time Collision
/// Detection* §5.1.5: Voronoi regions of vertices, edges, face).
pub fn closest_point_on_triangle(p: &P3, a: &P3, b: &P3, c: &P3) -> P3 {
    let sub = |u: &P3, v: &P3| [u[0] - v[0], u[1] - v[1], u[2] - v[2]];
    let dot = |u: &P3, v: &P3| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let at = |o: &P3, d: &P3, t: f64| [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(&ab, &ap), dot(&ac, &ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return *a;
    }
    let bp = sub(p, b);
    let (d3, d4) = (dot(&ab, &bp), dot(&ac, &bp));
    if d3 >= 0.0 && d4 <= d3 {
        return *b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return at(a, &ab, d1 / (d1 - d3));
    }
    let cp = sub(p, c);
    let (d5, d6) = (dot(&ab, &cp), dot(&ac, &cp));
    if d6 >= 0.0 && d5 <= d6 {
        return *c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return at(a, &ac, d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return at(b, &sub(c, b), (d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = va + vb + vc;
    if denom.abs() < f64::MIN_POSITIVE {
        // Degenerate (zero-area) triangle: the nearest of its vertices.
        return *[a, b, c].into_iter().min_by(|x, y| dist2(x, p).total_cmp(&dist2(y, p))).unwrap_or(a);
    }
    let (v, w) = (vb / denom, vc / denom);
    [a[0] + ab[0] * v + ac[0] * w, a[1] + ab[1] * v + ac[1] * w, a[2] + ab[2] * v + ac[2] * w]
}

/// A mesh surface ready for distance queries (in the mesh's own frame).
pub struct Surface {
    tree: KdTree,
    face_of: Vec<u32>,
    mesh: TriMesh,
    /// The samples in drawing order (a stride subset is spread over the surface).
    pts: Vec<P3>,
}

impl Surface {
    /// Sample `samples` surface points (seeded) and index them. A mesh
    /// without faces is a point set (e.g. Gaussian centres when no mesh was
    /// decoded): distances are then to its nearest point.
    pub fn new(mesh: TriMesh, samples: usize, seed: u64) -> Result<Self> {
        if mesh.vertices.is_empty() || (!mesh.faces.is_empty() && mesh.surface_area() <= 0.0) {
            return Err(Error::msg("alignment: the mesh has no surface to score against"));
        }
        let (pts, face_of) = mesh.sample_surface_faces(samples.max(1), seed);
        Ok(Surface { tree: KdTree::new(&pts), face_of, mesh, pts })
    }

    /// From a decoder mesh (f32, any frame).
    pub fn from_mesh(m: &crate::mesh::Mesh, samples: usize, seed: u64) -> Result<Self> {
        Self::new(TriMesh::from(m), samples, seed)
    }

    /// A point set (all points kept).
    pub fn from_points(points: &[[f32; 3]]) -> Result<Self> {
        let mesh = TriMesh { vertices: points.iter().map(|v| v.map(|x| x as f64)).collect(), faces: Vec::new() };
        let n = mesh.vertices.len();
        Self::new(mesh, n, 0)
    }

    /// Distance from `q` to the surface (see the module docs).
    pub fn distance(&self, q: &P3) -> f64 {
        let Some((i, d)) = self.tree.nearest(q) else { return f64::INFINITY };
        match self.face_of.get(i).copied() {
            Some(f) if f != u32::MAX => {
                let [a, b, c] = self.mesh.faces[f as usize].map(|k| self.mesh.vertices[k as usize]);
                d.min(dist2(&closest_point_on_triangle(q, &a, &b, &c), q).sqrt())
            }
            _ => d,
        }
    }

    /// [`Surface::distance`] of every point, computed in parallel.
    pub fn distances(&self, qs: &[P3]) -> Vec<f64> {
        qs.par_iter().map(|q| self.distance(q)).collect()
    }

    /// About `n` of the surface samples (a deterministic stride subset).
    pub fn samples(&self, n: usize) -> Vec<P3> {
        let stride = self.pts.len().div_ceil(n.max(1)).max(1);
        self.pts.iter().step_by(stride).copied().collect()
    }
}

/// A candidate's trimmed-mean distance in every view (metres).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CandidateScore {
    /// The view whose pose token produced the candidate.
    pub own_view: usize,
    /// Score in each view, view order (metres; NaN when there was nothing to score against).
    pub per_view_m: Vec<f64>,
}

impl CandidateScore {
    /// Score in the candidate's own view.
    pub fn single(&self) -> f64 {
        self.per_view_m[self.own_view]
    }

    /// Mean of the per-view scores.
    pub fn cross(&self) -> f64 {
        self.per_view_m.iter().sum::<f64>() / self.per_view_m.len() as f64
    }
}

/// Trimmed-mean distance from `view`'s points to `surface` placed by
/// `pose` (surface frame → anchor camera), plus the weighted free-space term
/// when `opts.free_space_weight > 0` and the view has depth.
pub fn view_score(surface: &Surface, pose: &Similarity, view: &ViewPoints, opts: &AlignOptions) -> f64 {
    view_score_with(surface, &free_space_samples(surface, std::slice::from_ref(view), opts), pose, view, opts)
}

/// The surface samples the free-space term of a full score uses (none when
/// the term is off or no view has depth).
fn free_space_samples(surface: &Surface, views: &[ViewPoints], opts: &AlignOptions) -> Vec<P3> {
    if opts.free_space_weight > 0.0 && views.iter().any(|v| v.depth.is_some()) {
        surface.samples(FREE_SPACE_SAMPLES)
    } else {
        Vec::new()
    }
}

/// [`view_score`] with the free-space term over the given surface samples.
pub fn view_score_with(surface: &Surface, samples: &[P3], pose: &Similarity, view: &ViewPoints, opts: &AlignOptions) -> f64 {
    view_score_stretched(surface, samples, pose, [0.0; 3], view, opts)
}

/// [`view_score_with`] of the surface stretched per axis by `e^a` (surface
/// frame) before `pose`. Point-to-surface distances are measured in the
/// unstretched frame and rescaled by the geometric-mean stretch (exact for a
/// uniform stretch, close for the mild ones the refinement allows).
pub fn view_score_stretched(
    surface: &Surface,
    samples: &[P3],
    pose: &Similarity,
    a: [f64; 3],
    view: &ViewPoints,
    opts: &AlignOptions,
) -> f64 {
    let stretched = a != [0.0; 3];
    let k = a.map(f64::exp);
    let gm = if stretched { ((a[0] + a[1] + a[2]) / 3.0).exp() } else { 1.0 };
    let to_surface = pose.inverse().compose(&view.to_anchor);
    let stride = view.points.len().div_ceil(opts.max_points.max(1)).max(1);
    let q: Vec<P3> = view
        .points
        .iter()
        .step_by(stride)
        .map(|p| {
            let c = to_surface.apply(p);
            if stretched {
                [c[0] / k[0], c[1] / k[1], c[2] / k[2]]
            } else {
                c
            }
        })
        .collect();
    let d: Vec<f64> = surface.distances(&q).into_iter().map(|x| x * pose.scale * gm).collect();
    let fit = trimmed_mean(&d, opts.trim);
    if opts.free_space_weight > 0.0 && !samples.is_empty() {
        let fs = if stretched {
            let st: Vec<P3> = samples.iter().map(|p| [p[0] * k[0], p[1] * k[1], p[2] * k[2]]).collect();
            free_space(&st, pose, view, opts)
        } else {
            free_space(samples, pose, view, opts)
        };
        fit + opts.free_space_weight * fs
    } else {
        fit
    }
}

/// Score one candidate in every view.
pub fn score_candidate(surface: &Surface, pose: &Similarity, own_view: usize, views: &[ViewPoints], opts: &AlignOptions) -> CandidateScore {
    let samples = free_space_samples(surface, views, opts);
    CandidateScore { own_view, per_view_m: views.iter().map(|v| view_score_with(surface, &samples, pose, v, opts)).collect() }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::pose_fit::select::{pose_spread, select_best, SelectMethod};
    use crate::geometry::camera_pose::parse_rel_pose;
    use crate::math::axis_angle;
    use crate::mesh::primitives::cuboid;
    use crate::rng::SeededRng;

    trait Mm {
        fn map_mm(&self) -> Vec<f64>;
    }
    impl Mm for Vec<f64> {
        fn map_mm(&self) -> Vec<f64> {
            self.iter().map(|x| (x * 1e4).round() / 10.0).collect()
        }
    }

    fn noisy(pts: &[P3], sigma: f64, rng: &mut SeededRng) -> Vec<P3> {
        pts.iter().map(|p| p.map(|x| x + sigma * rng.normal())).collect()
    }

    #[test]
    fn triangle_closest_points() {
        let (a, b, c) = ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        let near = |p: P3, q: P3| assert!(dist2(&p, &q) < 1e-24, "{p:?} vs {q:?}");
        near(closest_point_on_triangle(&[0.2, 0.2, 3.0], &a, &b, &c), [0.2, 0.2, 0.0]); // face
        near(closest_point_on_triangle(&[-1.0, -1.0, 0.5], &a, &b, &c), a); // vertex
        near(closest_point_on_triangle(&[2.0, -0.1, 0.0], &a, &b, &c), b);
        near(closest_point_on_triangle(&[0.5, -2.0, 0.0], &a, &b, &c), [0.5, 0.0, 0.0]); // edge ab
        near(closest_point_on_triangle(&[1.0, 1.0, 0.0], &a, &b, &c), [0.5, 0.5, 0.0]); // edge bc
                                                                                        // Brute force over a fine barycentric grid agrees.
        let mut rng = SeededRng::new(5);
        for _ in 0..200 {
            let q = [rng.normal(), rng.normal(), rng.normal()];
            let got = dist2(&closest_point_on_triangle(&q, &a, &b, &c), &q).sqrt();
            let mut best = f64::INFINITY;
            for i in 0..=100 {
                for j in 0..=(100 - i) {
                    let p = [i as f64 / 100.0, j as f64 / 100.0, 0.0];
                    best = best.min(dist2(&p, &q).sqrt());
                }
            }
            assert!(got <= best + 1e-12 && best - got < 0.01, "{got} vs {best}");
        }
    }

    #[test]
    fn surface_distance_is_exact_for_a_box() {
        let s = Surface::new(cuboid([0.05, 0.03, 0.02]), 5000, 1).unwrap();
        // Above the top face, beside a side face, and inside.
        assert!((s.distance(&[0.01, 0.0, 0.03]) - 0.01).abs() < 1e-12);
        assert!((s.distance(&[0.07, 0.01, 0.0]) - 0.02).abs() < 1e-12);
        assert!((s.distance(&[0.0, 0.0, 0.015]) - 0.005).abs() < 1e-12);
        assert!(Surface::new(TriMesh::default(), 10, 0).is_err());
        let pts = Surface::from_points(&[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]).unwrap();
        assert!((pts.distance(&[0.9, 0.0, 0.0]) - 0.1).abs() < 1e-12 && (pts.distance(&[0.2, 0.0, 0.0]) - 0.2).abs() < 1e-12);
    }

    #[test]
    fn trimmed_mean_drops_the_largest_tenth() {
        let mut v: Vec<f64> = (1..=9).map(|x| x as f64).collect();
        v.push(1e6);
        assert_eq!(trimmed_mean(&v, 0.1), 5.0);
        assert_eq!(trimmed_mean(&v[..9], 0.1), 5.0); // floor(0.9) = 0 dropped
        assert_eq!(trimmed_mean(&[2.0], 0.5), 2.0);
        assert!(trimmed_mean(&[], 0.1).is_nan());
    }

    #[test]
    fn similarity_inverse_round_trips() {
        let t = Similarity { rotation: axis_angle([0.3, -1.0, 0.2], 1.1), translation: [0.1, -0.2, 0.9], scale: 0.37 };
        let id = t.inverse().compose(&t);
        let p = [0.3, 0.4, -0.5];
        let q = id.apply(&p);
        assert!(dist2(&p, &q) < 1e-24);
    }

    /// A box seen by one camera: points sampled from its surface at the true pose,
    /// 1 mm noise, 5 % gross outliers. The true pose must score at noise level and
    /// beat perturbed ones; the trimming must absorb the outliers.
    #[test]
    fn correct_pose_beats_perturbed_poses() {
        let mesh = cuboid([0.5, 0.3, 0.15]); // canonical frame, longest side 1
        let truth = Similarity { rotation: axis_angle([0.2, 1.0, -0.4], 0.7), translation: [0.05, -0.02, 0.8], scale: 0.12 };
        let mut rng = SeededRng::new(11);
        let on_surface = truth.apply_all(&mesh.sample_surface(3000, 2));
        let mut pts = noisy(&on_surface, 0.001, &mut rng);
        for _ in 0..150 {
            pts.push([
                truth.translation[0] + 0.3 * (rng.uniform() - 0.5),
                truth.translation[1] + 0.3 * (rng.uniform() - 0.5),
                truth.translation[2] + 0.3 * (rng.uniform() - 0.5),
            ]);
        }
        let view = ViewPoints { points: pts, to_anchor: Similarity::identity(), depth: None };
        let surface = Surface::new(mesh, 20_000, 3).unwrap();
        let opts = AlignOptions::default();
        let good = view_score(&surface, &truth, &view, &opts);
        // E|N(0, σ)| = 0.8σ along the normal; the trimmed tail removes the outliers.
        assert!(good < 0.0012, "true pose scores {good} m");
        let untrimmed = view_score(&surface, &truth, &view, &AlignOptions { trim: 0.0, ..opts });
        assert!(untrimmed > 2.0 * good, "outliers must matter without trimming: {untrimmed} vs {good}");
        // 10° about the box's own vertical axis (through its centre).
        let rot_about_centre =
            truth.compose(&Similarity { rotation: axis_angle([0.0, 0.0, 1.0], 10f64.to_radians()), translation: [0.0; 3], scale: 1.0 });
        let shifted = Similarity { translation: [truth.translation[0] + 0.01, truth.translation[1], truth.translation[2]], ..truth };
        let bigger = Similarity { scale: truth.scale * 1.15, ..truth };
        let cands = [shifted, truth, rot_about_centre, bigger];
        let scores: Vec<CandidateScore> =
            cands.iter().map(|c| score_candidate(&surface, c, 0, std::slice::from_ref(&view), &opts)).collect();
        println!(
            "true {:.3} mm (untrimmed {:.3} mm); shifted 1 cm, rotated 10°, scaled 1.15: {:?} mm",
            good * 1e3,
            untrimmed * 1e3,
            [0, 2, 3].map(|i| (scores[i].single() * 1e4).round() / 10.0)
        );
        for (i, s) in scores.iter().enumerate() {
            if i != 1 {
                assert!(s.single() > good + 0.001, "candidate {i}: {} vs true {good}", s.single());
            }
        }
        for m in [SelectMethod::First, SelectMethod::Single, SelectMethod::Cross] {
            assert_eq!(select_best(m, &scores), Some(1), "{m:?}");
        }
    }

    /// Two cameras; view 2 sees only the top face of the box, view 1 a side
    /// face. Candidate A (view 2's prediction) is the box flipped about an axis
    /// in its top face: perfect in view 2, wrong in view 1. Candidate B (view
    /// 1's prediction) is the true pose 2 mm off. `single` is fooled by A,
    /// `cross` picks B, `first` takes view 1's candidate.
    #[test]
    fn cross_view_scoring_rejects_a_pose_right_only_in_its_own_view() {
        let h = [0.5, 0.3, 0.15];
        let mesh = cuboid(h);
        let truth = Similarity { rotation: axis_angle([0.0, 1.0, 0.0], 0.3), translation: [0.0, 0.02, 0.7], scale: 0.1 };
        // Camera 2: rotated 70° about y and shifted; T_c1_c2 maps camera-2 points to camera 1.
        let t_c1_c2 = Similarity { rotation: axis_angle([0.1, 1.0, 0.0], 70f64.to_radians()), translation: [-0.5, 0.0, 0.3], scale: 1.0 };
        let t_c2_c1 = t_c1_c2.inverse();
        let mut rng = SeededRng::new(3);
        let face = |axis: usize, sign: f64, n: usize, rng: &mut SeededRng| -> Vec<P3> {
            (0..n)
                .map(|_| {
                    let mut p: P3 = std::array::from_fn(|a| h[a] * (2.0 * rng.uniform() - 1.0));
                    p[axis] = sign * h[axis];
                    p
                })
                .collect()
        };
        let side = truth.apply_all(&face(0, 1.0, 1500, &mut rng)); // camera 1 sees +x
        let top = t_c2_c1.apply_all(&truth.apply_all(&face(2, 1.0, 1500, &mut rng))); // camera 2 sees +z
        let views = [
            ViewPoints { points: noisy(&side, 0.0005, &mut rng), to_anchor: Similarity::identity(), depth: None },
            ViewPoints { points: noisy(&top, 0.0005, &mut rng), to_anchor: t_c1_c2, depth: None },
        ];
        // A: rotate 180° about the canonical x axis through (0, 0, h_z): (x, y, z) ↦ (x, −y, 2h_z − z).
        let flip =
            Similarity { rotation: axis_angle([1.0, 0.0, 0.0], std::f64::consts::PI), translation: [0.0, 0.0, 2.0 * h[2]], scale: 1.0 };
        let a = truth.compose(&flip);
        let b = Similarity { translation: [truth.translation[0] + 0.002, truth.translation[1], truth.translation[2]], ..truth };
        let surface = Surface::new(mesh, 20_000, 1).unwrap();
        let opts = AlignOptions::default();
        let scores = vec![score_candidate(&surface, &b, 0, &views, &opts), score_candidate(&surface, &a, 1, &views, &opts)];
        let (sb, sa) = (&scores[0], &scores[1]);
        println!("A per view {:?} mm, B per view {:?} mm", sa.per_view_m.map_mm(), sb.per_view_m.map_mm());
        assert!(sa.single() < 0.0006, "A fits view 2: {}", sa.single());
        assert!(sa.per_view_m[0] > 0.005, "A is wrong in view 1: {}", sa.per_view_m[0]);
        assert!(sb.single() > sa.single() + 0.001 && sb.single() < 0.0025, "B in view 1: {}", sb.single());
        assert!(sb.cross() < sa.cross(), "{} vs {}", sb.cross(), sa.cross());
        assert_eq!(select_best(SelectMethod::Single, &scores), Some(1));
        assert_eq!(select_best(SelectMethod::Cross, &scores), Some(0));
        assert_eq!(select_best(SelectMethod::First, &scores), Some(0));
        // Without the view-1 candidate, `first` has nothing to choose.
        assert_eq!(select_best(SelectMethod::First, &scores[1..]), None);
    }

    #[test]
    fn spread_of_known_poses() {
        let z5 = axis_angle([0.0, 0.0, 1.0], 5f64.to_radians());
        let zm5 = axis_angle([0.0, 0.0, 1.0], -5f64.to_radians());
        let poses = [
            Similarity { rotation: z5, translation: [0.01, 0.0, 1.0], scale: 0.9 },
            Similarity { rotation: zm5, translation: [-0.01, 0.0, 1.0], scale: 1.1 },
        ];
        let s = pose_spread(&poses).unwrap();
        // Two values ±a about the mean: sqrt(2a²/1) = a·√2.
        assert!((s.translation_sd_mm - 10.0 * 2f64.sqrt()).abs() < 1e-9, "{s:?}");
        assert!((s.rotation_sd_deg - 5.0 * 2f64.sqrt()).abs() < 1e-6, "{s:?}");
        assert!((s.scale_sd_rel - 0.1 * 2f64.sqrt()).abs() < 1e-9, "{s:?}");
        assert!(pose_spread(&poses[..1]).is_none());
        // Identical poses: zero spread.
        let z = pose_spread(&[poses[0], poses[0], poses[0]]).unwrap();
        assert!(z.translation_sd_mm < 1e-9 && z.rotation_sd_deg < 1e-4 && z.scale_sd_rel < 1e-12, "{z:?}");
    }

    #[test]
    fn rel_pose_parsing() {
        let t = parse_rel_pose("0,-1,0,0.1, 1,0,0,0.2, 0,0,1,0.3, 0,0,0,1").unwrap();
        assert_eq!(t.translation, [0.1, 0.2, 0.3]);
        assert_eq!(t.apply(&[1.0, 0.0, 0.0]), [0.1, 1.2, 0.3]);
        assert!(parse_rel_pose("1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1").is_ok());
        for bad in [
            "1,2,3",
            "2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1",
            "1,0,0,0, 0,1,0,0, 0,0,-1,0, 0,0,0,1",
            "1,0,0,0, 0,1,0,0, 0,0,1,0, 1,0,0,1",
            "a b",
        ] {
            let e = parse_rel_pose(bad).unwrap_err().to_string();
            assert!(e.contains("rel-pose") || e.contains("T_c1_c2"), "{bad}: {e}");
        }
        let dir = crate::util::testing::tmp("relpose");
        let f = dir.join("rel.json");
        std::fs::write(&f, r#"{"T_c1_c2": [[1,0,0,0.5],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#).unwrap();
        assert_eq!(parse_rel_pose(f.to_str().unwrap()).unwrap().translation, [0.5, 0.0, 0.0]);
        std::fs::write(&f, r#"{"T": 1}"#).unwrap();
        let e = parse_rel_pose(f.to_str().unwrap()).unwrap_err().to_string();
        assert!(e.contains("rel.json") && e.contains("T_c1_c2"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}
