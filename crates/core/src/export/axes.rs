//! The output axis convention and the one file writer the formats share.

use crate::{Error, Result};
use std::path::Path;

/// Output axis convention. The decoders work z-up; TRELLIS exports y-up by
/// right-multiplying row vectors with `[[1,0,0],[0,0,-1],[0,1,0]]`, i.e.
/// (x, y, z) ↦ (x, z, −y).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axes {
    /// As the decoders work: z up (identity).
    ZUp,
    /// y up, as TRELLIS exports: (x, y, z) ↦ (x, z, −y).
    YUp,
}

impl Axes {
    /// The point `v` in these axes.
    pub fn apply(self, v: [f32; 3]) -> [f32; 3] {
        match self {
            Axes::ZUp => v,
            Axes::YUp => [v[0], v[2], -v[1]],
        }
    }

    /// The rotation as a matrix acting on column vectors.
    pub fn matrix(self) -> [[f32; 3]; 3] {
        match self {
            Axes::ZUp => [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            Axes::YUp => [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]],
        }
    }
}

pub(crate) fn write_file(path: &Path, bytes: &[u8]) -> Result<()> {
    std::fs::write(path, bytes).map_err(|e| Error::io(path, e))
}

#[cfg(test)]
mod tests {
    #[test]
    fn y_up_matrix_matches_apply() {
        let m = super::Axes::YUp.matrix();
        let v = [0.3f32, -0.7, 0.2];
        let mv = [0, 1, 2].map(|r| m[r][0] * v[0] + m[r][1] * v[1] + m[r][2] * v[2]);
        assert_eq!(mv, super::Axes::YUp.apply(v));
    }
}
