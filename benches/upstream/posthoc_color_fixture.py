#!/usr/bin/env python3
"""Fixture for recon's post-hoc colour calibration: upstream's fitters on fixed pixels.

Runs `FITTERS` and `apply_transform` of TRI-ML/recgen's
`recgen_inference/recgen_modules/utils/posthoc_color.py`, imported by path from a
checkout the user supplies with --recgen (nothing of upstream is copied into this
repository), on deterministic render/photo pixel pairs: a known gamma, a known affine
map, both, outliers, noise only, near-black renders, a gamma out of range and a gain
past its clamp. Writes the inputs and upstream's outputs as JSON for
`tests/posthoc_color.rs`.

    python3 benches/upstream/posthoc_color_fixture.py --recgen /path/to/recgen \
        --out tests/fixtures/posthoc_color/upstream_fits.json

Needs numpy and scipy (upstream's gamma fit calls scipy's minimize_scalar); the
renderer half of upstream's calibration (CUDA) is not run.
"""
import argparse
import importlib.util
import json
import os
import sys

import numpy as np

N = 300
DIGITS = 6


def load_upstream(recgen):
    path = os.path.join(os.path.abspath(recgen), "recgen_inference", "recgen_modules", "utils", "posthoc_color.py")
    if not os.path.isfile(path):
        sys.exit(f"--recgen {recgen}: not a TRI-ML/recgen checkout (no {path})")
    # By path, without the package's __init__ (it imports the CUDA pipeline).
    spec = importlib.util.spec_from_file_location("recgen_posthoc_color", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def cases(rng):
    def uniform(n=N, lo=0.05, hi=0.95):
        return rng.uniform(lo, hi, size=(n, 3))

    def noise(x, sigma=0.02):
        return np.clip(x + rng.normal(0.0, sigma, size=x.shape), 0.0, 1.0)

    out = []
    s = uniform()
    out.append(("gamma_1_5", s, noise(s ** 1.5)))
    s = uniform()
    out.append(("affine", s, noise(s * [0.8, 1.1, 0.7] + [0.05, -0.03, 0.1])))
    s = uniform()
    out.append(("gamma_then_affine", s, noise((s ** 0.7) * [0.9, 1.0, 1.2] + [0.0, 0.05, -0.05])))
    s = uniform()
    t = noise(s * [0.8, 1.1, 0.7] + [0.05, -0.03, 0.1])
    bad = rng.random(N) < 0.15
    t[bad] = rng.uniform(0.0, 1.0, size=(int(bad.sum()), 3))
    out.append(("affine_with_outliers", s, t))
    s = uniform()
    out.append(("noise_only", s, noise(s, 0.05)))
    s = uniform()
    s[: N - 150] *= 0.04  # near-black render: fewer than 200 pixels left
    out.append(("mostly_dark", s, noise(s ** 1.2)))
    s = uniform(lo=0.2)
    out.append(("gamma_3", s, noise(s ** 3.0)))
    s = uniform(hi=0.25)
    out.append(("gain_past_clamp", s, noise(s * 4.0)))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recgen", required=True, help="TRI-ML/recgen checkout")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    up = load_upstream(args.recgen)
    rng = np.random.default_rng(20261127)
    probe = np.round(rng.uniform(-0.1, 1.1, size=(24, 3)), DIGITS)
    entries = []
    for name, src, tgt in cases(rng):
        # The inputs exactly as written: upstream runs on the rounded values.
        src, tgt = np.round(src, DIGITS), np.round(tgt, DIGITS)
        fits = {}
        for variant, fitter in up.FITTERS.items():
            tr = fitter(src, tgt)
            fits[variant] = {
                "transform": tr,
                "applied_to_probe": None if tr is None else up.apply_transform(probe, tr).tolist(),
            }
        entries.append({"name": name, "src": src.tolist(), "tgt": tgt.tolist(), "fits": fits})
    doc = {
        "made_by": "benches/upstream/posthoc_color_fixture.py",
        "upstream": "TRI-ML/recgen recgen_inference/recgen_modules/utils/posthoc_color.py (FITTERS, apply_transform)",
        "numpy": np.__version__,
        "scipy": __import__("scipy").__version__,
        "probe": probe.tolist(),
        "cases": entries,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(doc, f)
    print(f"wrote {args.out}: {len(entries)} cases")
    for e in entries:
        print(e["name"], {k: (v["transform"] or {}).get("type") for k, v in e["fits"].items()})


if __name__ == "__main__":
    main()
