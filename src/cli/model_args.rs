//! The model settings `recon infer` and `recon eval --method recgen` share: one
//! set of flags with one set of defaults, flattened into both commands.
use recon::engine::InferOptions;
use recon::engine::LoadOptions;
use recon::engine::ModelSource;
use recon::engine::{Dtype, MeshFrom, PoseFit, SelectMethod, ShapeFit};
use std::path::PathBuf;

#[derive(clap::Args, Clone, Debug, serde::Serialize)]
pub struct ModelArgs {
    /// Weights: a directory (`<module>.safetensors` per module), a manifest name
    /// (e.g. `recgen`, or a manifest .json) resolved in the Hugging Face cache after
    /// `recon weights fetch`, or `random` (recgen-tiny with RANDOM weights: plumbing
    /// only). Default: the trained recgen-nano: models/recgen-nano/ in the working
    /// folder when present, else the copy embedded in the binary (unpacked once under
    /// $RECON_CACHE, $XDG_CACHE_HOME/recon or ~/.cache/recon).
    #[arg(long)]
    pub weights: Option<String>,
    /// Architecture file (default: the one in a --weights folder when it holds one,
    /// else models/recgen-tiny.json; models/recgen-large.json with a manifest name).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Model precision of the inference kernels. auto: bf16 for models whose flow
    /// transformers are ≥ 512 channels wide (recgen-large), f32 for smaller ones (the
    /// default recgen-nano); bf16: bf16 weights and products, f32 accumulation
    /// (vdpbf16ps where it beats f32 FMA, else bf16 weights widened onto FMA); f16: f16
    /// weights, f32 arithmetic.
    #[arg(long, value_enum, default_value_t = Dtype::Auto)]
    pub dtype: Dtype,
    /// Model seed: sample k of an object uses seed + k (also seeds random weights).
    #[arg(long, default_value_t = 42)]
    pub seed: u64,
    /// Samples per object (seeds seed, seed+1, …): the best pose is kept and the spread of
    /// the per-sample poses reported as uncertainty.
    #[arg(long, default_value_t = 1)]
    pub samples: usize,
    /// Pose selection among views and samples (score: trimmed mean, top 10 % dropped, of
    /// observed-point-to-mesh distances, metres).
    #[arg(long, value_enum, default_value_t = SelectMethod::Cross)]
    pub select: SelectMethod,
    /// How each predicted pose is checked against the measured depth.
    #[arg(long, value_enum, default_value_t = PoseFit::Depth)]
    pub pose_fit: PoseFit,
    /// Observation-guided structure: fit the stage-1 occupancy to the depth (carve observed
    /// free space, fill the observed surface, keep the outer shell) before stage 2.
    #[arg(long, value_enum, default_value_t = ShapeFit::Depth)]
    pub shape_fit: ShapeFit,
    /// With the shape fit: the mesh is the fitted occupancy's closed, smoothed surface
    /// coloured from the decoder (`fitted`), or the stage-2 decoder's surface (`decoder`).
    #[arg(long, value_enum, default_value_t = MeshFrom::Fitted)]
    pub mesh_from: MeshFrom,
    /// Sampler steps for both stages (default: the config's).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Classifier-free guidance strength for both stages (default: the config's).
    #[arg(long)]
    pub cfg: Option<f64>,
    /// Mesh face budget: larger meshes are decimated (quadric edge collapse); 0 = no limit.
    #[arg(long, default_value_t = recon::engine::DEFAULT_MAX_FACES)]
    pub max_faces: usize,
    /// Floater removal: mesh components with less than this fraction of the total area are
    /// dropped (the largest is always kept); 0 keeps every component.
    #[arg(long, default_value_t = 0.02)]
    pub min_component_area: f64,
    /// Taubin smoothing iterations on the decoded mesh (after floater removal, before
    /// decimation); 0 keeps the decoder's surface.
    #[arg(long, default_value_t = recon::engine::DEFAULT_SMOOTH_ITERATIONS)]
    pub smooth: usize,
    /// Objects of a frame reconstructed at once (threads sharing the loaded model and the
    /// kernels' threads; 1: one after another). Results are the same for any value; more
    /// than 1 pays only with cores the model leaves idle, and costs memory per object.
    #[arg(long, default_value_t = recon::engine::DEFAULT_PARALLEL_OBJECTS)]
    pub parallel_objects: std::num::NonZeroUsize,
}

impl ModelArgs {
    pub fn source(&self) -> anyhow::Result<ModelSource> {
        Ok(ModelSource::parse(self.weights.as_deref(), self.config.as_deref(), self.seed)?)
    }

    /// Load options with `--dtype` resolved for the architecture of `source`.
    pub fn load_options(&self, source: &ModelSource) -> anyhow::Result<LoadOptions> {
        Ok(source.load_options(self.dtype)?)
    }

    /// The per-frame options these flags set (checked).
    pub fn infer_options(&self) -> anyhow::Result<InferOptions> {
        if self.samples == 0 {
            anyhow::bail!("--samples must be at least 1");
        }
        if !(0.0..1.0).contains(&self.min_component_area) {
            anyhow::bail!("--min-component-area must be in [0, 1), got {}", self.min_component_area);
        }
        let mut opts = InferOptions {
            samples: self.samples,
            select: self.select,
            align: self.pose_fit.options(),
            max_faces: (self.max_faces > 0).then_some(self.max_faces),
            floater_area_fraction: self.min_component_area,
            smooth_iterations: self.smooth,
            shape_fit: self.shape_fit,
            mesh_from: self.mesh_from,
            parallel_objects: self.parallel_objects,
            ..Default::default()
        };
        opts.run.seed = self.seed;
        (opts.run.ss_steps, opts.run.slat_steps) = (self.steps, self.steps);
        (opts.run.ss_cfg_strength, opts.run.slat_cfg_strength) = (self.cfg, self.cfg);
        Ok(opts)
    }
}
