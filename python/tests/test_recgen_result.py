"""RecGen's result on `recon_rgbd.Object` (issue 36 §4): the fields `recgen_inference.generate`
returns, consistent with each other and with recon's own pose and assets, and `save(dir)`
writing exactly the files `recon infer` writes beside pose.json; and RecGen's
preprocessing keywords (§6)."""

import json
from pathlib import Path

import numpy as np
import pytest

import recon_rgbd
from conftest import INFER, cli_flags, run_cli

RECGEN_FILES = ["mesh.obj", "posed_mesh.obj", "gaussian.ply", "posed_gaussian.ply", "overlay.png", "metadata.json"]


def frame_and_masks(ds):
    f = recon_rgbd.dataset_frames(ds)[0]
    masks = [m["mask"] for m in recon_rgbd.load_masks(f["masks"])["objects"]]
    return f, recon_rgbd.load_frame(f["rgb"]), masks


def scipy_matrix(q):
    """scipy's Rotation.from_quat([x, y, z, w]).as_matrix(), written out."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_objects_carry_recgens_fields_and_save_its_files(synth_ds, engine, recon_cli, tmp_path):
    f, fr, masks = frame_and_masks(synth_ds)
    objs = engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, **INFER)
    run_cli(recon_cli, "infer", "--rgbd", f["rgb"], "--masks", *f["masks"], "--out", tmp_path / "cli", "--recgen-files", *cli_flags(), ok=(0, 3))
    index = json.loads((tmp_path / "cli" / recon_rgbd.OUTPUT_MARKER).read_text())
    assert len(objs) == len(index["objects"]) > 0
    for o, w in zip(objs, index["objects"]):
        # The camera-frame map: recon's pose with its scale, and RecGen's inv(cam2ncam) @ pose_matrix.
        cam = o.pose.copy()
        cam[:3, :3] *= o.scale
        assert np.allclose(np.linalg.inv(o.cam2ncam) @ o.pose_matrix, cam, atol=1e-6)
        place = lambda p: p.astype(np.float64) @ cam[:3, :3].T + cam[:3, 3]  # noqa: E731
        assert np.allclose(place(o.raw_mesh.vertices), o.mesh.vertices, atol=1e-5)
        assert np.array_equal(o.raw_mesh.faces, o.mesh.faces)
        assert np.allclose(place(o.raw_gaussians.means), o.gaussians.means, atol=1e-5)
        assert np.abs(o.raw_mesh.vertices).max() <= 1.0, "the object frame is the canonical cube"
        # pose_quat = translation, then the quaternion in scipy's order (w last).
        p = o.parsed_pose
        assert set(p) == {"quaternion", "translation", "scale", "rotation_matrix"}
        assert np.allclose(scipy_matrix(o.pose_quat[3:]), p["rotation_matrix"], atol=1e-5)
        assert np.array_equal(o.pose_quat[3:], p["quaternion"]) and p["quaternion"][3] >= 0
        assert np.array_equal(o.pose_quat[:3], p["translation"]) and np.array_equal(o.pose_matrix[:3, 3], p["translation"])
        assert np.allclose(o.pose_matrix[:3, :3], p["scale"] * p["rotation_matrix"], rtol=0, atol=1e-12)
        assert o.pose_representation == "6d_translation_scale"
        assert o.rgb.dtype == np.uint8 and np.array_equal(o.rgb, fr["rgb"])
        assert o.intrinsics.shape == (3, 3) and np.allclose(o.intrinsics, fr["K"])
        # save(dir): the files `recon infer` writes beside pose.json, byte for byte.
        mine = tmp_path / "py" / o.label
        o.save(mine)
        cli = tmp_path / "cli" / Path(w["pose"]).parent.name
        assert sorted(p.name for p in mine.iterdir()) == sorted(RECGEN_FILES)
        for n in RECGEN_FILES:
            assert (mine / n).read_bytes() == (cli / n).read_bytes(), n
        meta = json.loads((mine / "metadata.json").read_text())
        assert list(meta) == ["pose_matrix", "pose_quat", "pose", "cam2ncam", "pose_representation", "intrinsics"]
        assert np.allclose(meta["pose_quat"], o.pose_quat) and np.allclose(meta["cam2ncam"], o.cam2ncam)
    objs[0].save(tmp_path / "no-splat", save_splat=False)
    no_splat = sorted(set(RECGEN_FILES) - {"gaussian.ply", "posed_gaussian.ply"})
    assert sorted(p.name for p in (tmp_path / "no-splat").iterdir()) == no_splat


def test_preprocessing_keywords_are_checked_and_used(synth_ds, engine):
    _, fr, masks = frame_and_masks(synth_ds)
    run = lambda **kw: {o.label: o for o in engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, **INFER, **kw)}  # noqa: E731
    for kw, name in [
        ({"quantile_drop_threshold": 0.5}, "quantile_drop_threshold: must be in"),
        ({"clamp_range": (3.0, -2.0)}, "clamp_range: must be two finite numbers"),
        ({"clamp_range": (1.0,)}, "clamp_range"),
        ({"mask_erosion_kernel_size": 0}, "mask_erosion_kernel_size: must be in"),
        ({"mask_erosion_iterations": 1000}, "mask_erosion_iterations: must be in"),
        ({"use_pointmap": "no"}, "use_pointmap"),
    ]:
        with pytest.raises(recon_rgbd.ConfigError, match=name):
            run(**kw)
    base = run()
    assert base and all("use_pointmap" not in o.details["run"] for o in base.values())
    off = run(use_pointmap=False)
    assert off and all(o.details["run"]["use_pointmap"] is False for o in off.values())
    # Without erosion more of each mask's pixels enter the point statistics.
    wide = run(mask_erosion_enabled=False)
    points = lambda o: o.details["views"][0]["observed_points"]  # noqa: E731
    assert set(base) <= set(wide) and all(points(wide[k]) > points(o) for k, o in base.items())


def test_posthoc_color_is_recorded_applied_and_saved(synth_ds, engine, tmp_path):
    """§5: `posthoc_color=` calibrates the Gaussians' colours against the photo, records
    upstream's fields on the object, and `save` writes them as posthoc_color.json."""
    _, fr, masks = frame_and_masks(synth_ds)
    run = lambda **kw: {o.label: o for o in engine.reconstruct(fr["rgb"], fr["depth"], fr["K"], masks, **INFER, **kw)}  # noqa: E731
    with pytest.raises(recon_rgbd.ConfigError, match="posthoc_color"):
        run(posthoc_color="gama")
    plain, cal = run(), run(posthoc_color="gamma_affine")
    assert set(cal) == set(plain) and plain and all(o.posthoc_color is None for o in plain.values())
    for k, o in cal.items():
        r = o.posthoc_color
        assert r["variant"] == "gamma_affine" and set(r) == {"variant", "transform", "stats", "applied_to"}, r
        # Geometry is untouched; colours change only when a transform passed the gates.
        assert np.array_equal(o.gaussians.means, plain[k].gaussians.means)
        if r["transform"] is None:
            assert r["stats"]["reason"] and r["applied_to"] == []
            assert np.array_equal(o.gaussians.dc, plain[k].gaussians.dc)
        else:
            assert r["transform"]["type"] == "gamma_affine" and "gaussians" in r["applied_to"]
            assert r["stats"]["l1_after"] < r["stats"]["l1_before"]
            assert not np.array_equal(o.gaussians.dc, plain[k].gaussians.dc)
        o.save(tmp_path / k)
        assert json.loads((tmp_path / k / "posthoc_color.json").read_text()) == r
        # Without the calibration, save writes no such file.
        plain[k].save(tmp_path / f"{k}-plain")
        assert not (tmp_path / f"{k}-plain" / "posthoc_color.json").exists()
