//! Distractors from a folder of the user's assets.
//!
//! Layout: GLB, OBJ or PLY meshes anywhere under the folder (at most
//! [`MAX_ASSET_DEPTH`] levels deep, [`MAX_ASSET_FILES`] files), each with an
//! optional physics JSON of the same stem beside it (`mug.glb` +
//! `mug.json`). An asset's category is the physics JSON's `category`, else
//! the name of the first folder below the asset folder it sits in
//! (`assets/fruit/apple.obj` is a `fruit`), else `object`; the category also
//! picks its material from the material table when the JSON names none.
//!
//! The physics JSON (`"version": 1`; every other field optional):
//!
//! ```json
//! { "version": 1, "category": "fruit", "units_m": 0.001, "up_axis": "y",
//!   "material": "produce", "mass_kg": 0.15, "friction": 0.7, "restitution": 0.1,
//!   "color_rgba": [0.8, 0.1, 0.1, 1.0] }
//! ```
//!
//! `units_m`: metres per mesh unit (default 1). `up_axis`: the mesh's up
//! axis, `y` or `z` (default `y` for GLB, the glTF convention; `z` for OBJ
//! and PLY). `mass_kg` or `density_kg_m3` (not both) override the
//! material's density; a mass is for the asset at its own size and scales
//! with the volume when the spec resizes it. `friction`, `restitution` and
//! `color_rgba` override the material's.
//!
//! Everything is read and checked when the library is loaded, before any
//! scene work: a bad mesh or JSON stops the run with an error naming the
//! file, the field and what was expected.

use super::spec::AssetSpec;
use crate::materials::MaterialTable;
use crate::scene_file::PhysicsOverrides;
use recon_core::mesh::Mesh;
use recon_core::util::limits::{check_file_size, MAX_ASSET_DEPTH, MAX_ASSET_FILES, MAX_ASSET_JSON_BYTES};
use recon_core::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// An asset mesh's up axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UpAxis {
    /// Y up (converted to z up on load).
    Y,
    /// Z up.
    Z,
}

/// The physics JSON beside an asset mesh (see the module docs).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AssetPhysics {
    /// File format version (1).
    pub version: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Category (selects the default material).
    pub category: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Metres per mesh unit.
    pub units_m: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// The mesh's up axis.
    pub up_axis: Option<UpAxis>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Material name.
    pub material: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Mass in kilograms (overrides the density).
    pub mass_kg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Density in kg/m³.
    pub density_kg_m3: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Coulomb friction coefficient.
    pub friction: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Restitution coefficient.
    pub restitution: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Display colour (linear RGBA in [0, 1]).
    pub color_rgba: Option<[f64; 4]>,
}

impl AssetPhysics {
    /// Parse and check; errors name `file` and the field (`mass_kg`, …).
    /// `table` checks the material name when given.
    pub fn parse(text: &str, file: &str, table: Option<&MaterialTable>) -> Result<Self> {
        let de = &mut serde_json::Deserializer::from_str(text);
        let p: AssetPhysics = serde_path_to_error::deserialize(de).map_err(|e| {
            let field = e.path().to_string();
            let field = if field == "." { "<root>".to_string() } else { field };
            Error::config(file, field, e.into_inner().to_string())
        })?;
        if p.version != 1 {
            return Err(Error::config(file, "version", format!("expected 1, got {}", p.version)));
        }
        let range = |v: Option<f64>, name: &str, lo: f64, hi: f64, what: &str| -> Result<()> {
            match v {
                Some(x) if !(x.is_finite() && x >= lo && x <= hi) => Err(Error::config(file, name, format!("expected {what}, got {x}"))),
                _ => Ok(()),
            }
        };
        range(p.units_m, "units_m", 1e-6, 100.0, "metres per mesh unit in [1e-6, 100] (0.001 for millimetres)")?;
        range(p.mass_kg, "mass_kg", 1e-6, 1e3, "a mass in [1e-6, 1000] kg")?;
        range(p.density_kg_m3, "density_kg_m3", 1e-3, 1e5, "a density in [0.001, 1e5] kg/m³")?;
        range(p.friction, "friction", 0.0, 2.0, "a friction coefficient in [0, 2]")?;
        range(p.restitution, "restitution", 0.0, 1.0, "a restitution in [0, 1]")?;
        if p.mass_kg.is_some() && p.density_kg_m3.is_some() {
            return Err(Error::config(file, "mass_kg", "give one of mass_kg and density_kg_m3, not both"));
        }
        if let Some(c) = p.color_rgba {
            crate::materials::check_rgba(c, file, "color_rgba")?;
        }
        if let Some(c) = &p.category {
            if c.trim().is_empty() || c.len() > 64 {
                return Err(Error::config(file, "category", "expected a name of 1 to 64 characters"));
            }
        }
        if let (Some(m), Some(t)) = (&p.material, table) {
            if t.get(m).is_none() {
                let known: Vec<&str> = t.materials.keys().map(String::as_str).collect();
                return Err(Error::config(file, "material", format!("unknown material `{m}` (known: {})", known.join(", "))));
            }
        }
        Ok(p)
    }
}

/// One loaded asset: its mesh in metres, z up, checked.
#[derive(Debug, Clone)]
pub struct Asset {
    /// Path relative to the asset folder (recorded in the manifest).
    pub rel: String,
    /// Category (from its physics file, else the folder's default).
    pub category: String,
    /// Mesh in metres, z up.
    pub mesh: Mesh,
    /// Physics overrides from its physics file.
    pub physics: PhysicsOverrides,
    /// Display colour (linear RGBA), if given.
    pub color_rgba: Option<[f64; 4]>,
    /// Largest side of the mesh's bounding box (m).
    pub extent_m: f64,
}

/// The assets of one folder that a spec may draw from.
#[derive(Debug, Clone)]
pub struct AssetLibrary {
    /// The asset folder.
    pub dir: PathBuf,
    /// Sorted by path.
    pub assets: Vec<Asset>,
    /// Every category found, sorted.
    pub categories: Vec<String>,
}

/// Mesh files under `dir`, sorted, bounded in number and depth.
fn walk(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut stack = vec![(dir.to_path_buf(), 0usize)];
    while let Some((d, depth)) = stack.pop() {
        let rd = std::fs::read_dir(&d).map_err(|e| Error::io(&d, e))?;
        for e in rd {
            let p = e.map_err(|e| Error::io(&d, e))?.path();
            // Symbolic links are not followed (a link to `..` would loop).
            let meta = std::fs::symlink_metadata(&p).map_err(|e| Error::io(&p, e))?;
            if meta.is_dir() && depth + 1 < MAX_ASSET_DEPTH {
                stack.push((p, depth + 1));
            } else if meta.is_file() && recon_core::dataset::MeshFormat::of(&p).is_some() {
                out.push(p);
                if out.len() > MAX_ASSET_FILES {
                    return Err(Error::too_large(
                        dir.display().to_string(),
                        "asset mesh files",
                        out.len() as u128,
                        MAX_ASSET_FILES as u128,
                        "files",
                        "GLB, OBJ and PLY files in the asset folder",
                    ));
                }
            }
        }
    }
    out.sort();
    Ok(out)
}

impl AssetLibrary {
    /// Find, read and check the assets `spec` asks for; `spec_file` names
    /// the spec in errors about the spec's own fields.
    pub fn load(spec: &AssetSpec, table: &MaterialTable, spec_file: &str) -> Result<Self> {
        let dir = &spec.dir;
        if !dir.is_dir() {
            return Err(Error::config(spec_file, "distractors.assets.dir", format!("{} is not a folder", dir.display())));
        }
        // Physics JSONs first (they may set the category), meshes only for the chosen categories.
        let mut found = Vec::new();
        for f in walk(dir)? {
            let json = f.with_extension("json");
            let physics = if json.is_file() {
                let jf = json.display().to_string();
                check_file_size(&json, MAX_ASSET_JSON_BYTES, "asset physics JSON")?;
                let text = std::fs::read_to_string(&json).map_err(|e| Error::io(&json, e))?;
                AssetPhysics::parse(&text, &jf, Some(table))?
            } else {
                AssetPhysics { version: 1, ..Default::default() }
            };
            let rel = f.strip_prefix(dir).unwrap_or(&f).to_path_buf();
            let folder = (rel.components().count() > 1)
                .then(|| rel.components().next().and_then(|c| c.as_os_str().to_str()).map(str::to_string))
                .flatten();
            let category = physics.category.clone().or(folder).unwrap_or_else(|| "object".into());
            found.push((f, rel, category, physics));
        }
        let mut categories: Vec<String> = found.iter().map(|x| x.2.clone()).collect();
        categories.sort();
        categories.dedup();
        for (i, c) in spec.categories.iter().enumerate() {
            if !categories.contains(c) {
                return Err(Error::config(
                    spec_file,
                    format!("distractors.assets.categories[{i}]"),
                    format!("no asset of category `{c}` in {} (found: {})", dir.display(), categories.join(", ")),
                ));
            }
        }
        let mut assets = Vec::new();
        for (f, rel, category, physics) in found {
            if !spec.categories.is_empty() && !spec.categories.contains(&category) {
                continue;
            }
            assets.push(load_asset(&f, &rel, category, physics)?);
        }
        if assets.is_empty() && spec.count[1] > 0 {
            return Err(Error::config(spec_file, "distractors.assets.dir", format!("no GLB, OBJ or PLY mesh in {}", dir.display())));
        }
        Ok(AssetLibrary { dir: dir.clone(), assets, categories })
    }
}

fn load_asset(f: &Path, rel: &Path, category: String, p: AssetPhysics) -> Result<Asset> {
    let file = f.display().to_string();
    let tm = recon_core::dataset::read_mesh_file(f)?;
    let units = p.units_m.unwrap_or(1.0);
    let glb = recon_core::dataset::MeshFormat::of(f) == Some(recon_core::dataset::MeshFormat::Glb);
    let up = p.up_axis.unwrap_or(if glb { UpAxis::Y } else { UpAxis::Z });
    // y up → z up: (x, y, z) ↦ (x, −z, y).
    let turn = |v: &[f64; 3]| -> [f32; 3] {
        let v = v.map(|x| x * units);
        match up {
            UpAxis::Y => [v[0] as f32, -v[2] as f32, v[1] as f32],
            UpAxis::Z => v.map(|x| x as f32),
        }
    };
    let mesh = Mesh { vertices: tm.vertices.iter().map(turn).collect(), faces: tm.faces, vertex_attrs: None };
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for v in &mesh.vertices {
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    let extent = (0..3).map(|k| (hi[k] - lo[k]) as f64).fold(0.0, f64::max);
    if !(0.002..=5.0).contains(&extent) {
        return Err(Error::input(
            &file,
            format!(
                "largest extent {extent:.4} m at units_m {units}: expected 0.002 to 5 m (set `units_m` in {}, e.g. 0.001 for millimetres)",
                f.with_extension("json").display()
            ),
        ));
    }
    // The simulation's mesh checks now, so a bad asset stops the run before any scene work.
    crate::physics::check_mesh(&mesh, &file)?;
    Ok(Asset {
        rel: rel.display().to_string(),
        category,
        mesh,
        physics: PhysicsOverrides {
            material: p.material,
            density_kg_m3: p.density_kg_m3,
            mass_kg: p.mass_kg,
            friction: p.friction,
            restitution: p.restitution,
            treatment: None,
            shell_thickness_m: None,
        },
        color_rgba: p.color_rgba,
        extent_m: extent,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn physics_json_errors_name_the_field() {
        let t = MaterialTable::builtin();
        let p = |s: &str| AssetPhysics::parse(s, "a.json", Some(&t));
        assert_eq!(p(r#"{"version": 1, "mass_kg": 0.2, "up_axis": "z"}"#).unwrap().mass_kg, Some(0.2));
        let e = p(r#"{"version": 1, "mass_kg": "heavy"}"#).unwrap_err().to_string();
        assert!(e.contains("a.json") && e.contains("mass_kg") && e.contains("f64"), "{e}");
        let e = p(r#"{"version": 1, "masss_kg": 1}"#).unwrap_err().to_string();
        assert!(e.contains("masss_kg"), "{e}");
        let e = p(r#"{"version": 1, "mass_kg": 1, "density_kg_m3": 5}"#).unwrap_err().to_string();
        assert!(e.contains("not both"), "{e}");
        let e = p(r#"{"version": 1, "material": "adamantium"}"#).unwrap_err().to_string();
        assert!(e.contains("`material`") && e.contains("adamantium"), "{e}");
        let e = p(r#"{"version": 1, "friction": -1}"#).unwrap_err().to_string();
        assert!(e.contains("`friction`") && e.contains("[0, 2]"), "{e}");
        let e = p(r#"{"version": 1, "up_axis": "x"}"#).unwrap_err().to_string();
        assert!(e.contains("up_axis"), "{e}");
        let e = p(r#"{"version": 1, "color_rgba": [1, 0, 0]}"#).unwrap_err().to_string();
        assert!(e.contains("color_rgba"), "{e}");
        let e = p(r#"{"mass_kg": 1}"#).unwrap_err().to_string();
        assert!(e.contains("version"), "{e}");
    }
}
