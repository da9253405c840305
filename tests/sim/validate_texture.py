"""Check the textures of a recon scene in MuJoCo, usd-core and pybullet.

usage: validate_texture.py mujoco scene.xml body   -- MuJoCo loads the MJCF with its
           texture; a top-down offscreen render of `body` (whose top face is, in its
           own frame, red at x < 0, y > 0, green at x > 0, y > 0 and blue at y < 0) shows
           those colours in those quadrants of the image, not one flat colour.
       validate_texture.py usd scene.usda body     -- the visual mesh is bound to a
           UsdPreviewSurface whose diffuseColor is a UsdUVTexture of an existing PNG,
           read through the `st` primvar the mesh has (one per point).
       validate_texture.py pybullet out_dir body   -- pybullet loads the object's URDF
           and reports a texture-carrying visual shape.
Prints a JSON summary; exits 1 on failure, 3 when no OpenGL context can be made
(the caller decides whether that is a skip).
"""
import json
import os
import sys

kind, path, body = sys.argv[1], sys.argv[2], sys.argv[3]
errors = []
summary = {}

if kind == "mujoco":
    import mujoco
    import numpy as np

    text = open(path).read()
    m0 = mujoco.MjModel.from_xml_path(path)
    if m0.ntex < 1 or m0.nmat < 1:
        errors.append(f"{m0.ntex} textures, {m0.nmat} materials")
    bid = mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_BODY, body)
    gid = mujoco.mj_name2id(m0, mujoco.mjtObj.mjOBJ_GEOM, body + "_visual")
    mid = m0.geom_matid[gid]
    if mid < 0:
        errors.append("the visual geom has no material")
    mesh = m0.geom_dataid[gid]
    if m0.mesh_texcoordnum[mesh] == 0:
        errors.append("the visual mesh has no texture coordinates")
    pos = m0.body_pos[bid]
    # A camera above the body: image right = world +x, image up = world +y.
    cam = f'<camera name="recon_top" pos="{pos[0]} {pos[1]} {pos[2] + 0.5}" xyaxes="1 0 0 0 1 0" fovy="30"/>'
    text = text.replace("<worldbody>", "<worldbody>\n    " + cam, 1)
    top = os.path.join(os.path.dirname(path), "scene_top_view.xml")
    open(top, "w").write(text)
    m = mujoco.MjModel.from_xml_path(top)
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    try:
        r = mujoco.Renderer(m, 240, 240)
    except Exception as e:  # no GL backend
        print(json.dumps({"gl": f"unavailable: {e}"}))
        sys.exit(3)
    r.update_scene(d, camera="recon_top")
    rgb = r.render().astype(float)
    r.enable_segmentation_rendering()
    r.update_scene(d, camera="recon_top")
    seg = r.render()[:, :, 0]
    r.close()  # before interpreter shutdown (OSMesa's teardown needs PyOpenGL alive)
    ys, xs = np.nonzero(seg == gid)
    if len(xs) < 200:
        errors.append(f"the object covers {len(xs)} pixels")
    else:
        # Image up is world +y: the top half (y > 0) is red left of centre and green right
        # of it, the bottom half blue.
        mid_x, mid_y = (xs.min() + xs.max()) / 2, (ys.min() + ys.max()) / 2
        px = lambda sel: rgb[ys[sel], xs[sel]]
        top_left = px((xs < mid_x - 5) & (ys < mid_y - 5))
        top_right = px((xs > mid_x + 5) & (ys < mid_y - 5))
        bottom = px(ys > mid_y + 5)
        red = lambda p: float(np.mean(p[:, 0] - p[:, 1]))
        blue = lambda p: float(np.mean(p[:, 2] - np.maximum(p[:, 0], p[:, 1])))
        summary.update(pixels=int(len(xs)), top_left_red_minus_green=red(top_left), top_right_red_minus_green=red(top_right),
                       bottom_blue_excess=blue(bottom))
        if not (red(top_left) > 40 and red(top_right) < -40):
            errors.append(f"top-left red-green {red(top_left):.1f} (want > 40), top-right {red(top_right):.1f} (want < -40)")
        if not blue(bottom) > 40:
            errors.append(f"bottom half: blue over red and green {blue(bottom):.1f} (want > 40)")
elif kind == "usd":
    from pxr import Usd, UsdGeom, UsdShade, Sdf

    stage = Usd.Stage.Open(path)
    mesh = stage.GetPrimAtPath(f"/World/{body}/visual")
    mat, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
    if not mat:
        errors.append("the visual mesh has no bound material")
    else:
        surface = mat.ComputeSurfaceSource()[0]
        if surface.GetIdAttr().Get() != "UsdPreviewSurface":
            errors.append(f"surface shader {surface.GetIdAttr().Get()}")
        src = surface.GetInput("diffuseColor").GetConnectedSource()
        tex = UsdShade.Shader(src[0].GetPrim()) if src else None
        if not tex or tex.GetIdAttr().Get() != "UsdUVTexture":
            errors.append("diffuseColor is not connected to a UsdUVTexture")
        else:
            f = tex.GetInput("file").Get()
            resolved = f.resolvedPath or os.path.join(os.path.dirname(path), f.path)
            summary["texture"] = f.path
            if not os.path.isfile(resolved):
                errors.append(f"texture {f.path} not found")
            st_src = tex.GetInput("st").GetConnectedSource()
            reader = UsdShade.Shader(st_src[0].GetPrim()) if st_src else None
            if not reader or reader.GetInput("varname").Get() != "st":
                errors.append("the texture's st is not read from the `st` primvar")
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    pts = UsdGeom.Mesh(mesh).GetPointsAttr().Get()
    if not st or len(st.Get()) != len(pts):
        errors.append(f"st primvar: {len(st.Get()) if st else 0} values for {len(pts)} points")
    summary["points"] = len(pts)
elif kind == "pybullet":
    import pybullet as p

    p.connect(p.DIRECT)
    uid = p.loadURDF(os.path.join(path, "urdf", body + ".urdf"))
    shapes = p.getVisualShapeData(uid, flags=p.VISUAL_SHAPE_DATA_TEXTURE_UNIQUE_IDS)
    summary["visual_shapes"] = len(shapes)
    if not shapes:
        errors.append("no visual shape")
    elif len(shapes[0]) > 8 and shapes[0][8] < 0:
        errors.append(f"the visual shape has no texture (id {shapes[0][8]})")
else:
    errors.append(f"unknown check {kind}")

summary["errors"] = errors
print(json.dumps(summary))
sys.exit(1 if errors else 0)
