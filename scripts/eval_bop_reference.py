"""Reference ADD / ADD-S numbers for src/eval/metrics.rs (test add_matches_bop_toolkit_reference).

Run with the BOP toolkit's own bop_toolkit_lib on PYTHONPATH (not on PyPI; taken from
github.com/thodan/bop_toolkit at commit cea62d651c7e395b2e1962b9749e4e89693c6ac4):
    PYTHONPATH=/path/to/bop_toolkit python3 scripts/eval_bop_reference.py
Rotations are built with scipy's Rotation.from_rotvec (independent of the Rust axis_angle).
"""
import numpy as np
from scipy.spatial.transform import Rotation
from bop_toolkit_lib import pose_error

pts = np.array([
    [50, 0, 0], [-50, 10, 0], [0, 40, 5], [0, -40, -5], [10, 10, 60], [-10, -10, -60],
    [30, 25, 20], [-35, 20, -15], [25, -30, 40], [-20, -25, 35], [5, 45, -30], [40, -5, -45],
], dtype=np.float64)

def rot(axis, angle):
    a = np.asarray(axis, dtype=np.float64)
    return Rotation.from_rotvec(a / np.linalg.norm(a) * angle).as_matrix()

R_gt, t_gt = rot([0.2, 0.9, -0.4], 0.6), np.array([[12.0], [-30.0], [650.0]])
R_e, t_e = rot([-0.5, 0.3, 1.0], 0.9), np.array([[15.0], [-26.0], [640.0]])
print(repr(pose_error.add(R_e, t_e, R_gt, t_gt, pts)))
print(repr(pose_error.adi(R_e, t_e, R_gt, t_gt, pts)))
