//! A depth correction (`recon audit depth`'s `depth_correction.json`) applied to the frames
//! of a dataset before they are evaluated (`recon eval --depth-correction`).
use recon_core::dataset::bop::{Dataset, Frame};
use recon_core::dataset::frame::Intrinsics;
use recon_core::sensor::{DepthCorrection, Pinhole};
use std::collections::BTreeMap;

/// A [`DepthCorrection`] with the frame index of every frame of a dataset: its position
/// in the dataset as loaded (scenes and images sorted), the index the depth audit gives
/// it, so a drift correction sees the same frame numbers the audit fitted.
#[derive(Clone, Debug)]
pub struct DatasetCorrection {
    /// The correction.
    pub correction: DepthCorrection,
    index: BTreeMap<(String, u32), i64>,
}

impl DatasetCorrection {
    /// Frame indices from `ds` as loaded: build it before any scene filter.
    pub fn new(correction: DepthCorrection, ds: &Dataset) -> Self {
        let index = ds.frames.iter().enumerate().map(|(i, f)| ((f.scene.clone(), f.frame), i as i64)).collect();
        DatasetCorrection { correction, index }
    }

    /// The frame's index in the audited order (0 for a frame the dataset did not list).
    pub fn frame_index(&self, f: &Frame) -> i64 {
        self.index.get(&(f.scene.clone(), f.frame)).copied().unwrap_or(0)
    }

    /// Corrects `depth` (metres, `w × h`) of frame `f` taken with intrinsics `k`.
    pub fn apply(&self, f: &Frame, depth: &[f32], w: usize, h: usize, k: &Intrinsics) -> Vec<f32> {
        let pin = Pinhole { fx: k.fx, fy: k.fy, cx: k.cx, cy: k.cy };
        self.correction.apply(depth, w, h, pin, self.frame_index(f))
    }
}
