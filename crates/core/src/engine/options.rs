//! The per-frame options a user sets (`recon infer`'s flags, `Engine.reconstruct`'s
//! keywords, JSON), defined once: their names, defaults, help text and checks.
//!
//! [`InferOptions`] holds exactly the user-facing settings, flat, one name per setting at
//! every layer: the CLI flattens it (`--min-component-area`), Python and JSON take the same
//! names with `_` (`min_component_area`). `InferOptions::settings` (beside the engine, in
//! `engine::infer`) checks it and derives the engine's internal settings (sampler,
//! alignment and mesh settings).

use crate::engine::pose_fit::{PoseFit, SelectMethod};
use crate::engine::shape_fit::{MeshFrom, ShapeFit};
use crate::model::sampler::{Fusion, SlatFusion};
use serde::{Deserialize, Serialize};
use std::num::NonZeroUsize;

/// Default face budget of an output mesh.
pub const DEFAULT_MAX_FACES: usize = 200_000;

/// Default Taubin smoothing iterations of an output mesh.
pub const DEFAULT_SMOOTH_ITERATIONS: usize = 0;

/// Objects reconstructed at once by default: one. On 2 cores the model's
/// kernels already keep both busy, so two objects at once save no wall time
/// and cost memory (docs/performance.md).
pub const DEFAULT_PARALLEL_OBJECTS: NonZeroUsize = NonZeroUsize::MIN;

/// Default most objects of a frame the model runs on ([`InferOptions::max_objects`]).
pub const DEFAULT_MAX_OBJECTS: NonZeroUsize = match NonZeroUsize::new(256) {
    Some(n) => n,
    None => NonZeroUsize::MIN,
};

/// The per-frame options of `recon infer`, `recon eval --method recgen` and Python's
/// `Engine.reconstruct`. The field docs are the CLI's `--help` text.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct InferOptions {
    /// Model seed: sample k of an object uses seed + k (also seeds random weights).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.seed))]
    pub seed: u64,
    /// Samples per object (seeds seed, seed+1, …): the best pose is kept and the spread of
    /// the per-sample poses reported as uncertainty.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.samples))]
    pub samples: usize,
    /// Pose selection among views and samples (score: trimmed mean, top 10 % dropped, of
    /// observed-point-to-mesh distances, metres).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = InferOptions::DEFAULT.select))]
    pub select: SelectMethod,
    /// How each predicted pose is checked against the measured depth.
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = InferOptions::DEFAULT.pose_fit))]
    pub pose_fit: PoseFit,
    /// Observation-guided structure: fit the stage-1 occupancy to the depth (carve observed
    /// free space, fill the observed surface, keep the outer shell) before stage 2.
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = InferOptions::DEFAULT.shape_fit))]
    pub shape_fit: ShapeFit,
    /// With the shape fit: the mesh is the fitted occupancy's closed, smoothed surface
    /// coloured from the observed points (`fitted`), or the stage-2 decoder's surface (`decoder`).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = InferOptions::DEFAULT.mesh_from))]
    pub mesh_from: MeshFrom,
    /// Sampler steps for both stages (default: the config's).
    #[cfg_attr(feature = "clap", arg(long))]
    pub steps: Option<usize>,
    /// Classifier-free guidance strength for both stages (default: the config's).
    #[cfg_attr(feature = "clap", arg(long))]
    pub cfg: Option<f64>,
    /// Mesh face budget: larger meshes are decimated (quadric edge collapse); 0 = no limit.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.max_faces))]
    pub max_faces: usize,
    /// Floater removal: mesh components with less than this fraction of the total area are
    /// dropped (the largest is always kept); 0 keeps every component.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.min_component_area))]
    pub min_component_area: f64,
    /// Taubin smoothing iterations on the decoded mesh (after floater removal, before
    /// decimation); 0 keeps the decoder's surface.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.smooth))]
    pub smooth: usize,
    /// Objects of a frame reconstructed at once (threads sharing the loaded model and the
    /// kernels' threads; 1: one after another). Results are the same for any value; more
    /// than 1 pays only with cores the model leaves idle, and costs memory per object.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.parallel_objects))]
    pub parallel_objects: NonZeroUsize,
    /// Most objects of a frame the model runs on: masks that pass the mask checks (enough
    /// pixels with valid depth after erosion; smaller masks are skipped at the cost of their
    /// pixels). A frame with more is refused, naming the count, before any is reconstructed.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.max_objects))]
    pub max_objects: NonZeroUsize,
    /// Point-map normalisation (RecGen's `quantile_drop_threshold`): the fraction of the
    /// object's points dropped at each end of their distances from the median when sizing
    /// the unit cube; in [0, 0.5).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.quantile_drop_threshold))]
    pub quantile_drop_threshold: f64,
    /// The normalised point map is clamped to `LOW,HIGH` (RecGen's `clamp_range`; the
    /// object's median sits at 0.5).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.clamp_range, allow_hyphen_values = true))]
    pub clamp_range: ClampRange,
    /// Erode each object mask before everything else, trimming the mixed object/background
    /// depth at its silhouette (RecGen's `mask_erosion_enabled`).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.mask_erosion_enabled, action = clap::ArgAction::Set))]
    pub mask_erosion_enabled: bool,
    /// Side of the square erosion kernel, pixels, 1 to 255 (RecGen's
    /// `mask_erosion_params["kernel_size"]`).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.mask_erosion_kernel_size))]
    pub mask_erosion_kernel_size: usize,
    /// Erosion passes, 0 (none) to 100 (RecGen's `mask_erosion_params["iterations"]`).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.mask_erosion_iterations))]
    pub mask_erosion_iterations: usize,
    /// Condition both stages on the normalised point map (RecGen's `use_pointmap`); off,
    /// the model sees only the image and the mask (the depth still places the object).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.use_pointmap, action = clap::ArgAction::Set))]
    pub use_pointmap: bool,
    /// With more views than the model takes at once (a two-view model and several
    /// --view): how stage 1 fuses the (anchor, view i) pairs at every step: the mean of
    /// their guided velocities (multidiffusion, one model pass per pair and step) or one
    /// pair per step in turn (stochastic, no extra cost).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = InferOptions::DEFAULT.fusion))]
    pub fusion: Fusion,
    /// With more views than the model takes at once: stage 2 on the anchor and the first
    /// other view (none), or on every pair fused as --fusion does (each pair past the first
    /// then costs a stage-1 run for its pose).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = InferOptions::DEFAULT.slat_fusion))]
    pub slat_fusion: SlatFusion,
    /// Post-hoc colour calibration (RecGen's `posthoc_color`): render the predicted
    /// Gaussians into the input view, fit a colour transform to the photo on the overlap
    /// of mask and render, and apply it to the Gaussians (and to the mesh when its colours
    /// come from the model) when the fit passes the quality gates; the transform and its
    /// statistics go to posthoc_color.json.
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = InferOptions::DEFAULT.posthoc_color))]
    pub posthoc_color: PosthocColor,
    /// How the output mesh carries its colour: a UV atlas and a texture baked from the
    /// input views' photos where they see the surface, else from the vertex colours
    /// (`texture`: mesh.glb gets TEXCOORD_0 and an embedded PNG), or vertex colours alone
    /// (`vertex`: the files as before textures existed).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = InferOptions::DEFAULT.colour))]
    pub colour: MeshColour,
    /// Side of the square baked texture, texels (16 to 8192), with `--colour texture`.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = InferOptions::DEFAULT.texture_size))]
    pub texture_size: u32,
}

/// Default side of a baked texture, texels.
pub const DEFAULT_TEXTURE_SIZE: u32 = 1024;

/// Largest accepted texture side, texels.
pub const MAX_TEXTURE_SIZE: u32 = 8192;

/// How an output mesh carries its colour (`recon infer --colour`, `recon scene --colour`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum MeshColour {
    /// A UV atlas and a baked texture (PNG), vertex colours where no view sees the surface.
    #[default]
    Texture,
    /// Per-vertex colours only.
    Vertex,
}

impl std::fmt::Display for MeshColour {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            MeshColour::Texture => "texture",
            MeshColour::Vertex => "vertex",
        })
    }
}

/// Checks a texture side: `option` names it in the error.
pub fn check_texture_size(option: &str, size: u32) -> Result<(), OptionError> {
    if (16..=MAX_TEXTURE_SIZE).contains(&size) {
        Ok(())
    } else {
        Err(OptionError::new(option, &format!("in 16..={MAX_TEXTURE_SIZE}"), size))
    }
}

/// Which colour transform the post-hoc calibration fits (`engine::posthoc_color`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "snake_case")]
pub enum PosthocColor {
    /// No calibration.
    #[default]
    None,
    /// One luminance gamma for all channels (hue preserving).
    Gamma,
    /// A gain and an offset per channel.
    Affine,
    /// The gamma, then a per-channel affine map.
    #[cfg_attr(feature = "clap", value(name = "gamma_affine", alias = "gamma-affine"))]
    GammaAffine,
}

impl std::fmt::Display for PosthocColor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            PosthocColor::None => "none",
            PosthocColor::Gamma => "gamma",
            PosthocColor::Affine => "affine",
            PosthocColor::GammaAffine => "gamma_affine",
        })
    }
}

/// The range the normalised point map is clamped to (`low ≤ x ≤ high` per coordinate):
/// `[low, high]` in JSON and Python, `LOW,HIGH` on the command line.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(from = "[f64; 2]", into = "[f64; 2]")]
pub struct ClampRange {
    /// Lower bound.
    pub low: f64,
    /// Upper bound.
    pub high: f64,
}

impl From<[f64; 2]> for ClampRange {
    fn from([low, high]: [f64; 2]) -> Self {
        ClampRange { low, high }
    }
}

impl From<ClampRange> for [f64; 2] {
    fn from(c: ClampRange) -> Self {
        [c.low, c.high]
    }
}

impl std::fmt::Display for ClampRange {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{},{}", self.low, self.high)
    }
}

impl std::str::FromStr for ClampRange {
    type Err = String;

    /// `LOW,HIGH` (brackets or parentheses around it, spaces, are accepted).
    fn from_str(s: &str) -> Result<Self, String> {
        let inner = s.trim().trim_start_matches(['[', '(']).trim_end_matches([']', ')']);
        let parts: Vec<&str> = inner.split(',').map(str::trim).collect();
        let bad = || format!("`{s}`: expected two numbers LOW,HIGH (e.g. -2,3)");
        match parts.as_slice() {
            [lo, hi] => Ok(ClampRange { low: lo.parse().map_err(|_| bad())?, high: hi.parse().map_err(|_| bad())? }),
            _ => Err(bad()),
        }
    }
}

/// Largest accepted `mask_erosion_kernel_size`: beyond it every object of a VGA frame
/// erodes away anyway.
pub const MAX_EROSION_KERNEL: usize = 255;

/// Largest accepted `mask_erosion_iterations` (each pass costs a pass over the frame).
pub const MAX_EROSION_ITERATIONS: usize = 100;

impl InferOptions {
    /// The defaults, as a constant so the CLI's `[default: …]` is read from here.
    pub const DEFAULT: InferOptions = InferOptions {
        seed: 42,
        samples: 1,
        select: SelectMethod::Cross,
        pose_fit: PoseFit::Depth,
        shape_fit: ShapeFit::Depth,
        mesh_from: MeshFrom::Fitted,
        steps: None,
        cfg: None,
        max_faces: DEFAULT_MAX_FACES,
        min_component_area: 0.02,
        smooth: DEFAULT_SMOOTH_ITERATIONS,
        parallel_objects: DEFAULT_PARALLEL_OBJECTS,
        max_objects: DEFAULT_MAX_OBJECTS,
        // RecGen `inference.generate`'s defaults (also `PrepareOptions::default()`).
        quantile_drop_threshold: 0.05,
        clamp_range: ClampRange { low: -2.0, high: 3.0 },
        mask_erosion_enabled: true,
        mask_erosion_kernel_size: 5,
        mask_erosion_iterations: 1,
        use_pointmap: true,
        fusion: Fusion::Multidiffusion,
        slat_fusion: SlatFusion::None,
        posthoc_color: PosthocColor::None,
        colour: MeshColour::Vertex,
        texture_size: DEFAULT_TEXTURE_SIZE,
    };

    /// The option names, in `--help` order (the JSON and Python keyword names).
    pub const NAMES: [&'static str; 24] = [
        "seed",
        "samples",
        "select",
        "pose_fit",
        "shape_fit",
        "mesh_from",
        "steps",
        "cfg",
        "max_faces",
        "min_component_area",
        "smooth",
        "parallel_objects",
        "max_objects",
        "quantile_drop_threshold",
        "clamp_range",
        "mask_erosion_enabled",
        "mask_erosion_kernel_size",
        "mask_erosion_iterations",
        "use_pointmap",
        "fusion",
        "slat_fusion",
        "posthoc_color",
        "colour",
        "texture_size",
    ];

    /// Checks every option; the first one out of range is named in the error.
    pub fn validate(&self) -> Result<(), OptionError> {
        if self.samples == 0 {
            return Err(OptionError::new("samples", "at least 1", self.samples));
        }
        if !(0.0..1.0).contains(&self.min_component_area) {
            return Err(OptionError::new("min_component_area", "in [0, 1)", self.min_component_area));
        }
        if !(0.0..0.5).contains(&self.quantile_drop_threshold) {
            return Err(OptionError::new("quantile_drop_threshold", "in [0, 0.5)", self.quantile_drop_threshold));
        }
        let ClampRange { low, high } = self.clamp_range;
        // f32 is what the point map holds.
        let finite = [low, high].iter().all(|x| x.is_finite() && x.abs() <= f32::MAX as f64);
        if !(finite && low < high) {
            return Err(OptionError::new("clamp_range", "two finite numbers LOW < HIGH", format!("[{low}, {high}]")));
        }
        if !(1..=MAX_EROSION_KERNEL).contains(&self.mask_erosion_kernel_size) {
            return Err(OptionError::new(
                "mask_erosion_kernel_size",
                &format!("in 1..={MAX_EROSION_KERNEL}"),
                self.mask_erosion_kernel_size,
            ));
        }
        if self.mask_erosion_iterations > MAX_EROSION_ITERATIONS {
            return Err(OptionError::new(
                "mask_erosion_iterations",
                &format!("in 0..={MAX_EROSION_ITERATIONS}"),
                self.mask_erosion_iterations,
            ));
        }
        check_texture_size("texture_size", self.texture_size)
    }

    /// Options from JSON (an object of option names; absent ones take their defaults),
    /// checked. An unknown name is an error listing the valid ones.
    pub fn from_json(v: serde_json::Value) -> Result<Self, OptionError> {
        let o: InferOptions = options_from_json(v, &Self::NAMES)?;
        o.validate()?;
        Ok(o)
    }
}

impl Default for InferOptions {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// A bad option, named.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum OptionError {
    /// A value out of range: which option, what it must be, what it was.
    #[error("{} must be {expected}, got {given}", flag(option))]
    OutOfRange {
        /// The option's name.
        option: String,
        /// What the value must be (`in [0, 1)`).
        expected: String,
        /// The value given, as text.
        given: String,
    },
    /// A name that is no option.
    #[error("unknown option `{option}`; the options are {valid}")]
    Unknown {
        /// The name given.
        option: String,
        /// The valid names, comma-separated.
        valid: String,
    },
    /// A value of the wrong type (`message` says what was expected).
    #[error("{}: {message}", flag(option))]
    Invalid {
        /// The option's name (its path in the JSON).
        option: String,
        /// The deserialiser's message.
        message: String,
    },
}

impl OptionError {
    /// An [`OptionError::OutOfRange`]: `option` must be `expected`, was `given`.
    pub fn new(option: &str, expected: &str, given: impl std::fmt::Display) -> Self {
        OptionError::OutOfRange { option: option.to_string(), expected: expected.to_string(), given: given.to_string() }
    }

    /// The option's name (`min_component_area`).
    pub fn option(&self) -> &str {
        match self {
            OptionError::OutOfRange { option, .. } | OptionError::Unknown { option, .. } | OptionError::Invalid { option, .. } => option,
        }
    }

    /// The message with the option as a keyword (`min_component_area: must be in [0, 1),
    /// got 1.5`), for callers outside the CLI (Python).
    pub fn keyword_message(&self) -> String {
        match self {
            OptionError::OutOfRange { option, expected, given } => format!("{option}: must be {expected}, got {given}"),
            OptionError::Unknown { .. } => self.to_string(),
            OptionError::Invalid { option, message } => format!("{option}: {message}"),
        }
    }
}

/// Options of type `T` from JSON: an object of the option `names` (absent ones take their
/// defaults, through `T`'s `#[serde(default)]`). An unknown name is an error listing the
/// valid ones; a value of the wrong type names its option. Range checks are `T`'s.
pub fn options_from_json<T: serde::de::DeserializeOwned>(v: serde_json::Value, names: &[&str]) -> Result<T, OptionError> {
    if let Some(k) = v.as_object().and_then(|m| m.keys().find(|k| !names.contains(&k.as_str()))) {
        return Err(OptionError::Unknown { option: k.clone(), valid: names.join(", ") });
    }
    serde_path_to_error::deserialize(v)
        .map_err(|e| OptionError::Invalid { option: e.path().to_string(), message: e.into_inner().to_string() })
}

/// `min_component_area` → `--min-component-area`.
pub fn flag(option: &str) -> String {
    format!("--{}", option.replace('_', "-"))
}

impl From<OptionError> for crate::Error {
    fn from(e: OptionError) -> Self {
        crate::Error::config("infer options", e.option(), e.to_string())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_the_serialised_fields_in_order() {
        let v = serde_json::to_value(InferOptions::default()).unwrap();
        let keys: Vec<&str> = v.as_object().unwrap().keys().map(String::as_str).collect();
        let mut names = InferOptions::NAMES.to_vec();
        let mut sorted = keys.clone();
        names.sort();
        sorted.sort();
        assert_eq!(sorted, names);
    }

    #[test]
    fn checks_name_the_option_the_expectation_and_the_value() {
        let e = InferOptions { samples: 0, ..Default::default() }.validate().unwrap_err();
        assert_eq!(e.to_string(), "--samples must be at least 1, got 0");
        assert_eq!(e.keyword_message(), "samples: must be at least 1, got 0");
        let e = InferOptions { min_component_area: 1.5, ..Default::default() }.settings().unwrap_err();
        assert_eq!(e.to_string(), "--min-component-area must be in [0, 1), got 1.5");
        assert!(InferOptions { min_component_area: 0.0, ..Default::default() }.validate().is_ok());
    }

    #[test]
    fn json_takes_the_same_names_and_defaults() {
        let o = InferOptions::from_json(serde_json::json!({"cfg": 3, "pose_fit": "depth-stretch", "steps": null})).unwrap();
        assert_eq!(o, InferOptions { cfg: Some(3.0), pose_fit: PoseFit::DepthStretch, ..Default::default() });
        let o = InferOptions::from_json(serde_json::json!({"fusion": "stochastic", "slat_fusion": "multidiffusion"})).unwrap();
        assert_eq!((o.fusion, o.slat_fusion), (Fusion::Stochastic, SlatFusion::Multidiffusion));
        let e = InferOptions::from_json(serde_json::json!({"fusion": "average"})).unwrap_err();
        assert_eq!(e.option(), "fusion");
        assert_eq!(InferOptions::from_json(serde_json::json!({})).unwrap(), InferOptions::default());
        let e = InferOptions::from_json(serde_json::json!({"sample": 2})).unwrap_err();
        assert!(e.to_string().starts_with("unknown option `sample`; the options are seed, samples,"), "{e}");
        let e = InferOptions::from_json(serde_json::json!({"samples": "two"})).unwrap_err();
        assert!(e.keyword_message().starts_with("samples: invalid type"), "{e:?}");
        let e = InferOptions::from_json(serde_json::json!({"samples": 0})).unwrap_err();
        assert_eq!(e.option(), "samples");
        let e = InferOptions::from_json(serde_json::json!({"max_objects": 0})).unwrap_err();
        assert_eq!(e.option(), "max_objects");
    }

    #[test]
    fn settings_carry_every_option() {
        let o = InferOptions {
            seed: 9,
            samples: 3,
            select: SelectMethod::First,
            pose_fit: PoseFit::Recgen,
            shape_fit: ShapeFit::None,
            mesh_from: MeshFrom::Decoder,
            steps: Some(4),
            cfg: Some(2.5),
            max_faces: 0,
            min_component_area: 0.1,
            smooth: 5,
            parallel_objects: NonZeroUsize::new(2).unwrap(),
            max_objects: NonZeroUsize::new(7).unwrap(),
            fusion: Fusion::Stochastic,
            slat_fusion: SlatFusion::Multidiffusion,
            quantile_drop_threshold: 0.1,
            clamp_range: ClampRange { low: -1.0, high: 1.5 },
            mask_erosion_enabled: true,
            mask_erosion_kernel_size: 3,
            mask_erosion_iterations: 2,
            use_pointmap: false,
            posthoc_color: PosthocColor::GammaAffine,
            colour: MeshColour::Vertex,
            texture_size: 256,
        };
        let s = o.settings().unwrap();
        assert_eq!(s.posthoc_color, PosthocColor::GammaAffine);
        assert_eq!((s.colour, s.texture_size), (MeshColour::Vertex, 256));
        let e = InferOptions::from_json(serde_json::json!({"texture_size": 8})).unwrap_err();
        assert_eq!(e.option(), "texture_size");
        assert_eq!((s.prepare.quantile_drop, s.prepare.clamp), (0.1, Some((-1.0, 1.5))));
        assert_eq!(s.prepare.erosion, Some(crate::dataset::masks::Erosion { kernel: 3, iterations: 2 }));
        assert!(!s.run.use_pointmap);
        let off = InferOptions { mask_erosion_enabled: false, ..o.clone() }.settings().unwrap();
        assert_eq!(off.prepare.erosion, None);
        assert_eq!((s.run.fusion, s.run.slat_fusion), (Fusion::Stochastic, SlatFusion::Multidiffusion));
        assert_eq!((s.run.seed, s.samples, s.select), (9, 3, SelectMethod::First));
        assert_eq!(
            (s.run.ss_steps, s.run.slat_steps, s.run.ss_cfg_strength, s.run.slat_cfg_strength),
            (Some(4), Some(4), Some(2.5), Some(2.5))
        );
        assert_eq!((s.max_faces, s.floater_area_fraction, s.smooth_iterations), (None, 0.1, 5));
        assert_eq!((s.shape_fit, s.mesh_from, s.parallel_objects.get(), s.max_objects.get()), (ShapeFit::None, MeshFrom::Decoder, 2, 7));
        assert!(!s.align.refine);
        let d = InferOptions::default().settings().unwrap();
        assert_eq!((d.max_faces, d.run.seed, d.align.refine), (Some(DEFAULT_MAX_FACES), 42, true));
    }

    /// The preprocessing defaults are RecGen `generate`'s, which were recon's before they
    /// became options: the default settings prepare views exactly as before.
    #[test]
    fn preprocessing_defaults_are_recgens_and_unchanged() {
        let d = InferOptions::default().settings().unwrap();
        let before = crate::geometry::pointmap::PrepareOptions::default();
        assert_eq!((d.prepare.erosion, d.prepare.quantile_drop, d.prepare.clamp), (before.erosion, before.quantile_drop, before.clamp));
        assert_eq!(before.erosion, Some(crate::dataset::masks::Erosion { kernel: 5, iterations: 1 }));
        assert_eq!((before.quantile_drop, before.clamp), (0.05, Some((-2.0, 3.0))));
        assert!(d.run.use_pointmap && crate::engine::RunOptions::default().use_pointmap);
    }

    #[test]
    fn bad_preprocessing_values_name_their_option() {
        let bad = |v: serde_json::Value| InferOptions::from_json(v).unwrap_err();
        let e = bad(serde_json::json!({"quantile_drop_threshold": 0.5}));
        assert_eq!(e.to_string(), "--quantile-drop-threshold must be in [0, 0.5), got 0.5");
        assert_eq!(bad(serde_json::json!({"quantile_drop_threshold": -0.1})).option(), "quantile_drop_threshold");
        let e = bad(serde_json::json!({"clamp_range": [3, -2]}));
        assert_eq!(e.keyword_message(), "clamp_range: must be two finite numbers LOW < HIGH, got [3, -2]");
        assert_eq!(bad(serde_json::json!({"clamp_range": [1, 1]})).option(), "clamp_range");
        assert_eq!(bad(serde_json::json!({"clamp_range": [1e300, 2e300]})).option(), "clamp_range");
        let e = bad(serde_json::json!({"clamp_range": [1, 2, 3]}));
        assert_eq!(e.option(), "clamp_range", "{e}");
        assert_eq!(bad(serde_json::json!({"clamp_range": "-2,3"})).option(), "clamp_range");
        let e = bad(serde_json::json!({"mask_erosion_kernel_size": 0}));
        assert_eq!(e.to_string(), "--mask-erosion-kernel-size must be in 1..=255, got 0");
        assert_eq!(bad(serde_json::json!({"mask_erosion_kernel_size": 256})).option(), "mask_erosion_kernel_size");
        assert_eq!(bad(serde_json::json!({"mask_erosion_iterations": 101})).option(), "mask_erosion_iterations");
        assert_eq!(bad(serde_json::json!({"mask_erosion_enabled": "yes"})).option(), "mask_erosion_enabled");
        assert_eq!(bad(serde_json::json!({"use_pointmap": 1})).option(), "use_pointmap");
        // The good ones: JSON arrays of numbers, iterations 0 (no erosion), kernel 1.
        let o = InferOptions::from_json(
            serde_json::json!({"clamp_range": [-1, 2.5], "mask_erosion_iterations": 0, "mask_erosion_kernel_size": 1}),
        )
        .unwrap();
        assert_eq!(o.clamp_range, ClampRange { low: -1.0, high: 2.5 });
        assert_eq!(serde_json::to_value(o.clamp_range).unwrap(), serde_json::json!([-1.0, 2.5]));
    }

    #[test]
    fn clamp_range_reads_the_command_line_form() {
        let c: ClampRange = "-2,3".parse().unwrap();
        assert_eq!(c, InferOptions::DEFAULT.clamp_range);
        assert_eq!(c.to_string(), "-2,3");
        assert_eq!("[-0.5, 1.5]".parse::<ClampRange>().unwrap(), ClampRange { low: -0.5, high: 1.5 });
        assert_eq!("(0,1)".parse::<ClampRange>().unwrap(), ClampRange { low: 0.0, high: 1.0 });
        for bad in ["", "1", "1,2,3", "a,b", "1;2"] {
            let e = bad.parse::<ClampRange>().unwrap_err();
            assert!(e.contains("LOW,HIGH"), "{bad}: {e}");
        }
    }
}
