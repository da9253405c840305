//! A UV atlas for a triangle mesh: recon's own chart segmentation and packing.
//!
//! 1. Faces are grouped by the dominant axis (±x, ±y, ±z) of their smoothed
//!    normal (the mean of their vertices' area-weighted normals), so a chart
//!    is projected along the axis it faces.
//! 2. A chart is a connected set (shared edges) of faces of one group.
//! 3. Each chart is projected orthographically along its axis, at one scale
//!    common to every chart (texels per mesh unit), so texel density is even.
//! 4. The charts are shelf-packed (tallest first) into a square atlas with
//!    `gutter` empty texels between them; the scale is the largest that fits.
//! 5. A chart whose projection overlaps itself (a face turned away from its
//!    axis, an overhang) is split: its faces are re-grown breadth-first and a
//!    face whose texels collide with the chart's is left to a later chart.
//! 6. Vertices on chart seams are duplicated: one vertex per (vertex, chart).
//!
//! UV convention: `u` right, `v` down (glTF's; row 0 of the image is `v = 0`);
//! texel `(x, y)` has its centre at `((x + 0.5) / size, (y + 0.5) / size)`.
//! Writers of formats with `v` up (OBJ, USD) write `1 - v`. Deterministic: no
//! iteration over hashed containers decides anything.

use crate::mesh::indexed::{Mesh, UnionFind};
use crate::{Error, Result};
use std::collections::HashMap;

/// Settings of [`uv_atlas`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AtlasOptions {
    /// Side of the square texture the atlas is laid out for, texels.
    pub size: u32,
    /// Empty texels between two charts (and at the atlas border).
    pub gutter: u32,
}

impl AtlasOptions {
    /// An atlas for a `size`² texture with the default gutter (`size / 256`, at least 2).
    pub fn for_size(size: u32) -> Self {
        AtlasOptions { size, gutter: (size / 256).max(2) }
    }
}

impl Default for AtlasOptions {
    fn default() -> Self {
        Self::for_size(1024)
    }
}

/// An RGB8 image, row-major, row 0 at the top (`v = 0`).
#[derive(Clone, PartialEq, Eq)]
pub struct Texture {
    /// Width, texels.
    pub width: usize,
    /// Height, texels.
    pub height: usize,
    /// Interleaved RGB, `width · height · 3` bytes.
    pub rgb: Vec<u8>,
}

impl std::fmt::Debug for Texture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Texture").field("width", &self.width).field("height", &self.height).finish()
    }
}

impl Texture {
    /// The colour of texel `(x, y)`.
    pub fn texel(&self, x: usize, y: usize) -> [u8; 3] {
        let i = 3 * (y * self.width + x);
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }
}

/// A mesh laid out on a UV atlas: seam vertices duplicated.
#[derive(Debug, Clone, PartialEq)]
pub struct UvMesh {
    /// The mesh with one vertex per (source vertex, chart); vertex attributes carried over.
    pub mesh: Mesh,
    /// Per vertex of `mesh`: its texture coordinate (u right, v down, in [0, 1]).
    pub uv: Vec<[f32; 2]>,
    /// Per vertex of `mesh`: the source mesh's unit vertex normal (so shading has no seams).
    pub normals: Vec<[f32; 3]>,
    /// Per vertex of `mesh`: the source vertex it copies.
    pub source_vertex: Vec<u32>,
    /// Per face: its chart.
    pub face_chart: Vec<u32>,
    /// Number of charts.
    pub charts: usize,
    /// The options it was laid out with.
    pub options: AtlasOptions,
}

/// A mesh with texture coordinates and its texture: what the textured
/// exporters (GLB, OBJ + MTL, MJCF, USD, URDF) write.
#[derive(Debug, Clone, PartialEq)]
pub struct TexturedMesh {
    /// The atlas (mesh with seam vertices duplicated, UVs, normals).
    pub atlas: UvMesh,
    /// The baked texture.
    pub texture: Texture,
}

/// Visits the texel centres strictly inside the triangle `t` (texel
/// coordinates: texel `(x, y)` has its centre at `(x + 0.5, y + 0.5)`), clipped
/// to `[0, w) × [0, h)`, with their barycentric weights. Points on an edge
/// belong to neither face, so two faces sharing an edge never share a texel.
pub fn raster_triangle(t: [[f64; 2]; 3], w: usize, h: usize, mut visit: impl FnMut(usize, usize, [f64; 3])) {
    let [a, b, c] = t;
    let area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
    if area.abs() < 1e-18 || !area.is_finite() {
        return;
    }
    let lo = |k: usize| (a[k].min(b[k]).min(c[k]) - 0.5).floor().max(0.0) as usize;
    let hi = |k: usize, n: usize| ((a[k].max(b[k]).max(c[k]) - 0.5).ceil().max(0.0) as usize).min(n.saturating_sub(1));
    let (x0, x1, y0, y1) = (lo(0), hi(0, w), lo(1), hi(1, h));
    if w == 0 || h == 0 {
        return;
    }
    for y in y0..=y1 {
        let py = y as f64 + 0.5;
        for x in x0..=x1 {
            let px = x as f64 + 0.5;
            let wa = ((b[0] - px) * (c[1] - py) - (b[1] - py) * (c[0] - px)) / area;
            let wb = ((c[0] - px) * (a[1] - py) - (c[1] - py) * (a[0] - px)) / area;
            let wc = 1.0 - wa - wb;
            if wa > 1e-9 && wb > 1e-9 && wc > 1e-9 {
                visit(x, y, [wa, wb, wc]);
            }
        }
    }
}

/// Dominant-axis group (0..6: +x, −x, +y, −y, +z, −z) of a direction.
fn axis_group(n: [f64; 3]) -> u8 {
    let k = (0..3).max_by(|&i, &j| n[i].abs().total_cmp(&n[j].abs()).then(j.cmp(&i))).unwrap_or(2);
    2 * k as u8 + u8::from(n[k] < 0.0)
}

/// The two in-plane coordinates of `p` for a chart projected along the group's axis.
fn project(p: [f32; 3], group: u8) -> [f64; 2] {
    let p = p.map(f64::from);
    match group / 2 {
        0 => [p[1], p[2]],
        1 => [p[0], p[2]],
        _ => [p[0], p[1]],
    }
}

/// One chart before packing: its faces and 2D extent (mesh units).
struct Chart {
    faces: Vec<u32>,
    group: u8,
    min: [f64; 2],
    max: [f64; 2],
}

impl Chart {
    fn new(faces: Vec<u32>, group: u8, mesh: &Mesh) -> Self {
        let (mut min, mut max) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for &f in &faces {
            for &v in &mesh.faces[f as usize] {
                let q = project(mesh.vertices[v as usize], group);
                for k in 0..2 {
                    min[k] = min[k].min(q[k]);
                    max[k] = max[k].max(q[k]);
                }
            }
        }
        Chart { faces, group, min, max }
    }

    /// Size in texels at `scale` (texels per mesh unit), at least 1.
    fn texels(&self, scale: f64) -> [u32; 2] {
        [0, 1].map(|k| (((self.max[k] - self.min[k]) * scale).ceil() as u32).max(1))
    }
}

/// Shelf packing: per chart its top-left texel, or `None` when the charts do not fit.
fn shelf_pack(charts: &[Chart], order: &[usize], scale: f64, opts: &AtlasOptions) -> Option<Vec<[u32; 2]>> {
    let (size, g) = (opts.size as u64, opts.gutter as u64);
    let mut at = vec![[0u32; 2]; charts.len()];
    let (mut x, mut y, mut row_h) = (g, g, 0u64);
    for &i in order {
        let [w, h] = charts[i].texels(scale).map(u64::from);
        if w + 2 * g > size || h + 2 * g > size {
            return None;
        }
        if x + w + g > size {
            y += row_h + g;
            x = g;
            row_h = 0;
        }
        if y + h + g > size {
            return None;
        }
        at[i] = [x as u32, y as u32];
        x += w + g;
        row_h = row_h.max(h);
    }
    Some(at)
}

/// The largest scale (texels per mesh unit) at which the charts fit, and their placement.
fn fit_scale(charts: &[Chart], opts: &AtlasOptions) -> Result<(f64, Vec<[u32; 2]>)> {
    // Tallest first at the area-based guess (the order barely depends on the scale).
    let area: f64 = charts.iter().map(|c| (c.max[0] - c.min[0]).max(1e-12) * (c.max[1] - c.min[1]).max(1e-12)).sum();
    let size = opts.size as f64;
    let guess = (size * size / area.max(1e-30)).sqrt();
    let mut order: Vec<usize> = (0..charts.len()).collect();
    order.sort_by(|&a, &b| {
        let (ha, hb) = (charts[a].max[1] - charts[a].min[1], charts[b].max[1] - charts[b].min[1]);
        hb.total_cmp(&ha).then(a.cmp(&b))
    });
    // The first scale (from 1.5× the area guess, halving) that fits, then bisection
    // between it and the next larger one that does not.
    let mut scale = guess * 1.5;
    let mut fit = None;
    for _ in 0..80 {
        if let Some(p) = shelf_pack(charts, &order, scale, opts) {
            fit = Some(p);
            break;
        }
        scale *= 0.5;
    }
    let Some(mut placed) = fit else {
        return Err(Error::msg(format!(
            "uv atlas: {} charts do not fit a {}² texture with a {}-texel gutter; use a larger texture",
            charts.len(),
            opts.size,
            opts.gutter
        )));
    };
    let mut ok = scale;
    if ok < guess * 1.5 {
        let mut bad = ok * 2.0;
        for _ in 0..24 {
            let mid = 0.5 * (ok + bad);
            match shelf_pack(charts, &order, mid, opts) {
                Some(p) => {
                    ok = mid;
                    placed = p;
                }
                None => bad = mid,
            }
        }
    }
    Ok((ok, placed))
}

/// Texel coordinates of vertex `v` in `chart` placed at `at`.
fn texel_xy(mesh: &Mesh, v: u32, chart: &Chart, at: [u32; 2], scale: f64) -> [f64; 2] {
    let q = project(mesh.vertices[v as usize], chart.group);
    [0, 1].map(|k| at[k] as f64 + (q[k] - chart.min[k]) * scale)
}

/// Splits a chart whose faces overlap in its projection at `scale`: faces are
/// re-grown breadth-first over shared edges, a face whose texels collide with
/// the growing chart's is left for a later chart. Returns the chart unchanged
/// (one part) when nothing overlaps.
fn split_overlapping(chart: Chart, mesh: &Mesh, adj: &[Vec<u32>], scale: f64) -> Vec<Chart> {
    let [w, h] = chart.texels(scale).map(|x| x as usize + 2);
    let at = [1u32, 1];
    let tri = |f: u32| -> [[f64; 2]; 3] { mesh.faces[f as usize].map(|v| texel_xy(mesh, v, &chart, at, scale)) };
    // A quick check first: no texel covered twice means no split.
    let mut owner = vec![u32::MAX; w * h];
    let mut clash = false;
    for &f in &chart.faces {
        raster_triangle(tri(f), w, h, |x, y, _| {
            let o = &mut owner[y * w + x];
            if *o != u32::MAX {
                clash = true;
            }
            *o = f;
        });
        if clash {
            break;
        }
    }
    if !clash {
        return vec![chart];
    }
    let mut left: Vec<bool> = vec![false; mesh.faces.len()];
    for &f in &chart.faces {
        left[f as usize] = true;
    }
    let mut parts = Vec::new();
    for &seed in &chart.faces {
        if !left[seed as usize] {
            continue;
        }
        owner.iter_mut().for_each(|o| *o = u32::MAX);
        let mut part = Vec::new();
        let mut queue = std::collections::VecDeque::from([seed]);
        let mut queued = std::collections::HashSet::from([seed]);
        while let Some(f) = queue.pop_front() {
            let mut texels = Vec::new();
            raster_triangle(tri(f), w, h, |x, y, _| texels.push(y * w + x));
            if texels.iter().any(|&t| owner[t] != u32::MAX) && !part.is_empty() {
                continue; // stays in `left` for a later part
            }
            for t in texels {
                owner[t] = f;
            }
            left[f as usize] = false;
            part.push(f);
            for &n in &adj[f as usize] {
                if left[n as usize] && queued.insert(n) {
                    queue.push_back(n);
                }
            }
        }
        part.sort_unstable();
        parts.push(Chart::new(part, chart.group, mesh));
    }
    parts
}

/// Lays `mesh` out on a UV atlas ([module docs](self)). Errors on a mesh
/// without faces, a face past the vertices, non-finite vertices or an atlas
/// option out of range.
pub fn uv_atlas(mesh: &Mesh, opts: &AtlasOptions) -> Result<UvMesh> {
    mesh.validate()?;
    if mesh.faces.is_empty() {
        return Err(Error::msg("uv atlas: the mesh has no faces"));
    }
    if !(16..=16384).contains(&opts.size) {
        return Err(Error::msg(format!("uv atlas: texture size {} is out of range (16 to 16384 texels)", opts.size)));
    }
    if opts.gutter == 0 || opts.gutter * 8 > opts.size {
        return Err(Error::msg(format!("uv atlas: gutter {} must be 1 to size/8 ({}) texels", opts.gutter, opts.size / 8)));
    }
    if let Some(v) = mesh.vertices.iter().find(|v| v.iter().any(|x| !x.is_finite())) {
        return Err(Error::msg(format!("uv atlas: the mesh has a non-finite vertex {v:?}")));
    }
    let nf = mesh.faces.len();
    let vn = mesh.vertex_normals();
    let groups: Vec<u8> = mesh
        .faces
        .iter()
        .map(|f| {
            let s = f.iter().fold([0f64; 3], |acc, &v| {
                let n = vn[v as usize];
                [acc[0] + n[0] as f64, acc[1] + n[1] as f64, acc[2] + n[2] as f64]
            });
            axis_group(s)
        })
        .collect();
    // Faces sharing an edge, found by sorting the edges (deterministic).
    let mut edges: Vec<(u32, u32, u32)> = Vec::with_capacity(3 * nf);
    for (i, f) in mesh.faces.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            if a != b {
                edges.push((a.min(b), a.max(b), i as u32));
            }
        }
    }
    edges.sort_unstable();
    let mut adj: Vec<Vec<u32>> = vec![Vec::new(); nf];
    let mut uf = UnionFind::new(nf);
    let mut s = 0;
    while s < edges.len() {
        let mut e = s + 1;
        while e < edges.len() && (edges[e].0, edges[e].1) == (edges[s].0, edges[s].1) {
            e += 1;
        }
        for i in s..e {
            for j in i + 1..e {
                let (fa, fb) = (edges[i].2, edges[j].2);
                if fa != fb && groups[fa as usize] == groups[fb as usize] {
                    uf.union(fa as usize, fb as usize);
                    adj[fa as usize].push(fb);
                    adj[fb as usize].push(fa);
                }
            }
        }
        s = e;
    }
    // Charts in order of their first face.
    let mut chart_of_root: HashMap<usize, usize> = HashMap::new();
    let mut members: Vec<Vec<u32>> = Vec::new();
    for f in 0..nf {
        let r = uf.find(f);
        let c = *chart_of_root.entry(r).or_insert_with(|| {
            members.push(Vec::new());
            members.len() - 1
        });
        members[c].push(f as u32);
    }
    let mut charts: Vec<Chart> = members
        .into_iter()
        .map(|m| {
            let g = groups[m[0] as usize];
            Chart::new(m, g, mesh)
        })
        .collect();
    // Split overlapping charts at the packing scale; a split changes the scale, so repeat until none.
    let (mut scale, mut placed) = fit_scale(&charts, opts)?;
    for _ in 0..4 {
        let before = charts.len();
        charts = charts.into_iter().flat_map(|c| split_overlapping(c, mesh, &adj, scale)).collect();
        if charts.len() == before {
            break;
        }
        (scale, placed) = fit_scale(&charts, opts)?;
    }
    // Seam vertices: one per (source vertex, chart), numbered in face order.
    let mut face_chart = vec![0u32; nf];
    for (c, ch) in charts.iter().enumerate() {
        for &f in &ch.faces {
            face_chart[f as usize] = c as u32;
        }
    }
    let size = opts.size as f64;
    let mut key: HashMap<(u32, u32), u32> = HashMap::new();
    let (mut vertices, mut uv, mut normals, mut source) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut faces = Vec::with_capacity(nf);
    for (fi, f) in mesh.faces.iter().enumerate() {
        let c = face_chart[fi];
        let corners = f.map(|v| {
            *key.entry((v, c)).or_insert_with(|| {
                let t = texel_xy(mesh, v, &charts[c as usize], placed[c as usize], scale);
                vertices.push(mesh.vertices[v as usize]);
                uv.push([(t[0] / size) as f32, (t[1] / size) as f32]);
                let n = vn[v as usize];
                normals.push(if n == [0.0; 3] { [0.0, 0.0, 1.0] } else { n });
                source.push(v);
                vertices.len() as u32 - 1
            })
        });
        faces.push(corners);
    }
    let vertex_attrs = mesh.vertex_attrs.as_ref().map(|a| source.iter().map(|&v| a[v as usize]).collect());
    Ok(UvMesh {
        mesh: Mesh { vertices, faces, vertex_attrs },
        uv,
        normals,
        source_vertex: source,
        face_chart,
        charts: charts.len(),
        options: *opts,
    })
}

impl UvMesh {
    /// Per face its three corners in texel coordinates of the atlas.
    pub fn face_texels(&self, f: usize) -> [[f64; 2]; 3] {
        let s = self.options.size as f64;
        self.mesh.faces[f].map(|v| {
            let t = self.uv[v as usize];
            [t[0] as f64 * s, t[1] as f64 * s]
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::primitives::{box_mesh, sphere_mesh, torus_mesh};

    /// Rasterises every face into an owner grid: no texel is covered by two faces
    /// (charts do not overlap, nor does a chart overlap itself).
    fn assert_no_overlap(a: &UvMesh) {
        let n = a.options.size as usize;
        let mut owner = vec![u32::MAX; n * n];
        let mut covered = 0usize;
        for f in 0..a.mesh.faces.len() {
            raster_triangle(a.face_texels(f), n, n, |x, y, _| {
                let o = &mut owner[y * n + x];
                assert_eq!(*o, u32::MAX, "texel ({x}, {y}) is covered by faces {} and {f}", *o);
                *o = f as u32;
                covered += 1;
            });
        }
        assert!(covered > n * n / 10, "the atlas covers only {covered} of {} texels", n * n);
    }

    fn check_atlas(m: &Mesh, opts: AtlasOptions) -> UvMesh {
        let a = uv_atlas(m, &opts).unwrap();
        assert_eq!(a.mesh.faces.len(), m.faces.len());
        assert_eq!(a.uv.len(), a.mesh.vertices.len());
        // Every UV inside [0, 1], and at least a gutter from the border.
        let g = opts.gutter as f32 / opts.size as f32;
        for t in &a.uv {
            assert!(t.iter().all(|&x| (g - 1e-6..=1.0 - g + 1e-6).contains(&x)), "uv {t:?} outside [gutter, 1 - gutter]");
        }
        // Seams: each output vertex copies its source vertex's position, each face
        // its source face; a source vertex has one copy per chart it touches, each
        // copy lies in one chart only.
        let mut copies: std::collections::BTreeMap<u32, std::collections::BTreeSet<u32>> = Default::default();
        let mut chart_of_vertex = vec![u32::MAX; a.mesh.vertices.len()];
        for (f, (src, out)) in m.faces.iter().zip(&a.mesh.faces).enumerate() {
            assert_eq!(out.map(|v| a.source_vertex[v as usize]), *src);
            for &v in out {
                assert_eq!(a.mesh.vertices[v as usize], m.vertices[a.source_vertex[v as usize] as usize]);
                let c = &mut chart_of_vertex[v as usize];
                assert!(*c == u32::MAX || *c == a.face_chart[f], "vertex {v} is in two charts");
                *c = a.face_chart[f];
                copies.entry(a.source_vertex[v as usize]).or_default().insert(v);
            }
        }
        for (src, vs) in &copies {
            let charts: std::collections::BTreeSet<u32> = vs.iter().map(|&v| chart_of_vertex[v as usize]).collect();
            assert_eq!(charts.len(), vs.len(), "source vertex {src}: {} copies for {} charts", vs.len(), charts.len());
        }
        assert_no_overlap(&a);
        a
    }

    #[test]
    fn box_has_six_charts_without_overlap() {
        let a = check_atlas(&box_mesh(0.1, 0.2, 0.3), AtlasOptions::for_size(256));
        assert_eq!(a.charts, 6);
        // Determinism.
        assert_eq!(a, uv_atlas(&box_mesh(0.1, 0.2, 0.3), &AtlasOptions::for_size(256)).unwrap());
    }

    #[test]
    fn curved_meshes_pack_without_overlap() {
        check_atlas(&sphere_mesh(0.5), AtlasOptions::for_size(512));
        check_atlas(&torus_mesh(0.4, 0.15), AtlasOptions::for_size(512));
    }

    #[test]
    fn overlapping_projection_is_split() {
        // A flat grid with an interior vertex dragged past its neighbours: the
        // faces around it fold over the others in the plane's projection.
        let mut m = crate::mesh::primitives::flat_grid(4);
        m.vertices[12] = [0.9, 0.5, 0.0];
        let folded = m.face_normals().iter().filter(|n| n[2] < 0.0).count();
        assert!(folded > 0);
        let a = check_atlas(&m, AtlasOptions::for_size(128));
        assert!(a.charts >= 2);
    }

    #[test]
    fn bad_meshes_and_options_are_errors() {
        assert!(uv_atlas(&Mesh::default(), &AtlasOptions::default()).is_err());
        let mut m = box_mesh(1.0, 1.0, 1.0);
        assert!(uv_atlas(&m, &AtlasOptions { size: 8, gutter: 1 }).is_err());
        assert!(uv_atlas(&m, &AtlasOptions { size: 256, gutter: 0 }).is_err());
        m.vertices[0][0] = f32::NAN;
        assert!(uv_atlas(&m, &AtlasOptions::default()).unwrap_err().to_string().contains("non-finite"));
    }
}
