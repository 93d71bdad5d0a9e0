"""The cache as other programs read it: Unreal's groom conventions, collider normals and purpose, the stage's up
axis, units and start frame; and grooms from USD (widths, root UVs, Bezier, B-spline and NURBS curves, purpose)
through a run back into the cache. Everything is read back with usd-core and compared with closed forms or SciPy."""

from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

import hairwarp as hw
from hairwarp.io.usd_groom import SAMPLES_PER_SEGMENT, read_groom
from hairwarp.runner import simulate

SCENES = Path(__file__).resolve().parents[1] / "scenes"

F32_M = 1e-6
"""Tolerance on positions [m] read back from float32 USD arrays: a few ulps at 2 m (1.2e-7 m each)."""
F32_REL = 1e-6
"""Relative tolerance on float32 values read back (widths, UVs): float32 has 6e-8 relative resolution."""
EVAL_ATOL = 1e-12
"""Tolerance of float64 curve evaluation against SciPy or a closed form [m]: rounding only."""


def _run(tmp_path, name, *overrides, scene="tiny.toml", frames=2):
    sc = hw.Scene.load(SCENES / scene, overrides=[f"sim.frames={frames}", "output.preview=false", *overrides])
    out = tmp_path / f"{name}.usdc"
    simulate(sc, out, progress=False)
    return out, sc


def _stage_to_metres_z(stage, p):
    """Points of a stage in its own up axis and unit -> metres, Z up, written out here from USD's definitions:
    a Y-up (x, y, z) is the Z-up (x, -z, y)."""
    p = np.asarray(p, dtype=np.float64) * UsdGeom.GetStageMetersPerUnit(stage)
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y:
        p = np.column_stack([p[:, 0], -p[:, 2], p[:, 1]])
    return p


@pytest.fixture(scope="module")
def dense_cache(tmp_path_factory):
    return _run(tmp_path_factory.mktemp("cache"), "dense", "dense.count=24")


def test_unreal_groom_conventions(dense_cache):
    """Every schema and primvar Unreal's USD groom importer reads, with its type and interpolation: the GroomAPI
    schema on the groom prims, points, curveVertexCounts, widths (vertex), and per-curve (uniform) groom_id (int),
    groom_guide (int), groom_root_uv (float2) beside the standard st (texCoord2f); guides of purpose guide."""
    path, scene = dense_cache
    stage = Usd.Stage.Open(str(path))
    hair_root = stage.GetPrimAtPath("/World/Hair")
    assert "GroomAPI" in hair_root.GetPrimTypeInfo().GetAppliedAPISchemas()
    expected = {"hair": (24, 0, UsdGeom.Tokens.default_), "guides": (8, 1, UsdGeom.Tokens.guide)}
    uvs = {}
    for name, (count, guide, purpose) in expected.items():
        prim = stage.GetPrimAtPath(f"/World/Hair/{name}")
        curves = UsdGeom.BasisCurves(prim)
        assert "GroomAPI" in prim.GetPrimTypeInfo().GetAppliedAPISchemas()
        assert UsdGeom.Imageable(prim).ComputePurpose() == purpose
        counts = np.asarray(curves.GetCurveVertexCountsAttr().Get())
        assert len(counts) == count
        t = Usd.TimeCode(1.0)
        assert curves.GetPointsAttr().GetTypeName() == Sdf.ValueTypeNames.Point3fArray
        assert len(curves.GetPointsAttr().Get(t)) == counts.sum()
        assert curves.GetWidthsAttr().GetTypeName() == Sdf.ValueTypeNames.FloatArray
        assert curves.GetWidthsInterpolation() == UsdGeom.Tokens.vertex
        assert len(curves.GetWidthsAttr().Get()) == counts.sum()
        api = UsdGeom.PrimvarsAPI(prim)
        for pv_name, type_name in (("groom_id", Sdf.ValueTypeNames.IntArray),
                                   ("groom_guide", Sdf.ValueTypeNames.IntArray),
                                   ("groom_root_uv", Sdf.ValueTypeNames.Float2Array),
                                   ("st", Sdf.ValueTypeNames.TexCoord2fArray)):
            pv = api.GetPrimvar(pv_name)
            assert pv, f"{name}: primvars:{pv_name} missing"
            assert pv.GetTypeName() == type_name, (name, pv_name, pv.GetTypeName())
            assert pv.GetInterpolation() == UsdGeom.Tokens.uniform, (name, pv_name)
            assert len(pv.Get()) == count
        np.testing.assert_array_equal(np.asarray(api.GetPrimvar("groom_id").Get()), np.arange(count))
        np.testing.assert_array_equal(np.asarray(api.GetPrimvar("groom_guide").Get()), np.full(count, guide))
        st = np.asarray(api.GetPrimvar("st").Get())
        np.testing.assert_array_equal(st, np.asarray(api.GetPrimvar("groom_root_uv").Get()))
        assert st.min() >= 0.0 and st.max() <= 1.0 + F32_REL
        uvs[name] = st
    # the guides' st: the generator's root chart moved and scaled uniformly into the unit square
    chart = scene.build_groom().root_uv
    lo = chart.min(axis=0)
    np.testing.assert_allclose(uvs["guides"], (chart - lo) / np.max(chart.max(axis=0) - lo), atol=F32_REL)


def test_collider_normals_and_purpose(dense_cache, tmp_path):
    """The head mesh has unit vertex normals pointing out of the ellipsoid it approximates (a closed form: the
    ellipsoid's gradient direction, within 0.2 rad on a coarse mesh) and purpose proxy; output.collider_purpose =
    "render" keeps it renderable."""
    path, scene = dense_cache
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Colliders/head"))
    assert UsdGeom.Imageable(mesh.GetPrim()).ComputePurpose() == UsdGeom.Tokens.proxy
    assert mesh.GetNormalsAttr().GetTypeName() == Sdf.ValueTypeNames.Normal3fArray
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    n = np.asarray(mesh.GetNormalsAttr().Get(), dtype=np.float64)
    assert n.shape == pts.shape
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    radii = np.asarray(scene.groom.scalp_radii)
    grad = (pts - pts.mean(axis=0)) / radii**2  # the mesh is symmetric about the ellipsoid's centre
    grad /= np.linalg.norm(grad, axis=1, keepdims=True)
    assert np.arccos(np.clip(np.sum(grad * n, axis=1), -1, 1)).max() < 0.2

    out, _ = _run(tmp_path, "render", 'output.collider_purpose="render"', frames=1)
    stage = Usd.Stage.Open(str(out))
    prim = stage.GetPrimAtPath("/World/Colliders/head")
    assert UsdGeom.Imageable(prim).ComputePurpose() == UsdGeom.Tokens.render


def test_up_axis_units_start_frame(dense_cache, tmp_path):
    """A cache written Y up in centimetres from frame 1001 holds, read with its stage's own metadata, the same
    world points (hair, guides, the head mesh through its transform) as the Z-up metre cache from frame 0."""
    ref_path, _ = dense_cache
    path, _ = _run(tmp_path, "ycm", "dense.count=24", 'output.up_axis="Y"', "output.meters_per_unit=0.01",
                   "output.start_frame=1001")
    ref, got = Usd.Stage.Open(str(ref_path)), Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(got) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(got) == 0.01
    assert (got.GetStartTimeCode(), got.GetEndTimeCode()) == (1001.0, 1003.0)
    assert (ref.GetStartTimeCode(), ref.GetEndTimeCode()) == (0.0, 2.0)
    for frame in range(3):
        for prim_path in ("/World/Hair/hair", "/World/Hair/guides", "/World/Colliders/head"):
            worlds = []
            for stage, t in ((ref, frame), (got, 1001 + frame)):
                prim = stage.GetPrimAtPath(prim_path)
                tc = Usd.TimeCode(t)
                p = np.asarray(UsdGeom.PointBased(prim).GetPointsAttr().Get(tc), dtype=np.float64)
                m = np.asarray(UsdGeom.XformCache(tc).GetLocalToWorldTransform(prim), dtype=np.float64)
                worlds.append(_stage_to_metres_z(stage, p @ m[:3, :3] + m[3, :3]))
            np.testing.assert_allclose(worlds[1], worlds[0], atol=F32_M, err_msg=f"{prim_path} frame {frame}")
        widths = [np.asarray(UsdGeom.BasisCurves(s.GetPrimAtPath("/World/Hair/hair")).GetWidthsAttr().Get())
                  * UsdGeom.GetStageMetersPerUnit(s) for s in (ref, got)]
        np.testing.assert_allclose(widths[1], widths[0], rtol=F32_REL)


def test_cli_cache_options(monkeypatch):
    """--up-axis, --meters-per-unit (--units) and --start-frame become the output keys of the scene."""
    from hairwarp import cli

    seen = {}
    monkeypatch.setattr("hairwarp.runner.simulate", lambda scene, out, **kw: seen.setdefault("scene", scene) and
                        (_ for _ in ()).throw(SystemExit(0)))
    with pytest.raises(SystemExit):
        cli.main(["run", str(SCENES / "tiny.toml"), "--up-axis", "Y", "--units", "0.01", "--start-frame", "1001"])
    out = seen["scene"].output
    assert (out.up_axis, out.meters_per_unit, out.start_frame) == ("Y", 0.01, 1001)


# --- grooms from USD -----------------------------------------------------------------------------------------

ROOTS = np.array([[0.02, 0.0, 1.715], [-0.02, 0.01, 1.714], [0.0, -0.02, 1.713], [0.0, 0.03, 1.712]])
LINEAR_WIDTHS = np.array([4e-4, 3e-4, 2e-4, 1e-4])
ST = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6], [0.7, 0.8]])


def _bezier_ctrl(root):
    """7 control points (two cubic segments sharing a point), rising 0.12 m with a sideways bow."""
    z = np.linspace(0.0, 0.12, 7)
    return root + np.column_stack([0.02 * np.sin(np.linspace(0, np.pi, 7)), np.zeros(7), z])


def _nurbs_ctrl(root):
    z = np.linspace(0.0, 0.12, 6)
    return root + np.column_stack([np.zeros(6), 0.015 * np.sin(np.linspace(0, np.pi, 6)), z])


NURBS_KNOTS = [0.0, 0.0, 0.0, 0.0, 0.3, 0.6, 1.0, 1.0, 1.0, 1.0]  # order 4, 6 points, clamped, 3 spans


def _write_groom(path: Path, *, guide_purpose: bool = False, up_axis="Z", mpu=1.0):
    """A groom written with usd-core alone: a linear curve with vertex widths and st, a cubic Bezier, a NURBS
    curve (both with a constant width and st), and, with ``guide_purpose``, a second copy of the linear curve as
    a prim of purpose guide."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, up_axis)
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    k = 1.0 / mpu

    def to_stage(p):
        p = np.asarray(p) * k
        return p if up_axis == "Z" else np.column_stack([p[:, 0], p[:, 2], -p[:, 1]])

    def st(prim, values):
        UsdGeom.PrimvarsAPI(prim).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                UsdGeom.Tokens.uniform).Set(Vt.Vec2fArray.FromNumpy(
                                                    np.asarray(values, dtype=np.float32)))

    lines = [ROOTS[0] + np.outer(np.linspace(0, 1, 4), [0.0, 0.05, 0.1]),
             ROOTS[1] + np.outer(np.linspace(0, 1, 4), [0.0, -0.05, 0.1])]
    lin = UsdGeom.BasisCurves.Define(stage, "/groom/linear")
    lin.CreateTypeAttr(UsdGeom.Tokens.linear)
    lin.CreateCurveVertexCountsAttr([4, 4])
    lin.CreatePointsAttr([Gf.Vec3f(*map(float, p)) for p in to_stage(np.concatenate(lines))])
    lin.CreateWidthsAttr(list(np.tile(LINEAR_WIDTHS, 2) * k))
    lin.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
    st(lin.GetPrim(), ST[:2])

    bez = UsdGeom.BasisCurves.Define(stage, "/groom/bezier")
    bez.CreateTypeAttr(UsdGeom.Tokens.cubic)
    bez.CreateBasisAttr(UsdGeom.Tokens.bezier)
    bez.CreateCurveVertexCountsAttr([7])
    bez.CreatePointsAttr([Gf.Vec3f(*map(float, p)) for p in to_stage(_bezier_ctrl(ROOTS[2]))])
    bez.CreateWidthsAttr([3e-4 * k])
    bez.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    st(bez.GetPrim(), ST[2:3])

    nurbs = UsdGeom.NurbsCurves.Define(stage, "/groom/nurbs")
    nurbs.CreateCurveVertexCountsAttr([6])
    nurbs.CreateOrderAttr([4])
    nurbs.CreateKnotsAttr(NURBS_KNOTS)
    nurbs.CreatePointsAttr([Gf.Vec3f(*map(float, p)) for p in to_stage(_nurbs_ctrl(ROOTS[3]))])
    nurbs.CreateWidthsAttr([2e-4 * k])
    nurbs.SetWidthsInterpolation(UsdGeom.Tokens.constant)
    st(nurbs.GetPrim(), ST[3:4])

    if guide_purpose:
        g = UsdGeom.BasisCurves.Define(stage, "/guides/linear")
        g.CreateTypeAttr(UsdGeom.Tokens.linear)
        g.CreateCurveVertexCountsAttr([4])
        g.CreatePointsAttr([Gf.Vec3f(*map(float, p)) for p in to_stage(lines[0])])
        g.CreatePurposeAttr(UsdGeom.Tokens.guide)
    stage.GetRootLayer().Save()
    return path


def test_bezier_and_nurbs_evaluation(tmp_path):
    """Bezier curves are evaluated, not taken control point by control point (7 points -> 2 segments), equal to
    SciPy's Bernstein polynomials (BPoly); NURBS equal SciPy's BSpline de Boor evaluation of the same knots; a
    rational quadratic NURBS quarter circle stays on the unit circle (closed form); a pinned B-spline starts and
    ends at its end points and passes through (P[i-1] + 4 P[i] + P[i+1]) / 6 at its knots."""
    from scipy.interpolate import BPoly, BSpline

    data = read_groom(_write_groom(tmp_path / "g.usda"))
    lines = data["curves"]
    assert len(lines) == 4
    bez = lines[2]
    assert len(bez) == 2 * SAMPLES_PER_SEGMENT + 1
    ctrl = _bezier_ctrl(ROOTS[2])
    ref = BPoly(np.stack([ctrl[:4], ctrl[3:]], axis=1), [0.0, 1.0, 2.0])
    np.testing.assert_allclose(bez, ref(np.linspace(0.0, 2.0, len(bez))), atol=EVAL_ATOL * 1e3)
    nurbs = lines[3]
    assert len(nurbs) == 3 * SAMPLES_PER_SEGMENT + 1
    # A de Boor evaluation at the spans' own sample parameters (the curve's sample spacing is uniform in t)
    ref = BSpline(np.array(NURBS_KNOTS), _nurbs_ctrl(ROOTS[3]), 3)(np.linspace(0.0, 1.0, len(nurbs)))
    np.testing.assert_allclose(nurbs, ref, atol=EVAL_ATOL * 1e3)
    np.testing.assert_allclose(nurbs[[0, -1]], _nurbs_ctrl(ROOTS[3])[[0, -1]], atol=EVAL_ATOL * 1e3)

    # rational quarter circle of radius 1 about the origin
    stage = Usd.Stage.CreateNew(str(tmp_path / "arc.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)  # USD's fallbacks are Y up and centimetres
    arc = UsdGeom.NurbsCurves.Define(stage, "/arc")
    arc.CreateCurveVertexCountsAttr([3])
    arc.CreateOrderAttr([3])
    arc.CreateKnotsAttr([0, 0, 0, 1, 1, 1])
    arc.CreatePointsAttr([(1, 0, 0), (1, 1, 0), (0, 1, 0)])
    arc.CreatePointWeightsAttr([1.0, np.sqrt(0.5), 1.0])
    stage.GetRootLayer().Save()
    pts = read_groom(tmp_path / "arc.usda")["curves"][0]
    np.testing.assert_allclose(np.linalg.norm(pts, axis=1), 1.0, atol=1e-7)  # float32 control points

    # pinned uniform B-spline
    stage = Usd.Stage.CreateNew(str(tmp_path / "bs.usda"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)  # USD's fallbacks are Y up and centimetres
    bs = UsdGeom.BasisCurves.Define(stage, "/bs")
    bs.CreateTypeAttr(UsdGeom.Tokens.cubic)
    bs.CreateBasisAttr(UsdGeom.Tokens.bspline)
    bs.CreateWrapAttr(UsdGeom.Tokens.pinned)
    p = np.array([[0, 0, 0], [1, 0, 1], [2, 1, 0], [3, 0, 2], [4, 2, 1]], dtype=np.float64)
    bs.CreateCurveVertexCountsAttr([5])
    bs.CreatePointsAttr([Gf.Vec3f(*q) for q in p])
    stage.GetRootLayer().Save()
    got = read_groom(tmp_path / "bs.usda")["curves"][0]
    assert len(got) == 4 * SAMPLES_PER_SEGMENT + 1  # 5 points + 2 phantoms -> 4 segments
    np.testing.assert_allclose(got[[0, -1]], p[[0, -1]], atol=1e-6)
    for i in (1, 2, 3):
        np.testing.assert_allclose(got[i * SAMPLES_PER_SEGMENT], (p[i - 1] + 4 * p[i] + p[i + 1]) / 6, atol=1e-6)


def test_groom_purpose_selection(tmp_path):
    """A stage with guides (purpose guide) and render curves: "auto" and "guide" take the guides, "render" the
    others, "all" both; the scene key groom.purpose says which."""
    path = _write_groom(tmp_path / "g.usda", guide_purpose=True)
    counts = {p: len(read_groom(path, purpose=p)["curves"]) for p in ("auto", "guide", "render", "all")}
    assert counts == {"auto": 1, "guide": 1, "render": 4, "all": 5}
    assert hw.Groom.load(path, purpose="render").strand_count == 4
    with pytest.raises(hw.SceneError, match="purpose"):
        hw.Scene.load(SCENES / "tiny.toml", overrides=['groom.purpose="guide"'])


@pytest.mark.parametrize("up_axis,mpu", [("Z", 1.0), ("Y", 0.01)])
def test_usd_groom_round_trip(tmp_path, up_axis, mpu):
    """A groom with widths, root UVs, a Bezier and a NURBS curve, written with usd-core (Z up in metres, or Y up
    in centimetres), loaded, simulated for two frames, cached and read back with usd-core: as many curves, the
    roots where the file put them (frame 0), the widths of the file at root and tip, and its st per curve."""
    groom_path = _write_groom(tmp_path / "groom.usda", up_axis=up_axis, mpu=mpu)
    groom = hw.Groom.load(groom_path)
    assert groom.strand_count == 4
    np.testing.assert_allclose(groom.roots(), ROOTS, atol=F32_M)
    np.testing.assert_allclose(groom.surface_uv, ST, atol=F32_REL)
    np.testing.assert_allclose(groom.widths[0], LINEAR_WIDTHS, rtol=F32_REL)
    np.testing.assert_allclose(groom.widths[2], 3e-4, rtol=F32_REL)

    scene_file = tmp_path / "scene.toml"
    scene_file.write_text(f"""
[scene]
name = "usd_groom"
[sim]
fps = 30.0
segments = 6
substeps = 4
[groom]
file = "{groom_path.name}"
[head]
shape = "ellipsoid"
center = [0.0, 0.0, 1.6]
radii = [0.085, 0.1, 0.11]
[head.motion]
kind = "nod"
amplitude_deg = 10.0
""")
    out = tmp_path / "cache.usdc"
    simulate(hw.Scene.load(scene_file, overrides=["sim.frames=2", "output.preview=false"]), out,
             progress=False)
    stage = Usd.Stage.Open(str(out))
    guides = UsdGeom.BasisCurves(stage.GetPrimAtPath("/World/Hair/guides"))
    counts = np.asarray(guides.GetCurveVertexCountsAttr().Get())
    assert len(counts) == 4 and np.all(counts == 7)
    pts = np.asarray(guides.GetPointsAttr().Get(Usd.TimeCode(0.0)), dtype=np.float64)
    np.testing.assert_allclose(pts[np.cumsum(counts) - counts], ROOTS, atol=F32_M)
    widths = np.asarray(guides.GetWidthsAttr().Get(), dtype=np.float64).reshape(4, 7)
    np.testing.assert_allclose(widths[0, [0, -1]], LINEAR_WIDTHS[[0, -1]], rtol=F32_REL)
    np.testing.assert_allclose(widths[2], 3e-4, rtol=F32_REL)
    np.testing.assert_allclose(widths[3], 2e-4, rtol=F32_REL)
    st = np.asarray(UsdGeom.PrimvarsAPI(guides.GetPrim()).GetPrimvar("st").Get())
    np.testing.assert_allclose(st, ST, atol=F32_REL)
    # and the cache loads back as a groom with the same UVs and widths
    again = hw.Groom.load(out)
    np.testing.assert_allclose(again.surface_uv, ST, atol=F32_REL)
    np.testing.assert_allclose(again.widths[3], 2e-4, rtol=F32_REL)


@pytest.mark.parametrize("layout", ["clips", "single"])
def test_omniverse_asset_validator(dense_cache, tmp_path, layout):
    """NVIDIA's omniverse-asset-validator (its default rules, usd-core's among them) reports no failure and no
    error on a cache with dense hair, guides and a collider, in both layouts (.usdc; ASCII layers of this size
    are reported as slow by its UsdAsciiPerformanceChecker, as they should be)."""
    av = pytest.importorskip("omni.asset_validator", reason="omniverse-asset-validator is not installed "
                                                           "(pip install -e '.[test]')")
    path = dense_cache[0] if layout == "clips" else _run(tmp_path, "single", "dense.count=24",
                                                          'output.layout="single"')[0]
    issues = av.ValidationEngine(init_rules=True).validate(str(path)).issues()
    bad = [f"{i.rule.__name__ if i.rule else '?'}: {i.message}" for i in issues
           if i.severity in (av.IssueSeverity.FAILURE, av.IssueSeverity.ERROR)]
    assert not bad, bad
