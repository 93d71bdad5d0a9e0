"""Grooms: resampling, validation, the scalp generator, TressFX and .hair I/O, load dispatch.

Each check is against something independent: closed forms (straight lines, an L-shaped polyline,
a circle arc, the ellipsoid's implicit equation and gradient), a k-d tree over a dense sampling of
the ellipsoid, raw ``struct`` / ``np.frombuffer`` parses of the same bytes, and the body mesh's own
normals for the TressFX asset.
"""

import functools
import math
import struct
import sys
import types
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from hairwarp.groom import Groom, GroomError, scalp_groom
from hairwarp.io.cem_hair import read_hair, write_hair
from hairwarp.io.tfx import read_tfx

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RATBOY = DATA / "tressfx_ratboy" / "Ratboy_mohawk.tfx"
RATBOY_BODY = DATA / "tressfx_ratboy" / "Ratboy_body.tfxmesh"

RTOL_F64 = 1e-9  # float64 arithmetic on lengths of order 1
ATOL_EXACT = 1e-12  # closed-form positions in float64 [m]
RTOL_F32 = 1.2e-7  # .hair stores float32: one rounding, half an ulp (6e-8) relative, with slack
ARC_RTOL = 1e-6  # 2000 chords of an arc: chord deficit (pi f / S)^2 / 6 ~ 1e-7, plus the 20000-point polyline
CLEARANCE_FRACTION = 0.99  # clearance vs margin; the 0.7 mm sampling below overestimates a 4 mm gap by < 0.8 %
ROOT_NORMAL_MEDIAN_DEG = 20.0  # sphere-fit normals vs the Ratboy body mesh's normals (measured 17 deg)

SCALP_C = np.array([0.0, 0.0, 1.6])
SCALP_R = np.array([0.085, 0.1, 0.11])


def _record_warnings(fn, *args, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = fn(*args, **kwargs)
    return result, [w for w in caught if issubclass(w.category, UserWarning)]


def _polyline_length(a):
    return float(sum(np.linalg.norm(a[i + 1] - a[i]) for i in range(len(a) - 1)))


# --------------------------------------------------------------------------------------------
# resample


def test_resample_straight_polyline_equal_segments_and_exact_ends():
    start, end = np.array([0.1, -0.2, 1.5]), np.array([0.4, 0.3, 1.1])
    t = np.array([0.0, 0.05, 0.1, 0.13, 0.5, 0.51, 0.9, 1.0])  # uneven input spacing
    line = start + t[:, None] * (end - start)
    total = float(np.linalg.norm(end - start))
    for segments in (1, 3, 7, 20):
        out = Groom.from_polylines([line]).resample(segments)
        assert out.shape == (1, segments + 1, 3) and out.dtype == np.float64
        seg = np.linalg.norm(np.diff(out[0], axis=0), axis=1)
        np.testing.assert_allclose(seg, total / segments, rtol=RTOL_F64)
        assert abs(seg.sum() - total) <= RTOL_F64 * total
        assert (out[0, 0] == line[0]).all() and (out[0, -1] == line[-1]).all()


def test_resample_bent_polyline_follows_arc_length():
    a, b = 0.3, 0.5  # an L: along x, then along y; zero-length segment in the middle
    line = np.array([[0, 0, 0], [0.1, 0, 0], [a, 0, 0], [a, 0, 0], [a, 0.2, 0], [a, b, 0]], dtype=float)
    segments = 16
    out = Groom.from_polylines([line]).resample(segments)[0]
    s = np.arange(segments + 1) * (a + b) / segments
    expected = np.where(s[:, None] <= a, np.column_stack((s, 0 * s, 0 * s)), np.column_stack((a + 0 * s, s - a, 0 * s)))
    np.testing.assert_allclose(out, expected, rtol=0, atol=ATOL_EXACT)


def test_resample_circle_arc_length_converges():
    radius, fraction = 0.2, 0.3
    angle = np.linspace(0.0, 2 * np.pi * fraction, 20001)
    arc = np.column_stack((radius * np.cos(angle), radius * np.sin(angle), np.zeros_like(angle)))
    out = Groom.from_polylines([arc]).resample(2000)[0]
    chord_sum = np.linalg.norm(np.diff(out, axis=0), axis=1).sum()
    assert abs(chord_sum - 2 * np.pi * radius * fraction) <= ARC_RTOL * 2 * np.pi * radius * fraction
    # resampled points stay on the fine polyline, within its sag r (1 - cos(dphi / 2)) of the circle
    sag = radius * (1 - math.cos(angle[1] / 2))
    assert np.abs(np.linalg.norm(out[:, :2], axis=1) - radius).max() <= sag * 1.01


def test_resample_rejects_bad_segment_count():
    groom = Groom.from_polylines([[[0, 0, 0], [0, 0, 1]]])
    for bad in (0, -2, 2.5):
        with pytest.raises(GroomError, match="segments"):
            groom.resample(bad)


# --------------------------------------------------------------------------------------------
# from_polylines, accessors, transforms, subsets


def test_from_polylines_drops_short_strands_with_one_warning():
    long_ = [[0, 0, 0], [0, 0, -0.1]]
    short = [[0, 0, 0], [0, 0, -5e-4]]
    lines = [long_, short, long_, short, short, long_]
    uv = np.arange(12, dtype=float).reshape(6, 2)
    groom, caught = _record_warnings(
        Groom.from_polylines,
        lines,
        source="unit-test",
        root_uv=uv,
        root_normal=np.tile([0, 0, 2.0], (6, 1)),
        grid_shape=(2, 3),
    )
    assert len(caught) == 1
    text = str(caught[0].message)
    assert "3" in text and "unit-test" in text
    assert groom.strand_count == 3
    np.testing.assert_array_equal(groom.root_uv, uv[[0, 2, 5]])
    np.testing.assert_array_equal(groom.root_normal, np.tile([0, 0, 1.0], (3, 1)))
    assert groom.grid_shape is None
    _, none = _record_warnings(Groom.from_polylines, [long_, long_], grid_shape=(1, 2))
    assert none == []


@pytest.mark.parametrize(
    "bad, what",
    [
        ([[0, 0, 0]], "has 1 point; a strand needs at least 2"),  # one vertex
        ([[0, 0], [1, 1]], "shape"),  # 2-D points
        ([[0, 0, 0], [0, np.nan, 1]], r"vertex 1 is not finite \(0, nan, 1\)"),
        ([[0, 0, 0], [0, 0, 1], [0, np.inf, 1]], r"vertex 2 is not finite \(0, inf, 1\)"),
        ("abc", "numeric"),
    ],
)
def test_from_polylines_errors_name_strand_and_source(bad, what):
    good = [[0, 0, 0], [0, 0, 1]]
    with pytest.raises(GroomError, match=rf"my-groom: strand 2 .*{what}|my-groom: strand 2 {what}") as info:
        Groom.from_polylines([good, good, bad, good], source="my-groom")
    assert isinstance(info.value, ValueError)


def test_from_polylines_errors_for_metadata_and_empty():
    good = [[0, 0, 0], [0, 0, 1]]
    with pytest.raises(GroomError, match="no strands"):
        Groom.from_polylines([])
    with pytest.raises(GroomError, match="root_uv"):
        Groom.from_polylines([good, good], root_uv=np.zeros((3, 2)))
    with pytest.raises(GroomError, match="grid_shape"):
        Groom.from_polylines([good, good], grid_shape=(2, 2))
    with pytest.raises(GroomError, match="root_normal of strand 1"):
        Groom.from_polylines([good, good], root_normal=[[0, 0, 1], [0, 0, 0]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(GroomError, match="all 2 strands"):
            Groom.from_polylines([good, good], min_length=2.0, source="s")


def test_accessors_against_direct_computation():
    rng = np.random.default_rng(3)
    lines = [np.cumsum(rng.normal(size=(n, 3)), axis=0) for n in (2, 5, 9)]
    groom = Groom.from_polylines(lines, min_length=0.0)
    assert groom.strand_count == 3
    np.testing.assert_allclose(groom.lengths(), [_polyline_length(a) for a in lines], rtol=RTOL_F64)
    np.testing.assert_array_equal(groom.roots(), [a[0] for a in lines])
    allv = np.concatenate(lines)
    lo, hi = groom.bounds()
    np.testing.assert_array_equal(lo, allv.min(axis=0))
    np.testing.assert_array_equal(hi, allv.max(axis=0))


def test_transformed_maps_points_and_normals():
    groom = scalp_groom(count=40, length=0.1, points=6)
    scale = np.diag([2.0, 0.5, 1.5])
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # +90 deg about z
    m = np.eye(4)
    m[:3, :3] = rot @ scale
    m[:3, 3] = (0.3, -0.1, 0.2)
    moved = groom.transformed(m)
    for a, b in zip(groom.strands, moved.strands, strict=True):
        np.testing.assert_allclose(b, a @ (rot @ scale).T + m[:3, 3], rtol=0, atol=ATOL_EXACT)
    # The image of the ellipsoid is an ellipsoid too; its implicit gradient at the new roots is the normal.
    a_inv = np.linalg.inv(m[:3, :3])
    y = (moved.roots() - m[:3, 3] - rot @ scale @ SCALP_C) @ a_inv.T  # back in the head's frame, minus centre
    grad = (y / SCALP_R**2) @ a_inv
    expected = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    np.testing.assert_allclose(moved.root_normal, expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(moved.root_uv, groom.root_uv)
    assert moved.grid_shape == groom.grid_shape
    np.testing.assert_allclose(groom.transformed(rot).roots(), groom.roots() @ rot.T, atol=ATOL_EXACT)
    bad = np.eye(4)
    bad[3, 0] = 1.0
    for matrix in (bad, np.zeros((3, 3)), np.eye(2)):
        with pytest.raises(GroomError, match="scalp_groom: .*transform"):
            groom.transformed(matrix)


def test_subset_by_indices_and_mask():
    groom = scalp_groom(count=30, length=0.05, points=4)
    sub = groom.subset([4, 1, 7])
    for i, j in enumerate((4, 1, 7)):
        np.testing.assert_array_equal(sub.strands[i], groom.strands[j])
    np.testing.assert_array_equal(sub.root_uv, groom.root_uv[[4, 1, 7]])
    np.testing.assert_array_equal(sub.root_normal, groom.root_normal[[4, 1, 7]])
    assert sub.grid_shape is None
    mask = np.zeros(groom.strand_count, dtype=bool)
    mask[[2, 3]] = True
    assert groom.subset(mask).strand_count == 2
    assert groom.subset(np.arange(groom.strand_count)).grid_shape == groom.grid_shape
    with pytest.raises(GroomError, match="out of range"):
        groom.subset([groom.strand_count])


def test_projected_roots_on_a_sphere():
    centre, radius = np.array([0.2, -0.1, 1.5]), 0.09
    rng = np.random.default_rng(1)
    polar = rng.uniform(0.0, 1.6, 200)
    az = rng.uniform(0.0, 2 * np.pi, 200)
    n = np.column_stack((np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.cos(polar)))
    lines = [np.stack((centre + radius * d, centre + (radius + 0.05) * d)) for d in n]
    groom = Groom.from_polylines(lines).with_projected_roots()
    np.testing.assert_allclose(groom.root_normal, n, rtol=0, atol=1e-9)
    # azimuthal equidistant chart: |uv| is the angle from the mean direction
    e0 = n.mean(axis=0) / np.linalg.norm(n.mean(axis=0))
    np.testing.assert_allclose(np.linalg.norm(groom.root_uv, axis=1), np.arccos(np.clip(n @ e0, -1, 1)), atol=1e-9)


# --------------------------------------------------------------------------------------------
# scalp_groom


@functools.cache
def _ellipsoid_samples():
    """k-d tree over samples of the default head ellipsoid at most 0.7 mm apart."""
    polar, az = np.meshgrid(np.linspace(0, np.pi, 500), np.linspace(0, 2 * np.pi, 1000, endpoint=False))
    polar, az = polar.ravel(), az.ravel()
    unit = np.column_stack((np.sin(polar) * np.cos(az), np.sin(polar) * np.sin(az), np.cos(polar)))
    return cKDTree(SCALP_C + SCALP_R * unit)


def _ellipsoid_distance_sampled(points):
    """Distance to the default head ellipsoid from the sampled surface, negative inside."""
    dist, _ = _ellipsoid_samples().query(points)
    inside = (((points - SCALP_C) / SCALP_R) ** 2).sum(axis=1) < 1.0
    return np.where(inside, -dist, dist)


@pytest.mark.parametrize("count", [1, 7, 50, 200, 1000])
def test_scalp_groom_count_and_grid(count):
    groom = scalp_groom(count=count, length=0.05, points=4)
    assert abs(groom.strand_count - count) <= 0.1 * count
    rows, cols = groom.grid_shape
    assert rows * cols == groom.strand_count
    assert groom.root_uv.shape == (groom.strand_count, 2)


def test_scalp_groom_geometry():
    margin, length = 0.004, 0.3
    groom = scalp_groom(count=200, length=length, margin=margin, seed=5)
    roots = groom.roots()
    np.testing.assert_allclose((((roots - SCALP_C) / SCALP_R) ** 2).sum(axis=1), 1.0, rtol=0, atol=1e-9)
    grad = (roots - SCALP_C) / SCALP_R**2
    np.testing.assert_allclose(groom.root_normal, grad / np.linalg.norm(grad, axis=1, keepdims=True), atol=1e-12)
    lengths = np.array([_polyline_length(a) for a in groom.strands])
    assert (lengths >= 0.95 * length * (1 - RTOL_F64)).all() and (lengths <= 1.05 * length * (1 + RTOL_F64)).all()
    assert lengths.std() > 0.01 * length  # jittered
    assert all(len(a) == 32 for a in groom.strands)
    verts = np.concatenate([a[1:] for a in groom.strands])
    assert (_ellipsoid_distance_sampled(verts) >= CLEARANCE_FRACTION * margin).all()
    # no roots on the face: every root direction is at least 90 - front_cutoff degrees from -y
    unit = (roots - SCALP_C) / SCALP_R
    assert np.degrees(np.arccos(unit @ [0.0, -1.0, 0.0])).min() >= 90.0 - 55.0 - 1e-9
    # long strands hang: tips well below their roots
    assert (np.array([a[-1, 2] for a in groom.strands]) < roots[:, 2] - 0.1).all()


def test_scalp_groom_curl_is_a_helix_of_the_asked_pitch():
    curl, period, length, points, margin = 0.005, 0.05, 0.3, 121, 0.004
    groom = scalp_groom(count=60, length=length, points=points, curl=curl, curl_period=period, margin=margin)
    lengths = np.array([_polyline_length(a) for a in groom.strands])
    assert (lengths >= 0.95 * length * (1 - RTOL_F64)).all() and (lengths <= 1.05 * length * (1 + RTOL_F64)).all()
    # Steps (2.5 mm) are shorter than the margin: a vertex at arc length s can only be min(s, margin) clear.
    for a in groom.strands:
        s = np.arange(1, points) * _polyline_length(a) / (points - 1)
        assert (_ellipsoid_distance_sampled(a[1:]) >= CLEARANCE_FRACTION * np.minimum(s, margin)).all()
    # Where the axis hangs straight (the tip half, away from the head), consecutive step directions of a
    # helix with cone angle beta and phase step dpsi = 2 pi h / P differ by 2 asin(sin(beta) sin(dpsi / 2)).
    checked = 0
    for a in groom.strands:
        h = _polyline_length(a) / (points - 1)
        expected = 2 * math.asin(2 * math.pi * curl / period * math.sin(math.pi * h / period))
        tail = a[points // 2 :]
        if _ellipsoid_distance_sampled(tail).min() < 2 * margin:
            continue
        steps = np.diff(tail, axis=0)
        steps /= np.linalg.norm(steps, axis=1, keepdims=True)
        turn = np.arccos(np.clip((steps[1:] * steps[:-1]).sum(axis=1), -1, 1))
        np.testing.assert_allclose(turn, expected, rtol=1e-6)
        checked += 1
    assert checked >= 20
    with pytest.raises(GroomError, match="scalp_groom: curl"):
        scalp_groom(curl=0.01, curl_period=0.05)


def test_scalp_groom_reproducible_by_seed():
    a, b, c = scalp_groom(count=50, seed=11), scalp_groom(count=50, seed=11), scalp_groom(count=50, seed=12)
    for x, y in zip(a.strands, b.strands, strict=True):
        np.testing.assert_array_equal(x, y)
    np.testing.assert_array_equal(a.root_uv, b.root_uv)
    assert max(np.abs(x - y).max() for x, y in zip(a.strands, c.strands, strict=True)) > 1e-3


@pytest.mark.parametrize(
    "kwargs, key",
    [
        ({"count": 0}, "count"),
        ({"points": 1}, "points"),
        ({"length": -1.0}, "length"),
        ({"scalp_radii": (0.1, 0.0, 0.1)}, "scalp_radii"),
        ({"front_cutoff_deg": 120.0}, "front_cutoff_deg"),
        ({"margin": -0.1}, "margin"),
    ],
)
def test_scalp_groom_rejects_bad_arguments(kwargs, key):
    with pytest.raises(GroomError, match=f"scalp_groom: .*{key}"):
        scalp_groom(**kwargs)


# --------------------------------------------------------------------------------------------
# TressFX


def _ratboy_bytes():
    if not RATBOY.is_file():
        pytest.skip(f"TressFX asset not found at {RATBOY} (shared data beside the checkout)")
    return RATBOY.read_bytes()


def _raw_tfx(data):
    """Independent parse: header fields and float4 positions, as stored (Y up, float32)."""
    version, n_strands, n_verts, offset = struct.unpack_from("<fIII", data, 0)
    xyzw = np.frombuffer(data[offset : offset + n_strands * n_verts * 16], dtype=np.float32)
    return version, n_strands, n_verts, xyzw.reshape(n_strands, n_verts, 4)


@pytest.mark.shared_data
def test_read_tfx_ratboy_against_raw_bytes():
    data = _ratboy_bytes()
    version, n_strands, n_verts, xyzw = _raw_tfx(data)
    assert (version, n_strands, n_verts) == (4.0, 2228, 32)
    assert (xyzw[:, 0, 3] == 0).all()  # every root pinned
    raw = xyzw[:, :, :3].astype(np.float64)
    raw_len = np.array([_polyline_length(a) for a in raw])
    keep = raw_len >= 1e-3
    assert (~keep).sum() == 9

    groom, caught = _record_warnings(read_tfx, RATBOY)
    assert len(caught) == 1 and "9" in str(caught[0].message) and str(RATBOY) in str(caught[0].message)
    assert groom.strand_count == 2219
    expected = np.stack((raw[keep, :, 0], -raw[keep, :, 2], raw[keep, :, 1]), axis=-1)  # (x, y, z) -> (x, -z, y)
    np.testing.assert_array_equal(np.stack(groom.strands), expected)
    assert groom.grid_shape is None
    assert groom.root_uv.shape == (2219, 2) and np.isfinite(groom.root_uv).all()
    np.testing.assert_allclose(np.linalg.norm(groom.root_normal, axis=1), 1.0, atol=1e-12)
    # Z up: the roots run from the crown (0.91 m) down the spine along z, the asset's y.
    np.testing.assert_allclose(groom.roots()[:, 2].max(), raw[:, 0, 1].max())


@pytest.mark.shared_data
def test_read_tfx_root_normals_against_body_mesh():
    _ratboy_bytes()
    if not RATBOY_BODY.is_file():
        pytest.skip(f"TressFX body mesh not found at {RATBOY_BODY}")
    lines = RATBOY_BODY.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("numOfVertices"))
    count = int(lines[start].split()[1])
    rows = [line for line in lines[start + 1 : start + count + 2] if not line.startswith("#")][:count]
    vert = np.array([line.split()[1:7] for line in rows], dtype=np.float64)
    pos, nrm = vert[:, :3] @ _Y_TO_Z.T, vert[:, 3:] @ _Y_TO_Z.T
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        groom = read_tfx(RATBOY)
    _, nearest = cKDTree(pos).query(groom.roots())
    body_n = nrm[nearest] / np.linalg.norm(nrm[nearest], axis=1, keepdims=True)
    angle = np.degrees(np.arccos(np.clip((body_n * groom.root_normal).sum(axis=1), -1, 1)))
    assert np.median(angle) < ROOT_NORMAL_MEDIAN_DEG


_Y_TO_Z = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])


@pytest.mark.shared_data
def test_read_tfx_truncated_and_corrupt(tmp_path):
    data = _ratboy_bytes()
    cases = {
        "truncated.tfx": data[: len(data) // 2],
        "header_only.tfx": data[:100],
        "version.tfx": struct.pack("<f", 3.0) + data[4:],
        "offset.tfx": data[:12] + struct.pack("<I", len(data)) + data[16:],
    }
    for name, blob in cases.items():
        path = tmp_path / name
        path.write_bytes(blob)
        with pytest.raises(GroomError, match=str(path)):
            read_tfx(path)
    # strand 5 with its root free (w = 1) instead of pinned
    blob = bytearray(data)
    struct.pack_into("<f", blob, 160 + (5 * 32) * 16 + 12, 1.0)
    path = tmp_path / "unpinned.tfx"
    path.write_bytes(bytes(blob))
    with pytest.raises(GroomError, match=rf"{path}: strand 5 .*pinned"):
        read_tfx(path)


# --------------------------------------------------------------------------------------------
# .hair


def _random_lines(seed=0, count=6):
    rng = np.random.default_rng(seed)
    return [np.cumsum(rng.normal(scale=0.01, size=(n, 3)), axis=0) + [0, 0, 1.6] for n in rng.integers(2, 12, count)]


def test_hair_round_trip_and_layout(tmp_path):
    lines = _random_lines()
    groom = Groom.from_polylines(lines)
    thickness = np.linspace(1e-4, 2e-4, len(lines))
    path = tmp_path / "g.hair"
    write_hair(path, groom, thickness=thickness, info="test")
    back = read_hair(path)
    assert back.strand_count == len(lines)
    for a, b in zip(lines, back.strands, strict=True):
        assert b.shape == a.shape
        np.testing.assert_allclose(b, a, rtol=RTOL_F32, atol=0)
    assert str(path) == back.source
    # byte layout, parsed independently
    data = path.read_bytes()
    sig, n_hair, n_pts, bits, d_seg, d_thick, d_transp = struct.unpack_from("<4sIIIIff", data, 0)
    assert (sig, n_hair, n_pts, bits) == (b"HAIR", len(lines), sum(map(len, lines)), 1 | 2 | 4)
    assert data[40:44] == b"test"
    seg = np.frombuffer(data, "<u2", n_hair, 128)
    np.testing.assert_array_equal(seg, [len(a) - 1 for a in lines])
    pts = np.frombuffer(data, "<f4", 3 * n_pts, 128 + 2 * n_hair).reshape(-1, 3)
    np.testing.assert_array_equal(pts, np.concatenate(lines).astype(np.float32))
    thick = np.frombuffer(data, "<f4", n_pts, 128 + 2 * n_hair + 12 * n_pts)
    np.testing.assert_array_equal(thick, np.repeat(thickness, [len(a) for a in lines]).astype(np.float32))
    assert len(data) == 128 + 2 * n_hair + 16 * n_pts


def test_read_hair_written_by_hand(tmp_path):
    # No segment array (default 3 segments), with transparency and colours that must be skipped; Y up.
    lines = [np.array([[0, 0, 0], [0, 1, 0], [0, 2, 0], [1, 2, 0]], dtype=np.float32) + i for i in range(3)]
    pts = np.concatenate(lines)
    header = struct.pack("<4sIIIIff3f88s", b"HAIR", 3, 12, 2 | 8 | 16, 3, 0.1, 0.0, 1, 1, 1, b"")
    body = pts.tobytes() + np.zeros(12, "<f4").tobytes() + np.ones(36, "<f4").tobytes()
    path = tmp_path / "hand.hair"
    path.write_bytes(header + body)
    groom = read_hair(path, up_axis="y")
    for a, b in zip(lines, groom.strands, strict=True):
        np.testing.assert_array_equal(b, np.column_stack((a[:, 0], -a[:, 2], a[:, 1])))
    path.write_bytes(header + body[:-4])
    with pytest.raises(GroomError, match=rf"{path}: truncated"):
        read_hair(path)


def test_read_hair_bad_signature_and_counts(tmp_path):
    path = tmp_path / "g.hair"
    write_hair(path, Groom.from_polylines(_random_lines()))
    data = path.read_bytes()
    bad = tmp_path / "bad.hair"
    bad.write_bytes(b"HAIX" + data[4:])
    with pytest.raises(GroomError, match=rf"{bad}: not a .hair file"):
        read_hair(bad)
    bad.write_bytes(data[:8] + struct.pack("<I", 1000) + data[12:])
    with pytest.raises(GroomError, match=str(bad)):
        read_hair(bad)
    with pytest.raises(GroomError, match="thickness"):
        write_hair(path, Groom.from_polylines(_random_lines()), thickness=np.ones(5))


# --------------------------------------------------------------------------------------------
# load


def test_load_dispatch_and_errors(tmp_path, monkeypatch):
    lines = _random_lines(seed=2)
    hair = tmp_path / "g.HAIR"
    write_hair(hair, Groom.from_polylines(lines))
    loaded = Groom.load(hair)
    assert loaded.strand_count == len(lines) and loaded.root_normal.shape == (len(lines), 3)
    y_up = Groom.load(hair, up_axis="y")
    np.testing.assert_allclose(y_up.strands[0], loaded.strands[0] @ _Y_TO_Z.T, atol=ATOL_EXACT)

    with pytest.raises(GroomError, match=r"unknown groom suffix.*\.tfx.*\.hair.*\.usd"):
        Groom.load(tmp_path / "g.obj")
    missing = tmp_path / "missing.tfx"
    with pytest.raises(GroomError, match=rf"{missing}: no such"):
        Groom.load(missing)
    with pytest.raises(GroomError, match="up_axis"):
        Groom.load(hair, up_axis="x")

    calls = []
    fake = types.ModuleType("hairwarp.io.usd_groom")
    fake.read_groom = lambda p, purpose: calls.append(p) or {"curves": lines, "widths": None, "uv": None}
    monkeypatch.setitem(sys.modules, "hairwarp.io.usd_groom", fake)
    usd = tmp_path / "g.usda"
    usd.write_text("#usda 1.0\n")
    from_usd = Groom.load(usd)
    assert calls == [usd] and from_usd.strand_count == len(lines) and from_usd.source == str(usd)
    with pytest.raises(GroomError, match="USD"):
        Groom.load(usd, up_axis="y")


@pytest.mark.shared_data
def test_load_tfx():
    _ratboy_bytes()
    groom, caught = _record_warnings(Groom.load, RATBOY)
    assert groom.strand_count == 2219 and len(caught) == 1


def test_load_usd_curves_through_hairwarp_usd(tmp_path):
    """A Y-up centimetre stage written with pxr directly comes back in metres, Z up."""
    pytest.importorskip("pxr")
    from pxr import Gf, Usd, UsdGeom, Vt
    lines = [
        np.array([[0.0, 170.0, 0.0], [0.0, 160.0, 5.0], [1.0, 150.0, 8.0]]),
        np.array([[3.0, 168.0, 1.0], [3, 140, 2]]),
    ]
    path = tmp_path / "groom.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    curves = UsdGeom.BasisCurves.Define(stage, "/hair")
    curves.CreateTypeAttr(UsdGeom.Tokens.linear)
    curves.CreateCurveVertexCountsAttr(Vt.IntArray([len(a) for a in lines]))
    curves.CreatePointsAttr(Vt.Vec3fArray([Gf.Vec3f(*p) for a in lines for p in a]))
    stage.GetRootLayer().Save()
    groom = Groom.load(path)
    assert groom.strand_count == 2 and groom.source == str(path)
    for a, b in zip(lines, groom.strands, strict=True):
        np.testing.assert_allclose(b, 0.01 * a @ _Y_TO_Z.T, rtol=RTOL_F32, atol=1e-9)


def test_domain_types_import_no_file_format():
    """Groom and Collider read files through hairwarp.io, imported when a file is read; the old names still work."""
    import subprocess

    code = (
        "import sys, hairwarp, hairwarp.groom as g, hairwarp.colliders as c\n"
        "assert not [m for m in sys.modules if m.startswith('hairwarp.io')], sorted(sys.modules)\n"
        "import hairwarp.io.tfx as t, hairwarp.io.cem_hair as h\n"
        "assert g.read_tfx is t.read_tfx is hairwarp.read_tfx and c.read_tfxmesh is t.read_tfxmesh\n"
        "assert g.read_hair is h.read_hair is hairwarp.read_hair and g.write_hair is h.write_hair\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_grooms_repr_is_a_summary():
    """``repr`` of a groom names its size and source in one line, not every vertex (it printed 340,000
    characters for 200 strands)."""
    text = repr(scalp_groom(count=200))
    assert text.startswith("Groom(200 strands, ") and "scalp" in text and len(text) < 120 and "\n" not in text
