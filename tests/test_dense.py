"""Dense hair: root sampling and weights, interpolation, Hermite densification, velocities, push-out.

References: SciPy (Delaunay barycentric transforms, CubicHermiteSpline, Rotation), a float64 NumPy
implementation of the documented interpolation operator, closed forms (straight strands, a sphere,
a capsule, a plane), trimesh signed distances to mesh colliders.
"""

import numpy as np
import pytest
import trimesh
import warp as wp
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation

import hairwarp as hw
from hairwarp.colliders import Collider, ColliderSet
from hairwarp.dense import DenseHair, DenseHairError, bench_dense, scalp_uv
from hairwarp.kernels import interpolate as kernels

DEVICE = "cpu"
RADIUS = 0.1  # scalp sphere [m]
LENGTH = 0.25  # guide length [m]
# float32 kernels against float64 references: ~20 multiply-adds of coordinates of size ~LENGTH.
POS_TOL = 2e-6 * LENGTH
# Hermite samples vs SciPy: float32 evaluation of a cubic with O(1) coefficients, relative to the curve size.
HERMITE_REL_TOL = 1e-5
# Central differences of float32 positions with step H: round-off ~1e-7 * LENGTH / H dominates.
FD_STEP = 1e-3
FD_TOL = 1e-4
# Weights are computed in float64.
WEIGHT_TOL = 1e-12
# Push-out: a vertex ends at least the collider thickness above the surface, less the kernel's layer
# tolerance (1e-6 m) and float32 rounding of coordinates up to 1.7 m (ulp 1.2e-7), measured in float64.
LAYER_TOL = 2e-6
# Push-out keeps segment lengths up to float32 rounding of the propagated vertices (coordinates <= 1.7 m).
LENGTH_TOL = 1e-6
THICKNESS = 0.002  # collider contact layer [m]
# Push-out on a posed head vs the rest result posed: a lift turns the vertex toward its closest face's normal,
# which jumps across mesh edges, so float32 rounding that switches the face moves a vertex near an edge (and
# the strand after it) along its segment's sphere, by 0.2 mm measured on a 5k-face ellipsoid; most agree.
RIGID_TOL = 1e-3
RIGID_AGREE = 0.995


def cap_guides(G, S, seed=0, cap_deg=70.0):
    """Wavy guides on a spherical scalp cap: (G, S+1, 3) vertices, (G, 3) unit normals."""
    rng = np.random.default_rng(seed)
    i = np.arange(G) + 0.5
    cos_t = 1.0 - (1.0 - np.cos(np.radians(cap_deg))) * i / G
    phi = np.pi * (1.0 + 5.0**0.5) * i
    sin_t = np.sqrt(1.0 - cos_t**2)
    normal = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    steps = rng.normal(size=(G, S, 3)) * 0.3 + normal[:, None, :]
    steps *= LENGTH / S / np.linalg.norm(steps, axis=2, keepdims=True)
    verts = np.concatenate([RADIUS * normal[:, None, :], RADIUS * normal[:, None, :] + np.cumsum(steps, axis=1)], 1)
    return verts, normal


def grid_guides(rows, cols, S, seed=0):
    """Guides on an uneven planar grid (z = 0), growing up with random bends; strand r*cols + c."""
    rng = np.random.default_rng(seed)
    xs = np.cumsum(rng.uniform(0.01, 0.03, cols))
    ys = np.cumsum(rng.uniform(0.01, 0.03, rows))
    roots = np.stack(np.meshgrid(ys, xs, indexing="ij"), -1).reshape(-1, 2)[:, ::-1]
    roots = np.column_stack([roots, np.zeros(len(roots))])
    steps = rng.normal(size=(rows * cols, S, 3)) * 0.3 + [0.0, 0.0, 1.0]
    steps *= LENGTH / S / np.linalg.norm(steps, axis=2, keepdims=True)
    return np.concatenate([roots[:, None], roots[:, None] + np.cumsum(steps, axis=1)], 1)


def to_wp(a):
    return wp.array(np.asarray(a, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=DEVICE)


def strands(hair, arr):
    return arr.numpy().reshape(hair.dense_count, -1, 3).astype(np.float64)


def reference_interpolation(hair, gx, rot=None):
    """float64 NumPy version of the operator documented in DenseHair."""
    S = hair.seg_per_strand
    k = np.arange(S + 1)
    u = hair.length_scale[:, None] * k
    j = np.minimum(np.floor(u).astype(int), S - 1)
    t = (u - j)[..., None]

    def guide_at(g):
        return (1 - t) * gx[g[:, None], j] + t * gx[g[:, None], j + 1]

    x = sum(hair.guide_weight[:, i, None, None] * guide_at(hair.guide_index[:, i]) for i in range(4))
    f = (k / S)[None, :, None]
    x = x + hair.clumping * f * (guide_at(hair.clump_guide) - x)
    offset = hair.dense_root_offset.numpy()[:, None, :] + f * hair.dense_tip_offset.numpy()[:, None, :]
    return x + offset @ (np.eye(3) if rot is None else rot).T


def head_arrays(rot, trans, omega=(0, 0, 0), vel=(0, 0, 0)):
    q = Rotation.from_matrix(rot).as_quat()  # (x, y, z, w), as wp.quat
    xf = wp.array([wp.transform(wp.vec3(*trans), wp.quat(*q))], dtype=wp.transform, device=DEVICE)
    sv = wp.array([wp.spatial_vector(*omega, *vel)], dtype=wp.spatial_vector, device=DEVICE)
    return xf, sv


# ---------------------------------------------------------------- weights and sampling


def test_dense_root_on_guide_root_reproduces_guide_barycentric():
    guides, normal = cap_guides(20, 8)
    uv = scalp_uv(guides[:, 0])
    hair = DenseHair.build(guides, uv, root_samples=uv, root_normal=normal, samples_per_segment=3, device=DEVICE)
    dense = strands(hair, hair.interpolate(to_wp(guides)))
    assert np.array_equal(dense, guides.astype(np.float32))
    curves = strands(hair, hair.densify())
    assert np.array_equal(curves[:, ::3], guides.astype(np.float32))


def test_dense_root_on_guide_root_reproduces_guide_grid():
    rows, cols = 4, 5
    guides = grid_guides(rows, cols, 8)
    rc = np.stack(np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij"), -1).reshape(-1, 2)
    hair = DenseHair.build(guides, grid_shape=(rows, cols), root_samples=rc, device=DEVICE)
    dense = strands(hair, hair.interpolate(to_wp(guides)))
    assert np.array_equal(dense, guides.astype(np.float32))


@pytest.mark.parametrize("grid", [False, True])
def test_weights_partition_of_unity_and_area_uniform(grid):
    if grid:
        guides = grid_guides(4, 6, 4)
        hair = DenseHair.build(guides, grid_shape=(4, 6), count=3000, seed=3, device=DEVICE)
        assert hair.guide_weight.shape == (3000, 4)
    else:
        guides, _ = cap_guides(30, 4)
        hair = DenseHair.build(guides, count=3000, seed=3, device=DEVICE)
        assert np.all(hair.guide_weight[:, 3] == 0.0) and np.all(hair.guide_index[:, 3] == 0)
    w = hair.guide_weight
    assert np.all(w >= 0.0)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=WEIGHT_TOL)
    assert np.all(hair.guide_index[w == 0.0] == 0)
    # The dense root is the weighted guide roots (no root_normal: no lift).
    roots = guides[:, 0]
    np.testing.assert_allclose(
        hair.dense_root_position, np.einsum("dj,djc->dc", w, roots[hair.guide_index]), atol=1e-15
    )
    if grid:
        # Each cell holds floor or ceil of its area share (uneven grid; planar cells are rectangles here).
        cell = np.floor(hair.dense_root_uv).astype(int)
        counts = np.bincount(cell[:, 0] * 5 + cell[:, 1], minlength=15)
        g = roots.reshape(4, 6, 3)
        area = (np.diff(g[:, 0, 1])[:, None] * np.diff(g[0, :, 0])[None, :]).ravel()
        assert np.all(np.abs(counts - 3000 * area / area.sum()) <= 1.0)


def test_dense_roots_inside_triangulation_with_scipy_barycentrics():
    guides, _ = cap_guides(30, 4, seed=1)
    hair = DenseHair.build(guides, count=2000, seed=5, device=DEVICE)
    dela = Delaunay(hair.root_uv)
    simplex = dela.find_simplex(hair.dense_root_uv)
    assert np.all(simplex >= 0)
    # Every triangle used is a Delaunay triangle, and SciPy's barycentrics in it are the weights.
    delaunay_sets = {frozenset(s) for s in dela.simplices.tolist()}
    assert all(frozenset(t) in delaunay_sets for t in hair.triangles.tolist())
    tri = hair.guide_index[:, :3]
    for d in range(hair.dense_count):
        s = dela.simplices[simplex[d]]
        if set(s) != set(tri[d]):
            continue  # on an edge shared with a neighbour: found in the other triangle
        b = dela.transform[simplex[d], :2] @ (hair.dense_root_uv[d] - dela.transform[simplex[d], 2])
        bary = dict(zip(s.tolist(), [*b, 1.0 - b.sum()], strict=True))
        np.testing.assert_allclose([bary[i] for i in tri[d]], hair.guide_weight[d, :3], atol=1e-9)


def test_a_generator_grid_of_one_row_binds_by_the_roots_triangulation():
    """The scalp generator lays a few guides in one row of its grid (7 guides: 1 x 7), which spans no cell: the dense
    hair binds to the roots' triangulation instead, with SciPy's Delaunay triangles and barycentrics, as for a groom
    without a grid (it used to refuse the grid). Fewer than 3 guides are refused, naming the count."""
    groom = hw.scalp_groom(count=7, length=0.2, points=8)
    assert groom.grid_shape == (1, 7)
    guides = np.stack([np.asarray(s, dtype=np.float64) for s in groom.strands])
    hair = DenseHair.build(guides, groom.root_uv, grid_shape=groom.grid_shape, count=500, seed=2, device=DEVICE)
    assert hair.grid_shape is None and hair.dense_count == 500
    dela = Delaunay(groom.root_uv)
    assert {frozenset(t) for t in hair.triangles.tolist()} <= {frozenset(s) for s in dela.simplices.tolist()}
    assert np.all(dela.find_simplex(hair.dense_root_uv) >= 0)
    np.testing.assert_allclose(hair.guide_weight.sum(axis=1), 1.0, atol=1e-12)
    two = hw.scalp_groom(count=2, length=0.2, points=8)
    with pytest.raises(DenseHairError, match="at least 3, got 2"):
        DenseHair.build(np.stack([np.asarray(s, dtype=np.float64) for s in two.strands]), two.root_uv,
                        grid_shape=two.grid_shape, count=10, device=DEVICE)


def test_gap_between_scalp_patches_is_not_bridged():
    rng = np.random.default_rng(0)
    uv = np.vstack([rng.random((25, 2)) * 0.05, rng.random((25, 2)) * 0.05 + [0.12, 0.0]])
    guides = np.repeat(np.column_stack([uv, np.zeros(50)])[:, None], 3, axis=1) + [[0, 0, 0], [0, 0, 0.1], [0, 0, 0.2]]
    hair = DenseHair.build(guides, uv, count=1000, device=DEVICE)
    tri = hair.triangles
    assert np.all((tri < 25).all(1) | (tri >= 25).all(1))
    assert not np.any((hair.dense_root_uv[:, 0] > 0.05 + 1e-12) & (hair.dense_root_uv[:, 0] < 0.12 - 1e-12))


def test_density_and_default_scalp_uv_cover_the_cap():
    guides, _ = cap_guides(60, 2, cap_deg=80.0)
    hair = DenseHair.build(guides, density=1e5, device=DEVICE)
    a, b, c = (guides[hair.triangles[:, i], 0] for i in range(3))
    tri_normal = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(tri_normal, axis=1).sum()
    cap_area = 2 * np.pi * RADIUS**2 * (1 - np.cos(np.radians(80.0)))
    # Inscribed triangles of 60 roots: a few percent short of the cap.
    assert 0.85 * cap_area < area < cap_area
    assert hair.dense_count == round(1e5 * area)
    # Not folded: every triangle faces the same way (outward or inward) about the sphere's centre.
    outward = np.einsum("ij,ij->i", tri_normal, a + b + c)
    assert np.all(outward > 0) or np.all(outward < 0)


def test_root_lift_puts_dense_roots_on_sphere():
    guides, normal = cap_guides(30, 2)
    flat = DenseHair.build(guides, count=2000, device=DEVICE)
    lifted = DenseHair.build(guides, count=2000, root_normal=normal, device=DEVICE)
    err_flat = np.abs(np.linalg.norm(flat.dense_root_position, axis=1) - RADIUS).max()
    err_lift = np.abs(np.linalg.norm(lifted.dense_root_position, axis=1) - RADIUS).max()
    assert err_lift < 0.15 * err_flat
    n = lifted.dense_root_normal
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    # The rest strand's root sits at the lifted root.
    dense = strands(lifted, lifted.interpolate(to_wp(guides)))
    np.testing.assert_allclose(dense[:, 0], lifted.dense_root_position, atol=POS_TOL)


# ---------------------------------------------------------------- per-frame operator


def test_interpolation_matches_float64_reference_with_variation_and_head_rotation():
    guides, normal = cap_guides(25, 8, seed=2)
    hair = DenseHair.build(
        guides,
        count=400,
        root_normal=normal,
        seed=7,
        length_variation=0.3,
        tip_spread=0.01,
        clumping=0.6,
        device=DEVICE,
    )
    rot = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    trans = np.array([0.1, -0.2, 0.3])
    posed = guides @ rot.T + trans
    xf, _ = head_arrays(rot, trans)
    dense = strands(hair, hair.interpolate(to_wp(posed), xf))
    np.testing.assert_allclose(dense, reference_interpolation(hair, posed, rot), atol=POS_TOL)
    # Tip spread: at most tip_spread, normal to the rest strand's root-to-tip direction.
    rest = reference_interpolation(hair, guides)
    tip = hair.dense_tip_offset.numpy().astype(np.float64)
    assert np.all(np.linalg.norm(tip, axis=1) <= 0.01 * (1 + 1e-6))
    axis = rest[:, -1] - rest[:, 0] - tip
    cos = (
        np.einsum("ij,ij->i", axis, tip) / np.linalg.norm(axis, axis=1) / np.maximum(np.linalg.norm(tip, axis=1), 1e-30)
    )
    assert np.abs(cos).max() < 1e-5


def test_length_scale_shortens_along_the_guide_shape():
    # Straight parallel guides: a dense strand of scale s is straight with length s * LENGTH.
    g = np.column_stack([np.random.default_rng(0).random((12, 2)) * 0.1, np.zeros(12)])
    S = 8
    guides = g[:, None] + np.linspace(0, LENGTH, S + 1)[None, :, None] * [0.0, 0.6, 0.8]
    hair = DenseHair.build(guides, count=300, length_variation=0.4, device=DEVICE)
    assert hair.length_scale.min() >= 0.6 and hair.length_scale.max() <= 1.0
    dense = strands(hair, hair.interpolate(to_wp(guides)))
    spacing = np.linalg.norm(np.diff(dense, axis=1), axis=2)
    np.testing.assert_allclose(spacing, (hair.length_scale * LENGTH / S)[:, None] * np.ones(S), atol=POS_TOL)
    assert spacing.max() <= LENGTH / S + POS_TOL
    # Bent guides: vertex spacing stays within the longest segment of the strand's guides.
    guides, _ = cap_guides(20, S, seed=3)
    guides[:, :, 2] *= np.linspace(1.0, 1.5, 20)[:, None]  # uneven segment lengths between guides
    hair = DenseHair.build(guides, count=300, length_variation=0.4, clumping=0.5, device=DEVICE)
    dense = strands(hair, hair.interpolate(to_wp(guides)))
    seg = np.linalg.norm(np.diff(guides, axis=1), axis=2).max(1)
    allowed = seg[np.where(hair.guide_weight > 0, hair.guide_index, hair.clump_guide[:, None])].max(1)
    allowed = np.maximum(allowed, seg[hair.clump_guide])
    assert np.all(np.linalg.norm(np.diff(dense, axis=1), axis=2).max(1) <= allowed + POS_TOL)


def test_clumping_one_brings_tips_to_the_clump_guide():
    guides, _ = cap_guides(20, 6)
    hair = DenseHair.build(guides, count=200, clumping=1.0, device=DEVICE)
    dense = strands(hair, hair.interpolate(to_wp(guides)))
    np.testing.assert_allclose(dense[:, -1], guides[hair.clump_guide, -1], atol=POS_TOL)
    dist = np.linalg.norm(guides[None, :, 0] - hair.dense_root_position[:, None], axis=2)
    assert np.all(hair.clump_guide == dist.argmin(1))


def test_rigid_translation_translates_dense_hair():
    guides, normal = cap_guides(20, 8, seed=4)
    hair = DenseHair.build(
        guides, count=300, root_normal=normal, length_variation=0.3, tip_spread=0.01, clumping=0.5, device=DEVICE
    )
    shift = np.array([0.05, -0.03, 0.02])
    a = strands(hair, hair.evaluate(to_wp(guides))[0])
    b = strands(hair, hair.evaluate(to_wp(guides + shift))[0])
    np.testing.assert_allclose(b - a, np.broadcast_to(shift, a.shape), atol=POS_TOL)


def test_velocities_are_the_derivative_of_positions():
    guides, normal = cap_guides(16, 8, seed=5)
    hair = DenseHair.build(
        guides, count=200, root_normal=normal, length_variation=0.2, tip_spread=0.01, clumping=0.4, device=DEVICE
    )
    rng = np.random.default_rng(1)
    omega, lin = np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.1, -0.2])
    drift = rng.normal(size=guides.shape) * 0.5  # non-rigid guide motion in the head frame [m/s]

    def pose(t):
        rot = Rotation.from_rotvec(omega * t).as_matrix()
        return (guides + t * drift) @ rot.T + t * lin, rot

    def positions(t):
        x, rot = pose(t)
        xf, _ = head_arrays(rot, t * lin)
        return strands(hair, hair.evaluate(to_wp(x), None, xf)[0])

    fd = (positions(FD_STEP) - positions(-FD_STEP)) / (2 * FD_STEP)
    x0, rot0 = pose(0.0)
    v0 = np.cross(omega, x0) + drift + lin
    xf, sv = head_arrays(rot0, (0, 0, 0), omega, lin)
    p, v = hair.evaluate(to_wp(x0), to_wp(v0), xf, sv)
    assert v is hair.curve_velocities and p is hair.curve_points
    np.testing.assert_allclose(strands(hair, v), fd, atol=FD_TOL)
    assert np.abs(fd).max() > 0.1


def test_same_seed_reproduces_and_other_seed_differs():
    guides, normal = cap_guides(20, 6)
    kw = dict(count=300, root_normal=normal, length_variation=0.3, tip_spread=0.01, clumping=0.3, device=DEVICE)
    a, b, c = (DenseHair.build(guides, seed=s, **kw) for s in (11, 11, 12))
    x = to_wp(guides)
    pa, pb, pc = (h.evaluate(x)[0].numpy() for h in (a, b, c))
    assert np.array_equal(pa, pb) and np.array_equal(a.guide_weight, b.guide_weight)
    assert np.array_equal(a.length_scale, b.length_scale)
    assert not np.array_equal(a.guide_weight, c.guide_weight) and not np.allclose(pa, pc)


# ---------------------------------------------------------------- Hermite densification


def test_hermite_samples_match_scipy_cubic_hermite_spline():
    rng = np.random.default_rng(0)
    D, S, M = 7, 8, 5
    curves = np.cumsum(rng.normal(size=(D, S + 1, 3)), axis=1)
    curves32 = curves.astype(np.float32)
    out = wp.zeros(D * (M * S + 1), dtype=wp.vec3, device=DEVICE)
    wp.launch(kernels.hermite_samples, dim=out.shape[0], inputs=[0, S, M, to_wp(curves32)], outputs=[out],
              device=DEVICE)
    got = out.numpy().reshape(D, M * S + 1, 3)
    param = np.arange(M * S + 1) / M
    for d in range(D):
        y = curves32[d].astype(np.float64)
        tangent = np.empty_like(y)
        tangent[1:-1] = 0.5 * (y[2:] - y[:-2])
        tangent[0], tangent[-1] = y[1] - y[0], y[-1] - y[-2]
        expected = CubicHermiteSpline(np.arange(S + 1), y, tangent, axis=0)(param)
        size = np.abs(y).max()
        np.testing.assert_allclose(got[d], expected, atol=HERMITE_REL_TOL * size)
    # The curve passes through every vertex exactly (t = 0 samples and the tip).
    assert np.array_equal(got[:, ::M], curves32)


def test_widths_and_counts():
    guides, _ = cap_guides(10, 6)
    hair = DenseHair.build(guides, count=5, samples_per_segment=2, device=DEVICE)
    assert hair.points_per_curve == 13
    assert np.array_equal(hair.curve_vertex_counts(), np.full(5, 13))
    assert np.array_equal(hair.curve_vertex_counts(hermite=False), np.full(5, 7))
    w = hair.widths(1e-4, 2e-5).reshape(5, 13)
    np.testing.assert_allclose(w[:, 0], 1e-4)
    np.testing.assert_allclose(w[:, -1], 2e-5)
    assert np.all(np.diff(w, axis=1) < 0)


def test_bad_input_raises_naming_the_argument():
    guides, _ = cap_guides(10, 4)
    with pytest.raises(DenseHairError, match="count"):
        DenseHair.build(guides, device=DEVICE)
    with pytest.raises(DenseHairError, match="grid_shape"):
        DenseHair.build(guides, grid_shape=(3, 4), count=10, device=DEVICE)
    with pytest.raises(DenseHairError, match="root_samples"):
        DenseHair.build(guides, scalp_uv(guides[:, 0]), root_samples=[[50.0, 50.0]], device=DEVICE)
    with pytest.raises(DenseHairError, match="clumping"):
        DenseHair.build(guides, count=10, clumping=2.0, device=DEVICE)
    bad = guides.copy()
    bad[3, 2, 0] = np.nan
    with pytest.raises(DenseHairError, match="guide strand 3"):
        DenseHair.build(bad, count=10, device=DEVICE)
    hair = DenseHair.build(guides, count=10, with_velocities=False, device=DEVICE)
    with pytest.raises(DenseHairError, match="guide_vertices"):
        hair.interpolate(to_wp(guides[:5]))
    with pytest.raises(DenseHairError, match="with_velocities"):
        hair.evaluate(to_wp(guides), to_wp(guides))


def test_bench_dense_reports_times():
    result = bench_dense(counts=(200,), guides=30, segments=6, repeats=1, device=DEVICE)
    (row,) = result["results"]
    assert row["count"] == 200 and row["points"] == 200 * (4 * 6 + 1)
    assert row["interpolate_s"] > 0 and row["hermite_s"] > 0


# ---------------------------------------------------------------- push-out from body colliders


def draped_guides(G, S, hover, seed=0):
    """Guides lying on the scalp sphere (radius RADIUS, centre 0): roots on it, every later vertex ``hover[g]``
    above it, each strand following its meridian down and round the sphere. Interpolating between them cuts
    chords into the sphere."""
    _, normal = cap_guides(G, S, seed=seed)
    down = np.array([0.0, 0.0, -1.0])
    tangent = down - (normal @ down)[:, None] * normal
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    phi = np.arange(S + 1)[None, :] * (LENGTH / S) / RADIUS  # (1, S+1) angle along the meridian
    radius = np.where(np.arange(S + 1)[None, :] == 0, RADIUS, RADIUS + np.asarray(hover)[:, None])
    verts = radius[..., None] * (np.cos(phi)[..., None] * normal[:, None] + np.sin(phi)[..., None] * tangent[:, None])
    return verts, normal


def sphere_distance(x, center=(0.0, 0.0, 0.0), radius=RADIUS):
    return np.linalg.norm(x - np.asarray(center), axis=-1) - radius


def pushed(hair, guides, colliders, head_xform=None):
    """(interpolated vertices before, after push_out), float64 (D, S+1, 3)."""
    hair.interpolate(to_wp(guides), head_xform)
    before = strands(hair, hair.dense_vertices)
    after = strands(hair, hair.push_out(colliders, head_xform))
    return before, after


def seg_lengths(x):
    return np.linalg.norm(np.diff(x, axis=1), axis=2)


def check_untouched_before_first_contact(before, after, distance_before):
    """Roots never move; a strand moves only from its first vertex within the layer on; clear strands are bitwise
    unchanged."""
    in_layer = distance_before[:, 1:] < THICKNESS
    first = np.where(in_layer.any(1), in_layer.argmax(1) + 1, before.shape[1])
    k = np.arange(before.shape[1])[None, :]
    keep = k < first[:, None]
    assert np.array_equal(after[keep], before[keep])
    assert np.array_equal(after[:, 0], before[:, 0])
    return first


def test_push_out_sphere_keeps_lengths_and_leaves_clear_strands():
    G, S = 60, 10
    _, normal = cap_guides(G, S)
    hover = np.where(normal[:, 0] < 0.0, 0.0015, 0.02)  # low on one side (chords cut in), high on the other
    guides, normal = draped_guides(G, S, hover)
    hair = DenseHair.build(guides, count=3000, root_normal=normal, tip_spread=0.004, seed=2, device=DEVICE)
    colliders = ColliderSet([Collider.sphere(RADIUS, thickness=THICKNESS)], DEVICE)
    before, after = pushed(hair, guides, colliders)
    d0, d1 = sphere_distance(before), sphere_distance(after)
    # The set-up does what it is for: interpolated hair cuts into the sphere, and some strands are clear.
    assert (d0[:, 1:] < 0.0).sum() > 100 and (d0[:, 1:] < THICKNESS).any(1).mean() < 0.8
    assert d1[:, 1:].min() >= THICKNESS - LAYER_TOL
    lifted, projected = hair.push_counts
    assert projected == 0 and lifted > 0
    # Every segment keeps its length (roots lie on the sphere, so every lift is within its segment's reach).
    np.testing.assert_allclose(seg_lengths(after), seg_lengths(before), atol=LENGTH_TOL)
    first = check_untouched_before_first_contact(before, after, d0)
    clear = first == S + 1
    assert clear.sum() > 300
    # The first vertex in the layer is the first one moved (it turns about the previous one, so it may end
    # higher than the layer's top on a curved surface).
    hit = np.flatnonzero(~clear)
    assert np.all(np.any(after[hit, first[hit]] != before[hit, first[hit]], axis=1))


def test_push_out_mesh_on_moved_head_against_trimesh():
    """A head-attached ellipsoid mesh on a turned and translated head: depths measured by trimesh on the posed
    mesh, and the result is the rest-pose result moved rigidly."""
    G, S = 50, 8
    guides, normal = draped_guides(G, S, np.full(G, 0.001), seed=3)
    head = Collider.ellipsoid((0.0, 0.0, 0.0), (RADIUS, RADIUS, 0.95 * RADIUS), subdivisions=4, thickness=THICKNESS)
    colliders = ColliderSet([head], DEVICE)
    hair = DenseHair.build(guides, count=1000, root_normal=normal, tip_spread=0.003, seed=4, device=DEVICE)
    rot = Rotation.from_rotvec([0.2, -0.4, 0.7]).as_matrix()
    trans = np.array([0.1, -0.2, 1.6])
    xf, _ = head_arrays(rot, trans)
    before, after = pushed(hair, guides @ rot.T + trans, colliders, xf)
    posed = trimesh.Trimesh(head.mesh.vertices @ rot.T + trans, head.mesh.faces, process=False)
    # trimesh: signed distance positive inside.
    d0 = -trimesh.proximity.signed_distance(posed, before.reshape(-1, 3)).reshape(before.shape[:2])
    d1 = -trimesh.proximity.signed_distance(posed, after.reshape(-1, 3)).reshape(after.shape[:2])
    assert (d0[:, 1:] < 0.0).sum() > 50
    assert d1[:, 1:].min() >= THICKNESS - LAYER_TOL
    check_untouched_before_first_contact(before, after, d0)
    _, rest_after = pushed(hair, guides, colliders)
    moved_rest = rest_after @ rot.T + trans
    err = np.linalg.norm(after - moved_rest, axis=2)
    assert np.mean(err < 10 * LENGTH_TOL) > RIGID_AGREE and err.max() < RIGID_TOL
    assert hair.push_counts[1] == 0
    np.testing.assert_allclose(seg_lengths(after), seg_lengths(before), atol=LENGTH_TOL)


def test_push_out_roots_deep_inside_projects_out_of_reach():
    """Roots 30 mm under a larger sphere, segments of 21 mm: vertex 1 cannot clear the layer on its segment's
    sphere, so it is projected; every vertex after the root still ends on or above the layer."""
    G, S = 30, 12
    guides, normal = draped_guides(G, S, np.full(G, 0.001), seed=5)
    big = RADIUS + 0.03
    colliders = ColliderSet([Collider.sphere(big, thickness=THICKNESS)], DEVICE)
    hair = DenseHair.build(guides, count=400, root_normal=normal, seed=6, device=DEVICE)
    before, after = pushed(hair, guides, colliders)
    assert sphere_distance(after, radius=big)[:, 1:].min() >= THICKNESS - LAYER_TOL
    lifted, projected = hair.push_counts
    assert projected > 0
    assert np.array_equal(after[:, 0], before[:, 0])
    # Segments after the first keep their lengths (the seed's rule), the first one stretches.
    np.testing.assert_allclose(seg_lengths(after)[:, 1:], seg_lengths(before)[:, 1:], atol=LENGTH_TOL)


def test_push_out_world_capsule_and_plane_closed_forms():
    """Hair hanging down onto a world plane (a table at the tips) and through a capsule (an arm)."""
    S = 8
    guides = grid_guides(5, 8, S, seed=7)
    guides[..., 2] *= -1.0  # hanging down from z = 0 to about z = -LENGTH
    floor = -0.6 * LENGTH
    axis_y = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    arm_center = np.array([0.1, 0.05, -0.35 * LENGTH])
    axis_y[:3, 3] = arm_center
    capsule = Collider.capsule(0.02, 0.1, local_xform=axis_y, name="arm", attach="world", thickness=THICKNESS)
    plane = Collider.plane(point=(0.0, 0.0, floor), name="table", attach="world", thickness=THICKNESS)
    colliders = ColliderSet([capsule, plane], DEVICE)
    hair = DenseHair.build(guides, grid_shape=(5, 8), count=1500, seed=8, device=DEVICE)
    before, after = pushed(hair, guides, colliders)

    def capsule_distance(x):
        rel = x - arm_center
        t = np.clip(rel[..., 1], -0.1, 0.1)  # the capsule axis is world y here
        return np.linalg.norm(rel - t[..., None] * np.array([0.0, 1.0, 0.0]), axis=-1) - 0.02

    for dist in (capsule_distance, lambda x: x[..., 2] - floor):
        assert (dist(before)[:, 1:] < 0.0).any()
        assert dist(after)[:, 1:].min() >= THICKNESS - LAYER_TOL
    d0 = np.minimum(capsule_distance(before), before[..., 2] - floor)
    check_untouched_before_first_contact(before, after, d0)
    assert hair.push_counts[1] == 0
    np.testing.assert_allclose(seg_lengths(after), seg_lengths(before), atol=LENGTH_TOL)


def test_evaluate_with_colliders_is_push_out_between_interpolate_and_densify():
    G, S = 40, 8
    guides, normal = draped_guides(G, S, np.full(G, 0.0015), seed=9)
    colliders = ColliderSet([Collider.sphere(RADIUS, thickness=THICKNESS)], DEVICE)
    hair = DenseHair.build(guides, count=800, root_normal=normal, tip_spread=0.004, seed=1, device=DEVICE)
    x, v = to_wp(guides), to_wp(np.ones_like(guides))
    plain, plain_vel = (strands(hair, a) for a in hair.evaluate(x, v))
    assert sphere_distance(plain).min() < 0.0
    points, vel = hair.evaluate(x, v, colliders=colliders)
    got = strands(hair, points)
    hair.interpolate(x)
    hair.push_out(colliders)
    np.testing.assert_array_equal(got, strands(hair, hair.densify()))
    np.testing.assert_array_equal(strands(hair, vel), plain_vel)  # velocities stay as interpolated
    # The Hermite curves through lifted vertices stay out of the sphere (they may dip into the layer); the root
    # segment, which starts on the sphere, is left out.
    assert sphere_distance(got[:, hair.samples_per_segment:]).min() > 0.0
    vertices, _ = hair.evaluate(x, colliders=colliders, hermite=False)
    assert sphere_distance(strands(hair, vertices))[:, 1:].min() >= THICKNESS - LAYER_TOL
    # No colliders: nothing launched, the vertices are the interpolated ones.
    assert hair.push_out(ColliderSet([], DEVICE)) is hair.dense_vertices and hair.push_counts == (0, 0)
    with pytest.raises(DenseHairError, match="dense_vertices"):
        hair.push_out(colliders, dense_vertices=to_wp(guides))


def test_bench_dense_frame_reports_every_stage(monkeypatch):
    from hairwarp.benchmarks import common
    from hairwarp.benchmarks.dense import bench_dense_frame

    monkeypatch.setattr(common.GATE, "enabled", False)
    result = bench_dense_frame(counts=(300,), quick=True, device=DEVICE)
    assert result["simulate_frame_s"] > 0 and result["guides"] > 100 and result["substeps"] == 8
    (row,) = result["results"]
    assert row["count"] == 300 and row["points"] == 300 * row["points_per_curve"]
    for key in ("interpolate_s", "hermite_s", "push_out_s", "write_s", "frame_output_s", "catmull_rom_write_s"):
        assert row[key] > 0, key
    linear, catmull_rom = row["write"]
    assert (linear["basis"], catmull_rom["basis"]) == ("linear", "catmullRom")
    # Points and velocities, float32: 24 bytes a vertex, plus the crate's bookkeeping and the static topology.
    assert 24 * row["points"] <= linear["bytes_per_frame"] <= 1.5 * 24 * row["points"] + 2e5
    assert linear["convert_s"] > 0 and linear["save_s"] > 0
    assert row["write_cheaper_than_simulate"] == (row["write_s"] < result["simulate_frame_s"])


@pytest.mark.slow
def test_suite_dense_quick_through_hairwarp_bench(tmp_path, monkeypatch):
    """``hairwarp bench dense --quick``: both parts run, every pipeline figure is consistent with the frame times it
    is made of, and the files written read back as the same results."""
    import json

    from hairwarp.bench import run_suites
    from hairwarp.benchmarks import common
    from hairwarp.benchmarks.dense import md_dense

    monkeypatch.setattr(common.GATE, "enabled", False)
    results = run_suites(["dense"], common.BenchConfig(quick=True, device=DEVICE), tmp_path, log=lambda m: None)
    data = results["suites"]["dense"]
    assert json.loads((tmp_path / "benchmarks.json").read_text())["suites"]["dense"]["verdicts"] == data["verdicts"]
    pipe = data["pipeline"]
    assert [(r["count"], r["basis"]) for r in pipe["results"]] == [(1000, "catmullRom"), (1000, "linear")]
    for r in pipe["results"]:
        bg, inline = r["background"], r["inline"]
        assert r["background_write_s"] == bg["frame_s"] - r["output_frame_s"]
        assert r["writer_own_s"] == pytest.approx(bg["convert_s"] + bg["set_s"] + bg["save_s"])
        assert r["write_cheaper_than_simulate"] == (r["background_write_s"] < pipe["simulate_frame_s"])
        # Same frames, same file: the two writers store the same bytes per frame.
        # the same frames; the clip layers are named after each cache, so the roots differ by a few bytes
        assert bg["bytes_per_frame"] == pytest.approx(inline["bytes_per_frame"], rel=1e-3)
        assert inline["bytes_per_frame"] >= 24 * r["points"]
    assert data["stages"]["results"][0]["count"] == 1000
    # The disk floor of a row is its bytes at the disk's measured pace.
    assert data["disk_write_rate"] > 0
    floor = 1e3 * pipe["results"][1]["background"]["bytes_per_frame"] / data["disk_write_rate"]
    assert any(line.startswith("| 1,000 | linear |") and f"| {floor:.0f} |" in line for line in md_dense(data))
