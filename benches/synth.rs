//! `recon synth` throughput: a 50-scene, 640×480, one-view dataset with the stereo sensor
//! model (the "50 scenes in minutes on 2 cores"), plus the bare renderer's rays
//! per second. `cargo bench --bench synth` prints seconds, peak RSS and the target
//! occlusion histogram. `SYNTH_BENCH_SCENES` overrides the scene count.

use recon::sensor::SensorModel;
use recon::synth::{generate, Scene, SceneConfig, SynthOptions};
use std::time::Instant;

fn main() -> recon::Result<()> {
    let scenes: usize = std::env::var("SYNTH_BENCH_SCENES").ok().and_then(|v| v.parse().ok()).unwrap_or(50);
    let out = std::env::temp_dir().join(format!("recon-synth-bench-{}", std::process::id()));
    let opts = SynthOptions { scenes, views: 1, seed: 1, width: 640, height: 480, parts: false, sensor: SensorModel::stereo_default() };
    println!("synth bench: {scenes} scenes × 1 view, 640×480, stereo sensor, {} rayon threads", rayon::current_num_threads());
    let t0 = Instant::now();
    let s = generate(&out, &opts, &|| {})?;
    let secs = t0.elapsed().as_secs_f64();
    let b = s.target_occlusion_bins;
    println!("dataset: {secs:.2} s ({:.3} s/scene), {} GT instances, {} models", secs / scenes as f64, s.instances, s.models);
    println!("target occlusion: 0-3% {} | 3-20% {} | 20-40% {} | 40-70% {} | >70% {}", b[0], b[1], b[2], b[3], b[4]);
    std::fs::remove_dir_all(&out).ok();

    // Renderer alone: scene 0's view rendered repeatedly.
    let scene = Scene::generate(7, &SceneConfig::default())?;
    let units = scene.units(false)?;
    let ids: Vec<i64> = (0..units.len() as i64).collect();
    let reps = 5;
    let t0 = Instant::now();
    for _ in 0..reps {
        scene.render_view(&units, &ids, 0)?;
    }
    let per = t0.elapsed().as_secs_f64() / reps as f64;
    println!("render: {per:.3} s per 640×480 view ({} units), {:.2} Mpixel/s", units.len(), 640.0 * 480.0 / per / 1e6);
    if let Some(m) = recon::util::peak_rss_mib() {
        println!("peak RSS {m:.0} MiB");
    }
    Ok(())
}
