//! 3D Gaussians (activated values) and the standard 3DGS PLY layout read by
//! common splat viewers: x y z nx ny nz f_dc_0..2 opacity scale_0..2 rot_0..3,
//! all float, with opacity as a logit, log scales and rotation (w, x, y, z).

use super::axes::{write_file, Axes};
use crate::gaussians::Gaussians;
use crate::math::{normalize_quat, Similarity32};
use crate::Result;
use std::path::Path;

/// The 17 per-splat properties, in file order.
pub const SPLAT_PROPERTIES: [&str; 17] = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2",
    "rot_3",
];

fn logit(p: f32) -> f32 {
    let p = p.clamp(1e-6, 1.0 - 1e-6);
    (p / (1.0 - p)).ln()
}

/// Serialise as a binary little-endian 3DGS PLY.
pub fn splat_ply_bytes(g: &Gaussians, axes: Axes) -> Result<Vec<u8>> {
    g.validate()?;
    let placed;
    let g = if axes == Axes::ZUp {
        g
    } else {
        placed = Similarity32::new(axes.matrix(), [0.0; 3], 1.0)?.apply_gaussians(g);
        &placed
    };
    let mut h = format!("ply\nformat binary_little_endian 1.0\nelement vertex {}\n", g.len());
    for p in SPLAT_PROPERTIES {
        h += &format!("property float {p}\n");
    }
    h += "end_header\n";
    let mut out = h.into_bytes();
    out.reserve(g.len() * 17 * 4);
    for i in 0..g.len() {
        let q = normalize_quat(g.rotations[i]);
        let s = g.scales[i].map(|x| x.max(1e-12).ln());
        let row = [
            g.positions[i][0],
            g.positions[i][1],
            g.positions[i][2],
            0.0,
            0.0,
            0.0,
            g.dc[i][0],
            g.dc[i][1],
            g.dc[i][2],
            logit(g.opacities[i]),
            s[0],
            s[1],
            s[2],
            q[0],
            q[1],
            q[2],
            q[3],
        ];
        for x in row {
            out.extend_from_slice(&x.to_le_bytes());
        }
    }
    Ok(out)
}

/// Writes the Gaussians as a 3D Gaussian splatting PLY file.
pub fn save_splat_ply(g: &Gaussians, path: &Path, axes: Axes) -> Result<()> {
    write_file(path, &splat_ply_bytes(g, axes)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::export::ply::split_header;

    fn two() -> Gaussians {
        Gaussians {
            positions: vec![[0.1, 0.2, 0.3], [-0.1, 0.0, 0.4]],
            scales: vec![[0.01, 0.02, 0.03], [0.5, 1.0, 2.0]],
            rotations: vec![[1.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0]],
            opacities: vec![0.5, 0.9],
            dc: vec![[0.1, -0.2, 0.3], [1.0, 1.0, 1.0]],
        }
    }

    #[test]
    fn property_order_and_values() {
        let b = splat_ply_bytes(&two(), Axes::ZUp).unwrap();
        let (head, body) = split_header(&b).unwrap();
        assert_eq!(head[1], "format binary_little_endian 1.0");
        assert_eq!(head[2], "element vertex 2");
        let props: Vec<String> = head.iter().filter(|l| l.starts_with("property")).cloned().collect();
        let want: Vec<String> = SPLAT_PROPERTIES.iter().map(|p| format!("property float {p}")).collect();
        assert_eq!(props, want);
        assert_eq!(body.len(), 2 * 17 * 4);
        let f: Vec<f32> = body.chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
        let r1 = &f[17..];
        assert_eq!(&r1[0..3], &[-0.1, 0.0, 0.4]);
        assert_eq!(&r1[6..9], &[1.0, 1.0, 1.0]);
        assert!((r1[9] - (0.9f32 / 0.1).ln()).abs() < 1e-5);
        assert!((r1[10] - 0.5f32.ln()).abs() < 1e-6 && r1[11].abs() < 1e-6 && (r1[12] - 2f32.ln()).abs() < 1e-6);
        assert_eq!(&r1[13..17], &[0.0, 1.0, 0.0, 0.0]); // normalised
        assert_eq!(f[9], 0.0); // logit(0.5)
    }

    #[test]
    fn y_up_moves_positions_and_mismatched_lengths_fail() {
        let b = splat_ply_bytes(&two(), Axes::YUp).unwrap();
        let (_, body) = split_header(&b).unwrap();
        let f: Vec<f32> = body.chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
        assert!((f[0] - 0.1).abs() < 1e-7 && (f[1] - 0.3).abs() < 1e-7 && (f[2] + 0.2).abs() < 1e-7);
        let mut bad = two();
        bad.opacities.pop();
        assert!(splat_ply_bytes(&bad, Axes::ZUp).is_err());
    }
}
