"""recon over whole datasets on Ray.

`reconstruct_dataset` runs `recon infer` on every frame of a dataset with Ray Data: the
frame list becomes a dataset, and `map_batches` hands frames to a pool of actors, each
holding one loaded `recon_rgbd.Engine`. Every frame gets its own output folder below `out`,
written exactly as `recon infer --out <out>/<frame>` writes it, and a Parquet results
table (`<out>/results.parquet`) holds one row per object (or per failed frame). Finished
frames' rows are also kept per frame (`<out>/results.parts/`), so a job that dies before
the table is written gets it back, stage seconds included, from the rerun.

`synth` splits `recon synth` over Ray tasks by scene; the dataset is byte-identical to a
single-process `recon synth` with the same options.

Ray schedules; recon only says what one frame (or one range of scenes) is.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

from . import _recon

RESULTS = "results.parquet"
"""File name of the results table below `out`."""

PARTS = "results.parts"
"""Folder below `out` with one JSON file of result rows per finished frame
(`results.parts/<frame>.json`), written by the worker right after the frame's folder:
the table is rebuilt from them, stage seconds included, when a job died before writing it."""

STATUS_OK = "ok"
STATUS_FAILED = "failed"
STATUS_SKIPPED_OBJECT = "skipped"

_STAGES = list(_recon.STAGE_COLUMNS)


def _schema():
    import pyarrow as pa

    fields = [
        ("frame", pa.string()),
        ("object", pa.string()),
        ("id", pa.int64()),
        ("status", pa.string()),
        ("error", pa.string()),
        ("pose", pa.list_(pa.float64())),
        ("scale", pa.float64()),
        ("score", pa.float64()),
    ]
    fields += [(f"seconds_{s}", pa.float64()) for s in _STAGES]
    fields += [("frame_seconds", pa.float64()), ("out", pa.string()), ("worker_pid", pa.int64()), ("worker_peak_rss_mb", pa.float64())]
    return pa.schema(fields)


def _row(frame: str, out: str, **kw: Any) -> Dict[str, Any]:
    r: Dict[str, Any] = {name: None for name in _schema().names}
    r.update(frame=frame, out=out)
    r.update(kw)
    return r


def _plain(x: Any) -> Any:
    """A JSON-ready value: paths as text, arrays as lists."""
    if isinstance(x, os.PathLike):
        return str(x)
    if hasattr(x, "tolist"):
        return x.tolist()
    if isinstance(x, (list, tuple)):
        return [_plain(y) for y in x]
    return x


def _views(v: Any, i: int) -> List[Any]:
    """A row's views besides the anchor, as `recon infer --view` takes them: view files
    (JSON; in a CSV cell `;`-separated, or a JSON list) or dicts of the same keys (rgb,
    masks, T_c1_ci, depth, intrinsics, depth_scale), at most `MAX_SECOND_VIEWS`."""
    if isinstance(v, str):
        v = json.loads(v) if v.lstrip().startswith("[") else [p for p in v.split(";") if p.strip()]
    elif isinstance(v, (os.PathLike, Mapping)):
        v = [v]
    elif hasattr(v, "tolist"):
        v = v.tolist()
    views: List[Any] = []
    for k, x in enumerate(v):
        if isinstance(x, (str, os.PathLike)):
            views.append(str(x))
        elif isinstance(x, Mapping):
            views.append({key: _plain(y) for key, y in x.items()})
        else:
            raise _recon.InputError(f"frame table row {i}: views[{k}]: expected a view file or a dict, got {type(x).__name__}")
    if len(views) > _recon.MAX_SECOND_VIEWS:
        raise _recon.InputError(
            f"frame table row {i}: views: {len(views)} views besides the anchor, more than the limit of {_recon.MAX_SECOND_VIEWS}"
        )
    return views


def _normalise(item: Mapping[str, Any], i: int) -> Dict[str, Any]:
    """A frame of a table: `rgb` and `masks` required; `frame`, `depth`, `intrinsics`
    (a 3×3 K, [fx, fy, cx, cy] or a file), `depth_scale` and `views` (views besides the
    anchor: view files or dicts, as `Engine.reconstruct_files(views=)`) optional."""
    if "rgb" not in item or "masks" not in item:
        raise _recon.InputError(f"frame table row {i}: needs `rgb` and `masks` (got {sorted(item)})")
    masks = item["masks"]
    if isinstance(masks, (str, os.PathLike)):
        masks = [str(masks)]
    else:
        masks = [str(m) for m in masks]
    rgb = str(item["rgb"])
    frame = item.get("frame") or Path(rgb).stem
    out: Dict[str, Any] = {"frame": str(frame), "rgb": rgb, "masks": masks}
    for key in ("depth", "intrinsics", "depth_scale"):
        v = item.get(key)
        if v is not None and not (isinstance(v, float) and v != v):
            out[key] = str(v) if isinstance(v, os.PathLike) else v
    if isinstance(out.get("intrinsics"), Sequence) and not isinstance(out["intrinsics"], str):
        out["intrinsics"] = [float(x) for x in _flatten(out["intrinsics"])]
    views = item.get("views")
    if views is not None and not (isinstance(views, float) and views != views):
        out["views"] = _views(views, i)
    return out


def _flatten(x: Any) -> List[Any]:
    if isinstance(x, (list, tuple)) or hasattr(x, "tolist"):
        x = x.tolist() if hasattr(x, "tolist") else x
        return [y for e in x for y in _flatten(e)] if isinstance(x, list) else [x]
    return [x]


def frames_of(source: Any) -> List[Dict[str, Any]]:
    """The frame list of `source`: a BOP dataset (root or split folder) or a YCB-Video
    folder (masks as `recon infer` takes them: BOP `mask_visib` files, YCB-Video label
    maps), or a table of frames (a list of dicts, a pandas DataFrame, or a .parquet /
    .csv / .json(l) file) with columns `rgb`, `masks` and optionally `frame`, `depth`,
    `intrinsics`, `depth_scale`, `views` (the views besides the anchor: a list of view files
    or view dicts, `recon infer --view`'s format; in CSV, `;`-separated view files)."""
    if isinstance(source, (str, os.PathLike)):
        p = Path(source)
        if p.is_file():
            if p.suffix == ".parquet":
                import pyarrow.parquet as pq

                rows = pq.read_table(p).to_pylist()
            elif p.suffix == ".csv":
                import csv

                with open(p, newline="") as f:
                    rows = [dict(r) for r in csv.DictReader(f)]
                for r in rows:
                    if isinstance(r.get("masks"), str) and ";" in r["masks"]:
                        r["masks"] = r["masks"].split(";")
                    if r.get("depth_scale"):
                        r["depth_scale"] = float(r["depth_scale"])
            elif p.suffix in (".json", ".jsonl"):
                text = p.read_text()
                rows = json.loads(text) if p.suffix == ".json" else [json.loads(l) for l in text.splitlines() if l.strip()]
            else:
                raise _recon.InputError(f"{p}: a frame table must be .parquet, .csv, .json or .jsonl")
        else:
            return [dict(f) for f in _recon.dataset_frames(str(p))]
    elif hasattr(source, "to_dict"):
        rows = source.to_dict("records")
    else:
        rows = list(source)
    frames = [_normalise(r, i) for i, r in enumerate(rows)]
    names = [f["frame"] for f in frames]
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise _recon.InputError(f"frame table: frame names must be unique (output folders); repeated: {dup[:5]}")
    return frames


def _complete(out: Path, frame: str) -> bool:
    return (out / frame / _recon.OUTPUT_MARKER).is_file()


def _pose16(rotation: Sequence[Sequence[float]], translation: Sequence[float]) -> List[float]:
    m = [list(map(float, r)) + [float(t)] for r, t in zip(rotation, translation)]
    return [x for r in m for x in r] + [0.0, 0.0, 0.0, 1.0]


def _rows_of_folder(frame: str, folder: Path) -> List[Dict[str, Any]]:
    """Rows of a complete output folder written earlier (pose and score from pose.json)."""
    index = json.loads((folder / _recon.OUTPUT_MARKER).read_text())
    rows = []
    for o in index.get("objects", []):
        pose = json.loads((folder / Path(o["pose"]).parent.name / "pose.json").read_text())
        rows.append(
            _row(
                frame,
                str(folder),
                object=pose["object"],
                id=pose.get("id"),
                status=STATUS_OK,
                pose=_pose16(pose["rotation"], pose["translation_m"]),
                scale=pose["scale_m"],
                score=pose["selection"]["score_m"],
            )
        )
    for s in index.get("skipped", []):
        label, _, reason = s.partition(": skipped: ")
        rows.append(_row(frame, str(folder), object=label, status=STATUS_SKIPPED_OBJECT, error=reason))
    return rows


class _FrameWorker:
    """One Ray actor: one Engine, frames in, result rows out."""

    def __init__(self, out: str, engine: Dict[str, Any], options: Dict[str, Any]):
        self.out = Path(out)
        self.engine = _recon.Engine(**engine)
        self.options = options

    def __call__(self, batch: Dict[str, Any]) -> Dict[str, Any]:
        import numpy as np

        import resource

        rows: List[Dict[str, Any]] = []
        for task in batch["task"]:
            f = json.loads(task)
            frame_rows = reconstruct_frame(self.engine, f, self.out, self.options)
            # Linux reports ru_maxrss in KiB: this actor's peak resident memory so far.
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            for r in frame_rows:
                r.update(worker_pid=os.getpid(), worker_peak_rss_mb=peak)
            if _complete(self.out, f["frame"]):
                _write_part(self.out, f["frame"], frame_rows)
            rows.extend(frame_rows)
        return {"row": np.array([json.dumps(r) for r in rows], dtype=object)}


def _part(out: Path, frame: str) -> Path:
    return out / PARTS / f"{frame}.json"


def _write_part(out: Path, frame: str, rows: List[Dict[str, Any]]) -> None:
    """The frame's rows beside the table, atomically (a reader sees all or nothing)."""
    p = _part(out, frame)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f"{p.name}.{os.getpid()}.partial")
    tmp.write_text(json.dumps(rows))
    os.replace(tmp, p)


def _read_part(out: Path, frame: str) -> Optional[List[Dict[str, Any]]]:
    p = _part(out, frame)
    if not p.is_file():
        return None
    try:
        rows = json.loads(p.read_text())
    except ValueError:
        return None  # unreadable: rebuilt from the table or the folder instead
    names = set(_schema().names)
    return [{k: r.get(k) for k in names} for r in rows] if isinstance(rows, list) else None


def reconstruct_frame(engine: "_recon.Engine", f: Mapping[str, Any], out: Path, options: Mapping[str, Any]) -> List[Dict[str, Any]]:
    """`recon infer` on one frame of a frame list into `out/<frame>`; never raises for the
    frame's own errors: a failure becomes one row with status "failed" and the message."""
    folder = Path(out) / f["frame"]
    t0 = time.perf_counter()
    try:
        s = engine.reconstruct_files(
            f["rgb"],
            f["masks"],
            str(folder),
            depth=f.get("depth"),
            intrinsics=f.get("intrinsics"),
            depth_scale=f.get("depth_scale"),
            views=f.get("views"),
            **options,
        )
    except Exception as e:  # the job goes on; the row carries the message
        return [_row(f["frame"], str(folder), status=STATUS_FAILED, error=f"{type(e).__name__}: {e}", frame_seconds=time.perf_counter() - t0)]
    secs = time.perf_counter() - t0
    rows = []
    for o in s["objects"]:
        r = _row(
            f["frame"],
            str(folder),
            object=o["object"],
            id=o["id"],
            status=STATUS_OK,
            pose=_pose16(o["rotation"], o["translation_m"]),
            scale=o["scale_m"],
            score=o["score_m"],
            frame_seconds=secs,
        )
        for k, v in o["stage_seconds"].items():
            r[f"seconds_{k}"] = v
        rows.append(r)
    for sk in s["skipped"]:
        rows.append(_row(f["frame"], str(folder), object=sk["object"], status=STATUS_SKIPPED_OBJECT, error=sk["reason"], frame_seconds=secs))
    if not rows:
        rows.append(_row(f["frame"], str(folder), status=STATUS_OK, error="no objects", frame_seconds=secs))
    return rows


def _write_table(rows: List[Dict[str, Any]], path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    rows = sorted(rows, key=lambda r: (r["frame"], r["object"] or ""))
    table = pa.Table.from_pylist(rows, schema=_schema())
    tmp = path.with_name(path.name + ".partial")
    pq.write_table(table, tmp)
    os.replace(tmp, path)


def reconstruct_dataset(
    source: Any,
    out: Union[str, os.PathLike],
    *,
    num_workers: int = 2,
    weights: Optional[str] = None,
    config: Optional[str] = None,
    dtype: str = "auto",
    threads_per_worker: int = 1,
    resume: bool = True,
    **infer_options: Any,
) -> Dict[str, Any]:
    """Reconstruct every frame of `source` on the connected Ray cluster (`ray.init()` is
    called with defaults when none is). See the module docs; `infer_options` are those of
    `Engine.reconstruct_files`: `objects` and the per-frame options (`recon_rgbd.infer_defaults()`:
    names and defaults, the CLI's). Returns counts, the results table path and seconds."""
    import ray

    if num_workers < 1:
        raise _recon.ConfigError(f"num_workers: must be at least 1, got {num_workers}")
    t0 = time.perf_counter()
    out = Path(out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    frames = frames_of(source)
    results = out / RESULTS
    previous: Dict[str, List[Dict[str, Any]]] = {}
    if resume and results.is_file():
        import pyarrow.parquet as pq

        for r in pq.read_table(results).to_pylist():
            previous.setdefault(r["frame"], []).append(r)
    done = [f for f in frames if resume and _complete(out, f["frame"])]
    done_names = {f["frame"] for f in done}
    todo = [f for f in frames if f["frame"] not in done_names]
    rows: List[Dict[str, Any]] = []
    for f in done:
        # Finished earlier: its rows from the frame's part file (written with the folder),
        # else an earlier table, else (stage seconds unknown) the folder's pose.json files.
        kept = _read_part(out, f["frame"])
        if kept is None:
            kept = [r for r in previous.get(f["frame"], []) if r["status"] != STATUS_FAILED]
        rows.extend(kept or _rows_of_folder(f["frame"], out / f["frame"]))
    if todo:
        if not ray.is_initialized():
            ray.init()
        engine = {"weights": weights, "config": config, "dtype": dtype, "threads": threads_per_worker}
        # One block per frame, built in the driver: no upstream task has to compete with
        # the actors for CPUs (on a cluster that is all actors, a repartition would wait forever).
        ds = ray.data.from_items([{"task": json.dumps(f)} for f in todo], override_num_blocks=len(todo))
        res = ds.map_batches(
            _FrameWorker,
            fn_constructor_kwargs={"out": str(out), "engine": engine, "options": dict(infer_options)},
            batch_size=1,
            batch_format="numpy",
            compute=ray.data.ActorPoolStrategy(size=min(num_workers, len(todo))),
            num_cpus=threads_per_worker,
        )
        for r in res.iter_rows():
            rows.append(json.loads(r["row"]))
    _write_table(rows, results)
    failed = sorted({r["frame"] for r in rows if r["status"] == STATUS_FAILED})
    return {
        "frames": len(frames),
        "processed": len(todo),
        "resumed": len(done),
        "failed": len(failed),
        "failed_frames": failed,
        "objects": sum(1 for r in rows if r["status"] == STATUS_OK and r["object"] is not None),
        "results": str(results),
        "out": str(out),
        "seconds": time.perf_counter() - t0,
    }


def synth(
    out: Union[str, os.PathLike],
    *,
    num_workers: int = 2,
    scenes_per_task: Optional[int] = None,
    **options: Any,
) -> Dict[str, Any]:
    """`recon synth` split over Ray tasks by scene (`options`: `recon_rgbd.synth`'s keywords,
    scenes, views, seed, sensor, width, height, parts, with the library's defaults). Scene i
    is generated from (seed, i) alone and object ids come from the whole dataset's plan, so
    the result is byte-identical to `recon_rgbd.synth(out, **options)`. Returns the summary."""
    import ray

    if num_workers < 1:
        raise _recon.ConfigError(f"num_workers: must be at least 1, got {num_workers}")
    opts = dict(options)
    if "sensor" in opts and opts["sensor"] is not None:
        opts["sensor"] = str(opts["sensor"])
    out = Path(out).absolute()
    staging = _recon.synth_begin(str(out), **opts)
    # One first object id per scene: the plan also gives the scene count (the option or its default).
    first_ids = _recon.synth_plan(**opts)
    scenes = len(first_ids)
    per = scenes_per_task or max(1, -(-scenes // num_workers))
    if not ray.is_initialized():
        ray.init()

    @ray.remote(num_cpus=1)
    def shard(start: int, end: int) -> Dict[str, Any]:
        from recon_rgbd import _recon as r

        return r.synth_shard(str(staging), start, end, first_ids, **opts)

    refs = [shard.remote(a, min(a + per, scenes)) for a in range(0, scenes, per)]
    shards = ray.get(refs)
    return _recon.synth_finish(str(staging), str(out), shards, **opts)


__all__ = ["reconstruct_dataset", "reconstruct_frame", "frames_of", "synth", "RESULTS", "PARTS"]
