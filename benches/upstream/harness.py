#!/usr/bin/env python3
"""Side-by-side harness: upstream PyTorch (microsoft/TRELLIS) at full size on this machine.

The upstream modules are imported from a checkout the user supplies with
--trellis; nothing of upstream is copied into this repository. RecGen's pose
tokens (two small linear layers and a view-id embedding) are added here, as
recon's `ss_flow` bench step uses them.

Two jobs:
  * timing: each (module, precision) row runs in its own subprocess (so its
    peak RSS is its own): build with random weights, one forward on the same
    shapes and thread count as `recon bench --sections modules`; f32 and bf16
    autocast (oneDNN). Writes recon bench's JSON schema (machine, modules,
    notes), for `recon bench --compare FILE`.
  * --save DIR: the full-size modules stored the way the released checkpoints
    are (fp16 safetensors + {name, args} JSON under ckpts/ with the released
    file names), plus reference.safetensors: the inputs and upstream's outputs
    (f32 on the stored fp16 weights, and bf16 autocast) that
    tests/upstream_fullsize.rs checks recon against.

    python3 benches/upstream/harness.py --trellis /path/to/TRELLIS --threads 2 --json upstream.json
    python3 benches/upstream/harness.py --trellis /path/to/TRELLIS --save /tmp/fullsize

With --dinov2 /path/to/facebookresearch/dinov2 (a checkout), --save also writes DINOv2
ViT-L/14-reg as torch.hub stores it (hub/checkpoints/dinov2_vitl14_reg4_pretrain.pth,
random weights) and TRELLIS's conditioning on it (layer norm of `x_prenorm`, 1374 tokens
at 518²) in f32, float64 and bf16 autocast: `--modules dinov2` alone, or with the others.
"""
import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
import types

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
MODULES = ["ss_flow", "ss_decoder"]
DTYPES = ["f32", "bf16"]
# Released TRELLIS-image-large names (weights-manifest/trellis-image-large.json).
RELEASED = {"ss_flow": "ss_flow_img_dit_L_16l8_fp16", "ss_decoder": "ss_dec_conv3d_16l8_fp16"}
POSE_CHANNELS = {"quaternion_translation_scale": 8, "6d_translation_scale": 10, "9d_translation_scale": 13}


def import_upstream(trellis):
    """Import TRELLIS model modules from the checkout without running
    trellis/__init__.py (it pulls in the rendering pipelines and their
    CUDA-only dependencies)."""
    pkg_dir = os.path.join(os.path.abspath(trellis), "trellis")
    if not os.path.isfile(os.path.join(pkg_dir, "models", "sparse_structure_flow.py")):
        sys.exit(f"--trellis {trellis}: not a microsoft/TRELLIS checkout (no trellis/models/sparse_structure_flow.py)")
    os.environ.setdefault("ATTN_BACKEND", "sdpa")
    pkg = types.ModuleType("trellis")
    pkg.__path__ = [pkg_dir]
    sys.modules["trellis"] = pkg
    from trellis.models.sparse_structure_flow import SparseStructureFlowModel
    from trellis.models.sparse_structure_vae import SparseStructureDecoder

    return SparseStructureFlowModel, SparseStructureDecoder


def module_args(config_path, key):
    with open(config_path) as f:
        arch = json.load(f)
    spec = arch[key]
    return spec["name"], dict(spec["args"])


def build_ss_flow(trellis, config_path, with_pose):
    import torch
    import torch.nn as nn
    import torch.nn.functional as F

    Flow, _ = import_upstream(trellis)
    _, args = module_args(config_path, "ss_flow")
    pose_repr = args.get("pose_representation")
    k = int(args.get("num_pose_tokens", 1))
    trellis_args = {
        a: args[a]
        for a in [
            "resolution", "in_channels", "model_channels", "cond_channels", "out_channels", "num_blocks",
            "num_heads", "num_head_channels", "mlp_ratio", "patch_size", "pe_mode", "share_mod",
            "qk_rms_norm", "qk_rms_norm_cross",
        ]
        if a in args
    }

    class PoseFlow(Flow):
        """RecGen's pose tokens on the upstream torso: appended after the voxel
        tokens (no position embedding), split off after the final norm."""

        def __init__(self, pc, k, **kw):
            super().__init__(**kw)
            c = kw["model_channels"]
            self.input_layer_pose = nn.Linear(pc, c)
            self.out_layer_pose = nn.Linear(c, pc)
            self.pose_token_embedder = nn.Parameter(torch.zeros(k, c)) if k > 1 else None

        def forward(self, x, pose, t, cond):
            from trellis.modules.spatial import patchify, unpatchify

            h = patchify(x, self.patch_size)
            h = h.view(*h.shape[:2], -1).permute(0, 2, 1).contiguous()
            h = self.input_layer(h) + self.pos_emb[None]
            hp = self.input_layer_pose(pose)
            if self.pose_token_embedder is not None:
                hp = hp + self.pose_token_embedder[None, : pose.shape[1]]
            n = h.shape[1]
            h = torch.cat([h, hp], dim=1)
            t_emb = self.t_embedder(t)
            if self.share_mod:
                t_emb = self.adaLN_modulation(t_emb)
            for block in self.blocks:
                h = block(h, t_emb, cond)
            h = F.layer_norm(h.float(), h.shape[-1:])
            v = self.out_layer(h[:, :n])
            v = v.permute(0, 2, 1).view(v.shape[0], v.shape[2], *[self.resolution // self.patch_size] * 3)
            return unpatchify(v, self.patch_size).contiguous(), self.out_layer_pose(h[:, n:])

    if with_pose and pose_repr:
        return PoseFlow(POSE_CHANNELS[pose_repr], k, **trellis_args), args, POSE_CHANNELS[pose_repr], k
    return Flow(**trellis_args), args, None, 0


def build_ss_decoder(trellis, config_path):
    _, Dec = import_upstream(trellis)
    _, args = module_args(config_path, "ss_decoder")
    # The decoder's latent grid is the flow model's resolution (16 at full size).
    args["latent_resolution"] = module_args(config_path, "ss_flow")[1]["resolution"]
    kw = {a: args[a] for a in ["out_channels", "latent_channels", "num_res_blocks", "channels", "num_res_blocks_middle", "norm_type"] if a in args}
    return Dec(**kw), args


# torch.hub's file name for dinov2_vitl14_reg (weights-manifest/dinov2-vitl14-reg.json).
DINOV2_FILE = "dinov2_vitl14_reg4_pretrain.pth"


def build_dinov2(dinov2, tiny=False):
    """DINOv2 ViT-L/14 with 4 registers as torch.hub's `dinov2_vitl14_reg` builds it
    (img 518, layer scale, interpolate_antialias, offset 0), from the checkout by path;
    `tiny`: the same code at D 64, 2 blocks, 4 heads, img 56 (the CI fixture's size)."""
    sys.path.insert(0, os.path.abspath(dinov2))
    os.environ.setdefault("XFORMERS_DISABLED", "1")
    from dinov2.models import vision_transformer as vits

    kw = dict(patch_size=14, init_values=1.0, ffn_layer="mlp", block_chunks=0, num_register_tokens=4,
              interpolate_antialias=True, interpolate_offset=0.0)
    if tiny:
        return vits.DinoVisionTransformer(img_size=56, embed_dim=64, depth=2, num_heads=4, mlp_ratio=4, **kw), 56
    return vits.vit_large(img_size=518, **kw), 518


def randomize_dinov2(model, seed):
    """Every parameter redrawn: norm scales 1 + N(0, 0.1²), layer scales 0.1 + N(0, 0.02²),
    cls / register tokens and position embeddings N(0, 0.5²), biases N(0, 0.02²), other
    weights N(0, 0.02²)."""
    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            noise = torch.randn(p.shape, generator=g, dtype=torch.float32)
            if name.endswith("ls1.gamma") or name.endswith("ls2.gamma"):
                p.copy_(0.1 + 0.02 * noise)
            elif "norm" in name and name.endswith("weight"):
                p.copy_(1.0 + 0.1 * noise)
            elif name in ("cls_token", "register_tokens", "pos_embed", "mask_token"):
                p.copy_(0.5 * noise)
            else:
                p.copy_(0.02 * noise)


def save_dinov2(a, out, ref):
    """DINOv2 in torch.hub's layout and TRELLIS's condition on it: f32, float64, bf16 autocast."""
    import torch
    import torch.nn.functional as F

    model, size = build_dinov2(a.dinov2, tiny=a.tiny_dinov2)
    randomize_dinov2(model, 3)
    model.eval()
    hub = os.path.join(out, "hub", "checkpoints")
    os.makedirs(hub, exist_ok=True)
    torch.save(model.state_dict(), os.path.join(hub, DINOV2_FILE))
    if a.tiny_dinov2:
        # Not part of the hub layout: recon reads the tiny model's size from it (the real one is vitl14_reg).
        with open(os.path.join(hub, "dinov2_args.json"), "w") as f:
            json.dump({"embed_dim": 64, "depth": 2, "num_heads": 4, "mlp_ratio": 4.0, "patch_size": 14, "img_size": size,
                       "num_register_tokens": 4}, f, indent=2)
    g = torch.Generator().manual_seed(5)
    image01 = torch.rand(1, 3, size, size, generator=g)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    pixels = (image01 - mean) / std
    ref["input.dinov2.pixel_values"] = pixels.contiguous()

    def cond(m, x, dtype):
        # TRELLIS encode_image: layer norm (no affine) of the last block's output, all tokens.
        with torch.inference_mode():
            ctx = torch.autocast("cpu", dtype=torch.bfloat16) if dtype == "bf16" else torch.autocast("cpu", enabled=False)
            with ctx:
                f = m(x, is_training=True)["x_prenorm"]
                return F.layer_norm(f.float() if dtype == "bf16" else f, f.shape[-1:])

    for dtype in ["f32", "bf16", "f64"]:
        t = time.perf_counter()
        if dtype == "f64":
            o = cond(model.double(), pixels.double(), dtype)
        else:
            o = cond(model, pixels, dtype)
        print(f"dinov2 {dtype}: upstream forward {time.perf_counter() - t:.1f} s", flush=True)
        ref[f"output.dinov2.{dtype}"] = o.contiguous() if dtype == "f64" else o.float().contiguous()
    print(f"saved {hub}/{DINOV2_FILE}", flush=True)


def randomize(model, seed, std_by_prefix=()):
    """Upstream zero-initialises adaLN and output layers, which would make the
    outputs trivial: every parameter is redrawn (norm scales 1 + N(0, 0.05²),
    biases N(0, 0.01²), weights under a prefix of `std_by_prefix` ((prefix, std)
    pairs) N(0, std²), other weights N(0, 0.02²)); buffers keep their values."""
    import torch

    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            last = name.rsplit(".", 1)[-1]
            noise = torch.randn(p.shape, generator=g, dtype=torch.float32)
            std = next((s for prefix, s in std_by_prefix if name.startswith(prefix)), 0.02)
            if last == "gamma" or (p.dim() == 1 and last == "weight"):
                p.copy_(1.0 + 0.05 * noise)
            elif last == "bias":
                p.copy_(0.01 * noise)
            else:
                p.copy_(std * noise)


def inputs(key, args, pc, k, cond_tokens, seed=11):
    import torch

    g = torch.Generator().manual_seed(seed)
    if key == "ss_flow":
        r = args["resolution"]
        x = torch.randn(2, args["in_channels"], r, r, r, generator=g)
        pose = torch.randn(2, k, pc, generator=g) if pc else None
        cond = 0.5 * torch.randn(2, cond_tokens, args["cond_channels"], generator=g)
        return {"x": x, "pose": pose, "t": torch.tensor([750.0, 750.0]), "cond": cond}
    r = args["latent_resolution"]
    return {"x": torch.randn(1, args["latent_channels"], r, r, r, generator=g)}


def describe(key, inp):
    if key == "ss_flow":
        n = inp["x"].shape[2] ** 3
        pose = f" + {inp['pose'].shape[1]} pose tokens" if inp["pose"] is not None else ""
        return f"batch 2 (guided step), {n}{pose}, cond {list(inp['cond'].shape)}"
    return f"latent {list(inp['x'].shape)}"


def run(model, key, inp, dtype):
    import torch

    with torch.inference_mode():
        ctx = torch.autocast("cpu", dtype=torch.bfloat16) if dtype == "bf16" else torch.autocast("cpu", enabled=False)
        with ctx:
            if key == "ss_flow":
                if inp["pose"] is not None:
                    v, vp = model(inp["x"], inp["pose"], inp["t"], inp["cond"])
                    return [v.float(), vp.float()]
                return [model(inp["x"], inp["t"], inp["cond"]).float()]
            return [model(inp["x"]).float()]


def load_average():
    try:
        with open("/proc/loadavg") as f:
            return float(f.read().split()[0])
    except OSError:
        return None


def one_row(a, key, dtype):
    """Child process: build, one forward, print the row as JSON."""
    import torch

    torch.set_num_threads(a.threads)
    t0 = time.perf_counter()
    if key == "ss_flow":
        model, args, pc, k = build_ss_flow(a.trellis, a.config, with_pose=True)
    else:
        model, args = build_ss_decoder(a.trellis, a.config)
        pc, k = None, 0
    randomize(model, 0)
    model.eval()
    build_s = time.perf_counter() - t0
    inp = inputs(key, args, pc, k, a.cond_tokens)
    best = None
    for _ in range(a.reps):
        t1 = time.perf_counter()
        out = run(model, key, inp, dtype)
        s = time.perf_counter() - t1
        best = s if best is None else min(best, s)
    if not all(bool(o.isfinite().all()) for o in out):
        sys.exit(f"{key} {dtype}: non-finite output")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    label = "upstream torch f32" if dtype == "f32" else "upstream torch bf16 autocast"
    row = {
        "module": key,
        "input": describe(key, inp),
        "precision": f"{label} ({torch.backends.cpu.get_cpu_capability()})",
        "build_seconds": build_s,
        "forward_seconds": best,
        "peak_rss_mib": peak,
        "packed_weights_mib": None,
        "load_average": load_average(),
    }
    print("ROW " + json.dumps(row), flush=True)


def machine(threads):
    import torch

    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "threads": threads,
        "best_isa": f"torch {torch.__version__} {torch.backends.cpu.get_cpu_capability()}",
        "supported_isas": [torch.backends.cpu.get_cpu_capability()],
        "load_average": load_average(),
    }


def timing(a):
    import torch

    rows = []
    skipped = []
    for key in a.modules:
        for dtype in a.dtype:
            cmd = [sys.executable, os.path.abspath(__file__), "--trellis", a.trellis, "--config", a.config,
                   "--threads", str(a.threads), "--reps", str(a.reps), "--cond-tokens", str(a.cond_tokens), "--row", f"{key}:{dtype}"]
            try:
                p = subprocess.run(cmd, capture_output=True, text=True, timeout=a.row_timeout)
            except subprocess.TimeoutExpired:
                # Some rows have no fast kernel on a capped ISA (oneDNN's bf16 conv3d without
                # AVX512-BF16 runs for tens of minutes on one thread): say so and go on.
                print(f"{key:<11} {dtype:<40} did not finish within {a.row_timeout:.0f} s (stopped)", flush=True)
                skipped.append(f"{key} {dtype}: did not finish within {a.row_timeout:.0f} s (stopped; no row)")
                continue
            line = next((l for l in p.stdout.splitlines() if l.startswith("ROW ")), None)
            if p.returncode != 0 or line is None:
                sys.exit(f"{key} {dtype} failed (exit {p.returncode}):\n{p.stderr[-4000:]}")
            row = json.loads(line[4:])
            print(f"{row['module']:<11} {row['precision']:<40} build {row['build_seconds']:7.2f} s  forward {row['forward_seconds']:8.2f} s  "
                  f"peak {row['peak_rss_mib']:7.0f} MiB  load {row['load_average']}", flush=True)
            rows.append(row)
    report = {
        "machine": machine(a.threads),
        "modules": rows,
        "notes": [
            f"upstream microsoft/TRELLIS from {os.path.abspath(a.trellis)}, torch {torch.__version__}, "
            f"ATTN_BACKEND={os.environ.get('ATTN_BACKEND', 'sdpa')}, {a.threads} threads, python {platform.python_version()}",
            "random weights (benches/upstream/harness.py randomize), one forward per row, best of --reps; each row in its own process (peak RSS = ru_maxrss)",
        ],
    }
    # glibc allocator settings change both time and peak memory (recon's CLI keeps freed memory in the heap).
    malloc_env = {k: v for k, v in os.environ.items() if k.startswith("MALLOC_")}
    report["notes"].append(f"glibc allocator environment: {malloc_env or 'defaults'}")
    isa_env = {k: v for k, v in os.environ.items() if k in ("ATEN_CPU_CAPABILITY", "MKL_ENABLE_INSTRUCTIONS", "ONEDNN_MAX_CPU_ISA")}
    if isa_env:
        report["notes"].append(f"instruction-set caps: {isa_env}")
    report["notes"].extend(skipped)
    if a.json:
        tmp = a.json + ".partial"
        with open(tmp, "w") as f:
            json.dump(report, f, indent=2)
        os.replace(tmp, a.json)
        print(f"wrote {a.json}")


def save(a):
    """Full-size checkpoints in the released layout, and upstream's outputs on them."""
    import torch
    from safetensors.torch import save_file

    torch.set_num_threads(a.threads)
    out = os.path.abspath(a.save)
    os.makedirs(os.path.join(out, "ckpts"), exist_ok=True)
    ref = {}
    if "dinov2" in a.modules:
        if not a.dinov2:
            sys.exit("--modules dinov2 needs --dinov2 /path/to/facebookresearch/dinov2")
        save_dinov2(a, out, ref)
    for key in [m for m in a.modules if m != "dinov2"]:
        if key == "ss_flow":
            model, args, _, _ = build_ss_flow(a.trellis, a.config, with_pose=False)
            name = "SparseStructureFlowModel"
        else:
            model, args = build_ss_decoder(a.trellis, a.config)
            name = "SparseStructureDecoder"
        randomize(model, 1)
        model.eval()
        # The released files hold fp16; upstream's reference runs on exactly those values.
        state = {k: v.detach().to(torch.float16).contiguous() for k, v in model.state_dict().items()}
        model.load_state_dict({k: v.float() for k, v in state.items()})
        stem = os.path.join(out, "ckpts", RELEASED[key])
        save_file(state, stem + ".safetensors")
        cfg_args = {k: v for k, v in args.items() if k in model.__init__.__code__.co_varnames}
        cfg_args["use_fp16"] = True
        with open(stem + ".json", "w") as f:
            json.dump({"name": name, "args": cfg_args}, f, indent=2)
        inp = inputs(key, args, None, 0, a.cond_tokens)
        for k, v in inp.items():
            if v is not None:
                ref[f"input.{key}.{k}"] = v.contiguous()
        for dtype in ["f32", "bf16"]:
            t = time.perf_counter()
            o = run(model, key, inp, dtype)
            print(f"{key} {dtype}: upstream forward {time.perf_counter() - t:.1f} s", flush=True)
            ref[f"output.{key}.{dtype}"] = o[0].contiguous()
        print(f"saved {stem}.safetensors / .json", flush=True)
    save_file(ref, os.path.join(out, "reference.safetensors"))
    with open(os.path.join(out, "reference.json"), "w") as f:
        json.dump({"trellis": os.path.abspath(a.trellis), "torch": torch.__version__, "threads": a.threads,
                   "modules": {k: RELEASED.get(k, f"hub/checkpoints/{DINOV2_FILE}") for k in a.modules},
                   "dinov2": os.path.abspath(a.dinov2) if a.dinov2 else None,
                   "about": "output.<module>.f32: upstream f32 on the stored fp16 weights (DINOv2: its fp32 .pth); "
                            ".bf16: upstream bf16 autocast; .f64 (DINOv2): upstream in float64"}, f, indent=2)
    print(f"wrote {out}/reference.safetensors")


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--trellis", required=True, help="path to a microsoft/TRELLIS checkout")
    p.add_argument("--dinov2", help="path to a facebookresearch/dinov2 checkout (--save --modules dinov2)")
    p.add_argument("--tiny-dinov2", action="store_true", help="with --save: DINOv2 at the CI fixture's tiny size")
    p.add_argument("--config", default=os.path.join(REPO, "models", "recgen-large.json"))
    p.add_argument("--threads", type=int, default=os.cpu_count())
    p.add_argument("--modules", type=lambda s: s.split(","), default=MODULES)
    p.add_argument("--dtype", type=lambda s: s.split(","), default=DTYPES)
    p.add_argument("--reps", type=int, default=1)
    p.add_argument("--row-timeout", type=float, default=None,
                   help="seconds: a (module, precision) row still running then is stopped and left out, with a note")
    # DINOv2 ViT-L/14-reg at 518²: 37² patches + cls + 4 registers, as `recon bench`.
    p.add_argument("--cond-tokens", type=int, default=1374)
    p.add_argument("--json", help="write the timing report here (recon bench's schema)")
    p.add_argument("--save", help="write full-size released-layout checkpoints and upstream outputs here")
    p.add_argument("--row", help=argparse.SUPPRESS)
    a = p.parse_args()
    for m in a.modules:
        if m == "dinov2" and a.save:
            continue
        if m not in MODULES:
            sys.exit(f"--modules: unknown module `{m}` (known: {', '.join(MODULES)}; the sparse modules need spconv/flash-attn, CUDA only)")
    for d in a.dtype:
        if d not in DTYPES:
            sys.exit(f"--dtype: unknown `{d}` (known: {', '.join(DTYPES)})")
    if a.row:
        key, dtype = a.row.split(":")
        one_row(a, key, dtype)
    elif a.save:
        save(a)
    else:
        timing(a)


if __name__ == "__main__":
    main()
