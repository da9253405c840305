"""Inputs in the forms people hold them: numpy arrays of any layout and of dtypes that
convert without loss, PIL images, torch tensors and DLPack producers give the same objects
as the plain uint8 / uint16 arrays; lossy conversions are refused, naming the argument."""

import numpy as np
import pytest

import recon_rgbd
from conftest import REPO

TINY = REPO / "models/recgen-tiny.json"
OPTS = {"seed": 7, "steps": 2, "max_faces": 2000}


@pytest.fixture(scope="module")
def tiny():
    return recon_rgbd.Engine(weights="random", config=TINY)


@pytest.fixture(scope="module")
def frame(synth_ds):
    f = recon_rgbd.dataset_frames(synth_ds)[0]
    fr = recon_rgbd.load_frame(f["rgb"])
    ids = np.zeros(fr["rgb"].shape[:2], np.uint16)
    for i, m in enumerate(recon_rgbd.load_masks(f["masks"])["objects"]):
        ids[m["mask"]] = i + 1
    # The frame's depth back in millimetre units, as a sensor gives it.
    depth_mm = np.rint(fr["depth"] * 1000).astype(np.uint16)
    return fr["rgb"], depth_mm, fr["K"], ids


@pytest.fixture(scope="module")
def reference(tiny, frame):
    rgb, depth, K, ids = frame
    objs = tiny.reconstruct(rgb, depth, K, ids, **OPTS)
    assert objs, "no object reconstructed: nothing to compare"
    return objs


def same(objs, ref, what=""):
    assert [o.label for o in objs] == [o.label for o in ref], what
    for o, r in zip(objs, ref):
        assert np.array_equal(o.pose, r.pose) and o.scale == r.scale, what
        assert np.array_equal(o.mesh.vertices, r.mesh.vertices), what


def test_layouts_and_lossless_dtypes_give_the_same_objects(tiny, frame, reference):
    rgb, depth, K, ids = frame
    variants = {
        "fortran order": (np.asfortranarray(rgb), np.asfortranarray(depth)),
        "strided views": (np.ascontiguousarray(rgb[:, ::-1])[:, ::-1], np.ascontiguousarray(depth[::-1])[::-1]),
        "int64 rgb in 0..255": (rgb.astype(np.int64), depth),
        "float rgb in [0, 1]": (rgb.astype(np.float32) / 255, depth),
        "float64 rgb in [0, 1]": (rgb / 255.0, depth),
    }
    for name, (r, d) in variants.items():
        if name == "strided views":
            assert not r.flags.c_contiguous and not d.flags.c_contiguous
        same(tiny.reconstruct(r, d, K, ids, **OPTS), reference, name)
    # Integer depth of another width: the unit must be given, then it is the same depth.
    same(tiny.reconstruct(rgb, depth.astype(np.int32), K, ids, depth_scale=0.001, **OPTS), reference)


def test_lossy_conversions_are_refused_naming_the_argument(tiny, frame):
    rgb, depth, K, ids = frame
    with pytest.raises(recon_rgbd.InputError, match=r"rgb: float32 colour must be finite and in \[0, 1\] \(got [\d.]+\.\.1\.866"):
        tiny.reconstruct(rgb.astype(np.float32) / 127.5, depth, K, ids)
    with pytest.raises(recon_rgbd.InputError, match=r"rgb: float64 colour must be finite and in \[0, 1\] \(it holds NaN"):
        tiny.reconstruct(np.full(rgb.shape, np.nan), depth, K, ids)
    with pytest.raises(recon_rgbd.InputError, match=r"rgb: uint16 values \d+\.\.\d+ do not fit 8-bit colour without loss"):
        tiny.reconstruct(rgb.astype(np.uint16) * 4, depth, K, ids)
    with pytest.raises(recon_rgbd.InputError, match="depth: int32 depth has no known unit: pass depth_scale"):
        tiny.reconstruct(rgb, depth.astype(np.int32), K, ids)
    with pytest.raises(recon_rgbd.InputError, match="depth: negative depth values"):
        tiny.reconstruct(rgb, depth.astype(np.int32) - 5000, K, ids, depth_scale=0.001)
    with pytest.raises(recon_rgbd.InputError, match="rgb: expected an H×W×3 uint8 array .* got dtype complex128"):
        tiny.reconstruct(rgb.astype(complex), depth, K, ids)
    # The second view's arrays are checked the same way, named as that view's.
    with pytest.raises(recon_rgbd.InputError, match=r"view2 array> rgb: float32 colour"):
        view2 = {"rgb": rgb.astype(np.float32) * 2, "depth": depth, "K": K, "masks": ids, "T_c1_c2": np.eye(4)}
        tiny.reconstruct(rgb, depth, K, ids, view2=view2)


class DLPackOnly:
    """A producer that offers DLPack only (as cupy/jax arrays on the CPU do)."""

    def __init__(self, a):
        self.a = a

    def __dlpack__(self, **kw):
        return self.a.__dlpack__(**kw)

    def __dlpack_device__(self):
        return self.a.__dlpack_device__()


def test_dlpack_producers(tiny, frame, reference):
    rgb, depth, K, ids = frame
    same(tiny.reconstruct(DLPackOnly(rgb), DLPackOnly(depth), K, ids, **OPTS), reference)


def test_torch_tensors(tiny, frame, reference):
    torch = pytest.importorskip("torch")
    rgb, depth, K, ids = frame
    same(tiny.reconstruct(torch.from_numpy(rgb), torch.from_numpy(depth.astype(np.int32)), K, ids, depth_scale=0.001, **OPTS), reference)
    same(tiny.reconstruct(torch.from_numpy(rgb).float() / 255, torch.from_numpy(depth * 0.001).float(), K, ids, **OPTS), reference)


def test_pil_images(tiny, frame, reference):
    Image = pytest.importorskip("PIL.Image")
    rgb, depth, K, ids = frame
    same(tiny.reconstruct(Image.fromarray(rgb), Image.fromarray(depth), K, ids, **OPTS), reference)
