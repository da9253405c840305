"""The Python API: arrays in and out, errors, threads, and the same results as the CLI."""

import json
import threading
from pathlib import Path

import numpy as np
import pytest

import recon_rgbd
from conftest import INFER, REPO, assert_same_output, cli_infer, run_cli


def frame0(ds):
    return recon_rgbd.dataset_frames(ds)[0]


def test_error_hierarchy_and_messages(tmp_path):
    for cls in (recon_rgbd.InputError, recon_rgbd.WeightsError, recon_rgbd.ConfigError):
        assert issubclass(cls, recon_rgbd.ReconError) and issubclass(cls, Exception)
    with pytest.raises(recon_rgbd.WeightsError, match="/no/such/weights"):
        recon_rgbd.Engine(weights="/no/such/weights")
    with pytest.raises(recon_rgbd.ConfigError, match="dtype"):
        recon_rgbd.Engine(dtype="f8")
    (tmp_path / "a-color.png").write_bytes(b"not a png")
    with pytest.raises(recon_rgbd.InputError, match="a-color.png"):
        recon_rgbd.load_frame(tmp_path / "a-color.png")


def test_bad_arrays_are_input_and_config_errors(engine):
    rgb = np.zeros((12, 16, 3), np.uint8)
    depth = np.ones((12, 16), np.float32)
    K = np.array([[100.0, 0, 8], [0, 100, 6], [0, 0, 1]])
    ids = np.zeros((12, 16), np.uint16)
    # Float colour converts only from [0, 1] (test_inputs.py has the conversions).
    with pytest.raises(recon_rgbd.InputError, match=r"rgb: float32 colour must be finite and in \[0, 1\]"):
        engine.reconstruct(rgb.astype(np.float32) + 2, depth, K, ids)
    with pytest.raises(recon_rgbd.InputError, match="registered"):
        engine.reconstruct(rgb, depth[:5], K, ids)
    with pytest.raises(recon_rgbd.InputError, match="3×3"):
        engine.reconstruct(rgb, depth, K[:2], ids)
    with pytest.raises(recon_rgbd.ConfigError, match="cross"):
        engine.reconstruct(rgb, depth, K, ids, select="best")
    with pytest.raises(recon_rgbd.ConfigError, match="samples"):
        engine.reconstruct(rgb, depth, K, ids, samples=0)
    with pytest.raises(recon_rgbd.ConfigError, match="depth_scale"):
        engine.reconstruct(rgb, depth, K, ids, depth_scale=0.001)
    # No object in the mask: nothing to reconstruct, not an error.
    assert engine.reconstruct(rgb, depth, K, ids) == []


def test_options_have_one_name_and_default_everywhere(engine, recon_cli):
    """The per-frame options are the library's (`recon_rgbd.infer_defaults()`): the stub's
    keywords and `recon infer --help`'s flags have the same names and defaults, and an
    unknown keyword is an error naming the valid ones."""
    import ast

    defaults = recon_rgbd.infer_defaults()
    assert defaults["seed"] == 42 and defaults["samples"] == 1 and defaults["steps"] is None
    stub = ast.parse((REPO / "python/recon_rgbd/__init__.pyi").read_text())
    funcs = {
        n.name: {a.arg: ast.literal_eval(d) for a, d in zip(n.args.kwonlyargs, n.args.kw_defaults) if d is not None}
        for n in ast.walk(stub)
        if isinstance(n, ast.FunctionDef) and n.name in ("reconstruct", "reconstruct_files", "eval")
    }
    assert set(funcs) == {"reconstruct", "reconstruct_files", "eval"}
    for name, keywords in funcs.items():
        for k, v in defaults.items():
            # A pair (clamp_range) is a tuple in the stub, a list from JSON.
            assert k in keywords and keywords[k] == (tuple(v) if isinstance(v, list) else v), (name, k, keywords.get(k), v)
    help = run_cli(recon_cli, "infer", "--help").stdout

    def shown(v):  # as clap prints a default: true, -2,3
        return str(v).lower() if isinstance(v, bool) else ",".join(f"{x:g}" for x in v) if isinstance(v, list) else v

    for k, v in defaults.items():
        block = help.split("      --" + k.replace("_", "-") + " <")[1].split("\n      -")[0]
        assert (f"[default: {shown(v)}]" in block) if v is not None else ("[default:" not in block), (k, block)
    rgb, depth = np.zeros((12, 16, 3), np.uint8), np.ones((12, 16), np.float32)
    K, ids = np.array([[100.0, 0, 8], [0, 100, 6], [0, 0, 1]]), np.zeros((12, 16), np.uint16)
    with pytest.raises(recon_rgbd.ConfigError, match="unknown option `sample`.*samples"):
        engine.reconstruct(rgb, depth, K, ids, sample=2)
    with pytest.raises(recon_rgbd.ConfigError, match="min_component_area: must be in"):
        engine.reconstruct(rgb, depth, K, ids, min_component_area=1.0)


def test_load_frame_follows_the_bop_layout(synth_ds):
    f = frame0(synth_ds)
    fr = recon_rgbd.load_frame(f["rgb"])
    assert fr["rgb"].shape == (120, 160, 3) and fr["rgb"].dtype == np.uint8
    assert fr["depth"].shape == (120, 160) and fr["depth"].dtype == np.float32
    cam = json.loads((Path(f["rgb"]).parents[1] / "scene_camera.json").read_text())["0"]
    assert np.allclose(fr["K"].ravel(), cam["cam_K"])
    assert fr["depth_scale"] == pytest.approx(cam["depth_scale"] / 1000)
    assert "scene_camera.json" in fr["intrinsics_source"]
    assert np.nanmax(fr["depth"]) > 0.1


def test_arrays_give_the_cli_meshes_and_poses(synth_ds, engine, recon_cli, tmp_path):
    """reconstruct() on load_frame's arrays = `recon infer` on the files, bit for bit."""
    f = frame0(synth_ds)
    cli_infer(recon_cli, f, tmp_path / "cli")
    fr = recon_rgbd.load_frame(f["rgb"])
    masks = frame_masks(f)
    objs = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, **INFER)
    index = json.loads((tmp_path / "cli" / recon_rgbd.OUTPUT_MARKER).read_text())
    assert len(objs) == len(index["objects"]) > 0
    for o, w in zip(objs, index["objects"]):
        pose = json.loads((tmp_path / "cli" / Path(w["pose"]).parent.name / "pose.json").read_text())
        assert np.array_equal(o.pose[:3, :3], np.array(pose["rotation"], np.float32).astype(np.float64))
        assert np.array_equal(o.pose[:3, 3], np.array(pose["translation_m"], np.float32).astype(np.float64))
        assert o.scale == np.float32(pose["scale_m"])
        assert o.pose[3].tolist() == [0, 0, 0, 1]
        assert o.score == pose["selection"]["score_m"]
        assert set(o.stage_seconds) == set(recon_rgbd.STAGE_COLUMNS) and o.stage_seconds["total"] > 0
        assert o.mesh.vertices.dtype == np.float32 and o.mesh.vertices.shape[1] == 3
        assert o.mesh.faces.dtype == np.int32 and o.mesh.faces.shape == (pose["faces"], 3)
        assert o.mesh.colors.shape == o.mesh.vertices.shape and 0 <= o.mesh.colors.min() <= o.mesh.colors.max() <= 1
        assert len(o.gaussians) == o.gaussians.means.shape[0] == o.gaussians.opacities.shape[0] > 0
        assert o.gaussians.rotations.shape[1] == 4
        if w["mesh_ply"]:
            o.to_ply(tmp_path / "m.ply")
            o.to_glb(tmp_path / "m.glb")
            o.gaussians_to_ply(tmp_path / "g.ply")
            d = tmp_path / "cli" / Path(w["pose"]).parent.name
            assert (tmp_path / "m.ply").read_bytes() == (d / "mesh.ply").read_bytes()
            assert (tmp_path / "m.glb").read_bytes() == (d / "mesh.glb").read_bytes()
            assert (tmp_path / "g.ply").read_bytes() == (d / "gaussians.ply").read_bytes()


def frame_masks(f):
    """The frame's binary mask files as H×W booleans, read as `recon infer --masks` reads them."""
    got = recon_rgbd.load_masks(f["masks"])
    assert len(f["masks"]) > 1 and not got["skipped"]
    return [m["mask"] for m in got["objects"]]


def test_reconstruct_files_writes_the_cli_folder(synth_ds, engine, recon_cli, tmp_path):
    f = frame0(synth_ds)
    cli_infer(recon_cli, f, tmp_path / "cli")
    s = engine.reconstruct_files(f["rgb"], f["masks"], tmp_path / "py", **INFER)
    assert Path(s["out"]) == tmp_path / "py" and len(s["objects"]) > 0
    assert_same_output(tmp_path / "py", tmp_path / "cli")


def test_views_match_the_cli(synth_ds, engine, recon_cli, tmp_path):
    """Views besides the anchor: arrays (`views=`), view files (`reconstruct_files(views=)`)
    and `recon infer --view` give the same result; with three views the two-view model
    fuses pairs. Bad views are errors naming the view and the field."""
    f = frame0(synth_ds)
    fr = recon_rgbd.load_frame(f["rgb"])
    masks = frame_masks(f)
    Ts = []
    for i, dx in enumerate([0.03, -0.04]):
        T = np.eye(4)
        T[0, 3], T[2, 3] = dx, 0.01 * i
        Ts.append(T)
    files = []
    for i, T in enumerate(Ts):
        p = tmp_path / f"view{i + 2}.json"
        p.write_text(json.dumps({"rgb": f["rgb"], "masks": f["masks"], "T_c1_ci": T.tolist()}))
        files.append(p)
    opts = dict(INFER, fusion="stochastic")
    cli_out = tmp_path / "cli"
    flags = ["--seed", str(opts["seed"]), "--max-faces", str(opts["max_faces"]), "--steps", str(opts["steps"]), "--fusion", "stochastic"]
    views = [a for p in files for a in ("--view", p)]
    run_cli(recon_cli, "infer", "--rgbd", f["rgb"], "--masks", *f["masks"], "--out", cli_out, *views, *flags, ok=(0, 3))
    s = engine.reconstruct_files(f["rgb"], f["masks"], tmp_path / "py", views=files, **opts)
    assert len(s["objects"]) > 0
    assert_same_output(tmp_path / "py", cli_out)
    arrays = [{"rgb": fr["rgb"], "depth": fr["depth"], "K": fr["K"], "masks": masks, "T_c1_ci": T} for T in Ts]
    objs = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, views=arrays, **opts)
    index = json.loads((cli_out / recon_rgbd.OUTPUT_MARKER).read_text())
    assert len(objs) == len(index["objects"])
    for o, w in zip(objs, index["objects"]):
        pose = json.loads((cli_out / Path(w["pose"]).parent.name / "pose.json").read_text())
        assert np.array_equal(o.pose[:3, 3], np.array(pose["translation_m"], np.float32).astype(np.float64))
        assert [v["view"] for v in pose["views"]] == [1, 2, 3]
        assert pose["run"]["fusion"] == {"pairs": 2, "ss": "stochastic", "slat": "none"}
    # A view dict of paths is a view file's content.
    d = engine.reconstruct_files(f["rgb"], f["masks"], tmp_path / "dict", views=[files[0], json.loads(files[1].read_text())], **opts)
    assert_same_output(tmp_path / "dict", cli_out)
    assert d["objects"]

    bad = dict(arrays[1], T_c1_ci=np.zeros((4, 4)))
    with pytest.raises(recon_rgbd.InputError, match=r"views\[1\].*T_c1_ci"):
        engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, views=[arrays[0], bad], **opts)
    with pytest.raises(recon_rgbd.InputError, match=r"views\[0\].*missing key `depth`"):
        engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, views=[{"rgb": fr["rgb"]}], **opts)
    with pytest.raises(recon_rgbd.InputError, match="16"):
        engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, views=[arrays[0]] * 17, **opts)
    with pytest.raises(recon_rgbd.InputError, match=r"views\[0\].*`T_c1_ci`"):
        engine.reconstruct_files(f["rgb"], f["masks"], tmp_path / "x", views=[{"rgb": f["rgb"], "masks": f["masks"]}], **opts)
    with pytest.raises(recon_rgbd.ConfigError, match="fusion"):
        engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, views=arrays, fusion="mean")


def test_one_engine_serves_several_threads(synth_ds, engine):
    f = frame0(synth_ds)
    fr = recon_rgbd.load_frame(f["rgb"])
    masks = frame_masks(f)
    ref = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, **INFER)
    got = [None] * 3

    def work(i):
        got[i] = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, **INFER)

    ts = [threading.Thread(target=work, args=(i,)) for i in range(3)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    for g in got:
        assert [o.pose.tolist() for o in g] == [o.pose.tolist() for o in ref]
        assert all(np.array_equal(a.mesh.vertices, b.mesh.vertices) for a, b in zip(g, ref))


def test_keep_freed_memory_applies_and_changes_no_result(synth_ds, engine):
    import platform
    import sys

    f = frame0(synth_ds)
    fr = recon_rgbd.load_frame(f["rgb"])
    masks = frame_masks(f)
    ref = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, **INFER)
    kept = recon_rgbd.keep_freed_memory()
    if sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc":
        assert kept is True
    got = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, **INFER)
    assert [o.pose.tolist() for o in got] == [o.pose.tolist() for o in ref]
    assert all(np.array_equal(a.mesh.vertices, b.mesh.vertices) for a, b in zip(got, ref))


def test_progress_events_and_trimesh(synth_ds, engine):
    f = frame0(synth_ds)
    fr = recon_rgbd.load_frame(f["rgb"])
    events = []
    objs = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], frame_masks(f), progress=events.append, **INFER)
    assert objs
    kinds = {e["event"] for e in events}
    assert {"object", "stage", "object_done"} <= kinds
    trimesh = pytest.importorskip("trimesh")
    if objs[0].mesh is not None:
        tm = objs[0].to_trimesh()
        assert isinstance(tm, trimesh.Trimesh)
        assert np.array_equal(np.asarray(tm.vertices, np.float32), objs[0].mesh.vertices)
        assert tm.visual.vertex_colors.shape == (len(objs[0].mesh.vertices), 4)


def test_synth_eval_and_audit_match_the_cli(synth_ds, recon_cli, tmp_path):
    run_cli(recon_cli, "synth", "--out", tmp_path / "cli", "--scenes", 3, "--seed", 3, "--width", 160, "--height", 120)
    a = sorted(p.relative_to(synth_ds) for p in synth_ds.rglob("*") if p.is_file())
    b = sorted(p.relative_to(tmp_path / "cli") for p in (tmp_path / "cli").rglob("*") if p.is_file())
    assert a == b
    for p in a:
        assert (synth_ds / p).read_bytes() == (tmp_path / "cli" / p).read_bytes(), p

    rep = recon_rgbd.eval(synth_ds, method="observed", out=tmp_path / "ev")
    run_cli(recon_cli, "eval", "--dataset", synth_ds, "--method", "observed", "--out", tmp_path / "ev_cli")
    cli_rep = json.loads((tmp_path / "ev_cli" / "report.json").read_text())
    assert rep["objects"] and [o for o in rep["objects"]] == cli_rep["objects"]
    with pytest.raises(recon_rgbd.ConfigError, match="method"):
        recon_rgbd.eval(synth_ds, method="oracle", out=tmp_path / "ev2")

    aud = recon_rgbd.audit_depth(synth_ds, max_pixels=200, out=tmp_path / "au")
    assert isinstance(aud, dict) and (tmp_path / "au" / "report.json").is_file()
    with pytest.raises(recon_rgbd.ConfigError, match="alpha"):
        recon_rgbd.audit_depth(synth_ds, alpha=2.0)


def strip_names(objects):
    """Scene summaries without what names the objects or their input files."""
    return [{k: v for k, v in o.items() if k not in ("name", "mesh")} for o in objects]


def glb_without_names(path):
    """A GLB's JSON chunk without the `name` fields (scene.glb names each object's node,
    and in-memory objects are named differently from an infer folder's), and its binary chunk."""
    import struct

    data = path.read_bytes()
    assert data[:4] == b"glTF"
    n = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20 : 20 + n])

    def drop(v):
        if isinstance(v, dict):
            return {k: drop(x) for k, x in v.items() if k != "name"}
        if isinstance(v, list):
            return [drop(x) for x in v]
        return v

    return drop(doc), data[20 + n :]


def test_scene_from_objects_equals_scene_from_their_folder(synth_ds, engine, recon_cli, tmp_path):
    """recon_rgbd.scene on Engine.reconstruct's objects + the frame settles and exports exactly
    what `recon scene` makes of the same objects' `recon infer` folder."""
    f = frame0(synth_ds)
    engine.reconstruct_files(f["rgb"], f["masks"], tmp_path / "inf", **INFER)
    run_cli(recon_cli, "scene", "--input", tmp_path / "inf", "--frame", f["rgb"], "--out", tmp_path / "cli", "--collision", "hull")
    folder = recon_rgbd.scene(tmp_path / "inf", f["rgb"], tmp_path / "sim", collision="hull")
    fr = recon_rgbd.load_frame(f["rgb"])
    objs = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], frame_masks(f), **INFER)
    mem = recon_rgbd.scene(objs, fr, tmp_path / "mem", collision="hull")
    assert Path(mem["out"]) == tmp_path / "mem" and len(mem["objects"]) == len(folder["objects"]) > 0
    assert all(o["physics"]["mass_kg"] > 0 for o in mem["objects"])
    assert strip_names(mem["objects"]) == strip_names(folder["objects"])
    assert mem["settle"] == folder["settle"] and mem["support_plane"] == folder["support_plane"]
    for name in ("scene.glb", "scene.json"):
        if name == "scene.json":
            strip = lambda p: strip_names(json.loads(p.read_text())["objects"])
            assert strip(tmp_path / "mem" / name) == strip(tmp_path / "cli" / name)
        else:
            assert glb_without_names(tmp_path / "mem" / name) == glb_without_names(tmp_path / "cli" / name)
    assert (tmp_path / "mem" / mem["files"]["urdf_scene"]).is_file()
    assert "<in memory: objects[0]" in (tmp_path / "mem" / "scene.input.json").read_text()

    # The CLI's scene options pass through: a settle time below the 0.1 s minimum
    # cannot come to rest and stops after fewer steps.
    short = recon_rgbd.scene(objs, f["rgb"], tmp_path / "short", collision="hull", settle_time=0.05)
    assert not short["settle"]["at_rest"] and short["settle"]["steps"] < mem["settle"]["steps"]
    with pytest.raises(recon_rgbd.ConfigError, match="collision"):
        recon_rgbd.scene(objs, fr, tmp_path / "x", collision="spheres")
    with pytest.raises(recon_rgbd.InputError, match="frame"):
        recon_rgbd.scene(objs, None, tmp_path / "x")
    with pytest.raises(recon_rgbd.ConfigError, match="variations"):
        recon_rgbd.scene(objs, fr, tmp_path / "x", spec={"version": 1})


def test_scene_variations_match_the_cli(synth_ds, engine, recon_cli, tmp_path):
    """variations=N with a spec dict = `recon scene --variations N --seed S --spec file`."""
    f = frame0(synth_ds)
    engine.reconstruct_files(f["rgb"], f["masks"], tmp_path / "inf", **INFER)
    spec = {"version": 1, "sampled_predicates": 1}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    # Convex decomposition (the default): with one hull, an object of the random tiny model can
    # still creep ~1.5 mm per 0.5 s at the 5 s settle limit, so no variant is kept.
    common = ["--collision", "convex", "--variations", 2, "--seed", 5]
    run_cli(recon_cli, "scene", "--input", tmp_path / "inf", "--frame", f["rgb"], "--out", tmp_path / "cli", *common,
            "--spec", tmp_path / "spec.json", ok=(0, 1))
    r = recon_rgbd.scene(tmp_path / "inf", f["rgb"], tmp_path / "py", collision="convex", variations=2, seed=5, spec=spec)
    assert r["manifest"]["requested"] == 2 and r["manifest"]["seed"] == 5
    a = sorted(p.relative_to(tmp_path / "py") for p in (tmp_path / "py").rglob("*") if p.is_file())
    b = sorted(p.relative_to(tmp_path / "cli") for p in (tmp_path / "cli").rglob("*") if p.is_file())
    assert a == b and any(p.name == "scene.urdf" for p in a)
    for p in a:
        assert (tmp_path / "py" / p).read_bytes() == (tmp_path / "cli" / p).read_bytes(), p
    with pytest.raises(recon_rgbd.ConfigError, match="version"):
        recon_rgbd.scene(tmp_path / "inf", f["rgb"], tmp_path / "bad", variations=1, spec={"predicates": []})


def test_eval_recgen_takes_the_cli_model_flags(synth_ds, engine, recon_cli, tmp_path):
    """recon_rgbd.eval(method="recgen", steps=…) = `recon eval --method recgen --steps …`, and
    the flag changes the result as it does in the CLI."""
    flags = {"scenes": ["1"], "max_faces": 2000, "seed": 7}
    run_cli(recon_cli, "eval", "--dataset", synth_ds, "--method", "recgen", "--scenes", "1", "--max-faces", 2000,
            "--seed", 7, "--steps", 3, "--out", tmp_path / "cli3")
    cli3 = json.loads((tmp_path / "cli3" / "report.json").read_text())
    py3 = recon_rgbd.eval(synth_ds, method="recgen", out=tmp_path / "py3", steps=3, **flags)
    py2 = recon_rgbd.eval(synth_ds, method="recgen", engine=engine, out=tmp_path / "py2", steps=2, **flags)
    assert py3["objects"] and py3["objects"] == cli3["objects"]
    assert (tmp_path / "py3" / "predictions.json").read_bytes() == (tmp_path / "cli3" / "predictions.json").read_bytes()
    assert [o for o in py2["objects"]] != py3["objects"]
    with pytest.raises(recon_rgbd.ConfigError, match="min_component_area"):
        recon_rgbd.eval(synth_ds, method="recgen", engine=engine, out=tmp_path / "x", min_component_area=1.5)
    with pytest.raises(recon_rgbd.ConfigError, match="not both"):
        recon_rgbd.eval(synth_ds, method="recgen", engine=engine, weights="random", out=tmp_path / "x")
    with pytest.raises(recon_rgbd.ConfigError, match="two_view"):
        recon_rgbd.eval(synth_ds, method="observed", two_view=True, out=tmp_path / "x")
