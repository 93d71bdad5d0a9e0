"""A small character stage written with usd-core: a head xform that turns and nods, and a body mesh.

Y up, centimetres, 24 time codes per second (as Maya writes them), so the readers' unit and axis conversions are
part of what the tests check. ``scenes/character.usda`` is this stage (``write_character_stage``)."""

from __future__ import annotations

import math

import numpy as np

NECK_CM = (0.0, 149.0, 0.0)  # the head prim's origin, the pivot it turns about (Y up, cm)
FPS = 24.0
END = 72  # time codes: 3 s


def head_rotation_deg(code: float) -> tuple[float, float, float]:
    """(x, y, z) Euler angles [deg] of the head at a time code: a turn about the (Y) up axis, then a nod."""
    t = code / FPS
    turn = 40.0 * math.sin(math.pi * min(t, 2.0) / 2.0) ** 2  # 0 -> 40 -> 0 over 2 s, then still
    nod = 15.0 * math.sin(math.pi * max(t - 2.0, 0.0)) if t > 2.0 else 0.0
    return nod, turn, 0.0


def write_character_stage(path) -> None:
    from pxr import Gf, Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(FPS)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(END)
    root = UsdGeom.Xform.Define(stage, "/Character")
    stage.SetDefaultPrim(root.GetPrim())
    head = UsdGeom.Xform.Define(stage, "/Character/Head")
    translate = head.AddTranslateOp()
    rotate = head.AddRotateXYZOp()
    translate.Set(Gf.Vec3d(*NECK_CM))
    for code in range(0, END + 1, 2):
        rotate.Set(Gf.Vec3f(*head_rotation_deg(code)), Usd.TimeCode(code))
    # the torso: a box 34 x 44 x 20 cm below the neck
    body = UsdGeom.Mesh.Define(stage, "/Character/Body")
    lo, hi = np.array([-17.0, 95.0, -4.0]), np.array([17.0, 139.0, 16.0])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    body.CreatePointsAttr([Gf.Vec3f(*map(float, c)) for c in corners])
    body.CreateFaceVertexCountsAttr([4] * 6)
    body.CreateFaceVertexIndicesAttr([i for q in quads for i in q])
    body.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    stage.GetRootLayer().documentation = "hairwarp character stage: a head xform that turns and nods, a torso"
    stage.GetRootLayer().Save()
