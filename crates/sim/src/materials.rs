//! Physics material table (`models/materials.json`): density, friction,
//! restitution and shell wall thickness per material, and the material of
//! each object category. Per-object overrides come from the scene file.

use recon_core::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

/// The table shipped with the project, relative to the repository root.
pub const DEFAULT_TABLE: &str = "models/materials.json";

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Material {
    /// kg/m³: effective bulk density for solids, wall density for shells.
    pub density_kg_m3: f64,
    pub friction: f64,
    pub restitution: f64,
    /// Wall thickness for objects treated as shells.
    pub shell_thickness_m: f64,
    /// Display colour, linear RGBA in [0, 1]: written to the URDF visual
    /// material, the MJCF visual geom, USD `displayColor`/`displayOpacity`
    /// and the GLB material. Optional: without it the exports carry no colour.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub color_rgba: Option<[f64; 4]>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
/// The material table (`models/materials.json`): materials and the category → material map.
pub struct MaterialTable {
    /// File format version (1).
    pub version: u32,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    /// Free-text notes (sources of the values).
    pub notes: Vec<String>,
    /// Material of objects whose category is not in the table.
    pub default_material: String,
    /// Material of the support plane.
    pub support_plane_material: String,
    /// Materials by name.
    pub materials: BTreeMap<String, Material>,
    /// Category → material name.
    pub categories: BTreeMap<String, String>,
}

impl Material {
    /// `file`/`field` name the source in errors.
    pub fn validate(&self, file: &str, field: &str) -> Result<()> {
        let bad = |f: &str, msg: &str| Err(Error::config(file, format!("{field}.{f}"), msg));
        if !(self.density_kg_m3.is_finite() && self.density_kg_m3 > 0.0 && self.density_kg_m3 < 1e5) {
            return bad("density_kg_m3", &format!("expected a density in (0, 1e5) kg/m³, got {}", self.density_kg_m3));
        }
        if !(self.friction.is_finite() && (0.0..=2.0).contains(&self.friction)) {
            return bad("friction", &format!("expected a friction coefficient in [0, 2], got {}", self.friction));
        }
        if !(self.restitution.is_finite() && (0.0..=1.0).contains(&self.restitution)) {
            return bad("restitution", &format!("expected a restitution in [0, 1], got {}", self.restitution));
        }
        if !(self.shell_thickness_m.is_finite() && self.shell_thickness_m > 0.0 && self.shell_thickness_m < 0.1) {
            return bad("shell_thickness_m", &format!("expected a wall thickness in (0, 0.1) m, got {}", self.shell_thickness_m));
        }
        if let Some(c) = self.color_rgba {
            check_rgba(c, file, &format!("{field}.color_rgba"))?;
        }
        Ok(())
    }
}

/// A colour's four channels must be finite and in [0, 1].
pub fn check_rgba(c: [f64; 4], file: &str, field: &str) -> Result<()> {
    if c.iter().all(|x| x.is_finite() && (0.0..=1.0).contains(x)) {
        Ok(())
    } else {
        Err(Error::config(file, field, format!("expected linear RGBA, four numbers in [0, 1], got {c:?}")))
    }
}

impl MaterialTable {
    /// Reads and validates a table from a JSON file.
    pub fn load(path: &Path) -> Result<Self> {
        let t: MaterialTable = recon_core::util::json::read_json(path)?;
        t.validate(&path.display().to_string())?;
        Ok(t)
    }

    /// Parses and validates a table from JSON text; `file` names it in errors.
    pub fn from_json_str(s: &str, file: &str) -> Result<Self> {
        let t: MaterialTable = serde_json::from_str(s).map_err(|e| Error::config(file, "<root>", e.to_string()))?;
        t.validate(file)?;
        Ok(t)
    }

    /// The table shipped in `models/` (compiled in, so the library works from any directory;
    /// crates/sim/materials.json links to it, so the packaged crate carries it).
    pub fn builtin() -> Self {
        Self::from_json_str(include_str!("../materials.json"), DEFAULT_TABLE).expect("the shipped material table is valid (tested)")
    }

    /// Checks the version, the values' ranges and that every named material exists.
    pub fn validate(&self, file: &str) -> Result<()> {
        if self.version != 1 {
            return Err(Error::config(file, "version", format!("unsupported version {} (this build reads version 1)", self.version)));
        }
        for (name, m) in &self.materials {
            m.validate(file, &format!("materials.{name}"))?;
        }
        for (field, name) in [("default_material", &self.default_material), ("support_plane_material", &self.support_plane_material)] {
            if !self.materials.contains_key(name) {
                return Err(Error::config(file, field, format!("unknown material `{name}` (known: {})", self.known())));
            }
        }
        for (cat, name) in &self.categories {
            if !self.materials.contains_key(name) {
                return Err(Error::config(
                    file,
                    format!("categories.{cat}"),
                    format!("unknown material `{name}` (known: {})", self.known()),
                ));
            }
        }
        Ok(())
    }

    fn known(&self) -> String {
        self.materials.keys().cloned().collect::<Vec<_>>().join(", ")
    }

    /// The material named `name`.
    pub fn get(&self, name: &str) -> Option<&Material> {
        self.materials.get(name)
    }

    /// Material name for an object: explicit material, else its category's,
    /// else the default. An explicit unknown material is an error; an
    /// unknown category falls back to the default (recorded by the caller).
    pub fn resolve(&self, material: Option<&str>, category: &str, file: &str, field: &str) -> Result<(String, MaterialSource)> {
        if let Some(m) = material {
            if !self.materials.contains_key(m) {
                return Err(Error::config(file, field, format!("unknown material `{m}` (known: {})", self.known())));
            }
            return Ok((m.to_string(), MaterialSource::Explicit));
        }
        match self.categories.get(category) {
            Some(m) => Ok((m.clone(), MaterialSource::Category)),
            None => Ok((self.default_material.clone(), MaterialSource::Default)),
        }
    }
}

/// Where an object's material came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum MaterialSource {
    Explicit,
    Category,
    /// The category is not in the table.
    Default,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_table_is_valid_and_resolves() {
        let t = MaterialTable::load(&recon_testkit::repo().join(DEFAULT_TABLE)).unwrap();
        let (m, src) = t.resolve(None, "mug", "s.json", "objects[0]").unwrap();
        assert_eq!((m.as_str(), src), ("ceramic", MaterialSource::Category));
        let (m, src) = t.resolve(None, "spaceship", "s.json", "objects[0]").unwrap();
        assert_eq!((m.as_str(), src), ("plastic", MaterialSource::Default));
        let (m, src) = t.resolve(Some("wood"), "mug", "s.json", "objects[0]").unwrap();
        assert_eq!((m.as_str(), src), ("wood", MaterialSource::Explicit));
        let e = t.resolve(Some("unobtainium"), "mug", "s.json", "objects[0].physics.material").unwrap_err().to_string();
        assert!(e.contains("s.json") && e.contains("objects[0].physics.material") && e.contains("unobtainium"), "{e}");
        assert_eq!(MaterialTable::builtin().materials, t.materials);
    }

    #[test]
    fn bad_tables_name_the_field() {
        let base = include_str!("../materials.json");
        let e = MaterialTable::from_json_str(&base.replace("\"density_kg_m3\": 650.0", "\"density_kg_m3\": -1"), "t.json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("materials.wood.density_kg_m3"), "{e}");
        let e = MaterialTable::from_json_str(&base.replace("\"mug\": \"ceramic\"", "\"mug\": \"clay\""), "t.json").unwrap_err().to_string();
        assert!(e.contains("categories.mug") && e.contains("clay"), "{e}");
        let e = MaterialTable::from_json_str(&base.replace("\"friction\": 0.9", "\"friction\": 0.9, \"fricton\": 1"), "t.json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("fricton"), "{e}");
        let e = MaterialTable::from_json_str(&base.replace("\"version\": 1", "\"version\": 2"), "t.json").unwrap_err().to_string();
        assert!(e.contains("version"), "{e}");
        let e = MaterialTable::from_json_str(&base.replace("[0.55, 0.35, 0.17, 1.0]", "[0.55, 0.35, 1.7, 1.0]"), "t.json")
            .unwrap_err()
            .to_string();
        assert!(e.contains("materials.wood.color_rgba") && e.contains("[0, 1]"), "{e}");
    }

    #[test]
    fn every_shipped_material_has_a_colour() {
        let t = MaterialTable::builtin();
        assert!(t.materials.values().all(|m| m.color_rgba.is_some()));
    }
}
