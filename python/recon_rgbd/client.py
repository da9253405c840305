"""`recon_rgbd.Client`: `Engine.reconstruct` against a `recon serve` over HTTP (docs/serve.md).

A pipeline switches between in-process and remote by one line:

    engine = recon_rgbd.Engine()                              # in-process
    engine = recon_rgbd.Client("http://127.0.0.1:8080")       # remote, same calls
    for o in engine.reconstruct(rgb, depth, K, masks, seed=42):
        print(o.label, o.pose, o.scale)

The arrays are sent so that the server computes on exactly the frame `Engine.reconstruct`
builds from them: depth as float32 metres (`.npy`, converted here as the engine converts
uint16 depth), K as JSON numbers (shortest round-trip text), masks as a 16-bit instance-id
PNG or binary mask PNGs. The objects are built from the job's files: pose, score, spread,
stage seconds and details from `pose.json` and the answer, the mesh from `mesh.glb`
(vertices, faces and colours exactly; `attributes[:, 3:]`, the decoder's normal-map
triple, is not in the files and is NaN), the Gaussians from `gaussians.ply` (means,
rotations and SH colours exactly; opacities and scales through the file's logit and log,
within float rounding). `Object.to_ply` and `Object.to_glb` of a remote object write the
bytes the engine's object writes.

Pure Python (urllib, zlib, json, numpy); no dependency beyond the package's.
"""

from __future__ import annotations

import io
import json
import struct
import time
import urllib.error
import urllib.parse
import urllib.request
import uuid
import zlib

import numpy as np

from ._recon import ConfigError, Gaussians, InputError, Mesh, Object, ReconError

__all__ = ["Client", "Job"]


def _png(a: np.ndarray) -> bytes:
    """A PNG of an H×W (grey) or H×W×3 (RGB) uint8 or uint16 array."""
    a = np.ascontiguousarray(a)
    if a.dtype == np.uint8:
        depth = 8
    elif a.dtype == np.uint16:
        depth = 16
        a = a.astype(">u2")
    else:
        raise InputError(f"cannot write {a.dtype} as PNG")
    h, w = a.shape[:2]
    colour = 2 if a.ndim == 3 else 0
    raw = a.reshape(h, -1).view(np.uint8)
    rows = np.hstack([np.zeros((h, 1), np.uint8), raw]).tobytes()

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(rows, 6)) + chunk(b"IEND", b"")


def _npy(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(a, dtype="<f4"))
    return buf.getvalue()


def _depth_metres(depth, depth_scale, name: str) -> np.ndarray:
    """Depth as the engine takes it: uint16 × depth_scale (default 0.001) computed in float64
    and rounded to float32, or float metres as float32."""
    d = np.asarray(depth)
    if d.dtype == np.uint16:
        s = 0.001 if depth_scale is None else float(depth_scale)
        if not (np.isfinite(s) and s > 0):
            raise ConfigError(f"depth_scale: must be positive metres per unit, got {s}")
        return (d.astype(np.float64) * s).astype(np.float32)
    if d.dtype in (np.float32, np.float64):
        if depth_scale is not None:
            raise ConfigError("depth_scale: applies to uint16 depth; float depth is already in metres")
        return d.astype(np.float32)
    raise InputError(f"{name} depth: expected an H×W uint16 (with depth_scale) or float32 metres array")


def _mask_parts(masks, name: str, what: str | None = None):
    """`(parts, labels)`: an instance-id image as one 16-bit PNG part `name`, or a list of
    boolean masks as binary PNG parts named `mask-<i>.png` (labels map them back to
    `mask <i>`). `what` labels errors as the engine does (default: `name`)."""
    what = what or name
    if isinstance(masks, (list, tuple)):
        parts, labels = [], {}
        for i, m in enumerate(masks):
            m = np.asarray(m, dtype=bool)
            if m.ndim != 2:
                raise InputError(f"{what}: mask {i}: expected an H×W boolean array")
            fname = f"mask-{i}.png"
            parts.append((name, fname, _png(m.astype(np.uint8) * 255)))
            labels[fname] = f"mask {i}"
        return parts, labels
    ids = np.asarray(masks)
    if ids.dtype.kind not in "ui":
        raise InputError(f"{what}: expected an H×W integer instance-id image or a list of boolean masks, got dtype kind `{ids.dtype.kind}`")
    if ids.ndim != 2:
        raise InputError(f"{what}: an instance-id image must be H×W")
    if ids.size and (ids.min() < 0 or ids.max() > 65535):
        raise InputError(f"{what}: instance ids must be in 0..=65535 to be sent as a 16-bit PNG")
    return [(name, f"{name}.png", _png(ids.astype(np.uint16)))], {}


def _k_json(K, name: str) -> bytes:
    k = np.asarray(K, dtype=np.float64)
    if k.shape != (3, 3):
        raise InputError(f"{name} K: expected a 3×3 matrix, got shape {k.shape}")
    return json.dumps({"K": k.tolist()}).encode()


def _multipart(parts):
    boundary = "recon-client-" + uuid.uuid4().hex
    out = io.BytesIO()
    for name, filename, data in parts:
        out.write(f"--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"".encode())
        if filename:
            out.write(f"; filename=\"{filename}\"".encode())
        out.write(b"\r\nContent-Type: application/octet-stream\r\n\r\n")
        out.write(data)
        out.write(b"\r\n")
    out.write(f"--{boundary}--\r\n".encode())
    return f"multipart/form-data; boundary={boundary}", out.getvalue()


def _glb_mesh(data: bytes):
    """`recon_rgbd.Mesh` of the first primitive of a GLB recon wrote (positions, indices, COLOR_0)."""
    magic, _, _ = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF":
        raise ReconError("mesh.glb: not a GLB file")
    jlen, _ = struct.unpack_from("<I4s", data, 12)
    doc = json.loads(data[20 : 20 + jlen])
    bin_start = 20 + jlen + 8
    prim = doc["meshes"][0]["primitives"][0]

    def accessor(i, dtype, width):
        acc = doc["accessors"][i]
        view = doc["bufferViews"][acc["bufferView"]]
        off = bin_start + view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        n = acc["count"] * width
        return np.frombuffer(data, dtype=dtype, count=n, offset=off).reshape(-1, width) if width > 1 else np.frombuffer(data, dtype=dtype, count=n, offset=off)

    vertices = accessor(prim["attributes"]["POSITION"], "<f4", 3).astype(np.float32)
    faces = accessor(prim["indices"], "<u4", 1).reshape(-1, 3).astype(np.int32)
    attributes = None
    if "COLOR_0" in prim["attributes"]:
        colours = accessor(prim["attributes"]["COLOR_0"], "<f4", 3)
        attributes = np.full((len(vertices), 6), np.nan, np.float32)
        attributes[:, :3] = colours
    return Mesh(vertices, faces, attributes)


def _splat_gaussians(data: bytes):
    """`recon_rgbd.Gaussians` of a splat PLY recon wrote (17 float properties per Gaussian)."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    head = data[:end].decode().splitlines()
    n = int(next(l for l in head if l.startswith("element vertex")).split()[-1])
    props = [l.split()[-1] for l in head if l.startswith("property float")]
    rows = np.frombuffer(data, dtype="<f4", count=n * len(props), offset=end).reshape(n, len(props))
    col = {p: i for i, p in enumerate(props)}
    take = lambda *names: np.ascontiguousarray(rows[:, [col[p] for p in names]], dtype=np.float32)
    means = take("x", "y", "z")
    dc = take("f_dc_0", "f_dc_1", "f_dc_2")
    scales = np.exp(take("scale_0", "scale_1", "scale_2"))
    rotations = take("rot_0", "rot_1", "rot_2", "rot_3")
    opacities = (1.0 / (1.0 + np.exp(-rows[:, col["opacity"]]))).astype(np.float32)
    return Gaussians(means, scales, rotations, opacities, dc)


class Job:
    """A job on the server: `status()`, `result()` (the objects, once done), `cancel()`."""

    def __init__(self, client: "Client", id: str, labels=None):
        self.client = client
        self.id = id
        self._labels = labels or {}

    def __repr__(self):
        return f"recon_rgbd.Job({self.id})"

    def status(self) -> dict:
        """The job document: `status` (queued, running, done, failed, cancelled), `stage`,
        `progress`, `error`, and `result` when done."""
        return self.client._json("GET", f"/v1/jobs/{self.id}")

    def cancel(self) -> dict:
        """Cancels the job (a queued one at once, a running one at its next stage boundary);
        a job that has already finished is deleted from the server."""
        return self.client._json("DELETE", f"/v1/jobs/{self.id}")

    def result(self, timeout: float | None = None, poll: float = 0.1, progress=None):
        """Waits for the job and returns its objects as `Engine.reconstruct` does; a failed
        or cancelled job raises `recon_rgbd.ReconError` with the server's message."""
        t0 = time.monotonic()
        while True:
            doc = self.status()
            if progress is not None:
                progress({"event": "job", "status": doc["status"], "stage": doc.get("stage"), "object": doc.get("object"), "progress": doc.get("progress")})
            if doc["status"] in ("done", "failed", "cancelled"):
                return self.client._objects(doc, self._labels)
            if timeout is not None and time.monotonic() - t0 > timeout:
                raise TimeoutError(f"job {self.id} still {doc['status']} after {timeout} s")
            time.sleep(poll)


class Client:
    """A `recon serve` at `url` (`http://host:port`), with `token` for its bearer
    authentication. `reconstruct` takes `Engine.reconstruct`'s arguments and returns the
    same `recon_rgbd.Object`s; `timeout` bounds each HTTP exchange (seconds)."""

    def __init__(self, url: str, token: str | None = None, timeout: float = 3600.0):
        self.url = url.rstrip("/")
        self.token = token
        self.timeout = timeout

    def __repr__(self):
        return f"recon_rgbd.Client({self.url})"

    # --- HTTP -------------------------------------------------------------------------

    def _request(self, method: str, path: str, body: bytes | None = None, content_type: str | None = None):
        req = urllib.request.Request(self.url + path, data=body, method=method)
        if content_type:
            req.add_header("Content-Type", content_type)
        if self.token:
            req.add_header("Authorization", f"Bearer {self.token}")
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as r:
                return r.status, r.read()
        except urllib.error.HTTPError as e:
            return e.code, e.read()

    def _json(self, method: str, path: str, body: bytes | None = None, content_type: str | None = None, ok=(200, 202)):
        status, data = self._request(method, path, body, content_type)
        try:
            doc = json.loads(data) if data else {}
        except ValueError:
            doc = {}
        if status not in ok:
            if status in (409, 422, 503, 504) and isinstance(doc, dict) and "status" in doc and "error" in doc and "id" in doc:
                return doc  # a finished job's document (failed or cancelled): reported by `_objects`
            raise self._error(status, doc, data)
        return doc

    @staticmethod
    def _error(status: int, doc, data: bytes):
        e = doc.get("error") if isinstance(doc, dict) else None
        if not isinstance(e, dict):
            return ReconError(f"HTTP {status}: {data[:500].decode(errors='replace')}")
        msg = e.get("message", f"HTTP {status}")
        cls = ConfigError if e.get("part") == "options" else InputError if 400 <= status < 500 and status not in (401, 404, 409, 429) else ReconError
        err = cls(msg)
        err.status, err.part, err.field = status, e.get("part"), e.get("field")
        return err

    def _get(self, path: str) -> bytes:
        status, data = self._request("GET", path)
        if status != 200:
            try:
                doc = json.loads(data)
            except ValueError:
                doc = {}
            raise self._error(status, doc, data)
        return data

    # --- requests ---------------------------------------------------------------------

    @staticmethod
    def _view_parts(view, k: int, name: str, pose_key: str):
        """The parts of view `k` (`rgb<k>` … `T_c1_c<k>`) from a dict as `Engine.reconstruct`
        takes `view2` and the items of `views`; `name` labels errors as the engine does."""
        keys = f"rgb, depth, K, masks, {pose_key}[, depth_scale]"
        if not isinstance(view, dict):
            raise InputError(f"{name}: expected a dict with {keys}")
        missing = [k for k in ("rgb", "depth", "K", "masks", pose_key) if k not in view]
        if missing:
            raise InputError(f"{name}: missing key `{missing[0]}` ({keys})")
        mk, _ = _mask_parts(view["masks"], f"masks{k}", f"{name} masks")
        t = np.asarray(view[pose_key], dtype=np.float64)
        if t.shape != (4, 4):
            raise InputError(f"{name} {pose_key}: expected a 4×4 matrix, got {t.shape}")
        return [
            (f"rgb{k}", f"rgb{k}.png", _png(np.asarray(view["rgb"]))),
            (f"depth{k}", f"depth{k}.npy", _npy(_depth_metres(view["depth"], view.get("depth_scale"), f"<{name} array>"))),
            (f"intrinsics{k}", None, _k_json(view["K"], f"<{name} array>")),
            *mk,
            (f"T_c1_c{k}", None, json.dumps(t.ravel().tolist()).encode()),
        ]

    def _parts(self, rgb, depth, K, masks, depth_scale, view2, views, options):
        # The views besides the anchor, counted before any is converted: view2, then views
        # (view 2, 3, …), as `Engine.reconstruct` numbers them.
        views = [] if views is None else list(views)
        others = (view2 is not None) + len(views)
        if others > 16:
            raise InputError(
                f"views: count claims {others} views besides the anchor, more than the limit of 16 (each is a fused "
                "condition of every object's run (memory, and with multidiffusion a model pass per step))"
            )
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise InputError("<array> rgb: expected an H×W×3 uint8 array")
        mparts, labels = _mask_parts(masks, "masks")
        parts = [
            ("rgb", "rgb.png", _png(rgb)),
            ("depth", "depth.npy", _npy(_depth_metres(depth, depth_scale, "<array>"))),
            ("intrinsics", None, _k_json(K, "<array>")),
            *mparts,
        ]
        k = 2
        if view2 is not None:
            parts += self._view_parts(view2, k, "view2", "T_c1_c2")
            k += 1
        for i, v in enumerate(views):
            parts += self._view_parts(v, k + i, f"views[{i}]", "T_c1_ci")
        if options:
            parts.append(("options", None, json.dumps(options).encode()))
        return parts, labels

    def submit(self, rgb, depth, K, masks, *, depth_scale=None, view2=None, views=None, **options) -> Job:
        """Queues a reconstruction (`?wait=false`) and returns its `Job` at once; the
        arguments are `reconstruct`'s."""
        parts, labels = self._parts(rgb, depth, K, masks, depth_scale, view2, views, options)
        ct, body = _multipart(parts)
        doc = self._json("POST", "/v1/reconstruct?wait=false", body, ct)
        return Job(self, doc["id"], labels)

    def reconstruct(self, rgb, depth, K, masks, *, depth_scale=None, view2=None, views=None, progress=None, **options):
        """`Engine.reconstruct` on the server: the same arguments, the same objects. With
        `progress`, the job is queued and polled, and `progress` hears its status. `views`:
        more views besides the anchor, each a dict {"rgb", "depth", "K", "masks", "T_c1_ci"
        (camera i → camera 1, 4×4)[, "depth_scale"]}, after `view2` (view 2, 3, …; at most 16
        in all), sent as the parts `rgb<N>` … `T_c1_c<N>`."""
        if progress is not None:
            return self.submit(rgb, depth, K, masks, depth_scale=depth_scale, view2=view2, views=views, **options).result(progress=progress)
        parts, labels = self._parts(rgb, depth, K, masks, depth_scale, view2, views, options)
        ct, body = _multipart(parts)
        doc = self._json("POST", "/v1/reconstruct?wait=true", body, ct)
        return self._objects(doc, labels)

    def scene(self, job: Job | str, **options) -> dict:
        """`recon scene` on a finished job (collision, settling, URDF/MJCF/USD exports) with
        `recon scene`'s options by name; the server's answer (summaries, file URLs)."""
        jid = job.id if isinstance(job, Job) else str(job)
        return self._json("POST", f"/v1/jobs/{jid}/scene", json.dumps(options).encode(), "application/json", ok=(200,))

    def file(self, url: str) -> bytes:
        """The bytes of a file URL of an answer (`/v1/jobs/<id>/files/...`)."""
        return self._get(url)

    def health(self) -> bool:
        status, _ = self._request("GET", "/health")
        return status == 200

    # --- answers ----------------------------------------------------------------------

    def _objects(self, doc: dict, labels: dict):
        status = doc.get("status")
        if status != "done":
            err = doc.get("error") or {}
            raise ReconError(f"job {doc.get('id')} {status}: {err.get('reason', '')}: {err.get('message', '')}".rstrip(": "))
        out = []
        for o in doc["result"]["objects"]:
            if o.get("status") != "ok":
                continue
            files = o["files"]
            pose_json = json.loads(self._get(files["pose"]))
            r = np.asarray(pose_json["rotation"], dtype=np.float32).astype(np.float64)
            t = np.asarray(pose_json["translation_m"], dtype=np.float32).astype(np.float64)
            pose = np.eye(4)
            pose[:3, :3] = r
            pose[:3, 3] = t
            details = {k: pose_json.get(k) for k in ("selection", "views", "candidates", "occupied_voxels", "faces_decoded", "samples")}
            details["run"] = pose_json.get("run")
            details["notes"] = pose_json.get("notes")
            mesh = _glb_mesh(self._get(files["mesh_glb"])) if files.get("mesh_glb") else None
            gaussians = _splat_gaussians(self._get(files["gaussians_ply"])) if files.get("gaussians_ply") else None
            label = labels.get(o["label"], o["label"])
            out.append(
                Object._from_parts(
                    id=o.get("id") if label == o["label"] else None,
                    label=label,
                    pose=pose,
                    scale=float(np.float32(pose_json["scale_m"])),
                    score=float(pose_json["selection"]["score_m"]),
                    spread=pose_json.get("uncertainty"),
                    stage_seconds=dict(o.get("stage_seconds", {})),
                    details=details,
                    mesh=mesh,
                    gaussians=gaussians,
                )
            )
        return out
