//! Sparse FlexiCubes mesh extraction (TRELLIS `SparseFeatures2Mesh` +
//! FlexiCubes inference path, spec §5.1–5.2).
//!
//! Upstream scatters the sparse cube features into a dense (R+1)³ vertex grid
//! and runs FlexiCubes over all R³ cubes (~700 MB at R = 256). Only cubes with
//! an occupied corner (sdf < 0) can be surface cubes, and only corners of
//! active cubes can be occupied (untouched vertices default to sdf = +1), so
//! this port visits just the cubes around occupied vertices, with sorted
//! lattice ids and a dense per-column table (`ColumnIndex`) standing in for
//! the dense grids. Cubes outside the active set get the
//! dense defaults: raw weights 0, deform 0, colour 0.
//!
//! Output order matches upstream: dual vertices are grouped by their cube's
//! dual-vertex count (ascending), then cube id `(x·R + y)·R + z`, then group;
//! quads follow the sorted surface-edge ids, the ones whose first endpoint is
//! outside (sdf > 0) first.

pub(crate) mod tables;

pub use crate::mesh::Mesh;
use crate::model::sparse::SparseTensor;
use crate::{Error, Result};
use candle_core::DType;
use rayon::prelude::*;
pub use tables::CUBE_CORNERS;
use tables::{CHECK_TABLE, CUBE_EDGES, DMC_TABLE, NUM_VD_TABLE};

/// Channel ranges of the per-cube feature vector (dict order of upstream `_calc_layout`).
pub const SDF: std::ops::Range<usize> = 0..8;
/// Per-corner vertex deformation: 8 corners × 3.
pub const DEFORM: std::ops::Range<usize> = 8..32;
/// FlexiCubes weights: β (12 edges), α (8 corners), γ (1).
pub const WEIGHTS: std::ops::Range<usize> = 32..53;
/// Per-corner raw colour: 8 corners × 6 (only with colour).
pub const COLOR: std::ops::Range<usize> = 53..101;

const WEIGHT_SCALE: f32 = 0.99;

/// Sorted, distinct lattice ids `column · depth + z` with a dense table of
/// where each column's ids start: a lookup reads the table and searches the
/// few ids of one column, in memory the caller walks in order (the hash maps
/// it replaces hashed every corner of every cube to a random place).
pub(crate) struct ColumnIndex {
    keys: Vec<u64>,
    starts: Vec<u32>,
    depth: u64,
}

impl ColumnIndex {
    /// `keys` sorted and distinct, each below `columns · depth`.
    fn new(keys: Vec<u64>, columns: usize, depth: u64) -> Self {
        let mut starts = vec![0u32; columns + 1];
        for &k in &keys {
            starts[(k / depth) as usize + 1] += 1;
        }
        for c in 0..columns {
            starts[c + 1] += starts[c];
        }
        ColumnIndex { keys, starts, depth }
    }

    /// The position of `key` among the keys.
    fn find(&self, key: u64) -> Option<usize> {
        let col = (key / self.depth) as usize;
        let (a, b) = (*self.starts.get(col)? as usize, self.starts[col + 1] as usize);
        self.keys[a..b].binary_search(&key).ok().map(|i| a + i)
    }
}

/// `SparseFeatures2Mesh(res, use_color)`.
#[derive(Debug, Clone, Copy)]
pub struct SparseFeatures2Mesh {
    /// Cube grid side `R`.
    pub res: usize,
    /// Whether the features carry vertex colours (101 channels instead of 53).
    pub use_color: bool,
}

/// Per-vertex attributes on the (R+1)³ lattice, stored only where some
/// active cube touches the vertex (mean over those cubes, as upstream's
/// `scatter_reduce(mean)`).
pub struct VertexField {
    res: usize,
    /// Touched vertices; a vertex's slot is its position here.
    index: ColumnIndex,
    sdf: Vec<f32>,
    deform: Vec<[f32; 3]>,
    color: Vec<[f32; 6]>,
    deform_scale: f32,
}

impl VertexField {
    fn key(&self, v: [u32; 3]) -> u64 {
        let n = self.res as u64 + 1;
        (v[0] as u64 * n + v[1] as u64) * n + v[2] as u64
    }

    fn slot(&self, v: [u32; 3]) -> Option<usize> {
        self.index.find(self.key(v))
    }

    /// Signed distance (bias included); +1 where no active cube touches `v`.
    pub fn sdf(&self, v: [u32; 3]) -> f32 {
        self.slot(v).map_or(1.0, |i| self.sdf[i])
    }

    /// Deformed position `v/R - 0.5 + (1-1e-8)/(2R)·tanh(deform)`.
    pub fn position(&self, v: [u32; 3]) -> [f32; 3] {
        self.position_at(v, self.slot(v))
    }

    /// [`Self::position`] of `v`, whose slot is known.
    fn position_at(&self, v: [u32; 3], slot: Option<usize>) -> [f32; 3] {
        let d = slot.map_or([0.0; 3], |i| self.deform[i]);
        let r = self.res as f32;
        [0, 1, 2].map(|k| (v[k] as f32 / r - 0.5) + self.deform_scale * d[k].tanh())
    }

    /// Raw (pre-sigmoid) colour; 0 where untouched or without colour.
    pub fn color_raw(&self, v: [u32; 3]) -> [f32; 6] {
        self.color_raw_at(self.slot(v))
    }

    fn color_raw_at(&self, slot: Option<usize>) -> [f32; 6] {
        match slot {
            Some(i) if !self.color.is_empty() => self.color[i],
            _ => [0.0; 6],
        }
    }

    /// Number of touched lattice vertices.
    pub fn len(&self) -> usize {
        self.sdf.len()
    }

    /// Whether no lattice vertex is touched.
    pub fn is_empty(&self) -> bool {
        self.sdf.is_empty()
    }
}

/// The sparse stand-in for upstream's dense FlexiCubes inputs.
pub struct SparseGrid {
    /// Cube grid side `R`.
    pub res: usize,
    /// Whether the vertices carry colour.
    pub use_color: bool,
    /// Per-vertex attributes on the touched lattice vertices.
    pub field: VertexField,
    /// Active cubes; a cube's row of `weight_rows` is its position here.
    weights: ColumnIndex,
    weight_rows: Vec<[f32; 21]>,
}

impl SparseGrid {
    fn cube_key(&self, c: [u32; 3]) -> u64 {
        let n = self.res as u64;
        (c[0] as u64 * n + c[1] as u64) * n + c[2] as u64
    }

    /// Raw weights of cube `c` (β 0..12, α 12..20, γ 20); zeros when inactive.
    pub fn cube_weights(&self, c: [u32; 3]) -> [f32; 21] {
        self.weights.find(self.cube_key(c)).map_or([0.0; 21], |i| self.weight_rows[i])
    }
}

struct SurfCube {
    c: [u32; 3],
    case: u8,
    s: [f32; 8],
    /// The corners' vertex slots (`None`: untouched).
    slots: [Option<u32>; 8],
}

impl SparseFeatures2Mesh {
    /// The extractor for an `R = res` cube grid, with or without colour.
    pub fn new(res: usize, use_color: bool) -> Self {
        Self { res, use_color }
    }

    /// Feature channels per cube: 53, or 101 with colour.
    pub fn channels(&self) -> usize {
        if self.use_color {
            COLOR.end
        } else {
            WEIGHTS.end
        }
    }

    /// Scatter the cube features onto the sparse lattice (upstream
    /// `sparse_cube2verts` + `get_dense_attrs`, sdf bias applied).
    /// `coords` are cube coordinates in [0, R)³, `feats` is row-major `[N, C]`.
    pub fn prepare(&self, coords: &[[i32; 3]], feats: &[f32]) -> Result<SparseGrid> {
        let res = self.res;
        let ch = self.channels();
        if res == 0 || res > (1 << 20) {
            return Err(Error::msg(format!("flexicubes: resolution {res} out of range")));
        }
        if coords.len() > (u32::MAX / 8) as usize {
            return Err(Error::msg(format!("flexicubes: {} cubes, at most {}", coords.len(), u32::MAX / 8)));
        }
        if feats.len() != coords.len() * ch {
            return Err(Error::msg(format!("flexicubes: {} feature values for {} cubes x {ch} channels", feats.len(), coords.len())));
        }
        if let Some(c) = coords.iter().find(|c| c.iter().any(|&v| v < 0 || v as usize >= res)) {
            return Err(Error::msg(format!("flexicubes: cube {c:?} outside [0, {res})^3")));
        }
        let bias = (-1.0f64 / res as f64) as f32;
        let n = res as u64 + 1;
        // Every (vertex, cube, corner), sorted by vertex and then by cube: each
        // vertex's sums are taken over its cubes in input order, as a scatter
        // in input order takes them.
        let mut touches: Vec<(u64, u32)> = Vec::with_capacity(coords.len() * 8);
        for (i, c) in coords.iter().enumerate() {
            for (k, o) in CUBE_CORNERS.iter().enumerate() {
                let v = [c[0] as u64 + o[0] as u64, c[1] as u64 + o[1] as u64, c[2] as u64 + o[2] as u64];
                touches.push(((v[0] * n + v[1]) * n + v[2], (i * 8 + k) as u32));
            }
        }
        touches.par_sort_unstable();
        let mut keys: Vec<u64> = Vec::with_capacity(coords.len() * 2);
        let mut sums: Vec<[f32; 10]> = Vec::with_capacity(coords.len() * 2);
        let mut counts: Vec<u32> = Vec::with_capacity(coords.len() * 2);
        for run in touches.chunk_by(|a, b| a.0 == b.0) {
            let mut acc = [0f32; 10];
            for &(_, ik) in run {
                let (i, k) = (ik as usize / 8, ik as usize % 8);
                let row = &feats[i * ch..(i + 1) * ch];
                acc[0] += row[SDF.start + k] + bias;
                for d in 0..3 {
                    acc[1 + d] += row[DEFORM.start + 3 * k + d];
                }
                if self.use_color {
                    for d in 0..6 {
                        acc[4 + d] += row[COLOR.start + 6 * k + d];
                    }
                }
            }
            keys.push(run[0].0);
            sums.push(acc);
            counts.push(run.len() as u32);
        }
        drop(touches);
        // Duplicate coordinates: the last row wins, like a dense index_put.
        let r = res as u64;
        let mut cubes: Vec<(u64, u32)> =
            coords.iter().enumerate().map(|(i, c)| ((c[0] as u64 * r + c[1] as u64) * r + c[2] as u64, i as u32)).collect();
        cubes.par_sort_unstable();
        let mut cube_keys = Vec::with_capacity(cubes.len());
        let mut weight_rows = Vec::with_capacity(cubes.len());
        for run in cubes.chunk_by(|a, b| a.0 == b.0) {
            let (key, i) = run[run.len() - 1];
            let mut w = [0f32; 21];
            w.copy_from_slice(&feats[i as usize * ch..(i as usize + 1) * ch][WEIGHTS]);
            cube_keys.push(key);
            weight_rows.push(w);
        }
        let weights = ColumnIndex::new(cube_keys, res * res, r);
        let mean = |s: &[f32; 10], c: u32, k: usize| s[k] / c as f32;
        let field = VertexField {
            res,
            sdf: sums.iter().zip(&counts).map(|(s, &c)| mean(s, c, 0)).collect(),
            deform: sums.iter().zip(&counts).map(|(s, &c)| [1, 2, 3].map(|k| mean(s, c, k))).collect(),
            color: if self.use_color {
                sums.iter().zip(&counts).map(|(s, &c)| [4, 5, 6, 7, 8, 9].map(|k| mean(s, c, k))).collect()
            } else {
                Vec::new()
            },
            index: ColumnIndex::new(keys, (res + 1) * (res + 1), n),
            deform_scale: ((1.0 - 1e-8) / (res as f64 * 2.0)) as f32,
        };
        Ok(SparseGrid { res, use_color: self.use_color, field, weights, weight_rows })
    }

    /// Extract the mesh of one object from its active cubes.
    pub fn extract(&self, coords: &[[i32; 3]], feats: &[f32]) -> Result<Mesh> {
        let grid = self.prepare(coords, feats)?;
        Ok(flexicubes(&grid))
    }

    /// Extract one mesh per batch item of a sparse tensor (coords `(b, x, y, z)`).
    pub fn extract_sparse(&self, st: &SparseTensor) -> Result<Vec<Mesh>> {
        let ch = st.feats.dim(1)?;
        if ch != self.channels() {
            return Err(Error::msg(format!("flexicubes: {ch} feature channels, expected {}", self.channels())));
        }
        let feats: Vec<f32> = st.feats.to_dtype(DType::F32)?.flatten_all()?.to_vec1()?;
        st.batch_ranges()
            .into_iter()
            .map(|r| {
                let coords: Vec<[i32; 3]> = st.coords[r.clone()].iter().map(|c| [c[1], c[2], c[3]]).collect();
                self.extract(&coords, &feats[r.start * ch..r.end * ch])
            })
            .collect()
    }
}

fn tanh_weight(x: f32) -> f32 {
    x.tanh() * WEIGHT_SCALE + 1.0
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

fn offset(c: [u32; 3], o: [u32; 3]) -> [u32; 3] {
    [c[0] + o[0], c[1] + o[1], c[2] + o[2]]
}

/// FlexiCubes (training = false) over the sparse grid.
pub fn flexicubes(g: &SparseGrid) -> Mesh {
    let lattice = Lattice::new(g.res);
    let surf = surface_cubes(g, &lattice);
    if surf.is_empty() {
        return Mesh { vertices: vec![], faces: vec![], vertex_attrs: g.use_color.then(Vec::new) };
    }
    let cases = resolve_ambiguity(&surf, &lattice);
    let edges = surface_edges(&surf, &lattice);
    let duals = dual_vertices(g, &surf, &cases);
    let faces = quad_faces(g, &lattice, &edges, &duals);
    let DualVertices { vertices, colors, .. } = duals;
    Mesh { vertices, faces, vertex_attrs: g.use_color.then_some(colors) }
}

/// Ids on the `res³` cube grid and its `(res + 1)³` vertex grid.
struct Lattice {
    res: usize,
    /// Vertices per side (`res + 1`).
    nv: u64,
}

impl Lattice {
    fn new(res: usize) -> Self {
        Self { res, nv: res as u64 + 1 }
    }

    /// Vertex id `(x·nv + y)·nv + z`.
    fn vkey(&self, v: [u32; 3]) -> u64 {
        let nv = self.nv;
        (v[0] as u64 * nv + v[1] as u64) * nv + v[2] as u64
    }

    /// Cube id `(x·res + y)·res + z`.
    fn ckey(&self, c: [u32; 3]) -> u64 {
        let res = self.res;
        (c[0] as u64 * res as u64 + c[1] as u64) * res as u64 + c[2] as u64
    }

    /// The cube of a cube id.
    fn decode(&self, k: u64) -> [u32; 3] {
        let res = self.res;
        [(k / (res as u64 * res as u64)) as u32, ((k / res as u64) % res as u64) as u32, (k % res as u64) as u32]
    }

    /// Whether a signed cube coordinate lies on the grid.
    fn contains(&self, c: &[i64; 3]) -> bool {
        let r = self.res as i64;
        c.iter().all(|&x| (0..r).contains(&x))
    }
}

/// 1. Surface cubes: every cube around an occupied vertex whose corners' signs
///    differ, in cube-id order.
fn surface_cubes(g: &SparseGrid, lattice: &Lattice) -> Vec<SurfCube> {
    let field = &g.field;
    let nv = lattice.nv;
    let mut cand: Vec<u64> = Vec::new();
    for (&k, &sdf) in field.index.keys.iter().zip(&field.sdf) {
        if sdf < 0.0 {
            let v = [(k / (nv * nv)) as i64, ((k / nv) % nv) as i64, (k % nv) as i64];
            for o in CUBE_CORNERS {
                let c = [v[0] - o[0] as i64, v[1] - o[1] as i64, v[2] - o[2] as i64];
                if lattice.contains(&c) {
                    cand.push(lattice.ckey([c[0] as u32, c[1] as u32, c[2] as u32]));
                }
            }
        }
    }
    cand.par_sort_unstable();
    cand.dedup();
    cand.par_iter()
        .filter_map(|&k| {
            let c = lattice.decode(k);
            let slots = CUBE_CORNERS.map(|o| field.slot(offset(c, o)).map(|i| i as u32));
            let s = slots.map(|i| i.map_or(1.0, |i| field.sdf[i as usize]));
            let case = s.iter().enumerate().fold(0u32, |acc, (i, &v)| acc | ((v < 0.0) as u32) << i);
            (case != 0 && case != 255).then_some(SurfCube { c, case: case as u8, s, slots })
        })
        .collect()
}

/// 2. Ambiguity resolution: a problem case whose neighbour in the table's
///    direction is also a problem case is inverted (original cases decide).
fn resolve_ambiguity(surf: &[SurfCube], lattice: &Lattice) -> Vec<u8> {
    // In cube-id order, as the candidates were.
    let surf_keys: Vec<u64> = surf.iter().map(|sc| lattice.ckey(sc.c)).collect();
    let is_problem = |case: u8| CHECK_TABLE[case as usize][0] == 1;
    surf.par_iter()
        .map(|sc| {
            let row = CHECK_TABLE[sc.case as usize];
            if row[0] != 1 {
                return sc.case;
            }
            let n = [sc.c[0] as i64 + row[1] as i64, sc.c[1] as i64 + row[2] as i64, sc.c[2] as i64 + row[3] as i64];
            if lattice.contains(&n) {
                let nk = lattice.ckey([n[0] as u32, n[1] as u32, n[2] as u32]);
                if let Ok(j) = surf_keys.binary_search(&nk) {
                    if is_problem(surf[j].case) {
                        return row[4] as u8;
                    }
                }
            }
            sc.case
        })
        .collect()
}

/// The unique sign-changing edges of the surface cubes.
struct SurfaceEdges {
    /// (first vertex id, second vertex id), sorted.
    uniq: Vec<(u64, u64)>,
    /// Surface cubes sharing each edge.
    counts: Vec<u32>,
    /// Surface-edge id of each (cube, edge slot), -1 without a sign change.
    edge_ids: Vec<[i64; 12]>,
}

/// 3. Surface edges: unique sign-changing edges of surface cubes, sorted by
///    (first vertex id, second vertex id) like torch.unique(dim=0).
///    Each carries where it came from (cube · 12 + edge slot), so the ids
///    are handed back without searching for them.
fn surface_edges(surf: &[SurfCube], lattice: &Lattice) -> SurfaceEdges {
    let mut edges: Vec<(u64, u64, usize)> = surf
        .par_iter()
        .enumerate()
        .flat_map_iter(|(i, sc)| {
            CUBE_EDGES.iter().enumerate().filter(move |&(_, &[a, b])| (sc.s[a] < 0.0) != (sc.s[b] < 0.0)).map(move |(e, &[a, b])| {
                (lattice.vkey(offset(sc.c, CUBE_CORNERS[a])), lattice.vkey(offset(sc.c, CUBE_CORNERS[b])), i * 12 + e)
            })
        })
        .collect();
    edges.par_sort_unstable();
    let mut uniq: Vec<(u64, u64)> = Vec::with_capacity(edges.len() / 3);
    let mut counts: Vec<u32> = Vec::with_capacity(edges.len() / 3);
    let mut edge_ids: Vec<[i64; 12]> = vec![[-1i64; 12]; surf.len()];
    for run in edges.chunk_by(|x, y| (x.0, x.1) == (y.0, y.1)) {
        let id = uniq.len() as i64;
        for &(_, _, from) in run {
            edge_ids[from / 12][from % 12] = id;
        }
        uniq.push((run[0].0, run[0].1));
        counts.push(run.len() as u32);
    }
    SurfaceEdges { uniq, counts, edge_ids }
}

/// The dual vertices and what the faces need of them.
struct DualVertices {
    vertices: Vec<[f32; 3]>,
    /// Per vertex with colour, else empty.
    colors: Vec<[f32; 6]>,
    /// γ of each vertex's cube (splits the quads).
    vd_gamma: Vec<f32>,
    /// Per surface cube: the dual vertex of each edge slot.
    vd_of_slot: Vec<[u32; 12]>,
}

/// 4. Dual vertices, numbered by (vertex count of the cube, cube, group).
fn dual_vertices(g: &SparseGrid, surf: &[SurfCube], cases: &[u8]) -> DualVertices {
    let field = &g.field;
    let num_vd: Vec<usize> = cases.iter().map(|&c| NUM_VD_TABLE[c as usize] as usize).collect();
    let mut first_vd = vec![0u32; surf.len()];
    let mut total = 0u32;
    for num in 0..=4 {
        for (i, &n) in num_vd.iter().enumerate() {
            if n == num {
                first_vd[i] = total;
                total += n as u32;
            }
        }
    }
    struct CubeVd {
        pos: Vec<[f32; 3]>,
        color: Vec<[f32; 6]>,
        gamma: f32,
        vd_of_slot: [u32; 12],
    }
    let per_cube: Vec<CubeVd> = surf
        .par_iter()
        .enumerate()
        .map(|(i, sc)| {
            let w = g.cube_weights(sc.c);
            let beta: [f32; 12] = std::array::from_fn(|k| tanh_weight(w[k]));
            let alpha: [f32; 8] = std::array::from_fn(|k| tanh_weight(w[12 + k]));
            let gamma = sigmoid(w[20]) * WEIGHT_SCALE + ((1.0 - 0.99f64) / 2.0) as f32;
            let case = cases[i] as usize;
            let mut pos = Vec::with_capacity(num_vd[i]);
            let mut color = Vec::new();
            let mut vd_of_slot = [0u32; 12];
            for (v, group) in DMC_TABLE[case].iter().take(num_vd[i]).enumerate() {
                let mut acc = [0f32; 3];
                let mut cacc = [0f32; 6];
                let mut bsum = 0f32;
                for &e in group.iter().filter(|&&e| e >= 0) {
                    let e = e as usize;
                    vd_of_slot[e] = first_vd[i] + v as u32;
                    let [a, b] = CUBE_EDGES[e];
                    // Weighted zero crossing (x0·w1 − x1·w0)/(w1 − w0), w = s·α.
                    let w0 = sc.s[a] * alpha[a];
                    let w1 = sc.s[b] * alpha[b];
                    let (p, q) = (w1, -w0);
                    let den = p + q;
                    let va = offset(sc.c, CUBE_CORNERS[a]);
                    let vb = offset(sc.c, CUBE_CORNERS[b]);
                    let (sa, sb) = (sc.slots[a].map(|i| i as usize), sc.slots[b].map(|i| i as usize));
                    let (x0, x1) = (field.position_at(va, sa), field.position_at(vb, sb));
                    let be = beta[e];
                    for k in 0..3 {
                        acc[k] += (x0[k] * p + x1[k] * q) / den * be;
                    }
                    if g.use_color {
                        let (c0, c1) = (field.color_raw_at(sa).map(sigmoid), field.color_raw_at(sb).map(sigmoid));
                        for k in 0..6 {
                            cacc[k] += (c0[k] * p + c1[k] * q) / den * be;
                        }
                    }
                    bsum += be;
                }
                pos.push(acc.map(|x| x / bsum));
                if g.use_color {
                    color.push(cacc.map(|x| x / bsum));
                }
            }
            CubeVd { pos, color, gamma, vd_of_slot }
        })
        .collect();
    let mut vertices = vec![[0f32; 3]; total as usize];
    let mut colors = vec![[0f32; 6]; if g.use_color { total as usize } else { 0 }];
    let mut vd_gamma = vec![0f32; total as usize];
    for (i, cv) in per_cube.iter().enumerate() {
        for (v, p) in cv.pos.iter().enumerate() {
            let j = first_vd[i] as usize + v;
            vertices[j] = *p;
            vd_gamma[j] = cv.gamma;
            if g.use_color {
                colors[j] = cv.color[v];
            }
        }
    }
    let vd_of_slot = per_cube.iter().map(|cv| cv.vd_of_slot).collect();
    DualVertices { vertices, colors, vd_gamma, vd_of_slot }
}

/// 5. Quads around interior surface edges (shared by 4 cubes), their 4
///    dual vertices in cube order; triangles split along the larger γ product.
fn quad_faces(g: &SparseGrid, lattice: &Lattice, edges: &SurfaceEdges, duals: &DualVertices) -> Vec<[u32; 3]> {
    let nv = lattice.nv;
    let mut group: Vec<(u32, u32)> = Vec::new();
    for (i, ids) in edges.edge_ids.iter().enumerate() {
        for (e, &id) in ids.iter().enumerate() {
            if id >= 0 && edges.counts[id as usize] == 4 {
                group.push((id as u32, duals.vd_of_slot[i][e]));
            }
        }
    }
    group.sort_by_key(|&(id, _)| id); // stable
    let mut flipped: Vec<[u32; 4]> = Vec::new();
    let mut kept: Vec<[u32; 4]> = Vec::new();
    for q in group.chunks_exact(4) {
        let (ka, _) = edges.uniq[q[0].0 as usize];
        let nn = nv * nv;
        let v0 = [(ka / nn) as u32, ((ka / nv) % nv) as u32, (ka % nv) as u32];
        let quad = [q[0].1, q[1].1, q[2].1, q[3].1];
        // Wind every face towards positive sdf.
        if g.field.sdf(v0) > 0.0 {
            flipped.push([quad[0], quad[1], quad[3], quad[2]]);
        } else {
            kept.push([quad[2], quad[3], quad[1], quad[0]]);
        }
    }
    let vd_gamma = &duals.vd_gamma;
    let mut faces = Vec::with_capacity(2 * (flipped.len() + kept.len()));
    for q in flipped.iter().chain(kept.iter()) {
        let g02 = vd_gamma[q[0] as usize] * vd_gamma[q[2] as usize];
        let g13 = vd_gamma[q[1] as usize] * vd_gamma[q[3] as usize];
        if g02 > g13 {
            faces.push([q[0], q[1], q[2]]);
            faces.push([q[0], q[2], q[3]]);
        } else {
            faces.push([q[0], q[1], q[3]]);
            faces.push([q[3], q[1], q[2]]);
        }
    }
    faces
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sphere SDF (voxel units) at the corners of every cube; `solid` keeps
    /// the interior cubes active, otherwise only a narrow band around the surface.
    fn sphere(res: usize, radius: f32, solid: bool) -> (Vec<[i32; 3]>, Vec<f32>) {
        let mut coords = Vec::new();
        let mut feats = Vec::new();
        let r = res as f32;
        for x in 0..res as i32 {
            for y in 0..res as i32 {
                for z in 0..res as i32 {
                    let s = CUBE_CORNERS.map(|o| {
                        let p = [x + o[0] as i32, y + o[1] as i32, z + o[2] as i32].map(|v| v as f32 / r - 0.5);
                        ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - radius) * r
                    });
                    let keep = if solid {
                        s.iter().cloned().fold(f32::INFINITY, f32::min) < 1.5
                    } else {
                        s.iter().map(|v| v.abs()).fold(f32::INFINITY, f32::min) < 1.5
                    };
                    if keep {
                        coords.push([x, y, z]);
                        let mut row = vec![0f32; WEIGHTS.end];
                        row[SDF].copy_from_slice(&s);
                        feats.extend(row);
                    }
                }
            }
        }
        (coords, feats)
    }

    #[test]
    fn solid_sphere_is_a_closed_outward_manifold() {
        let res = 32;
        let (coords, feats) = sphere(res, 0.3, true);
        let mesh = SparseFeatures2Mesh::new(res, false).extract(&coords, &feats).unwrap();
        mesh.validate().unwrap();
        let t = mesh.topology();
        assert!(t.faces > 1000, "{t:?}");
        assert!(t.is_closed_oriented_manifold(), "{t:?}");
        assert_eq!(t.components, 1, "{t:?}");
        assert_eq!(t.euler(), 2, "{t:?}");
        for v in &mesh.vertices {
            let rad = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((rad - 0.3).abs() < 1.0 / res as f32, "vertex radius {rad}");
        }
        for (f, n) in mesh.faces.iter().zip(mesh.face_normals()) {
            let c = [0, 1, 2].map(|k| f.iter().map(|&i| mesh.vertices[i as usize][k]).sum::<f32>() / 3.0);
            let dot = n[0] * c[0] + n[1] * c[1] + n[2] * c[2];
            assert!(dot > 0.0, "inward face {f:?}");
        }
    }

    #[test]
    fn narrow_band_gives_an_inner_shell_too() {
        // Untouched interior vertices default to sdf = +1 (outside), so a
        // surface-only active set yields a second, inward-facing shell.
        let res = 32;
        let (coords, feats) = sphere(res, 0.3, false);
        let mesh = SparseFeatures2Mesh::new(res, false).extract(&coords, &feats).unwrap();
        let t = mesh.topology();
        assert!(t.is_closed_oriented_manifold(), "{t:?}");
        assert_eq!(t.components, 2, "{t:?}");
        assert_eq!(t.euler(), 4, "{t:?}");
    }

    #[test]
    fn colours_and_batches() {
        let res = 16;
        let (coords, feats53) = sphere(res, 0.3, true);
        // Colour channels: constant raw 0 → sigmoid 0.5 everywhere.
        let mut feats = Vec::new();
        for row in feats53.chunks(WEIGHTS.end) {
            feats.extend_from_slice(row);
            feats.extend(std::iter::repeat_n(0.0, COLOR.len()));
        }
        let m = SparseFeatures2Mesh::new(res, true);
        let mesh = m.extract(&coords, &feats).unwrap();
        let attrs = mesh.vertex_attrs.as_ref().unwrap();
        assert_eq!(attrs.len(), mesh.vertices.len());
        assert!(attrs.iter().flatten().all(|&c| (c - 0.5).abs() < 1e-6));

        // Two identical batch items give two identical meshes.
        let n = coords.len();
        let mut c4: Vec<[i32; 4]> = coords.iter().map(|c| [0, c[0], c[1], c[2]]).collect();
        c4.extend(coords.iter().map(|c| [1, c[0], c[1], c[2]]));
        let mut both = feats.clone();
        both.extend_from_slice(&feats);
        let t = candle_core::Tensor::from_vec(both, (2 * n, COLOR.end), &candle_core::Device::Cpu).unwrap();
        let st = SparseTensor::new(c4, t, 2).unwrap();
        let meshes = m.extract_sparse(&st).unwrap();
        assert_eq!(meshes.len(), 2);
        assert_eq!(meshes[0], mesh);
        assert_eq!(meshes[1], mesh);
    }

    #[test]
    fn bad_inputs_are_errors_and_empty_is_empty() {
        let m = SparseFeatures2Mesh::new(8, false);
        assert!(m.extract(&[[8, 0, 0]], &[0.0; 53]).is_err());
        assert!(m.extract(&[[-1, 0, 0]], &[0.0; 53]).is_err());
        assert!(m.extract(&[[0, 0, 0]], &[0.0; 52]).is_err());
        let empty = m.extract(&[], &[]).unwrap();
        assert!(empty.vertices.is_empty() && empty.faces.is_empty());
        // All corners outside: nothing to extract.
        let mut row = [0.0f32; 53];
        row[SDF].fill(2.0);
        assert!(m.extract(&[[3, 3, 3]], &row).unwrap().faces.is_empty());
    }

    /// Timing at the decoder's resolution: `cargo test --release --lib
    /// flexicubes_r256 -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn flexicubes_r256_timing() {
        let res = 256usize;
        let r = res as f32;
        let mut coords = Vec::new();
        let mut feats = Vec::new();
        let mut seed = 1u32;
        let mut rnd = || {
            seed ^= seed << 13;
            seed ^= seed >> 17;
            seed ^= seed << 5;
            seed as f32 / u32::MAX as f32 - 0.5
        };
        for x in 0..res as i32 {
            for y in 0..res as i32 {
                for z in 0..res as i32 {
                    let c = [x, y, z].map(|v| (v as f32 + 0.5) / r - 0.5);
                    let d = ((c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt() - 0.4) * r;
                    if d.abs() > 4.0 {
                        continue;
                    }
                    let s = CUBE_CORNERS.map(|o| {
                        let p = [x + o[0] as i32, y + o[1] as i32, z + o[2] as i32].map(|v| v as f32 / r - 0.5);
                        ((p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt() - 0.4) * r
                    });
                    coords.push([x, y, z]);
                    let mut row = vec![0f32; COLOR.end];
                    row[SDF].copy_from_slice(&s);
                    for v in &mut row[DEFORM.start..] {
                        *v = rnd();
                    }
                    feats.extend(row);
                }
            }
        }
        let m = SparseFeatures2Mesh::new(res, true);
        let t0 = std::time::Instant::now();
        let grid = m.prepare(&coords, &feats).unwrap();
        let t1 = std::time::Instant::now();
        let mesh = flexicubes(&grid);
        let t2 = std::time::Instant::now();
        println!(
            "R={res}: {} active cubes -> {} vertices, {} faces; scatter {:.0} ms, flexicubes {:.0} ms",
            coords.len(),
            mesh.vertices.len(),
            mesh.faces.len(),
            (t1 - t0).as_secs_f64() * 1e3,
            (t2 - t1).as_secs_f64() * 1e3
        );
        assert!(!mesh.faces.is_empty());
    }
}

#[cfg(test)]
mod post_tests {
    //! Mesh post-processing on FlexiCubes output.
    use super::tables::CUBE_CORNERS;
    use super::{SparseFeatures2Mesh, SDF, WEIGHTS};
    use crate::mesh::post::*;
    use crate::mesh::Mesh;

    fn sphere_mesh(res: usize, radius: f32, center: [f32; 3]) -> Mesh {
        let r = res as f32;
        let mut coords = Vec::new();
        let mut feats = Vec::new();
        for x in 0..res as i32 {
            for y in 0..res as i32 {
                for z in 0..res as i32 {
                    let s = CUBE_CORNERS.map(|o| {
                        let p = [x + o[0] as i32, y + o[1] as i32, z + o[2] as i32].map(|v| v as f32 / r - 0.5);
                        let d = [0, 1, 2].map(|k| p[k] - center[k]);
                        ((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() - radius) * r
                    });
                    if s.iter().cloned().fold(f32::INFINITY, f32::min) < 1.5 {
                        coords.push([x, y, z]);
                        let mut row = vec![0f32; WEIGHTS.end];
                        row[SDF].copy_from_slice(&s);
                        feats.extend(row);
                    }
                }
            }
        }
        SparseFeatures2Mesh::new(res, false).extract(&coords, &feats).unwrap()
    }

    fn merge(a: &Mesh, b: &Mesh) -> Mesh {
        let off = a.vertices.len() as u32;
        let mut m = a.clone();
        m.vertices.extend_from_slice(&b.vertices);
        m.faces.extend(b.faces.iter().map(|f| f.map(|i| i + off)));
        m
    }

    #[test]
    fn floaters_are_removed() {
        let big = sphere_mesh(32, 0.3, [0.0; 3]);
        let small = sphere_mesh(32, 0.06, [0.3, 0.3, 0.3]);
        let both = merge(&big, &small);
        assert_eq!(both.topology().components, 2);
        let kept = remove_small_components(&both, 10, 0.1);
        let t = kept.topology();
        assert_eq!(t.components, 1);
        assert_eq!(t.faces, big.faces.len());
        assert_eq!(kept.vertices.len(), t.vertices);
        assert!(kept.vertices.iter().all(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() < 0.34));
        let largest = keep_largest_component(&both);
        assert_eq!(largest.faces.len(), big.faces.len());
        // Face-count criterion alone.
        let by_count = remove_small_components(&both, small.faces.len() + 1, 0.0);
        assert_eq!(by_count.faces.len(), big.faces.len());
    }

    /// A flat square of side `s` at `x` (two triangles), appended to `m`.
    fn square(m: &mut Mesh, x: f32, s: f32) {
        let b = m.vertices.len() as u32;
        m.vertices.extend([[x, 0.0, 0.0], [x + s, 0.0, 0.0], [x + s, s, 0.0], [x, s, 0.0]]);
        m.faces.extend([[b, b + 1, b + 2], [b, b + 2, b + 3]]);
    }

    #[test]
    fn floaters_are_dropped_and_the_largest_component_kept() {
        let mut m = Mesh { vertices: Vec::new(), faces: Vec::new(), vertex_attrs: None };
        square(&mut m, 0.0, 1.0);
        square(&mut m, 5.0, 0.1); // 1 % of the area
        square(&mut m, 9.0, 0.5); // 20 %
        let d = drop_floaters(m.clone(), 0.02);
        assert_eq!(d.faces.len(), 4);
        assert!(d.vertices.iter().all(|v| v[0] < 5.0 || v[0] >= 9.0));
        assert_eq!(drop_floaters(m, 0.0).faces.len(), 6);
        // Every component under the threshold: the largest survives.
        let mut many = Mesh { vertices: Vec::new(), faces: Vec::new(), vertex_attrs: None };
        for i in 0..60 {
            square(&mut many, 2.0 * i as f32, if i == 7 { 1.1 } else { 1.0 });
        }
        let d = drop_floaters(many, 0.02);
        assert_eq!(d.faces.len(), 2);
        assert!((d.vertices[0][0] - 14.0).abs() < 1e-6);
    }

    #[test]
    fn decimated_sphere_stays_a_closed_manifold() {
        let mut sphere = sphere_mesh(48, 0.3, [0.0; 3]);
        sphere = remove_unreferenced_vertices(&sphere);
        sphere.vertex_attrs = Some(sphere.vertices.iter().map(|v| [v[0] + 0.5, 0.2, 0.3, 0.5, 0.5, 0.5]).collect());
        let n0 = sphere.faces.len();
        let target = n0 / 10;
        let dec = decimate(&sphere, target);
        dec.validate().unwrap();
        let t = dec.topology();
        assert!(t.is_closed_oriented_manifold(), "{t:?}");
        assert_eq!(t.euler(), 2);
        assert_eq!(t.components, 1);
        assert!(dec.faces.len() <= target + target / 10, "{} faces for target {target} (from {n0})", dec.faces.len());
        for v in &dec.vertices {
            let r = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
            assert!((r - 0.3).abs() < 0.02, "radius {r}");
        }
        for (f, n) in dec.faces.iter().zip(dec.face_normals()) {
            let c = [0, 1, 2].map(|k| f.iter().map(|&i| dec.vertices[i as usize][k]).sum::<f32>() / 3.0);
            assert!(n[0] * c[0] + n[1] * c[1] + n[2] * c[2] > 0.0);
        }
        // Colours were interpolated along collapsed edges: still a function of x.
        let attrs = dec.vertex_attrs.as_ref().unwrap();
        for (v, a) in dec.vertices.iter().zip(attrs) {
            assert!((a[0] - (v[0] + 0.5)).abs() < 0.05, "{a:?} at {v:?}");
        }
    }

    #[test]
    fn flat_grid_decimates_and_keeps_its_boundary() {
        let n = 20u32;
        let mesh = crate::mesh::flat_grid(n);
        let before = mesh.topology();
        let dec = decimate(&mesh, 100);
        let t = dec.topology();
        assert!(dec.faces.len() < mesh.faces.len() / 2, "{}", dec.faces.len());
        assert_eq!(t.nonmanifold_edges, 0);
        assert_eq!(t.misoriented_edges, 0);
        assert_eq!(t.boundary_edges, before.boundary_edges);
        assert_eq!(t.euler(), 1);
        assert!(dec.vertices.iter().all(|v| v[2] == 0.0));
        assert!((dec.area() - 1.0).abs() < 1e-4);
        assert!(dec.face_normals().iter().all(|n| n[2] > 0.99));
    }

    #[test]
    fn colours_from_points_and_bytes() {
        let mut m = sphere_mesh(16, 0.3, [0.0; 3]);
        assert!(vertex_colors_u8(&m).is_none());
        // Red points on +x, blue on -x.
        let pts = vec![[0.4, 0.0, 0.0], [-0.4, 0.0, 0.0]];
        let rgb = vec![[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        transfer_colors(&mut m, &pts, &rgb, 1);
        let c = vertex_colors_u8(&m).unwrap();
        for (v, c) in m.vertices.iter().zip(&c) {
            if v[0] > 0.01 {
                assert_eq!(*c, [255, 0, 0]);
            } else if v[0] < -0.01 {
                assert_eq!(*c, [0, 0, 255]);
            }
        }
    }
}
