"""recon_rgbd.ray on a local Ray cluster the test starts itself (2 CPUs)."""

import os
import shutil
import subprocess
from pathlib import Path

import pytest

import recon_rgbd
from conftest import INFER, assert_same_output, cli_infer

if os.environ.get("RECON_REQUIRE_PYTHON_TESTS") == "1":  # CI: a missing Ray fails
    import pyarrow.parquet as pq
    import ray
else:
    ray = pytest.importorskip("ray")
    pq = pytest.importorskip("pyarrow.parquet")
import recon_rgbd.ray as rr  # noqa: E402


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def broken_ds(synth_ds, tmp_path_factory):
    """The synth dataset with frame 1's colour image made unreadable."""
    ds = tmp_path_factory.mktemp("broken") / "ds"
    shutil.copytree(synth_ds, ds)
    frames = recon_rgbd.dataset_frames(ds)
    Path(frames[1]["rgb"]).write_bytes(b"this is not a PNG")
    return ds


def test_dataset_run_matches_cli_records_failure_and_resumes(cluster, broken_ds, recon_cli, tmp_path):
    frames = recon_rgbd.dataset_frames(broken_ds)
    bad = frames[1]["frame"]
    out = tmp_path / "out"
    s = rr.reconstruct_dataset(broken_ds, out, num_workers=2, **INFER)
    assert (s["frames"], s["processed"], s["resumed"], s["failed"]) == (3, 3, 0, 1)
    assert s["failed_frames"] == [bad]

    # The results table has every frame; the failing one carries its error text.
    t = pq.read_table(out / rr.RESULTS).to_pylist()
    assert {r["frame"] for r in t} == {f["frame"] for f in frames}
    (failed,) = [r for r in t if r["frame"] == bad]
    assert failed["status"] == "failed" and "InputError" in failed["error"]
    assert "rgb/000000.png" in failed["error"]
    ok = [r for r in t if r["status"] == "ok"]
    assert ok and all(len(r["pose"]) == 16 and r["pose"][-4:] == [0, 0, 0, 1] for r in ok)
    assert all(r["seconds_total"] > 0 and r["score"] >= 0 for r in ok)

    # Outputs identical to `recon infer` with the same seed on the same frames.
    for f in frames:
        if f["frame"] == bad:
            assert not (out / bad / recon_rgbd.OUTPUT_MARKER).exists()
            continue
        cli_infer(recon_cli, f, tmp_path / "cli" / f["frame"])
        assert_same_output(out / f["frame"], tmp_path / "cli" / f["frame"])

    # A second run redoes only the failed frame; finished folders are not touched.
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.name != rr.RESULTS}
    s2 = rr.reconstruct_dataset(broken_ds, out, num_workers=2, **INFER)
    assert (s2["processed"], s2["resumed"], s2["failed"]) == (1, 2, 1)
    assert stamps == {p: p.stat().st_mtime_ns for p in stamps}
    t2 = pq.read_table(out / rr.RESULTS).to_pylist()
    assert sorted((r["frame"], r["object"] or "") for r in t2) == sorted((r["frame"], r["object"] or "") for r in t)
    key = lambda r: (r["frame"], r["object"] or "")
    assert [r["pose"] for r in sorted(t2, key=key)] == [r["pose"] for r in sorted(t, key=key)]

    # A job that died before writing the table: the rerun rebuilds it from the finished
    # frames' part files, stage seconds and worker figures included.
    (out / rr.RESULTS).unlink()
    s3 = rr.reconstruct_dataset(broken_ds, out, num_workers=2, **INFER)
    assert (s3["processed"], s3["resumed"], s3["failed"]) == (1, 2, 1)
    finished = lambda t: sorted((r for r in t if r["frame"] != bad), key=key)
    t3 = pq.read_table(out / rr.RESULTS).to_pylist()
    assert finished(t3) == finished(t) and all(r["seconds_total"] > 0 for r in finished(t3) if r["status"] == "ok")


def test_frame_table_source(cluster, synth_ds, tmp_path):
    frames = recon_rgbd.dataset_frames(synth_ds)[:1]
    table = [{"frame": "only", "rgb": f["rgb"], "masks": f["masks"]} for f in frames]
    s = rr.reconstruct_dataset(table, tmp_path / "o", num_workers=1, **INFER)
    assert (s["frames"], s["failed"]) == (1, 0)
    assert (tmp_path / "o" / "only" / recon_rgbd.OUTPUT_MARKER).is_file()
    with pytest.raises(recon_rgbd.InputError, match="masks"):
        rr.frames_of([{"rgb": "x.png"}])


def test_multi_view_rows(cluster, synth_ds, recon_cli, tmp_path):
    """A row with `views` (view files or dicts) is `recon infer --view …` on that frame;
    too many views are refused when the table is read."""
    import json

    f = recon_rgbd.dataset_frames(synth_ds)[0]
    T = [[1, 0, 0, 0.03], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    spec = {"rgb": f["rgb"], "masks": f["masks"], "T_c1_ci": T}
    vf = tmp_path / "v2.json"
    vf.write_text(json.dumps(spec))
    opts = dict(INFER, fusion="stochastic")
    table = [{"frame": "multi", "rgb": f["rgb"], "masks": f["masks"], "views": [vf, dict(spec, T_c1_ci=T[:3] + [[0, 0, 0, 1]])]}]
    s = rr.reconstruct_dataset(table, tmp_path / "o", num_workers=1, **opts)
    assert (s["frames"], s["failed"]) == (1, 0), pq.read_table(tmp_path / "o" / rr.RESULTS).to_pylist()
    cli = tmp_path / "cli"
    r = subprocess.run(
        [str(recon_cli), "infer", "--rgbd", f["rgb"], "--masks", *f["masks"], "--out", str(cli), "--view", str(vf), "--view", str(vf),
         "--seed", "7", "--max-faces", "2000", "--steps", "2", "--fusion", "stochastic"],
        capture_output=True, text=True,
    )
    assert r.returncode in (0, 3), r.stderr
    assert_same_output(tmp_path / "o" / "multi", cli)
    with pytest.raises(recon_rgbd.InputError, match="views.*limit of 16"):
        rr.frames_of([{"rgb": "x.png", "masks": "m.png", "views": [str(vf)] * 17}])


def test_ray_synth_is_identical_to_one_process(cluster, synth_ds, tmp_path):
    s = rr.synth(tmp_path / "ds", scenes=3, num_workers=2, scenes_per_task=1, seed=3, width=160, height=120)
    assert s["scenes"] == 3
    a = sorted(p.relative_to(synth_ds) for p in synth_ds.rglob("*") if p.is_file())
    b = sorted(p.relative_to(tmp_path / "ds") for p in (tmp_path / "ds").rglob("*") if p.is_file())
    assert a == b
    for p in a:
        assert (synth_ds / p).read_bytes() == (tmp_path / "ds" / p).read_bytes(), p
