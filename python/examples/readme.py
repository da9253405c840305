# The Python example of README.md ("## From Python"), verbatim below this header (python/tests/
# test_package.py checks both that and what it prints; CI runs it from the installed wheel).
# Run it from a folder holding the sample frame as data/sample/ (a checkout's root).

import recon_rgbd

engine = recon_rgbd.Engine()   # the embedded recgen-nano; Engine.from_pretrained("TRI-ML/RecGen") for RecGen's release
f = recon_rgbd.load_frame("data/sample/000001-color.png")   # depth and intrinsics found beside it
masks = [m["mask"] for m in recon_rgbd.load_masks("data/sample/000001-label.png")["objects"]]
for i, o in enumerate(engine.reconstruct(f["rgb"], f["depth"], f["K"], masks, seed=42)):
    print(o.label, "at", o.pose[:3, 3].round(3), "m; size", round(o.scale, 3), "m;", len(o.mesh.faces), "faces")
    o.to_glb(f"object{i}.glb")   # also to_ply, gaussians_to_ply, to_trimesh(); o.gaussians
