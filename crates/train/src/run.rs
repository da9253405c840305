//! One training run of `recon train`, as a library call (the CLI parses
//! arguments and calls [`run`]; the smoke tests call it directly).
//!
//! **Output folder** (`--out`):
//! - `recon-train.json`: the run record (also the marker that the folder
//!   belongs to `recon train`; any other non-empty folder is refused);
//! - `<key>.safetensors`: the trained modules, labelled `recon.trained`
//!   (`ss_encoder` + `ss_decoder` for ss-vae; `image_cond_model` +
//!   `ss_flow` for ss-flow, plus a copy of the VAE's `ss_decoder`, so the
//!   folder runs stage 1 with `Pipeline::load_stages`);
//! - ss-flow only: `pose_stats.json` (training-set pose statistics) and the
//!   architecture file with its pose-stat paths pointing at it;
//! - `loss.jsonl`, `loss.svg`, `checkpoints/`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::data::{pose_stats_json, scan, TrainingSource};
use crate::flow::FlowMatching;
use crate::objective::{fixed_eval, frozen_var_builder, FlowObjective, Objective, VaeObjective};
use crate::params::ModuleParams;
use crate::trainer::{latest_checkpoint, train, write_weights, LoopSettings, RunSummary};
use recon_core::geometry::pose::PoseStats;
use recon_core::geometry::voxelize::Fill;
use recon_core::model::config::{ModuleKey, RecGenConfig};
use recon_core::model::stage1::ss_vae::encoder::ReconLoss;
use recon_core::model::Compute;
use recon_core::weights::registry::{self, ModuleConfig};
use recon_core::{Error, Result};

/// Which model to train.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    /// Sparse-structure VAE (stage 1).
    SsVae,
    /// Sparse-structure flow with pose tokens (stage 1).
    SsFlow,
    /// Structured-latent encoder and decoders (stage 2).
    SlatAe,
    /// Structured-latent flow (stage 2).
    SlatFlow,
}

impl Stage {
    /// Kebab-case name, as on the command line (`ss-vae`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Stage::SsVae => "ss-vae",
            Stage::SsFlow => "ss-flow",
            Stage::SlatAe => "slat-ae",
            Stage::SlatFlow => "slat-flow",
        }
    }
}

/// Where to resume from.
#[derive(Debug, Clone, PartialEq)]
pub enum Resume {
    /// The newest checkpoint under `<out>/checkpoints`.
    Latest,
    /// A given checkpoint folder.
    Dir(PathBuf),
}

/// Everything a run needs besides its data.
#[derive(Debug, Clone)]
pub struct TrainOptions {
    /// Which model to train.
    pub stage: Stage,
    /// Architecture file (`models/recgen-nano.json`).
    pub config: PathBuf,
    /// Output folder (weights, checkpoints, logs).
    pub out: PathBuf,
    /// Resume from a checkpoint (`None`: start fresh).
    pub resume: Option<Resume>,
    /// Optimisation settings (steps, batch, learning rate, ...).
    pub settings: LoopSettings,
    /// How the model meshes are voxelised (surface or solid).
    pub fill: Fill,
    /// ss-vae: reconstruction loss.
    pub recon_loss: ReconLoss,
    /// ss-vae: weight of the KL term.
    pub lambda_kl: f64,
    /// ss-flow, slat-flow: flow-matching hyper-parameters.
    pub flow: FlowMatching,
    /// ss-flow: crop context factor range (inference uses 1.2).
    pub context: [f64; 2],
    /// ss-flow: probability of a two-view batch.
    pub p_two_view: f64,
    /// ss-flow: the ss-vae output folder (`ss_encoder.safetensors`, `ss_decoder.safetensors`).
    pub vae: Option<PathBuf>,
    /// slat-ae: crop side in voxels (0: whole objects) and most voxels per crop.
    pub crop: usize,
    /// slat-ae: most voxels per crop.
    pub max_voxels: usize,
    /// slat-flow: the ss-flow output folder (frozen image encoder, pose
    /// statistics, stage-1 modules copied into the complete model folder).
    pub stage1: Option<PathBuf>,
    /// slat-flow: the slat-ae output folder (frozen encoder, decoders copied).
    pub slat_ae: Option<PathBuf>,
    /// slat-flow: most models encoded.
    pub max_models: usize,
    /// Warm start: the trained modules start from this folder's
    /// `<key>.safetensors` (a finished run of the same stage) instead of
    /// random; the optimiser starts afresh, so settings may differ.
    pub init: Option<PathBuf>,
    /// Show a progress bar.
    pub progress: bool,
    /// Batches of the fixed evaluation before and after training (0: skip).
    pub eval_batches: usize,
}

impl TrainOptions {
    /// Defaults for `stage`, reading the architecture from `config` and writing to `out`.
    pub fn new(stage: Stage, config: PathBuf, out: PathBuf) -> Self {
        Self {
            stage,
            config,
            out,
            resume: None,
            settings: LoopSettings::default(),
            fill: Fill::Solid,
            // TRELLIS's SS VAE recipe: Dice on occupancy, λ_KL = 1e-3.
            recon_loss: ReconLoss::Dice,
            lambda_kl: 1e-3,
            flow: FlowMatching::default(),
            context: [1.2, 2.0],
            p_two_view: 0.5,
            vae: None,
            crop: 10,
            max_voxels: 400,
            stage1: None,
            slat_ae: None,
            max_models: 1000,
            init: None,
            progress: true,
            eval_batches: 4,
        }
    }
}

/// The run record (`recon-train.json`).
#[derive(Debug, Clone, Serialize)]
pub struct RunReport {
    pub stage: Stage,
    pub status: &'static str,
    pub architecture: String,
    pub data: String,
    pub params: BTreeMap<String, usize>,
    pub settings: serde_json::Value,
    pub summary: Option<RunSummary>,
    /// Mean loss of a fixed set of batches before / after training.
    pub eval_before: Option<f64>,
    pub eval_after: Option<f64>,
    pub files: Vec<PathBuf>,
    pub notes: Vec<String>,
}

const MARKER: &str = "recon-train.json";
const EVAL_SEED: u64 = 0x5EED_E7A1;

/// Refuse folders that are not ours, and finished-or-started runs without `--resume`.
fn check_out(out: &Path, resume: bool) -> Result<()> {
    if !out.exists() {
        return Ok(());
    }
    let non_empty = std::fs::read_dir(out).map_err(|e| Error::io(out, e))?.next().is_some();
    if !non_empty {
        return Ok(());
    }
    if !out.join(MARKER).is_file() {
        return Err(Error::input(
            out.display().to_string(),
            format!("folder exists and is not a recon train output (no {MARKER}); choose an empty or new --out"),
        ));
    }
    if !resume {
        return Err(Error::input(
            out.display().to_string(),
            "already holds a training run; pass --resume to continue it or choose another --out",
        ));
    }
    Ok(())
}

fn write_json(path: &Path, v: &impl Serialize) -> Result<()> {
    let s = serde_json::to_string_pretty(v).map_err(|e| Error::msg(e.to_string()))?;
    let tmp = path.with_extension("json.partial");
    std::fs::write(&tmp, s).map_err(|e| Error::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| Error::io(path, e))
}

fn load_module(dir: &Path, key: ModuleKey) -> Result<BTreeMap<String, candle_core::Tensor>> {
    let p = dir.join(format!("{key}.safetensors"));
    if !p.is_file() {
        return Err(Error::input(
            dir.display().to_string(),
            format!("no {key}.safetensors (give the output folder of the `recon train` stage that writes it)"),
        ));
    }
    let m = candle_core::safetensors::load(&p, &candle_core::Device::Cpu)
        .map_err(|e| Error::input(p.display().to_string(), format!("cannot read: {e}")))?;
    Ok(m.into_iter().collect())
}

/// Write `tensors` as `<out>/<key>.safetensors`, labelled trained and copied from `from`
/// (the modules a run's folder carries beside its own, so the folder runs a pipeline).
fn write_copied_module(tensors: &BTreeMap<String, candle_core::Tensor>, from: &Path, out: &Path, key: ModuleKey) -> Result<PathBuf> {
    let meta: BTreeMap<String, String> =
        [("recon.trained".to_string(), "true".to_string()), ("recon.copied_from".to_string(), from.display().to_string())].into();
    let path = out.join(format!("{key}.safetensors"));
    recon_core::weights::init::write_safetensors(tensors, &meta, &path)?;
    Ok(path)
}

/// The architecture file of a run folder: `config` reading its pose statistics from
/// the folder's `pose_stats.json`, and with `slat_norm` as its `slat_normalization`.
fn write_architecture(config: &Path, out: &Path, slat_norm: Option<&(Vec<f32>, Vec<f32>)>) -> Result<PathBuf> {
    let mut v: serde_json::Value = recon_core::util::json::read_json(config)?;
    v["pose"]["ss_stats"] = "pose_stats.json".into();
    v["pose"]["slat_stats"] = "pose_stats.json".into();
    if let Some((m, s)) = slat_norm {
        v["slat_normalization"] = serde_json::json!({"mean": m, "std": s});
    }
    let name = config.file_name().ok_or_else(|| Error::input(config.display().to_string(), "not a file"))?;
    let arch_out = out.join(name);
    write_json(&arch_out, &v)?;
    Ok(arch_out)
}

/// Run one stage on `source` (see the module docs for what is written).
pub fn run(source: &dyn TrainingSource, opts: &TrainOptions) -> Result<RunReport> {
    let arch = RecGenConfig::load(&opts.config)?;
    let cfile = opts.config.display().to_string();
    check_out(&opts.out, opts.resume.is_some())?;
    std::fs::create_dir_all(&opts.out).map_err(|e| Error::io(&opts.out, e))?;
    let resume_dir = resume_dir(opts)?;
    let mut setup = Setup::new(source, opts, &arch, &cfile);
    let obj = match opts.stage {
        Stage::SsVae => setup.ss_vae(source)?,
        Stage::SsFlow => setup.ss_flow(source)?,
        Stage::SlatAe => setup.slat_ae(source)?,
        Stage::SlatFlow => setup.slat_flow(source)?,
    };
    train_and_write(source, opts, setup, obj.as_ref(), resume_dir)
}

/// The checkpoint folder `--resume` names (`None`: a fresh run).
fn resume_dir(opts: &TrainOptions) -> Result<Option<PathBuf>> {
    Ok(match &opts.resume {
        None => None,
        Some(Resume::Dir(d)) => Some(d.clone()),
        Some(Resume::Latest) => Some(
            latest_checkpoint(&opts.out)?
                .ok_or_else(|| Error::input(opts.out.display().to_string(), "--resume: no checkpoint in <out>/checkpoints"))?,
        ),
    })
}

/// What building a stage's objective records besides the objective itself:
/// the run record's settings and notes, the modules copied into the output
/// folder and (slat-flow) the latent normalisation.
struct Setup<'o> {
    opts: &'o TrainOptions,
    arch: &'o RecGenConfig,
    /// The architecture file's name, for errors.
    cfile: &'o str,
    settings: serde_json::Value,
    notes: Vec<String>,
    /// Modules copied into the output folder (reported after the trained ones).
    copied: Vec<PathBuf>,
    slat_norm: Option<(Vec<f32>, Vec<f32>)>,
}

impl<'o> Setup<'o> {
    /// The settings every stage records (and the warm start, if any).
    fn new(source: &dyn TrainingSource, opts: &'o TrainOptions, arch: &'o RecGenConfig, cfile: &'o str) -> Self {
        let mut notes = Vec::new();
        let mut settings = serde_json::json!({
            "loop": opts.settings,
            "architecture": arch.name,
            "data": source.describe(),
            "fill": opts.fill,
        });
        if let Some(dir) = &opts.init {
            settings["init"] = serde_json::json!(dir);
            notes.push(format!("warm start from {}", dir.display()));
        }
        Self { opts, arch, cfile, settings, notes, copied: Vec::new(), slat_norm: None }
    }

    fn ss_encoder_cfg(&self) -> Result<ModuleConfig> {
        let spec = self.arch.ss_encoder.as_ref().ok_or_else(|| {
            Error::config(self.cfile, ModuleKey::SsEncoder.name(), "missing: training needs the SS VAE encoder's section")
        })?;
        Ok(spec.clone())
    }

    /// A trained module: random for the seed, or the --init folder's weights.
    fn module(&self, key: ModuleKey, cfg: &ModuleConfig) -> Result<ModuleParams> {
        match &self.opts.init {
            None => ModuleParams::init(key, cfg, registry::module_seed(self.opts.settings.seed, key.name())),
            Some(dir) => {
                let file = dir.join(format!("{key}.safetensors"));
                ModuleParams::from_tensors(key, cfg, &load_module(dir, key)?, &file.display().to_string())
            }
        }
    }

    fn ss_vae<'a>(&mut self, source: &'a dyn TrainingSource) -> Result<Box<dyn Objective + 'a>> {
        let (opts, arch) = (self.opts, self.arch);
        let enc_cfg = self.ss_encoder_cfg()?;
        let dec_cfg = arch.ss_decoder.clone();
        self.settings["modules"] = serde_json::json!({"ss_encoder": enc_cfg, "ss_decoder": dec_cfg});
        self.settings["vae"] = serde_json::json!({"recon_loss": opts.recon_loss, "lambda_kl": opts.lambda_kl});
        let enc = self.module(ModuleKey::SsEncoder, &enc_cfg)?;
        let dec = self.module(ModuleKey::SsDecoder, &dec_cfg)?;
        let f = enc.args.ss_encoder(self.cfile)?.downsample_factor();
        let res = arch.ss_flow_config().resolution * f;
        let obj = Box::new(VaeObjective::new(source, enc, dec, res, opts.fill, opts.recon_loss, opts.lambda_kl)?);
        self.notes.push(format!("occupancy {res}³ ({:?} fill) of {} models", opts.fill, source.num_models()));
        Ok(obj)
    }

    fn ss_flow<'a>(&mut self, source: &'a dyn TrainingSource) -> Result<Box<dyn Objective + 'a>> {
        let (opts, arch) = (self.opts, self.arch);
        let enc_cfg = self.ss_encoder_cfg()?;
        let vae = opts.vae.as_ref().ok_or_else(|| {
            Error::config("recon train ss-flow", "--vae", "the ss-vae output folder is required (its encoder makes the latents)")
        })?;
        let enc_t = load_module(vae, ModuleKey::SsEncoder)?;
        let dec_t = load_module(vae, ModuleKey::SsDecoder)?;
        let encoder =
            registry::build_ss_encoder(&arch.module_args(ModuleKey::SsEncoder)?, frozen_var_builder(enc_t), "ss_encoder", Compute::Plain)?;
        let scan = scan(source)?;
        self.notes.push(format!(
            "{} usable samples ({} with two views), {} views without depth skipped",
            scan.usable.len(),
            scan.two_view.len(),
            scan.skipped_views
        ));
        let stats_json = pose_stats_json(&scan.poses, arch.pose.nine_d_layout, &source.describe())?;
        let stats = PoseStats::from_json(&stats_json, "pose_stats.json")?;
        write_json(&opts.out.join("pose_stats.json"), &stats_json)?;
        let dino_cfg = arch.image_cond_model.clone();
        let flow_cfg = arch.ss_flow.clone();
        self.settings["modules"] = serde_json::json!({"image_cond_model": dino_cfg, "ss_flow": flow_cfg, "ss_encoder": enc_cfg});
        self.settings["flow"] = serde_json::json!({"fm": opts.flow, "context": opts.context, "p_two_view": opts.p_two_view, "vae": vae});
        let dino = self.module(ModuleKey::ImageCondModel, &dino_cfg)?;
        let flow = self.module(ModuleKey::SsFlow, &flow_cfg)?;
        let mut fo = FlowObjective::new(source, scan, stats, dino, flow, &encoder, opts.fill, opts.flow.clone())?;
        fo.context = opts.context;
        fo.p_two_view = opts.p_two_view;
        let (m, s) = fo.latent_stats()?;
        self.notes.push(format!("VAE latents: mean {m:.4}, std {s:.4} (the flow starts from unit noise)"));
        // The decoder travels with the flow so the folder runs stage 1.
        self.copied.push(write_copied_module(&dec_t, vae, &opts.out, ModuleKey::SsDecoder)?);
        Ok(Box::new(fo))
    }

    fn slat_ae<'a>(&mut self, source: &'a dyn TrainingSource) -> Result<Box<dyn Objective + 'a>> {
        let (opts, arch) = (self.opts, self.arch);
        let enc_spec = arch.slat_encoder.as_ref().ok_or_else(|| {
            Error::config(self.cfile, ModuleKey::SlatEncoder.name(), "missing: training needs the SLat VAE encoder's section")
        })?;
        let cfgs = [
            (ModuleKey::SlatEncoder, enc_spec.clone()),
            (ModuleKey::SlatDecMesh, arch.slat_dec_mesh.clone()),
            (ModuleKey::SlatDecGs, arch.slat_dec_gs.clone()),
        ];
        self.settings["modules"] = serde_json::json!({"slat_encoder": cfgs[0].1, "slat_dec_mesh": cfgs[1].1, "slat_dec_gs": cfgs[2].1});
        let [e, m, g] = cfgs.map(|(k, c)| self.module(k, &c));
        let mut so = crate::slat::SlatAeObjective::new(source, e?, m?, g?)?;
        so.crop = opts.crop;
        so.max_voxels = opts.max_voxels;
        self.settings["slat_ae"] = serde_json::json!({"crop": so.crop, "max_voxels": so.max_voxels, "weights": so.weights, "sdf_band_fine_voxels": crate::slat::BAND, "cubes_per_voxel_side": crate::slat::SUB});
        self.notes.push(format!("surface voxels at {}³, crops of {} voxels (≤ {})", so.res, so.crop, so.max_voxels));
        Ok(Box::new(so))
    }

    fn slat_flow<'a>(&mut self, source: &'a dyn TrainingSource) -> Result<Box<dyn Objective + 'a>> {
        let (opts, arch) = (self.opts, self.arch);
        let s1 = opts.stage1.as_ref().ok_or_else(|| {
            Error::config(
                "recon train slat-flow",
                "--stage1",
                "the ss-flow output folder is required (frozen image encoder, pose statistics)",
            )
        })?;
        let ae = opts.slat_ae.as_ref().ok_or_else(|| {
            Error::config("recon train slat-flow", "--slat-ae", "the slat-ae output folder is required (frozen SLat encoder)")
        })?;
        arch.slat_encoder.as_ref().ok_or_else(|| {
            Error::config(self.cfile, ModuleKey::SlatEncoder.name(), "missing: the SLat encoder's section is needed to encode the latents")
        })?;
        let encoder = registry::build_slat_encoder(
            &arch.module_args(ModuleKey::SlatEncoder)?,
            frozen_var_builder(load_module(ae, ModuleKey::SlatEncoder)?),
            "slat_encoder",
            Compute::Plain,
        )?;
        let dino = registry::build_dinov2(
            &arch.module_args(ModuleKey::ImageCondModel)?,
            frozen_var_builder(load_module(s1, ModuleKey::ImageCondModel)?),
            "image_cond_model",
            Compute::Plain,
        )?;
        let stats_path = s1.join("pose_stats.json");
        let stats = PoseStats::from_json_file(&stats_path)?;
        let scan = scan(source)?;
        let flow_cfg = arch.slat_flow.clone();
        self.settings["modules"] = serde_json::json!({"slat_flow": flow_cfg});
        self.settings["slat_flow"] =
            serde_json::json!({"fm": opts.flow, "context": opts.context, "stage1": s1, "slat_ae": ae, "max_models": opts.max_models});
        let flow = self.module(ModuleKey::SlatFlow, &flow_cfg)?;
        let mut fo = crate::slat_flow::SlatFlowObjective::new(
            source,
            scan,
            stats,
            arch.pose.nine_d_layout,
            dino,
            flow,
            &encoder,
            opts.max_models,
            opts.flow.clone(),
        )?;
        fo.context = opts.context;
        let (models, pool, usable) = fo.counts();
        self.notes.push(format!("{models} models encoded; {pool} of {usable} usable samples use them"));
        self.notes.push(format!("latent mean {:?}, std {:?}", fo.mean, fo.std));
        // The complete model folder: stage 1 and the decoders travel with the flow.
        for (dir, key) in [
            (s1, ModuleKey::ImageCondModel),
            (s1, ModuleKey::SsFlow),
            (s1, ModuleKey::SsDecoder),
            (ae, ModuleKey::SlatDecMesh),
            (ae, ModuleKey::SlatDecGs),
        ] {
            self.copied.push(write_copied_module(&load_module(dir, key)?, dir, &opts.out, key)?);
        }
        std::fs::copy(&stats_path, opts.out.join("pose_stats.json")).map_err(|e| Error::io(&stats_path, e))?;
        self.slat_norm = Some((fo.mean.clone(), fo.std.clone()));
        Ok(Box::new(fo))
    }
}

/// The run record, the fixed evaluations around training, the training loop
/// and the output folder's files.
fn train_and_write(
    source: &dyn TrainingSource,
    opts: &TrainOptions,
    setup: Setup<'_>,
    obj: &dyn Objective,
    resume_dir: Option<PathBuf>,
) -> Result<RunReport> {
    let Setup { arch, settings, notes, copied, slat_norm, .. } = setup;
    let seed = opts.settings.seed;
    let params: BTreeMap<String, usize> = obj.trainable().iter().map(|m| (m.key.to_string(), m.num_params())).collect();
    let mut report = RunReport {
        stage: opts.stage,
        status: "running",
        architecture: arch.name.clone(),
        data: source.describe(),
        params,
        settings: settings.clone(),
        summary: None,
        eval_before: None,
        eval_after: None,
        files: Vec::new(),
        notes,
    };
    write_json(&opts.out.join(MARKER), &report)?;
    let eval_batch = opts.settings.batch.min(4);
    if opts.eval_batches > 0 && resume_dir.is_none() {
        report.eval_before = Some(fixed_eval(obj, EVAL_SEED, opts.eval_batches, eval_batch)?);
    }
    let summary = train(obj, &opts.settings, &settings, &opts.out, resume_dir.as_deref(), opts.progress)?;
    if opts.eval_batches > 0 {
        report.eval_after = Some(fixed_eval(obj, EVAL_SEED, opts.eval_batches, eval_batch)?);
    }
    let meta: BTreeMap<String, String> = [
        ("recon.stage".to_string(), opts.stage.name().to_string()),
        ("recon.architecture".to_string(), arch.name.clone()),
        ("recon.steps".to_string(), summary.last_step.to_string()),
        ("recon.seed".to_string(), seed.to_string()),
    ]
    .into();
    report.files = write_weights(&opts.out, obj, &meta)?;
    report.files.extend(copied);
    if matches!(opts.stage, Stage::SsFlow | Stage::SlatFlow) {
        // The architecture file, reading its pose statistics (and, for the complete
        // model, the latent normalisation of this run) from this folder.
        report.files.push(write_architecture(&opts.config, &opts.out, slat_norm.as_ref())?);
        report.files.push(opts.out.join("pose_stats.json"));
    }
    report.summary = Some(summary);
    report.status = "complete";
    write_json(&opts.out.join(MARKER), &report)?;
    Ok(report)
}
