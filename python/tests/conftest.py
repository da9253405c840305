"""Shared fixtures: a tiny `recon synth` dataset and the `recon` CLI to compare with.

Inference runs with few sampler steps and a small face budget so the suite stays quick;
the comparisons with the CLI pass the same settings to both.
"""

import json
import os
import subprocess
from pathlib import Path

import pytest

import recon_rgbd

REPO = Path(__file__).resolve().parents[2]

# Settings shared by every comparison with the CLI (both sides get exactly these).
INFER = {"seed": 7, "max_faces": 2000, "steps": 2}


def cli_flags(opts=INFER):
    return ["--seed", str(opts["seed"]), "--max-faces", str(opts["max_faces"]), "--steps", str(opts["steps"])]


@pytest.fixture(scope="session")
def recon_cli():
    """The `recon` binary: $RECON_CLI, else target/{debug,release}/recon, else built now."""
    env = os.environ.get("RECON_CLI")
    if env:
        return Path(env)
    for p in (REPO / "target/debug/recon", REPO / "target/release/recon"):
        if p.is_file():
            return p
    subprocess.run(["cargo", "build", "--bin", "recon"], cwd=REPO, check=True)
    return REPO / "target/debug/recon"


@pytest.fixture(scope="session")
def synth_ds(tmp_path_factory):
    """3 scenes, one view each, 160×120: frames `test/00000N/000000`."""
    root = tmp_path_factory.mktemp("synth") / "ds"
    recon_rgbd.synth(root, scenes=3, views=1, seed=3, width=160, height=120)
    return root


@pytest.fixture(scope="session")
def engine():
    return recon_rgbd.Engine()


def run_cli(cli, *args, ok=(0,)):
    r = subprocess.run([str(cli), *map(str, args)], cwd=REPO, capture_output=True, text=True)
    assert r.returncode in ok, r.stderr
    return r


def cli_infer(cli, frame, out):
    """`recon infer` on a frame of `recon_rgbd.dataset_frames` into `out`."""
    # Exit 3: some objects written, others skipped (README: exit codes); the skipped ones are
    # in the index and the comparisons look at what was written.
    run_cli(cli, "infer", "--rgbd", frame["rgb"], "--masks", *frame["masks"], "--out", out, *cli_flags(), ok=(0, 3))


# Fields of pose.json that are wall-clock measurements or name the input files.
VOLATILE = {"timings_s", "postprocess_s", "select_s", "frame"}


def comparable_pose(path):
    p = json.loads(Path(path).read_text())
    for k in VOLATILE:
        p.pop(k, None)
    for v in p.get("views", []):
        v.pop("frame", None)
    # Where the (identical) weights were read from: the checkout's models/ or the
    # embedded copy's cache folder, depending on the process's working folder.
    run = p.get("run", {})
    run.pop("weights", None)
    run.pop("architecture", None)
    return p


def assert_same_output(a, b):
    """Two `recon infer` output folders hold the same files with the same content (pose.json
    up to its timings)."""
    a, b = Path(a), Path(b)
    fa = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    fb = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    assert fa == fb
    assert any(f.name == "mesh.ply" for f in fa), "no object was reconstructed: nothing compared"
    for f in fa:
        if f.name == "pose.json":
            assert comparable_pose(a / f) == comparable_pose(b / f), f
        elif f.name == recon_rgbd.OUTPUT_MARKER:
            ja, jb = json.loads((a / f).read_text()), json.loads((b / f).read_text())
            strip = lambda j: [{k: Path(v).name if isinstance(v, str) else v for k, v in o.items()} for o in j["objects"]]
            assert strip(ja) == strip(jb) and ja["skipped"] == jb["skipped"]
        else:
            assert (a / f).read_bytes() == (b / f).read_bytes(), f
