//! A user's mesh file by its extension: GLB, OBJ or PLY, with the file's
//! size bounded before it is read.

use crate::mesh::trimesh::TriMesh;
use crate::util::limits::{check_file_size, MAX_MESH_FILE_BYTES};
use crate::{Error, Result};
use std::path::Path;

/// The mesh formats [`read_mesh_file`] reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    /// Binary glTF 2.0 (y up by the glTF convention).
    Glb,
    /// Wavefront OBJ.
    Obj,
    /// PLY (ASCII or binary).
    Ply,
}

impl MeshFormat {
    /// By the file's extension (case-insensitive); `None` for anything else.
    pub fn of(path: &Path) -> Option<MeshFormat> {
        match path.extension()?.to_str()?.to_ascii_lowercase().as_str() {
            "glb" => Some(MeshFormat::Glb),
            "obj" => Some(MeshFormat::Obj),
            "ply" => Some(MeshFormat::Ply),
            _ => None,
        }
    }
}

/// Parse mesh bytes of a known format; `file` names the source in errors.
pub fn parse_mesh(bytes: &[u8], format: MeshFormat, file: &str) -> Result<TriMesh> {
    let m = match format {
        MeshFormat::Glb => crate::dataset::glb::parse_glb(bytes, file)?,
        MeshFormat::Obj => crate::dataset::obj::parse_obj(bytes, file)?,
        MeshFormat::Ply => crate::dataset::ply::parse_ply(bytes, file)?,
    };
    if m.faces.is_empty() {
        return Err(Error::input(file, "expected a triangle mesh, the file has no faces (a point cloud cannot be simulated)"));
    }
    Ok(m)
}

/// Read a GLB, OBJ or PLY mesh (vertices in the file's units and axes).
pub fn read_mesh_file(path: &Path) -> Result<TriMesh> {
    let file = path.display().to_string();
    let format = MeshFormat::of(path).ok_or_else(|| Error::input(&file, "expected a .glb, .obj or .ply mesh file"))?;
    check_file_size(path, MAX_MESH_FILE_BYTES, "user mesh file")?;
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    parse_mesh(&bytes, format, &file)
}
