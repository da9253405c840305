//! Training cost of an architecture (default `models/recgen-nano.json`):
//! parameters and f32 size per module, then seconds per training step of
//! the SS VAE and the SS flow (data + forward, backward, AdamW update) on
//! toy data, and peak RSS.
//!
//! `cargo bench --bench train [-- CONFIG [BATCH [STEPS [vae|flow]]]]`
//!
//! On a machine shared with other jobs, set `CANDLE_NUM_THREADS=1`: candle's
//! element-wise worker pool spin-waits, which wastes the whole time slice
//! when its worker thread is descheduled.

use std::path::PathBuf;
use std::time::Instant;

use candle_nn::ParamsAdamW;
use recon::geometry::Fill;
use recon::geometry::PoseStats;
use recon::model::RecGenConfig;
use recon::model::ReconLoss;
use recon::rng::SeededRng;
use recon::train::FlowMatching;
use recon::train::ModuleParams;
use recon::train::{clip_grad_norm, AdamW};
use recon::train::{pose_stats_json, scan};
use recon::train::{FlowObjective, Objective, VaeObjective};
use recon::train::{ToyConfig, ToySource};
use recon::weights::ModuleConfig;

fn cfg(s: &recon::model::ModuleSpec) -> ModuleConfig {
    ModuleConfig { name: s.name.clone(), args: s.args.clone() }
}

fn time_steps(obj: &dyn Objective, batch: usize, steps: usize) -> (f64, f64, f64) {
    let vars: Vec<_> =
        obj.trainable().iter().flat_map(|m| m.vars.iter().map(move |(n, v)| (format!("{}/{n}", m.key), v.clone()))).collect();
    let mut opt = AdamW::new(&vars, ParamsAdamW { lr: 1e-4, weight_decay: 0.0, ..Default::default() }).unwrap();
    let mut rng = SeededRng::new(1);
    let (mut f, mut b, mut u) = (0.0, 0.0, 0.0);
    // One warm-up step, then `steps` timed ones.
    for i in 0..=steps {
        let t = Instant::now();
        let l = obj.loss(&mut rng, batch).unwrap();
        let tf = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let mut g = l.total.backward().unwrap();
        let tb = t.elapsed().as_secs_f64();
        let t = Instant::now();
        clip_grad_norm(&mut g, &vars, Some(1.0)).unwrap();
        opt.step(&g).unwrap();
        let tu = t.elapsed().as_secs_f64();
        if i > 0 {
            f += tf;
            b += tb;
            u += tu;
        }
    }
    let n = steps.max(1) as f64;
    (f / n, b / n, u / n)
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let config = args.first().map(PathBuf::from).unwrap_or_else(|| root.join("models/recgen-nano.json"));
    let batch: usize = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(8);
    let steps: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(3);
    let only = args.get(3).map(String::as_str);
    let arch = RecGenConfig::load(&config).unwrap();
    println!(
        "architecture {} ({}), batch {batch}, {steps} timed steps after one warm-up, {} threads",
        arch.name,
        config.display(),
        rayon::current_num_threads()
    );
    println!("{:<18} {:>12} {:>10}", "module", "parameters", "MB (f32)");
    let mut shipped = 0usize;
    let mut modules: Vec<(&str, ModuleConfig)> = arch.modules().into_iter().map(|(k, s)| (k, cfg(s))).collect();
    if let Some(e) = &arch.ss_encoder {
        modules.push(("ss_encoder (train)", cfg(e)));
    }
    for (key, c) in &modules {
        let n: usize = recon::weights::expected_tensors(c, key).unwrap().iter().map(|s| s.shape.iter().product::<usize>()).sum();
        if !key.contains("train") {
            shipped += n;
        }
        println!("{key:<18} {n:>12} {:>10.2}", n as f64 * 4.0 / 1e6);
    }
    println!("{:<18} {shipped:>12} {:>10.2}", "shipped total", shipped as f64 * 4.0 / 1e6);

    if only == Some("none") {
        return;
    }
    let src =
        ToySource::new(ToyConfig { models: 8, samples: 16, width: 320, height: 240, seed: 1, occluders: true, second_view: true }).unwrap();
    let enc_cfg = cfg(arch.ss_encoder.as_ref().expect("the architecture needs an ss_encoder section"));
    if only != Some("flow") {
        recon::util::reset_peak_rss();
        let enc = ModuleParams::init("ss_encoder", &enc_cfg, 1).unwrap();
        let dec = ModuleParams::init("ss_decoder", &cfg(&arch.ss_decoder), 2).unwrap();
        let f = recon::model::SparseStructureEncoderConfig::from_json(&enc_cfg.args).unwrap().downsample_factor();
        let res = arch.ss_flow_config().unwrap().resolution * f;
        let vae = VaeObjective::new(&src, enc, dec, res, Fill::Solid, ReconLoss::Dice, 1e-3).unwrap();
        let (tf, tb, tu) = time_steps(&vae, batch, steps);
        println!(
            "ss-vae  ({res}³): data+forward {tf:.3} s, backward {tb:.3} s, update {tu:.3} s → {:.3} s/step; peak RSS {:.0} MiB",
            tf + tb + tu,
            recon::util::peak_rss_mib().unwrap_or(f64::NAN)
        );
    }
    if only == Some("vae") {
        return;
    }

    recon::util::reset_peak_rss();
    let enc_p = ModuleParams::init("ss_encoder", &enc_cfg, 1).unwrap();
    let encoder = recon::weights::build_ss_encoder(&enc_cfg, enc_p.var_builder(), "ss_encoder", recon::model::Compute::Plain).unwrap();
    let sc = scan(&src).unwrap();
    let stats = PoseStats::from_value(&pose_stats_json(&sc.poses, arch.pose.nine_d_layout, "toy").unwrap(), "toy").unwrap();
    let dino = ModuleParams::init("image_cond_model", &cfg(&arch.image_cond_model), 3).unwrap();
    let flow = ModuleParams::init("ss_flow", &cfg(&arch.ss_flow), 4).unwrap();
    let mut obj = FlowObjective::new(&src, sc, stats, dino, flow, &encoder, Fill::Solid, FlowMatching::default()).unwrap();
    for (label, p) in [("1 view", 0.0), ("2 views", 1.0)] {
        obj.p_two_view = p;
        let (tf, tb, tu) = time_steps(&obj, batch, steps);
        println!(
            "ss-flow ({label}): data+forward {tf:.3} s, backward {tb:.3} s, update {tu:.3} s → {:.3} s/step; peak RSS {:.0} MiB",
            tf + tb + tu,
            recon::util::peak_rss_mib().unwrap_or(f64::NAN)
        );
    }
}
