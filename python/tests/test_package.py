"""The package as a user installs it: its name and version, `info()`, the docs' example,
`python -m recon_rgbd` (the CLI's commands from the wheel), the default-model warning and
`Engine.from_pretrained`."""

import json
import os
import re
import signal
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

import recon_rgbd
from conftest import REPO, assert_same_output, cli_flags, cli_infer

DOC = REPO / "docs/python.md"
QUICKSTART = REPO / "python/examples/quickstart.py"
README_EXAMPLE = REPO / "python/examples/readme.py"
TINY = REPO / "models/recgen-tiny.json"


def indented_blocks(text, heading):
    """The indented (code) blocks of a markdown section, unindented, in order."""
    lines = text.split("\n")
    blocks, cur = [], []
    for i in range(lines.index(heading) + 1, len(lines)):
        line = lines[i]
        if line.startswith("## "):
            break
        following = lines[i + 1] if i + 1 < len(lines) else ""
        if line.startswith("    ") or (line == "" and cur and following.startswith("    ")):
            cur.append(line[4:])
        elif cur:
            blocks.append("\n".join(cur))
            cur = []
    return blocks + (["\n".join(cur)] if cur else [])


def run_module(*args, cwd=REPO):
    return subprocess.run([sys.executable, "-m", "recon_rgbd", *map(str, args)], cwd=cwd, capture_output=True, text=True)


def test_version_and_info():
    cargo = (REPO / "python/Cargo.toml").read_text()
    assert recon_rgbd.__version__ == re.search(r'^version = "([^"]+)"', cargo, re.M).group(1)
    i = recon_rgbd.info()
    assert i["version"] == recon_rgbd.__version__
    assert i["commit"] is None or re.fullmatch(r"[0-9a-f]{40}", i["commit"]), i["commit"]
    assert i["profile"] in ("dev", "release") and "hub" in i["features"]
    # The kernels' choice: the best instruction set this CPU supports (`recon bench`'s machine line).
    assert i["isa"] in i["supported_isas"] and "portable" in i["supported_isas"], i
    assert i["threads"] >= 1 and i["target"].endswith("-linux") or sys.platform != "linux"
    try:
        from importlib.metadata import PackageNotFoundError, version
    except ImportError:  # Python 3.7 has no importlib.metadata; the package needs 3.9
        return
    try:
        assert version("recon-rgbd") == recon_rgbd.__version__
    except PackageNotFoundError:
        pass  # run from a copied extension (HELPERS.md recipe), not an installed distribution


@pytest.mark.skipif(not os.environ.get("RECON_EXPECT_WHEEL"), reason="RECON_EXPECT_WHEEL unset: not testing an installed wheel")
def test_the_installed_wheel_is_under_test():
    """CI installs the wheel into a fresh venv without cargo: the package under test is that
    wheel's, not the source tree's."""
    from importlib.metadata import distribution

    here = Path(recon_rgbd.__file__).resolve()
    assert REPO / "python" not in here.parents, here
    assert Path(sys.prefix).resolve() in here.parents, (here, sys.prefix)
    files = {str(f) for f in distribution("recon-rgbd").files}
    assert "recon_rgbd/__main__.py" in files and any(f.startswith("recon_rgbd/_recon") for f in files), files


def test_quickstart_script_is_the_docs_example():
    code = indented_blocks(DOC.read_text(), "## Example")[0]
    assert QUICKSTART.read_text().endswith("\n\n" + code + "\n")


OBJECT_LINE = re.compile(r"^(mask \d+) \[\s*(\S+)\s+(\S+)\s+(\S+)\] (\S+) (\S+) (\(\d+, 3\)) (\d+)$")
SCENE_LINE = re.compile(r"^(mask \d+) (\w+) ([\d.]+ kg);")


def example_summary(text):
    """What the example's printout must keep: per object its label, translation, scale,
    score, mesh shape and Gaussian count; per scene object its material and mass; the
    scene file and that it came to rest."""
    lines = text.rstrip("\n").split("\n")
    objects = [OBJECT_LINE.match(l).groups() for l in lines if OBJECT_LINE.match(l)]
    scene = [SCENE_LINE.match(l).groups() for l in lines if SCENE_LINE.match(l)]
    return objects, scene, lines[-1].split(" after ")[0]


def test_docs_example_prints_what_the_docs_say(tmp_path):
    """The docs' example, run as a user runs it (a fresh process in a folder of their own,
    with the sample frame at data/sample/): the objects, poses, sizes and scene the docs show
    (scores to 5 %: the printed digits are the float's full repr)."""
    printed = indented_blocks(DOC.read_text(), "## Example")[1]
    (tmp_path / "data").symlink_to(REPO / "data")
    r = subprocess.run([sys.executable, str(QUICKSTART)], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    (got, got_scene, got_last), (doc, doc_scene, doc_last) = example_summary(r.stdout), example_summary(printed)
    assert len(doc) == 3 and [g[0] for g in got] == [d[0] for d in doc], r.stdout
    for g, d in zip(got, doc):
        assert [float(x) for x in g[1:5]] == pytest.approx([float(x) for x in d[1:5]], abs=1e-6), (g, d)
        assert float(g[5]) == pytest.approx(float(d[5]), rel=0.05) and g[6:] == d[6:], (g, d)
    assert got_scene == doc_scene and got_last == doc_last == "urdf/scene.urdf at rest: True", r.stdout
    assert "DefaultModelWarning" in r.stderr and r.stderr.count("no weights given") == 1, r.stderr
    assert (tmp_path / "object0.glb").stat().st_size > 0 and (tmp_path / "sample_sim/urdf/scene.urdf").is_file()


def test_readme_example_runs_as_printed(tmp_path):
    """README.md's Python example (python/examples/readme.py, verbatim), run as a user runs it
    from a folder holding the sample: one line per masked object, at the place and size the
    docs' example prints for the same seed, and one GLB each."""
    code = indented_blocks((REPO / "README.md").read_text(), "## From Python")[0]
    assert README_EXAMPLE.read_text().endswith("\n\n" + code + "\n")
    (tmp_path / "data").symlink_to(REPO / "data")
    r = subprocess.run([sys.executable, str(README_EXAMPLE)], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    line = re.compile(r"^(mask \d+) at \[\s*(\S+)\s+(\S+)\s+(\S+)\s*\] m; size (\S+) m; (\d+) faces$")
    got = [line.match(l) for l in r.stdout.strip().split("\n")]
    assert len(got) == 3 and all(got), r.stdout
    doc, _, _ = example_summary(indented_blocks(DOC.read_text(), "## Example")[1])
    for g, d in zip(got, doc):
        assert g[1] == d[0], (g[0], d)
        assert [float(x) for x in g.groups()[1:5]] == pytest.approx([round(float(x), 3) for x in d[1:5]], abs=1.5e-3), (g[0], d)
        assert int(g[6]) > 1000, g[0]
    assert sorted(p.name for p in tmp_path.glob("*.glb")) == ["object0.glb", "object1.glb", "object2.glb"]
    assert all(p.stat().st_size > 10_000 for p in tmp_path.glob("*.glb"))


def test_default_model_warns_once_per_process(tmp_path):
    code = """
import json, warnings, recon_rgbd
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    recon_rgbd.Engine(weights="random", config=%r)
    first = recon_rgbd.Engine()
    recon_rgbd.Engine()
print(json.dumps({"warnings": [[c.category.__name__, issubclass(c.category, UserWarning), str(c.message), c.filename] for c in w],
                  "model": first.model}))
""" % str(TINY)
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert [w[:2] for w in out["warnings"]] == [["DefaultModelWarning", True]], out
    msg = out["warnings"][0][2]
    assert "recgen-nano" in msg and "weights fetch recgen" in msg and 'from_pretrained("TRI-ML/RecGen")' in msg, msg
    assert out["warnings"][0][3] == "<string>", "the warning points at the caller's line"
    assert out["model"] == "Default"


def test_objects_name_their_model(synth_ds, engine):
    f = recon_rgbd.dataset_frames(synth_ds)[0]
    fr = recon_rgbd.load_frame(f["rgb"])
    masks = [m["mask"] for m in recon_rgbd.load_masks(f["masks"])["objects"]]
    objs = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, seed=7, steps=2, max_faces=2000)
    assert objs and all(o.details["run"]["architecture"] == "recgen-nano" for o in objs)
    assert all(not o.details["run"]["random_weights"] for o in objs)


def test_from_pretrained_is_the_hf_weights_path(tmp_path, recon_cli):
    """`Engine.from_pretrained(repo, revision)` loads as `--weights hf:REPO@REV` does: offline
    with an empty Hugging Face cache, both fail with the same message naming the repo."""
    env = {**os.environ, "HF_HOME": str(tmp_path / "hf"), "HF_HUB_OFFLINE": "1"}
    env.pop("HF_HUB_CACHE", None)
    code = """
import recon_rgbd
try:
    recon_rgbd.Engine.from_pretrained("TRI-ML/RecGen", revision="v1.0")
except recon_rgbd.WeightsError as e:
    print(e)
"""
    # From a folder of its own: the architecture file is the one the wheel carries.
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert r.returncode == 0 and r.stdout.strip(), r.stderr
    cli = subprocess.run(
        [str(recon_cli), "infer", "--rgbd", "data/sample/000001-color.png", "--masks", "data/sample/000001-label.png",
         "--weights", "hf:TRI-ML/RecGen@v1.0", "--out", str(tmp_path / "out")],
        cwd=REPO, capture_output=True, text=True, env=env,
    )  # fmt: skip
    assert cli.returncode == 1
    assert "TRI-ML/RecGen" in r.stdout and "HF_HUB_OFFLINE" in r.stdout, r.stdout
    assert r.stdout.strip() in cli.stderr, (r.stdout, cli.stderr)
    with pytest.raises(recon_rgbd.WeightsError, match="expected hf:ORG/NAME"):
        recon_rgbd.Engine.from_pretrained("not a repo")


def test_random_weights_outside_a_checkout(tmp_path):
    """`weights="random"` reads models/recgen-tiny.json in a checkout; elsewhere (a wheel in
    a project of its own) the copy the extension carries, unpacked into RECON_CACHE."""
    code = "import recon_rgbd; e = recon_rgbd.Engine(weights='random'); print(e.random_weights, e.model)"
    env = {**os.environ, "RECON_CACHE": str(tmp_path / "cache")}
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("True Random"), r.stdout
    # recon-core carries the architecture files and unpacks them under RECON_CACHE.
    unpacked = list((tmp_path / "cache").glob("**/recgen-tiny.json"))
    assert len(unpacked) == 1 and unpacked[0].read_bytes() == TINY.read_bytes(), unpacked


def test_module_help_version_and_errors(tmp_path, recon_cli):
    r = run_module("--help")
    assert r.returncode == 0 and "python -m recon_rgbd" in r.stdout
    for cmd in ("infer", "scene", "serve", "synth", "eval", "weights"):
        assert re.search(rf"^\s+{cmd}\s", r.stdout, re.M), (cmd, r.stdout)
    r = run_module("--version")
    assert r.returncode == 0 and r.stdout.split() == ["python", "-m", "recon_rgbd", recon_rgbd.__version__]
    assert run_module("bench").returncode == 2  # not carried by the wheel
    r = run_module("infer", "--rgbd", "x.png")
    assert r.returncode == 2 and "--masks" in r.stderr
    # A runtime error: the binary's message and exit status.
    args = ["infer", "--rgbd", tmp_path / "none-color.png", "--masks", tmp_path / "none-label.png"]
    r, cli = run_module(*args), subprocess.run([str(recon_cli), *map(str, args)], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == cli.returncode == 1
    # (The first line: a backtrace may follow where RUST_BACKTRACE is set, with other frames.)
    assert r.stderr.startswith("Error: ") and "none-color.png" in r.stderr
    assert r.stderr.split("\n")[0] == cli.stderr.split("\n")[0]


def test_module_infer_and_scene_write_the_cli_folders(synth_ds, recon_cli, tmp_path):
    f = recon_rgbd.dataset_frames(synth_ds)[0]
    cli_infer(recon_cli, f, tmp_path / "cli")
    r = run_module("infer", "--rgbd", f["rgb"], "--masks", *f["masks"], "--out", tmp_path / "py", *cli_flags())
    assert r.returncode in (0, 3), r.stderr
    assert_same_output(tmp_path / "cli", tmp_path / "py")
    r = run_module("scene", "--input", tmp_path / "py", "--out", tmp_path / "sim", "--json")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "sim/scene.json").is_file() and json.loads(r.stdout)


def test_module_infer_random_weights_outside_a_checkout(synth_ds, tmp_path):
    """`--weights random` without `--config`, from a folder without models/: the architecture
    file the extension carries, as for `Engine(weights="random")`."""
    f = recon_rgbd.dataset_frames(synth_ds)[0]
    r = run_module("infer", "--rgbd", f["rgb"], "--masks", *f["masks"], "--out", tmp_path / "out", "--weights", "random", *cli_flags(), cwd=tmp_path)
    assert r.returncode in (0, 3), r.stderr
    index = json.loads((tmp_path / "out" / recon_rgbd.OUTPUT_MARKER).read_text())
    assert index["objects"] and "RANDOM" in r.stderr, r.stderr


def test_module_serve_answers_and_stops_on_ctrl_c(tmp_path):
    log = open(tmp_path / "serve.log", "wb")
    p = subprocess.Popen(
        [sys.executable, "-m", "recon_rgbd", "serve", "--bind", "127.0.0.1:0", "--data-dir", str(tmp_path / "jobs"),
         "--weights", "random", "--config", str(TINY)],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=log,
    )  # fmt: skip
    try:
        line = p.stdout.readline().decode()
        assert line.startswith("recon serve: listening on http://"), (line, (tmp_path / "serve.log").read_text())
        url = line.strip().rsplit(" ", 1)[1]
        with urllib.request.urlopen(f"{url}/health", timeout=30) as h:
            assert h.status == 200
        # Ctrl-C stops it as it stops the binary (a graceful shutdown, exit status 0).
        p.send_signal(signal.SIGINT)
        assert p.wait(timeout=60) == 0, (tmp_path / "serve.log").read_text()
    finally:
        if p.poll() is None:
            p.kill()
        log.close()
