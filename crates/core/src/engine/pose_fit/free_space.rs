//! What a view observed of an object: its points ([`ViewPoints`]) and its
//! depth image ([`DepthView`]), and the free-space term: how far a posed
//! surface lies in front of the measured depth, which an oversized mesh cannot
//! avoid.

use std::sync::Arc;

use crate::dataset::frame::{depth_valid, Intrinsics};
use crate::engine::pose_fit::options::AlignOptions;
use crate::math::Similarity;
use crate::spatial::P3;
use crate::util::trimmed_mean;

/// One view's observed object points.
#[derive(Debug, Clone)]
pub struct ViewPoints {
    /// Points in this view's camera frame, metres.
    pub points: Vec<P3>,
    /// This camera → the anchor (first) camera, rigid.
    pub to_anchor: Similarity,
    /// This view's depth image, for the free-space term (`None`: points only).
    pub depth: Option<std::sync::Arc<DepthView>>,
}

/// A view's depth image prepared for free-space tests (3×3 minimum filter).
#[derive(Debug, Clone)]
pub struct DepthView {
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// The depth camera's intrinsics.
    pub k: Intrinsics,
    /// Minimum valid depth over each pixel's 3×3 neighbourhood (0: none valid).
    min_depth: Vec<f32>,
}

impl DepthView {
    /// From a metric depth image (`0`/non-finite = invalid); `None` when the
    /// sizes disagree.
    pub fn new(depth_m: &[f32], width: usize, height: usize, k: Intrinsics) -> Option<Arc<Self>> {
        if depth_m.len() != width * height || width == 0 || height == 0 {
            return None;
        }
        let mut min_depth = vec![0f32; width * height];
        for v in 0..height {
            for u in 0..width {
                let mut m = f32::INFINITY;
                for vv in v.saturating_sub(1)..(v + 2).min(height) {
                    for uu in u.saturating_sub(1)..(u + 2).min(width) {
                        let z = depth_m[vv * width + uu];
                        if depth_valid(z) && z < m {
                            m = z;
                        }
                    }
                }
                min_depth[v * width + u] = if m.is_finite() { m } else { 0.0 };
            }
        }
        Some(Arc::new(DepthView { width, height, k, min_depth }))
    }

    /// The filtered depth at the pixel a camera-frame point projects to
    /// (`None`: behind the camera, off the image, or no valid reading).
    #[inline]
    pub fn depth_at(&self, q: &P3) -> Option<f64> {
        if q[2] <= 1e-6 {
            return None;
        }
        let u = (self.k.fx * q[0] / q[2] + self.k.cx).round();
        let v = (self.k.fy * q[1] / q[2] + self.k.cy).round();
        if u < 0.0 || v < 0.0 || u >= self.width as f64 || v >= self.height as f64 {
            return None;
        }
        let d = self.min_depth[v as usize * self.width + u as usize];
        (d > 0.0).then_some(d as f64)
    }
}

/// Trimmed mean (metres) of the free-space violations of `samples` (surface
/// frame) placed by `pose` (surface → anchor) in `view`; 0 without a depth
/// image or when no sample lands on a valid pixel.
pub fn free_space(samples: &[P3], pose: &Similarity, view: &ViewPoints, opts: &AlignOptions) -> f64 {
    let Some(depth) = view.depth.as_deref() else { return 0.0 };
    let to_view = view.to_anchor.inverse().compose(pose);
    let v: Vec<f64> = samples
        .iter()
        .filter_map(|p| {
            let q = to_view.apply(p);
            depth.depth_at(&q).map(|d| (d - opts.free_space_margin_m - q[2]).clamp(0.0, opts.free_space_cap_m))
        })
        .collect();
    if v.is_empty() {
        0.0
    } else {
        trimmed_mean(&v, opts.trim)
    }
}
