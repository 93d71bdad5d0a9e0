"""USD caches and grooms: everything written is read back with usd-core (pxr) directly, and the readers are checked
against stages authored by hand with pxr and numbers worked out by hand."""

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdUtils, Vt

from hairwarp.usd import CacheWriter, UsdFileError, describe, read_curves, read_frames, write_curves

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
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache.usdc"], "temporary file left behind"

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
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crash.usdc"]
    stage = Usd.Stage.Open(str(path))
    attr = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides")).GetPointsAttr()
    assert attr.GetTimeSamples() == [0.0, 1.0]
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 1)
    np.testing.assert_array_equal(np.asarray(attr.Get(1)), _strands(2, 4, 1).astype(np.float32))
    assert cache.close() == path  # idempotent


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
