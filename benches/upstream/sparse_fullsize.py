#!/usr/bin/env python3
"""Upstream's stage-2 sparse modules at full size on a CPU, saved the way they are released,
with upstream's outputs in float32 and float64 (issue 36 §1).

    python3 benches/upstream/sparse_fullsize.py --save /tmp/sparse --trellis /path/to/TRELLIS \\
        --recgen /path/to/recgen --modules slat_flow,slat_dec_gs
    RECON_UPSTREAM_SPARSE_DIR=/tmp/sparse cargo test --release --test upstream_fullsize -- --ignored

`--tiny` writes the CI fixture (tests/fixtures/upstream_tiny_slat): the same code at small widths.

Nothing of upstream is copied into this repository: TRELLIS (`--trellis`, a microsoft/TRELLIS
checkout) and RecGen (`--recgen`, a TRI-ML/recgen checkout, or its `recgen_modules` package
folder) are imported by path.

`slat_flow`: RecGen's SLatCondFlowModel with models/recgen-large.json's `slat_flow` args (the
release's), random weights (every parameter redrawn, so nothing is trivially zero), stored as
RecGen releases it: `slat_denoiser_ema0.9999_step0075000.pt` (`torch.save(state_dict)`, fp16)
beside `slat_config.json` (`models.denoiser`). One forward on a sphere shell of voxels at 64³,
at t = 750, with the condition built as RecGen builds it for stage 2: DINOv2 patch tokens plus
`encode_pointmap(pointmap)` plus `encode_mask(mask)`, then the `encode_pose(pose)` token
appended. Upstream runs in float32 on the stored fp16 values, and in float64 (`.double()`).

`slat_dec_gs`: TRELLIS's SLatGaussianDecoder with recgen-large.json's `slat_dec_gs` args (the
release's), random weights, stored as TRELLIS-image-large stores it:
`ckpts/slat_dec_gs_swin8_B_64l8gs32_fp16.{json,safetensors}` (fp16, `offset_perturbation`
included). One forward on the same sphere shell (random latents); the out layer's features and
the Gaussians (`_xyz`, `_features_dc`, activated scaling, rotation, opacity) are kept.

How TRELLIS's sparse modules run on a CPU (the recipe of the conformance fixtures):
  * spconv 2.3.8 (the CPU wheel) with SPCONV_ALGO=native, single-threaded (with 2 threads its CPU
    kernels return wrong results above ~500 voxels);
  * a pure-torch stand-in for `xformers.ops.memory_efficient_attention` /
    `fmha.BlockDiagonalMask.from_seqlens` (softmax(qkᵀ/√d)·v per sequence), installed as a
    fake `xformers` module (TRELLIS's sparse attention only supports xformers or flash_attn);
  * spconv's leaf convs in `.train()` so the bias is added after the conv (its CPU kernel
    refuses fused bias in eval mode; the maths is identical).
  * the Gaussian's `device="cuda"` default and its `.cuda()` biases stay on the CPU.
The float64 run needs the code's hard-wired float32 steps lifted: `Tensor.float()` (LayerNorm32,
the RMS norms, SparseTensor.float) keeps float64 tensors as they are, the timestep and position
embeddings' frequency tables are built in float64, the model's `dtype` attribute (which the
forward casts to) is float64, and the Gaussian's biases are computed in float64. Nothing else
changes; the stored weights (fp16 values) are exact in both.

Outputs under --save: the checkpoint files, `sparse_reference.safetensors` (inputs
`input.<module>.*`; outputs `output.<module>.<name>.{f32,f64}`) and `sparse_reference.json`
(versions, counts, timings).
"""
import argparse
import contextlib
import json
import math
import os
import sys
import time
import types

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from harness import module_args, randomize  # noqa: E402  (the same directory)

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
MODULES = ["slat_flow", "slat_dec_gs"]
SLAT_FLOW_PT = "slat_denoiser_ema0.9999_step0075000.pt"
SLAT_FLOW_CONFIG = "slat_config.json"
# RecGen's stage-2 class in the release's slat_config.json.
SLAT_FLOW_CLASS = "ElasticSLatCondFlowModel"
# TRELLIS-image-large's decoder files (ckpts/<stem>.json + .safetensors, fp16) and classes.
SLAT_DEC_GS = ("slat_dec_gs_swin8_B_64l8gs32_fp16", "ElasticSLatGaussianDecoder")


FLOAT32 = None  # torch.Tensor.float as torch defines it (float64_mode replaces it)


def setup_env():
    os.environ["SPCONV_ALGO"] = "native"
    os.environ["SPARSE_BACKEND"] = "spconv"
    os.environ["SPARSE_ATTN_BACKEND"] = "xformers"
    os.environ.setdefault("ATTN_BACKEND", "sdpa")
    for v in ["OMP_NUM_THREADS", "MKL_NUM_THREADS"]:
        os.environ[v] = "1"


def install_fake_xformers():
    """`xformers.ops.memory_efficient_attention` and `fmha.BlockDiagonalMask.from_seqlens`
    in plain torch: softmax(q kᵀ / √d) v, separately for each sequence, in the inputs' dtype."""
    import torch

    class BlockDiagonalMask:
        def __init__(self, q_seqlen, kv_seqlen):
            self.q_seqlen = [int(s) for s in q_seqlen]
            self.kv_seqlen = [int(s) for s in (kv_seqlen if kv_seqlen is not None else q_seqlen)]

        @classmethod
        def from_seqlens(cls, q_seqlen, kv_seqlen=None):
            return cls(q_seqlen, kv_seqlen)

    def attend(q, k, v):
        # [N, H, D] -> [H, N, D]
        q, k, v = (x.transpose(0, 1) for x in (q, k, v))
        w = torch.softmax((q @ k.transpose(1, 2)) / math.sqrt(q.shape[-1]), dim=-1)
        return (w @ v).transpose(0, 1)

    def memory_efficient_attention(q, k, v, attn_bias=None):
        # q, k, v: [B, N, H, D]
        if attn_bias is None:
            return torch.stack([attend(q[b], k[b], v[b]) for b in range(q.shape[0])])
        assert q.shape[0] == 1
        out, qo, ko = [], 0, 0
        for nq, nk in zip(attn_bias.q_seqlen, attn_bias.kv_seqlen):
            out.append(attend(q[0, qo:qo + nq], k[0, ko:ko + nk], v[0, ko:ko + nk]))
            qo, ko = qo + nq, ko + nk
        return torch.cat(out)[None]

    xf = types.ModuleType("xformers")
    ops = types.ModuleType("xformers.ops")
    ops.memory_efficient_attention = memory_efficient_attention
    ops.fmha = types.SimpleNamespace(BlockDiagonalMask=BlockDiagonalMask)
    xf.ops = ops
    sys.modules["xformers"] = xf
    sys.modules["xformers.ops"] = ops


def import_recgen(recgen, trellis):
    """RecGen's stage-2 module from the user's checkout; its relative imports (`..modules`,
    `.sparse_structure_flow`, `.sparse_elastic_mixin`) resolve inside that package."""
    import importlib

    root = os.path.abspath(recgen)
    pkg = next((p for p in [os.path.join(root, "recgen_inference", "recgen_modules"), root]
                if os.path.isfile(os.path.join(p, "models", "structured_latent_cond_flow.py"))), None)
    if pkg is None:
        sys.exit(f"--recgen {recgen}: no recgen_inference/recgen_modules/models/structured_latent_cond_flow.py")
    # Package stubs: the packages' __init__ files pull in pipelines and CUDA-only code.
    for name, path in [("recgen_modules", pkg), ("recgen_modules.models", os.path.join(pkg, "models"))]:
        m = types.ModuleType(name)
        m.__path__ = [path]
        sys.modules[name] = m
    return importlib.import_module("recgen_modules.models.structured_latent_cond_flow")


# Embedder convs N(0, 0.05²) (harness.randomize's default for other weights is N(0, 0.02²)).
EMBEDDER_STD = (("point_embedder", 0.05), ("mask_embedder", 0.05))


def released_fp16(model, seed):
    """`model` randomised, in eval with spconv's leaf convs in train (bias after the conv), and
    rounded to fp16 as released: upstream's reference runs on exactly the stored values.
    Returns the fp16 state dict to save."""
    import torch

    randomize(model, seed, EMBEDDER_STD)
    model.eval()
    spconv_leaves_train(model)
    state = {k: v.detach().to(torch.float16).contiguous() for k, v in model.state_dict().items()}
    model.load_state_dict({k: v.float() for k, v in state.items()})
    return state


def spconv_leaves_train(model):
    import spconv.pytorch as spconv

    for m in model.modules():
        if isinstance(m, spconv.conv.SparseConvolution):
            m.train()


@contextlib.contextmanager
def float64_mode(model):
    """Lift the code's hard-wired float32 steps for the float64 run (see the module doc)."""
    import numpy as np
    import torch

    real_float = torch.Tensor.float

    def keep64(self, *a, **kw):
        return self if self.dtype == torch.float64 else real_float(self, *a, **kw)

    patched = []
    for m in model.modules():
        if hasattr(m, "freqs") and isinstance(m.freqs, torch.Tensor) and hasattr(m, "freq_dim"):
            patched.append((m, m.freqs))
            m.freqs = 1.0 / (10000 ** (torch.arange(m.freq_dim, dtype=torch.float64) / m.freq_dim))
    te = type(model.t_embedder) if hasattr(model, "t_embedder") else None
    real_te = te.__dict__["timestep_embedding"] if te else None

    def timestep_embedding64(t, dim, max_period=10000):
        half = dim // 2
        freqs = torch.exp(-np.log(max_period) * torch.arange(0, half, dtype=torch.float64) / half)
        args = t[:, None].double() * freqs[None]
        emb = torch.cat([torch.cos(args), torch.sin(args)], dim=-1)
        if dim % 2:
            emb = torch.cat([emb, torch.zeros_like(emb[:, :1])], dim=-1)
        return emb

    torch.Tensor.float = keep64
    if te:
        te.timestep_embedding = staticmethod(timestep_embedding64)
    old_dtype = model.dtype
    model.dtype = torch.float64
    try:
        yield
    finally:
        torch.Tensor.float = real_float
        if te:
            te.timestep_embedding = real_te
        model.dtype = old_dtype
        for m, f in patched:
            m.freqs = f


def sphere_shell(res, radius, width):
    """Voxels of a sphere shell centred in the grid, in (x, y, z) order."""
    import torch

    r = torch.arange(res, dtype=torch.float64)
    c = (res - 1) / 2.0
    x, y, z = torch.meshgrid(r, r, r, indexing="ij")
    d = ((x - c) ** 2 + (y - c) ** 2 + (z - c) ** 2).sqrt()
    return ((d - radius).abs() <= width / 2).nonzero().to(torch.int32)


def view_inputs(size, seed):
    """A view as RecGen's stage 2 sees it: layer-normed DINOv2 patch tokens, a normalised point
    map of a sphere seen from the front (zero outside), its mask, and a 9D pose."""
    import torch

    g = torch.Generator().manual_seed(seed)
    n = (size // 14) ** 2
    tokens = torch.randn(1, n, 1024, generator=g)
    u = (torch.arange(size, dtype=torch.float32) + 0.5) / size * 2 - 1
    yy, xx = torch.meshgrid(u, u, indexing="ij")
    rr = xx ** 2 + yy ** 2
    inside = rr < 0.7 ** 2
    zz = torch.sqrt((0.7 ** 2 - rr).clamp(min=0))
    pm = torch.stack([xx, -yy, zz]) * inside
    mask = inside.float()[None, None]
    pose = torch.randn(1, 13, generator=g)
    return tokens, pm[None].contiguous(), mask.contiguous(), pose


def slat_flow(a, out, ref, meta):
    import torch

    mod = import_recgen(a.recgen, a.trellis)
    args = module_args(a.config, "slat_flow")[1]
    if a.tiny:
        args.update(resolution=16, model_channels=32, cond_channels=32, num_blocks=2, num_heads=2,
                    io_block_channels=[16], point_embedder_out_channels=32, mask_embedder_out_channels=32,
                    pose_embedder_out_channels=32)
    ctor = {k: v for k, v in args.items() if k in mod.SLatCondFlowModel.__init__.__code__.co_varnames}
    ctor["use_fp16"] = False
    model = mod.SLatCondFlowModel(**ctor)
    state = released_fp16(model, 21)
    t0 = time.perf_counter()
    torch.save(state, os.path.join(out, SLAT_FLOW_PT))
    saved = dict(args, use_fp16=True)
    with open(os.path.join(out, SLAT_FLOW_CONFIG), "w") as f:
        json.dump({"models": {"denoiser": {"name": SLAT_FLOW_CLASS, "args": saved}},
                   "dataset": {"args": {"normalization": json.load(open(a.config))["slat_normalization"]}}}, f, indent=2)
    print(f"slat_flow: saved {SLAT_FLOW_PT} ({sum(v.numel() for v in state.values()) / 1e6:.1f} M parameters) "
          f"in {time.perf_counter() - t0:.1f} s", flush=True)

    coords = shell_voxels(args["resolution"], a.tiny)
    g = torch.Generator().manual_seed(31)
    feats = torch.randn(len(coords), args["in_channels"], generator=g)
    size = 518 if not a.tiny else 56
    tokens, pm, mask, pose = view_inputs(size, 41)
    if a.tiny:
        tokens = tokens[..., : args["cond_channels"]].contiguous()
    t = torch.tensor([750.0])
    for k, v in [("coords", coords.long()), ("feats", feats), ("t", t), ("patch_tokens", tokens),
                 ("pointmap", pm), ("mask", mask), ("pose", pose)]:
        ref[f"input.slat_flow.{k}"] = v.contiguous()
    sp = mod.sp

    def forward(m, dtype):
        with torch.inference_mode():
            c = tokens.to(dtype) + m.encode_pointmap(pm.to(dtype)) + m.encode_mask(mask.to(dtype))
            c = torch.cat([c, m.encode_pose(pose.to(dtype))], 1)
            x = sp.SparseTensor(feats=feats.to(dtype), coords=coords)
            y = m(x, t.to(dtype), c)
            return c, y

    timings = {}
    for dtype in ["f32", "f64"]:
        t1 = time.perf_counter()
        if dtype == "f32":
            c, y = forward(model, torch.float32)
        else:
            model.double()
            with float64_mode(model):
                c, y = forward(model, torch.float64)
        timings[dtype] = time.perf_counter() - t1
        if not torch.equal(y.coords.cpu(), coords):
            sys.exit("slat_flow: output coords differ from the input's (order changed)")
        print(f"slat_flow {dtype}: upstream forward {timings[dtype]:.1f} s, out {list(y.feats.shape)} {y.feats.dtype}", flush=True)
        ref[f"output.slat_flow.cond.{dtype}"] = c.contiguous()
        ref[f"output.slat_flow.{dtype}"] = y.feats.contiguous()
    for what in ["", "cond."]:
        a32, a64 = ref[f"output.slat_flow.{what}f32"].double(), ref[f"output.slat_flow.{what}f64"]
        d = (a32 - a64).abs()
        print(f"slat_flow {what or 'velocity'}: upstream f32 vs f64: max rel {d.max() / a64.abs().max():.2e} "
              f"mean rel {d.mean() / a64.abs().mean():.2e}", flush=True)
    # Tokens after the ×2 downsample: what the 24 transformer blocks see.
    coarse = len(torch.unique(coords[:, 1:] // 2, dim=0))
    meta["slat_flow"] = {"file": SLAT_FLOW_PT, "config": SLAT_FLOW_CONFIG, "voxels": len(coords), "tokens": coarse,
                         "cond_tokens": int(ref["output.slat_flow.cond.f32"].shape[1]), "seconds": timings,
                         "args": saved}


def stub_missing(name, **attrs):
    """A stand-in for an optional import upstream only uses to read and write files."""
    try:
        __import__(name)
    except ImportError:
        m = types.ModuleType(name)
        for k, v in attrs.items():
            setattr(m, k, v)
        sys.modules[name] = m


def shell_voxels(res, tiny):
    import torch

    coords3 = sphere_shell(res, res * (0.3 if tiny else 0.375), 1.0)
    return torch.cat([torch.zeros(len(coords3), 1, dtype=torch.int32), coords3], 1).contiguous()


def slat_dec_gs(a, out, ref, meta):
    """TRELLIS's SLat Gaussian decoder: the out layer's features and the Gaussians' parameters
    (raw `_xyz` positions, `_features_dc`, and the activated scaling, rotation, opacity)."""
    import torch

    class EasyDict(dict):
        __getattr__ = dict.__getitem__

    stub_missing("easydict", EasyDict=EasyDict)
    stub_missing("plyfile", PlyData=None, PlyElement=None)
    stub_missing("utils3d")
    # FlexiCubes is a git submodule of TRELLIS that the Gaussian decoder does not use; a checkout
    # without it still imports trellis.representations.
    fc = "trellis.representations.mesh.flexicubes"
    if not os.path.isfile(os.path.join(os.path.abspath(a.trellis), *fc.split("."), "flexicubes.py")):
        for name in [fc, fc + ".flexicubes"]:
            m = types.ModuleType(name)
            m.__path__ = []
            m.FlexiCubes = None
            sys.modules[name] = m
    from trellis.models.structured_latent_vae import decoder_gs
    from trellis.modules import sparse as sp
    from trellis.representations.gaussian import gaussian_model

    # Its `device="cuda"` default, on a CPU.
    real_init = gaussian_model.Gaussian.__init__

    def cpu_init(self, *args, **kw):
        kw["device"] = "cpu"
        real_init(self, *args, **kw)

    gaussian_model.Gaussian.__init__ = cpu_init
    real_setup = gaussian_model.Gaussian.setup_functions

    def setup(self):
        # Its biases are `.cuda()` tensors: on a CPU here, and in float64 for the float64 run.
        cuda = torch.Tensor.cuda
        torch.Tensor.cuda = lambda t, *a, **k: t.double() if torch.Tensor.float is not FLOAT32 else t
        try:
            real_setup(self)
        finally:
            torch.Tensor.cuda = cuda
        if torch.Tensor.float is not FLOAT32:
            p = self.init_params
            self.scale_bias = self.inverse_scaling_activation(torch.tensor(p["scaling_bias"], dtype=torch.float64))
            self.opacity_bias = self.inverse_opacity_activation(torch.tensor(p["opacity_bias"], dtype=torch.float64))
            self.aabb = self.aabb.double()

    gaussian_model.Gaussian.setup_functions = setup
    stem, cls = SLAT_DEC_GS
    args = module_args(a.config, "slat_dec_gs")[1]
    if a.tiny:
        args.update(resolution=16, model_channels=64, num_blocks=2, num_heads=4, window_size=8)
        args["representation_config"] = dict(args["representation_config"], num_gaussians=4)
    ctor = {k: v for k, v in args.items() if k in decoder_gs.SLatGaussianDecoder.__init__.__code__.co_varnames}
    ctor["use_fp16"] = False
    model = decoder_gs.SLatGaussianDecoder(**ctor)
    state = released_fp16(model, 22)  # the offset_perturbation buffer included
    from safetensors.torch import save_file

    os.makedirs(os.path.join(out, "ckpts"), exist_ok=True)
    save_file(state, os.path.join(out, "ckpts", stem + ".safetensors"))
    with open(os.path.join(out, "ckpts", stem + ".json"), "w") as f:
        json.dump({"name": cls, "args": dict(args, use_fp16=True)}, f, indent=2)
    print(f"slat_dec_gs: saved ckpts/{stem} ({sum(v.numel() for v in state.values()) / 1e6:.1f} M parameters)", flush=True)

    coords = shell_voxels(args["resolution"], a.tiny)
    g = torch.Generator().manual_seed(32)
    feats = torch.randn(len(coords), args["latent_channels"], generator=g)
    ref["input.slat_dec_gs.coords"] = coords.long()
    ref["input.slat_dec_gs.feats"] = feats
    captured = {}
    model.out_layer.register_forward_hook(lambda m, i, o: captured.__setitem__("feats", o.feats))
    timings = {}
    for dtype in ["f32", "f64"]:
        t1 = time.perf_counter()
        with torch.inference_mode():
            if dtype == "f32":
                reps = model(sp.SparseTensor(feats=feats, coords=coords))
            else:
                model.double()
                with float64_mode(model):
                    reps = model(sp.SparseTensor(feats=feats.double(), coords=coords))
        timings[dtype] = time.perf_counter() - t1
        gs = reps[0]
        outs = {"feats": captured["feats"], "xyz": gs._xyz, "features_dc": gs._features_dc,
                "scaling": gs.get_scaling, "rotation": gs.get_rotation, "opacity": gs.get_opacity}
        for k, v in outs.items():
            ref[f"output.slat_dec_gs.{k}.{dtype}"] = v.detach().reshape(v.shape[0], -1).contiguous()
        print(f"slat_dec_gs {dtype}: upstream forward {timings[dtype]:.1f} s, {gs._xyz.shape[0]} Gaussians", flush=True)
    for k in outs:
        a32, a64 = ref[f"output.slat_dec_gs.{k}.f32"].double(), ref[f"output.slat_dec_gs.{k}.f64"]
        d = (a32 - a64).abs()
        print(f"slat_dec_gs {k}: upstream f32 vs f64: max rel {d.max() / a64.abs().max():.2e} "
              f"mean rel {d.mean() / a64.abs().mean():.2e}", flush=True)
    meta["slat_dec_gs"] = {"file": f"ckpts/{stem}.safetensors", "voxels": len(coords), "seconds": timings}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--save", required=True, help="output folder")
    p.add_argument("--trellis", required=True, help="a microsoft/TRELLIS checkout")
    p.add_argument("--recgen", required=True, help="a TRI-ML/recgen checkout (or its recgen_modules folder)")
    p.add_argument("--modules", type=lambda s: s.split(","), default=MODULES)
    p.add_argument("--config", default=os.path.join(REPO, "models", "recgen-large.json"))
    p.add_argument("--tiny", action="store_true", help="the CI fixture's size (same code, small widths)")
    a = p.parse_args()
    for m in a.modules:
        if m not in MODULES:
            sys.exit(f"--modules: unknown `{m}` (known: {', '.join(MODULES)})")
    setup_env()
    import torch
    from safetensors.torch import save_file

    # spconv's CPU kernels are wrong with more than one thread above ~500 voxels.
    torch.set_num_threads(1)
    global FLOAT32
    FLOAT32 = torch.Tensor.float
    install_fake_xformers()
    pkg = types.ModuleType("trellis")
    pkg.__path__ = [os.path.join(os.path.abspath(a.trellis), "trellis")]
    sys.modules["trellis"] = pkg
    out = os.path.abspath(a.save)
    os.makedirs(out, exist_ok=True)
    ref, meta = {}, {}
    if "slat_flow" in a.modules:
        slat_flow(a, out, ref, meta)
    if "slat_dec_gs" in a.modules:
        slat_dec_gs(a, out, ref, meta)
    save_file(ref, os.path.join(out, "sparse_reference.safetensors"))
    import spconv

    with open(os.path.join(out, "sparse_reference.json"), "w") as f:
        json.dump({"trellis": os.path.abspath(a.trellis), "recgen": os.path.abspath(a.recgen), "torch": torch.__version__,
                   "spconv": getattr(spconv, "__version__", "?"), "threads": 1, "modules": meta,
                   "about": "output.<module>.f32: upstream float32 on the stored fp16 weights; .f64: the same code in "
                            "float64 (.double()); .cond.*: the stage-2 condition (patch tokens + point map + mask "
                            "embeddings, then the pose token)"}, f, indent=2)
    print(f"wrote {out}/sparse_reference.safetensors", flush=True)


if __name__ == "__main__":
    main()
