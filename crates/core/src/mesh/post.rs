//! Mesh post-processing: floater removal by connected components, quadric
//! edge-collapse decimation, and per-vertex colours.
//!
//! Upstream (`to_glb`) decimates with VTK's quadric decimation and removes
//! floaters by rasterised visibility; this is the CPU-only substitute the
//! spec's §5.3 "cheapest acceptable path" allows.

use crate::math::{cross, dot, sub};
use crate::mesh::indexed::{face_area, Mesh, UnionFind};
use std::cmp::Ordering;

/// Drop vertices no face references, keeping order and attributes.
pub fn remove_unreferenced_vertices(mesh: &Mesh) -> Mesh {
    let mut used = vec![false; mesh.vertices.len()];
    for f in &mesh.faces {
        for &i in f {
            used[i as usize] = true;
        }
    }
    let mut remap = vec![u32::MAX; mesh.vertices.len()];
    let mut next = 0u32;
    for (i, &u) in used.iter().enumerate() {
        if u {
            remap[i] = next;
            next += 1;
        }
    }
    let keep = |i: &usize| used[*i];
    Mesh {
        vertices: (0..mesh.vertices.len()).filter(keep).map(|i| mesh.vertices[i]).collect(),
        faces: mesh.faces.iter().map(|f| f.map(|i| remap[i as usize])).collect(),
        vertex_attrs: mesh.vertex_attrs.as_ref().map(|a| (0..a.len()).filter(keep).map(|i| a[i]).collect()),
    }
}

/// Face-connected components (faces sharing a vertex), as a component id per face.
pub fn face_components(mesh: &Mesh) -> (Vec<usize>, usize) {
    let mut uf = UnionFind::new(mesh.vertices.len());
    for f in &mesh.faces {
        uf.union(f[0] as usize, f[1] as usize);
        uf.union(f[0] as usize, f[2] as usize);
    }
    let mut ids = std::collections::HashMap::new();
    let comp: Vec<usize> = mesh
        .faces
        .iter()
        .map(|f| {
            let r = uf.find(f[0] as usize);
            let n = ids.len();
            *ids.entry(r).or_insert(n)
        })
        .collect();
    (comp, ids.len())
}

/// Per component (ids from [`face_components`]): each face's component, and
/// every component's face count and area.
fn component_stats(mesh: &Mesh) -> (Vec<usize>, Vec<usize>, Vec<f64>) {
    let (comp, n) = face_components(mesh);
    let mut faces = vec![0usize; n];
    let mut area = vec![0f64; n];
    for (f, &c) in mesh.faces.iter().zip(&comp) {
        faces[c] += 1;
        area[c] += face_area(&mesh.vertices, f);
    }
    (comp, faces, area)
}

/// How clean a surface is: one closed, smooth component scores 1 component,
/// no boundary edges and a small mean dihedral angle.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct MeshQuality {
    /// Connected components.
    pub components: usize,
    /// The largest component's share of the area.
    pub largest_area_fraction: f64,
    /// Mean angle (degrees) between the normals of faces sharing an edge.
    pub mean_dihedral_deg: f64,
    /// Edges of one face (holes, open shells).
    pub boundary_edges: usize,
    /// Edges of three or more faces.
    pub non_manifold_edges: usize,
}

/// [`MeshQuality`] of a mesh (`None` without faces).
pub fn mesh_quality(mesh: &Mesh) -> Option<MeshQuality> {
    if mesh.faces.is_empty() {
        return None;
    }
    let (_, _, area) = component_stats(mesh);
    let total: f64 = area.iter().sum();
    let normals: Vec<[f64; 3]> = mesh.face_normals().iter().map(|n| n.map(f64::from)).collect();
    // Ordered, so the sum (and the figure's last digits) is the same run to run.
    let mut edges: std::collections::BTreeMap<(u32, u32), Vec<usize>> = std::collections::BTreeMap::new();
    for (k, f) in mesh.faces.iter().enumerate() {
        for (a, b) in [(f[0], f[1]), (f[1], f[2]), (f[2], f[0])] {
            edges.entry((a.min(b), a.max(b))).or_default().push(k);
        }
    }
    let (mut sum, mut n, mut boundary, mut non_manifold) = (0.0, 0usize, 0, 0);
    for fs in edges.values() {
        match fs.len() {
            1 => boundary += 1,
            2 => {
                let c = dot(normals[fs[0]], normals[fs[1]]).clamp(-1.0, 1.0);
                sum += c.acos().to_degrees();
                n += 1;
            }
            _ => non_manifold += 1,
        }
    }
    Some(MeshQuality {
        components: area.len(),
        largest_area_fraction: if total > 0.0 { area.iter().cloned().fold(0.0, f64::max) / total } else { 0.0 },
        mean_dihedral_deg: if n > 0 { sum / n as f64 } else { f64::NAN },
        boundary_edges: boundary,
        non_manifold_edges: non_manifold,
    })
}

/// The faces of the components `keep` marks, without unreferenced vertices.
fn keep_components(mesh: &Mesh, comp: &[usize], keep: &[bool]) -> Mesh {
    let kept = Mesh {
        vertices: mesh.vertices.clone(),
        faces: mesh.faces.iter().zip(comp).filter(|(_, &c)| keep[c]).map(|(f, _)| *f).collect(),
        vertex_attrs: mesh.vertex_attrs.clone(),
    };
    remove_unreferenced_vertices(&kept)
}

/// The component with the largest area.
fn largest(area: &[f64]) -> Option<usize> {
    (0..area.len()).max_by(|&a, &b| area[a].total_cmp(&area[b]))
}

/// Remove components with fewer than `min_faces` faces or less than
/// `min_area_fraction` of the total area (floaters), then unreferenced vertices.
pub fn remove_small_components(mesh: &Mesh, min_faces: usize, min_area_fraction: f64) -> Mesh {
    let (comp, faces, area) = component_stats(mesh);
    let total: f64 = area.iter().sum();
    let keep: Vec<bool> = (0..area.len()).map(|c| faces[c] >= min_faces && area[c] >= min_area_fraction * total).collect();
    keep_components(mesh, &comp, &keep)
}

/// Keep only the component with the largest area.
pub fn keep_largest_component(mesh: &Mesh) -> Mesh {
    let (comp, _, area) = component_stats(mesh);
    let best = largest(&area);
    let keep: Vec<bool> = (0..area.len()).map(|c| Some(c) == best).collect();
    keep_components(mesh, &comp, &keep)
}

/// Drop floaters: components under `fraction` of the total area, always
/// keeping the largest (so no mesh is emptied); `fraction <= 0` keeps all.
pub fn drop_floaters(mesh: Mesh, fraction: f64) -> Mesh {
    if fraction <= 0.0 || mesh.faces.is_empty() {
        return mesh;
    }
    let (comp, _, area) = component_stats(&mesh);
    let total: f64 = area.iter().sum();
    let best = largest(&area);
    let keep: Vec<bool> = (0..area.len()).map(|c| area[c] >= fraction * total || Some(c) == best).collect();
    keep_components(&mesh, &comp, &keep)
}

/// RGB vertex colours as bytes (from the first three attribute channels).
pub fn vertex_colors_u8(mesh: &Mesh) -> Option<Vec<[u8; 3]>> {
    mesh.vertex_colors().map(|c| c.iter().map(|c| c.map(to_u8)).collect())
}

/// Colour every vertex from coloured points (e.g. Gaussian centres with their
/// RGB): inverse-distance weighting of the `k` nearest points, found through a
/// uniform grid. Channels 3..6 of the attributes (normal map) are kept, or 0.5.
pub fn transfer_colors(mesh: &mut Mesh, points: &[[f32; 3]], rgb: &[[f32; 3]], k: usize) {
    if points.is_empty() || points.len() != rgb.len() || k == 0 {
        return;
    }
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in points {
        for d in 0..3 {
            lo[d] = lo[d].min(p[d]);
            hi[d] = hi[d].max(p[d]);
        }
    }
    // Cells sized so that a cell holds a few points on average.
    let extent = (0..3).map(|d| hi[d] - lo[d]).fold(0f32, f32::max).max(1e-6);
    let cells = ((points.len() as f32 / 4.0).cbrt().ceil() as usize).clamp(1, 256);
    let h = extent / cells as f32;
    let cell_of = |p: [f32; 3]| -> [i64; 3] { [0, 1, 2].map(|d| ((p[d] - lo[d]) / h).floor() as i64) };
    let mut grid: std::collections::HashMap<[i64; 3], Vec<u32>> = std::collections::HashMap::new();
    for (i, p) in points.iter().enumerate() {
        grid.entry(cell_of(*p)).or_default().push(i as u32);
    }
    let old = mesh.vertex_attrs.take();
    let attrs = mesh
        .vertices
        .iter()
        .enumerate()
        .map(|(vi, &v)| {
            let c = cell_of(v);
            let mut best: Vec<(f32, u32)> = Vec::new();
            // Grow the search shell until k candidates lie within the searched radius.
            for ring in 0i64..=(2 * cells as i64 + 2) {
                for x in -ring..=ring {
                    for y in -ring..=ring {
                        for z in -ring..=ring {
                            if x.abs().max(y.abs()).max(z.abs()) != ring {
                                continue;
                            }
                            if let Some(ids) = grid.get(&[c[0] + x, c[1] + y, c[2] + z]) {
                                for &i in ids {
                                    let p = points[i as usize];
                                    let d2 = (0..3).map(|d| (p[d] - v[d]).powi(2)).sum::<f32>();
                                    best.push((d2, i));
                                }
                            }
                        }
                    }
                }
                best.sort_by(|a, b| a.0.total_cmp(&b.0));
                best.truncate(k);
                let covered = ring as f32 * h;
                if best.len() == k && best[k - 1].0.sqrt() <= covered {
                    break;
                }
            }
            let mut acc = [0f32; 3];
            let mut wsum = 0f32;
            for &(d2, i) in &best {
                let w = 1.0 / (d2.sqrt() + 1e-6);
                for d in 0..3 {
                    acc[d] += w * rgb[i as usize][d];
                }
                wsum += w;
            }
            let prev = old.as_ref().map_or([0.5; 6], |a| a[vi]);
            [acc[0] / wsum, acc[1] / wsum, acc[2] / wsum, prev[3], prev[4], prev[5]]
        })
        .collect();
    mesh.vertex_attrs = Some(attrs);
}

// ---------------------------------------------------------------------------
// Quadric edge-collapse decimation (Garland & Heckbert).

/// Symmetric 4×4 quadric stored as its upper triangle.
#[derive(Clone, Copy, Default)]
struct Quadric([f64; 10]);

impl Quadric {
    fn plane(n: [f64; 3], d: f64, w: f64) -> Self {
        let [a, b, c] = n;
        Quadric([a * a, a * b, a * c, a * d, b * b, b * c, b * d, c * c, c * d, d * d].map(|x| x * w))
    }
    fn add(&mut self, o: &Quadric) {
        for k in 0..10 {
            self.0[k] += o.0[k];
        }
    }
    fn eval(&self, p: [f64; 3]) -> f64 {
        let q = &self.0;
        let [x, y, z] = p;
        q[0] * x * x
            + 2.0 * q[1] * x * y
            + 2.0 * q[2] * x * z
            + 2.0 * q[3] * x
            + q[4] * y * y
            + 2.0 * q[5] * y * z
            + 2.0 * q[6] * y
            + q[7] * z * z
            + 2.0 * q[8] * z
            + q[9]
    }
    /// Minimiser of the quadric, if well conditioned.
    fn optimum(&self) -> Option<[f64; 3]> {
        let q = &self.0;
        let m = [[q[0], q[1], q[2]], [q[1], q[4], q[5]], [q[2], q[5], q[7]]];
        let b = [-q[3], -q[6], -q[8]];
        let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
        let scale = (q[0] + q[4] + q[7]).powi(3);
        let well_conditioned = det.abs() > 1e-9 * scale && scale > 0.0; // false on NaN
        if !well_conditioned {
            return None;
        }
        let solve = |col: usize| {
            let mut mm = m;
            for r in 0..3 {
                mm[r][col] = b[r];
            }
            (mm[0][0] * (mm[1][1] * mm[2][2] - mm[1][2] * mm[2][1]) - mm[0][1] * (mm[1][0] * mm[2][2] - mm[1][2] * mm[2][0])
                + mm[0][2] * (mm[1][0] * mm[2][1] - mm[1][1] * mm[2][0]))
                / det
        };
        Some([solve(0), solve(1), solve(2)])
    }
}

/// Whether candidate `a` collapses before `b`: the smaller cost first, ties
/// by the smaller `(u, v)`. At most one candidate per edge is queued, so this
/// is a strict order and the collapse sequence does not depend on how the
/// queue stores its entries.
fn collapses_before(a: (f64, u32, u32), b: (f64, u32, u32)) -> bool {
    a.0.total_cmp(&b.0).then_with(|| (a.1, a.2).cmp(&(b.1, b.2))) == Ordering::Less
}

/// The decimator's candidate collapses.
trait CollapseQueue {
    /// Queue edge `(u, v)` (`u < v`) at `cost`.
    fn push(&mut self, cost: f64, u: u32, v: u32);
    /// The first edge in [`collapses_before`] order, removed from the queue.
    fn pop(&mut self) -> Option<(u32, u32)>;
    /// `v` was collapsed into `u`: every queued edge touching either is void.
    fn collapsed(&mut self, u: u32, v: u32);
}

const NOT_QUEUED: u32 = u32::MAX;

/// One queued edge, kept in the heap array itself so that sifting compares
/// neighbouring memory.
#[derive(Clone, Copy)]
struct QueuedEdge {
    cost: f64,
    u: u32,
    v: u32,
    /// Its handle: `EdgeQueue::at[slot]` is its heap position.
    slot: u32,
}

impl QueuedEdge {
    fn key(&self) -> (f64, u32, u32) {
        (self.cost, self.u, self.v)
    }
}

/// An indexed binary min-heap of edges: a collapse removes the edges of its
/// two vertices from the heap at once, so the heap only ever holds live
/// candidates (a lazy heap pops about nine void entries per collapse).
struct EdgeQueue {
    /// A binary heap in [`collapses_before`] order.
    heap: Vec<QueuedEdge>,
    /// Per handle, the heap position, or [`NOT_QUEUED`] once popped or removed.
    at: Vec<u32>,
    free: Vec<u32>,
    /// Per vertex, the handles of the edges queued with it (some since popped,
    /// removed or reused: checked on use).
    of_vertex: Vec<Vec<u32>>,
}

impl EdgeQueue {
    fn new(vertices: usize) -> Self {
        EdgeQueue { heap: Vec::new(), at: Vec::new(), free: Vec::new(), of_vertex: vec![Vec::new(); vertices] }
    }

    /// Queue every edge at once (a heap built bottom-up, O(n)).
    fn with_edges(vertices: usize, edges: impl IntoIterator<Item = (f64, u32, u32)>) -> Self {
        let mut q = Self::new(vertices);
        for (cost, u, v) in edges {
            let slot = q.at.len() as u32;
            q.at.push(slot);
            q.heap.push(QueuedEdge { cost, u, v, slot });
            q.of_vertex[u as usize].push(slot);
            q.of_vertex[v as usize].push(slot);
        }
        for i in (0..q.heap.len() / 2).rev() {
            q.sift_down(i);
        }
        q
    }

    fn place(&mut self, i: usize, e: QueuedEdge) {
        self.at[e.slot as usize] = i as u32;
        self.heap[i] = e;
    }

    fn sift_up(&mut self, mut i: usize) {
        let e = self.heap[i];
        while i > 0 {
            let parent = (i - 1) / 2;
            if !collapses_before(e.key(), self.heap[parent].key()) {
                break;
            }
            self.place(i, self.heap[parent]);
            i = parent;
        }
        self.place(i, e);
    }

    fn sift_down(&mut self, mut i: usize) {
        let n = self.heap.len();
        let e = self.heap[i];
        loop {
            let l = 2 * i + 1;
            if l >= n {
                break;
            }
            let r = l + 1;
            let c = if r < n && collapses_before(self.heap[r].key(), self.heap[l].key()) { r } else { l };
            if !collapses_before(self.heap[c].key(), e.key()) {
                break;
            }
            self.place(i, self.heap[c]);
            i = c;
        }
        self.place(i, e);
    }

    /// Take the edge at heap position `i` out of the heap and free its handle.
    fn remove_at(&mut self, i: usize) -> QueuedEdge {
        let e = self.heap[i];
        let last = self.heap.pop().unwrap_or(e);
        if i < self.heap.len() {
            self.place(i, last);
            if i > 0 && collapses_before(last.key(), self.heap[(i - 1) / 2].key()) {
                self.sift_up(i);
            } else {
                self.sift_down(i);
            }
        }
        self.at[e.slot as usize] = NOT_QUEUED;
        self.free.push(e.slot);
        e
    }

    /// Whether handle `slot` is a queued edge of `x`.
    fn queued_with(&self, slot: u32, x: u32) -> Option<usize> {
        let at = self.at[slot as usize];
        let e = self.heap.get(at as usize)?;
        (e.u == x || e.v == x).then_some(at as usize)
    }

    /// Remove every queued edge of `x`.
    fn remove_vertex(&mut self, x: u32) {
        let slots = std::mem::take(&mut self.of_vertex[x as usize]);
        for &s in &slots {
            // A stale handle: popped, removed through its other vertex, or
            // reused for an edge without `x`.
            if let Some(at) = self.queued_with(s, x) {
                self.remove_at(at);
            }
        }
        // Keep the list's allocation.
        let mut slots = slots;
        slots.clear();
        self.of_vertex[x as usize] = slots;
    }
}

impl CollapseQueue for EdgeQueue {
    fn push(&mut self, cost: f64, u: u32, v: u32) {
        let slot = self.free.pop().unwrap_or_else(|| {
            self.at.push(NOT_QUEUED);
            self.at.len() as u32 - 1
        });
        let i = self.heap.len();
        self.heap.push(QueuedEdge { cost, u, v, slot });
        self.at[slot as usize] = i as u32;
        self.sift_up(i);
        for x in [u, v] {
            let mut list = std::mem::take(&mut self.of_vertex[x as usize]);
            // Stale handles pile up at vertices whose neighbours collapse; drop
            // them now and then so a list stays about the vertex's valence.
            if list.len() >= 32 && list.len().is_power_of_two() {
                list.retain(|&t| self.queued_with(t, x).is_some());
            }
            list.push(slot);
            self.of_vertex[x as usize] = list;
        }
    }

    fn pop(&mut self) -> Option<(u32, u32)> {
        if self.heap.is_empty() {
            return None;
        }
        let e = self.remove_at(0);
        Some((e.u, e.v))
    }

    fn collapsed(&mut self, u: u32, v: u32) {
        self.remove_vertex(u);
        self.remove_vertex(v);
    }
}

struct Decimator {
    pos: Vec<[f64; 3]>,
    attrs: Option<Vec<[f32; 6]>>,
    faces: Vec<[u32; 3]>,
    face_alive: Vec<bool>,
    vfaces: Vec<Vec<u32>>,
    quadric: Vec<Quadric>,
    locked: Vec<bool>,
    alive_faces: usize,
    /// Every distinct edge `(min, max)` of the live input faces, sorted.
    edges: Vec<(u32, u32)>,
}

impl Decimator {
    fn new(mesh: &Mesh) -> Self {
        let n = mesh.vertices.len();
        let pos: Vec<[f64; 3]> = mesh.vertices.iter().map(|v| v.map(|x| x as f64)).collect();
        let mut vfaces = vec![Vec::new(); n];
        let mut quadric = vec![Quadric::default(); n];
        let mut edge_uses: Vec<(u32, u32)> = Vec::with_capacity(3 * mesh.faces.len());
        let mut face_alive = vec![true; mesh.faces.len()];
        for (fi, f) in mesh.faces.iter().enumerate() {
            if f[0] == f[1] || f[1] == f[2] || f[0] == f[2] {
                face_alive[fi] = false;
                continue;
            }
            let [a, b, c] = f.map(|i| pos[i as usize]);
            let nrm = cross(sub(b, a), sub(c, a));
            let len = dot(nrm, nrm).sqrt();
            for k in 0..3 {
                vfaces[f[k] as usize].push(fi as u32);
                let (x, y) = (f[k], f[(k + 1) % 3]);
                edge_uses.push((x.min(y), x.max(y)));
            }
            if len > 0.0 {
                let n3 = nrm.map(|x| x / len);
                // Area-weighted plane quadric.
                let q = Quadric::plane(n3, -dot(n3, a), 0.5 * len);
                for &i in f {
                    quadric[i as usize].add(&q);
                }
            }
        }
        // Boundary and non-manifold edges pin their vertices: boundaries stay exact.
        edge_uses.sort_unstable();
        let mut locked = vec![false; n];
        let mut edges = Vec::with_capacity(edge_uses.len() / 2);
        for run in edge_uses.chunk_by(|a, b| a == b) {
            let (a, b) = run[0];
            if run.len() != 2 {
                locked[a as usize] = true;
                locked[b as usize] = true;
            }
            edges.push((a, b));
        }
        let alive_faces = face_alive.iter().filter(|&&a| a).count();
        Decimator {
            pos,
            attrs: mesh.vertex_attrs.clone(),
            faces: mesh.faces.clone(),
            face_alive,
            vfaces,
            quadric,
            locked,
            alive_faces,
            edges,
        }
    }

    /// The distinct neighbours of `v` through live faces, sorted, into `out`.
    fn neighbours_into(&self, v: u32, out: &mut Vec<u32>) {
        out.clear();
        for &f in &self.vfaces[v as usize] {
            if self.face_alive[f as usize] {
                out.extend(self.faces[f as usize].iter().copied().filter(|&w| w != v));
            }
        }
        out.sort_unstable();
        out.dedup();
    }

    /// Best position for collapsing edge (u, v) and its cost.
    fn plan(&self, u: u32, v: u32) -> ([f64; 3], f64) {
        let mut q = self.quadric[u as usize];
        q.add(&self.quadric[v as usize]);
        let (a, b) = (self.pos[u as usize], self.pos[v as usize]);
        let mid = [0, 1, 2].map(|k| 0.5 * (a[k] + b[k]));
        // Ignore optima far off the edge (nearly flat regions).
        let l2 = dot(sub(a, b), sub(a, b));
        let optimum = q.optimum().filter(|&p| dot(sub(p, mid), sub(p, mid)) <= 4.0 * l2);
        // The first of the cheapest, the optimum tried first.
        optimum.into_iter().chain([a, b, mid]).map(|p| (p, q.eval(p).max(0.0))).min_by(|x, y| x.1.total_cmp(&y.1)).unwrap_or((mid, 0.0))
    }

    /// The queue entry of edge (u, v), `None` when a vertex is pinned.
    fn candidate(&self, u: u32, v: u32) -> Option<(f64, u32, u32)> {
        if self.locked[u as usize] || self.locked[v as usize] {
            return None;
        }
        let (u, v) = (u.min(v), u.max(v));
        Some((self.plan(u, v).1, u, v))
    }

    /// Link condition and normal-flip test for collapsing v into u at `p`.
    fn allowed(&self, u: u32, v: u32, p: [f64; 3], scratch: &mut [Vec<u32>; 2]) -> bool {
        let mut shared = [0u32; 2];
        let mut n_shared = 0;
        for &f in &self.vfaces[u as usize] {
            if self.face_alive[f as usize] && self.faces[f as usize].contains(&v) {
                if n_shared < 2 {
                    shared[n_shared] = f;
                }
                n_shared += 1;
            }
        }
        if n_shared != 2 {
            return false;
        }
        let [nu, nv] = scratch;
        self.neighbours_into(u, nu);
        self.neighbours_into(v, nv);
        if sorted_common(nu, nv) != 2 {
            return false;
        }
        // The two opposite vertices keep valence ≥ 3.
        for &f in &shared {
            let w = self.faces[f as usize].iter().copied().find(|&w| w != u && w != v).unwrap_or(u);
            self.neighbours_into(w, nu);
            if nu.len() <= 3 {
                return false;
            }
        }
        for x in [u, v] {
            for &f in &self.vfaces[x as usize] {
                let face = self.faces[f as usize];
                if !self.face_alive[f as usize] || face.contains(&u) && face.contains(&v) {
                    continue;
                }
                let before = face.map(|i| self.pos[i as usize]);
                let after = face.map(|i| if i == u || i == v { p } else { self.pos[i as usize] });
                let n0 = cross(sub(before[1], before[0]), sub(before[2], before[0]));
                let n1 = cross(sub(after[1], after[0]), sub(after[2], after[0]));
                let (l0, l1) = (dot(n0, n0).sqrt(), dot(n1, n1).sqrt());
                if l1 <= 1e-12 * (1.0 + l0) || dot(n0, n1) < 0.2 * l0 * l1 {
                    return false;
                }
            }
        }
        true
    }

    fn collapse(&mut self, u: u32, v: u32, p: [f64; 3]) {
        let (ui, vi) = (u as usize, v as usize);
        if let Some(attrs) = &mut self.attrs {
            // Attributes follow the position's projection onto the edge.
            let (a, b) = (self.pos[ui], self.pos[vi]);
            let e = sub(b, a);
            let t = (dot(sub(p, a), e) / dot(e, e).max(1e-300)).clamp(0.0, 1.0) as f32;
            let (ca, cb) = (attrs[ui], attrs[vi]);
            attrs[ui] = std::array::from_fn(|k| (1.0 - t) * ca[k] + t * cb[k]);
        }
        self.pos[ui] = p;
        let qv = self.quadric[vi];
        self.quadric[ui].add(&qv);
        let moved = std::mem::take(&mut self.vfaces[vi]);
        for f in moved {
            let fi = f as usize;
            if !self.face_alive[fi] {
                continue;
            }
            if self.faces[fi].contains(&u) {
                self.face_alive[fi] = false;
                self.alive_faces -= 1;
            } else {
                for i in self.faces[fi].iter_mut() {
                    if *i == v {
                        *i = u;
                    }
                }
                self.vfaces[ui].push(f);
            }
        }
        let alive = &self.face_alive;
        self.vfaces[ui].retain(|&f| alive[f as usize]);
    }

    /// Collapse the queue's edges in order until `target` faces remain or
    /// none is left; the live faces' mesh.
    fn run(mut self, queue: &mut impl CollapseQueue, target: usize) -> Mesh {
        let mut scratch = [Vec::new(), Vec::new()];
        let mut around = Vec::new();
        while self.alive_faces > target {
            let Some((u, v)) = queue.pop() else { break };
            let (p, _) = self.plan(u, v);
            if !self.allowed(u, v, p, &mut scratch) {
                continue;
            }
            self.collapse(u, v, p);
            queue.collapsed(u, v);
            self.neighbours_into(u, &mut around);
            for &w in &around {
                if let Some((cost, a, b)) = self.candidate(u, w) {
                    queue.push(cost, a, b);
                }
            }
        }
        let out = Mesh {
            vertices: self.pos.iter().map(|p| p.map(|x| x as f32)).collect(),
            faces: self.faces.iter().zip(&self.face_alive).filter(|(_, &a)| a).map(|(f, _)| *f).collect(),
            vertex_attrs: self.attrs,
        };
        remove_unreferenced_vertices(&out)
    }
}

/// Common elements of two sorted, distinct lists.
fn sorted_common(a: &[u32], b: &[u32]) -> usize {
    let (mut i, mut j, mut n) = (0, 0, 0);
    while i < a.len() && j < b.len() {
        match a[i].cmp(&b[j]) {
            Ordering::Less => i += 1,
            Ordering::Greater => j += 1,
            Ordering::Equal => {
                n += 1;
                i += 1;
                j += 1;
            }
        }
    }
    n
}

/// Quadric edge-collapse decimation towards `target_faces` faces.
///
/// Collapses keep a closed 2-manifold manifold (link condition, valence ≥ 3,
/// no face flips), so the target may not be reached exactly. Boundary and
/// non-manifold edges are never collapsed.
pub fn decimate(mesh: &Mesh, target_faces: usize) -> Mesh {
    let d = Decimator::new(mesh);
    let mut queue = EdgeQueue::with_edges(d.pos.len(), d.edges.iter().filter_map(|&(a, b)| d.candidate(a, b)));
    d.run(&mut queue, target_faces.max(4))
}

/// Taubin λ|μ smoothing (Taubin 1995, uniform umbrella weights): per
/// iteration one shrinking step (λ = 0.5) and one inflating step (μ = −0.53),
/// which removes noise at the vertex spacing without the shrinkage of plain
/// Laplacian smoothing. Faces and vertex attributes are kept.
pub fn taubin_smooth(mesh: &Mesh, iterations: usize) -> Mesh {
    const STEPS: [f32; 2] = [0.5, -0.53];
    let n = mesh.vertices.len();
    if iterations == 0 || mesh.faces.is_empty() {
        return mesh.clone();
    }
    // Vertex neighbours through edges, in CSR form, sorted so the sums are
    // taken in one fixed order.
    let mut edges: Vec<(u32, u32)> = Vec::with_capacity(mesh.faces.len() * 6);
    for f in &mesh.faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            if a != b {
                edges.extend([(a, b), (b, a)]);
            }
        }
    }
    edges.sort_unstable();
    edges.dedup();
    let mut start = vec![0usize; n + 1];
    for &(a, _) in &edges {
        start[a as usize + 1] += 1;
    }
    for i in 0..n {
        start[i + 1] += start[i];
    }
    let mut v = mesh.vertices.clone();
    let mut next = v.clone();
    for _ in 0..iterations {
        for w in STEPS {
            for (i, out) in next.iter_mut().enumerate() {
                let nb = &edges[start[i]..start[i + 1]];
                if nb.is_empty() {
                    *out = v[i];
                    continue;
                }
                let mut c = [0f32; 3];
                for &(_, j) in nb {
                    let p = v[j as usize];
                    c = [c[0] + p[0], c[1] + p[1], c[2] + p[2]];
                }
                let inv = 1.0 / nb.len() as f32;
                *out = std::array::from_fn(|k| v[i][k] + w * (c[k] * inv - v[i][k]));
            }
            std::mem::swap(&mut v, &mut next);
        }
    }
    Mesh { vertices: v, faces: mesh.faces.clone(), vertex_attrs: mesh.vertex_attrs.clone() }
}

/// [0, 1] → 0..=255 with rounding and clamping.
pub fn to_u8(x: f32) -> u8 {
    (x.clamp(0.0, 1.0) * 255.0).round() as u8
}

#[cfg(test)]
mod decimate_tests {
    use super::*;
    use std::collections::BinaryHeap;
    use std::time::{Duration, Instant};

    /// The queue the decimator used before [`EdgeQueue`]: a lazy binary heap
    /// whose entries carry their vertices' versions; a collapse bumps both
    /// versions and the void entries are skipped when popped. The reference
    /// the indexed queue must match collapse for collapse.
    #[derive(Default)]
    struct LazyHeap {
        heap: BinaryHeap<Entry>,
        version: Vec<u32>,
        pops: usize,
        stale: usize,
        /// With `timed`, the time spent popping void entries.
        timed: bool,
        stale_time: Duration,
    }

    #[derive(PartialEq)]
    struct Entry {
        cost: f64,
        u: u32,
        v: u32,
        ver_u: u32,
        ver_v: u32,
    }

    impl Eq for Entry {}

    impl Ord for Entry {
        fn cmp(&self, other: &Self) -> Ordering {
            // Min-heap on cost; ties broken by ids for determinism.
            other.cost.total_cmp(&self.cost).then_with(|| (other.u, other.v).cmp(&(self.u, self.v)))
        }
    }

    impl PartialOrd for Entry {
        fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
            Some(self.cmp(other))
        }
    }

    impl LazyHeap {
        fn new(vertices: usize) -> Self {
            LazyHeap { version: vec![0; vertices], ..Default::default() }
        }
    }

    impl CollapseQueue for LazyHeap {
        fn push(&mut self, cost: f64, u: u32, v: u32) {
            let (ver_u, ver_v) = (self.version[u as usize], self.version[v as usize]);
            self.heap.push(Entry { cost, u, v, ver_u, ver_v });
        }
        fn pop(&mut self) -> Option<(u32, u32)> {
            loop {
                let t = self.timed.then(Instant::now);
                let e = self.heap.pop()?;
                self.pops += 1;
                if self.version[e.u as usize] == e.ver_u && self.version[e.v as usize] == e.ver_v {
                    return Some((e.u, e.v));
                }
                self.stale += 1;
                if let Some(t) = t {
                    self.stale_time += t.elapsed();
                }
            }
        }
        fn collapsed(&mut self, u: u32, v: u32) {
            self.version[u as usize] += 1;
            self.version[v as usize] += 1;
        }
    }

    fn lazy_decimate(mesh: &Mesh, target: usize, timed: bool) -> (Mesh, LazyHeap) {
        let d = Decimator::new(mesh);
        let mut q = LazyHeap::new(d.pos.len());
        q.timed = timed;
        for &(a, b) in &d.edges {
            if let Some((cost, u, v)) = d.candidate(a, b) {
                q.push(cost, u, v);
            }
        }
        (d.run(&mut q, target.max(4)), q)
    }

    /// UV sphere (`nu` × `nv`), vertex radius jittered by `noise` (deterministic).
    fn uv_sphere(nu: usize, nv: usize, noise: f32) -> Mesh {
        let mut mesh = Mesh::default();
        mesh.vertices.push([0.0, 0.0, 0.3]);
        for i in 1..nv {
            let th = std::f32::consts::PI * i as f32 / nv as f32;
            for j in 0..nu {
                let ph = 2.0 * std::f32::consts::PI * j as f32 / nu as f32;
                mesh.vertices.push([0.3 * th.sin() * ph.cos(), 0.3 * th.sin() * ph.sin(), 0.3 * th.cos()]);
            }
        }
        mesh.vertices.push([0.0, 0.0, -0.3]);
        let ring = |i: usize, j: usize| (1 + (i - 1) * nu + j % nu) as u32;
        let south = mesh.vertices.len() as u32 - 1;
        for j in 0..nu {
            mesh.faces.push([0, ring(1, j), ring(1, j + 1)]);
            mesh.faces.push([south, ring(nv - 1, j + 1), ring(nv - 1, j)]);
        }
        for i in 1..nv - 1 {
            for j in 0..nu {
                mesh.faces.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
                mesh.faces.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
            }
        }
        jitter(&mut mesh, noise);
        mesh
    }

    fn jitter(mesh: &mut Mesh, noise: f32) {
        for (i, v) in mesh.vertices.iter_mut().enumerate() {
            let h = ((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) as f32 / (1u64 << 24) as f32;
            *v = v.map(|x| x * (1.0 + noise * (h - 0.5)));
        }
    }

    /// The 0.5 level of a blobby field on an `n`³ grid (three overlapping
    /// balls and a bar): a closed surface with flat-ish and curved parts.
    fn blobs(n: usize) -> Mesh {
        let h = 1.0 / n as f32;
        let mut values = Vec::with_capacity(n * n * n);
        for x in 0..n {
            for y in 0..n {
                for z in 0..n {
                    let p = [x, y, z].map(|c| c as f32 * h - 0.5);
                    let ball = |c: [f32; 3], r: f32| {
                        let d2: f32 = (0..3).map(|k| (p[k] - c[k]).powi(2)).sum();
                        (-(d2 / (r * r))).exp()
                    };
                    let bar = if p[0].abs() < 0.35 && p[1].abs() < 0.06 && p[2].abs() < 0.06 { 1.0 } else { 0.0 };
                    values.push(ball([-0.15, 0.0, 0.0], 0.2) + ball([0.15, 0.05, 0.0], 0.18) + ball([0.0, -0.1, 0.12], 0.12) + bar);
                }
            }
        }
        let grid = crate::mesh::ScalarGrid { values: &values, dims: [n, n, n], origin: [-0.5; 3], spacing: h };
        crate::mesh::marching_tetrahedra(&grid, 0.5)
    }

    fn with_colours(mut m: Mesh) -> Mesh {
        m.vertex_attrs = Some(m.vertices.iter().map(|v| [v[0] + 0.5, v[1] + 0.5, v[2] + 0.5, 0.5, 0.5, 0.5]).collect());
        m
    }

    fn bits(m: &Mesh) -> (Vec<[u32; 3]>, Vec<[u32; 3]>, Option<Vec<[u32; 6]>>) {
        (
            m.vertices.iter().map(|v| v.map(f32::to_bits)).collect(),
            m.faces.clone(),
            m.vertex_attrs.as_ref().map(|a| a.iter().map(|c| c.map(f32::to_bits)).collect()),
        )
    }

    /// The indexed queue makes exactly the lazy heap's collapses: the same
    /// mesh, bit for bit, on closed, noisy, tied and open meshes.
    #[test]
    fn indexed_queue_decimates_exactly_like_the_lazy_heap() {
        let meshes = [
            ("uv sphere", uv_sphere(40, 30, 0.0), 200),
            ("noisy uv sphere", with_colours(uv_sphere(40, 30, 0.05)), 300),
            ("blobs", with_colours(blobs(40)), 1000),
            // Every interior collapse of a flat grid costs 0, so ties decide the order.
            ("flat grid", crate::mesh::flat_grid(20), 100),
            ("torus", crate::mesh::primitives::torus_mesh(0.3, 0.1), 60),
        ];
        for (name, mesh, target) in meshes {
            let (reference, lazy) = lazy_decimate(&mesh, target, false);
            let ours = decimate(&mesh, target);
            assert!(ours.faces.len() < mesh.faces.len(), "{name}: nothing collapsed");
            assert!(lazy.stale > 0, "{name}: the reference popped no void entry");
            assert!(bits(&ours) == bits(&reference), "{name}: {} vs {} faces", ours.faces.len(), reference.faces.len());
        }
    }

    /// The indexed heap pops in the strict collapse order after any mix of
    /// pushes, pops and vertex removals (against a sorted reference).
    #[test]
    fn edge_queue_pops_in_order_after_removals() {
        let nv = 50u32;
        let mut q = EdgeQueue::new(nv as usize);
        let mut reference: Vec<(f64, u32, u32)> = Vec::new();
        let mut state = 7u64;
        let mut rnd = |m: u64| {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 33) % m
        };
        for step in 0..4000 {
            match rnd(10) {
                0..=5 => {
                    let (a, b) = (rnd(nv as u64) as u32, rnd(nv as u64) as u32);
                    let (u, v) = (a.min(b), a.max(b) + (a == b) as u32);
                    if v >= nv || reference.iter().any(|e| (e.1, e.2) == (u, v)) {
                        continue;
                    }
                    // Few distinct costs: the ties by (u, v) are exercised.
                    let cost = rnd(8) as f64 * 0.25;
                    q.push(cost, u, v);
                    reference.push((cost, u, v));
                }
                6..=7 => {
                    reference.sort_by(|a, b| if collapses_before(*a, *b) { Ordering::Less } else { Ordering::Greater });
                    let want = (!reference.is_empty()).then(|| reference.remove(0)).map(|e| (e.1, e.2));
                    assert_eq!(q.pop(), want, "step {step}");
                }
                _ => {
                    let (u, v) = (rnd(nv as u64) as u32, rnd(nv as u64) as u32);
                    q.collapsed(u, v);
                    reference.retain(|e| ![e.1, e.2].iter().any(|&x| x == u || x == v));
                }
            }
            assert_eq!(q.heap.len(), reference.len(), "step {step}");
        }
    }

    /// `cargo test --release --lib decimate_timing -- --ignored --nocapture`:
    /// the lazy heap (before) against the indexed queue (now), with the lazy
    /// heap's void pops counted and timed.
    #[test]
    #[ignore]
    fn decimate_timing() {
        let meshes = [
            ("uv sphere 500k faces, /20", uv_sphere(500, 500, 0.0), 20),
            ("noisy uv sphere 500k faces, /20", uv_sphere(500, 500, 0.02), 20),
            ("blobs 160^3, /10", with_colours(blobs(160)), 10),
        ];
        for (name, mesh, div) in meshes {
            let target = mesh.faces.len() / div;
            let t0 = Instant::now();
            let (reference, lazy) = lazy_decimate(&mesh, target, false);
            let lazy_s = t0.elapsed().as_secs_f64();
            let t0 = Instant::now();
            let (_, timed) = lazy_decimate(&mesh, target, true);
            let timed_s = t0.elapsed().as_secs_f64();
            let t0 = Instant::now();
            let ours = decimate(&mesh, target);
            let ours_s = t0.elapsed().as_secs_f64();
            println!(
                "{name}: {} -> {} faces; lazy heap {lazy_s:.2} s ({} pops, {} void = {:.0} %, void pops {:.2} s = {:.0} % of a timed run); indexed queue {ours_s:.2} s ({:.2}x)",
                mesh.faces.len(),
                ours.faces.len(),
                lazy.pops,
                lazy.stale,
                100.0 * lazy.stale as f64 / lazy.pops as f64,
                timed.stale_time.as_secs_f64(),
                100.0 * timed.stale_time.as_secs_f64() / timed_s,
                lazy_s / ours_s
            );
            assert!(bits(&ours) == bits(&reference), "{name}");
        }
    }
}

#[cfg(test)]
mod quality_tests {
    use super::*;

    fn cube(offset: f32) -> Mesh {
        let c = crate::mesh::primitives::cuboid([0.5, 0.5, 0.5]);
        Mesh {
            vertices: c.vertices.iter().map(|v| [v[0] as f32 + offset, v[1] as f32, v[2] as f32]).collect(),
            faces: c.faces.clone(),
            vertex_attrs: None,
        }
    }

    #[test]
    fn a_closed_cube_has_one_component_no_boundary_and_sixty_degrees() {
        let q = mesh_quality(&cube(0.0)).unwrap();
        // 6 face diagonals at 0°, 12 cube edges at 90°.
        assert_eq!((q.components, q.boundary_edges, q.non_manifold_edges), (1, 0, 0));
        assert!((q.mean_dihedral_deg - 60.0).abs() < 1e-4, "{q:?}");
        // Two cubes: two components of half the area each; one face removed: 3 open edges.
        let mut two = cube(0.0);
        let other = cube(3.0);
        let n = two.vertices.len() as u32;
        two.vertices.extend(other.vertices);
        two.faces.extend(other.faces.iter().map(|f| f.map(|i| i + n)));
        two.faces.pop();
        let q = mesh_quality(&two).unwrap();
        assert_eq!((q.components, q.boundary_edges), (2, 3));
        assert!((q.largest_area_fraction - 12.0 / 23.0).abs() < 1e-9, "{q:?}");
        assert_eq!(mesh_quality(&Mesh::default()), None);
    }
}

#[cfg(test)]
mod smooth_tests {
    use super::*;

    fn radii(m: &Mesh) -> (f64, f64) {
        let r: Vec<f64> = m.vertices.iter().map(|v| v.iter().map(|&x| (x as f64).powi(2)).sum::<f64>().sqrt()).collect();
        let mean = r.iter().sum::<f64>() / r.len() as f64;
        let sd = (r.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / r.len() as f64).sqrt();
        (mean, sd)
    }

    /// A sphere with radial noise at the vertex spacing comes out smoother
    /// (lower dihedral angle, less radial spread) and not shrunk.
    #[test]
    fn taubin_removes_noise_without_shrinking() {
        let mut m = crate::mesh::primitives::sphere_mesh(0.3);
        for (i, v) in m.vertices.iter_mut().enumerate() {
            // Deterministic ±4 % radial noise.
            let h = ((i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 40) as f32 / (1u64 << 24) as f32;
            let s = 1.0 + 0.08 * (h - 0.5);
            *v = v.map(|x| x * s);
        }
        let (before_q, (_, before_sd)) = (mesh_quality(&m).unwrap(), radii(&m));
        assert!(taubin_smooth(&m, 0) == m);
        let s = taubin_smooth(&m, 10);
        let (after_q, (mean, sd)) = (mesh_quality(&s).unwrap(), radii(&s));
        assert_eq!(s.faces, m.faces);
        assert!(after_q.mean_dihedral_deg < 0.6 * before_q.mean_dihedral_deg, "{before_q:?} -> {after_q:?}");
        assert!(sd < 0.5 * before_sd, "radial spread {before_sd} -> {sd}");
        assert!((mean - 0.3).abs() < 0.3 * 0.03, "mean radius {mean}");
    }
}
