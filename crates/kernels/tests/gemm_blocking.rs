//! The GEMM's loop order and row blocks decide only where each tile's
//! products run, never the order of a sum: every blocking with the same `kc`
//! gives the same bits, and so does the single-thread entry point.
use recon_kernels::gemm::{gemm_blocked, gemm_on_this_thread, Blocking, PackedMatrix, WeightFormat};
use recon_kernels::isa::Isa;
use recon_kernels::vecmath::Activation;

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn values(seed: u64, n: usize) -> Vec<f32> {
    let mut s = seed;
    (0..n)
        .map(|_| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        })
        .collect()
}

#[test]
fn panel_blocks_and_row_blocks_keep_the_bits() {
    let (m, k, n) = (233, 700, 230);
    let a = values(1, m * k);
    let w = values(2, n * k);
    let bias = values(3, n);
    for isa in Isa::all_supported() {
        for format in [WeightFormat::F32, WeightFormat::Bf16, WeightFormat::F16] {
            let b = PackedMatrix::from_linear_weight(&w, n, k, format).unwrap();
            let run = |blk: Blocking| {
                let mut c = vec![0f32; m * n];
                gemm_blocked(isa, &a, m, k, &b, Some(&bias), Activation::GeluTanh, &mut c, n, blk).unwrap();
                bits(&c)
            };
            let kc = Blocking::for_isa(isa, format).kc;
            // nc 0: each panel past every A tile of the row block (the order before panel blocks).
            let want = run(Blocking { mc: 336, kc, nc: 0 });
            for (mc, nc) in [(336, 1), (336, 4), (70, 3), (28, 100), (1000, 2)] {
                assert!(run(Blocking { mc, kc, nc }) == want, "{isa:?} {format:?} mc {mc} nc {nc}");
            }
            let mut c = vec![0f32; m * n];
            gemm_on_this_thread(isa, &a, m, k, &b, Some(&bias), Activation::GeluTanh, &mut c, n).unwrap();
            assert!(bits(&c) == want, "{isa:?} {format:?} on this thread");
        }
    }
}
