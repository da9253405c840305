"""Write the seed corpus of the fuzz targets (fuzz/corpus/<target>/): small
valid files of every format, in the shapes the shipped samples have. Kept in
the repository; rerun only to regenerate. Needs numpy and scipy (MAT files).

Run from the repository root: python3 fuzz/make_corpus.py
"""
import json
import os
import shutil
import struct

import numpy as np
import scipy.io

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "corpus")


def put(target, name, data):
    d = os.path.join(ROOT, target)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, name), "wb") as f:
        f.write(data if isinstance(data, bytes) else data.encode())


def safetensors(tensors, meta=None):
    header, blobs, off = {}, [], 0
    if meta:
        header["__metadata__"] = meta
    for name, (dtype, shape, raw) in tensors.items():
        header[name] = {"dtype": dtype, "shape": shape, "data_offsets": [off, off + len(raw)]}
        blobs.append(raw)
        off += len(raw)
    h = json.dumps(header).encode()
    h += b" " * (-len(h) % 8)
    return struct.pack("<Q", len(h)) + h + b"".join(blobs)


f32 = lambda v: struct.pack("<%df" % len(v), *v)
f16 = lambda v: np.array(v, dtype="<f2").tobytes()
put("safetensors", "f32.safetensors", safetensors({"a.weight": ("F32", [2, 3], f32([1, 2, 3, 4, 5, 6])), "a.bias": ("F32", [2], f32([0.5, -1]))}))
put("safetensors", "mixed.safetensors", safetensors(
    {"module.x": ("F16", [2, 2], f16([1, 2, 3, 4])), "module.y": ("BF16", [3], bytes(6)), "z": ("F32", [], f32([7]))},
    {"recon_random_init": "true", "seed": "0"}))

for n in ["plain.pt", "wrapped.pt"]:
    shutil.copy(os.path.join("tests/fixtures/weights", n), os.path.join(ROOT, "pt", n)) if os.path.isdir(os.path.join(ROOT, "pt")) else (
        os.makedirs(os.path.join(ROOT, "pt"), exist_ok=True), shutil.copy(os.path.join("tests/fixtures/weights", n), os.path.join(ROOT, "pt", n)))

K = np.array([[1066.778, 0, 312.9869], [0, 1067.487, 241.3109], [0, 0, 1]])
for comp in [False, True]:
    p = "/tmp/recon-corpus.mat"
    scipy.io.savemat(p, {"intrinsic_matrix": K, "factor_depth": np.array([[10000.0]]), "cls_indexes": np.array([[1], [4]], dtype=np.uint8),
                         "poses": np.zeros((3, 4, 2))}, do_compression=comp)
    put("matv5", "meta_%s.mat" % ("zlib" if comp else "plain"), open(p, "rb").read())

ply_head = "ply\nformat {fmt} 1.0\ncomment recon fuzz seed\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n" \
           "property uchar red\nproperty uchar green\nproperty uchar blue\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
verts = [(0, 0, 0, 255, 0, 0), (1, 0, 0, 0, 255, 0), (0, 1, 0, 0, 0, 255), (1, 1, 0.5, 9, 9, 9)]
faces = [(0, 1, 2), (1, 3, 2, 0)]
put("ply", "ascii.ply", ply_head.format(fmt="ascii") + "".join("%g %g %g %d %d %d\n" % v for v in verts)
    + "".join("%d %s\n" % (len(f), " ".join(map(str, f))) for f in faces))
for fmt, e in [("binary_little_endian", "<"), ("binary_big_endian", ">")]:
    body = b"".join(struct.pack(e + "fffBBB", *v) for v in verts) + b"".join(struct.pack(e + "B%di" % len(f), len(f), *f) for f in faces)
    put("ply", fmt + ".ply", ply_head.format(fmt=fmt).encode() + body)

put("scene_json", "scene.json", json.dumps({
    "version": 1, "source": "hand-made", "support_plane": {"material": "wood"},
    "objects": [
        {"name": "box", "category": "food_box", "mesh": "box_mm.ply", "scale": 0.001,
         "pose": {"quaternion_wxyz": [1, 0, 0, 0], "translation_m": [0, 0, 0.015]}},
        {"name": "can", "category": "can", "mesh": "can.ply", "physics": {"mass_kg": 0.35},
         "pose": {"rotation": [[0, -1, 0], [1, 0, 0], [0, 0, 1]], "translation_m": [0.1, 0, 0.05]}}]}, indent=1))

put("bop_scene_gt", "scene_gt.json", json.dumps({"0": [{"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 500], "obj_id": 1}],
                                                 "3": [{"cam_R_m2c": [0, -1, 0, 1, 0, 0, 0, 0, 1], "cam_t_m2c": [10, 20, 800], "obj_id": 1}]}))
put("bop_scene_camera", "scene_camera.json", json.dumps({"0": {"cam_K": [500, 0, 32, 0, 500, 24, 0, 0, 1], "depth_scale": 1.0,
                                                               "cam_R_w2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_w2c": [0, 0, 0]}}))
put("bop_models_info", "models_info.json", json.dumps({"1": {"diameter": 100.0, "min_x": -5, "size_x": 10}}))

for n in ["recgen-tiny.json", "recgen-nano.json"]:
    put("architecture", n, open(os.path.join("models", n)).read())
for n in sorted(os.listdir("models/sensors")):
    put("sensor", n, open(os.path.join("models/sensors", n)).read())
put("materials", "materials.json", open("models/materials.json").read())

put("predictions", "predictions.json", json.dumps({"predictions": [
    {"scene": "000000", "frame": 0, "obj_id": 1, "gt_index": 0, "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "t": [0, 0, 0.5], "scale": 1.0},
    {"scene": "000000", "frame": 3, "obj_id": 1, "R": [[0, -1, 0], [1, 0, 0], [0, 0, 1]], "t": [0.01, 0.02, 0.8], "mesh": "m.ply", "model_frame": False}]}, indent=1))

put("variation_spec", "spec.json", json.dumps({
    "version": 1, "frame": "camera",
    "predicates": [{"predicate": "on_top", "a": "mug", "b": "box"}, {"predicate": "inside", "a": "ball", "b": "bowl"},
                   {"predicate": "left_of", "a": "can", "b": "box"}, {"predicate": "near", "a": "can", "b": "mug", "distance_m": 0.05}],
    "sampled_predicates": 2, "region": {"center_m": [0, 0], "half_extent_m": [0.3, 0.3]},
    "distractors": {"count": [1, 3], "categories": ["box", "cylinder", "bowl"], "scale": [0.6, 1.0]},
    "object_variants": {"probability": 0.5, "scale": [0.9, 1.1], "aspect": [0.9, 1.1], "materials": ["plastic", "wood"]}}, indent=1))

put("intrinsics_json", "fxfy.json", json.dumps({"fx": 500.0, "fy": 501.0, "cx": 320.0, "cy": 240.0, "depth_scale_m": 0.001}))
put("intrinsics_json", "cam_K.json", json.dumps({"cam_K": [500, 0, 320, 0, 500, 240, 0, 0, 1], "depth_scale": 1.0}))
put("intrinsics_json", "nested.json", json.dumps({"intrinsics": {"K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]]}}))
put("intrinsics_yaml", "list.yml", "INTRINSICS: [1066.778, 0, 312.9869, 0, 1067.487, 241.3109, 0, 0, 1]\n")
put("intrinsics_yaml", "lines.yml", "fx: 500\nfy: 500.5\ncx: 320\ncy: 240\ndepth_scale_m: 0.001\n")

# User assets (recon scene --variations, distractors.assets): OBJ, GLB and the physics JSON.
put("obj", "quad.obj", "# recon fuzz seed\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 0.5 1\nvn 0 0 1\nvt 0 0\n"
    "g pyramid\nf 1/1/1 4/1/1 3/1/1 2/1/1\nf 1//1 2//1 5//1\nf 2 3 5\nf -3 -2 -1\nf 4 1 5\n")


def glb(positions, indices, extra_nodes=False):
    bin_ = b"".join(struct.pack("<3f", *p) for p in positions)
    ioff = len(bin_)
    bin_ += b"".join(struct.pack("<H", i) for i in indices)
    while len(bin_) % 4:
        bin_ += b"\0"
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
           "nodes": [{"mesh": 0, "translation": [0, 0.1, 0], "rotation": [0, 0, 0.7071068, 0.7071068]}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": len(positions), "type": "VEC3",
                          "min": [0, 0, 0], "max": [1, 1, 1]},
                         {"bufferView": 1, "componentType": 5123, "count": len(indices), "type": "SCALAR"}],
           "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": ioff},
                           {"buffer": 0, "byteOffset": ioff, "byteLength": 2 * len(indices)}],
           "buffers": [{"byteLength": len(bin_)}]}
    if extra_nodes:
        doc["scene"] = 0
        doc["nodes"] = [{"children": [1], "matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0.5, 1]},
                        {"mesh": 0, "scale": [2, 2, 2]}]
    js = json.dumps(doc).encode()
    while len(js) % 4:
        js += b" "
    return (struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js) + 8 + len(bin_)) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(bin_), 0x004E4942) + bin_)


tet = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
tet_faces = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3]
put("glb", "tetrahedron.glb", glb(tet, tet_faces))
put("glb", "nodes.glb", glb(tet, tet_faces, extra_nodes=True))
put("asset_physics", "mass.json", json.dumps({"version": 1, "category": "fruit", "units_m": 0.001, "up_axis": "y",
                                              "material": "produce", "mass_kg": 0.15, "friction": 0.7, "restitution": 0.1,
                                              "color_rgba": [0.8, 0.1, 0.1, 1.0]}, indent=1))
put("asset_physics", "density.json", json.dumps({"version": 1, "density_kg_m3": 650, "up_axis": "z"}))
