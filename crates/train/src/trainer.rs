//! The training loop: AdamW steps over an [`Objective`], gradient clipping,
//! the loss log and plot, checkpoints and bit-identical resume.
//!
//! **Determinism.** Every random draw of a run (batch choice, crop context,
//! flow times, noise, CFG dropout, posterior samples) comes from one
//! [`SeededRng`] seeded by `--seed` (per-sample preprocessing gets a seed
//! drawn from it, so running samples in parallel changes nothing); the
//! gradient norm is summed in parameter-name order. The same seed and data
//! give the same weights; a run resumed from a checkpoint continues exactly
//! as the uninterrupted run would (tests in `tests/train.rs`).
//!
//! **Checkpoints** (`<out>/checkpoints/step-NNNNNNN/`, the newest
//! `keep_checkpoints` kept): the trained modules' weights
//! (`<key>.safetensors`), the AdamW moments (`optimizer.safetensors`) and
//! `state.json` (step, optimizer step count, RNG state, settings). Each is
//! written to a `.partial` folder first and renamed when complete.

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::Instant;

use candle_core::{Device, Tensor, Var};
use candle_nn::ParamsAdamW;
use serde::{Deserialize, Serialize};

use crate::log::{append_log, loss_svg, read_log, truncate_log, LogRecord};
use crate::objective::Objective;
use crate::optim::{clip_grad_norm, AdamW};
use recon_core::rng::SeededRng;
use recon_core::weights::init::write_safetensors;
use recon_core::{Error, Result};

/// Optimisation settings shared by every objective.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LoopSettings {
    pub steps: usize,
    pub batch: usize,
    pub lr: f64,
    pub weight_decay: f64,
    /// Global gradient-norm clip (`None`: no clipping).
    pub grad_clip: Option<f64>,
    pub seed: u64,
    pub checkpoint_every: usize,
    pub keep_checkpoints: usize,
}

impl Default for LoopSettings {
    fn default() -> Self {
        Self {
            steps: 1000,
            batch: 8,
            lr: 2e-4,
            weight_decay: 0.0,
            grad_clip: Some(1.0),
            seed: 0,
            checkpoint_every: 500,
            keep_checkpoints: 2,
        }
    }
}

/// What `state.json` of a checkpoint holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CheckpointState {
    pub objective: String,
    pub step: usize,
    pub optimizer_step: usize,
    pub rng: [u64; 4],
    pub rng_spare_bits: Option<u64>,
    /// The run's settings (objective-specific ones included), compared on resume.
    pub settings: serde_json::Value,
}

/// Result of a run.
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    pub first_step: usize,
    pub last_step: usize,
    pub final_loss: Option<f64>,
    pub mean_step_seconds: f64,
    pub seconds: f64,
}

/// Trainable variables of every module, named `<module key>/<param>`.
fn all_vars(obj: &dyn Objective) -> Vec<(String, Var)> {
    obj.trainable().iter().flat_map(|m| m.vars.iter().map(move |(n, v)| (format!("{}/{n}", m.key), v.clone()))).collect()
}

pub fn checkpoint_dir(out: &Path, step: usize) -> PathBuf {
    out.join("checkpoints").join(format!("step-{step:07}"))
}

/// The newest complete checkpoint under `<out>/checkpoints`, if any.
pub fn latest_checkpoint(out: &Path) -> Result<Option<PathBuf>> {
    let dir = out.join("checkpoints");
    if !dir.is_dir() {
        return Ok(None);
    }
    let mut best: Option<(usize, PathBuf)> = None;
    for e in std::fs::read_dir(&dir).map_err(|e| Error::io(&dir, e))? {
        let p = e.map_err(|e| Error::io(&dir, e))?.path();
        let name = p.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if let Some(step) = name.strip_prefix("step-").and_then(|s| s.parse::<usize>().ok()) {
            if p.join("state.json").is_file() && best.as_ref().is_none_or(|b| step > b.0) {
                best = Some((step, p));
            }
        }
    }
    Ok(best.map(|b| b.1))
}

fn write_checkpoint(out: &Path, obj: &dyn Objective, opt: &AdamW, state: &CheckpointState, keep: usize) -> Result<PathBuf> {
    let dir = checkpoint_dir(out, state.step);
    let tmp = dir.with_extension("partial");
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).map_err(|e| Error::io(&tmp, e))?;
    }
    std::fs::create_dir_all(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let meta: BTreeMap<String, String> = [("recon.checkpoint_step".to_string(), state.step.to_string())].into();
    for m in obj.trainable() {
        write_safetensors(&m.export()?, &meta, &tmp.join(format!("{}.safetensors", m.key)))?;
    }
    write_safetensors(&opt.state_tensors()?, &meta, &tmp.join("optimizer.safetensors"))?;
    let json = serde_json::to_string_pretty(state).map_err(|e| Error::msg(e.to_string()))?;
    std::fs::write(tmp.join("state.json"), json).map_err(|e| Error::io(tmp.join("state.json"), e))?;
    if dir.exists() {
        std::fs::remove_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
    }
    std::fs::rename(&tmp, &dir).map_err(|e| Error::io(&dir, e))?;
    // Drop all but the newest `keep` checkpoints.
    let parent = out.join("checkpoints");
    let mut steps: Vec<(usize, PathBuf)> = std::fs::read_dir(&parent)
        .map_err(|e| Error::io(&parent, e))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter_map(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .and_then(|n| n.strip_prefix("step-"))
                .and_then(|s| s.parse().ok())
                .map(|s| (s, p.clone()))
        })
        .collect();
    steps.sort();
    let n = steps.len();
    for (_, p) in steps.into_iter().take(n.saturating_sub(keep.max(1))) {
        std::fs::remove_dir_all(&p).map_err(|e| Error::io(&p, e))?;
    }
    Ok(dir)
}

fn load_tensors(path: &Path) -> Result<BTreeMap<String, Tensor>> {
    let m = candle_core::safetensors::load(path, &Device::Cpu)
        .map_err(|e| Error::input(path.display().to_string(), format!("cannot read safetensors: {e}")))?;
    Ok(m.into_iter().collect())
}

/// Restore weights, optimizer and RNG from a checkpoint folder; returns its state.
fn load_checkpoint(dir: &Path, obj: &dyn Objective, opt: &mut AdamW, settings: &serde_json::Value) -> Result<CheckpointState> {
    let sp = dir.join("state.json");
    let state: CheckpointState = recon_core::util::json::read_json(&sp)?;
    let file = sp.display().to_string();
    if state.objective != obj.name() {
        return Err(Error::config(
            &file,
            "objective",
            format!("checkpoint is for `{}`, this run trains `{}`", state.objective, obj.name()),
        ));
    }
    // Everything but the step count must match, or the continuation is not the same run.
    let strip = |v: &serde_json::Value| {
        let mut v = v.clone();
        if let Some(l) = v.get_mut("loop").and_then(|l| l.as_object_mut()) {
            l.remove("steps");
        }
        v
    };
    let (a, b) = (strip(&state.settings), strip(settings));
    if a != b {
        let diff: Vec<String> = match (a.as_object(), b.as_object()) {
            (Some(x), Some(y)) => x.keys().chain(y.keys()).filter(|k| x.get(*k) != y.get(*k)).map(|k| k.to_string()).collect(),
            _ => vec!["<all>".into()],
        };
        return Err(Error::config(
            &file,
            "settings",
            format!("differ from this run's in {diff:?}; resume with the same options (only --steps may change)"),
        ));
    }
    for m in obj.trainable() {
        let p = dir.join(format!("{}.safetensors", m.key));
        let t = load_tensors(&p)?;
        for (name, var) in &m.vars {
            let v = t.get(name).ok_or_else(|| Error::MissingTensor {
                file: p.display().to_string(),
                name: name.clone(),
                expected: var.dims().to_vec(),
            })?;
            if v.dims() != var.dims() {
                return Err(Error::ShapeMismatch {
                    file: p.display().to_string(),
                    name: name.clone(),
                    found: v.dims().to_vec(),
                    expected: var.dims().to_vec(),
                });
            }
            var.set(v)?;
        }
    }
    let op = dir.join("optimizer.safetensors");
    opt.load_state(&load_tensors(&op)?, state.optimizer_step, &op.display().to_string())?;
    Ok(state)
}

/// Train `obj` for `settings.steps` steps (from a checkpoint when `resume`
/// is given), logging to `<out>/loss.jsonl` and `<out>/loss.svg`.
/// `run_settings` is the full settings record stored in checkpoints.
pub fn train(
    obj: &dyn Objective,
    settings: &LoopSettings,
    run_settings: &serde_json::Value,
    out: &Path,
    resume: Option<&Path>,
    progress: bool,
) -> Result<RunSummary> {
    if settings.batch == 0 || settings.steps == 0 {
        return Err(Error::config("train settings", "steps/batch", "must be positive"));
    }
    if !(settings.lr.is_finite() && settings.lr > 0.0) {
        return Err(Error::config("train settings", "lr", format!("{} must be a positive number", settings.lr)));
    }
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let vars = all_vars(obj);
    let params = ParamsAdamW { lr: settings.lr, weight_decay: settings.weight_decay, ..ParamsAdamW::default() };
    let mut opt = AdamW::new(&vars, params)?;
    let log_path = out.join("loss.jsonl");
    let (mut rng, first) = match resume {
        Some(dir) => {
            let st = load_checkpoint(dir, obj, &mut opt, run_settings)?;
            if st.step >= settings.steps {
                return Err(Error::config(
                    dir.display().to_string(),
                    "step",
                    format!("checkpoint is at step {} already; ask for more --steps", st.step),
                ));
            }
            truncate_log(&log_path, st.step)?;
            (SeededRng::from_state(st.rng, st.rng_spare_bits), st.step + 1)
        }
        None => {
            if log_path.exists() {
                std::fs::remove_file(&log_path).map_err(|e| Error::io(&log_path, e))?;
            }
            (SeededRng::new(settings.seed), 1)
        }
    };
    let bar = if progress && std::io::stderr().is_terminal() {
        let b = indicatif::ProgressBar::new(settings.steps as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} ({elapsed} < {eta})")
                .map_err(|e| Error::msg(e.to_string()))?
                .progress_chars("=> "),
        );
        b.set_prefix(obj.name().to_string());
        b.set_position(first as u64 - 1);
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let t_run = Instant::now();
    let mut last_loss = None;
    let mut step_secs = 0.0;
    for step in first..=settings.steps {
        let t0 = Instant::now();
        let bl = obj.loss(&mut rng, settings.batch)?;
        let loss = bl.total.to_scalar::<f32>()? as f64;
        if !loss.is_finite() {
            return Err(Error::msg(format!("{} step {step}: loss is {loss} (diverged; lower --lr)", obj.name())));
        }
        let mut grads = bl.total.backward()?;
        let grad_norm = clip_grad_norm(&mut grads, &vars, settings.grad_clip)?;
        opt.step(&grads)?;
        drop(grads);
        let seconds = t0.elapsed().as_secs_f64();
        step_secs += seconds;
        append_log(&log_path, &LogRecord { step, loss, terms: bl.terms, info: bl.info, grad_norm, lr: settings.lr, seconds })?;
        last_loss = Some(loss);
        bar.set_position(step as u64);
        bar.set_message(format!("loss {loss:.4}"));
        if step % settings.checkpoint_every.max(1) == 0 || step == settings.steps {
            let (s, spare) = rng.state();
            let st = CheckpointState {
                objective: obj.name().to_string(),
                step,
                optimizer_step: opt.step_t,
                rng: s,
                rng_spare_bits: spare,
                settings: run_settings.clone(),
            };
            write_checkpoint(out, obj, &opt, &st, settings.keep_checkpoints)?;
            write_plot(out, obj.name())?;
        }
    }
    bar.finish_and_clear();
    let n = settings.steps + 1 - first;
    Ok(RunSummary {
        first_step: first,
        last_step: settings.steps,
        final_loss: last_loss,
        mean_step_seconds: step_secs / n.max(1) as f64,
        seconds: t_run.elapsed().as_secs_f64(),
    })
}

/// `<out>/loss.svg` from `<out>/loss.jsonl`.
pub fn write_plot(out: &Path, title: &str) -> Result<()> {
    let recs = read_log(&out.join("loss.jsonl"))?;
    let p = out.join("loss.svg");
    std::fs::write(&p, loss_svg(&recs, &format!("recon train {title}"))).map_err(|e| Error::io(&p, e))
}

/// Write the final weights of every trained module as `<out>/<key>.safetensors`
/// (through a temporary file, renamed when complete), labelled as trained.
pub fn write_weights(out: &Path, obj: &dyn Objective, extra_meta: &BTreeMap<String, String>) -> Result<Vec<PathBuf>> {
    let mut written = Vec::new();
    for m in obj.trainable() {
        let mut meta = extra_meta.clone();
        meta.insert("recon.trained".into(), "true".into());
        meta.insert("recon.module".into(), m.config.name.clone());
        meta.insert("recon.key".into(), m.key.to_string());
        let path = out.join(format!("{}.safetensors", m.key));
        let tmp = out.join(format!(".{}.safetensors.partial", m.key));
        write_safetensors(&m.export()?, &meta, &tmp)?;
        std::fs::rename(&tmp, &path).map_err(|e| Error::io(&path, e))?;
        written.push(path);
    }
    Ok(written)
}
