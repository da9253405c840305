"""recon_rgbd.Client against a `recon serve` (random tiny model, 127.0.0.1, port 0): the same
objects as Engine.reconstruct on the same arrays, jobs, cancellation, scenes, errors."""

import subprocess

import numpy as np
import pytest

import recon_rgbd
from conftest import INFER, REPO

TINY = REPO / "models/recgen-tiny.json"


@pytest.fixture(scope="module")
def server(recon_cli, tmp_path_factory):
    data = tmp_path_factory.mktemp("serve")
    log = open(data / "server.log", "wb")
    p = subprocess.Popen(
        [str(recon_cli), "serve", "--bind", "127.0.0.1:0", "--data-dir", str(data / "jobs"), "--weights", "random", "--config", str(TINY)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=log,
    )
    line = p.stdout.readline().decode()
    assert line.startswith("recon serve: listening on http://"), (line, (data / "server.log").read_text())
    yield line.strip().rsplit("http://", 1)[1]
    p.terminate()
    p.wait(timeout=60)
    log.close()


@pytest.fixture(scope="module")
def client(server):
    return recon_rgbd.Client(f"http://{server}")


@pytest.fixture(scope="module")
def tiny_engine():
    return recon_rgbd.Engine(weights="random", config=TINY)


@pytest.fixture(scope="module")
def frame(synth_ds):
    f = recon_rgbd.dataset_frames(synth_ds)[0]
    fr = recon_rgbd.load_frame(f["rgb"])
    masks = [m["mask"] for m in recon_rgbd.load_masks(f["masks"])["objects"]]
    ids = np.zeros(masks[0].shape, np.uint16)
    for i, m in enumerate(masks):
        ids[m] = 3 * i + 2
    return fr, masks, ids


def assert_same_objects(remote, local, tmp_path):
    assert [o.label for o in remote] == [o.label for o in local] and len(local) > 0
    for r, o in zip(remote, local):
        assert isinstance(r, recon_rgbd.Object)
        assert r.id == o.id
        assert np.array_equal(r.pose, o.pose) and r.pose.dtype == np.float64
        assert (r.scale, r.score) == (o.scale, o.score)
        assert r.spread == o.spread
        assert set(r.stage_seconds) == set(o.stage_seconds)
        assert r.details["selection"] == o.details["selection"]
        assert np.array_equal(r.mesh.vertices, o.mesh.vertices) and np.array_equal(r.mesh.faces, o.mesh.faces)
        assert np.array_equal(r.mesh.colors, o.mesh.colors)
        for a, b in (("r.ply", "o.ply"), ("r.glb", "o.glb")):
            getattr(r, "to_" + a[2:])(tmp_path / a)
            getattr(o, "to_" + b[2:])(tmp_path / b)
            assert (tmp_path / a).read_bytes() == (tmp_path / b).read_bytes(), a
        g, h = r.gaussians, o.gaussians
        assert np.array_equal(g.means, h.means) and np.array_equal(g.dc, h.dc) and np.array_equal(g.colors, h.colors)
        assert np.allclose(g.opacities, h.opacities, rtol=1e-5, atol=1e-6) and np.allclose(g.scales, h.scales, rtol=1e-5)


def test_client_reconstruct_gives_the_engine_objects(client, tiny_engine, frame, tmp_path):
    fr, masks, ids = frame
    # An instance-id image, float32 metres.
    local = tiny_engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, **INFER)
    remote = client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, **INFER)
    assert_same_objects(remote, local, tmp_path)
    assert all(o.label.startswith("id ") for o in remote)
    # Boolean masks, uint16 depth with a scale: labels `mask i`, no ids.
    depth16 = np.round(np.nan_to_num(fr["depth"]) / 0.0005).astype(np.uint16)
    local = tiny_engine.reconstruct(fr["rgb"], depth16, fr["K"], masks, depth_scale=0.0005, **INFER)
    remote = client.reconstruct(fr["rgb"], depth16, fr["K"], masks, depth_scale=0.0005, **INFER)
    assert_same_objects(remote, local, tmp_path)
    assert all(o.label.startswith("mask ") and o.id is None for o in remote)


def test_client_views_give_the_engine_objects(client, tiny_engine, frame, tmp_path):
    """`views=[…]` (after `view2`) go as the parts rgb<N> … T_c1_c<N>: the same objects as
    `Engine.reconstruct(views=…)`, the two-view model fusing (anchor, view i) pairs; the
    engine's checks on the dicts, the server's on the poses."""
    fr, masks, ids = frame
    # The largest object, one sampler step: two reconstructions on each side.
    big = max(range(len(masks)), key=lambda i: masks[i].sum())
    ids = np.where(ids == 3 * big + 2, ids, 0).astype(ids.dtype)
    Ts = []
    for i, dx in enumerate([0.03, -0.04, 0.02]):
        T = np.eye(4)
        T[0, 3], T[2, 3] = dx, 0.01 * i
        Ts.append(T)
    views = [{"rgb": fr["rgb"], "depth": fr["depth"], "K": fr["K"], "masks": ids, "T_c1_ci": T} for T in Ts[:2]]
    opts = dict(INFER, steps=1, fusion="stochastic")
    local = tiny_engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, views=views, **opts)
    remote = client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, views=views, **opts)
    assert_same_objects(remote, local, tmp_path)
    for r, o in zip(remote, local):
        assert [v["view"] for v in r.details["views"]] == [v["view"] for v in o.details["views"]] == [1, 2, 3]
        assert r.details["run"]["fusion"] == {"pairs": 2, "ss": "stochastic", "slat": "none"}
    # view2, then views (views 2, 3, 4); uint16 depth with a scale.
    depth16 = np.round(np.nan_to_num(fr["depth"]) / 0.0005).astype(np.uint16)
    view2 = {"rgb": fr["rgb"], "depth": depth16, "depth_scale": 0.0005, "K": fr["K"], "masks": ids, "T_c1_c2": Ts[2]}
    local = tiny_engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, view2=view2, views=views, **opts)
    remote = client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, view2=view2, views=views, **opts)
    assert_same_objects(remote, local, tmp_path)
    assert all([v["view"] for v in r.details["views"]] == [1, 2, 3, 4] for r in remote)

    with pytest.raises(recon_rgbd.InputError, match=r"views\[0\]: missing key `depth` \(rgb, depth, K, masks, T_c1_ci\[, depth_scale\]\)"):
        client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, views=[{"rgb": fr["rgb"]}], **opts)
    with pytest.raises(recon_rgbd.InputError, match="more than the limit of 16"):
        client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, view2=view2, views=[views[0]] * 16, **opts)
    with pytest.raises(recon_rgbd.InputError, match=r"views\[1\] T_c1_ci: expected a 4×4 matrix"):
        client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, views=[views[0], dict(views[1], T_c1_ci=np.eye(3))], **opts)
    with pytest.raises(recon_rgbd.InputError, match="T_c1_c3: the last row must be 0 0 0 1") as e:
        client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, views=[views[0], dict(views[1], T_c1_ci=2 * np.eye(4))], **opts)
    assert (e.value.status, e.value.part, e.value.field) == (400, "T_c1_c3", "T_c1_c3")


def test_client_jobs_cancel_and_scene(client, tiny_engine, frame, tmp_path):
    fr, _, ids = frame
    job = client.submit(fr["rgb"], fr["depth"], fr["K"], ids, **INFER)
    assert isinstance(job, recon_rgbd.Job) and len(job.id) == 32
    events = []
    objs = job.result(progress=events.append)
    assert job.status()["status"] == "done" and events[-1]["status"] == "done"
    assert_same_objects(objs, tiny_engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, **INFER), tmp_path)
    scene = client.scene(job, settle_time=0.5)
    assert scene["job"] == job.id and any(f.endswith(".urdf") for f in scene["files"]), scene
    # Cancelled at once (queued or at its first stage boundary): result() says so.
    slow = client.submit(fr["rgb"], fr["depth"], fr["K"], ids, samples=4, **INFER)
    slow.cancel()
    with pytest.raises(recon_rgbd.ReconError, match="cancelled"):
        slow.result(timeout=300)


def test_client_errors_are_the_engine_classes(client, frame):
    fr, _, ids = frame
    with pytest.raises(recon_rgbd.ConfigError, match="unknown option `sample`") as e:
        client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, sample=2)
    assert (e.value.status, e.value.part) == (400, "options")
    with pytest.raises(recon_rgbd.InputError, match="max_objects") as e:
        client.reconstruct(fr["rgb"], fr["depth"], fr["K"], ids, max_objects=1, **INFER)
    assert e.value.status == 413
    with pytest.raises(recon_rgbd.InputError, match="uint8"):
        client.reconstruct(fr["rgb"].astype(np.float32), fr["depth"], fr["K"], ids)
