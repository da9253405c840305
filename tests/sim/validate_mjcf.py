"""Load a recon scene MJCF with MuJoCo, step it and check that no object
falls through the plane and that objects stay near their settled poses.

usage: validate_mjcf.py scene.xml [seconds] [max_move_m] [min_z_m]
Prints one JSON line per body and a final JSON summary; exits 1 on failure.
"""
import json
import sys

import mujoco
import numpy as np

path = sys.argv[1]
seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 1.5
max_move = float(sys.argv[3]) if len(sys.argv) > 3 else 0.005
min_z = float(sys.argv[4]) if len(sys.argv) > 4 else -0.002

model = mujoco.MjModel.from_xml_path(path)
data = mujoco.MjData(model)
mujoco.mj_forward(model, data)

bodies = [b for b in range(1, model.nbody) if model.body_jntnum[b] == 1 and model.jnt_type[model.body_jntadr[b]] == mujoco.mjtJoint.mjJNT_FREE]
start = {b: (data.xpos[b].copy(), data.xmat[b].reshape(3, 3).copy()) for b in bodies}


def lowest_point(g):
    """Lowest world z of a colliding geom."""
    pos, mat = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)
    t = model.geom_type[g]
    size = model.geom_size[g]
    if t == mujoco.mjtGeom.mjGEOM_MESH:
        m = model.geom_dataid[g]
        a, n = model.mesh_vertadr[m], model.mesh_vertnum[m]
        v = model.mesh_vert[a:a + n]
        return float((v @ mat.T + pos)[:, 2].min())
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return float(pos[2] - size[0])
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        c = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size
        return float((c @ mat.T + pos)[:, 2].min())
    if t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        ring = np.stack([np.cos(ang) * size[0], np.sin(ang) * size[0], np.zeros_like(ang)], 1)
        pts = np.concatenate([ring + [0, 0, size[1]], ring - [0, 0, size[1]]])
        return float((pts @ mat.T + pos)[:, 2].min())
    return float(pos[2])


colliding = [g for g in range(model.ngeom) if model.geom_bodyid[g] in start and (model.geom_contype[g] or model.geom_conaffinity[g])]
lowest = {b: 1e9 for b in bodies}
steps = int(round(seconds / model.opt.timestep))
for i in range(steps):
    mujoco.mj_step(model, data)
    if i % 10 == 0 or i == steps - 1:
        for g in colliding:
            b = model.geom_bodyid[g]
            lowest[b] = min(lowest[b], lowest_point(g))

ok = True
rows = []
for b in bodies:
    p0, r0 = start[b]
    p1, r1 = data.xpos[b], data.xmat[b].reshape(3, 3)
    move = float(np.linalg.norm(p1 - p0))
    ang = float(np.degrees(np.arccos(np.clip((np.trace(r0.T @ r1) - 1) / 2, -1, 1))))
    good = move <= max_move and lowest[b] >= min_z
    ok &= good
    row = {"body": mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b), "move_m": move, "rot_deg": ang, "lowest_z_m": lowest[b], "ok": good}
    rows.append(row)
    print(json.dumps(row))
print(json.dumps({"mujoco": mujoco.__version__, "bodies": len(bodies), "seconds": seconds, "ok": ok}))
sys.exit(0 if ok and bodies else 1)
