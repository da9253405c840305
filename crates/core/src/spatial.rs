//! Exact nearest-neighbour search: a static 3D k-d tree (median splits, leaf buckets).
//!
//! Build is O(n log n); each query is O(log n) on well-spread points. Batch queries run
//! in parallel with rayon. Distances are Euclidean, in the units of the input points.

use rayon::prelude::*;

/// A 3D point.
pub type P3 = [f64; 3];

const LEAF: usize = 12;

#[inline]
/// Squared Euclidean distance.
pub fn dist2(a: &P3, b: &P3) -> f64 {
    let (x, y, z) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    x * x + y * y + z * z
}

enum Node {
    Leaf { start: usize, end: usize },
    Split { axis: usize, value: f64, left: usize, right: usize },
}

/// A k-d tree over a copy of the points (reordered for locality).
pub struct KdTree {
    pts: Vec<P3>,
    /// `idx[i]` is the caller's index of `pts[i]`.
    idx: Vec<usize>,
    nodes: Vec<Node>,
}

impl KdTree {
    /// A tree over `points` (copied).
    pub fn new(points: &[P3]) -> Self {
        let mut order: Vec<usize> = (0..points.len()).collect();
        let mut nodes = Vec::new();
        if !points.is_empty() {
            build(points, &mut order, 0, &mut nodes);
        }
        let pts = order.iter().map(|&i| points[i]).collect();
        KdTree { pts, idx: order, nodes }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        self.pts.len()
    }

    /// Whether the tree holds no points.
    pub fn is_empty(&self) -> bool {
        self.pts.is_empty()
    }

    /// Nearest point to `q`: (caller's index, Euclidean distance). `None` on an empty tree.
    pub fn nearest(&self, q: &P3) -> Option<(usize, f64)> {
        if self.nodes.is_empty() {
            return None;
        }
        let mut best = (usize::MAX, f64::INFINITY);
        self.search(0, q, &mut best);
        Some((self.idx[best.0], best.1.sqrt()))
    }

    fn search(&self, node: usize, q: &P3, best: &mut (usize, f64)) {
        match self.nodes[node] {
            Node::Leaf { start, end } => {
                for i in start..end {
                    let d = dist2(&self.pts[i], q);
                    if d < best.1 {
                        *best = (i, d);
                    }
                }
            }
            Node::Split { axis, value, left, right } => {
                let diff = q[axis] - value;
                let (near, far) = if diff <= 0.0 { (left, right) } else { (right, left) };
                self.search(near, q, best);
                if diff * diff < best.1 {
                    self.search(far, q, best);
                }
            }
        }
    }

    /// Distance from every query point to its nearest tree point (parallel).
    pub fn nearest_dists(&self, queries: &[P3]) -> Vec<f64> {
        queries.par_iter().map(|q| self.nearest(q).map_or(f64::INFINITY, |r| r.1)).collect()
    }

    /// (index, distance) of the nearest tree point for every query (parallel).
    pub fn nearest_all(&self, queries: &[P3]) -> Vec<(usize, f64)> {
        queries.par_iter().map(|q| self.nearest(q).unwrap_or((usize::MAX, f64::INFINITY))).collect()
    }

    /// The `k` nearest tree points to `q` as (caller's index, distance), nearest first
    /// (fewer when the tree is smaller). Equal distances are ordered by index, so the
    /// result does not depend on the tree's internal order.
    pub fn k_nearest(&self, q: &P3, k: usize) -> Vec<(usize, f64)> {
        if self.nodes.is_empty() || k == 0 {
            return Vec::new();
        }
        // Sorted list of the best k (squared distance, caller index); k is small.
        let mut best: Vec<(f64, usize)> = Vec::with_capacity(k + 1);
        self.search_k(0, q, k, &mut best);
        best.into_iter().map(|(d, i)| (i, d.sqrt())).collect()
    }

    fn search_k(&self, node: usize, q: &P3, k: usize, best: &mut Vec<(f64, usize)>) {
        let worst = |b: &Vec<(f64, usize)>| if b.len() < k { f64::INFINITY } else { b[b.len() - 1].0 };
        match self.nodes[node] {
            Node::Leaf { start, end } => {
                for i in start..end {
                    let c = (dist2(&self.pts[i], q), self.idx[i]);
                    if c.0 <= worst(best) {
                        let at = best.partition_point(|b| b.0 < c.0 || (b.0 == c.0 && b.1 < c.1));
                        if at < k {
                            best.insert(at, c);
                            best.truncate(k);
                        }
                    }
                }
            }
            Node::Split { axis, value, left, right } => {
                let diff = q[axis] - value;
                let (near, far) = if diff <= 0.0 { (left, right) } else { (right, left) };
                self.search_k(near, q, k, best);
                if diff * diff <= worst(best) {
                    self.search_k(far, q, k, best);
                }
            }
        }
    }

    /// [`Self::k_nearest`] for every query (parallel, order preserved).
    pub fn k_nearest_all(&self, queries: &[P3], k: usize) -> Vec<Vec<(usize, f64)>> {
        queries.par_iter().map(|q| self.k_nearest(q, k)).collect()
    }
}

/// Builds the subtree over `order[..]` (whose positions are `offset..offset+len` in the
/// final array); returns the node id.
fn build(points: &[P3], order: &mut [usize], offset: usize, nodes: &mut Vec<Node>) -> usize {
    let id = nodes.len();
    if order.len() <= LEAF {
        nodes.push(Node::Leaf { start: offset, end: offset + order.len() });
        return id;
    }
    // Split on the axis of largest extent: keeps cells compact for any point distribution.
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for &i in order.iter() {
        for a in 0..3 {
            lo[a] = lo[a].min(points[i][a]);
            hi[a] = hi[a].max(points[i][a]);
        }
    }
    let axis = (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0);
    let mid = order.len() / 2;
    order.select_nth_unstable_by(mid, |&a, &b| points[a][axis].total_cmp(&points[b][axis]));
    let value = points[order[mid]][axis];
    nodes.push(Node::Split { axis, value, left: 0, right: 0 });
    let (l, r) = order.split_at_mut(mid);
    let left = build(points, l, offset, nodes);
    let right = build(points, r, offset + mid, nodes);
    nodes[id] = Node::Split { axis, value, left, right };
    id
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SeededRng;

    #[test]
    fn matches_brute_force() {
        let mut rng = SeededRng::new(7);
        let pts: Vec<P3> = (0..3000).map(|_| [rng.uniform(), rng.uniform() * 2.0, rng.normal()]).collect();
        // Duplicates and a degenerate (flat) cluster must not break the splits.
        let mut pts2 = pts.clone();
        pts2.extend((0..100).map(|i| [0.5, 0.5, i as f64 * 0.0]));
        let tree = KdTree::new(&pts2);
        for _ in 0..500 {
            let q = [rng.uniform() * 1.4 - 0.2, rng.uniform() * 2.4 - 0.2, rng.normal() * 1.5];
            let (i, d) = tree.nearest(&q).unwrap();
            let bf = pts2.iter().map(|p| dist2(p, &q)).fold(f64::INFINITY, f64::min).sqrt();
            assert!((d - bf).abs() < 1e-12, "{d} vs {bf}");
            assert!((dist2(&pts2[i], &q).sqrt() - d).abs() < 1e-12);
        }
        assert!(KdTree::new(&[]).nearest(&[0.0; 3]).is_none());
    }

    #[test]
    fn k_nearest_matches_brute_force() {
        let mut rng = SeededRng::new(9);
        let mut pts: Vec<P3> = (0..2000).map(|_| [rng.uniform(), rng.uniform(), rng.uniform() * 0.1]).collect();
        // Exact ties: the tie order must be by index.
        pts.extend([[2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 0.0, 0.0]]);
        let tree = KdTree::new(&pts);
        for q in (0..300).map(|_| [rng.uniform() * 1.2 - 0.1, rng.uniform(), rng.uniform() * 0.1]).chain([[2.0, 0.0, 0.0]]) {
            let got = tree.k_nearest(&q, 8);
            let mut bf: Vec<(f64, usize)> = pts.iter().enumerate().map(|(i, p)| (dist2(p, &q), i)).collect();
            bf.sort_by(|a, b| a.partial_cmp(b).unwrap());
            let want: Vec<(usize, f64)> = bf[..8].iter().map(|&(d, i)| (i, d.sqrt())).collect();
            assert_eq!(got, want);
        }
        assert_eq!(KdTree::new(&pts[..3]).k_nearest(&[0.0; 3], 8).len(), 3);
        assert!(KdTree::new(&[]).k_nearest(&[0.0; 3], 8).is_empty());
    }

    #[test]
    fn handles_100k_points() {
        let mut rng = SeededRng::new(8);
        let pts: Vec<P3> = (0..100_000).map(|_| [rng.normal(), rng.normal(), rng.normal() * 0.1]).collect();
        let qs: Vec<P3> = (0..100_000).map(|_| [rng.normal(), rng.normal(), rng.normal() * 0.1]).collect();
        let t0 = std::time::Instant::now();
        let tree = KdTree::new(&pts);
        let d = tree.nearest_dists(&qs);
        eprintln!("k-d tree: 100k build + 100k queries in {:?}", t0.elapsed());
        for k in (0..qs.len()).step_by(5000) {
            let bf = pts.iter().map(|p| dist2(p, &qs[k])).fold(f64::INFINITY, f64::min).sqrt();
            assert_eq!(d[k], bf);
        }
    }
}
