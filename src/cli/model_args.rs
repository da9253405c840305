//! The model settings `recon infer` and `recon eval --method recgen` share: one
//! set of flags with one set of defaults, flattened into both commands.
use recon::engine::LoadOptions;
use recon::engine::ModelSource;
use recon::engine::{Dtype, InferOptions, InferSettings};
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
    /// The per-frame options (`--seed`, `--samples`, …): their names, defaults, help and
    /// checks are the library's ([`InferOptions`]).
    #[command(flatten)]
    #[serde(flatten)]
    pub infer: InferOptions,
}

/// The one line `recon infer`, `eval --method recgen` and `serve` print on stderr when no `--weights`
/// were given: the small
/// default answers, and how to load the released model instead.
pub const DEFAULT_MODEL_NOTE: &str = "recon: no --weights given, so recgen-nano answers: the small default model, trained only on \
     recon's synthetic scenes (not the released RecGen). Real weights: `recon weights fetch recgen`, then --weights recgen \
     (or --weights hf:TRI-ML/RecGen).";

impl ModelArgs {
    /// Says on stderr, once, that the default model answers ([`DEFAULT_MODEL_NOTE`]) when no
    /// `--weights` were given.
    pub fn note_default_model(&self) {
        if self.weights.is_none() {
            eprintln!("{DEFAULT_MODEL_NOTE}");
        }
    }

    pub fn source(&self) -> anyhow::Result<ModelSource> {
        Ok(ModelSource::parse(self.weights.as_deref(), self.config.as_deref(), self.infer.seed)?)
    }

    /// Load options with `--dtype` resolved for the architecture of `source`.
    pub fn load_options(&self, source: &ModelSource) -> anyhow::Result<LoadOptions> {
        Ok(source.load_options(self.dtype)?)
    }

    /// The engine's per-frame settings these flags set (checked).
    pub fn infer_settings(&self) -> anyhow::Result<InferSettings> {
        Ok(self.infer.settings()?)
    }
}
