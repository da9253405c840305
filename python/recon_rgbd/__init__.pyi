"""recon_rgbd (distribution `recon-rgbd`): RGB-D frames + object masks -> posed meshes, 3D Gaussians and metric poses."""

from os import PathLike
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, PathLike]

__version__: str
OUTPUT_MARKER: str
"""Index file written last into every `recon infer` output folder (`recon-output.json`)."""
STAGE_COLUMNS: List[str]
"""Keys of `Object.stage_seconds`: the columns of `recon infer`'s timing table."""

class ReconError(Exception):
    """Base class of every error recon raises; the message is the CLI's."""

class InputError(ReconError):
    """Bad input: a file, an array, a mask or a dataset is not what recon expects."""

class WeightsError(ReconError):
    """The model's weights could not be found, read or matched to the architecture."""

class ConfigError(ReconError):
    """An option or a configuration field is missing or out of range."""

class DefaultModelWarning(UserWarning):
    """Given once per process by the first `Engine()` without `weights`: the embedded
    recgen-nano (trained on recon's synthetic scenes only) answers, not RecGen's released
    weights (`Engine.from_pretrained("TRI-ML/RecGen")` after `python -m recon_rgbd weights
    fetch recgen`)."""

class Mesh:
    """A mesh in the camera frame of view 1 (OpenCV: x right, y down, z forward), metres."""

    vertices: npt.NDArray[np.float32]
    """N×3 float32."""
    faces: npt.NDArray[np.int32]
    """M×3 int32 vertex indices."""
    attributes: Optional[npt.NDArray[np.float32]]
    """N×6 float32 in [0, 1]: RGB, then a normal-map triple (TRELLIS's channels)."""
    @property
    def colors(self) -> Optional[npt.NDArray[np.float32]]:
        """N×3 float32 RGB in [0, 1] (a view of `attributes`)."""
    def __init__(
        self, vertices: npt.ArrayLike, faces: npt.ArrayLike, attributes: Optional[npt.ArrayLike] = None
    ) -> None:
        """A mesh from arrays: N×3 float32 vertices, M×3 int faces (checked against N),
        optional N×6 float32 attributes."""

class Gaussians:
    """3D Gaussians in the camera frame (metres)."""

    means: npt.NDArray[np.float32]
    """N×3 centres."""
    scales: npt.NDArray[np.float32]
    """N×3 standard deviations along the local axes."""
    rotations: npt.NDArray[np.float32]
    """N×4 unit quaternions (w, x, y, z)."""
    opacities: npt.NDArray[np.float32]
    """N opacities in (0, 1)."""
    colors: npt.NDArray[np.float32]
    """N×3 RGB in [0, 1]."""
    dc: npt.NDArray[np.float32]
    """N×3 SH degree-0 coefficients (colors = 0.28209479·dc + 0.5)."""
    def __init__(
        self,
        means: npt.ArrayLike,
        scales: npt.ArrayLike,
        rotations: npt.ArrayLike,
        opacities: npt.ArrayLike,
        dc: npt.ArrayLike,
    ) -> None:
        """Gaussians from float32 arrays (one row per Gaussian), checked."""
    def __len__(self) -> int: ...

class Object:
    """One reconstructed object."""

    id: Optional[int]
    """Instance id in the mask image; None for a boolean mask."""
    label: str
    """`id N`, or `mask N` for the N-th boolean mask."""
    pose: npt.NDArray[np.float64]
    """4×4 rigid camera-from-object transform (metres). With `scale`:
    x_camera = R · (scale · x_object) + t; object frame = the decoder's [-0.5, 0.5]³."""
    scale: float
    """Object scale (metres per object-frame unit)."""
    score: float
    """Selection score (metres): trimmed mean distance of the observed points to the posed
    mesh, plus the free-space term with pose_fit="depth"; lower is better."""
    spread: Optional[Dict[str, float]]
    """With samples > 1: translation_sd_mm, rotation_sd_deg, scale_sd_rel, samples."""
    stage_seconds: Dict[str, float]
    """Seconds per stage (keys: STAGE_COLUMNS)."""
    mesh: Optional[Mesh]
    gaussians: Optional[Gaussians]
    details: Dict[str, Any]
    """What pose.json holds besides the pose: selection, views, candidates, run, notes."""
    raw_mesh: Optional[Mesh]
    """The mesh in the object frame (RecGen's `raw_mesh`): the decoder's canonical
    [-0.5, 0.5]³, z up (with the shape fit, that cube re-fitted around the fitted solid; with
    pose_fit="depth-stretch", stretched per axis); `mesh` is this mesh placed by the pose."""
    raw_gaussians: Optional[Gaussians]
    """The Gaussians in the object frame; `gaussians` are these placed by the pose."""
    pose_matrix: Optional[npt.NDArray[np.float64]]
    """RecGen's `pose_matrix`: 4×4 [s·R | t], object frame → the anchor view's normalised
    point-map frame (not metres: `inv(cam2ncam) @ pose_matrix` is the camera-frame map)."""
    pose_quat: Optional[npt.NDArray[np.float64]]
    """RecGen's `pose_quat`: [tx, ty, tz, qx, qy, qz, qw] of `pose_matrix` (scipy order, w last)."""
    parsed_pose: Optional[Dict[str, Any]]
    """RecGen's `pose` dict: quaternion [x, y, z, w], translation, scale, rotation_matrix
    (normalised frame)."""
    cam2ncam: Optional[npt.NDArray[np.float64]]
    """RecGen's `cam2ncam`: 4×4 anchor camera (metres) → normalised frame."""
    pose_representation: Optional[str]
    """RecGen's `pose_representation`: the stage-1 pose layout ("6d_translation_scale")."""
    rgb: Optional[npt.NDArray[np.uint8]]
    """The anchor view's H×W×3 image (shared by the frame's objects)."""
    intrinsics: Optional[npt.NDArray[np.float64]]
    """The anchor view's 3×3 K.
    The RecGen fields above are None for objects of a `recon_rgbd.Client` answer."""
    posthoc_color: Optional[Dict[str, Any]]
    """The colour calibration (`posthoc_color=`): "variant", "transform" (None when gated
    out), "stats" (overlap_px, iou, reason or l1_before/l1_after), "applied_to"; as
    posthoc_color.json. None when not asked for."""
    def to_glb(self, path: _Path) -> None:
        """Write the mesh as `recon infer` writes `<object>/mesh.glb`."""
    def to_ply(self, path: _Path) -> None:
        """Write the mesh as `recon infer` writes `<object>/mesh.ply`."""
    def gaussians_to_ply(self, path: _Path) -> None:
        """Write the Gaussians as `recon infer` writes `<object>/gaussians.ply`."""
    def save(self, output_dir: _Path, *, save_splat: bool = True) -> None:
        """RecGen's `RecGenResult.save`: mesh.obj (object frame), posed_mesh.obj (camera
        frame), gaussian.ply and posed_gaussian.ply (with save_splat), overlay.png and
        metadata.json (and posthoc_color.json after a calibration) into `output_dir`
        (created if needed): the files `recon infer --recgen-files` writes beside pose.json."""
    def to_trimesh(self) -> Any:
        """The mesh as a `trimesh.Trimesh` with RGBA vertex colours (needs trimesh)."""

class Engine:
    """A loaded model, reused across objects, frames and threads (the GIL is released while
    it computes).

    weights: None = the embedded trained recgen-nano; "random" = recgen-tiny with random
    weights (plumbing only); a folder of `<module>.safetensors`; or a manifest name
    ("recgen") resolved in the Hugging Face cache after `recon weights fetch`.
    config: the architecture file when the weights do not imply it.
    dtype: "auto" (bf16 for models whose flow transformers are >= 512 channels wide, i.e. recgen-large; f32 for smaller ones such as the default recgen-nano), "f32", "bf16" or "f16": the inference kernels' precision.
    threads: worker threads of this engine (default: all cores, shared pool).
    seed: seeds random weights.
    """

    random_weights: bool
    model: str
    """Where the model comes from (`Default` = the embedded recgen-nano, `Dir`, `Manifest`
    with the `hf:` or manifest name, `Random`); each object's `details["run"]` names the
    architecture (e.g. `recgen-nano`) and the weights files."""
    def __init__(
        self,
        weights: Optional[_Path] = None,
        config: Optional[_Path] = None,
        dtype: str = "auto",
        threads: Optional[int] = None,
        seed: int = 42,
    ) -> None: ...
    @classmethod
    def from_pretrained(
        cls,
        repo: str,
        revision: Optional[str] = None,
        *,
        manifest: Optional[_Path] = None,
        config: Optional[_Path] = None,
        dtype: str = "auto",
        threads: Optional[int] = None,
    ) -> "Engine":
        """RecGen's released weights from a Hugging Face repository (e.g. "TRI-ML/RecGen"):
        `Engine(weights="hf:REPO[@REVISION]")`. Files the Hugging Face cache (HF_HUB_CACHE,
        else HF_HOME/hub) lacks are downloaded into it through hf-hub with a progress bar,
        unless HF_HUB_OFFLINE is set; HF_TOKEN for gated repos. Every file's SHA-256 is
        checked against the manifest's pins. `revision`: a commit, branch or tag (default:
        the manifest's pinned commit for TRI-ML/RecGen, else `main`). `manifest`: a manifest
        file for this repo (`python -m recon_rgbd weights manifest recgen --pin DIR` writes
        one for a fine-tune or a mirror) whose pins and tensor lists are used instead of
        recon's own."""
    def reconstruct(
        self,
        rgb: Any,
        depth: Any,
        K: npt.ArrayLike,
        masks: Union[npt.NDArray[np.integer], Sequence[npt.NDArray[np.bool_]]],
        *,
        depth_scale: Optional[float] = None,
        view2: Optional[Dict[str, Any]] = None,
        progress: Optional[Callable[[Dict[str, Any]], None]] = None,
        seed: int = 42,
        samples: int = 1,
        select: str = "cross",
        pose_fit: str = "depth",
        shape_fit: str = "depth",
        mesh_from: str = "fitted",
        steps: Optional[int] = None,
        cfg: Optional[float] = None,
        max_faces: int = 200000,
        min_component_area: float = 0.02,
        smooth: int = 0,
        parallel_objects: int = 1,
        max_objects: int = 256,
        quantile_drop_threshold: float = 0.05,
        clamp_range: Tuple[float, float] = (-2.0, 3.0),
        mask_erosion_enabled: bool = True,
        mask_erosion_kernel_size: int = 5,
        mask_erosion_iterations: int = 1,
        use_pointmap: bool = True,
        fusion: str = "multidiffusion",
        slat_fusion: str = "none",
        posthoc_color: str = "none",
        colour: str = "vertex",
        texture_size: int = 1024,
        views: Optional[Sequence[Dict[str, Any]]] = None,
    ) -> List[Object]:
        """Reconstruct every masked object of one RGB-D frame.

        rgb: H×W×3 uint8. depth: H×W uint16 (× depth_scale metres, default 0.001) or
        float32/float64 metres (0 or NaN = no reading). K: 3×3 intrinsics. masks: an H×W
        instance-id image (0 = background) or a list of H×W boolean masks.
        Arrays of any layout, PIL images, torch CPU tensors and DLPack producers are read, in
        dtypes that convert without loss (integer colour in 0..255, float colour in [0, 1],
        float16 depth, other integer depth with depth_scale); others raise InputError.
        view2: {"rgb", "depth", "K", "masks", "T_c1_c2"[, "depth_scale"]} for two-view
        conditioning; T_c1_c2 maps camera 2 to camera 1 (x1 = R·x2 + t, metres).
        views: more views besides the anchor, each such a dict with "T_c1_ci" (camera i to
            camera 1); they follow view2 (view 2, 3, …; at most 16 in all). More views than
            the model takes at once run as fused (anchor, view i) pairs: fusion
            "multidiffusion" (mean of the pairs' velocities at every step) or "stochastic"
            (one pair per step in turn); slat_fusion "none" (stage 2 on the anchor and the
            first other view), "multidiffusion" or "stochastic" (stage 2 fused as well).
        posthoc_color: "none" | "gamma" | "affine" | "gamma_affine": fit a colour transform
            from the rendered Gaussians to the photo and apply it (Object.posthoc_color).
        samples: seeds seed … seed+samples−1, best pose kept, spread reported.
        select: "cross" | "single" | "first". pose_fit: "depth" | "depth-stretch" | "recgen".
        shape_fit: "depth" | "depth-hull" | "none" (the stage-1 occupancy fitted to the depth; see the README).
        mesh_from: with the shape fit, "fitted" (the fitted occupancy's closed, smoothed surface,
            coloured from the observed points) or "decoder" (the stage-2 mesh decoder's surface).
        smooth: Taubin smoothing iterations on the mesh (0: none).
        max_faces: face budget (0 = off). steps / cfg: sampler overrides for both stages.
        parallel_objects: objects reconstructed at once (results do not depend on it).
        max_objects: most objects whose masks pass the checks (the ones the model runs on);
            a frame with more is an InputError naming the count and the limit.
        RecGen's preprocessing, with `recgen_inference.generate`'s names and defaults:
            quantile_drop_threshold (fraction of points dropped at each end when sizing the
            unit cube), clamp_range (of the normalised point map), mask_erosion_enabled /
            mask_erosion_kernel_size / mask_erosion_iterations (its `mask_erosion_params`),
            use_pointmap (False: the model is conditioned on the image and mask only).
        progress: called with event dicts (object, sample, stage, …) from worker threads.
        The per-frame keywords (seed … use_pointmap) are `recon infer`'s flags with `_`,
        with the CLI's defaults (`infer_defaults()`); an unknown keyword is a ConfigError
        listing them.
        Objects that fail validation are left out (see `reconstruct_files` for the reasons).
        """
    def reconstruct_files(
        self,
        rgbd: _Path,
        masks: Union[_Path, Sequence[_Path]],
        out: Optional[_Path] = None,
        *,
        depth: Optional[_Path] = None,
        intrinsics: Optional[Union[_Path, npt.ArrayLike]] = None,
        depth_scale: Optional[float] = None,
        objects: Optional[Sequence[int]] = None,
        progress: Optional[Callable[[Dict[str, Any]], None]] = None,
        seed: int = 42,
        samples: int = 1,
        select: str = "cross",
        pose_fit: str = "depth",
        shape_fit: str = "depth",
        mesh_from: str = "fitted",
        steps: Optional[int] = None,
        cfg: Optional[float] = None,
        max_faces: int = 200000,
        min_component_area: float = 0.02,
        smooth: int = 0,
        parallel_objects: int = 1,
        max_objects: int = 256,
        quantile_drop_threshold: float = 0.05,
        clamp_range: Tuple[float, float] = (-2.0, 3.0),
        mask_erosion_enabled: bool = True,
        mask_erosion_kernel_size: int = 5,
        mask_erosion_iterations: int = 1,
        use_pointmap: bool = True,
        fusion: str = "multidiffusion",
        slat_fusion: str = "none",
        posthoc_color: str = "none",
        colour: str = "vertex",
        texture_size: int = 1024,
        views: Optional[Sequence[Union[_Path, Dict[str, Any]]]] = None,
    ) -> Dict[str, Any]:
        """`recon infer` on files: the same discovery of depth and intrinsics beside `rgbd`,
        the same masks (one instance-id PNG or several binary masks), the same output folder
        (default `<stem>_recon` beside the image). The defaults are the CLI's (seed 42).
        views: the views besides `rgbd` as `recon infer --view` takes them: view files (JSON
        {"rgb", "masks", "T_c1_ci"[, "depth", "intrinsics", "depth_scale"]}, relative paths
        from the file's folder) or such dicts (relative paths from the working folder).
        Returns the summary: objects (pose, score, stage seconds, files), skipped, notes."""

def infer_defaults() -> Dict[str, Any]:
    """The per-frame options of `Engine.reconstruct`, `Engine.reconstruct_files` and `eval`
    (`recon infer`'s flags with `_`) and their defaults, from the library."""

def load_frame(
    path: _Path,
    *,
    depth: Optional[_Path] = None,
    intrinsics: Optional[Union[_Path, npt.ArrayLike]] = None,
    depth_scale: Optional[float] = None,
) -> Dict[str, Any]:
    """A frame as `recon infer --rgbd` finds it (YCB-Video, BOP, LINEMOD, generic layouts):
    {"rgb": H×W×3 uint8, "depth": H×W float32 metres, "K": 3×3, "rgb_path", "depth_path",
    "intrinsics_source", "depth_scale"}."""

def load_masks(paths: Union[_Path, Sequence[_Path]], objects: Optional[Sequence[int]] = None) -> Dict[str, Any]:
    """Masks as `recon infer --masks` reads them (one instance-id PNG, `objects` selecting
    ids, or several binary mask files): {"objects": [{"label", "id", "mask": H×W bool}],
    "skipped": [(label, reason)]}."""

def scene(
    objects: Union[_Path, Sequence[Object]],
    frame: Optional[Union[_Path, Dict[str, Any]]] = None,
    out: Optional[_Path] = None,
    *,
    view: Optional[int] = None,
    depth: Optional[_Path] = None,
    depth_scale: Optional[float] = None,
    materials: Optional[_Path] = None,
    variations: Optional[int] = None,
    spec: Optional[Union[_Path, Dict[str, Any]]] = None,
    plane_threshold_mm: float = 10.0,
    collision: str = "convex",
    vhacd_resolution: int = 64,
    vhacd_concavity: float = 0.01,
    vhacd_max_hulls: int = 16,
    primitive_volume_tolerance: float = 0.05,
    settle_time: float = 5.0,
    max_corrective_velocity: float = 0.05,
    flag_mm: float = 10.0,
    flag_deg: float = 10.0,
    seed: int = 0,
    colour: str = "texture",
    texture_size: int = 1024,
) -> Dict[str, Any]:
    """`recon scene`: settle the objects on the support plane seen in the frame's depth and
    export a simulator-ready scene (URDF, MJCF, USD, GLB, scene.json) into `out`.

    objects: the list `Engine.reconstruct` returned (then `frame` is required: the colour
    image path, its depth and intrinsics found beside it, or a dict with "rgb", "depth",
    "K" as `load_frame` returns; objects without a mesh are left out, listed in "notes"), or
    a `recon infer` output folder (`frame` defaults to the image its pose.json records), a
    scene.json, or a BOP scene folder (`view`: the image id). The meshes of in-memory objects
    go through a temporary folder; scene.input.json names them `<in memory: objects[i] label>`.
    In-memory objects give the same scene as their `recon infer` folder.

    The options are `recon scene`'s flags: collision "convex" (VHACD: vhacd_resolution,
    vhacd_concavity, vhacd_max_hulls) | "hull" | "primitive" (primitive_volume_tolerance);
    settle_time (s of simulated settling; objects still moving then are reported, not at
    rest), max_corrective_velocity (m/s), flag_mm / flag_deg (objects moved or turned more
    are flagged), materials (a material table JSON), seed (plane fit and decomposition).

    Returns {"out", "files" (paths relative to out), "objects" (per object: name, category,
    material, "physics" (mass_kg, com, inertia, treatment), friction, restitution,
    collision, start_pose, settled_pose, displacement_mm, rotation_deg, flagged, …), "settle" {"at_rest", "simulated_s", "steps", "depenetration_s"},
    "support_plane", "plane_check" (BOP), "timings", "notes"}.

    variations=N: N re-arranged, settled variants instead (`recon scene --variations N
    --seed S --spec`): `out/variant_NNNN/` folders and manifest.json; spec is a spec file or
    a dict of the same JSON (passed to recon unchanged; default: the built-in spec). Returns
    {"out", "manifest_file", "manifest" (kept, requested, variants, …), "seconds", "notes"}.
    """

def synth(
    out: _Path,
    *,
    scenes: int = 10,
    views: int = 1,
    seed: int = 0,
    sensor: Optional[_Path] = None,
    width: int = 640,
    height: int = 480,
    parts: bool = False,
) -> Dict[str, Any]:
    """`recon synth`: a BOP-format dataset of occluded tabletop scenes; returns its summary."""

def eval(
    dataset: _Path,
    *,
    predictions: Optional[_Path] = None,
    method: Optional[str] = None,
    engine: Optional[Engine] = None,
    out: Optional[_Path] = None,
    shape: str = "hull",
    f1_tau: float = 0.05,
    scenes: Optional[Sequence[str]] = None,
    occlusion: Optional[Sequence[float]] = None,
    surface_samples: int = 10_000,
    surface_seed: int = 0,
    all_frames: bool = False,
    two_view: bool = False,
    views: Optional[int] = None,
    weights: Optional[_Path] = None,
    config: Optional[_Path] = None,
    dtype: Optional[str] = None,
    threads: Optional[int] = None,
    seed: int = 42,
    samples: int = 1,
    select: str = "cross",
    pose_fit: str = "depth",
    shape_fit: str = "depth",
    mesh_from: str = "fitted",
    steps: Optional[int] = None,
    cfg: Optional[float] = None,
    max_faces: int = 200000,
    min_component_area: float = 0.02,
    smooth: int = 0,
    parallel_objects: int = 1,
    max_objects: int = 256,
    quantile_drop_threshold: float = 0.05,
    clamp_range: Tuple[float, float] = (-2.0, 3.0),
    mask_erosion_enabled: bool = True,
    mask_erosion_kernel_size: int = 5,
    mask_erosion_iterations: int = 1,
    use_pointmap: bool = True,
    fusion: str = "multidiffusion",
    slat_fusion: str = "none",
    posthoc_color: str = "none",
    colour: str = "vertex",
    texture_size: int = 1024,
) -> Dict[str, Any]:
    """`recon eval`: score a predictions file, or run method "observed" or "recgen" over the
    dataset first (then `out` is required: predictions.json, meshes, report files).

    Every flag of `recon eval` is a keyword here with the CLI's default: shape, f1_tau,
    scenes (`["48"]` matches 000048), occlusion ((LO, HI) percent), surface_samples,
    surface_seed, all_frames, two_view, views (N views: each frame with the next N−1 of
    its scene); and for method="recgen" the model flags: either
    `engine` (a loaded Engine), or weights / config / dtype / threads, loaded as
    `recon eval --method recgen` loads them (seed also seeds weights="random"); then the
    per-frame flags of `recon infer` with their defaults (`infer_defaults()`): seed, samples,
    select, pose_fit, shape_fit, mesh_from, steps, cfg, max_faces, min_component_area, smooth,
    parallel_objects, max_objects, and RecGen's preprocessing (quantile_drop_threshold,
    clamp_range, mask_erosion_enabled, mask_erosion_kernel_size, mask_erosion_iterations,
    use_pointmap), fusion, slat_fusion. Returns report.json's dict."""

def audit_depth(
    dataset: _Path,
    *,
    sensor: Optional[_Path] = None,
    out: Optional[_Path] = None,
    max_pixels: int = 3000,
    frames: Optional[int] = None,
    alpha: float = 0.01,
    max_findings: int = 8,
    robust: bool = True,
    interactions: bool = True,
    max_folds: int = 20,
    seed: int = 0,
) -> Dict[str, Any]:
    """`recon audit depth`: measured vs simulated depth; returns the report (and writes the
    CLI's files when `out` is given)."""

def info() -> Dict[str, Any]:
    """This build and the machine it runs on: `version`, `commit` (git commit the extension
    was built from, or None), `features`, `profile` ("release" or "dev"), `target`, `cpu`,
    `isa` (the instruction set recon's kernels use, as `recon bench`'s machine line says),
    `bf16_isa`, `supported_isas`, `threads`, `allocator`, `default_model`."""

def keep_freed_memory() -> bool:
    """Keep large freed buffers in the process heap for reuse (glibc's thresholds), for
    every library in the process. recon's own large buffers are already reused by size
    (the extension's allocator, as in the `recon` CLI), so this only concerns other
    libraries; it raises peak memory a little. Process-wide, hence opt-in. False where
    it did not apply."""

def dataset_frames(source: _Path) -> List[Dict[str, Any]]:
    """The frames of a BOP dataset or YCB-Video folder: {"frame": "<scene>/<NNNNNN>", "rgb",
    "masks"} with the masks `recon infer` takes for it."""

class Job:
    """A job queued on a `recon serve` (`Client.submit`)."""

    id: str
    client: Client
    def status(self) -> Dict[str, Any]:
        """The job document: status (queued | running | done | failed | cancelled), stage,
        progress, error, and the result when done."""
    def cancel(self) -> Dict[str, Any]:
        """Cancels the job (a queued one at once, a running one at its next stage boundary);
        a job that has already finished is deleted from the server."""
    def result(
        self, timeout: Optional[float] = None, poll: float = 0.1, progress: Optional[Callable[[Dict[str, Any]], None]] = None
    ) -> List[Object]:
        """Waits for the job and returns its objects as `Engine.reconstruct` does; a failed
        or cancelled job raises ReconError with the server's message."""

class Client:
    """`Engine.reconstruct` on a `recon serve` at `url` over HTTP (docs/serve.md): the same
    arguments, the same objects, so a pipeline switches by one line
    (`engine = recon_rgbd.Client(url)` instead of `recon_rgbd.Engine()`). Pure Python (urllib).

    The objects are built from the job's files: poses, scale, score, spread and meshes
    (vertices, faces, colours) exactly as the engine's; `Mesh.attributes[:, 3:]` (the
    normal-map triple, not in the files) is NaN; Gaussian opacities and scales pass through
    the splat file's logit and log (within float rounding). Errors: the server's 4xx as
    InputError (ConfigError for the `options` part) with `status`, `part` and `field`.
    """

    url: str
    token: Optional[str]
    timeout: float
    def __init__(self, url: str, token: Optional[str] = None, timeout: float = 3600.0) -> None: ...
    def reconstruct(
        self,
        rgb: npt.NDArray[np.uint8],
        depth: npt.NDArray[Any],
        K: npt.ArrayLike,
        masks: Union[npt.NDArray[np.integer], Sequence[npt.NDArray[np.bool_]]],
        *,
        depth_scale: Optional[float] = None,
        view2: Optional[Dict[str, Any]] = None,
        views: Optional[Sequence[Dict[str, Any]]] = None,
        progress: Optional[Callable[[Dict[str, Any]], None]] = None,
        seed: int = 42,
        samples: int = 1,
        select: str = "cross",
        pose_fit: str = "depth",
        shape_fit: str = "depth",
        mesh_from: str = "fitted",
        steps: Optional[int] = None,
        cfg: Optional[float] = None,
        max_faces: int = 200000,
        min_component_area: float = 0.02,
        smooth: int = 0,
        parallel_objects: int = 1,
        max_objects: int = 256,
        quantile_drop_threshold: float = 0.05,
        clamp_range: Tuple[float, float] = (-2.0, 3.0),
        mask_erosion_enabled: bool = True,
        mask_erosion_kernel_size: int = 5,
        mask_erosion_iterations: int = 1,
        use_pointmap: bool = True,
        fusion: str = "multidiffusion",
        slat_fusion: str = "none",
        posthoc_color: str = "none",
        colour: str = "vertex",
        texture_size: int = 1024,
    ) -> List[Object]:
        """`Engine.reconstruct` on the server (POST /v1/reconstruct?wait=true). Options not
        given take the server's defaults (its flags), which are the library's unless it was
        started with others. With `progress`, the job is queued and polled instead.
        view2 and views are Engine.reconstruct's (views: dicts with "T_c1_ci", after view2;
        at most 16 views besides the anchor), sent as the parts rgb2 … T_c1_c2, rgb3 … T_c1_c3, …"""
    def submit(
        self,
        rgb: npt.NDArray[np.uint8],
        depth: npt.NDArray[Any],
        K: npt.ArrayLike,
        masks: Union[npt.NDArray[np.integer], Sequence[npt.NDArray[np.bool_]]],
        *,
        depth_scale: Optional[float] = None,
        view2: Optional[Dict[str, Any]] = None,
        views: Optional[Sequence[Dict[str, Any]]] = None,
        **options: Any,
    ) -> Job:
        """Queues the reconstruction (`?wait=false`) and returns its Job at once."""
    def scene(self, job: Union[Job, str], **options: Any) -> Dict[str, Any]:
        """`recon scene` on a finished job with `recon scene`'s options by name; the
        server's answer (object summaries, whether they came to rest, file URLs)."""
    def file(self, url: str) -> bytes:
        """The bytes of a file URL of an answer."""
    def health(self) -> bool:
        """Whether the server answers /health."""
