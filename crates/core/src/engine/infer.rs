//! `recon infer` as a library: RGB-D frame + object masks → per-object pose,
//! mesh and Gaussians in the metric camera frame.
//!
//! ```no_run
//! use recon_core::dataset::{FrameOptions, InstanceMap, RgbdFrame};
//! use recon_core::engine::{Engine, InferOptions, LoadOptions, ModelSource};
//! # fn main() -> recon_core::Result<()> {
//! // The shipped recgen-nano; or ModelSource::Dir { .. }, ::Manifest { .. }, ::Random { .. }.
//! let engine = Engine::load(&ModelSource::Default, &LoadOptions::default())?;
//! let frame = RgbdFrame::open("data/sample/000001-color.png".as_ref(), &FrameOptions::default())?;
//! let (objects, _skipped) = InstanceMap::open("data/sample/000001-label.png".as_ref())?.objects(None);
//! // The CLI's defaults; `InferOptions` is what `recon infer`'s flags and Python's keywords set.
//! let settings = InferOptions::default().settings()?;
//! let result = engine.reconstruct(&frame, objects, &settings)?;
//! for o in &result.objects { println!("{} {:?}", o.label, o.pose_camera.translation); }
//! # Ok(()) }
//! ```
//!
//! The model is loaded once ([`Engine`]) and reused for every object.
//! Objects that fail validation or preprocessing are reported in
//! [`FrameResult::skipped`] and do not stop the others.
//!
//! **Two views** ([`Engine::reconstruct_two_view`]): each view is prepared
//! on its own (own crop and normaliser, as RecGen's `generate_multiview`)
//! and both condition one run; pose token `k` belongs to view `k` and is
//! mapped to view `k`'s camera through view `k`'s normaliser, then to the
//! anchor (view 1) camera with the relative pose `T_c1_c2`.
//!
//! **N views** ([`Engine::reconstruct_views`]): with more views than the
//! model's pose tokens, the anchor is paired with every other view and the
//! pairs are fused at every sampling step (RecGen `generate_multiview` with
//! several second views; [`crate::engine::pipeline`], **Pair fusion**). Only
//! the anchor's token is a pose of its own, so it is the one candidate of a
//! sample; every view's observed points still score it, and every view's
//! depth carves and fills the shape fit.
//!
//! **Samples and selection**: with `samples > 1` the object is run with
//! seeds `seed, seed + 1, …`. Every (sample, view) pose is a candidate,
//! scored by the trimmed-mean distance of the observed points to its posed
//! mesh ([`crate::engine::score_candidate`]); the winner gives the reported
//! pose, mesh and Gaussians, and the spread of the per-sample winners is the
//! uncertainty figure. Everything is reported in the anchor camera frame.

use crate::dataset::frame::{depth_valid, Intrinsics, RgbdFrame};
use crate::dataset::masks::{check_object, MaskOptions, MaskSkip, ObjectMask, SkipReason};
use crate::engine::options::{
    InferOptions, MeshColour, OptionError, PosthocColor, DEFAULT_MAX_FACES, DEFAULT_MAX_OBJECTS, DEFAULT_PARALLEL_OBJECTS,
    DEFAULT_SMOOTH_ITERATIONS, DEFAULT_TEXTURE_SIZE,
};
use crate::engine::pipeline::Weights;
use crate::engine::pipeline::{
    LoadOptions, ObjectInputs, ObjectReconstruction, Pipeline, PredictedPose, RunMetadata, RunOptions, Stage, StageTimings, Stages,
    ViewInput, MAX_SECOND_VIEWS,
};
use crate::engine::pose_fit::refine_pose;
use crate::engine::pose_fit::AlignOptions;
use crate::engine::pose_fit::DepthView;
use crate::engine::pose_fit::ViewPoints;
use crate::engine::pose_fit::{pose_spread, select_best, PoseSpread, SelectMethod};
use crate::engine::pose_fit::{score_candidate, CandidateScore, Surface};
use crate::engine::posthoc_color::{self, PhotoView, PosthocColorRecord};
use crate::engine::shape_fit::{fit_in_pose, rest_on_supports, Grid, MeshFrom, ShapeFit, ShapeFitOptions, ShapeFitReport};
use crate::engine::source::{default_model_dir, find_architecture, ModelSource};
use crate::gaussians::Gaussians;
use crate::gaussians::{stretch_gaussians, SH_C0};
use crate::geometry::camera_pose::pose_to_camera;
use crate::geometry::plane::{fit_plane, Plane, PlaneFitOptions};
use crate::geometry::pointmap::backproject;
use crate::geometry::pointmap::{object_points, prepare_frame_objects, Normaliser, PrepareOptions, PreparedView};
use crate::geometry::pose::{pose_to_similarity, similarity_to_pose};
use crate::geometry::pose::{Pose, PoseRepresentation};
use crate::math::Similarity;
use crate::mesh::post::{decimate, drop_floaters, taubin_smooth};
use crate::mesh::stretch_mesh;
use crate::mesh::Mesh;
use crate::model::sampler::Fusion;
use crate::spatial::KdTree;
use crate::weights::WeightFiles;
use crate::{Error, Result};
use candle_core::Device;
use serde::Serialize;
use std::num::NonZeroUsize;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::sync::{Mutex, PoisonError};
use std::time::Instant;

pub use crate::math::Similarity as RigidTransform;

/// The engine's per-frame settings, derived from the user-facing
/// [`InferOptions`](crate::engine::options::InferOptions) ([`settings`](crate::engine::options::InferOptions::settings)); library callers may set the internal ones here.
///
/// `Default` is the engine's plain baseline (RecGen's one-sided score, no
/// refinement); the defaults of the CLI and Python are `InferOptions::default().settings()`.
#[derive(Debug, Clone)]
pub struct InferSettings {
    /// Model run settings; `run.seed` is the first sample's seed.
    pub run: RunOptions,
    /// Minimum eroded-mask pixels with valid depth for an object to run.
    pub min_valid_depth_pixels: usize,
    /// Preprocessing of each view: mask erosion, crop, point-map normalisation.
    pub prepare: PrepareOptions,
    /// Samples per object (seeds `run.seed`, `run.seed + 1`, …); the best
    /// pose is selected and the spread reported.
    pub samples: usize,
    /// How the pose is chosen among views and samples ([`SelectMethod`]).
    pub select: SelectMethod,
    /// How candidate poses are refined and scored against the observed points and depth.
    pub align: AlignOptions,
    /// Meshes with more faces are decimated (quadric edge collapse) to about
    /// this many; `None` keeps the decoder's mesh.
    pub max_faces: Option<usize>,
    /// Connected components with less than this fraction of the mesh's area
    /// are dropped as floaters before decimation (0: keep all; the largest
    /// component is always kept).
    pub floater_area_fraction: f64,
    /// Taubin smoothing iterations on the decoded mesh, after floater removal
    /// and before decimation (0: the decoder's surface as it is).
    pub smooth_iterations: usize,
    /// Whether the stage-1 occupancy is fitted to the depth before stage 2
    /// ([`crate::engine::fit_in_pose`]); the pose is then refined before the
    /// fit and not after it, so the fit sees the final pose.
    pub shape_fit: ShapeFit,
    /// Settings of the shape fit; [`ShapeFit::DepthHull`] turns its `hull` on whatever is set here.
    pub shape_fit_options: ShapeFitOptions,
    /// With the shape fit, whether the mesh is the fitted occupancy's closed
    /// surface or the stage-2 decoder's (without the fit: always the decoder's).
    pub mesh_from: MeshFrom,
    /// Objects of a frame reconstructed at once, each in a thread of its own
    /// sharing the loaded model and the rayon pool; the results do not depend
    /// on it (an object's seeds are its own). Default
    /// [`DEFAULT_PARALLEL_OBJECTS`].
    pub parallel_objects: NonZeroUsize,
    /// Most objects of a frame that pass the mask checks; a frame with more is
    /// refused before any object runs ([`check_object_count`]).
    pub max_objects: NonZeroUsize,
    /// Post-hoc colour calibration of each object against the anchor photo
    /// ([`crate::engine::posthoc_color`]).
    pub posthoc_color: PosthocColor,
    /// Whether each object's mesh gets a UV atlas and a texture baked from the views
    /// ([`ObjectResult::textured`]), or keeps its vertex colours alone.
    pub colour: MeshColour,
    /// Side of the baked texture, texels.
    pub texture_size: u32,
}

impl Default for InferSettings {
    fn default() -> Self {
        Self {
            run: RunOptions::default(),
            min_valid_depth_pixels: 100,
            prepare: PrepareOptions::default(),
            samples: 1,
            select: SelectMethod::Cross,
            align: AlignOptions::default(),
            max_faces: Some(DEFAULT_MAX_FACES),
            floater_area_fraction: 0.02,
            smooth_iterations: DEFAULT_SMOOTH_ITERATIONS,
            shape_fit: ShapeFit::default(),
            shape_fit_options: ShapeFitOptions::default(),
            mesh_from: MeshFrom::default(),
            parallel_objects: DEFAULT_PARALLEL_OBJECTS,
            max_objects: DEFAULT_MAX_OBJECTS,
            posthoc_color: PosthocColor::None,
            // The plain baseline bakes nothing; `InferOptions` (CLI, Python) defaults to textures.
            colour: MeshColour::Vertex,
            texture_size: DEFAULT_TEXTURE_SIZE,
        }
    }
}

// Here rather than in `options`, so that the options module does not import the engine
// (the engine imports the options' defaults and errors).
impl InferOptions {
    /// The engine's settings for these options (checked first).
    pub fn settings(&self) -> std::result::Result<InferSettings, OptionError> {
        self.validate()?;
        let mut s = InferSettings {
            samples: self.samples,
            select: self.select,
            align: self.pose_fit.options(),
            max_faces: (self.max_faces > 0).then_some(self.max_faces),
            floater_area_fraction: self.min_component_area,
            smooth_iterations: self.smooth,
            shape_fit: self.shape_fit,
            mesh_from: self.mesh_from,
            parallel_objects: self.parallel_objects,
            max_objects: self.max_objects,
            posthoc_color: self.posthoc_color,
            colour: self.colour,
            texture_size: self.texture_size,
            ..Default::default()
        };
        s.run.seed = self.seed;
        s.run.use_pointmap = self.use_pointmap;
        s.prepare.quantile_drop = self.quantile_drop_threshold;
        s.prepare.clamp = Some((self.clamp_range.low as f32, self.clamp_range.high as f32));
        s.prepare.erosion = self
            .mask_erosion_enabled
            .then_some(crate::dataset::masks::Erosion { kernel: self.mask_erosion_kernel_size, iterations: self.mask_erosion_iterations });
        // One `--steps` / `--cfg` sets both stages' samplers.
        (s.run.ss_steps, s.run.slat_steps) = (self.steps, self.steps);
        (s.run.ss_cfg_strength, s.run.slat_cfg_strength) = (self.cfg, self.cfg);
        (s.run.fusion, s.run.slat_fusion) = (self.fusion, self.slat_fusion);
        Ok(s)
    }
}

/// A view besides the anchor: the second view of a two-view
/// reconstruction, or one of several ([`Engine::reconstruct_views`]).
pub struct SecondView<'a> {
    /// This view's RGB-D frame.
    pub frame: &'a RgbdFrame,
    /// This frame's masks, matched to the anchor frame's by instance id, or
    /// by order when masks carry no id ([`match_views`]).
    pub objects: Vec<ObjectMask>,
    /// This view's camera → the anchor camera, rigid: `x₁ = R·xᵢ + t` (metres).
    pub t_c1_c2: RigidTransform,
}

/// What the engine is doing, for progress displays.
#[derive(Debug, Clone, Copy)]
pub enum Progress<'a> {
    /// An object starts (its views are prepared, then its samples run).
    Object {
        /// Position of the object in the frame's list, from 0.
        index: usize,
        /// Objects in the frame.
        total: usize,
        /// The object's mask label.
        label: &'a str,
    },
    /// A sample of the current object starts.
    Sample {
        /// Sample number, from 0.
        index: usize,
        /// Samples per object.
        total: usize,
        /// This sample's seed (`run.seed + index`).
        seed: u64,
    },
    /// A model stage of the current sample starts.
    Stage(Stage),
    /// Applying the face budget.
    Decimating,
    /// Scoring the candidate poses.
    Selecting,
    /// An object is reconstructed (not sent for an object that is skipped).
    ObjectDone {
        /// The object's mask label.
        label: &'a str,
        /// Wall-clock seconds since the object started, preprocessing included.
        seconds: f64,
    },
}

/// A loaded model, reused across objects and frames.
pub struct Engine {
    /// The loaded two-stage model.
    pub pipeline: Pipeline,
}

/// One view of a reconstructed object.
#[derive(Debug, Clone, Serialize)]
pub struct ViewPose {
    /// 1 = the anchor (`--rgbd`), 2 = `--view2` or the first `--view`, 3 = the next, …
    pub view: usize,
    /// This view's colour image file.
    pub frame: PathBuf,
    /// Label of this view's object mask.
    pub mask: String,
    /// This view's point normaliser (metres).
    pub normaliser_centre_m: [f64; 3],
    /// This view's point normaliser diameter (metres).
    pub normaliser_diameter_m: f64,
    /// Observed object points (eroded mask, valid depth).
    pub observed_points: usize,
    /// This view's own pose token of the selected sample, in this view's
    /// camera frame; `None` (left out of the JSON) for the views besides the
    /// anchor of a run with pair fusion, which have no token of their own.
    #[serde(serialize_with = "ser_opt_pose", skip_serializing_if = "Option::is_none")]
    pub pose_own_token: Option<Pose>,
    /// The selected pose in this view's camera frame.
    #[serde(serialize_with = "ser_pose")]
    pub pose_selected: Pose,
}

/// One candidate pose: one view's token of one sample.
#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    /// Seed of the sample the candidate comes from.
    pub seed: u64,
    /// The view whose token it is: its position in [`ObjectResult::views`], from 1.
    pub view: usize,
    /// In the anchor camera frame (after refinement with `--pose-fit depth`).
    #[serde(serialize_with = "ser_pose")]
    pub pose_camera: Pose,
    /// Per-axis stretch of the object frame fitted with `--pose-fit
    /// depth-stretch` (`[1, 1, 1]` otherwise); the mesh is stretched before the pose.
    pub stretch: [f64; 3],
    /// Per-view score (metres): trimmed-mean distance of the observed points
    /// to the mesh, plus the free-space term with `--pose-fit depth`.
    pub score: CandidateScore,
}

/// Which candidate won.
#[derive(Debug, Clone, Serialize)]
pub struct Selection {
    /// The selection method used.
    pub method: SelectMethod,
    /// Index into [`ObjectResult::candidates`].
    pub candidate: usize,
    /// Seed of the winning candidate's sample.
    pub seed: u64,
    /// The view whose token won: its position in [`ObjectResult::views`], from 1.
    pub view: usize,
    /// The selection key (metres): own-view score (`single`, `first`) or the mean over views (`cross`).
    pub score_m: f64,
}

/// One reconstructed object.
#[derive(Debug, Clone)]
pub struct ObjectResult {
    /// The object's mask label (view 1's).
    pub label: String,
    /// The mask's instance id, when it has one.
    pub id: Option<u32>,
    /// The selected token's pose: canonical object frame → that view's normalised pointmap frame.
    pub pose_normalised: Pose,
    /// The selected pose: canonical object frame → metric (anchor) camera frame.
    pub pose_camera: Pose,
    /// Which candidate was selected, and its score.
    pub selection: Selection,
    /// Each view of the object, view 1 first.
    pub views: Vec<ViewPose>,
    /// Every scored candidate, in sample order, then view order.
    pub candidates: Vec<Candidate>,
    /// Spread of the per-sample poses (with two or more samples).
    pub uncertainty: Option<PoseSpread>,
    /// Occupied stage-1 voxels stage 2 ran on, of the selected sample (after the shape fit, when it ran).
    pub occupied_voxels: usize,
    /// What the shape fit did to the selected sample's occupancy (`None`: not run).
    pub shape_fit: Option<ShapeFitReport>,
    /// Faces as decoded, before the face budget.
    pub faces_decoded: usize,
    /// Mesh and Gaussians placed in the anchor camera frame (metres).
    pub mesh_camera: Option<Mesh>,
    /// Gaussians placed in the anchor camera frame (metres); `None` when not decoded.
    pub gaussians_camera: Option<Gaussians>,
    /// The mesh in the object frame, before the pose (RecGen's `raw_mesh`): the decoder's
    /// canonical `[-0.5, 0.5]³`, z up; with the shape fit that cube re-fitted around the
    /// fitted solid (same axes, the pose absorbing shift and scale), and stretched per axis
    /// with `--pose-fit depth-stretch`. `mesh_camera` is this mesh placed by `pose_camera`.
    pub mesh_object: Option<Mesh>,
    /// The Gaussians in the object frame (as `mesh_object`); `gaussians_camera` is these
    /// placed by `pose_camera`.
    pub gaussians_object: Option<Gaussians>,
    /// Observed object points (anchor camera frame, metres) of every view, view 1 first.
    pub observed_points: Vec<[f32; 3]>,
    /// RGB colour of each of `observed_points`, in the same order.
    pub observed_colors: Vec<[u8; 3]>,
    /// Model stages, summed over samples.
    pub timings: StageTimings,
    /// Decimation seconds.
    pub postprocess_seconds: f64,
    /// Scoring and selection seconds.
    pub select_seconds: f64,
    /// The selected sample's run.
    pub metadata: RunMetadata,
    /// Samples requested per object ([`InferSettings::samples`]), failed ones included.
    pub samples: usize,
    /// Remarks on the object (failed samples, a view 2 without a usable mask, …).
    pub notes: Vec<String>,
    /// The post-hoc colour calibration (`None` when not asked for): the transform applied
    /// to the Gaussians (and the model-coloured mesh) above, or why none was.
    pub posthoc_color: Option<PosthocColorRecord>,
    /// With [`MeshColour::Texture`]: `mesh_camera` laid out on a UV atlas (seam vertices
    /// duplicated) with its texture, baked from every view's photo where the view's depth
    /// sees the surface, else from the vertex colours ([`crate::render::bake`]).
    pub textured: Option<crate::mesh::TexturedMesh>,
    /// Where the texture's texels came from (its seconds are in `postprocess_seconds`).
    pub texture_report: Option<TextureReport>,
}

/// What the texture bake of an object did.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TextureReport {
    /// Side of the texture, texels.
    pub size: u32,
    /// Charts of the UV atlas.
    pub charts: usize,
    /// Where the texels came from.
    #[serde(flatten)]
    pub texels: crate::render::BakeReport,
    /// Atlas and bake, wall-clock seconds: counted in the object's post-processing time, and
    /// kept out of pose.json's texture record, which a seed reproduces byte for byte.
    #[serde(skip)]
    pub seconds: f64,
}

/// The textured form of `mesh` (anchor camera frame) baked from `views`: each view's
/// photo, measured depth and intrinsics, with its camera → anchor transform.
fn bake_views(mesh: &Mesh, views: &[ObjView], size: u32) -> Result<(crate::mesh::TexturedMesh, TextureReport)> {
    let t = Instant::now();
    let bv: Vec<crate::render::BakeView> = views
        .iter()
        .map(|v| crate::render::BakeView {
            rgb: &v.frame.rgb,
            depth_m: &v.frame.depth_m,
            width: v.frame.width,
            height: v.frame.height,
            intrinsics: v.frame.intrinsics,
            camera_from_mesh: v.points.to_anchor.inverse(),
        })
        .collect();
    let (tm, texels) = crate::render::texture_mesh(mesh, size, &bv, &crate::render::BakeOptions::default())?;
    let charts = tm.atlas.charts;
    Ok((tm, TextureReport { size, charts, texels, seconds: t.elapsed().as_secs_f64() }))
}

/// Everything one frame produces.
#[derive(Debug, Clone)]
pub struct FrameResult {
    /// The reconstructed objects, in mask order.
    pub objects: Vec<ObjectResult>,
    /// Objects left out, with the reason (validation, preprocessing or model failure).
    pub skipped: Vec<MaskSkip>,
    /// Seconds spent preparing the objects' views (crops, point maps), summed over objects.
    pub preprocess_seconds: f64,
    /// Frame-level remarks (e.g. masks of view 2 without a partner in view 1).
    pub notes: Vec<String>,
    /// The anchor view's colour image and camera (RecGen's result keeps them for its overlay).
    pub image: FrameImage,
    /// Layout of the model's stage-1 pose tokens (RecGen's `pose_representation`).
    pub pose_representation: PoseRepresentation,
}

/// A frame's colour image and intrinsics.
#[derive(Clone, PartialEq)]
pub struct FrameImage {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Interleaved RGB, row-major, `width · height · 3` bytes.
    pub rgb: Vec<u8>,
    /// The camera's pinhole intrinsics.
    pub intrinsics: Intrinsics,
}

impl FrameImage {
    /// The colour image and intrinsics of `frame` (a copy).
    pub fn of(frame: &RgbdFrame) -> Self {
        FrameImage { width: frame.width, height: frame.height, rgb: frame.rgb.clone(), intrinsics: frame.intrinsics }
    }
}

// Not the pixels: a result printed with {:?} stays readable.
impl std::fmt::Debug for FrameImage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameImage")
            .field("width", &self.width)
            .field("height", &self.height)
            .field("intrinsics", &self.intrinsics)
            .finish()
    }
}

/// Refuses a frame with more objects than `opts.max_objects` that pass the mask checks
/// ([`check_object`](crate::dataset::masks::check_object): the objects the model would
/// run on); returns their count. Tiny masks are checked on their runs, so this costs the
/// masks' pixels, not a frame per mask. `what` names the masks in the error (`--masks`).
pub fn check_object_count(frame: &RgbdFrame, objects: &[ObjectMask], opts: &InferSettings, what: &str) -> Result<usize> {
    let mopts = MaskOptions { erosion: opts.prepare.erosion, min_valid_depth_pixels: opts.min_valid_depth_pixels };
    let count = objects.iter().filter(|o| check_object(frame, o, &mopts).is_ok()).count();
    let limit = opts.max_objects.get();
    if count > limit {
        return Err(Error::too_large(
            what,
            "max_objects",
            count as u128,
            limit as u128,
            "objects",
            "masks that pass the mask checks, each a model run; raise --max-objects (max_objects) or select instances (--objects)",
        ));
    }
    Ok(count)
}

/// Refuses more than [`MAX_SECOND_VIEWS`] views besides the anchor, before any
/// work (each is a fused condition of every object's run).
pub fn check_view_count(others: usize) -> Result<()> {
    if others > MAX_SECOND_VIEWS {
        return Err(Error::too_large(
            "views",
            "count",
            others as u128,
            MAX_SECOND_VIEWS as u128,
            "views besides the anchor",
            "each is a fused condition of every object's run (memory, and with multidiffusion a model pass per step)",
        ));
    }
    Ok(())
}

/// Pair the objects of two views: by instance id when every mask has one,
/// else by order (then both views must list the same number of masks).
/// Objects of view 1 without a partner run on view 1 alone; view-2 masks
/// without a partner are reported in the returned notes.
#[allow(clippy::type_complexity)]
pub fn match_views(v1: Vec<ObjectMask>, v2: Vec<ObjectMask>) -> Result<(Vec<(ObjectMask, Option<ObjectMask>)>, Vec<String>)> {
    let (partners, notes) = match_view(&v1, v2, 2).map_err(|e| match e {
        Error::Input { msg, .. } => Error::input("--masks2", msg),
        e => e,
    })?;
    Ok((v1.into_iter().zip(partners).collect(), notes))
}

/// The partner in view `view` (2, 3, …) of each anchor object of `v1`, as
/// [`match_views`] pairs them, and notes on `view`'s masks without a partner.
/// A count mismatch without ids is an error naming the view.
pub fn match_view(v1: &[ObjectMask], vk: Vec<ObjectMask>, view: usize) -> Result<(Vec<Option<ObjectMask>>, Vec<String>)> {
    let by_id = v1.iter().chain(&vk).all(|o| o.id.is_some());
    if !by_id {
        if v1.len() != vk.len() {
            return Err(Error::input(
                format!("view {view} masks"),
                format!(
                    "{} mask(s) for view {view} but {} for view 1: masks without instance ids are matched by order",
                    vk.len(),
                    v1.len()
                ),
            ));
        }
        return Ok((vk.into_iter().map(Some).collect(), Vec::new()));
    }
    let mut vk: Vec<Option<ObjectMask>> = vk.into_iter().map(Some).collect();
    let partners = v1.iter().map(|a| vk.iter_mut().find(|b| b.as_ref().is_some_and(|b| b.id == a.id)).and_then(Option::take)).collect();
    let notes = vk.into_iter().flatten().map(|b| format!("view {view}: {} has no partner in view 1; ignored", b.label)).collect();
    Ok((partners, notes))
}

fn add_timings(a: &mut StageTimings, b: &StageTimings) {
    a.image_encoder += b.image_encoder;
    a.ss_condition += b.ss_condition;
    a.ss_sampling += b.ss_sampling;
    a.ss_decoder += b.ss_decoder;
    a.pose += b.pose;
    a.shape_fit += b.shape_fit;
    a.slat_condition += b.slat_condition;
    a.slat_sampling += b.slat_sampling;
    a.mesh_decoder += b.mesh_decoder;
    a.flexicubes += b.flexicubes;
    a.gaussian_decoder += b.gaussian_decoder;
    a.loading += b.loading;
    a.total += b.total;
}

/// A prepared view of one object with what scoring needs.
struct ObjView<'a> {
    /// The input view it comes from: 1 = the anchor, 2 = the first view besides it, …
    number: usize,
    frame: &'a RgbdFrame,
    /// The frame's support plane (camera frame, facing the camera), for the shape fit.
    support: Option<Plane>,
    label: String,
    prepared: PreparedView,
    points: ViewPoints,
}

/// `number`: the input view (1 = the anchor); `depth`: the frame's free-space depth view, shared by all its objects.
fn object_view<'a>(
    number: usize,
    frame: &'a RgbdFrame,
    label: String,
    prepared: PreparedView,
    to_anchor: RigidTransform,
    depth: Option<Arc<DepthView>>,
    support: Option<Plane>,
) -> Result<ObjView<'a>> {
    let (points, _) = object_points(frame, &prepared.mask_full, None)?;
    Ok(ObjView { number, frame, support, label, prepared, points: ViewPoints { points, to_anchor, depth } })
}

/// A frame besides the anchor's, with what all its objects share.
struct ExtraFrame<'a> {
    frame: &'a RgbdFrame,
    /// This camera → the anchor camera.
    to_anchor: RigidTransform,
    depth: Option<Arc<DepthView>>,
    plane: Option<Plane>,
}

/// The dominant plane of a frame's depth, facing the camera (`None` when the
/// fit fails or the shape fit is off).
fn support_plane(frame: &RgbdFrame, opts: &InferSettings) -> Option<Plane> {
    if opts.shape_fit == ShapeFit::None {
        return None;
    }
    let pts = backproject(&frame.depth_m, frame.width, frame.height, &frame.intrinsics).ok()?;
    fit_plane(&pts, &PlaneFitOptions::default()).ok().map(|f| f.plane.facing(&[0.0; 3]))
}

/// A frame's depth view for the free-space term and the shape fit (built
/// once per frame, and only when one of them uses it).
fn depth_view(frame: &RgbdFrame, opts: &InferSettings) -> Option<Arc<DepthView>> {
    let used = opts.align.free_space_weight > 0.0 || opts.shape_fit != ShapeFit::None;
    used.then(|| DepthView::new(&frame.depth_m, frame.width, frame.height, frame.intrinsics)).flatten()
}

/// The shape fit of one sample: the pose it was fitted in and the voxels.
struct Fitted {
    /// The token (view index) whose pose won.
    view: usize,
    /// Canonical → anchor camera, refined against the depth before the fit.
    anchor: Similarity,
    stretch: [f64; 3],
    report: ShapeFitReport,
    /// The fitted occupancy handed to stage 2 (its outer shell).
    shell: Grid,
}

/// Refine every token's pose against the model's own occupancy (its outer
/// shell), pick one as the selection would, and fit the occupancy in that
/// pose ([`crate::engine::shape_fit`]); returns the fit and the voxels for stage 2.
fn fit_shape(
    pose: &PredictedPose,
    coords: &[[i32; 3]],
    r: usize,
    views: &[ObjView],
    view_points: &[ViewPoints],
    supports: &[Option<Plane>],
    opts: &InferSettings,
) -> Result<(Fitted, Vec<[i32; 3]>)> {
    let model = Grid::from_coords(coords, r);
    let surface = Surface::from_points(&model.outer_surface_points())?;
    let mut cands = Vec::new();
    // The views with a pose token of their own (with pair fusion the anchor alone).
    for (k, v) in views.iter().enumerate().take(pose.view_tokens) {
        let own = pose_to_similarity(&pose_to_camera(&pose.per_token[k], &v.prepared.normaliser));
        let mut anchor = v.points.to_anchor.compose(&own);
        let mut stretch = [1.0; 3];
        if opts.align.refine {
            let r = refine_pose(&surface, &anchor, view_points, &opts.align);
            (anchor, stretch) = (r.pose, r.stretch);
        }
        let score = score_candidate(&surface, &anchor, k, view_points, &opts.align);
        cands.push((k, anchor, stretch, score));
    }
    let scores: Vec<CandidateScore> = cands.iter().map(|c| c.3.clone()).collect();
    let (view, anchor, stretch, _) = cands.swap_remove(select_best(opts.select, &scores).unwrap_or(0));
    let fo = &ShapeFitOptions { hull: opts.shape_fit_options.hull || opts.shape_fit == ShapeFit::DepthHull, ..opts.shape_fit_options };
    let (anchor, shell, report) = fit_in_pose(model, anchor, stretch, view_points, supports, fo);
    let coords = shell.coords();
    Ok((Fitted { view, anchor, stretch, report, shell }, coords))
}

/// The closed surface of the fitted occupancy ([`Grid::smooth_surface`] at
/// twice its resolution, Taubin-smoothed against the facets of the
/// tetrahedra), coloured from the measured colours of the object's observed
/// points (4 nearest; the hidden side takes the nearest seen colour), or from
/// the Gaussians' degree-0 colour without observed points.
/// `observed`: the object's observed points (anchor frame) and their colours.
fn fitted_surface(fitted: &Fitted, observed: (&[[f32; 3]], &[[u8; 3]]), gaussians: Option<&Gaussians>, floater_area_fraction: f64) -> Mesh {
    let mut m = taubin_smooth(&drop_floaters(fitted.shell.smooth_surface(2), floater_area_fraction), 30);
    let to_canonical = fitted.anchor.inverse();
    let mut points: Vec<[f32; 3]> = observed
        .0
        .iter()
        .map(|q| {
            let c = to_canonical.apply(&q.map(|x| x as f64));
            std::array::from_fn(|a| (c[a] / fitted.stretch[a]) as f32)
        })
        .collect();
    let mut rgb: Vec<[f32; 3]> = observed.1.iter().map(|c| c.map(|x| x as f32 / 255.0)).collect();
    if points.is_empty() {
        if let Some(g) = gaussians.filter(|g| !g.is_empty()) {
            points = g.positions.clone();
            rgb = g.dc.iter().map(|d| d.map(|c| (SH_C0 * c + 0.5).clamp(0.0, 1.0))).collect();
        }
    }
    if !points.is_empty() {
        // A k-d tree, not transfer_colors' grid: the hidden side lies far from every seen point.
        let tree = KdTree::new(&points.iter().map(|p| p.map(|x| x as f64)).collect::<Vec<_>>());
        let queries: Vec<[f64; 3]> = m.vertices.iter().map(|v| v.map(|x| x as f64)).collect();
        let attrs = tree
            .k_nearest_all(&queries, 4)
            .iter()
            .map(|near| {
                let (mut acc, mut wsum) = ([0f64; 3], 0f64);
                for &(i, d) in near {
                    let w = 1.0 / (d + 1e-6);
                    acc = std::array::from_fn(|k| acc[k] + w * rgb[i][k] as f64);
                    wsum += w;
                }
                let c = acc.map(|x| (x / wsum) as f32);
                [c[0], c[1], c[2], 0.5, 0.5, 0.5]
            })
            .collect();
        m.vertex_attrs = Some(attrs);
    }
    m
}

/// The observed points of a view in the anchor frame, with their colours.
fn observed_in_anchor(v: &ObjView) -> (Vec<[f32; 3]>, Vec<[u8; 3]>) {
    let f = v.frame;
    let cols = (0..f.width * f.height)
        .filter(|&i| v.prepared.mask_full[i] && depth_valid(f.depth_m[i]))
        .map(|i| [f.rgb[3 * i], f.rgb[3 * i + 1], f.rgb[3 * i + 2]])
        .collect();
    let pts = v.points.points.iter().map(|p| v.points.to_anchor.apply(p).map(|x| x as f32)).collect();
    (pts, cols)
}

/// The outputs kept of the best sample so far.
struct Kept {
    per_token: Vec<Pose>,
    /// Views `0..view_tokens` have their own token ([`PredictedPose::view_tokens`]).
    view_tokens: usize,
    coords: usize,
    faces_decoded: usize,
    mesh: Option<Mesh>,
    gaussians: Option<Gaussians>,
    metadata: RunMetadata,
    shape_fit: Option<ShapeFitReport>,
}

/// How one object of a frame ended (a result is large, a skip small).
enum ObjectOutcome {
    Done(Box<ObjectResult>),
    Skipped(Vec<MaskSkip>),
}

/// Stack of an object's thread: the size of a main thread's, where objects
/// run one at a time.
const OBJECT_STACK_BYTES: usize = 8 << 20;

/// `f(index, item)` for every item, at most `workers` at once, each in a
/// thread of its own (the model's kernels inside still share the global
/// rayon pool, the model its weights); results in item order. Once a result
/// is flagged by `stop`, no further item starts (its slot stays `None`).
fn map_in_flight<T: Send, R: Send>(
    items: Vec<T>,
    workers: usize,
    f: impl Fn(usize, T) -> R + Sync,
    stop: impl Fn(&R) -> bool + Sync,
) -> Result<Vec<Option<R>>> {
    let n = items.len();
    if workers <= 1 || n <= 1 {
        let mut out = Vec::with_capacity(n);
        for (i, t) in items.into_iter().enumerate() {
            let r = f(i, t);
            let halt = stop(&r);
            out.push(Some(r));
            if halt {
                break;
            }
        }
        return Ok(out);
    }
    let next = Mutex::new(items.into_iter().enumerate());
    let halted = AtomicBool::new(false);
    let slots: Vec<Mutex<Option<R>>> = (0..n).map(|_| Mutex::new(None)).collect();
    std::thread::scope(|s| -> Result<()> {
        let work = || loop {
            if halted.load(Ordering::Relaxed) {
                break;
            }
            let item = next.lock().unwrap_or_else(PoisonError::into_inner).next();
            let Some((i, t)) = item else { break };
            let r = f(i, t);
            if stop(&r) {
                halted.store(true, Ordering::Relaxed);
            }
            *slots[i].lock().unwrap_or_else(PoisonError::into_inner) = Some(r);
        };
        for k in 0..workers.min(n) {
            std::thread::Builder::new()
                .name(format!("recon-object-{k}"))
                .stack_size(OBJECT_STACK_BYTES)
                .spawn_scoped(s, work)
                .map_err(|e| Error::msg(format!("starting an object thread: {e}")))?;
        }
        Ok(())
    })?;
    Ok(slots.into_iter().map(|m| m.into_inner().unwrap_or_else(PoisonError::into_inner)).collect())
}

impl Engine {
    /// Load a model (see [`ModelSource`]): the one constructor.
    pub fn load(source: &ModelSource, options: &LoadOptions) -> Result<Self> {
        let all = Stages::All;
        let pipeline = match source {
            ModelSource::Default => {
                let dir = default_model_dir()?;
                Pipeline::load(&find_architecture(&dir)?, Weights::Dir(&dir), all, options)?
            }
            ModelSource::Dir { dir, .. } => Pipeline::load(&source.architecture()?, Weights::Dir(dir), all, options)?,
            ModelSource::Manifest { name, cache, .. } => {
                let config = source.architecture()?;
                let cfg = crate::model::config::RecGenConfig::load(&config)?;
                let manifest = crate::engine::source::manifest_of(name)?;
                // What the cache lacks is downloaded as `recon weights fetch` downloads it.
                let download = |m: &crate::weights::Manifest, files: &[&crate::weights::ManifestFile], cache: &std::path::Path| {
                    crate::weights::fetch::get_files(m, files, cache, false).map(|_| ())
                };
                let files: WeightFiles = crate::weights::manifest::resolve_manifest(&manifest, name, &cfg, cache, Some(&download))?;
                Pipeline::load(&config, Weights::Files(&files), all, options)?
            }
            ModelSource::Random { seed, .. } => Pipeline::load(&source.architecture()?, Weights::Random(*seed), all, options)?,
        };
        Ok(Self { pipeline })
    }

    /// Reconstruct every object of a frame (single view).
    pub fn reconstruct(&self, frame: &RgbdFrame, objects: Vec<ObjectMask>, opts: &InferSettings) -> Result<FrameResult> {
        self.reconstruct_with(frame, objects, None, opts, &|_| {})
    }

    /// Reconstruct every object seen in two views (RecGen two-view conditioning).
    pub fn reconstruct_two_view(
        &self,
        frame: &RgbdFrame,
        objects: Vec<ObjectMask>,
        second: SecondView,
        opts: &InferSettings,
    ) -> Result<FrameResult> {
        self.reconstruct_with(frame, objects, Some(second), opts, &|_| {})
    }

    /// One or two views: [`Self::reconstruct_views`] with `second` as the one view besides the anchor.
    pub fn reconstruct_with(
        &self,
        frame: &RgbdFrame,
        objects: Vec<ObjectMask>,
        second: Option<SecondView>,
        opts: &InferSettings,
        progress: &(dyn Fn(Progress) + Sync),
    ) -> Result<FrameResult> {
        self.reconstruct_views(frame, objects, second.into_iter().collect(), opts, progress)
    }

    /// The general entry: the anchor frame and any number of other views (at
    /// most [`MAX_SECOND_VIEWS`]; more than the model's pose tokens run as
    /// fused pairs, module docs), `opts.samples` seeds per object, pose
    /// selection, face budget; `progress` hears what is running.
    ///
    /// Per-object problems (masks, depth, an empty occupancy for every seed)
    /// become [`FrameResult::skipped`]; an object's view besides the anchor
    /// that fails preprocessing is left out of that object, with a note.
    pub fn reconstruct_views(
        &self,
        frame: &RgbdFrame,
        objects: Vec<ObjectMask>,
        others: Vec<SecondView>,
        opts: &InferSettings,
        progress: &(dyn Fn(Progress) + Sync),
    ) -> Result<FrameResult> {
        if opts.samples == 0 {
            return Err(OptionError::new("samples", "at least 1", opts.samples).into());
        }
        if !others.is_empty() && self.pipeline.max_views() < 2 {
            return Err(Error::config(
                &self.pipeline.config.name,
                "ss_flow.args.num_pose_tokens",
                format!("this model takes {} view(s); a second view needs a two-view (num_pose_tokens 2) model", self.pipeline.max_views()),
            ));
        }
        check_view_count(others.len())?;
        check_object_count(frame, &objects, opts, "masks")?;
        let size = self.pipeline.image_size();
        let dev = Device::Cpu;
        let mut preprocess_seconds = 0.0;
        let n_other = others.len();
        let mut notes = Vec::new();
        if self.pipeline.fuses_pairs(1 + n_other) && opts.run.fusion == Fusion::Stochastic {
            let steps = opts.run.ss_steps.unwrap_or(self.pipeline.config.samplers.sparse_structure.steps);
            if n_other > steps {
                notes.push(format!(
                    "stochastic fusion of {n_other} views in {steps} stage-1 steps: views {} to {} take no step",
                    steps + 2,
                    n_other + 1
                ));
            }
        }
        // Each object's partner in every other view (view 2 first).
        let mut partners: Vec<Vec<Option<ObjectMask>>> = vec![Vec::with_capacity(n_other); objects.len()];
        let mut extra = Vec::with_capacity(n_other);
        for (i, sv) in others.into_iter().enumerate() {
            let (p, n) = match_view(&objects, sv.objects, i + 2)?;
            notes.extend(n);
            for (slot, m) in partners.iter_mut().zip(p) {
                slot.push(m);
            }
            let f = sv.frame;
            extra.push(ExtraFrame { frame: f, to_anchor: sv.t_c1_c2, depth: depth_view(f, opts), plane: support_plane(f, opts) });
        }
        let items: Vec<(ObjectMask, Vec<Option<ObjectMask>>)> = objects.into_iter().zip(partners).collect();
        let (depth1, plane1) = (depth_view(frame, opts), support_plane(frame, opts));
        let total = items.len();
        // What an object's note says of a view left out (one other view: the two-view wording).
        let left_out = |k: usize, what: String| {
            if n_other == 1 {
                format!("{what}; reconstructed from view 1 alone")
            } else {
                format!("{what}; view {k} left out")
            }
        };
        // One object from its masks to its result: independent of the others
        // (its seeds are `run.seed + sample`), so objects may run at once.
        let run_one = |index: usize, (o1, mine): (ObjectMask, Vec<Option<ObjectMask>>)| -> Result<(f64, ObjectOutcome)> {
            let t_obj = Instant::now();
            progress(Progress::Object { index, total, label: &o1.label });
            let (label, id) = (o1.label.clone(), o1.id);
            let t = Instant::now();
            let (mut p1, s1) = prepare_frame_objects(frame, vec![o1], size, opts.min_valid_depth_pixels, &opts.prepare, &dev);
            let mut obj_notes = Vec::new();
            let Some(p1) = p1.pop() else {
                return Ok((t.elapsed().as_secs_f64(), ObjectOutcome::Skipped(s1)));
            };
            let anchor = object_view(1, frame, p1.object.label.clone(), p1.view, RigidTransform::identity(), depth1.clone(), plane1)?;
            let mut views = vec![anchor];
            for (i, (x, o)) in extra.iter().zip(mine).enumerate() {
                let k = i + 2;
                let Some(o) = o else {
                    obj_notes.push(left_out(k, format!("no mask in view {k}")));
                    continue;
                };
                let (mut p, s) = prepare_frame_objects(x.frame, vec![o], size, opts.min_valid_depth_pixels, &opts.prepare, &dev);
                match p.pop() {
                    Some(p) => views.push(object_view(k, x.frame, p.object.label.clone(), p.view, x.to_anchor, x.depth.clone(), x.plane)?),
                    None => obj_notes.extend(s.iter().map(|s| left_out(k, format!("view {k} {s}")))),
                }
            }
            let prepare_s = t.elapsed().as_secs_f64();
            // One object's failure (an error in its decoding, meshing or pose
            // fit, even a panic) is reported for that object; the others go on.
            let attempt = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                self.reconstruct_object(&label, id, &views, opts, progress, obj_notes)
            }));
            let outcome = match attempt {
                Ok(Ok(r)) => r,
                Ok(Err(e)) => Err(SkipReason::Preprocessing(format!("error: {}", e.to_string().lines().next().unwrap_or_default()))),
                Err(p) => {
                    let msg = p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()));
                    Err(SkipReason::Preprocessing(format!("internal error: {}", msg.unwrap_or_default())))
                }
            };
            Ok((
                prepare_s,
                match outcome {
                    Ok(r) => {
                        progress(Progress::ObjectDone { label: &label, seconds: t_obj.elapsed().as_secs_f64() });
                        ObjectOutcome::Done(Box::new(r))
                    }
                    Err(reason) => ObjectOutcome::Skipped(vec![MaskSkip { label, reason }]),
                },
            ))
        };
        let outcomes = map_in_flight(items, opts.parallel_objects.get(), run_one, |r| r.is_err())?;
        let (mut skipped, mut results) = (Vec::new(), Vec::new());
        // In object order, whatever order they finished in; an object left
        // unrun follows a fatal error, which is returned first.
        for outcome in outcomes.into_iter().flatten() {
            let (prepare_s, outcome) = outcome?;
            preprocess_seconds += prepare_s;
            match outcome {
                ObjectOutcome::Done(r) => results.push(*r),
                ObjectOutcome::Skipped(s) => skipped.extend(s),
            }
        }
        let (image, pose_representation) = (FrameImage::of(frame), self.pipeline.config.pose.ss_representation);
        Ok(FrameResult { objects: results, skipped, preprocess_seconds, notes, image, pose_representation })
    }

    /// All samples of one object. The outer error is fatal, the inner a skip.
    fn reconstruct_object(
        &self,
        label: &str,
        id: Option<u32>,
        views: &[ObjView],
        opts: &InferSettings,
        progress: &(dyn Fn(Progress) + Sync),
        mut notes: Vec<String>,
    ) -> Result<std::result::Result<ObjectResult, SkipReason>> {
        let ctx = ObjectContext::new(views);
        let mut tally = SampleTally::default();
        let mut last_err = None;
        for s in 0..opts.samples {
            let seed = opts.run.seed.wrapping_add(s as u64);
            progress(Progress::Sample { index: s, total: opts.samples, seed });
            let (rec, fitted) = match self.run_sample(&ctx, seed, opts, progress) {
                Ok(r) => r,
                Err(e) => {
                    // candle may append a backtrace; the first line says what failed.
                    let e = e.to_string().lines().next().unwrap_or_default().to_string();
                    notes.push(format!("seed {seed}: {e}"));
                    last_err = Some(e);
                    continue;
                }
            };
            add_timings(&mut tally.timings, &rec.timings);
            progress(Progress::Decimating);
            let t = Instant::now();
            let faces_decoded = rec.mesh.as_ref().map_or(0, |m| m.faces.len());
            let mesh = finish_mesh(rec.mesh, rec.gaussians.as_ref(), fitted.as_ref(), &ctx, opts);
            tally.post_s += t.elapsed().as_secs_f64();

            progress(Progress::Selecting);
            let t = Instant::now();
            let first = tally.candidates.len();
            let mine = sample_candidates(seed, mesh.as_ref(), rec.gaussians.as_ref(), &rec.pose, fitted.as_ref(), &ctx, opts);
            tally.candidates.extend(mine);
            let scores: Vec<CandidateScore> = tally.candidates.iter().map(|c| c.score.clone()).collect();
            // This sample's own best, for the spread.
            let mine = select_best(opts.select, &scores[first..]).map(|i| first + i).unwrap_or(first);
            tally.per_sample_best.push(pose_to_similarity(&tally.candidates[mine].pose_camera));
            let best = select_best(opts.select, &scores).unwrap_or(0);
            if best >= first || tally.kept.is_none() {
                tally.kept = Some(Kept {
                    per_token: rec.pose.per_token.clone(),
                    view_tokens: rec.pose.view_tokens,
                    coords: rec.coords.len(),
                    faces_decoded,
                    mesh,
                    gaussians: rec.gaussians,
                    metadata: rec.metadata,
                    shape_fit: fitted.map(|f| f.report),
                });
            }
            tally.select_s += t.elapsed().as_secs_f64();
        }
        let Some(kept) = tally.kept.take() else {
            return Ok(Err(SkipReason::Preprocessing(format!("model: {}", last_err.unwrap_or_default()))));
        };
        object_result(label, id, ctx, opts, tally, kept, notes).map(Ok)
    }

    /// One sample's model run (with the shape fit between the stages when it is on).
    fn run_sample(
        &self,
        ctx: &ObjectContext,
        seed: u64,
        opts: &InferSettings,
        progress: &(dyn Fn(Progress) + Sync),
    ) -> Result<(ObjectReconstruction, Option<Fitted>)> {
        let mut run = RunOptions { seed, ..opts.run.clone() };
        // The fitted mesh takes its colours from the measured ones: the decoder's mesh is not needed.
        if opts.shape_fit != ShapeFit::None && opts.mesh_from == MeshFrom::Fitted && run.decode_gaussians {
            run.decode_mesh = false;
        }
        let mut fitted: Option<Fitted> = None;
        let on_stage = |st| progress(Progress::Stage(st));
        let rec = match opts.shape_fit {
            ShapeFit::None => self.pipeline.run_observed(&ctx.inputs, &run, &on_stage),
            ShapeFit::Depth | ShapeFit::DepthHull => {
                let mut hook = |pose: &PredictedPose, coords: &[[i32; 3]], r: usize| {
                    let (f, c) = fit_shape(pose, coords, r, ctx.views, &ctx.view_points, &ctx.supports, opts)?;
                    fitted = Some(f);
                    Ok(c)
                };
                self.pipeline.run_guided(&ctx.inputs, &run, &on_stage, Some(&mut hook))
            }
        }?;
        Ok((rec, fitted))
    }
}

/// What every sample of one object shares: the model's inputs and the
/// observations its candidates are scored against.
struct ObjectContext<'v, 'a> {
    views: &'v [ObjView<'a>],
    inputs: ObjectInputs,
    view_points: Vec<ViewPoints>,
    supports: Vec<Option<Plane>>,
    /// Observed points (anchor frame) of every view, view 1 first, and their colours.
    observed_points: Vec<[f32; 3]>,
    observed_colors: Vec<[u8; 3]>,
}

impl<'v, 'a> ObjectContext<'v, 'a> {
    fn new(views: &'v [ObjView<'a>]) -> Self {
        let inputs = ObjectInputs {
            views: views
                .iter()
                .map(|v| ViewInput {
                    pixels: v.prepared.pixel_values.clone(),
                    pointmap: v.prepared.pointmap.clone(),
                    mask: v.prepared.mask.clone(),
                })
                .collect(),
        };
        let view_points: Vec<ViewPoints> = views.iter().map(|v| v.points.clone()).collect();
        let supports: Vec<Option<Plane>> = views.iter().map(|v| v.support).collect();
        let (mut observed_points, mut observed_colors) = (Vec::new(), Vec::new());
        for v in views {
            let (p, c) = observed_in_anchor(v);
            observed_points.extend(p);
            observed_colors.extend(c);
        }
        ObjectContext { views, inputs, view_points, supports, observed_points, observed_colors }
    }
}

/// What the samples of one object add up to.
#[derive(Default)]
struct SampleTally {
    /// Model stages, summed over samples.
    timings: StageTimings,
    post_s: f64,
    select_s: f64,
    candidates: Vec<Candidate>,
    /// Each sample's own best pose, for the spread.
    per_sample_best: Vec<Similarity>,
    /// The best sample's outputs so far.
    kept: Option<Kept>,
}

/// A sample's output mesh: the fitted surface or the decoder's, floaters
/// dropped, smoothed, rested on the support planes (with the shape fit) and
/// held to the face budget.
fn finish_mesh(
    decoded: Option<Mesh>,
    gaussians: Option<&Gaussians>,
    fitted: Option<&Fitted>,
    ctx: &ObjectContext,
    opts: &InferSettings,
) -> Option<Mesh> {
    let mesh = match (opts.mesh_from, fitted) {
        (MeshFrom::Fitted, Some(f)) => {
            Some(fitted_surface(f, (&ctx.observed_points, &ctx.observed_colors), gaussians, opts.floater_area_fraction))
        }
        _ => decoded.map(|m| drop_floaters(m, opts.floater_area_fraction)),
    };
    mesh.map(|m| {
        let mut m = taubin_smooth(&m, opts.smooth_iterations);
        if let Some(f) = fitted {
            rest_on_supports(&mut m, &f.anchor, f.stretch, &ctx.view_points, &ctx.supports, opts.shape_fit_options.margin_m);
        }
        m
    })
    .map(|m| match opts.max_faces {
        Some(n) if m.faces.len() > n => decimate(&m, n),
        _ => m,
    })
}

/// One sample's candidate poses, scored: with the shape fit its one pose
/// (refined before the fit and kept as the fit saw it), else every view's
/// token, refined against the sample's surface when the alignment refines.
fn sample_candidates(
    seed: u64,
    mesh: Option<&Mesh>,
    gaussians: Option<&Gaussians>,
    pose: &PredictedPose,
    fitted: Option<&Fitted>,
    ctx: &ObjectContext,
    opts: &InferSettings,
) -> Vec<Candidate> {
    let (views, view_points) = (ctx.views, &ctx.view_points);
    // The mesh; without one (decode_mesh off) the Gaussian centres.
    let surface = match (mesh, gaussians) {
        (Some(m), _) if !m.faces.is_empty() => Surface::from_mesh(m, opts.align.surface_samples, opts.align.seed).ok(),
        (_, Some(g)) if !g.is_empty() => Surface::from_points(&g.positions).ok(),
        _ => None,
    };
    let mut candidates = Vec::new();
    if let Some(f) = fitted {
        let stretched = match (mesh, f.stretch != [1.0; 3]) {
            (Some(m), true) => Surface::from_mesh(&stretch_mesh(m, f.stretch), opts.align.surface_samples, opts.align.seed).ok(),
            _ => None,
        };
        let score = match stretched.as_ref().or(surface.as_ref()) {
            Some(sf) => score_candidate(sf, &f.anchor, f.view, view_points, &opts.align),
            None => CandidateScore { own_view: f.view, per_view_m: vec![f64::NAN; views.len()] },
        };
        candidates.push(Candidate { seed, view: f.view + 1, pose_camera: similarity_to_pose(&f.anchor), stretch: f.stretch, score });
    }
    // The views with a pose token of their own (with pair fusion the anchor alone).
    for (k, v) in views.iter().enumerate().take(pose.view_tokens).filter(|_| fitted.is_none()) {
        let pose_n = pose.per_token[k];
        let own = pose_to_similarity(&pose_to_camera(&pose_n, &v.prepared.normaliser));
        let mut anchor = v.points.to_anchor.compose(&own);
        let mut stretch = [1.0; 3];
        if let (true, Some(sf)) = (opts.align.refine, &surface) {
            let r = refine_pose(sf, &anchor, view_points, &opts.align);
            (anchor, stretch) = (r.pose, r.stretch);
        }
        // A stretched candidate is scored on its stretched mesh.
        let stretched = match (mesh, stretch != [1.0; 3]) {
            (Some(m), true) => Surface::from_mesh(&stretch_mesh(m, stretch), opts.align.surface_samples, opts.align.seed).ok(),
            _ => None,
        };
        let score = match stretched.as_ref().or(surface.as_ref()) {
            Some(sf) => score_candidate(sf, &anchor, k, view_points, &opts.align),
            None => CandidateScore { own_view: k, per_view_m: vec![f64::NAN; views.len()] },
        };
        candidates.push(Candidate { seed, view: k + 1, pose_camera: similarity_to_pose(&anchor), stretch, score });
    }
    candidates
}

/// The object's result: the best candidate over all samples, the kept
/// sample's mesh and Gaussians placed in the anchor camera frame.
fn object_result(
    label: &str,
    id: Option<u32>,
    ctx: ObjectContext,
    opts: &InferSettings,
    tally: SampleTally,
    kept: Kept,
    mut notes: Vec<String>,
) -> Result<ObjectResult> {
    let SampleTally { timings, post_s, select_s, candidates, per_sample_best, .. } = tally;
    let views = ctx.views;
    let scores: Vec<CandidateScore> = candidates.iter().map(|c| c.score.clone()).collect();
    let best = select_best(opts.select, &scores).unwrap_or(0);
    let chosen = &candidates[best];
    if chosen.score.per_view_m.iter().all(|x| x.is_nan()) {
        notes.push("no mesh or Gaussians to score the poses against; took the first candidate".to_string());
    }
    let key = opts.select.key(&chosen.score).unwrap_or(f64::NAN);
    let selection = Selection { method: opts.select, candidate: best, seed: chosen.seed, view: chosen.view, score_m: key };
    let anchor = pose_to_similarity(&chosen.pose_camera);
    let (pose_camera, stretch, chosen_view) = (chosen.pose_camera, chosen.stretch, chosen.view);
    let place = crate::math::Similarity32::new(pose_camera.rotation, pose_camera.translation, pose_camera.scale)?;
    let vposes = views
        .iter()
        .enumerate()
        .map(|(k, v)| {
            let n: &Normaliser = &v.prepared.normaliser;
            ViewPose {
                view: v.number,
                frame: v.frame.rgb_path.clone(),
                mask: v.label.clone(),
                normaliser_centre_m: n.centre,
                normaliser_diameter_m: n.diameter,
                observed_points: v.points.points.len(),
                pose_own_token: (k < kept.view_tokens).then(|| pose_to_camera(&kept.per_token[k], n)),
                pose_selected: similarity_to_pose(&v.points.to_anchor.inverse().compose(&anchor)),
            }
        })
        .collect();
    let mut mesh_object = kept.mesh.as_ref().map(|m| stretch_mesh(m, stretch));
    let mut gaussians_object = kept.gaussians.as_ref().map(|g| stretch_gaussians(g, stretch));
    let posthoc_color = match opts.posthoc_color {
        PosthocColor::None => None,
        variant => {
            // A mesh coloured from the measured points already has the photo's colours.
            let measured_colors = opts.mesh_from == MeshFrom::Fitted && kept.shape_fit.is_some();
            let v = &views[0];
            let photo = PhotoView {
                width: v.frame.width,
                height: v.frame.height,
                rgb: &v.frame.rgb,
                mask: &v.prepared.mask_full,
                intrinsics: v.frame.intrinsics,
            };
            let placed = gaussians_object.as_ref().map(|g| place.apply_gaussians(g));
            let (transform, stats) = posthoc_color::calibrate(placed.as_ref(), &anchor, &photo, variant)?;
            let mut applied_to = Vec::new();
            if let Some(tr) = &transform {
                if let Some(g) = gaussians_object.as_mut() {
                    posthoc_color::apply_to_gaussians(g, tr);
                    applied_to.push("gaussians".to_string());
                }
                if let (Some(m), false) = (mesh_object.as_mut(), measured_colors) {
                    posthoc_color::apply_to_mesh(m, tr);
                    applied_to.push("mesh".to_string());
                }
            }
            Some(PosthocColorRecord { variant, transform, stats, applied_to })
        }
    };
    let mesh_camera = mesh_object.as_ref().map(|m| place.apply_mesh(m));
    let (textured, texture_report) = match (&mesh_camera, opts.colour) {
        // A texture that cannot be made (an atlas that does not fit) leaves the vertex colours.
        (Some(m), MeshColour::Texture) if !m.faces.is_empty() => match bake_views(m, views, opts.texture_size) {
            Ok((tm, r)) => (Some(tm), Some(r)),
            Err(e) => {
                notes.push(format!("no texture: {e}; mesh.glb keeps the vertex colours"));
                (None, None)
            }
        },
        _ => (None, None),
    };
    Ok(ObjectResult {
        label: label.to_string(),
        id,
        pose_normalised: kept.per_token[chosen_view - 1],
        pose_camera,
        selection,
        views: vposes,
        uncertainty: pose_spread(&per_sample_best),
        candidates,
        occupied_voxels: kept.coords,
        shape_fit: kept.shape_fit,
        faces_decoded: kept.faces_decoded,
        mesh_camera,
        gaussians_camera: gaussians_object.as_ref().map(|g| place.apply_gaussians(g)),
        mesh_object,
        gaussians_object,
        observed_points: ctx.observed_points,
        observed_colors: ctx.observed_colors,
        timings,
        postprocess_seconds: post_s + texture_report.map_or(0.0, |r| r.seconds),
        select_seconds: select_s,
        metadata: kept.metadata,
        samples: opts.samples,
        notes,
        posthoc_color,
        textured,
        texture_report,
    })
}

fn ser_pose<S: serde::Serializer>(p: &Pose, s: S) -> std::result::Result<S::Ok, S::Error> {
    PoseJson::from(p).serialize(s)
}

fn ser_opt_pose<S: serde::Serializer>(p: &Option<Pose>, s: S) -> std::result::Result<S::Ok, S::Error> {
    p.as_ref().map(PoseJson::from).serialize(s)
}

/// A [`Pose`] as written to JSON: `x' = scale · rotation · x + translation`.
#[derive(Debug, Serialize)]
pub struct PoseJson {
    /// Rotation matrix, row-major.
    pub rotation: [[f32; 3]; 3],
    /// Translation, in the units of the target frame.
    pub translation: [f32; 3],
    /// Uniform scale.
    pub scale: f32,
}

impl From<&Pose> for PoseJson {
    fn from(p: &Pose) -> Self {
        PoseJson { rotation: p.rotation, translation: p.translation, scale: p.scale }
    }
}
