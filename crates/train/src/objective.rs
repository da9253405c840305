//! The two stage-1 objectives: the SS VAE (encoder + decoder on occupancy)
//! and the SS flow (image encoder + flow transformer with pose tokens, on
//! the frozen VAE encoder's latents).

use std::collections::BTreeMap;

use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

use crate::data::{canonical_frame, occupancy, Scan, TrainingSource};
use crate::flow::{drop_condition, masked_pose_mse, FlowMatching};
use crate::params::ModuleParams;
use recon_core::geometry::pose::PoseStats;
use recon_core::geometry::voxelize::{CanonicalFrame, Fill};
use recon_core::model::config::ModuleKey;
use recon_core::model::stage1::dinov2::Dinov2;
use recon_core::model::stage1::embedders::ViewInputs;
use recon_core::model::stage1::ss_flow::SparseStructureFlowModel;
use recon_core::model::stage1::ss_vae::decoder::SparseStructureDecoder;
use recon_core::model::stage1::ss_vae::encoder::{vae_loss, ReconLoss, SparseStructureEncoder};
use recon_core::model::Compute;
use recon_core::rng::SeededRng;
use recon_core::weights::registry;
use recon_core::{Error, Result};

/// Scalar values of one batch, by name.
pub type Terms = BTreeMap<String, f64>;

/// The loss of one batch.
pub struct BatchLoss {
    /// Differentiable total.
    pub total: Tensor,
    /// Its terms (logged and plotted).
    pub terms: Terms,
    /// Other per-batch facts (logged, not plotted).
    pub info: Terms,
}

/// A training objective over some trainable modules.
pub trait Objective {
    /// `ss-vae` or `ss-flow`.
    fn name(&self) -> &'static str;
    /// Parameters the optimiser updates.
    fn trainable(&self) -> &[ModuleParams];
    /// Loss of one random batch of `batch` samples drawn from `rng`.
    fn loss(&self, rng: &mut SeededRng, batch: usize) -> Result<BatchLoss>;
}

/// Mean loss over `batches` batches drawn from a fixed seed: the same
/// numbers before and after training, so a drop measures learning, not
/// batch luck.
pub fn fixed_eval(obj: &dyn Objective, seed: u64, batches: usize, batch: usize) -> Result<f64> {
    let mut rng = SeededRng::new(seed);
    let mut acc = 0.0;
    for _ in 0..batches {
        acc += scalar(&obj.loss(&mut rng, batch)?.total)?;
    }
    Ok(acc / batches.max(1) as f64)
}

/// A scalar tensor's value as f64.
pub fn scalar_of(t: &Tensor) -> Result<f64> {
    scalar(t)
}

fn scalar(t: &Tensor) -> Result<f64> {
    Ok(t.to_dtype(DType::F32)?.to_scalar::<f32>()? as f64)
}

/// SS VAE: occupancy → encoder → posterior sample → decoder → BCE/Dice + λ·KL.
pub struct VaeObjective {
    params: Vec<ModuleParams>,
    encoder: SparseStructureEncoder,
    decoder: SparseStructureDecoder,
    /// Occupancy per model `[1, r, r, r]`.
    occupancy: Vec<Tensor>,
    /// Reconstruction loss of the decoded occupancy.
    pub recon: ReconLoss,
    /// Weight of the KL term.
    pub lambda_kl: f64,
}

impl VaeObjective {
    /// `encoder` and `decoder` hold `ss_encoder` / `ss_decoder` params;
    /// every model of `source` is voxelised at `resolution` up front.
    pub fn new(
        source: &dyn TrainingSource,
        encoder: ModuleParams,
        decoder: ModuleParams,
        resolution: usize,
        fill: Fill,
        recon: ReconLoss,
        lambda_kl: f64,
    ) -> Result<Self> {
        let enc = registry::build_ss_encoder(&encoder.args, encoder.var_builder(), encoder.key.name(), Compute::Plain)?;
        let dec = registry::build_ss_decoder(&decoder.args, decoder.var_builder(), decoder.key.name(), Compute::Plain)?;
        let f = enc.config().downsample_factor();
        if !resolution.is_multiple_of(f) {
            return Err(Error::config(
                ModuleKey::SsEncoder.name(),
                "channels",
                format!("occupancy resolution {resolution} is not a multiple of the encoder's downsampling {f}"),
            ));
        }
        if source.num_models() == 0 {
            return Err(Error::input(source.describe(), "no object models"));
        }
        let occupancy = (0..source.num_models())
            .into_par_iter()
            .map(|i| occupancy(&source.model(i)?.mesh, resolution, fill))
            .collect::<Result<Vec<_>>>()?;
        Ok(Self { params: vec![encoder, decoder], encoder: enc, decoder: dec, occupancy, recon, lambda_kl })
    }
}

impl Objective for VaeObjective {
    fn name(&self) -> &'static str {
        "ss-vae"
    }
    fn trainable(&self) -> &[ModuleParams] {
        &self.params
    }
    fn loss(&self, rng: &mut SeededRng, batch: usize) -> Result<BatchLoss> {
        let idx: Vec<usize> = (0..batch).map(|_| (rng.next_u64() % self.occupancy.len() as u64) as usize).collect();
        let occ = Tensor::stack(&idx.iter().map(|&i| self.occupancy[i].clone()).collect::<Vec<_>>(), 0)?;
        let post = self.encoder.forward(&occ)?;
        let noise = rng.randn(post.mean.dims(), &Device::Cpu)?;
        let logits = self.decoder.forward_differentiable(&post.sample(&noise)?)?;
        let t = vae_loss(&logits, &occ, &post, self.recon, self.lambda_kl)?;
        // Voxel accuracy of the reconstruction at the decoder's threshold (logit > 0).
        let acc = logits.gt(0.0)?.to_dtype(DType::F32)?.eq(&occ)?.to_dtype(DType::F32)?.mean_all()?;
        let terms: Terms = [("recon".to_string(), scalar(&t.recon)?), ("kl".to_string(), scalar(&t.kl)?)].into();
        let info: Terms = [("voxel_acc".to_string(), scalar(&acc)?)].into();
        Ok(BatchLoss { total: t.total, terms, info })
    }
}

/// Stage-1 flow objective (module docs of `crate::flow`).
pub struct FlowObjective<'a> {
    params: Vec<ModuleParams>,
    dino: Dinov2,
    flow: SparseStructureFlowModel,
    source: &'a dyn TrainingSource,
    scan: Scan,
    canon: Vec<CanonicalFrame>,
    /// Frozen-encoder latent mean per model `[C, R, R, R]`.
    latents: Vec<Tensor>,
    stats: PoseStats,
    /// Flow-matching hyper-parameters.
    pub fm: FlowMatching,
    /// Crop context factor range (inference uses 1.2).
    pub context: [f64; 2],
    /// Probability of a two-view batch (when the data has second views).
    pub p_two_view: f64,
    image_size: usize,
}

impl<'a> FlowObjective<'a> {
    /// `dino` / `flow` hold the `image_cond_model` / `ss_flow` params;
    /// `encoder` is the trained, frozen SS VAE encoder; `scan` and `stats`
    /// come from [`crate::data::scan`] and the pose statistics of the set.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        source: &'a dyn TrainingSource,
        scan: Scan,
        stats: PoseStats,
        dino: ModuleParams,
        flow: ModuleParams,
        encoder: &SparseStructureEncoder,
        fill: Fill,
        fm: FlowMatching,
    ) -> Result<Self> {
        let d = registry::build_dinov2(&dino.args, dino.var_builder(), dino.key.name(), Compute::Plain)?;
        let f = registry::build_ss_flow(&flow.args, flow.var_builder(), flow.key.name(), Compute::Plain)?;
        if f.cfg.pose_channels() != Some(10) {
            return Err(Error::config(
                ModuleKey::SsFlow.name(),
                "pose_representation",
                "training needs RecGen pose tokens (6d_translation_scale)",
            ));
        }
        if encoder.config().latent_channels != f.cfg.in_channels {
            return Err(Error::config(
                ModuleKey::SsEncoder.name(),
                "latent_channels",
                format!("{} differs from ss_flow in_channels {}", encoder.config().latent_channels, f.cfg.in_channels),
            ));
        }
        let res = f.cfg.resolution * encoder.config().downsample_factor();
        let canon = (0..source.num_models()).map(|i| canonical_frame(&source.model(i)?.mesh)).collect::<Result<Vec<_>>>()?;
        // Latents of every model: the encoder's posterior mean (TRELLIS encodes
        // its training latents with `sample_posterior=False`).
        let occ =
            (0..source.num_models()).into_par_iter().map(|i| occupancy(&source.model(i)?.mesh, res, fill)).collect::<Result<Vec<_>>>()?;
        let mut latents = Vec::with_capacity(occ.len());
        for chunk in occ.chunks(8) {
            let m = encoder.forward(&Tensor::stack(chunk, 0)?)?.mean.detach();
            if m.dims()[2..] != [f.cfg.resolution; 3] {
                return Err(Error::config(
                    ModuleKey::SsFlow.name(),
                    "resolution",
                    format!("encoder latents are {:?}, the flow expects {}³", &m.dims()[2..], f.cfg.resolution),
                ));
            }
            for i in 0..m.dim(0)? {
                latents.push(m.get(i)?);
            }
        }
        let image_size = d.cfg.img_size;
        Ok(Self {
            params: vec![dino, flow],
            dino: d,
            flow: f,
            source,
            scan,
            canon,
            latents,
            stats,
            fm,
            context: [1.2, 2.0],
            p_two_view: 0.5,
            image_size,
        })
    }

    /// Latent statistics (mean, std over every value), for the run record.
    pub fn latent_stats(&self) -> Result<(f64, f64)> {
        let all = Tensor::stack(&self.latents, 0)?.flatten_all()?;
        let m = scalar(&all.mean_all()?)?;
        let s = scalar(&all.affine(1.0, -m)?.sqr()?.mean_all()?)?.sqrt();
        Ok((m, s))
    }
}

impl Objective for FlowObjective<'_> {
    fn name(&self) -> &'static str {
        "ss-flow"
    }
    fn trainable(&self) -> &[ModuleParams] {
        &self.params
    }
    fn loss(&self, rng: &mut SeededRng, batch: usize) -> Result<BatchLoss> {
        let dev = Device::Cpu;
        let k = self.flow.cfg.num_pose_tokens.max(1);
        let two = k >= 2 && !self.scan.two_view.is_empty() && rng.uniform() < self.p_two_view;
        let (pool, n_views) = if two { (&self.scan.two_view, 2) } else { (&self.scan.usable, 1) };
        let picks: Vec<(usize, u64)> = (0..batch).map(|_| (pool[(rng.next_u64() % pool.len() as u64) as usize], rng.next_u64())).collect();
        // Inputs per sample, in parallel; each sample has its own seeded stream.
        let prepared = crate::data::prepare_picks(self.source, &self.canon, &picks, n_views, self.image_size, self.context)?;
        let b = prepared.len();
        let x0 = Tensor::stack(&prepared.iter().map(|(m, _)| self.latents[*m].clone()).collect::<Vec<_>>(), 0)?;
        // Pose targets [B, K, 10], z-scored; tokens without a view are unsupervised.
        let mut pose = vec![0f32; b * k * 10];
        let mut mask = vec![0f32; b * k];
        for (bi, (_, views)) in prepared.iter().enumerate() {
            for (vi, v) in views.iter().enumerate() {
                let z = self.stats.normalize(&v.pose.to_10d())?;
                pose[(bi * k + vi) * 10..(bi * k + vi + 1) * 10].copy_from_slice(&z);
                mask[bi * k + vi] = 1.0;
            }
        }
        let pose0 = Tensor::from_vec(pose, (b, k, 10), &dev)?;
        let pose_mask = Tensor::from_vec(mask, (b, k), &dev)?;
        // Condition: image tokens (trained jointly), + point-map and mask embeddings.
        let mut views = Vec::with_capacity(n_views);
        for vi in 0..n_views {
            let cat =
                |f: fn(&crate::data::TrainView) -> &Tensor| Tensor::cat(&prepared.iter().map(|(_, v)| f(&v[vi])).collect::<Vec<_>>(), 0);
            let pixels = cat(|v| &v.pixels)?;
            views.push(ViewInputs {
                patch_tokens: self.dino.recgen_cond(&pixels)?,
                pointmap: Some(cat(|v| &v.pointmap)?),
                mask: Some(cat(|v| &v.mask)?),
            });
        }
        let (cond, _neg) = self.flow.condition(&views)?;
        let drop = self.fm.drop_mask(rng, b);
        let cond = drop_condition(&cond, &drop)?;
        // Noised state at a shared t per sample.
        let t = Tensor::from_vec(self.fm.sample_t(rng, b), b, &dev)?;
        let eps = rng.randn(x0.dims(), &dev)?;
        let eps_pose = rng.randn(pose0.dims(), &dev)?;
        let xt = self.fm.diffuse(&x0, &t, &eps)?;
        let pt = self.fm.diffuse(&pose0, &t, &eps_pose)?;
        let (v, vp) = self.flow.forward(&xt, Some(&pt), &(&t * 1000.0)?, &cond)?;
        let vp = vp.ok_or_else(|| Error::msg("ss_flow returned no pose velocity"))?;
        let vp = if vp.rank() == 2 { vp.unsqueeze(1)? } else { vp };
        let mse = (v - self.fm.target(&x0, &eps)?)?.sqr()?.mean_all()?;
        let mse_pose = masked_pose_mse(&vp, &self.fm.target(&pose0, &eps_pose)?, &pose_mask)?;
        let total = (&mse + (&mse_pose * self.fm.pose_alpha)?)?;
        let terms: Terms = [("mse".to_string(), scalar(&mse)?), ("mse_pose".to_string(), scalar(&mse_pose)?)].into();
        let info: Terms =
            [("views".to_string(), n_views as f64), ("dropped".to_string(), drop.iter().filter(|&&d| d).count() as f64)].into();
        Ok(BatchLoss { total, terms, info })
    }
}

/// Build a module on stored, frozen tensors (no variables, no gradients).
pub fn frozen_var_builder(tensors: BTreeMap<String, Tensor>) -> VarBuilder<'static> {
    VarBuilder::from_tensors(tensors.into_iter().collect(), DType::F32, &Device::Cpu)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::toy::{micro_architecture, ToyConfig, ToySource};
    use recon_core::model::config::RecGenConfig;

    fn micro() -> RecGenConfig {
        let p = recon_testkit::repo().join("models/recgen-nano.json");
        let v: serde_json::Value = recon_core::util::json::read_json(&p).unwrap();
        RecGenConfig::from_json(&micro_architecture(&v), "micro").unwrap()
    }

    /// The whole stage-1 flow objective (image encoder, embedders, flow
    /// transformer, pose tokens) is differentiable through plain candle ops
    /// and every parameter gets a gradient except DINOv2's `mask_token` and
    /// final `norm`, which RecGen's conditioning does not use (it takes
    /// `x_prenorm` through a LayerNorm without affine parameters).
    #[test]
    fn flow_objective_gradient_matches_finite_difference() -> Result<()> {
        let arch = micro();
        let src = ToySource::new(ToyConfig { samples: 3, models: 2, second_view: true, ..Default::default() })?;
        let enc_p = ModuleParams::init(ModuleKey::SsEncoder, arch.ss_encoder.as_ref().unwrap(), 1)?;
        let encoder = registry::build_ss_encoder(&enc_p.args, enc_p.var_builder(), enc_p.key.name(), Compute::Plain)?;
        let scan = crate::data::scan(&src)?;
        let stats = PoseStats::from_json(&crate::data::pose_stats_json(&scan.poses, arch.pose.nine_d_layout, "toy")?, "toy")?;
        let dino = ModuleParams::init(ModuleKey::ImageCondModel, &arch.image_cond_model, 2)?;
        let flow = ModuleParams::init(ModuleKey::SsFlow, &arch.ss_flow, 3)?;
        // Zero-initialised output layers would hide every upstream gradient: perturb them.
        let mut r = SeededRng::new(9);
        for (n, v) in &flow.vars {
            if n.contains("adaLN") || n.starts_with("out_layer") {
                v.set(&(r.randn(v.dims(), &Device::Cpu)? * 0.05)?)?;
            }
        }
        let fm = FlowMatching { p_uncond: 0.0, ..Default::default() };
        let mut obj = FlowObjective::new(&src, scan, stats, dino, flow, &encoder, Fill::Solid, fm)?;
        for p_two in [0.0, 1.0] {
            obj.p_two_view = p_two;
            let vars: Vec<_> =
                obj.trainable().iter().flat_map(|m| m.vars.iter().map(move |(n, v)| (format!("{}/{n}", m.key), v.clone()))).collect();
            let loss = || -> Result<Tensor> { Ok(obj.loss(&mut SeededRng::new(4), 2)?.total) };
            // A single view has no frame-token embedding (as at inference).
            let mut unused = vec!["image_cond_model/mask_token", "image_cond_model/norm.weight", "image_cond_model/norm.bias"];
            if p_two == 0.0 {
                unused.push("ss_flow/frame_token_embedder");
            }
            recon_testkit::gradcheck::directional_check(&vars, &unused, loss, 5, 2e-2)?;
        }
        // Two-view batches supervise both pose tokens.
        obj.p_two_view = 1.0;
        assert_eq!(obj.loss(&mut SeededRng::new(4), 2)?.info["views"], 2.0);
        Ok(())
    }
}
