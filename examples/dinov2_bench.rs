//! Times the full-size DINOv2 ViT-L/14-reg forward (random weights) on one
//! 518×518 image: `cargo run --release --example dinov2_bench [-- N]`.

use candle_core::{Device, Tensor};
use recon::model::{recgen_cond, Dinov2, Dinov2Config};
use recon::weights::RandomInit;

fn main() -> anyhow::Result<()> {
    let runs: usize = std::env::args().nth(1).and_then(|s| s.parse().ok()).unwrap_or(2);
    let cfg = Dinov2Config::vitl14_reg();
    let t0 = std::time::Instant::now();
    let init = RandomInit::new(0);
    let model = Dinov2::new(&cfg, init.var_builder(&Device::Cpu), recon::model::Compute::Plain)?;
    println!("init {:.2}s", t0.elapsed().as_secs_f64());
    let x = Tensor::randn(0f32, 1.0, (1, 3, 518, 518), &Device::Cpu)?;
    for i in 0..runs {
        let t = std::time::Instant::now();
        let out = model.forward(&x)?;
        let c = recgen_cond(&out.x_prenorm, cfg.num_prefix_tokens())?;
        println!("run {i}: forward {:.2}s, cond {:?}", t.elapsed().as_secs_f64(), c.dims());
    }
    println!("threads: {}", rayon::current_num_threads());
    Ok(())
}
