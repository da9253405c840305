"""Load recon scene URDFs in pybullet: every object URDF at its settled pose
on a ground plane, step, check they stay put; and the scene URDF loads.

usage: validate_pybullet.py out_dir [seconds] [max_move_m]
Prints a JSON summary; exits 1 on failure.
"""
import json
import os
import sys

import pybullet as p

out = sys.argv[1]
seconds = float(sys.argv[2]) if len(sys.argv) > 2 else 1.0
max_move = float(sys.argv[3]) if len(sys.argv) > 3 else 0.01
scene = json.load(open(os.path.join(out, "scene.json")))

p.connect(p.DIRECT)
p.setGravity(0, 0, -9.81)
p.setTimeStep(1.0 / 240.0)
plane = p.createMultiBody(0, p.createCollisionShape(p.GEOM_PLANE))
ids = {}
for o in scene["objects"]:
    stem = os.path.basename(os.path.dirname(o["mesh"]))
    q = o["pose"]["quaternion_wxyz"]
    ids[o["name"]] = p.loadURDF(os.path.join(out, "urdf", stem + ".urdf"), basePosition=o["pose"]["translation_m"], baseOrientation=[q[1], q[2], q[3], q[0]])
start = {n: p.getBasePositionAndOrientation(i)[0] for n, i in ids.items()}
for _ in range(int(seconds * 240)):
    p.stepSimulation()
rows, ok = [], True
for n, i in ids.items():
    pos = p.getBasePositionAndOrientation(i)[0]
    move = sum((a - b) ** 2 for a, b in zip(pos, start[n])) ** 0.5
    mass = p.getDynamicsInfo(i, -1)[0]
    good = move <= max_move and mass > 0
    ok &= good
    rows.append({"object": n, "move_m": move, "mass_kg": mass, "ok": good})
p.resetSimulation()
scene_id = p.loadURDF(os.path.join(out, "urdf", "scene.urdf"), useFixedBase=True)
ok &= scene_id >= 0
print(json.dumps({"objects": rows, "scene_urdf_links": p.getNumJoints(scene_id), "ok": ok}))
sys.exit(0 if ok else 1)
