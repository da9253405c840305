//! The variations spec (`variations.json`, `"version": 1`): spatial
//! predicates between the scene's objects, distractors and object variants.
//! Typed with serde, so an unknown predicate, category or field is an error
//! that names it. Checks that need only names run in [`VariationSpec::check_names`];
//! the ones that need shapes run in `validate` (mod.rs) before any settling.
//!
//! ```json
//! {
//!   "version": 1,
//!   "frame": "camera",
//!   "predicates": [
//!     { "predicate": "on_top", "a": "mug", "b": "box" },
//!     { "predicate": "left_of", "a": "can", "b": "box" },
//!     { "predicate": "near", "a": "can", "b": "mug", "distance_m": 0.05 },
//!     { "predicate": "inside", "a": "ball", "b": "bowl" }
//!   ],
//!   "distractors": { "count": [1, 3], "categories": ["box", "cylinder"], "scale": [0.6, 1.0] },
//!   "object_variants": { "probability": 0.5, "scale": [0.9, 1.1], "aspect": [0.9, 1.1], "materials": ["plastic", "wood"] }
//! }
//! ```

use crate::materials::MaterialTable;
use recon_core::{Error, Result};
use recon_synth::objects::Kind;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub const SPEC_VERSION: u32 = 1;

/// A spatial relation between two objects, `a` relative to `b`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "predicate", rename_all = "snake_case", deny_unknown_fields)]
pub enum Predicate {
    /// `a` rests on `b`'s top surface (not on the plane).
    OnTop {
        /// The object on top.
        a: String,
        /// The object below.
        b: String,
    },
    /// Directions in the spec's `frame`, centre of mass to centre of mass,
    /// within 45° of the direction and at least 1 cm apart along it.
    LeftOf {
        /// The object placed.
        a: String,
        /// The reference object.
        b: String,
    },
    /// `a` to the right of `b` (see [`Predicate::LeftOf`]).
    RightOf {
        /// The object placed.
        a: String,
        /// The reference object.
        b: String,
    },
    /// `a` in front of `b` (nearer the camera; see [`Predicate::LeftOf`]).
    InFrontOf {
        /// The object placed.
        a: String,
        /// The reference object.
        b: String,
    },
    /// `a` behind `b` (see [`Predicate::LeftOf`]).
    Behind {
        /// The object placed.
        a: String,
        /// The reference object.
        b: String,
    },
    /// Collision geometries at most `distance_m` apart.
    Near {
        /// The object placed.
        a: String,
        /// The reference object.
        b: String,
        /// Largest gap between the collision geometries (metres).
        distance_m: f64,
    },
    /// `a`'s centre of mass over `b`'s cavity and its lowest point below `b`'s rim.
    Inside {
        /// The object inside.
        a: String,
        /// The container.
        b: String,
    },
}

impl Predicate {
    /// Snake-case name, as in the spec file (`on_top`, `left_of`, ...).
    pub fn name(&self) -> &'static str {
        match self {
            Predicate::OnTop { .. } => "on_top",
            Predicate::LeftOf { .. } => "left_of",
            Predicate::RightOf { .. } => "right_of",
            Predicate::InFrontOf { .. } => "in_front_of",
            Predicate::Behind { .. } => "behind",
            Predicate::Near { .. } => "near",
            Predicate::Inside { .. } => "inside",
        }
    }
    /// The two objects `(a, b)`.
    pub fn objects(&self) -> (&str, &str) {
        match self {
            Predicate::OnTop { a, b }
            | Predicate::LeftOf { a, b }
            | Predicate::RightOf { a, b }
            | Predicate::InFrontOf { a, b }
            | Predicate::Behind { a, b }
            | Predicate::Near { a, b, .. }
            | Predicate::Inside { a, b } => (a, b),
        }
    }
    /// `a` is carried by `b` (placed on or in it).
    pub fn is_support(&self) -> bool {
        matches!(self, Predicate::OnTop { .. } | Predicate::Inside { .. })
    }
    /// Unit direction index in the frame (right, behind) and sign, for the directional ones.
    pub fn direction(&self) -> Option<(usize, f64)> {
        match self {
            Predicate::RightOf { .. } => Some((0, 1.0)),
            Predicate::LeftOf { .. } => Some((0, -1.0)),
            Predicate::Behind { .. } => Some((1, 1.0)),
            Predicate::InFrontOf { .. } => Some((1, -1.0)),
            _ => None,
        }
    }
    /// `pred(a, b)` as text.
    pub fn label(&self) -> String {
        let (a, b) = self.objects();
        match self {
            Predicate::Near { distance_m, .. } => format!("near({a}, {b}, {distance_m} m)"),
            _ => format!("{}({a}, {b})", self.name()),
        }
    }
}

/// Frame of the directional predicates, projected onto the support plane.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DirFrame {
    /// Right: the image's x axis; behind: the image's up axis (away from the camera).
    /// Falls back to `world` when the scene has no camera.
    #[default]
    Camera,
    /// Right: world +x; behind: world +y.
    World,
}

/// Procedural library categories (`recon synth`'s objects).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Category {
    /// A rectangular box.
    Box,
    /// A closed cylinder (a can).
    Cylinder,
    /// A bottle: body and cap.
    Bottle,
    /// An open bowl.
    Bowl,
    /// A mug: body and handle.
    Mug,
    /// A sphere.
    Sphere,
    /// A torus.
    Torus,
    /// An L-shaped solid.
    LShape,
}

impl Category {
    /// Every category, in declaration order.
    pub const ALL: [Category; 8] = [
        Category::Box,
        Category::Cylinder,
        Category::Bottle,
        Category::Bowl,
        Category::Mug,
        Category::Sphere,
        Category::Torus,
        Category::LShape,
    ];
    /// The procedural object kind it draws from.
    pub fn kind(self) -> Kind {
        match self {
            Category::Box => Kind::Box,
            Category::Cylinder => Kind::Cylinder,
            Category::Bottle => Kind::Bottle,
            Category::Bowl => Kind::Bowl,
            Category::Mug => Kind::Mug,
            Category::Sphere => Kind::Sphere,
            Category::Torus => Kind::Torus,
            Category::LShape => Kind::LShape,
        }
    }
}

fn default_count() -> [u32; 2] {
    [0, 0]
}
fn default_unit() -> [f64; 2] {
    [1.0, 1.0]
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DistractorSpec {
    /// Inclusive range of the number of distractors per variant.
    #[serde(default = "default_count")]
    pub count: [u32; 2],
    /// Library categories to draw from (default: all).
    #[serde(default)]
    pub categories: Vec<Category>,
    /// Uniform size factor on the library's random size (3–30 cm objects).
    #[serde(default = "default_unit")]
    pub scale: [f64; 2],
    /// Distractors from a folder of the user's meshes, drawn in addition to the library's.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub assets: Option<AssetSpec>,
}

impl Default for DistractorSpec {
    fn default() -> Self {
        Self { count: default_count(), categories: vec![], scale: default_unit(), assets: None }
    }
}

/// Distractors from the user's assets: GLB, OBJ or PLY files under `dir`
/// (see `sim::variations::assets` for the layout and the physics JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AssetSpec {
    /// The asset folder; relative paths are resolved against the spec file's folder.
    pub dir: PathBuf,
    /// Inclusive range of the number of asset distractors per variant.
    #[serde(default = "default_count")]
    pub count: [u32; 2],
    /// Asset categories to draw from (default: all found).
    #[serde(default)]
    pub categories: Vec<String>,
    /// Range of the largest extent (m) an asset is rescaled to; default: its own size.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size_m: Option<[f64; 2]>,
    /// Uniform size factor range, after `size_m`.
    #[serde(default = "default_unit")]
    pub scale: [f64; 2],
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectVariantSpec {
    /// Chance that a scene object is varied in a variant.
    #[serde(default)]
    pub probability: f64,
    /// Uniform scale factor range.
    #[serde(default = "default_unit")]
    pub scale: [f64; 2],
    /// Extra stretch range of the horizontal axes (x and y independently).
    #[serde(default = "default_unit")]
    pub aspect: [f64; 2],
    /// Materials (of the material table) to draw from; empty keeps the object's.
    /// A drawn material brings its density (mass and inertia are recomputed),
    /// friction, restitution and colour.
    #[serde(default)]
    pub materials: Vec<String>,
    /// Colours (linear RGBA in [0, 1]) to draw from; empty: the material's colour.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub colors: Vec<[f64; 4]>,
}

impl Default for ObjectVariantSpec {
    fn default() -> Self {
        Self { probability: 0.0, scale: default_unit(), aspect: default_unit(), materials: vec![], colors: vec![] }
    }
}

fn default_sampled() -> usize {
    2
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Region {
    pub center_m: [f64; 2],
    pub half_extent_m: [f64; 2],
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
/// A variations spec file: predicates, placement region, distractors, object variants.
pub struct VariationSpec {
    /// File format version (1).
    pub version: u32,
    #[serde(default)]
    /// Frame of the directional predicates.
    pub frame: DirFrame,
    /// Held by every variant; when empty, `sampled_predicates` are drawn per variant.
    #[serde(default)]
    pub predicates: Vec<Predicate>,
    #[serde(default = "default_sampled")]
    /// Predicates drawn per variant when `predicates` is empty.
    pub sampled_predicates: usize,
    /// Where objects may be placed on the plane (world frame; default: around the scene's objects).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub region: Option<Region>,
    #[serde(default)]
    /// Distractors added to each variant.
    pub distractors: DistractorSpec,
    #[serde(default)]
    /// Rescaling, stretching and material/colour changes of the scene objects.
    pub object_variants: ObjectVariantSpec,
}

impl Default for VariationSpec {
    fn default() -> Self {
        Self {
            version: SPEC_VERSION,
            frame: DirFrame::Camera,
            predicates: vec![],
            sampled_predicates: default_sampled(),
            region: None,
            distractors: Default::default(),
            object_variants: Default::default(),
        }
    }
}

impl VariationSpec {
    /// Read and check a spec file; the asset folder is resolved against the file's folder.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let mut s = Self::parse(&text, &path.display().to_string())?;
        if let Some(a) = &mut s.distractors.assets {
            if a.dir.is_relative() {
                a.dir = path.parent().unwrap_or(Path::new(".")).join(&a.dir);
            }
        }
        Ok(s)
    }

    /// Parse and check value ranges; errors name the file and the field
    /// (`predicates[2]` for an unknown predicate, with its name).
    pub fn parse(text: &str, file: &str) -> Result<Self> {
        let v: serde_json::Value = serde_json::from_str(text).map_err(|e| Error::config(file, "<root>", format!("invalid JSON: {e}")))?;
        let root = v.as_object().ok_or_else(|| Error::config(file, "<root>", "expected a JSON object"))?;
        match root.get("version").and_then(|x| x.as_u64()) {
            Some(n) if n == SPEC_VERSION as u64 => {}
            _ => {
                return Err(Error::config(file, "version", format!("missing or unsupported; this build reads \"version\": {SPEC_VERSION}")))
            }
        }
        // Predicates one by one, so an error names its index.
        if let Some(ps) = root.get("predicates").and_then(|p| p.as_array()) {
            for (i, p) in ps.iter().enumerate() {
                serde_json::from_value::<Predicate>(p.clone())
                    .map_err(|e| Error::config(file, format!("predicates[{i}]"), e.to_string()))?;
            }
        }
        let s: VariationSpec = serde_json::from_value(v).map_err(|e| Error::config(file, "<root>", e.to_string()))?;
        s.check_values(file)?;
        Ok(s)
    }

    fn check_values(&self, file: &str) -> Result<()> {
        let range = |r: [f64; 2], field: &str, lo: f64, hi: f64| -> Result<()> {
            if r.iter().all(|x| x.is_finite() && *x >= lo && *x <= hi) && r[0] <= r[1] {
                Ok(())
            } else {
                Err(Error::config(file, field, format!("expected [min, max] with {lo} ≤ min ≤ max ≤ {hi}, got {r:?}")))
            }
        };
        range(self.distractors.scale, "distractors.scale", 0.2, 3.0)?;
        let c = self.distractors.count;
        if c[0] > c[1] || c[1] > 20 {
            return Err(Error::config(file, "distractors.count", format!("expected [min, max] with min ≤ max ≤ 20, got {c:?}")));
        }
        if let Some(a) = &self.distractors.assets {
            if a.count[0] > a.count[1] || a.count[1] > 20 {
                return Err(Error::config(
                    file,
                    "distractors.assets.count",
                    format!("expected [min, max] with min ≤ max ≤ 20, got {:?}", a.count),
                ));
            }
            if let Some(r) = a.size_m {
                range(r, "distractors.assets.size_m", 0.01, 2.0)?;
            }
            range(a.scale, "distractors.assets.scale", 0.2, 3.0)?;
            if a.dir.as_os_str().is_empty() {
                return Err(Error::config(file, "distractors.assets.dir", "expected the asset folder"));
            }
        }
        let ov = &self.object_variants;
        for (i, c) in ov.colors.iter().enumerate() {
            crate::materials::check_rgba(*c, file, &format!("object_variants.colors[{i}]"))?;
        }
        range([ov.probability, ov.probability], "object_variants.probability", 0.0, 1.0)?;
        range(ov.scale, "object_variants.scale", 0.2, 3.0)?;
        range(ov.aspect, "object_variants.aspect", 0.5, 2.0)?;
        if self.sampled_predicates > 8 {
            return Err(Error::config(file, "sampled_predicates", format!("at most 8, got {}", self.sampled_predicates)));
        }
        if let Some(r) = &self.region {
            if !(r.center_m.iter().all(|x| x.is_finite()) && r.half_extent_m.iter().all(|x| x.is_finite() && *x > 0.02 && *x < 10.0)) {
                return Err(Error::config(file, "region", "expected a finite centre and half extents in (0.02, 10) m"));
            }
        }
        for (i, p) in self.predicates.iter().enumerate() {
            if let Predicate::Near { distance_m, .. } = p {
                if !(distance_m.is_finite() && *distance_m >= 0.005 && *distance_m <= 1.0) {
                    return Err(Error::config(
                        file,
                        format!("predicates[{i}].distance_m"),
                        format!("{}: expected a distance in [0.005, 1] m, got {distance_m}", p.label()),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Checks that need the object names and the material table only:
    /// unknown objects and materials, a predicate of an object with itself,
    /// two supports for one object, contradictions and support cycles.
    pub fn check_names(&self, names: &[String], table: &MaterialTable, file: &str) -> Result<()> {
        for (i, m) in self.object_variants.materials.iter().enumerate() {
            if table.get(m).is_none() {
                let known: Vec<&str> = table.materials.keys().map(|s| s.as_str()).collect();
                return Err(Error::config(
                    file,
                    format!("object_variants.materials[{i}]"),
                    format!("unknown material `{m}` (known: {})", known.join(", ")),
                ));
            }
        }
        let mut support: BTreeMap<&str, (usize, &Predicate)> = BTreeMap::new();
        for (i, p) in self.predicates.iter().enumerate() {
            let field = format!("predicates[{i}]");
            let (a, b) = p.objects();
            for o in [a, b] {
                if !names.iter().any(|n| n == o) {
                    return Err(Error::config(
                        file,
                        &field,
                        format!("{}: unknown object `{o}` (the scene's objects: {})", p.label(), names.join(", ")),
                    ));
                }
            }
            if a == b {
                return Err(Error::config(file, &field, format!("{}: an object cannot be related to itself", p.label())));
            }
            if p.is_support() {
                if let Some((j, q)) = support.insert(a, (i, p)) {
                    return Err(Error::config(
                        file,
                        &field,
                        format!("{}: `{a}` already rests on or in another object by predicates[{j}] {}", p.label(), q.label()),
                    ));
                }
            }
            for (j, q) in self.predicates[..i].iter().enumerate() {
                if contradicts(p, q) {
                    return Err(Error::config(file, &field, format!("{} contradicts predicates[{j}] {}", p.label(), q.label())));
                }
            }
        }
        // Support cycles: follow a → b links from every object.
        for (&start, (i, p)) in &support {
            let mut seen = vec![start];
            let mut cur = start;
            while let Some((_, q)) = support.get(cur) {
                cur = q.objects().1;
                if seen.contains(&cur) {
                    let chain: Vec<String> = seen.iter().map(|s| s.to_string()).chain([cur.to_string()]).collect();
                    return Err(Error::config(
                        file,
                        format!("predicates[{i}]"),
                        format!("{}: a cycle of supports ({}); objects cannot carry each other", p.label(), chain.join(" → ")),
                    ));
                }
                seen.push(cur);
            }
        }
        Ok(())
    }
}

/// Two predicates that no placement can satisfy together.
pub(crate) fn contradicts(p: &Predicate, q: &Predicate) -> bool {
    let (pa, pb) = p.objects();
    let (qa, qb) = q.objects();
    let same = pa == qa && pb == qb;
    let swapped = pa == qb && pb == qa;
    match (p.direction(), q.direction()) {
        // Same axis: opposite signs on the same pair, or the same sign on the swapped pair.
        (Some((ap, sp)), Some((aq, sq))) if ap == aq => (same && sp != sq) || (swapped && sp == sq),
        _ => {
            // A support and any directional relation of the same pair.
            (same || swapped) && ((p.is_support() && q.direction().is_some()) || (q.is_support() && p.direction().is_some()))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names() -> Vec<String> {
        ["mug", "box", "bowl"].map(String::from).to_vec()
    }

    fn check(text: &str) -> Result<VariationSpec> {
        let s = VariationSpec::parse(text, "v.json")?;
        s.check_names(&names(), &MaterialTable::builtin(), "v.json")?;
        Ok(s)
    }

    fn err(text: &str) -> String {
        check(text).unwrap_err().to_string()
    }

    #[test]
    fn parses_every_predicate() {
        let s = check(
            r#"{"version": 1, "frame": "world", "predicates": [
              {"predicate": "on_top", "a": "mug", "b": "box"},
              {"predicate": "left_of", "a": "bowl", "b": "box"},
              {"predicate": "right_of", "a": "box", "b": "bowl"},
              {"predicate": "in_front_of", "a": "bowl", "b": "mug"},
              {"predicate": "behind", "a": "mug", "b": "bowl"},
              {"predicate": "near", "a": "bowl", "b": "box", "distance_m": 0.05}],
              "distractors": {"count": [1, 2], "categories": ["l_shape", "mug"]},
              "object_variants": {"probability": 0.5, "materials": ["wood"]}}"#,
        )
        .unwrap();
        assert_eq!(s.predicates.len(), 6);
        assert_eq!(s.frame, DirFrame::World);
        assert_eq!(s.distractors.categories, vec![Category::LShape, Category::Mug]);
        let back = VariationSpec::parse(&serde_json::to_string(&s).unwrap(), "again").unwrap();
        assert_eq!(back, s);
    }

    #[test]
    fn bad_specs_name_the_field_object_and_predicate() {
        let e = err(r#"{"version": 1, "predicates": [{"predicate": "on_topp", "a": "mug", "b": "box"}]}"#);
        assert!(e.contains("predicates[0]") && e.contains("on_topp"), "{e}");
        let e = err(r#"{"version": 1, "predicates": [{"predicate": "on_top", "a": "cup", "b": "box"}]}"#);
        assert!(e.contains("unknown object `cup`") && e.contains("on_top(cup, box)"), "{e}");
        let e = err(
            r#"{"version": 1, "predicates": [{"predicate": "on_top", "a": "mug", "b": "box"}, {"predicate": "on_top", "a": "box", "b": "mug"}]}"#,
        );
        assert!(e.contains("cycle") && e.contains("box → mug → box") && e.contains("predicates[1]"), "{e}");
        let e = err(
            r#"{"version": 1, "predicates": [{"predicate": "left_of", "a": "mug", "b": "box"}, {"predicate": "left_of", "a": "box", "b": "mug"}]}"#,
        );
        assert!(e.contains("contradicts") && e.contains("predicates[1]"), "{e}");
        let e = err(r#"{"version": 1, "distractors": {"categories": ["teapot"]}}"#);
        assert!(e.contains("teapot"), "{e}");
        let e = err(r#"{"version": 1, "object_variants": {"materials": ["unobtainium"]}}"#);
        assert!(e.contains("object_variants.materials[0]") && e.contains("unobtainium"), "{e}");
        let e = err(r#"{"version": 1, "predicates": [{"predicate": "near", "a": "mug", "b": "box", "distance_m": -1}]}"#);
        assert!(e.contains("predicates[0].distance_m"), "{e}");
        let e = err(r#"{"version": 2}"#);
        assert!(e.contains("version"), "{e}");
        let e = err(r#"{"version": 1, "predicates": [{"predicate": "on_top", "a": "mug", "b": "mug"}]}"#);
        assert!(e.contains("itself"), "{e}");
    }
}
