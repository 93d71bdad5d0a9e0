"""USD caches and grooms: everything written is read back with usd-core (pxr) directly, and the readers are checked
against stages authored by hand with pxr and numbers worked out by hand."""

import os

import numpy as np
import pytest
import trimesh
from pxr import Gf, Sdf, Usd, UsdGeom, UsdUtils, Vt

from hairwarp.colliders import ColliderSet
from hairwarp.io.cache import CacheWriter
from hairwarp.io.cache_folder import CacheWriteError
from hairwarp.io.usd_anim import mesh_motion, read_animated_collider, read_animated_mesh
from hairwarp.io.usd_common import UsdFileError
from hairwarp.io.usd_groom import read_curves, write_curves
from hairwarp.io.usd_inspect import (
    describe,
    read_frames,
)

F32_ATOL = 1e-6
"""Values pass through float32 in the file: ~1e-7 relative for the metre-scale numbers used here."""
F32_RTOL = 1e-6

FPS = 30.0
ROOT_W, TIP_W = 8e-5, 2e-5


def _strands(n_curves, n_pts, frame, seed=0):
    """Deterministic wavy strands hanging down from z = 0.1, moving with the frame number."""
    rng = np.random.default_rng(seed)
    roots = rng.uniform(-0.05, 0.05, (n_curves, 1, 3))
    k = np.arange(n_pts)[None, :, None]
    drop = np.concatenate([np.zeros((1, n_pts, 2)), -0.01 * np.arange(n_pts)[None, :, None]], axis=2)
    sway = 0.002 * np.sin(0.5 * k + 0.3 * frame) * np.array([1.0, 0.5, 0.0])
    return (roots + np.array([0, 0, 0.1]) + drop + sway).reshape(-1, 3)


def _tetra():
    pts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]], dtype=np.float64)
    faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return pts, faces


def _xform(frame):
    """Column-convention 4x4: a rotation about z by 0.2*frame rad and a translation."""
    c, s = np.cos(0.2 * frame), np.sin(0.2 * frame)
    m = np.eye(4)
    m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    m[:3, 3] = [0.01 * frame, -0.02, 0.3]
    return m


def _write_small_cache(path, frames=(0, 1, 2)):
    written = {}
    with CacheWriter(path, fps=FPS, comment="test cache") as cache:
        cache.add_curves("guides", np.full(3, 5), widths=(ROOT_W, TIP_W), kind="guides")
        cache.add_curves("dense", np.full(4, 6), widths=(ROOT_W, TIP_W), basis="catmullRom")
        cache.add_mesh("head", *_tetra())
        for f in frames:
            g = _strands(3, 5, f, seed=1)
            d = _strands(4, 6, f, seed=2)
            gv = np.full_like(g, 0.5) * (f + 1)
            cache.write_frame(f, {"guides": (g, gv), "dense": (d, None)}, xforms={"head": _xform(f)})
            written[f] = (g, gv, d)
    return written


def test_cache_read_back_with_pxr(tmp_path):
    path = tmp_path / "cache.usdc"
    written = _write_small_cache(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache.clips", "cache.usdc"], "temporary file left behind"

    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == FPS
    assert stage.GetFramesPerSecond() == FPS
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 2)
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")

    guides = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides"))
    dense = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/dense"))
    assert guides and dense
    assert guides.GetTypeAttr().Get() == UsdGeom.Tokens.linear
    assert dense.GetTypeAttr().Get() == UsdGeom.Tokens.cubic
    assert dense.GetBasisAttr().Get() == UsdGeom.Tokens.catmullRom
    assert dense.GetWrapAttr().Get() == UsdGeom.Tokens.pinned
    assert guides.GetPrim().GetAttribute("hairwarp:curveKind").Get() == "guides"
    assert list(guides.GetCurveVertexCountsAttr().Get()) == [5, 5, 5]

    for attr in (guides.GetPointsAttr(), dense.GetPointsAttr(), guides.GetVelocitiesAttr(), guides.GetExtentAttr()):
        assert attr.GetTimeSamples() == [0.0, 1.0, 2.0], attr.GetPath()
    assert not dense.GetVelocitiesAttr().HasAuthoredValue()

    for f, (g, gv, d) in written.items():
        for prim, expected in ((guides, g), (dense, d)):
            pts = np.asarray(prim.GetPointsAttr().Get(f))
            assert pts.dtype == np.float32
            np.testing.assert_array_equal(pts, expected.astype(np.float32))
            lo, hi = np.asarray(prim.GetExtentAttr().Get(f))
            assert np.all(pts >= lo) and np.all(pts <= hi)
            # The extent is tight up to the half width of the thickest vertex.
            np.testing.assert_allclose(lo, pts.min(axis=0) - ROOT_W / 2, rtol=F32_RTOL, atol=F32_ATOL)
        np.testing.assert_array_equal(np.asarray(guides.GetVelocitiesAttr().Get(f)), gv.astype(np.float32))

    for prim, n in ((guides, 5), (dense, 6)):
        assert prim.GetWidthsInterpolation() == UsdGeom.Tokens.vertex
        w = np.asarray(prim.GetWidthsAttr().Get()).reshape(-1, n)
        np.testing.assert_allclose(w, np.tile(np.linspace(ROOT_W, TIP_W, n), (len(w), 1)), rtol=F32_RTOL)

    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Colliders/head"))
    pts, faces = _tetra()
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get()), pts, atol=F32_ATOL)
    np.testing.assert_array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()), faces.ravel())
    for f in written:
        world = np.array(UsdGeom.XformCache(f).GetLocalToWorldTransform(mesh.GetPrim()))
        # USD row vectors: p_world = [p, 1] @ world, so world is the transpose of our column-convention matrix.
        np.testing.assert_allclose(world, _xform(f).T, atol=1e-12)


def test_exception_inside_with_keeps_frames_written(tmp_path):
    path = tmp_path / "crash.usdc"
    with pytest.raises(RuntimeError, match="solver blew up"):
        with CacheWriter(path, fps=24) as cache:
            cache.add_curves("guides", np.full(2, 4))
            for f in range(5):
                if f == 2:
                    raise RuntimeError("solver blew up")
                cache.write_frame(f, {"guides": (_strands(2, 4, f), None)})
    # the frames stay in the visible working folder, a valid cache; nothing is put at the output path
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crash.partial"]
    assert cache.partial_path == tmp_path / "crash.partial" / "crash.usdc"
    assert sorted(p.name for p in cache.partial_path.parent.iterdir()) == ["crash.clips", "crash.usdc"]
    stage = Usd.Stage.Open(str(cache.partial_path))
    attr = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides")).GetPointsAttr()
    assert attr.GetTimeSamples() == [0.0, 1.0]
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 1)
    np.testing.assert_array_equal(np.asarray(attr.Get(1)), _strands(2, 4, 1).astype(np.float32))


@pytest.mark.parametrize("suffix", [".usda", ".usd"])
def test_text_and_plain_usd_suffixes(tmp_path, suffix):
    path = tmp_path / f"cache{suffix}"
    written = _write_small_cache(path, frames=(3, 7))
    stage = Usd.Stage.Open(str(path))
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (3, 7)
    attr = stage.GetPrimAtPath("/World/Hair/dense").GetAttribute("points")
    np.testing.assert_array_equal(np.asarray(attr.Get(7)), written[7][2].astype(np.float32))
    if suffix == ".usda":
        assert path.read_text().startswith("#usda")


def _validation_errors(path):
    """Errors from usd-core's compliance checker (UsdUtils.ComplianceChecker, or the UsdValidation framework that
    replaced it in newer releases)."""
    checker_cls = getattr(UsdUtils, "ComplianceChecker", None)
    if checker_cls is not None:
        checker = checker_cls()
        checker.CheckCompliance(str(path))
        return list(checker.GetErrors()) + list(checker.GetFailedChecks())
    from pxr import UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    errors = UsdValidation.ValidationContext(validators).Validate(Usd.Stage.Open(str(path)))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors if e.GetType() != UsdValidation.ValidationErrorType.Info]


def test_compliance_checker_finds_nothing(tmp_path):
    cache = tmp_path / "cache.usdc"
    _write_small_cache(cache)
    assert _validation_errors(cache) == []
    groom = tmp_path / "groom.usda"
    write_curves(groom, [np.array([[0, 0, 0], [0, 0, -0.1]])], up_axis="Y", meters_per_unit=0.01)
    assert _validation_errors(groom) == []
    # The checker does catch a stage that lacks the metadata.
    bare = tmp_path / "bare.usda"
    stage = Usd.Stage.CreateNew(str(bare))
    UsdGeom.BasisCurves.Define(stage, "/curves")
    stage.Save()
    assert _validation_errors(bare)


def test_read_curves_y_up_centimetres_by_hand(tmp_path):
    """A stage authored directly with pxr: Y up, centimetres, the curves under a translated and scaled Xform."""
    path = tmp_path / "maya_groom.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    parent = UsdGeom.Xform.Define(stage, "/groom")
    parent.AddTranslateOp().Set(Gf.Vec3d(100.0, 0.0, 0.0))
    parent.AddScaleOp().Set(Gf.Vec3f(2.0, 2.0, 2.0))
    curves = UsdGeom.BasisCurves.Define(stage, "/groom/hair")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([3, 2]))
    curves.CreatePointsAttr(Vt.Vec3fArray([(0, 10, 0), (0, 10, 5), (1, 4, 5), (3, 0, -1), (3, -2, -1)]))
    stage.Save()

    got = read_curves(path)
    # World cm = (100 + 2x, 2y, 2z); metres Z up = (X, -Z, Y) / 100.
    expected = [
        np.array([[1.00, 0.0, 0.20], [1.00, -0.10, 0.20], [1.02, -0.10, 0.08]]),
        np.array([[1.06, 0.02, 0.0], [1.06, 0.02, -0.04]]),
    ]
    assert len(got) == 2
    for g, e in zip(got, expected, strict=True):
        assert g.dtype == np.float64
        np.testing.assert_allclose(g, e, atol=1e-12)


def test_writer_converts_to_y_up_centimetres(tmp_path):
    path = tmp_path / "cm.usdc"
    p = np.array([[0.0, 0.0, 1.0], [0.1, 0.2, 0.9]])
    v = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, -1.0]])
    m = np.eye(4)
    m[:3, 3] = [0.0, 0.5, 0.0]  # 0.5 m along +y (Z up) = 50 cm along -z (Y up)
    with CacheWriter(path, fps=24, up_axis="Y", meters_per_unit=0.01) as cache:
        cache.add_curves("c", [2], widths=1e-3)
        cache.add_mesh("m", *_tetra())
        cache.write_frame(0, {"c": (p, v)}, xforms={"m": m})
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    c = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/c"))
    # Z-up metres (x, y, z) -> Y-up centimetres (100 x, 100 z, -100 y), worked by hand.
    np.testing.assert_allclose(np.asarray(c.GetPointsAttr().Get(0)), [[0, 100, 0], [10, 90, -20]], atol=1e-4)
    np.testing.assert_allclose(np.asarray(c.GetVelocitiesAttr().Get(0)), [[100, 300, -200], [0, -100, 0]], atol=1e-4)
    np.testing.assert_allclose(np.asarray(c.GetWidthsAttr().Get()), [0.1], rtol=F32_RTOL)
    assert c.GetWidthsInterpolation() == UsdGeom.Tokens.constant
    mesh_world = np.array(UsdGeom.XformCache(0).GetLocalToWorldTransform(stage.GetPrimAtPath("/World/Colliders/m")))
    np.testing.assert_allclose(mesh_world[3, :3], [0, 0, -50], atol=1e-9)
    np.testing.assert_allclose(read_curves(path)[0], p, atol=F32_ATOL)
    frame = read_frames(path)[0]
    verts, _, world = frame["meshes"]["m"]
    np.testing.assert_allclose(world, m, atol=1e-12)
    np.testing.assert_allclose(verts, _tetra()[0] + [0, 0.5, 0], atol=F32_ATOL)


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_write_curves_round_trip(tmp_path, suffix):
    rng = np.random.default_rng(3)
    lines = [np.cumsum(rng.normal(size=(n, 3)) * 0.01, axis=0) for n in (2, 7, 12)]
    path = write_curves(tmp_path / f"groom{suffix}", lines, widths=(1e-4, 1e-5), up_axis="Y", meters_per_unit=0.01)
    got = read_curves(path)
    assert [len(g) for g in got] == [2, 7, 12]
    for g, e in zip(got, lines, strict=True):
        np.testing.assert_allclose(g, e, atol=F32_ATOL)
    stage = Usd.Stage.Open(str(path))
    w = np.asarray(stage.GetPrimAtPath("/World/Hair/groom").GetAttribute("widths").Get())
    np.testing.assert_allclose(w[2:9], np.linspace(1e-2, 1e-3, 7), rtol=F32_RTOL)  # centimetres


def test_groom_written_to_usd_loads_back_the_same_strands(tmp_path):
    from hairwarp.groom import Groom, scalp_groom

    groom = scalp_groom(40, 0.3, points=12, curl=0.004, seed=2)
    for suffix, up, mpu in ((".usdc", "Z", 1.0), (".usda", "Y", 0.01)):
        path = write_curves(tmp_path / f"groom{suffix}", groom.strands, up_axis=up, meters_per_unit=mpu)
        back = Groom.load(path)
        assert back.strand_count == groom.strand_count
        for a, b in zip(groom.strands, back.strands, strict=True):
            assert a.shape == b.shape
            np.testing.assert_allclose(b, a, atol=2 * F32_ATOL)  # float32 in the file, metres ~1.7


def test_read_frames_and_describe(tmp_path):
    path = tmp_path / "cache.usdc"
    written = _write_small_cache(path)
    frames = read_frames(path)
    assert [f["frame"] for f in frames] == [0, 1, 2]
    assert frames[1]["time"] == pytest.approx(1 / FPS)
    pts, counts = frames[2]["curves"]["dense"]
    np.testing.assert_array_equal(counts, [6, 6, 6, 6])
    np.testing.assert_allclose(pts, written[2][2], atol=F32_ATOL)
    verts, tris, world = frames[2]["meshes"]["head"]
    local, faces = _tetra()
    np.testing.assert_array_equal(tris, faces)
    np.testing.assert_allclose(verts, (np.c_[local, np.ones(4)] @ _xform(2).T)[:, :3], atol=F32_ATOL)
    assert [f["frame"] for f in read_frames(path, frames=[1])] == [1]

    text = describe(path)
    for piece in ("30 time codes per second", "frames 0 .. 2", "3 time samples", "/World/Hair/guides [guides]",
                  "3 curves, 15 vertices", "cubic catmullRom (pinned)", "/World/Colliders/head: 4 points, 4 faces",
                  "transform animated (3 samples)", "extent (last frame 2)", "per frame"):
        assert piece in text, piece


def test_bad_input_is_reported(tmp_path):
    with pytest.raises(UsdFileError, match="missing.usd"):
        read_curves(tmp_path / "missing.usd")
    junk = tmp_path / "junk.usda"
    junk.write_text("this is not usd")
    with pytest.raises(UsdFileError, match="junk.usda"):
        read_curves(junk)
    empty = tmp_path / "empty.usda"
    Usd.Stage.CreateNew(str(empty)).Save()
    with pytest.raises(UsdFileError, match="no BasisCurves"):
        read_curves(empty)
    with pytest.raises(UsdFileError, match="must end in"):
        CacheWriter(tmp_path / "cache.abc", fps=24)

    path = tmp_path / "cache.usdc"
    with CacheWriter(path, fps=24) as cache:
        cache.add_curves("c", [3])
        cache.write_frame(0, {"c": (np.zeros((3, 3)), None)})
        with pytest.raises(UsdFileError, match="frames must increase"):
            cache.write_frame(0, {"c": (np.zeros((3, 3)), None)})
        with pytest.raises(UsdFileError, match="NaN"):
            cache.write_frame(1, {"c": (np.full((3, 3), np.nan), None)})
        with pytest.raises(UsdFileError, match=r"\(3, 3\)"):
            cache.write_frame(1, {"c": (np.zeros((4, 3)), None)})
        with pytest.raises(UsdFileError, match="no points for curves"):
            cache.write_frame(1, {})
        with pytest.raises(UsdFileError, match="before the first frame"):
            cache.add_curves("late", [3])
    # A rejected frame leaves nothing behind.
    stage = Usd.Stage.Open(str(path))
    attr = stage.GetPrimAtPath("/World/Hair/c").GetAttribute("points")
    assert attr.GetTimeSamples() == [0.0]


def test_rewrite_while_the_old_file_is_open(tmp_path):
    """A stage still holding the previous cache sees the new one: the layer registry is refreshed at close."""
    path = tmp_path / "cache.usdc"
    _write_small_cache(path, frames=(0, 1))
    held = Usd.Stage.Open(str(path))
    _write_small_cache(path, frames=(0, 1, 2, 3))
    attr = held.GetPrimAtPath("/World/Hair/dense").GetAttribute("points")
    assert attr.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    assert len(read_frames(path)) == 4


def test_velocities_must_be_given_consistently(tmp_path):
    with CacheWriter(tmp_path / "v.usdc", fps=24) as cache:
        cache.add_curves("c", [3])
        cache.write_frame(0, {"c": (np.zeros((3, 3)), np.zeros((3, 3)))})
        with pytest.raises(UsdFileError, match="has velocities in earlier frames"):
            cache.write_frame(1, {"c": (np.zeros((3, 3)), None)})


# --- animated colliders ----------------------------------------------------------------------------------------

ANIM_FPS = 24.0
ANIM_FRAMES = 25
OMEGA = np.pi  # [rad/s]: one sway per 2 s
# Catmull-Rom keys every h = 1/24 s: the interpolated velocity is off by O(h^2) times the third derivative,
# measured 0.2 % of the peak speed of the sway (0.3 % of the peak turn rate).
VEL_REL_TOL = 0.01
# The motion's own velocities against central differences of its poses (step FD_H): O(FD_H^2) truncation.
FD_H = 1e-5
FD_REL_TOL = 1e-5

_CUBE_POINTS = np.array([(x, y, z) for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], dtype=float)[
    [0, 1, 3, 2, 4, 5, 7, 6]] * 10.0  # cm, a 20 cm cube
_CUBE_QUADS = [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (0, 4, 7, 3), (1, 2, 6, 5)]  # outward


def _sway(t):
    """The rig's animation in the Y-up centimetre stage: translation [cm] and rotation about +Y [deg]."""
    return np.array([10.0 * np.sin(OMEGA * t), 5.0 * t, 0.0]), 30.0 * np.sin(OMEGA * t)


def _expected_world(t, points_cm):
    """World points [m, Z up] of mesh-local points at time t [s], worked out in numpy from the authored ops."""
    trans, angle = _sway(t)
    c, s = np.cos(np.radians(angle)), np.sin(np.radians(angle))
    rot_y = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    local = 2.0 * points_cm + [0.0, 170.0, 0.0]  # the mesh's own ops: translate, then scale (applied first)
    world_cm = local @ rot_y.T + trans  # the rig's ops: translate, then rotateY (applied first)
    return 0.01 * world_cm @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]).T  # (x, -z, y)


def _write_animated_stage(path, *, animated_points=False, left_handed=False, scale_anim=False):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(ANIM_FPS)
    rig = UsdGeom.Xform.Define(stage, "/Rig")
    translate, rotate = rig.AddTranslateOp(), rig.AddRotateYOp()
    body = UsdGeom.Mesh.Define(stage, "/Rig/Body")
    body.AddTranslateOp().Set(Gf.Vec3d(0.0, 170.0, 0.0))
    scale = body.AddScaleOp()
    scale.Set(Gf.Vec3f(2.0, 2.0, 2.0))
    quads = [q[::-1] for q in _CUBE_QUADS] if left_handed else _CUBE_QUADS
    body.CreateFaceVertexCountsAttr(Vt.IntArray([4] * 6))
    body.CreateFaceVertexIndicesAttr(Vt.IntArray([i for q in quads for i in q]))
    if left_handed:
        body.CreateOrientationAttr(UsdGeom.Tokens.leftHanded)
    points = body.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(_CUBE_POINTS.astype(np.float32)))
    for f in range(ANIM_FRAMES):
        trans, angle = _sway(f / ANIM_FPS)
        translate.Set(Gf.Vec3d(*trans), f)
        rotate.Set(float(angle), f)
        if animated_points:
            points.Set(Vt.Vec3fArray.FromNumpy((_CUBE_POINTS * (1.0 + 0.01 * f)).astype(np.float32)), f)
        if scale_anim:
            scale.Set(Gf.Vec3f(2.0 + 0.1 * f, 2.0, 2.0), f)
    stage.Save()
    return path


def _moved(matrix, vertices):
    return vertices @ matrix[:3, :3].T + matrix[:3, 3]


def test_read_animated_mesh_poses_against_the_authored_animation(tmp_path):
    path = _write_animated_stage(tmp_path / "rig.usda")
    vertices, faces, times, matrices = read_animated_mesh(path)
    np.testing.assert_allclose(times, np.arange(ANIM_FRAMES) / ANIM_FPS, rtol=0, atol=1e-12)
    assert vertices.shape == (8, 3) and faces.shape == (12, 3) and matrices.shape == (ANIM_FRAMES, 4, 4)
    for t, m in zip(times, matrices, strict=True):
        np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-12)  # rigid: the scale is baked
        assert np.linalg.det(m[:3, :3]) > 0.0
        np.testing.assert_allclose(_moved(m, vertices), _expected_world(t, _CUBE_POINTS), atol=F32_ATOL)
    cube = trimesh.Trimesh(vertices, faces, process=False)
    assert cube.is_watertight and cube.volume == pytest.approx(0.4**3, rel=1e-9)  # outward: positive volume
    # The same mesh named explicitly; a left-handed copy comes back with the same (outward) winding.
    assert np.array_equal(read_animated_mesh(path, "/Rig/Body")[1], faces)
    left = read_animated_mesh(_write_animated_stage(tmp_path / "left.usda", left_handed=True))
    assert trimesh.Trimesh(left[0], left[1], process=False).volume > 0.0


def test_mesh_motion_velocities_against_the_authored_animation(tmp_path):
    vertices, _, times, matrices = read_animated_mesh(_write_animated_stage(tmp_path / "rig.usdc"))
    motion = mesh_motion(times, matrices)
    for t, m in zip(times, matrices, strict=True):
        np.testing.assert_allclose(motion.evaluate(t).matrix(), m, atol=1e-12)
    turn_rate = np.radians(30.0) * OMEGA
    peak = 0.01 * 10.0 * OMEGA + 0.01 * 5.0 + turn_rate * 0.4  # sway, drift, and the turn at 0.4 m from the axis
    for t in np.linspace(times[2], times[-3], 17) + 0.3 / ANIM_FPS:  # between keys, away from the held ends
        sample = motion.evaluate(t)
        x = _moved(sample.matrix(), vertices)
        v = sample.linear_velocity + np.cross(sample.angular_velocity, x - sample.matrix()[:3, 3])
        # Independent: central differences of the authored animation, worked out in numpy.
        v_true = (_expected_world(t + FD_H, _CUBE_POINTS) - _expected_world(t - FD_H, _CUBE_POINTS)) / (2 * FD_H)
        np.testing.assert_allclose(v, v_true, atol=VEL_REL_TOL * peak)
        np.testing.assert_allclose(sample.angular_velocity, [0.0, 0.0, turn_rate * np.cos(OMEGA * t)],
                                   atol=VEL_REL_TOL * turn_rate)
        # The motion's velocities and accelerations are the derivatives of its own poses.
        before, after = motion.evaluate(t - FD_H), motion.evaluate(t + FD_H)
        fd_x = (_moved(after.matrix(), vertices) - _moved(before.matrix(), vertices)) / (2 * FD_H)
        np.testing.assert_allclose(v, fd_x, atol=FD_REL_TOL * peak)
        fd_a = (after.linear_velocity - before.linear_velocity) / (2 * FD_H)
        np.testing.assert_allclose(sample.linear_acceleration, fd_a, atol=1e-3 * np.abs(fd_a).max() + 1e-6)
        fd_al = (after.angular_velocity - before.angular_velocity) / (2 * FD_H)
        np.testing.assert_allclose(sample.angular_acceleration, fd_al, atol=1e-3 * np.abs(fd_al).max() + 1e-6)
    # Held before the first and after the last sample.
    np.testing.assert_allclose(motion.evaluate(-1.0).matrix(), matrices[0], atol=1e-12)
    assert np.all(motion.evaluate(10.0).linear_velocity == 0.0)


def test_animated_collider_follows_the_stage(tmp_path):
    path = _write_animated_stage(tmp_path / "rig.usd")
    collider = read_animated_collider(path, thickness=0.001)
    assert collider.name == "Body" and collider.attach == "world" and collider.motion is not None
    colliders = ColliderSet([collider], "cpu")
    _, _, times, matrices = read_animated_mesh(path)
    for i in (3, 11):
        colliders.update(times[i])
        np.testing.assert_allclose(colliders.world_matrices()[0], matrices[i], atol=1e-9)
        centre = _expected_world(times[i], np.zeros((1, 3)))
        corner = _expected_world(times[i], _CUBE_POINTS[:1] * 1.5)  # 0.1 m beyond a corner along every axis
        d = colliders.signed_distance(np.concatenate([centre, corner]))[0][:, 0]
        np.testing.assert_allclose(d, [-0.2, 0.1 * np.sqrt(3.0)], atol=1e-5)


def test_read_animated_mesh_points_scale_and_errors(tmp_path):
    path = _write_animated_stage(tmp_path / "points.usda", animated_points=True)
    vertices, _, times, matrices = read_animated_mesh(path)
    assert vertices.shape == (ANIM_FRAMES, 8, 3)
    for f in (0, 7, 24):
        expected = _expected_world(times[f], _CUBE_POINTS * (1.0 + 0.01 * f))
        np.testing.assert_allclose(_moved(matrices[f], vertices[f]), expected, atol=F32_ATOL)
    with pytest.raises(UsdFileError, match="deforms"):
        read_animated_collider(path)
    with pytest.raises(UsdFileError, match="scale changes with time"):
        read_animated_mesh(_write_animated_stage(tmp_path / "scale.usda", scale_anim=True))
    with pytest.raises(UsdFileError, match="/Rig is a Xform, not a Mesh"):
        read_animated_mesh(path, "/Rig")
    with pytest.raises(UsdFileError, match="no prim at /Nope"):
        read_animated_mesh(path, "/Nope")
    with pytest.raises(UsdFileError, match="no Mesh prim"):
        read_animated_mesh(write_curves(tmp_path / "groom.usda", [np.zeros((2, 3)) + [[0, 0, 0], [0, 0, 1]]]))
    # A static stage: one pose at time 0.
    static = tmp_path / "static.usda"
    stage = Usd.Stage.CreateNew(str(static))
    mesh = UsdGeom.Mesh.Define(stage, "/m")
    mesh.CreatePointsAttr(Vt.Vec3fArray([(0, 0, 0), (1, 0, 0), (0, 1, 0)]))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray([3]))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2]))
    stage.Save()
    vertices, faces, times, matrices = read_animated_mesh(static)
    assert times.tolist() == [0.0] and np.array_equal(matrices, np.eye(4)[None])
    np.testing.assert_array_equal(faces, [[0, 1, 2]])



def test_writer_timings_add_up_per_phase(tmp_path):
    with CacheWriter(tmp_path / "t.usdc", fps=24) as cache:
        cache.add_curves("c", np.full(2, 4))
        assert cache.timings == {"check": 0.0, "convert": 0.0, "set": 0.0, "save": 0.0, "wait": 0.0}
        for f in range(3):
            cache.write_frame(f, {"c": (_strands(2, 4, f), np.ones((8, 3)))})
        cache.flush()  # the last frame's save is counted once its commit is done
        assert all(v > 0.0 for v in cache.timings.values())
        bad = np.ones((8, 3))
        bad[5, 1] = np.inf
        with pytest.raises(UsdFileError, match="velocities: contains NaN or infinite"):
            cache.write_frame(3, {"c": (_strands(2, 4, 3), bad)})


def test_bench_usd_write_reports_phases():
    from hairwarp.benchmarks.dense import bench_usd_write

    result = bench_usd_write(counts=(50,), quick=True, points_per_curve=9)
    (row,) = result["results"]
    assert row["points"] == 450 and row["write_s"] > 0 and row["convert_s"] > 0 and row["save_s"] > 0
    assert row["bytes_per_frame"] >= 24 * 450  # float32 points and velocities


# --- the background writer -------------------------------------------------------------------------------------


def _all_samples(path):
    """Every authored attribute of a stage: path -> (time samples, default value, value at each sample)."""
    stage = Usd.Stage.Open(str(path))
    out = {"range": (stage.GetStartTimeCode(), stage.GetEndTimeCode(), stage.GetTimeCodesPerSecond())}
    for prim in stage.Traverse():
        for attr in prim.GetAuthoredAttributes():
            times = attr.GetTimeSamples()
            out[str(attr.GetPath())] = (times, attr.Get(), [attr.Get(t) for t in times])
    return out


def _assert_same_stage(a, b):
    sa, sb = _all_samples(a), _all_samples(b)
    assert sa.keys() == sb.keys()
    for key in sa:
        va, vb = sa[key], sb[key]
        if key == "range":
            assert va == vb
            continue
        assert va[0] == vb[0], key
        for x, y in zip([va[1], *va[2]], [vb[1], *vb[2]], strict=True):
            if isinstance(x, Vt.Vec3fArray | Vt.FloatArray | Vt.IntArray):
                np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=key)  # exact, no tolerance
            else:
                assert x == y, key


def _child_gone(cache):
    """The writer process has exited and was reaped; multiprocessing knows of no child either."""
    import multiprocessing

    return cache._proc.poll() is not None and multiprocessing.active_children() == []


def test_vec3f_direct_copy_reads_back_exactly():
    from hairwarp.io.usd_common import _direct_copy_works, _vec3f

    assert _direct_copy_works()  # else the writer falls back to FromNumpy, and this test would not test the copy
    rng = np.random.default_rng(3)
    for a in (rng.normal(size=(1001, 3)).astype(np.float32), rng.normal(size=(50, 6))[:, ::2],
              np.array([[np.float32(1e-38), -0.0, 3.4e38]], dtype=np.float32)):
        out = _vec3f(a)
        expected = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32))
        assert len(out) == len(expected)
        np.testing.assert_array_equal(np.asarray(out), np.asarray(expected))
    # Two arrays made in turn do not share storage.
    first, second = _vec3f(np.ones((4, 3))), _vec3f(np.zeros((4, 3)))
    assert np.asarray(first).sum() == 12.0 and np.asarray(second).sum() == 0.0


@pytest.mark.parametrize("suffix", [".usdc", ".usda"])
def test_background_writer_writes_the_inline_stage(tmp_path, suffix):
    from hairwarp.io.background import BackgroundCacheWriter

    inline, background = tmp_path / f"inline{suffix}", tmp_path / f"background{suffix}"
    _write_small_cache(inline)
    with pytest.MonkeyPatch.context() as m:  # the same frames through the background writer
        m.setitem(globals(), "CacheWriter", BackgroundCacheWriter)
        _write_small_cache(background)
    clips = [p.with_name(p.stem + ".clips").name for p in (inline, background)]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([inline.name, background.name, *clips])
    _assert_same_stage(inline, background)
    # The static topology is there too (compared above as default values): spot-check one against the input.
    stage = Usd.Stage.Open(str(background))
    assert list(UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides")).GetCurveVertexCountsAttr().Get()) \
        == [5, 5, 5]


def test_background_writer_y_up_animated_mesh_and_timings(tmp_path):
    from hairwarp.io.background import BackgroundCacheWriter

    pts, faces = _tetra()
    paths = {}
    for cls in (CacheWriter, BackgroundCacheWriter):
        path = paths[cls] = tmp_path / f"{cls.__name__}.usdc"
        with cls(path, fps=FPS, up_axis="Y", meters_per_unit=0.01) as cache:
            cache.add_curves("c", np.full(2, 4), basis="catmullRom")
            cache.add_mesh("blob", pts, faces, animated_points=True)
            for f in range(3):
                cache.write_frame(f, {"c": (_strands(2, 4, f), np.ones((8, 3)) * f)}, xforms={"blob": _xform(f)},
                                  mesh_points={"blob": pts * (1.0 + 0.1 * f)})
    _assert_same_stage(paths[CacheWriter], paths[BackgroundCacheWriter])
    assert set(cache.timings) == {"check", "copy", "wait", "convert", "set", "save"}
    assert cache.frames_saved == 3 and cache.timings["save"] > 0.0 and cache.timings["copy"] > 0.0
    assert _child_gone(cache)


def test_background_invalid_frame_raises_in_the_caller_and_keeps_earlier_frames(tmp_path):
    from hairwarp.io.background import BackgroundCacheWriter

    path = tmp_path / "bad.usdc"
    with BackgroundCacheWriter(path, fps=24) as cache:
        cache.add_curves("c", np.full(2, 4))
        for f in range(2):
            cache.write_frame(f, {"c": (_strands(2, 4, f), None)})
        nan = _strands(2, 4, 2)
        nan[3, 2] = np.nan
        with pytest.raises(UsdFileError, match=r"bad\.usdc: frame 2: curves 'c' points: contains NaN"):
            cache.write_frame(2, {"c": (nan, None)})
        with pytest.raises(UsdFileError, match=r"bad\.usdc: frame 2: .*\(8, 3\)"):
            cache.write_frame(2, {"c": (np.zeros((7, 3)), None)})
        with pytest.raises(UsdFileError, match="already used"):
            cache.add_curves("c", [4])
        cache.write_frame(3, {"c": (_strands(2, 4, 3), None)})
    stage = Usd.Stage.Open(str(path))
    attr = stage.GetPrimAtPath("/World/Hair/c").GetAttribute("points")
    assert attr.GetTimeSamples() == [0.0, 1.0, 3.0]
    np.testing.assert_array_equal(np.asarray(attr.Get(3)), _strands(2, 4, 3).astype(np.float32))
    assert _child_gone(cache)


def test_background_exception_inside_with_keeps_frames_and_ends_the_process(tmp_path):
    from hairwarp.io.background import BackgroundCacheWriter

    path = tmp_path / "crash.usdc"
    with pytest.raises(RuntimeError, match="solver blew up"):
        with BackgroundCacheWriter(path, fps=24) as cache:
            cache.add_curves("guides", np.full(2, 4))
            for f in range(5):
                if f == 3:
                    raise RuntimeError("solver blew up")
                cache.write_frame(f, {"guides": (_strands(2, 4, f), None)})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crash.partial"]
    stage = Usd.Stage.Open(str(cache.partial_path))
    attr = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides")).GetPointsAttr()
    assert attr.GetTimeSamples() == [0.0, 1.0, 2.0]
    assert _child_gone(cache)


def test_background_failure_in_the_process_names_the_file(tmp_path):
    import shutil

    from hairwarp.io.background import BackgroundCacheWriter

    folder = tmp_path / "shot"
    path = folder / "hair.usdc"
    cache = BackgroundCacheWriter(path, fps=24)
    cache.add_curves("c", np.full(2, 4))
    cache.write_frame(0, {"c": (_strands(2, 4, 0), None)})
    cache.flush()
    shutil.rmtree(folder)  # the working folder goes, a file takes its place: the next layer fails in the process
    folder.write_text("")
    cache.write_frame(1, {"c": (_strands(2, 4, 1), None)})
    with pytest.raises(CacheWriteError, match=r"shot/hair\.usdc: the background writer failed at frame 1"):
        for f in range(2, 50):  # raised by a later write_frame once the failure is reported
            cache.write_frame(f, {"c": (_strands(2, 4, f), None)})
            cache.flush()
    cache.close()  # already raised: the close does not raise it again, and ends the process
    assert _child_gone(cache)


def test_background_process_killed_is_reported(tmp_path):
    import os
    import signal

    from hairwarp.io.background import BackgroundCacheWriter

    path = tmp_path / "killed.usdc"
    cache = BackgroundCacheWriter(path, fps=24)
    cache.add_curves("c", np.full(2, 4))
    cache.write_frame(0, {"c": (_strands(2, 4, 0), None)})
    cache.flush()
    os.kill(cache._proc.pid, signal.SIGKILL)
    cache._proc.wait()
    with pytest.raises(UsdFileError, match=r"killed\.usdc: the background writer process ended unexpectedly .*keeps"):
        cache.write_frame(1, {"c": (_strands(2, 4, 1), None)})
        cache.close()
    cache._abandon()
    # The working folder holds the frame saved before the kill, and no lock.
    assert sorted(p.name for p in (tmp_path / "killed.partial").iterdir()) == ["killed.clips", "killed.usdc"]
    stage = Usd.Stage.Open(str(cache.partial_path))
    assert stage.GetPrimAtPath("/World/Hair/c").GetAttribute("points").GetTimeSamples() == [0.0]


def test_background_writer_dropped_without_close_ends_its_process(tmp_path):
    """A writer that is never closed (lost reference, or the interpreter exiting: the same hook runs at exit) ends
    its process and leaves the frames saved in the working folder, as the inline writer does."""
    import gc

    from hairwarp.io.background import BackgroundCacheWriter

    cache = BackgroundCacheWriter(tmp_path / "dropped.usdc", fps=24)
    cache.add_curves("c", np.full(2, 4))
    for f in range(2):
        cache.write_frame(f, {"c": (_strands(2, 4, f), None)})
    cache.flush()
    proc = cache._proc
    del cache
    gc.collect()
    assert proc.poll() is not None
    stage = Usd.Stage.Open(str(tmp_path / "dropped.partial" / "dropped.usdc"))
    assert stage.GetPrimAtPath("/World/Hair/c").GetAttribute("points").GetTimeSamples() == [0.0, 1.0]


def _root_frames(root):
    """(first, last) frame the working root layer names, as a resumed run reads them."""
    data = Sdf.Layer.OpenAsAnonymous(str(root)).customLayerData
    return data["hairwarp:firstFrame"], data["hairwarp:lastFrame"]


def test_commit_thread_commits_frames_in_order_each_complete_before_the_next(tmp_path, monkeypatch):
    """The commit thread saves frame N while the caller goes on; frame N+1's commit starts only once N is
    complete, and the working root is a valid cache of the frames it names after every frame."""
    import threading

    commits, overlapped = [], []
    original = CacheWriter._commit_frame

    def commit(self, frame, *args):
        overlapped.append(threading.current_thread() is not threading.main_thread())
        assert not commits or _root_frames(self.partial_path)[1] == commits[-1]  # the previous one is complete
        original(self, frame, *args)
        commits.append(frame)

    monkeypatch.setattr(CacheWriter, "_commit_frame", commit)
    path = tmp_path / "order.usdc"
    with CacheWriter(path, fps=FPS) as cache:
        cache.add_curves("c", np.full(2, 4))
        for f in range(6):
            points = _strands(2, 4, f)
            cache.write_frame(f, {"c": (points, None)})
            points[:] = np.nan  # the frame was copied: the caller may reuse its arrays at once
            assert cache.last_frame in (f - 1, f) if f else cache.last_frame in (None, 0)
            if f % 2:
                cache.flush()
                assert cache.last_frame == f and _root_frames(cache.partial_path) == (0, f)
                stage = Usd.Stage.Open(str(cache.partial_path))
                attr = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/c")).GetPointsAttr()
                assert attr.GetTimeSamples() == [float(k) for k in range(f + 1)]
                np.testing.assert_array_equal(np.asarray(attr.Get(f)), _strands(2, 4, f).astype(np.float32))
                del stage, attr  # else the next Open finds this root layer still loaded
    assert commits == list(range(6)) and all(overlapped)
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/c")).GetPointsAttr()
    assert attr.GetTimeSamples() == [float(k) for k in range(6)]
    for f in range(6):  # the Vt arrays reused every other frame held each frame's own values when it was saved
        np.testing.assert_array_equal(np.asarray(attr.Get(f)), _strands(2, 4, f).astype(np.float32))


@pytest.mark.parametrize("when", ["next frame", "close"])
def test_commit_thread_failure_is_raised_in_the_caller_and_keeps_the_frames_before(tmp_path, monkeypatch, when):
    """A full disk while the thread saves frame 2 is raised by the next write_frame (or by close) as the same
    CacheWriteError an unthreaded save raises, again on every later call; frames 0-1 stay a valid cache."""
    import errno

    import hairwarp.io.cache_folder as cache_folder

    original = cache_folder.fsync_path

    def fsync(path):
        if path.name.startswith("000002.tmp"):
            raise OSError(errno.ENOSPC, "No space left on device")
        original(path)

    monkeypatch.setattr(cache_folder, "fsync_path", fsync)
    path = tmp_path / "full.usdc"
    cache = CacheWriter(path, fps=FPS)
    cache.add_curves("c", np.full(2, 4))
    for f in range(3):
        cache.write_frame(f, {"c": (_strands(2, 4, f), None)})
    message = r"writing frame 2 to .*000002\.usdc failed: No space left on device"
    with pytest.raises(CacheWriteError, match=message):
        if when == "close":
            cache.close()
        else:
            cache.write_frame(3, {"c": (_strands(2, 4, 3), None)})
    assert cache.last_frame == 1 and not cache.closed
    with pytest.raises(CacheWriteError, match=message):  # the cache takes no frame after a gap
        cache.write_frame(4, {"c": (_strands(2, 4, 4), None)})
    assert cache.abandon() == cache.partial_path and not path.exists()
    assert _root_frames(cache.partial_path) == (0, 1)
    assert sorted(p.name for p in (tmp_path / "full.partial" / "full.clips").iterdir()) == \
        ["000000.usdc", "000001.usdc", "manifest.usdc", "topology.usdc"]
    stage = Usd.Stage.Open(str(cache.partial_path))
    assert UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/c")).GetPointsAttr().GetTimeSamples() == [0.0, 1.0]


def test_unpipelined_writer_completes_each_frame_before_returning(tmp_path):
    with CacheWriter(tmp_path / "sync.usdc", fps=FPS, pipelined=False) as cache:
        cache.add_curves("c", np.full(2, 4))
        for f in range(3):
            cache.write_frame(f, {"c": (_strands(2, 4, f), None)})
            assert cache.last_frame == f and _root_frames(cache.partial_path) == (0, f)


_TWO_CURVES = """#usda 1.0
(
    upAxis = "{up}"
    metersPerUnit = {mpu}
)
{extra}
def BasisCurves "hair"
{{
    uniform token type = "linear"
    int[] curveVertexCounts = {counts}
    point3f[] points = [(0,0,0),(0,0,-0.05),(0,0,-0.1),(0,0,-0.15),
                        (0.01,0,0),(0.01,0,-0.05),(0.01,0,-0.1),(0.01,0,-0.15)]
    {widths}
}}
"""


def _groom_stage(tmp_path, name, *, up="Z", mpu="1", extra="", counts="[4, 4]", widths=""):
    path = tmp_path / f"{name}.usda"
    path.write_text(_TWO_CURVES.format(up=up, mpu=mpu, extra=extra, counts=counts, widths=widths))
    return path


def test_usd_grooms_other_tools_write_are_read_or_refused_in_one_line(tmp_path):
    """Stage metadata that would mirror the groom (a negative metersPerUnit), make it NaN (0, nan) or be read as
    another axis (X up) is refused naming the file and the value; a placeholder curves prim beside real ones is
    skipped (it failed with zip's own message), an empty constant widths primvar is no widths (it raised an
    IndexError with a traceback), and curve counts below 1 and scipy's knot errors name the file and the prim."""
    from hairwarp.groom import Groom, GroomError

    for mpu in ("-1", "0", "nan"):
        with pytest.raises(UsdFileError, match=f"metersPerUnit = {mpu}.*; it must be a finite number > 0"):
            read_curves(_groom_stage(tmp_path, f"mpu{mpu}", mpu=mpu))
    with pytest.raises(UsdFileError, match="upAxis = 'X'; USD stages are Y or Z up"):
        read_curves(_groom_stage(tmp_path, "xup", up="X"))
    placeholder = 'def BasisCurves "placeholder"\n{\n    uniform token type = "linear"\n}'
    groom = Groom.load(_groom_stage(tmp_path, "placeholder", extra=placeholder))
    assert groom.strand_count == 2 and np.allclose(groom.lengths(), 0.15)
    empty = 'float[] primvars:widths = [] (interpolation = "constant")'
    groom = Groom.load(_groom_stage(tmp_path, "empty_widths", widths=empty))
    assert groom.strand_count == 2 and groom.widths is None
    for counts, value in (("[8, 0]", "0"), ("[10, -2]", "-2")):
        with pytest.raises((UsdFileError, GroomError), match=f"/hair: curveVertexCounts holds {value} \\(curve 1\\)"):
            Groom.load(_groom_stage(tmp_path, f"counts{value}", counts=counts))
    nurbs = tmp_path / "nurbs.usda"
    nurbs.write_text("""#usda 1.0
def NurbsCurves "n"
{
    int[] curveVertexCounts = [4]
    int[] order = [4]
    double[] knots = [0, 0, 0, 0, 1, 0.5, 1, 1]
    point3f[] points = [(0,0,0),(0,0,-0.05),(0,0,-0.1),(0,0,-0.15)]
}
""")
    with pytest.raises((UsdFileError, GroomError), match=f"{nurbs}: /n: NURBS curve 0: "):
        Groom.load(nurbs)


def test_head_motion_stages_with_values_a_run_cannot_take_are_refused_naming_the_file(tmp_path):
    """A head prim keyed to NaN (numpy's 'SVD did not converge', naming nothing) or to 1e300 m (a run that faulted
    at frame 1 with advice for the step API), and a negative timeCodesPerSecond (read as key times out of order), are
    refused naming the file, the prim and the time code; a file name that is not UTF-8, which USD cannot take, is
    named too (the codec's message named nothing)."""
    from hairwarp.io.usd_anim import read_prim_motion
    from hairwarp.io.usd_common import check_usd_path

    def stage(name, last, rate=24):
        path = tmp_path / f"{name}.usda"
        path.write_text(f"""#usda 1.0
(
    metersPerUnit = 1
    timeCodesPerSecond = {rate}
    upAxis = "Z"
)
def Xform "Head"
{{
    double3 xformOp:translate.timeSamples = {{1: (0, 0, 0), 3: {last}}}
    uniform token[] xformOpOrder = ["xformOp:translate"]
}}
""")
        return path

    times, poses = read_prim_motion(stage("ok", "(0.1, 0, 0)"), "/Head")
    assert np.allclose(poses[-1][:3, 3], (0.1, 0.0, 0.0)) and np.allclose(times[-1] - times[0], 2 / 24)
    with pytest.raises(UsdFileError, match="nan.usda: /Head: its world transform at time code 2 is not finite"):
        read_prim_motion(stage("nan", "(nan, 0, 0)"), "/Head")
    with pytest.raises(UsdFileError, match="far.usda: /Head: its world transform at time code 2 puts it at .* beyond"):
        read_prim_motion(stage("far", "(1e300, 0, 0)"), "/Head")
    with pytest.raises(UsdFileError, match="rate.usda: timeCodesPerSecond = -24.0; it must be a finite number > 0"):
        read_prim_motion(stage("rate", "(0.1, 0, 0)", rate=-24), "/Head")
    with pytest.raises(UsdFileError, match=r"o\\xffx.usdc: USD takes UTF-8 file names only"):
        check_usd_path(os.fsdecode(b"out/o\xffx.usdc"))
