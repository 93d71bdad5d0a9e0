"""A small character stage written with usd-core: a head xform that turns and nods, its scalp skin sliding over
the skull, the same head motion on a joint of a UsdSkel skeleton, and a body mesh.

Y up, centimetres, 24 time codes per second (as Maya writes them), so the readers' unit and axis conversions are
part of what the tests check. ``scenes/character.usda`` is this stage (``write_character_stage``)."""

from __future__ import annotations

import math

import numpy as np

NECK_CM = (0.0, 149.0, 0.0)  # the head prim's origin, the pivot it turns about (Y up, cm)
# The skeleton's joints and their local translations (cm): the Head joint sits at NECK_CM and turns as the head
# prim does.
SKEL_JOINTS = ("Hips", "Hips/Spine", "Hips/Spine/Neck", "Hips/Spine/Neck/Head")
SKEL_OFFSETS_CM = ((0.0, 100.0, 0.0), (0.0, 25.0, 0.0), (0.0, 15.0, 0.0), (0.0, 9.0, 0.0))
FPS = 24.0
END = 72  # time codes: 3 s
SCALP_CENTER_CM = (0.0, 160.0, 0.0)  # the scene's scalp ellipsoid (0, 0, 1.6) m, Z up
SCALP_RADII_CM = (8.5, 11.0, 10.0)  # its (0.085, 0.1, 0.11) m semi-axes in the stage's x, y (up), z
SCALP_STEP = 4  # time codes between the scalp's point samples


def head_rotation_deg(code: float) -> tuple[float, float, float]:
    """(x, y, z) Euler angles [deg] of the head at a time code: a turn about the (Y) up axis, then a nod."""
    t = code / FPS
    turn = 40.0 * math.sin(math.pi * min(t, 2.0) / 2.0) ** 2  # 0 -> 40 -> 0 over 2 s, then still
    nod = 15.0 * math.sin(math.pi * max(t - 2.0, 0.0)) if t > 2.0 else 0.0
    return nod, turn, 0.0


def scalp_rest_points() -> tuple[np.ndarray, list[int], list[int]]:
    """The scalp cap in the head prim's frame [cm]: a latitude-longitude grid over the top of the ellipsoid down to
    125 degrees from the crown; (points, face vertex counts, face vertex indices)."""
    rows, cols = 12, 24
    centre = np.asarray(SCALP_CENTER_CM) - np.asarray(NECK_CM)
    polar = np.radians(np.linspace(0.0, 125.0, rows + 1))[1:]
    azimuth = np.linspace(0.0, 2.0 * math.pi, cols, endpoint=False)
    unit = [(0.0, 1.0, 0.0)] + [(math.sin(p) * math.cos(a), math.cos(p), math.sin(p) * math.sin(a))
                                for p in polar for a in azimuth]
    points = centre + np.asarray(unit) * np.asarray(SCALP_RADII_CM)
    counts, indices = [], []
    for c in range(cols):  # the crown's fan, then quads ring by ring, wound outward
        counts.append(3)
        indices += [0, 1 + (c + 1) % cols, 1 + c]
    for r in range(rows - 1):
        for c in range(cols):
            a, b = 1 + r * cols + c, 1 + r * cols + (c + 1) % cols
            counts.append(4)
            indices += [a, b, b + cols, a + cols]
    return points, counts, indices


def scalp_points(code: float) -> np.ndarray:
    """The scalp at a time code [cm, head prim frame]: the skin slides forward and back over the skull, the crown
    most (a turn about the ear-to-ear axis through the centre, by an angle that grows with height; the rim holds)."""
    rest, _, _ = scalp_rest_points()
    centre = np.asarray(SCALP_CENTER_CM) - np.asarray(NECK_CM)
    rel = rest - centre
    height = np.clip((rel[:, 1] / SCALP_RADII_CM[1] + 0.5) / 1.5, 0.0, 1.0)
    angle = np.radians(8.0) * math.sin(2.0 * math.pi * code / END) * height
    c, s = np.cos(angle), np.sin(angle)
    out = rel.copy()
    out[:, 1] = c * rel[:, 1] - s * rel[:, 2]
    out[:, 2] = s * rel[:, 1] + c * rel[:, 2]
    return centre + out


def head_quaternion(code: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the head's rotation at a time code: the rotateXYZ op's Rz Ry Rx as a quaternion."""
    q = (1.0, 0.0, 0.0, 0.0)
    for axis, deg in sorted(enumerate(head_rotation_deg(code)), reverse=True):  # z, then y, then x
        h = math.radians(deg) / 2.0
        v = [0.0, 0.0, 0.0]
        v[axis] = math.sin(h)
        w1, x1, y1, z1 = q
        w2, (x2, y2, z2) = math.cos(h), v
        q = (w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
             w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2)
    return tuple(0.0 if abs(c) < 1e-12 else c for c in q)  # no sin(pi) residue in the stage


def _write_skeleton(stage) -> None:
    """/Character/Rig (SkelRoot): Skeleton Skel, its Head joint at the neck moved by the SkelAnimation Skel/Anim."""
    from pxr import Gf, Usd, UsdSkel, Vt

    UsdSkel.Root.Define(stage, "/Character/Rig")
    skel = UsdSkel.Skeleton.Define(stage, "/Character/Rig/Skel")
    skel.CreateJointsAttr(list(SKEL_JOINTS))
    rest, bind, total = [], [], Gf.Vec3d(0.0)
    for offset in SKEL_OFFSETS_CM:
        total += Gf.Vec3d(*offset)
        rest.append(Gf.Matrix4d(1.0).SetTranslate(Gf.Vec3d(*offset)))
        bind.append(Gf.Matrix4d(1.0).SetTranslate(total))
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray(rest))
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray(bind))
    anim = UsdSkel.Animation.Define(stage, "/Character/Rig/Skel/Anim")
    anim.CreateJointsAttr(list(SKEL_JOINTS))
    anim.CreateTranslationsAttr(Vt.Vec3fArray([Gf.Vec3f(*o) for o in SKEL_OFFSETS_CM]))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1.0)] * len(SKEL_JOINTS)))
    rotations = anim.CreateRotationsAttr()
    still = Gf.Quatf(1.0)
    for code in range(0, END + 1, 2):
        w, x, y, z = head_quaternion(code)
        rotations.Set(Vt.QuatfArray([still] * 3 + [Gf.Quatf(w, x, y, z)]), Usd.TimeCode(code))
    UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])


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
    # the scalp skin, a child of the head: its points move over the skull (time-sampled, as a skinned mesh's are)
    scalp = UsdGeom.Mesh.Define(stage, "/Character/Head/Scalp")
    _, counts, indices = scalp_rest_points()
    scalp.CreateFaceVertexCountsAttr(counts)
    scalp.CreateFaceVertexIndicesAttr(indices)
    scalp.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    scalp.CreatePurposeAttr(UsdGeom.Tokens.guide)
    points = scalp.CreatePointsAttr()
    for code in range(0, END + 1, SCALP_STEP):
        points.Set([Gf.Vec3f(*map(float, p)) for p in np.round(scalp_points(code), 4)], Usd.TimeCode(code))
    _write_skeleton(stage)
    # the torso: a box 34 x 44 x 20 cm below the neck
    body = UsdGeom.Mesh.Define(stage, "/Character/Body")
    lo, hi = np.array([-17.0, 95.0, -4.0]), np.array([17.0, 139.0, 16.0])
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    body.CreatePointsAttr([Gf.Vec3f(*map(float, c)) for c in corners])
    body.CreateFaceVertexCountsAttr([4] * 6)
    body.CreateFaceVertexIndicesAttr([i for q in quads for i in q])
    body.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    stage.GetRootLayer().documentation = ("hairwarp character stage: a head xform that turns and nods, its sliding "
                                          "scalp, a skeleton whose Head joint does the same, a torso")
    stage.GetRootLayer().Save()
