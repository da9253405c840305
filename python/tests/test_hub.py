"""Weights by name from the Hugging Face hub, with no network: a fake hub endpoint
(HF_ENDPOINT, the routes and headers hf-hub reads) serves a release laid out as
RecGen's (`pipeline.json`, `sparse-structure-ft-70k/…`, the `.pt` denoisers, the TRELLIS
decoders; torch.hub's DINOv2 by URL) made of tiny random modules by the wheel's own
`python -m recon_rgbd weights init`. `Engine.from_pretrained` downloads it into the
standard cache (HF_HOME) through hf-hub, checks every SHA-256 against the manifest's pins
and runs; then, offline with the endpoint gone, it runs from that cache alone; a changed
byte, a missing token and a missing file each stop it with a message that names them."""

import hashlib
import http.server
import json
import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from conftest import REPO

TINY = REPO / "models/recgen-tiny.json"
REPO_ID = "TRI-ML/RecGen"
TOKEN = "hf_test_token"
DINO = "dinov2_vitl14_reg4_pretrain.pth"


def module(*args, cwd=None):
    r = subprocess.run([sys.executable, "-m", "recon_rgbd", *map(str, args)], cwd=cwd, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return r


def sha256(p):
    return hashlib.sha256(Path(p).read_bytes()).hexdigest()


def make_release(root):
    """The release's files by their released names under root/remote, DINOv2 under
    root/dino/recon-url/dinov2-vitl14-reg; the two manifests, pinned to them, as
    `weights manifest --pin` writes them."""
    arch = json.loads(TINY.read_text())
    pt, st = root / "pt", root / "st"
    module("weights", "init", "--config", TINY, "--out", pt, "--format", "pt", "--seed", "7")
    module("weights", "init", "--config", TINY, "--out", st, "--seed", "7")
    remote = root / "remote"

    def put(path, src=None, data=None):
        dest = remote / path
        dest.parent.mkdir(parents=True, exist_ok=True)
        if src is not None:
            shutil.copyfile(src, dest)
        else:
            dest.write_text(json.dumps(data, indent=1))

    def spec(name, key):
        return {"name": name, "args": arch[key]["args"]}

    def sampler(steps):
        return {"name": "FlowEulerGuidanceIntervalSampler", "args": {"sigma_min": 1e-5},
                "params": {"steps": steps, "cfg_strength": 7.5, "cfg_interval": [0.5, 1.0], "rescale_t": 3.0}}  # fmt: skip

    decoders = [
        ("ckpts/ss_dec_conv3d_16l8_fp16", "SparseStructureDecoder", "ss_decoder"),
        ("ckpts/slat_dec_mesh_swin8_B_64l8m256c_fp16", "ElasticSLatMeshDecoder", "slat_dec_mesh"),
        ("ckpts/slat_dec_gs_swin8_B_64l8gs32_fp16", "ElasticSLatGaussianDecoder", "slat_dec_gs"),
    ]
    models = {
        "sparse_structure_decoder": decoders[0][0],
        "sparse_structure_flow_model": "ckpts/ss_flow_img_dit_L_16l8_fp16",
        "slat_decoder_gs": decoders[2][0],
        "slat_decoder_rf": "ckpts/slat_dec_rf_swin8_B_64l8r16_fp16",
        "slat_decoder_mesh": decoders[1][0],
        "slat_flow_model": "ckpts/slat_flow_img_dit_L_64l8p2_fp16",
    }
    put("pipeline.json", data={"name": "TrellisImageTo3DPipeline", "args": {
        "models": models, "sparse_structure_sampler": sampler(3), "slat_sampler": sampler(2),
        "image_cond_model": "dinov2_vitl14_reg"}})  # fmt: skip
    ft = "sparse-structure-ft-70k"
    put(f"{ft}/stereo_denoiser_ema0.9999_step0070000.pt", pt / "ss_flow.pt")
    put(f"{ft}/stereo_config.json", data={
        "models": {"denoiser": spec("SparseStructurePoseFlowModel", "ss_flow")},
        "trainer": {"name": "MultiImageConditionedFlowMatchingCFGTrainer", "args": {"use_pose_normalization": True}}})  # fmt: skip
    put(f"{ft}/stereo_pose_stats.json", TINY.parent / arch["pose"]["ss_stats"])
    put("slat_denoiser_ema0.9999_step0075000.pt", pt / "slat_flow.pt")
    put("slat_config.json", data={
        "models": {"denoiser": spec("ElasticSLatCondFlowModel", "slat_flow")},
        "dataset": {"args": {"use_pose_normalization": True, "normalization": arch["slat_normalization"]}}})  # fmt: skip
    put("slat_pose_stats.json", TINY.parent / arch["pose"]["slat_stats"])
    for stem, cls, key in decoders:
        put(f"{stem}.json", data=spec(cls, key))
        put(f"{stem}.safetensors", st / f"{key}.safetensors")
    dino = root / "dino/recon-url/dinov2-vitl14-reg"
    dino.mkdir(parents=True)
    shutil.copyfile(pt / "image_cond_model.pt", dino / DINO)

    rm, dm = root / "recgen.json", root / "dinov2.json"
    module("weights", "manifest", "recgen", "--config", TINY, "--pin", remote, "--out", rm)
    module("weights", "manifest", "dinov2-vitl14-reg", "--config", TINY, "--pin", root / "dino", "--out", dm)
    m = json.loads(rm.read_text())
    assert m["repo"] == REPO_ID and m["requires"] == ["dinov2-vitl14-reg"]
    m["requires"] = ["dinov2.json"]
    rm.write_text(json.dumps(m))
    return remote, dino / DINO, m


class FakeHub(http.server.ThreadingHTTPServer):
    """The routes hf-hub reads: `/{repo}/resolve/{rev}/{path}` with `Range` (its metadata
    request is `bytes=0-0`), answering `x-repo-commit`, `x-linked-etag` (the SHA-256 of an
    LFS file) and `Content-Range`; 401 without the token; 404 for an absent file. `/dino`
    serves the DINOv2 checkpoint as its URL does."""

    def __init__(self, remote, dino, commit):
        self.remote, self.dino, self.commit, self.requests = remote, dino, commit, []
        super().__init__(("127.0.0.1", 0), Handler)

    @property
    def url(self):
        return f"http://127.0.0.1:{self.server_address[1]}"


class Handler(http.server.BaseHTTPRequestHandler):
    def log_message(self, *a):
        pass

    def do_GET(self):
        hub = self.server
        hub.requests.append(self.path)
        if self.path == "/dino":
            return self.send(hub.dino.read_bytes(), etag=None)
        prefix = f"/{REPO_ID}/resolve/"
        if not self.path.startswith(prefix):
            return self.fail(404)
        if self.headers.get("Authorization") != f"Bearer {TOKEN}":
            return self.fail(401)
        rev, _, rel = self.path[len(prefix) :].partition("/")
        f = hub.remote / rel
        if rev != hub.commit or not f.is_file():
            return self.fail(404)
        self.send(f.read_bytes(), etag=sha256(f))

    def send(self, data, etag):
        start, end = 0, len(data) - 1
        rng = self.headers.get("Range")
        if rng:
            a, _, b = rng.removeprefix("bytes=").partition("-")
            start, end = int(a), int(b) if b else len(data) - 1
        self.send_response(206 if rng else 200)
        if etag:
            self.send_header("x-repo-commit", self.server.commit)
            self.send_header("x-linked-etag", f'"{etag}"')
            self.send_header("ETag", '"git-blob-sha1"')
        self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
        self.send_header("Content-Length", str(end + 1 - start))
        self.end_headers()
        self.wfile.write(data[start : end + 1])

    def fail(self, code):
        self.send_response(code)
        self.send_header("Content-Length", "0")
        self.end_headers()


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    root = tmp_path_factory.mktemp("hub")
    remote, dino, m = make_release(root)
    dm = json.loads((root / "dinov2.json").read_text())
    hub = FakeHub(remote, dino, m["revision"])
    dm["files"][0]["url"] = hub.url + "/dino"
    (root / "dinov2.json").write_text(json.dumps(dm))
    threading.Thread(target=hub.serve_forever, daemon=True).start()
    yield root, hub, m
    hub.shutdown()


LOAD = """
import json, sys, recon_rgbd
repo, manifest, tiny, sample = sys.argv[1:5]
try:
    e = recon_rgbd.Engine.from_pretrained(repo, manifest=manifest, config=tiny)
except recon_rgbd.WeightsError as err:
    print(json.dumps({"error": str(err)}))
    sys.exit(0)
f = recon_rgbd.load_frame(sample + "/000001-color.png")
masks = [m["mask"] for m in recon_rgbd.load_masks(sample + "/000001-label.png")["objects"]][:1]
objs = e.reconstruct(f["rgb"], f["depth"], f["K"], masks, steps=1, max_faces=0)
print(json.dumps({"objects": len(objs), "run": objs[0].details["run"]}, default=str))
"""


def from_pretrained(root, env_extra, drop=()):
    env = {k: v for k, v in os.environ.items() if not k.startswith("HF_") and k not in drop}
    env.update(HF_HOME=str(root / "hf"), **env_extra)
    args = [REPO_ID, root / "recgen.json", TINY, REPO / "data/sample"]
    r = subprocess.run([sys.executable, "-c", LOAD, *map(str, args)], cwd=root, capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1]), r.stderr


def test_from_pretrained_downloads_checks_and_runs_offline(release):
    root, hub, m = release
    cache = root / "hf/hub"
    online = {"HF_ENDPOINT": hub.url, "HF_TOKEN": TOKEN}

    # No token: the hub's 401 becomes advice to set HF_TOKEN.
    out, _ = from_pretrained(root, {"HF_ENDPOINT": hub.url})
    assert "HF_TOKEN" in out["error"] and REPO_ID in out["error"] and "gated or private" in out["error"], out

    # With the token: every needed file downloaded into the standard cache, then checked.
    out, err = from_pretrained(root, online)
    assert out.get("objects") == 1, (out, err)
    w = out["run"]["weights"]
    assert w["kind"] == "files", w
    read = {(f["manifest"], f["path"]): f for f in w["manifest_files"]}
    pins = {f["path"]: f.get("sha256") for f in m["files"]}
    needed = [f["path"] for f in m["files"] if not f.get("optional")]
    assert sorted(p for (n, p) in read if n == "recgen") == sorted(needed)
    for (name, path), f in read.items():
        local = Path(f["local"])
        assert local.is_relative_to(cache), f
        assert f["sha256"] == sha256(local), f
        if name == "recgen":
            assert f["sha256"] == pins[path] and local.is_symlink(), f
            # hf-hub's layout: snapshots/<commit>/<path> -> blobs/<sha256>.
            assert local.resolve() == cache / "models--TRI-ML--RecGen/blobs" / f["sha256"], f
            assert f"snapshots/{m['revision']}/" in str(local), f
    assert (cache / "recon-url/dinov2-vitl14-reg" / DINO).is_file()
    assert any(r.startswith(f"/{REPO_ID}/resolve/{m['revision']}/pipeline.json") for r in hub.requests)
    assert out["run"]["random_weights"] is True, "the tiny files carry recon's random-init label"

    # Offline, with the endpoint unreachable: the cache alone, no request made.
    before = len(hub.requests)
    out, _ = from_pretrained(root, {"HF_HUB_OFFLINE": "1", "HF_ENDPOINT": "http://127.0.0.1:9"})
    assert out.get("objects") == 1 and len(hub.requests) == before, out

    # One byte of a cached blob changed: the pin stops the load, naming file and both hashes.
    pt = "slat_denoiser_ema0.9999_step0075000.pt"
    blob = (cache / "models--TRI-ML--RecGen/snapshots" / m["revision"] / pt).resolve()
    good = blob.read_bytes()
    bad = bytearray(good)
    bad[len(bad) // 2] ^= 0x40
    blob.write_bytes(bytes(bad))
    out, _ = from_pretrained(root, {"HF_HUB_OFFLINE": "1"})
    assert pt in out["error"] and pins[pt] in out["error"] and sha256(blob) in out["error"], out
    blob.write_bytes(good)

    # A file gone from the cache, offline: named, with the repo and HF_HUB_OFFLINE.
    link = cache / "models--TRI-ML--RecGen/snapshots" / m["revision"] / "slat_config.json"
    link.unlink()
    out, _ = from_pretrained(root, {"HF_HUB_OFFLINE": "1"})
    assert "slat_config.json" in out["error"] and "HF_HUB_OFFLINE" in out["error"] and REPO_ID in out["error"], out
    # Online again: only that file is fetched.
    before = len(hub.requests)
    out, _ = from_pretrained(root, online)
    assert out.get("objects") == 1, out
    assert {r.split("/resolve/")[-1] for r in hub.requests[before:]} == {f"{m['revision']}/slat_config.json"}, hub.requests[before:]


def test_from_pretrained_refuses_a_manifest_of_another_repo(release):
    root, _, m = release
    import recon_rgbd

    with pytest.raises(recon_rgbd.WeightsError, match="is for repo `TRI-ML/RecGen`, not `someone/else`"):
        recon_rgbd.Engine.from_pretrained("someone/else", manifest=root / "recgen.json")
    with pytest.raises(recon_rgbd.WeightsError, match="pass revision=None"):
        recon_rgbd.Engine.from_pretrained(REPO_ID, revision="v2", manifest=root / "recgen.json")
