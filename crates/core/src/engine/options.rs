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
}

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
        fusion: Fusion::Multidiffusion,
        slat_fusion: SlatFusion::None,
    };

    /// The option names, in `--help` order (the JSON and Python keyword names).
    pub const NAMES: [&'static str; 15] = [
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
        "fusion",
        "slat_fusion",
    ];

    /// Checks every option; the first one out of range is named in the error.
    pub fn validate(&self) -> Result<(), OptionError> {
        if self.samples == 0 {
            return Err(OptionError::new("samples", "at least 1", self.samples));
        }
        if !(0.0..1.0).contains(&self.min_component_area) {
            return Err(OptionError::new("min_component_area", "in [0, 1)", self.min_component_area));
        }
        Ok(())
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
        };
        let s = o.settings().unwrap();
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
}
