//! The options of `recon scene` a user sets (flags, Python keywords, JSON), defined once:
//! their names, defaults, help text and checks.
//!
//! [`SceneOptions`] is flat, one name per setting at every layer: the CLI flattens it
//! (`--plane-threshold-mm`), Python and JSON take the same names with `_`. The inputs
//! (which scene, frame, output folder, variations) are not options: each front end reads
//! them its own way. [`SceneOptions::settings`] derives what [`crate::build_scene`] runs with.

use crate::collision::{CollisionMethod, VhacdOptions};
use crate::scene::SceneSettings;
use recon_core::engine::{check_texture_size, options_from_json, MeshColour, OptionError, DEFAULT_TEXTURE_SIZE};
use recon_core::geometry::PlaneFitOptions;
use serde::{Deserialize, Serialize};

/// The options of `recon scene` and Python's `recon_rgbd.scene`. The field docs are the CLI's
/// `--help` text.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct SceneOptions {
    /// Plane inlier distance for the support-plane fit (mm).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.plane_threshold_mm))]
    pub plane_threshold_mm: f64,
    /// Collision geometry of each object.
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = SceneOptions::DEFAULT.collision))]
    pub collision: CollisionMethod,
    /// VHACD voxel resolution (longest axis).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.vhacd_resolution))]
    pub vhacd_resolution: u32,
    /// VHACD maximum concavity per part.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.vhacd_concavity))]
    pub vhacd_concavity: f32,
    /// VHACD maximum number of convex parts per object.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.vhacd_max_hulls))]
    pub vhacd_max_hulls: u32,
    /// Primitive fit: accepted excess volume over the mesh (fraction).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.primitive_volume_tolerance))]
    pub primitive_volume_tolerance: f64,
    /// Simulated settling time limit (s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.settle_time))]
    pub settle_time: f64,
    /// Bound on the depenetration speed (m/s).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.max_corrective_velocity))]
    pub max_corrective_velocity: f64,
    /// Flag objects that moved more than this while settling (mm).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.flag_mm))]
    pub flag_mm: f64,
    /// Flag objects that rotated more than this while settling (degrees).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.flag_deg))]
    pub flag_deg: f64,
    /// Seed of the plane fit, the collision builders and the variations.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.seed))]
    pub seed: u64,
    /// How a mesh with vertex colours (a `recon infer` mesh.ply) carries them into the
    /// simulator files: a UV atlas and a texture baked from the colours (`texture`: OBJ +
    /// MTL + PNG, MJCF `<texture>`/`<material>`, USD `UsdPreviewSurface`), or not at all
    /// (`vertex`: the material's flat colour, the files as before textures existed).
    #[cfg_attr(feature = "clap", arg(long, value_enum, default_value_t = SceneOptions::DEFAULT.colour))]
    pub colour: MeshColour,
    /// Side of a baked texture, texels (16 to 8192), with `--colour texture`.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = SceneOptions::DEFAULT.texture_size))]
    pub texture_size: u32,
}

impl SceneOptions {
    /// The defaults, as a constant so the CLI's `[default: …]` is read from here.
    pub const DEFAULT: SceneOptions = SceneOptions {
        plane_threshold_mm: 10.0,
        collision: CollisionMethod::Convex,
        vhacd_resolution: 64,
        vhacd_concavity: 0.01,
        vhacd_max_hulls: 16,
        primitive_volume_tolerance: 0.05,
        settle_time: 5.0,
        max_corrective_velocity: 0.05,
        flag_mm: 10.0,
        flag_deg: 10.0,
        seed: 0,
        colour: MeshColour::Texture,
        texture_size: DEFAULT_TEXTURE_SIZE,
    };

    /// The option names, in `--help` order (the JSON and Python keyword names).
    pub const NAMES: [&'static str; 13] = [
        "plane_threshold_mm",
        "collision",
        "vhacd_resolution",
        "vhacd_concavity",
        "vhacd_max_hulls",
        "primitive_volume_tolerance",
        "settle_time",
        "max_corrective_velocity",
        "flag_mm",
        "flag_deg",
        "seed",
        "colour",
        "texture_size",
    ];

    /// Checks every option; the first one out of range is named in the error.
    pub fn validate(&self) -> Result<(), OptionError> {
        let positive = |name: &str, v: f64| if v > 0.0 && v.is_finite() { Ok(()) } else { Err(OptionError::new(name, "> 0", v)) };
        positive("plane_threshold_mm", self.plane_threshold_mm)?;
        if self.vhacd_resolution == 0 {
            return Err(OptionError::new("vhacd_resolution", "at least 1", self.vhacd_resolution));
        }
        if !(self.vhacd_concavity >= 0.0 && self.vhacd_concavity.is_finite()) {
            return Err(OptionError::new("vhacd_concavity", ">= 0", self.vhacd_concavity));
        }
        if self.vhacd_max_hulls == 0 {
            return Err(OptionError::new("vhacd_max_hulls", "at least 1", self.vhacd_max_hulls));
        }
        if !(self.primitive_volume_tolerance >= 0.0 && self.primitive_volume_tolerance.is_finite()) {
            return Err(OptionError::new("primitive_volume_tolerance", ">= 0", self.primitive_volume_tolerance));
        }
        positive("settle_time", self.settle_time)?;
        positive("max_corrective_velocity", self.max_corrective_velocity)?;
        positive("flag_mm", self.flag_mm)?;
        positive("flag_deg", self.flag_deg)?;
        check_texture_size("texture_size", self.texture_size)
    }

    /// Options from JSON (an object of option names; absent ones take their defaults),
    /// checked. An unknown name is an error listing the valid ones.
    pub fn from_json(v: serde_json::Value) -> Result<Self, OptionError> {
        let o: SceneOptions = options_from_json(v, &Self::NAMES)?;
        o.validate()?;
        Ok(o)
    }

    /// Checked, the settings [`crate::build_scene`] runs with.
    pub fn settings(&self) -> Result<SceneSettings, OptionError> {
        self.validate()?;
        let mut s = SceneSettings { collision: self.collision, colour: self.colour, texture_size: self.texture_size, ..Default::default() };
        s.collision_opts.vhacd = VhacdOptions {
            resolution: self.vhacd_resolution,
            concavity: self.vhacd_concavity,
            max_convex_hulls: self.vhacd_max_hulls,
            ..Default::default()
        };
        s.collision_opts.primitive.volume_tolerance = self.primitive_volume_tolerance;
        s.collision_opts.seed = self.seed;
        s.settle.max_time_s = self.settle_time;
        s.settle.max_corrective_velocity_m_s = self.max_corrective_velocity;
        s.settle.flag_displacement_m = self.flag_mm * 1e-3;
        s.settle.flag_rotation_deg = self.flag_deg;
        Ok(s)
    }

    /// The support-plane fit these options ask for.
    pub fn plane_fit(&self) -> PlaneFitOptions {
        PlaneFitOptions { threshold_m: self.plane_threshold_mm * 1e-3, seed: self.seed, ..Default::default() }
    }
}

impl Default for SceneOptions {
    fn default() -> Self {
        Self::DEFAULT
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_the_serialised_fields_in_order() {
        let v = serde_json::to_value(SceneOptions::default()).unwrap();
        let keys: Vec<&str> = v.as_object().unwrap().keys().map(String::as_str).collect();
        let mut names = SceneOptions::NAMES.to_vec();
        names.sort_unstable();
        let mut keys = keys;
        keys.sort_unstable();
        assert_eq!(keys, names);
    }

    #[test]
    fn defaults_give_the_library_defaults() {
        // The flags' defaults are the builders' own defaults: a scene built with default
        // options is the one `build_scene` gives with default settings.
        let s = SceneOptions::default().settings().unwrap();
        let d = SceneSettings::default();
        assert_eq!(s.collision, d.collision);
        assert_eq!((s.colour, s.texture_size), (d.colour, d.texture_size));
        assert_eq!(s.collision_opts.vhacd, d.collision_opts.vhacd);
        assert_eq!(s.collision_opts.primitive.volume_tolerance, d.collision_opts.primitive.volume_tolerance);
        assert_eq!(s.collision_opts.seed, d.collision_opts.seed);
        assert_eq!(
            (s.settle.max_time_s, s.settle.max_corrective_velocity_m_s, s.settle.flag_displacement_m, s.settle.flag_rotation_deg),
            (d.settle.max_time_s, d.settle.max_corrective_velocity_m_s, d.settle.flag_displacement_m, d.settle.flag_rotation_deg)
        );
        assert_eq!(SceneOptions::default().plane_fit().threshold_m, PlaneFitOptions::default().threshold_m);
    }

    #[test]
    fn bad_options_are_named() {
        let e = SceneOptions::from_json(serde_json::json!({"settle_time": 0.0})).unwrap_err();
        assert_eq!(e.option(), "settle_time");
        assert!(e.to_string().contains("--settle-time") && e.to_string().contains("> 0"), "{e}");
        let e = SceneOptions::from_json(serde_json::json!({"collison": "hull"})).unwrap_err();
        assert!(e.to_string().contains("collison") && e.to_string().contains("collision"), "{e}");
        let e = SceneOptions::from_json(serde_json::json!({"collision": "mesh"})).unwrap_err();
        assert_eq!(e.option(), "collision");
        let o = SceneOptions::from_json(serde_json::json!({"collision": "hull", "seed": 3})).unwrap();
        assert_eq!((o.collision, o.seed), (CollisionMethod::Hull, 3));
    }
}
