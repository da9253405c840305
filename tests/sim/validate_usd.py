"""Open a recon scene usda with usd-core (pxr) and check the UsdPhysics
schemas: every object is a rigid body with mass, has colliders bound to a
physics material; UsdPhysics' own parser sees the same bodies and colliders.

usage: validate_usd.py scene.usda expected_bodies
Prints a JSON summary; exits 1 on failure.
"""
import json
import sys

from pxr import Usd, UsdPhysics, UsdShade, UsdGeom

path, expected = sys.argv[1], int(sys.argv[2])
stage = Usd.Stage.Open(path)
errors = []
if UsdGeom.GetStageUpAxis(stage) != UsdGeom.Tokens.z:
    errors.append("stage up axis is not Z")
if abs(UsdGeom.GetStageMetersPerUnit(stage) - 1.0) > 1e-9:
    errors.append("metersPerUnit is not 1")
scenes = [p for p in stage.Traverse() if p.IsA(UsdPhysics.Scene)]
if len(scenes) != 1:
    errors.append(f"{len(scenes)} PhysicsScene prims")

bodies = [p for p in stage.Traverse() if p.HasAPI(UsdPhysics.RigidBodyAPI)]
n_colliders = 0
for b in bodies:
    if not b.HasAPI(UsdPhysics.MassAPI):
        errors.append(f"{b.GetPath()}: no MassAPI")
        continue
    mass = UsdPhysics.MassAPI(b).GetMassAttr().Get()
    if not mass or mass <= 0:
        errors.append(f"{b.GetPath()}: mass {mass}")
    inertia = UsdPhysics.MassAPI(b).GetDiagonalInertiaAttr().Get()
    if inertia is None or min(inertia) < 0:
        errors.append(f"{b.GetPath()}: diagonal inertia {inertia}")
    colliders = [c for c in Usd.PrimRange(b) if c.HasAPI(UsdPhysics.CollisionAPI)]
    if not colliders:
        errors.append(f"{b.GetPath()}: no collider")
    for c in colliders:
        n_colliders += 1
        if c.IsA(UsdGeom.Mesh):
            if not c.HasAPI(UsdPhysics.MeshCollisionAPI):
                errors.append(f"{c.GetPath()}: mesh collider without MeshCollisionAPI")
            elif UsdPhysics.MeshCollisionAPI(c).GetApproximationAttr().Get() != "convexHull":
                errors.append(f"{c.GetPath()}: approximation is not convexHull")
        mat, _ = UsdShade.MaterialBindingAPI(c).ComputeBoundMaterial(materialPurpose="physics")
        if not mat or not mat.GetPrim().HasAPI(UsdPhysics.MaterialAPI):
            errors.append(f"{c.GetPath()}: no physics material bound")
        else:
            f = UsdPhysics.MaterialAPI(mat.GetPrim()).GetDynamicFrictionAttr().Get()
            if f is None or f < 0:
                errors.append(f"{c.GetPath()}: friction {f}")
if len(bodies) != expected:
    errors.append(f"{len(bodies)} rigid bodies, expected {expected}")

# UsdPhysics' own parsing of the stage (what a simulator importer sees).
load = getattr(UsdPhysics, "UsdPhysicsLoadStageFromPrimRange", None) or UsdPhysics.LoadUsdPhysicsFromRange
parsed = load(stage, ["/"])
kinds = {}
for obj_type, (paths, descs) in parsed.items():
    kind = str(obj_type).split(".")[-1]
    kinds[kind] = len(paths)
    if kind == "RigidBody":
        for path, desc in zip(paths, descs):
            if not desc.collisions:
                errors.append(f"UsdPhysics parser: {path} has no collisions")
if kinds.get("RigidBody", 0) != expected:
    errors.append(f"UsdPhysics parser found {kinds.get('RigidBody', 0)} rigid bodies: {kinds}")

summary = {"usd": ".".join(map(str, Usd.GetVersion())), "rigid_bodies": len(bodies), "colliders": n_colliders, "parsed": kinds, "errors": errors}
print(json.dumps(summary))
sys.exit(1 if errors else 0)
