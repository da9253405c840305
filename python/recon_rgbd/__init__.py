"""recon_rgbd (the `recon-rgbd` distribution): RGB-D frames + object masks -> per-object
textured meshes, 3D Gaussians and metric 6-DoF poses (RecGen re-implemented in Rust), from Python.

    import recon_rgbd
    engine = recon_rgbd.Engine()                 # the embedded recgen-nano, loaded once
    f = recon_rgbd.load_frame("data/sample/000001-color.png")
    masks = ...                                  # H×W instance ids, or a list of boolean masks
    for o in engine.reconstruct(f["rgb"], f["depth"], f["K"], masks, seed=42):
        print(o.label, o.pose, o.scale, o.mesh.vertices.shape)

`recon_rgbd.Client(url)` is an `Engine` on a `recon serve` over HTTP: the same `reconstruct`
call, the same objects. `recon_rgbd.ray` runs whole datasets on Ray. Errors are
`recon_rgbd.ReconError` (subclasses `InputError`, `WeightsError`, `ConfigError`) carrying the
CLI's messages. `python -m recon_rgbd infer|scene|serve|synth|eval|weights …` runs the `recon`
CLI's commands from the wheel; `recon_rgbd.info()` says what this build is and runs on.
"""

from ._recon import (
    OUTPUT_MARKER,
    STAGE_COLUMNS,
    ConfigError,
    DefaultModelWarning,
    Engine,
    Gaussians,
    InputError,
    Mesh,
    Object,
    ReconError,
    WeightsError,
    __version__,
    audit_depth,
    dataset_frames,
    eval,
    infer_defaults,
    info,
    keep_freed_memory,
    load_frame,
    load_masks,
    scene,
    synth,
)
from .client import Client, Job

__all__ = [
    "Engine",
    "Client",
    "Job",
    "Object",
    "Mesh",
    "Gaussians",
    "ReconError",
    "InputError",
    "WeightsError",
    "ConfigError",
    "DefaultModelWarning",
    "load_frame",
    "load_masks",
    "scene",
    "synth",
    "eval",
    "infer_defaults",
    "info",
    "audit_depth",
    "dataset_frames",
    "keep_freed_memory",
    "OUTPUT_MARKER",
    "STAGE_COLUMNS",
    "__version__",
]
