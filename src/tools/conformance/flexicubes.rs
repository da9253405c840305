//! Conformance runner for `SparseFeatures2Mesh` + FlexiCubes.
//!
//! The sparse grid is evaluated on the dense lattice to compare upstream's
//! dense intermediates (small resolutions only); outputs are compared in
//! upstream order (faces exactly). When the face order differs, a set
//! comparison (vertices matched to their nearest upstream vertex, faces as
//! rotation-normalised triangles) is reported in the note to help debugging.

use super::fixture::{Check, Fixture};
use crate::mesh::Mesh;
use crate::model::stage2::slat_vae::flexicubes::{flexicubes, SparseFeatures2Mesh, SparseGrid};
use crate::Result;
use candle_core::{DType, Device, Tensor};
use std::collections::HashSet;

/// Largest lattice densified for the intermediate checks.
const MAX_DENSE_VERTICES: usize = 1 << 22;

pub fn run(fx: &Fixture) -> Result<Vec<Check>> {
    let args = fx.field("args")?;
    let res = args.get("res").and_then(|v| v.as_u64()).ok_or_else(|| fx.config_err("args.res", "missing or not an integer"))? as usize;
    let use_color = args.get("use_color").and_then(|v| v.as_bool()).unwrap_or(false);
    let model = SparseFeatures2Mesh::new(res, use_color);

    let coords = fx.tensor("input.coords")?.to_dtype(DType::I64)?.to_vec2::<i64>()?;
    let coords: Vec<[i32; 3]> = coords.iter().map(|c| [c[1] as i32, c[2] as i32, c[3] as i32]).collect();
    let feats: Vec<f32> = fx.tensor("input.feats")?.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
    let grid = model.prepare(&coords, &feats)?;
    let tol = fx.abs_tolerance(1e-5);
    let mut checks = Vec::new();

    if (res + 1).pow(3) <= MAX_DENSE_VERTICES {
        dense_intermediates(fx, &grid, tol, &mut checks)?;
    }

    let t0 = std::time::Instant::now();
    let mesh = flexicubes(&grid);
    let elapsed = t0.elapsed();
    mesh.validate()?;

    let want_v = fx.tensor("output.vertices")?;
    let want_f = fx.tensor("output.faces")?;
    let nv_want = want_v.dim(0)?;
    let nf_want = want_f.dim(0)?;
    checks.push(
        Check::exact("num_vertices", mesh.vertices.len().abs_diff(nv_want))
            .with_note(format!("got {} want {nv_want}", mesh.vertices.len())),
    );
    checks.push(Check::exact("num_faces", mesh.faces.len().abs_diff(nf_want)).with_note(format!(
        "got {} want {nf_want}; extraction {:.1} ms",
        mesh.faces.len(),
        elapsed.as_secs_f64() * 1e3
    )));

    let got_v = rows_tensor(&mesh.vertices)?;
    checks.push(compare(fx, "output.vertices", &got_v, tol)?);

    let want_faces: Vec<[i64; 3]> = want_f.to_dtype(DType::I64)?.to_vec2::<i64>()?.iter().map(|r| [r[0], r[1], r[2]]).collect();
    let got_faces: Vec<[i64; 3]> = mesh.faces.iter().map(|f| f.map(|i| i as i64)).collect();
    let mismatches = if got_faces.len() == want_faces.len() {
        got_faces.iter().zip(&want_faces).filter(|(a, b)| a != b).count()
    } else {
        got_faces.len().max(want_faces.len())
    };
    let mut face_check = Check::exact("output.faces", mismatches);
    if mismatches > 0 {
        let want_verts: Vec<[f32; 3]> = want_v.to_dtype(DType::F32)?.to_vec2::<f32>()?.iter().map(|r| [r[0], r[1], r[2]]).collect();
        let set_diff = face_set_mismatches(&mesh, &want_verts, &want_faces);
        face_check = face_check.with_note(format!("order differs; as sets: {set_diff} unmatched faces"));
    }
    checks.push(face_check);

    if fx.tensors.contains_key("output.face_normal") {
        // Normals divide vertex rounding by the edge length: 10x looser.
        let got_n = rows_tensor(&mesh.face_normals())?;
        checks.push(compare(fx, "output.face_normal", &got_n, tol * 10.0)?);
    }
    if fx.tensors.contains_key("output.vertex_attrs") {
        match &mesh.vertex_attrs {
            Some(a) => checks.push(compare(fx, "output.vertex_attrs", &rows_tensor(a)?, tol)?),
            None => checks.push(Check::new("output.vertex_attrs", f64::INFINITY, tol).with_note("no colours produced")),
        }
    }
    Ok(checks)
}

/// Dense upstream intermediates rebuilt from the sparse grid.
fn dense_intermediates(fx: &Fixture, grid: &SparseGrid, tol: f64, checks: &mut Vec<Check>) -> Result<()> {
    let r = grid.res as u32;
    let lattice: Vec<[u32; 3]> = (0..=r).flat_map(|x| (0..=r).flat_map(move |y| (0..=r).map(move |z| [x, y, z]))).collect();
    let cubes: Vec<[u32; 3]> = (0..r).flat_map(|x| (0..r).flat_map(move |y| (0..r).map(move |z| [x, y, z]))).collect();
    let dev = Device::Cpu;
    let f = &grid.field;
    let mut add = |key: &str, t: Tensor| -> Result<()> {
        if fx.tensors.contains_key(key) {
            checks.push(compare(fx, key, &t, tol)?);
        }
        Ok(())
    };
    add("intermediate.scalar_field", Tensor::new(lattice.iter().map(|&v| f.sdf(v)).collect::<Vec<_>>(), &dev)?)?;
    add("intermediate.voxelgrid_vertices", rows_tensor(&lattice.iter().map(|&v| f.position(v)).collect::<Vec<_>>())?)?;
    if grid.use_color {
        add("intermediate.voxelgrid_colors", rows_tensor(&lattice.iter().map(|&v| f.color_raw(v)).collect::<Vec<_>>())?)?;
    }
    let w: Vec<[f32; 21]> = cubes.iter().map(|&c| grid.cube_weights(c)).collect();
    add("intermediate.beta", rows_tensor(&w.iter().map(|w| <[f32; 12]>::try_from(&w[..12]).unwrap_or([0.0; 12])).collect::<Vec<_>>())?)?;
    add("intermediate.alpha", rows_tensor(&w.iter().map(|w| <[f32; 8]>::try_from(&w[12..20]).unwrap_or([0.0; 8])).collect::<Vec<_>>())?)?;
    add("intermediate.gamma_f", Tensor::new(w.iter().map(|w| w[20]).collect::<Vec<_>>(), &dev)?)?;
    Ok(())
}

fn rows_tensor<const K: usize>(rows: &[[f32; K]]) -> Result<Tensor> {
    let flat: Vec<f32> = rows.iter().flatten().copied().collect();
    Ok(Tensor::from_vec(flat, (rows.len(), K), &Device::Cpu)?)
}

/// `fx.check`, but a shape mismatch is a failed check instead of an error.
fn compare(fx: &Fixture, key: &str, got: &Tensor, tol: f64) -> Result<Check> {
    let want = fx.tensor(key)?;
    if got.dims() != want.dims() {
        return Ok(Check::new(key, f64::INFINITY, tol).with_note(format!("shape {:?} vs {:?}", got.dims(), want.dims())));
    }
    fx.check(key, got, tol)
}

/// Faces of `mesh` absent from the upstream face set, after mapping each of
/// our vertices to the nearest upstream vertex and normalising rotations.
fn face_set_mismatches(mesh: &Mesh, want_v: &[[f32; 3]], want_f: &[[i64; 3]]) -> usize {
    let nearest = |p: [f32; 3]| -> i64 {
        let mut best = (f32::INFINITY, -1i64);
        for (i, q) in want_v.iter().enumerate() {
            let d = (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f32>();
            if d < best.0 {
                best = (d, i as i64);
            }
        }
        best.1
    };
    let remap: Vec<i64> = mesh.vertices.iter().map(|&p| nearest(p)).collect();
    let canon = |f: [i64; 3]| {
        let m = (0..3).min_by_key(|&k| f[k]).unwrap_or(0);
        [f[m], f[(m + 1) % 3], f[(m + 2) % 3]]
    };
    let want: HashSet<[i64; 3]> = want_f.iter().map(|&f| canon(f)).collect();
    mesh.faces.iter().filter(|f| !want.contains(&canon(f.map(|i| remap[i as usize])))).count()
}
