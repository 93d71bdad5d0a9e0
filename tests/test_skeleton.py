"""The head's motion from a joint of a UsdSkel skeleton, checked against the joint chain composed by hand."""

import subprocess
import sys
import textwrap

import numpy as np
import pytest

FPS = 24.0
ANIM_CODES = list(range(0, 25, 2))  # the SkelAnimation's samples
PRIM_CODES = [0, 5, 16, 24]  # the skeleton prim's rotateY samples; 5 is between two of the animation's
PRIM_TRANSLATE = (10.0, 0.0, -5.0)  # cm
JOINTS = ["Hips", "Hips/Spine", "Hips/Spine/Neck", "Hips/Spine/Neck/Head", "Hips/ArmL", "Hips/ArmL/Hand",
          "Hips/ArmR", "Hips/ArmR/Hand"]
ANIMATED = JOINTS[:4]  # the animation is sparse: the arms keep their rest transforms
SPINE_SCALE = 1.25  # uniform and constant (exact in half precision): taken out of the head's pose
# Y up in cm to Z up in m: (x, y, z) -> 0.01 (x, -z, y)
Y_TO_Z = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
# The stage stores translations and quaternions as float32 (7 digits): 1.6 m and unit rotations, composed over
# four joints, agree with the float64 chain to a few 1e-7.
ATOL_M = 1e-6
ATOL_ROT = 1e-6


def _axis_angle_quat(axis, deg):
    """(w, x, y, z) of a rotation by ``deg`` about ``axis`` (right-handed)."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    h = np.radians(deg) / 2.0
    return np.array([np.cos(h), *(np.sin(h) * axis)])


def _quat_matrix(q):
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _slerp(q0, q1, u):
    q0, q1 = np.asarray(q0, dtype=np.float64), np.asarray(q1, dtype=np.float64)
    d = float(q0 @ q1)
    if d < 0.0:
        q1, d = -q1, -d
    theta = np.arccos(min(d, 1.0))
    if theta < 1e-12:
        return q0
    return (np.sin((1 - u) * theta) * q0 + np.sin(u * theta) * q1) / np.sin(theta)


def _anim_at(code):
    """Translations (cm) and quaternions (w, x, y, z) of the animated joints at one of the animation's samples."""
    s = code / FPS
    translations = [(0.0, 100.0 + 3.0 * np.sin(2.0 * s), 4.0 * s), (0.0, 20.0, 0.0), (0.0, 25.0, 1.0 + s),
                    (0.0, 8.0, 0.0)]
    rotations = [_axis_angle_quat((0, 1, 0), 30.0 * np.sin(1.5 * s)), _axis_angle_quat((1, 0, 0), 10.0 * s),
                 _axis_angle_quat((0, 0, 1), -20.0 * np.sin(s)), _axis_angle_quat((1, 1, 0.5), 25.0 * s)]
    # float32, as the stage stores them
    return ([np.float32(t).astype(np.float64) for t in np.array(translations)],
            [np.float32(q).astype(np.float64) for q in np.array(rotations)])


def _prim_angle(code):
    return {0: 0.0, 5: 20.0, 16: 35.0, 24: 30.0}[code]


REST = {"Hips/ArmL": (15.0, 40.0, 0.0), "Hips/ArmL/Hand": (30.0, 0.0, 0.0), "Hips/ArmR": (-15.0, 40.0, 0.0),
        "Hips/ArmR/Hand": (-30.0, 0.0, 0.0)}


def write_skeleton_stage(path, *, bind_animation=True):
    """SkelRoot /Char: Skeleton /Char/Skel (translated, turning about Y up), its SkelAnimation /Char/Skel/Anim,
    a plain xform /Char/Body; Y up, centimetres, 24 time codes per second, as a DCC writes it."""
    from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(FPS)
    root = UsdSkel.Root.Define(stage, "/Char")
    stage.SetDefaultPrim(root.GetPrim())
    UsdGeom.Xform.Define(stage, "/Char/Body").AddTranslateOp().Set(Gf.Vec3d(0.0, 120.0, 0.0))
    skel = UsdSkel.Skeleton.Define(stage, "/Char/Skel")
    skel.AddTranslateOp().Set(Gf.Vec3d(*PRIM_TRANSLATE))
    turn = skel.AddRotateYOp()
    for code in PRIM_CODES:
        turn.Set(_prim_angle(code), Usd.TimeCode(code))
    skel.CreateJointsAttr(JOINTS)
    t0, q0 = _anim_at(0)
    rest = []
    for j in JOINTS:
        m = Gf.Matrix4d(1.0)
        if j in ANIMATED:
            i = ANIMATED.index(j)
            m.SetTransform(Gf.Rotation(Gf.Quatd(*q0[i])), Gf.Vec3d(*t0[i]))
        else:
            m.SetTranslate(Gf.Vec3d(*REST[j]))
        rest.append(m)
    skel.CreateRestTransformsAttr(Vt.Matrix4dArray(rest))
    bind = []  # skeleton space at rest (no scale)
    for j, m in zip(JOINTS, rest):
        parent = j.rpartition("/")[0]
        bind.append(m * bind[JOINTS.index(parent)] if parent else m)
    skel.CreateBindTransformsAttr(Vt.Matrix4dArray(bind))
    anim = UsdSkel.Animation.Define(stage, "/Char/Skel/Anim")
    anim.CreateJointsAttr(ANIMATED)
    translations, rotations = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr()
    for code in ANIM_CODES:
        t, q = _anim_at(code)
        translations.Set(Vt.Vec3fArray([Gf.Vec3f(*map(float, v)) for v in t]), Usd.TimeCode(code))
        rotations.Set(Vt.QuatfArray([Gf.Quatf(float(v[0]), Gf.Vec3f(*map(float, v[1:]))) for v in q]),
                      Usd.TimeCode(code))
    anim.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1.0), Gf.Vec3h(SPINE_SCALE), Gf.Vec3h(1.0), Gf.Vec3h(1.0)]))
    if bind_animation:
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    stage.GetRootLayer().Save()


def _expected_head(code):
    """World pose of the Head joint at a time code in metres, Z up (column convention), composed here: the joints'
    local T R S along Hips/Spine/Neck/Head, times the skeleton prim's T(translate) Ry(angle); also the rotation
    as the product of the rotations alone (the spine's uniform scale is not part of it)."""
    if code in ANIM_CODES:
        t, q = _anim_at(code)
    else:  # between two samples: translations lerp, rotations slerp (USD's linear interpolation)
        a = max(c for c in ANIM_CODES if c < code)
        b = min(c for c in ANIM_CODES if c > code)
        u = (code - a) / (b - a)
        (ta, qa), (tb, qb) = _anim_at(a), _anim_at(b)
        t = [(1 - u) * x + u * y for x, y in zip(ta, tb)]
        q = [_slerp(x, y, u) for x, y in zip(qa, qb)]
    scales = [1.0, SPINE_SCALE, 1.0, 1.0]
    chain, rot = np.eye(4), np.eye(3)
    for i in range(4):
        local = np.eye(4)
        local[:3, :3] = _quat_matrix(q[i]) * scales[i]
        local[:3, 3] = t[i]
        chain = chain @ local
        rot = rot @ _quat_matrix(q[i])
    angle = np.interp(code, PRIM_CODES, [_prim_angle(c) for c in PRIM_CODES])
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    prim = np.eye(4)
    prim[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    prim[:3, 3] = PRIM_TRANSLATE
    world = prim @ chain
    expect = np.eye(4)
    expect[:3, :3] = Y_TO_Z @ prim[:3, :3] @ rot @ Y_TO_Z.T
    expect[:3, 3] = 0.01 * Y_TO_Z @ world[:3, 3]
    return expect


@pytest.fixture
def skel_stage(tmp_path):
    path = tmp_path / "skel.usda"
    write_skeleton_stage(path)
    return path


@pytest.mark.parametrize("joint", ["Hips/Spine/Neck/Head", "Head", "/Hips/Spine/Neck/Head"])
def test_joint_world_poses_equal_the_chain_composed_by_hand(skel_stage, joint):
    """At every time sample of the animation and of the skeleton prim, the pose read for the joint is the product
    of the joints' local transforms along its path and the prim's world transform, in metres Z up."""
    from hairwarp.io.usd_anim import read_prim_motion

    times, matrices = read_prim_motion(skel_stage, "/Char/Skel", joint)
    codes = sorted(set(ANIM_CODES) | set(PRIM_CODES))
    # read at every frame of the stage between the first sample and the last, so that the head follows USD's own
    # interpolation between the samples; checked by hand at the samples
    np.testing.assert_allclose(times, np.arange(codes[0], codes[-1] + 1) / FPS, rtol=0, atol=1e-12)
    for code in codes:
        m = matrices[code - codes[0]]
        expect = _expected_head(code)
        np.testing.assert_allclose(m[:3, 3], expect[:3, 3], rtol=0, atol=ATOL_M, err_msg=f"code {code}")
        np.testing.assert_allclose(m[:3, :3], expect[:3, :3], rtol=0, atol=ATOL_ROT, err_msg=f"code {code}")
        np.testing.assert_allclose(m[3], [0.0, 0.0, 0.0, 1.0])


def test_head_motion_from_a_joint_is_relative_to_its_first_sample(skel_stage):
    from hairwarp.io.usd_anim import head_motion_from_usd

    motion = head_motion_from_usd(skel_stage, "/Char/Skel", joint="Head")
    first_inv = np.linalg.inv(_expected_head(0))
    for code in sorted(set(ANIM_CODES) | set(PRIM_CODES)):
        got = motion.evaluate(code / FPS).matrix()
        np.testing.assert_allclose(got, _expected_head(code) @ first_inv, rtol=0, atol=ATOL_M, err_msg=f"code {code}")


def test_a_joint_whose_scale_changes_is_refused(tmp_path):
    from pxr import Gf, Usd, UsdSkel, Vt

    from hairwarp.io.usd_common import UsdFileError

    path = tmp_path / "skel.usda"
    write_skeleton_stage(path)
    stage = Usd.Stage.Open(str(path))
    scales = UsdSkel.Animation(stage.GetPrimAtPath("/Char/Skel/Anim")).GetScalesAttr()
    for code, s in ((0, 1.0), (24, 1.5)):
        scales.Set(Vt.Vec3hArray([Gf.Vec3h(1.0), Gf.Vec3h(s), Gf.Vec3h(1.0), Gf.Vec3h(1.0)]), Usd.TimeCode(code))
    stage.GetRootLayer().Save()
    from hairwarp.io.usd_anim import read_prim_motion

    with pytest.raises(UsdFileError, match="joint Hips/Spine/Neck/Head: its world scale changes with time"):
        read_prim_motion(path, "/Char/Skel", "Head")


def _scene(tmp_path, stage, motion):
    path = tmp_path / "skel.toml"
    path.write_text(textwrap.dedent("""
        [sim]
        frames = 2
        [groom]
        generator = "scalp"
        count = 4
        [head.motion]
        kind = "usd"
        file = "{}"
        """).format(stage.name) + motion)
    return path


@pytest.mark.parametrize("motion, words", [
    ('prim = "/Char/Skel"\n', ["head.motion.joint", "/Char/Skel", "is a Skeleton", "Hips/Spine/Neck/Head"]),
    ('prim = "/Char/Skel"\njoint = "Haed"\n', ["head.motion.joint", "/Char/Skel", "no joint 'Haed'",
                                               "close: Hips/Spine/Neck/Head"]),
    ('prim = "/Char/Skel"\njoint = "Hand"\n', ["head.motion.joint", "2 joints are named 'Hand'",
                                               "Hips/ArmL/Hand, Hips/ArmR/Hand"]),
    ('prim = "/Char"\njoint = "Head"\n', ["head.motion.joint", "/Char is a SkelRoot, not a Skeleton",
                                          "its skeletons: /Char/Skel"]),
    ('prim = "/Char/Body"\njoint = "Head"\n', ["head.motion.joint", "/Char/Body is a Xform, not a Skeleton"]),
    ('prim = "/Char/Nope"\njoint = "Head"\n', ["head.motion.prim", "no prim '/Char/Nope'"]),
])
def test_joint_errors_are_one_line_naming_file_prim_and_key(tmp_path, skel_stage, motion, words):
    scene = _scene(tmp_path, skel_stage, motion)
    r = subprocess.run([sys.executable, "-m", "hairwarp", "info", str(scene)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, (r.stdout, r.stderr)
    assert r.stdout == "" and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr, r.stderr
    for w in [str(skel_stage), *words]:
        assert w in r.stderr, r.stderr


def test_a_skeleton_without_animation_or_motion_is_refused(tmp_path):
    """An unbound animation would leave the head still at the rest pose: a mistake worth one line, through run."""
    from pxr import Usd, UsdGeom

    path = tmp_path / "skel.usda"
    write_skeleton_stage(path, bind_animation=False)
    stage = Usd.Stage.Open(str(path))
    UsdGeom.Xformable(stage.GetPrimAtPath("/Char/Skel")).ClearXformOpOrder()
    stage.GetRootLayer().Save()
    scene = _scene(tmp_path, path, 'prim = "/Char/Skel"\njoint = "Head"\n')
    r = subprocess.run([sys.executable, "-m", "hairwarp", "run", str(scene), "-o", str(tmp_path / "x.usdc")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    for w in ("head.motion.prim", str(path), "/Char/Skel joint Hips/Spine/Neck/Head", "no bound animation"):
        assert w in last, r.stderr
    assert not (tmp_path / "x.usdc").exists()


def test_joint_applies_to_usd_motion_only(tmp_path):
    import hairwarp as hw

    with pytest.raises(hw.SceneError, match=r"head.motion.joint: applies to kind = \"usd\" only"):
        hw.Scene.from_dict({"head": {"motion": {"kind": "nod", "joint": "Head"}}})


def _turning_head(path, start: float, angles: dict, start_time_code=None):
    """A Z-up stage at 24 codes a second whose /Head Xform turns about z: ``angles`` time code -> degrees."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    stage.SetTimeCodesPerSecond(FPS)
    if start_time_code is not None:
        stage.SetStartTimeCode(start_time_code)
        stage.SetEndTimeCode(max(angles))
    op = UsdGeom.Xform.Define(stage, "/Head").AddRotateZOp()
    for code, deg in angles.items():
        op.Set(float(deg), start + code - min(angles))
    stage.Save()
    return path


def _turn_deg(matrix) -> float:
    return float(np.degrees(np.arctan2(matrix[1, 0], matrix[0, 0])))


def test_a_usd_head_plays_from_the_stages_start_and_turns_as_usd_interpolates(tmp_path):
    """A shot authored from time code 1001 (its stage's startTimeCode) plays from the run's first frame: 12 codes
    later (0.5 s at 24 codes a second) the head has turned as keyed. A turn keyed 0 then 270 degrees 12 codes apart
    goes the long way round, as USD's rotateZ interpolates it: 90 degrees at code 4, where keys through the two
    samples alone turned -30 degrees the short way."""
    from hairwarp.io.usd_anim import head_motion_from_usd

    shot = _turning_head(tmp_path / "shot.usda", 1001.0, {1001: 0.0, 1013: 30.0}, start_time_code=1001.0)
    motion = head_motion_from_usd(shot, "/Head", interpolation="linear")
    assert _turn_deg(motion.evaluate(0.0).matrix()) == pytest.approx(0.0, abs=1e-9)
    # float32 angles: 1e-5 degrees
    assert _turn_deg(motion.evaluate(12 / FPS).matrix()) == pytest.approx(30.0, abs=1e-5)
    long_way = _turning_head(tmp_path / "spin.usda", 0.0, {0: 0.0, 12: 270.0})
    motion = head_motion_from_usd(long_way, "/Head", interpolation="linear")
    assert _turn_deg(motion.evaluate(4 / FPS).matrix()) == pytest.approx(90.0, abs=1e-5)
    assert _turn_deg(motion.evaluate(6 / FPS).matrix()) == pytest.approx(135.0, abs=1e-5)
