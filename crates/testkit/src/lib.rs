//! What the tests of every crate above recon-core share: fresh temporary
//! folders, the small BOP fixture, primitive meshes, random weights and
//! gradient checks. One definition each; recon-core's own unit tests use the
//! same items inside recon-core (doc-hidden modules re-exported here).

use recon_core::mesh::Mesh;

pub use recon_core::dataset::bop::tests::write_bop;
pub use recon_core::model::nn::gradcheck;
pub use recon_core::util::testing::{repo, tmp};
pub use recon_core::weights::init::write_random_init;
pub use recon_core::weights::registry::random_var_builder;

/// Primitive meshes: recon-core's ([`recon_core::mesh::primitives`]) and the
/// test shapes built on them.
pub mod meshes {
    pub use recon_core::mesh::primitives::*;

    use super::Mesh;

    /// The closed box of half extents `half` centred at `c`, outward faces.
    pub fn box_at(half: [f32; 3], c: [f32; 3]) -> Mesh {
        box_between(std::array::from_fn(|k| c[k] - half[k]), std::array::from_fn(|k| c[k] + half[k]))
    }

    /// The closed z-axis cylinder of radius `r` and height `h` centred at the
    /// origin, `seg` flat sides, caps fanned from their centres (vertices 0 and 1).
    pub fn plain_cylinder(r: f32, h: f32, seg: u32) -> Mesh {
        let mut vertices = vec![[0.0, 0.0, -h / 2.0], [0.0, 0.0, h / 2.0]];
        for i in 0..seg {
            let a = std::f32::consts::TAU * i as f32 / seg as f32;
            vertices.push([r * a.cos(), r * a.sin(), -h / 2.0]);
            vertices.push([r * a.cos(), r * a.sin(), h / 2.0]);
        }
        let mut faces = Vec::new();
        for i in 0..seg {
            let (b0, t0, b1, t1) = (2 + 2 * i, 3 + 2 * i, 2 + 2 * ((i + 1) % seg), 3 + 2 * ((i + 1) % seg));
            faces.extend([[0, b1, b0], [1, t0, t1], [b0, b1, t1], [b0, t1, t0]]);
        }
        Mesh { vertices, faces, vertex_attrs: None }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tmp_is_fresh_and_empty() {
        let d = tmp("testkit-fresh");
        std::fs::write(d.join("x"), "1").unwrap();
        let again = tmp("testkit-fresh");
        assert_eq!(again, d);
        assert_eq!(std::fs::read_dir(&again).unwrap().count(), 0);
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn box_at_spans_centre_minus_to_plus_half() {
        let m = meshes::box_at([0.5, 1.0, 2.0], [1.0, 0.0, -1.0]);
        assert_eq!((m.vertices.len(), m.faces.len()), (8, 12));
        assert_eq!(m.vertices[0], [0.5, -1.0, -3.0]);
        assert_eq!(m.vertices[7], [1.5, 1.0, 1.0]);
        // Closed and outward: the signed volume is the box's.
        let vol: f64 = m
            .faces
            .iter()
            .map(|f| {
                let [a, b, c] = f.map(|i| m.vertices[i as usize].map(f64::from));
                (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0]) + a[2] * (b[0] * c[1] - b[1] * c[0])) / 6.0
            })
            .sum();
        assert!((vol - 8.0).abs() < 1e-9, "{vol}");
    }
}
