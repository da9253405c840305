"""ADD / ADD-S by the BOP toolkit's own bop_toolkit_lib.pose_error (add, adi) on the cases
that tests/bop_toolkit.rs writes: reads a JSON file {"cases": [{"pts", "R_gt", "t_gt",
"R_e", "t_e"}]}, prints a JSON list of [add, adi] per case.

Install (CI: .ci/run): pip install --no-deps "bop_toolkit_lib @ <bop_toolkit tarball>";
pose_error only needs numpy and scipy.
"""
import json
import sys

import numpy as np
from bop_toolkit_lib import pose_error

with open(sys.argv[1]) as f:
    cases = json.load(f)["cases"]
out = []
for c in cases:
    pts = np.asarray(c["pts"], dtype=np.float64)
    R_gt, R_e = np.asarray(c["R_gt"], dtype=np.float64), np.asarray(c["R_e"], dtype=np.float64)
    t_gt = np.asarray(c["t_gt"], dtype=np.float64).reshape(3, 1)
    t_e = np.asarray(c["t_e"], dtype=np.float64).reshape(3, 1)
    out.append([float(pose_error.add(R_e, t_e, R_gt, t_gt, pts)), float(pose_error.adi(R_e, t_e, R_gt, t_gt, pts))])
print(json.dumps(out))
