//! Pose-fit settings: how candidates are scored and refined.

/// Scoring settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AlignOptions {
    /// Fraction of the largest distances dropped (RecGen: 0.1).
    pub trim: f64,
    /// Surface samples per mesh.
    pub surface_samples: usize,
    /// Observed points used per view (a deterministic stride subset above this).
    pub max_points: usize,
    /// Seed of the surface sampling.
    pub seed: u64,
    /// Weight of the free-space term (`crate::engine::pose_fit::refine`) in a view's score;
    /// 0 gives RecGen's one-sided score.
    pub free_space_weight: f64,
    /// Depth noise allowance of the free-space test (metres).
    pub free_space_margin_m: f64,
    /// Largest violation one sample can contribute (metres).
    pub free_space_cap_m: f64,
    /// Refine each candidate's scale and translation against the depth
    /// before scoring ([`crate::engine::pose_fit::refine::refine_pose`]).
    pub refine: bool,
    /// Points per view and surface samples used inside the refinement.
    pub refine_points: usize,
    /// Objective evaluations per refinement.
    pub refine_evals: usize,
    /// Also fit a per-axis stretch of the object frame (the shape's proportions),
    /// not only its uniform scale ([`crate::engine::pose_fit::refine::refine_pose`]).
    pub refine_stretch: bool,
    /// Weight of the refinement's pull towards the predicted scale:
    /// `prior · s · Σ (log scale change)²` metres (`s` the object's scale), so
    /// that a direction the depth does not constrain (behind an occluder, along
    /// the rays) keeps the model's estimate instead of drifting.
    pub refine_prior: f64,
}

/// Surface samples used for the free-space term of a full score.
pub const FREE_SPACE_SAMPLES: usize = 5000;

impl Default for AlignOptions {
    fn default() -> Self {
        AlignOptions {
            trim: 0.1,
            surface_samples: 20_000,
            max_points: 20_000,
            seed: 0,
            free_space_weight: 0.0,
            free_space_margin_m: 0.006,
            free_space_cap_m: 0.05,
            refine: false,
            refine_points: 1500,
            refine_evals: 160,
            refine_stretch: false,
            refine_prior: 0.0,
        }
    }
}

impl AlignOptions {
    /// RecGen's score (one-sided, no refinement).
    pub fn recgen() -> Self {
        Self::default()
    }

    /// The depth-consistent score with refinement (`crate::engine::pose_fit::refine`).
    pub fn depth() -> Self {
        // The prior weight was chosen on held-out scenes (README §Evaluation): 0.03 shrinks
        // the growth behind occluders without holding back fits the depth does constrain.
        AlignOptions { free_space_weight: 1.0, refine: true, refine_prior: 0.03, ..Self::default() }
    }
}

/// How each predicted pose is checked against the measured depth (`--pose-fit`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum PoseFit {
    /// Refine scale and translation against the depth and add the free-space term to the score.
    #[default]
    Depth,
    /// `depth`, plus a per-axis stretch of the object frame (proportions; can flatten along the rays).
    DepthStretch,
    /// The paper's one-sided point-to-mesh score, no refinement.
    Recgen,
}

impl PoseFit {
    /// The alignment settings this mode stands for.
    pub fn options(self) -> AlignOptions {
        match self {
            PoseFit::Recgen => AlignOptions::recgen(),
            PoseFit::Depth => AlignOptions::depth(),
            PoseFit::DepthStretch => AlignOptions { refine_stretch: true, refine_evals: 320, refine_prior: 0.1, ..AlignOptions::depth() },
        }
    }
}
