# The example of docs/python.md ("## Example"), verbatim below this header (python/tests/
# test_package.py checks both that and its printed output). Run it from a folder holding the
# sample frame as data/sample/ (a checkout's root): `python python/examples/quickstart.py`.
# It writes object0.glb and sample_sim/ into the working folder.

import numpy as np, recon_rgbd

engine = recon_rgbd.Engine()                   # weights=None: the embedded recgen-nano; "random", a folder, or "recgen"
f = recon_rgbd.load_frame("data/sample/000001-color.png")   # depth + intrinsics found as `recon infer` finds them
ids = recon_rgbd.load_masks("data/sample/000001-label.png")["objects"]
masks = [m["mask"] for m in ids]               # or one H×W instance-id array
objects = engine.reconstruct(f["rgb"], f["depth"], f["K"], masks, seed=42, max_faces=20_000)
for o in objects:
    print(o.label, o.pose[:3, 3], o.scale, o.score, o.mesh.vertices.shape, len(o.gaussians))
objects[0].to_glb("object0.glb")               # to_ply, gaussians_to_ply, to_trimesh()
sim = recon_rgbd.scene(objects, f, "sample_sim", collision="convex")   # the objects in memory + their frame
for o in sim["objects"]:
    print(o["name"], o["material"], f'{o["physics"]["mass_kg"]:.3f} kg;', f'started {o["start_penetration_mm"]:.1f} mm into {o["start_penetration_with"]},',
          f'moved {o["displacement_mm"]:.1f} mm', "(flagged)" if o["flagged"] else "")
print(sim["files"]["urdf_scene"], "at rest:", sim["settle"]["at_rest"], f'after {sim["settle"]["simulated_s"]:.1f} s simulated')
