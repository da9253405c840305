//! Stage-2 flow training (`recon train slat-flow`): the structured-latent
//! flow on the frozen SLat encoder's latents of whole objects, conditioned
//! like inference (frozen image encoder of the ss-flow run, point-map and
//! mask embeddings, the ground-truth pose as 9D + t + s tokens).
//!
//! Latents are the encoder's posterior means (as TRELLIS encodes its
//! training latents), normalised per channel with statistics of the encoded
//! set; the statistics are the `slat_normalization` written with the
//! weights, so inference denormalises exactly what was learned.

use candle_core::{Device, Tensor};
use rayon::prelude::*;

use crate::data::{canonical_frame, prepare_picks, Scan, TrainingSource};
use crate::flow::{drop_condition, FlowMatching};
use crate::objective::{scalar_of, BatchLoss, Objective, Terms};
use crate::params::ModuleParams;
use crate::slat::{in_channels, SlatGeometry};
use recon_core::geometry::pose::{NineDLayout, PoseStats};
use recon_core::geometry::voxelize::CanonicalFrame;
use recon_core::model::config::ModuleKey;
use recon_core::model::sparse::SparseTensor;
use recon_core::model::stage1::dinov2::Dinov2;
use recon_core::model::stage1::embedders::ViewInputs;
use recon_core::model::stage2::slat_flow::{ConvPath, SLatFlowModel};
use recon_core::model::stage2::slat_vae::encoder::SLatEncoder;
use recon_core::model::Compute;
use recon_core::rng::SeededRng;
use recon_core::weights::registry;
use recon_core::{Error, Result};

/// One encoded object: its active voxels and normalised latents `[N, C]`.
struct Encoded {
    coords: Vec<[i32; 3]>,
    latents: Tensor,
}

pub struct SlatFlowObjective<'a> {
    params: Vec<ModuleParams>,
    dino: Dinov2,
    flow: SLatFlowModel,
    source: &'a dyn TrainingSource,
    scan: Scan,
    canon: Vec<CanonicalFrame>,
    encoded: Vec<Option<Encoded>>,
    /// Usable samples whose model was encoded.
    pool: Vec<usize>,
    stats: PoseStats,
    layout: NineDLayout,
    /// Per-channel latent mean and std (the `slat_normalization`).
    pub mean: Vec<f32>,
    pub std: Vec<f32>,
    pub fm: FlowMatching,
    pub context: [f64; 2],
    image_size: usize,
}

impl<'a> SlatFlowObjective<'a> {
    /// `dino`: the frozen image encoder; `flow`: the trainable SLat flow;
    /// `encoder`: the frozen SLat encoder. At most `max_models` models (the
    /// first ones the samples use) are encoded.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        source: &'a dyn TrainingSource,
        scan: Scan,
        stats: PoseStats,
        layout: NineDLayout,
        dino: Dinov2,
        flow: ModuleParams,
        encoder: &SLatEncoder,
        max_models: usize,
        fm: FlowMatching,
    ) -> Result<Self> {
        let mut f = registry::build_slat_flow(&flow.args, flow.var_builder(), flow.key.name(), Compute::Plain)?;
        f.set_conv_path(ConvPath::Differentiable);
        if f.cfg.pose_dim() != 13 {
            return Err(Error::config(
                ModuleKey::SlatFlow.name(),
                "pose_representation",
                "training needs RecGen pose conditioning (9d_translation_scale)",
            ));
        }
        if f.cfg.in_channels != encoder.latent_channels {
            return Err(Error::config(
                ModuleKey::SlatFlow.name(),
                "in_channels",
                format!("{} differs from the SLat encoder's latent_channels {}", f.cfg.in_channels, encoder.latent_channels),
            ));
        }
        let res = f.cfg.resolution;
        let canon = (0..source.num_models()).map(|i| canonical_frame(&source.model(i)?.mesh)).collect::<Result<Vec<_>>>()?;
        // Models to encode: first use order over the usable samples.
        let mut chosen = Vec::new();
        let mut seen = vec![false; source.num_models()];
        for &i in &scan.usable {
            let m = scan.models[i];
            if !seen[m] && chosen.len() < max_models {
                seen[m] = true;
                chosen.push(m);
            }
        }
        let feats: Vec<(usize, Vec<[i32; 3]>, Vec<f32>)> = chosen
            .par_iter()
            .map(|&m| {
                let e = source.model(m)?;
                let g = SlatGeometry::new(&e.mesh, e.colors.as_deref().map(Vec::as_slice), res, m as u64)?;
                let f = g.input_features(&g.voxels);
                Ok((m, g.voxels, f))
            })
            .collect::<Result<_>>()?;
        let mut raw: Vec<(usize, Vec<[i32; 3]>, Tensor)> = Vec::with_capacity(feats.len());
        for (m, coords, f) in feats {
            let n = coords.len();
            let x = SparseTensor::new(
                coords.iter().map(|c| [0, c[0], c[1], c[2]]).collect(),
                Tensor::from_vec(f, (n, in_channels()), &Device::Cpu)?,
                1,
            )?;
            raw.push((m, coords, encoder.forward(&x)?.mean.detach()));
        }
        if raw.is_empty() {
            return Err(Error::msg("slat-flow: no usable sample to encode"));
        }
        let all = Tensor::cat(&raw.iter().map(|r| r.2.clone()).collect::<Vec<_>>(), 0)?;
        let mean_t = all.mean(0)?;
        let std_t = all.broadcast_sub(&mean_t)?.sqr()?.mean(0)?.sqrt()?.clamp(1e-6, f64::INFINITY)?;
        let mut encoded: Vec<Option<Encoded>> = (0..source.num_models()).map(|_| None).collect();
        for (m, coords, l) in raw {
            encoded[m] = Some(Encoded { coords, latents: l.broadcast_sub(&mean_t)?.broadcast_div(&std_t)? });
        }
        let pool: Vec<usize> = scan.usable.iter().copied().filter(|&i| encoded[scan.models[i]].is_some()).collect();
        let image_size = dino.cfg.img_size;
        Ok(Self {
            params: vec![flow],
            dino,
            flow: f,
            source,
            scan,
            canon,
            encoded,
            pool,
            stats,
            layout,
            mean: mean_t.to_vec1()?,
            std: std_t.to_vec1()?,
            fm,
            context: [1.2, 2.0],
            image_size,
        })
    }

    /// Encoded models and the samples that use them.
    pub fn counts(&self) -> (usize, usize, usize) {
        (self.encoded.iter().filter(|e| e.is_some()).count(), self.pool.len(), self.scan.usable.len())
    }
}

impl Objective for SlatFlowObjective<'_> {
    fn name(&self) -> &'static str {
        "slat-flow"
    }
    fn trainable(&self) -> &[ModuleParams] {
        &self.params
    }
    fn loss(&self, rng: &mut SeededRng, batch: usize) -> Result<BatchLoss> {
        let dev = Device::Cpu;
        let picks: Vec<(usize, u64)> =
            (0..batch).map(|_| (self.pool[(rng.next_u64() % self.pool.len() as u64) as usize], rng.next_u64())).collect();
        let prepared: Vec<(usize, crate::data::TrainView)> =
            prepare_picks(self.source, &self.canon, &picks, 1, self.image_size, self.context)?
                .into_iter()
                .map(|(m, mut v)| (m, v.swap_remove(0)))
                .collect();
        let b = prepared.len();
        let mut coords = Vec::new();
        let mut x0 = Vec::with_capacity(b);
        let mut pose = Vec::with_capacity(b * 13);
        for (bi, (m, v)) in prepared.iter().enumerate() {
            let e = self.encoded[*m].as_ref().ok_or_else(|| Error::msg("slat-flow: sample of an unencoded model"))?;
            coords.extend(e.coords.iter().map(|c| [bi as i32, c[0], c[1], c[2]]));
            x0.push(e.latents.clone());
            pose.extend(self.stats.normalize(&v.pose.to_13d(self.layout))?);
        }
        let x0 = Tensor::cat(&x0, 0)?;
        let pose = Tensor::from_vec(pose, (b, 1, 13), &dev)?;
        let cat = |f: fn(&crate::data::TrainView) -> &Tensor| Tensor::cat(&prepared.iter().map(|(_, v)| f(v)).collect::<Vec<_>>(), 0);
        let tokens = self.dino.recgen_cond(&cat(|v| &v.pixels)?)?.detach();
        let views = [ViewInputs { patch_tokens: tokens, pointmap: Some(cat(|v| &v.pointmap)?), mask: Some(cat(|v| &v.mask)?) }];
        let (cond, _neg) = self.flow.condition(&views, Some(&pose))?;
        let drop = self.fm.drop_mask(rng, b);
        let cond = drop_condition(&cond, &drop)?;
        let t = Tensor::from_vec(self.fm.sample_t(rng, b), b, &dev)?;
        let xs = SparseTensor::new(coords, x0.clone(), b)?;
        let t_rows = xs.batch_broadcast(&t.unsqueeze(1)?)?.squeeze(1)?;
        let eps = rng.randn(x0.dims(), &dev)?;
        let xt = xs.with_feats(self.fm.diffuse(&x0, &t_rows, &eps)?)?;
        let v = self.flow.forward(&xt, &(&t * 1000.0)?, &cond)?;
        let mse = (v.feats - self.fm.target(&x0, &eps)?)?.sqr()?.mean_all()?;
        let terms: Terms = [("mse".to_string(), scalar_of(&mse)?)].into();
        let info: Terms =
            [("voxels".to_string(), x0.dim(0)? as f64), ("dropped".to_string(), drop.iter().filter(|&&d| d).count() as f64)].into();
        Ok(BatchLoss { total: mse, terms, info })
    }
}
