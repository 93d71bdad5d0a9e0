"""Dynamic hair-hair contacts (DESIGN §4.4): detection against brute force, forces against closed forms.

Segment pairs are checked against an all-pairs float64 search, vertex-face pairs against trimesh's closest
points on every triangle; the force law against hand-computed two-body cases; friction by integrating a tiny
system in numpy. Arrays are built here directly, independent of the Model and State classes.
"""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import trimesh
import warp as wp
from _reference import segment_distances
from scipy.spatial.transform import Rotation

from hairwarp.interactions import HairContacts, InteractionError, StaticLinks, TriangleStrips
from hairwarp.kernels.contacts import CONTACT_SEGMENT_SEGMENT, CONTACT_VERTEX_FACE, EDGE_RAMP, PLANE_RAMP
from hairwarp.kernels.types import REFERENCE_SEGMENT_LENGTH, Fault

# Distances within this of the threshold [m] may fall on either side in float32 (coordinates < 0.1 m).
BOUNDARY_BAND = 1.0e-6
# Float32 closest points agree with float64 ones to a few ulp of the coordinates [m].
POINT_TOL = 1.0e-6
# Barycentric weights of a float64 closest point on an edge or corner are zero (or one) to this round-off.
FEATURE_TOL = 1.0e-9
# A closest point this near (in barycentric weight) to another feature may be classed differently in float32.
FEATURE_BAND = 1.0e-4
# 1 - |T_a . T_b| this near the alignment cutoff may fall on either side in float32.
ALIGN_BAND = 1.0e-5
# Closed-form force checks: float32 relative error of a few products.
FORCE_RTOL = 1.0e-4
# Momentum sums cancel many float32 terms: residual as a fraction of the sum of magnitudes.
MOMENTUM_RTOL = 1.0e-5

ROWS, COLS, S = 4, 5, 8
G = ROWS * COLS
SEG_LEN = 0.006
SPACING = 0.004
THRESHOLD = 0.002
MASS = 2.0e-6


def _force_law(*args, **kw):
    """Contacts whose force pass applies the seed's law whole (``response=False``, the default): the tests of the law
    read it there; with the response on, the force of a contact is solved after the free step (tests below)."""
    kw.setdefault("response", False)
    return HairContacts.build(*args, **kw)


def _model(G_, S_, mass=MASS):
    return SimpleNamespace(
        seg_per_strand=S_,
        seg_count=G_ * S_,
        seg_length=wp.array(np.full(G_ * S_, SEG_LEN), dtype=float),
        seg_mass=wp.array(np.full(G_ * S_, mass), dtype=float),
    )


def _state(verts, vel=None):
    vel = np.zeros_like(verts) if vel is None else vel
    return SimpleNamespace(
        vertex_positions=wp.array(verts.reshape(-1, 3), dtype=wp.vec3),
        vertex_velocities=wp.array(vel.reshape(-1, 3), dtype=wp.vec3),
        fault=wp.zeros(1, dtype=wp.int32),
    )


def _tangled(seed, bend=0.6, spacing=SPACING):
    """Random-walk strands from a grid of roots: they cross each other and the strips between their neighbours."""
    rng = np.random.default_rng(seed)
    c, r = np.meshgrid(np.arange(COLS), np.arange(ROWS))
    roots = np.stack([c.ravel() * spacing, r.ravel() * spacing, np.zeros(G)], axis=1)
    rot = Rotation.from_rotvec(rng.normal(0.0, bend, (G * S, 3))).as_matrix().reshape(G, S, 3, 3)
    verts = np.zeros((G, S + 1, 3))
    verts[:, 0] = roots
    d = np.array([0.0, 0.0, -SEG_LEN])
    frame = np.broadcast_to(np.eye(3), (G, 3, 3))
    for k in range(S):
        frame = frame @ rot[:, k]
        verts[:, k + 1] = verts[:, k] + frame @ d
    return verts, rng


def _apply(contacts, model, state, dt=1.0e-3):
    n = model.seg_count
    force = wp.zeros(n, dtype=wp.vec3)
    torque = wp.zeros(n, dtype=wp.vec3)
    mass = wp.zeros(n, dtype=float)
    contacts.apply(model, state, wp.array([dt], dtype=float), force, torque, mass)
    return force.numpy().astype(np.float64), torque.numpy().astype(np.float64), mass.numpy().astype(np.float64)


@pytest.mark.parametrize("seed, cutoff, skip, bend", [(0, 0.0, False, 0.6), (1, 0.0, False, 0.6), (2, 0.0, True, 0.6),
                                                     (0, 0.2, True, 0.6), (1, 0.2, False, 0.6), (3, 0.0, True, 0.6),
                                                     (4, 0.01, False, 0.03), (5, 0.01, True, 0.03)])
def test_detection_matches_brute_force(seed, cutoff, skip, bend):
    """All pairs closer than the threshold (and crossing by more than the alignment cutoff) are found, once. A
    bundle of nearly parallel strands (``bend`` 0.05 rad a joint, roots 1.5 mm apart) at the default cutoff: most
    near pairs are aligned, and the detection passes over whole blocks by their directions' cones
    (``kernels.contacts.CONE_SLACK``), which must drop no pair the per-pair test keeps."""
    spacing = SPACING if bend > 0.1 else 0.0015
    verts, _ = _tangled(seed, bend, spacing)
    strips = TriangleStrips.build(verts, grid_shape=(ROWS, COLS))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=1.0, capacity=20000,
                                  alignment_cutoff=cutoff, skip_neighbour_strips=skip)
    # Detect on a moved configuration: the BVHs are refit, not rebuilt.
    moved, _ = _tangled(seed + 100, bend, spacing)
    model = _model(G, S)
    _apply(contacts, model, _state(moved))
    found = contacts.contact_list()
    assert not contacts.overflowed()

    p0 = moved[:, :-1].reshape(-1, 3)
    p1 = moved[:, 1:].reshape(-1, 3)
    i, j = np.triu_indices(G * S, k=1)
    other = i // S != j // S
    i, j = i[other], j[other]
    dist = segment_distances(p0[i], p1[i], p0[j], p1[j])
    unit = (p1 - p0) / np.linalg.norm(p1 - p0, axis=1, keepdims=True)
    align = 1.0 - np.abs(np.sum(unit[i] * unit[j], axis=1))
    if cutoff == 0.01:  # the cones' case: most near pairs are aligned
        assert ((dist < THRESHOLD) & (align < cutoff)).sum() > ((dist < THRESHOLD) & (align >= cutoff)).sum()
    dist = np.where(align >= cutoff, dist, np.inf)
    clear = (np.abs(dist - THRESHOLD) > BOUNDARY_BAND) & (np.abs(align - cutoff) > ALIGN_BAND)
    expected = set(zip(i[(dist < THRESHOLD) & clear].tolist(), j[(dist < THRESHOLD) & clear].tolist(), strict=True))
    ambiguous = set(zip(i[~clear].tolist(), j[~clear].tolist(), strict=True))
    ee = found["kind"] == CONTACT_SEGMENT_SEGMENT
    got = [tuple(sorted(x)) for x in zip(found["a"][ee].tolist(), found["b"][ee].tolist(), strict=True)]
    assert len(got) == len(set(got))  # each pair once
    assert len(expected) > 10
    assert set(got) - ambiguous == expected

    # Vertex-face, per (vertex, quad): the nearer of the quad's two triangles (trimesh), if the strip is not the
    # vertex's own (nor, with skip, one of its root neighbours') and the quad is no wider than the strips' max_width.
    # Whether the closest point belongs to the quad (off both strands, below the top edge) is the force's test, at
    # every step, not the detection's.
    flat = moved.reshape(-1, 3)
    tris = contacts.strips.indices.numpy().reshape(-1, 3)
    pairs = contacts.strips.pairs
    neighbours = np.eye(G, dtype=bool)
    if skip:
        neighbours[pairs[:, 0], pairs[:, 1]] = neighbours[pairs[:, 1], pairs[:, 0]] = True
    vertices = np.array([v for v in range(G * (S + 1)) if v % (S + 1) != 0])
    vv, qq = np.meshgrid(vertices, np.arange(len(tris) // 2), indexing="ij")
    vv, qq = vv.ravel(), qq.ravel()
    strand = vv // (S + 1)
    pa, pb = pairs[qq // S, 0], pairs[qq // S, 1]
    keep = ~neighbours[strand, pa] & ~neighbours[strand, pb]
    vv, qq = vv[keep], qq[keep]
    k = qq % S
    width = np.maximum(np.linalg.norm(moved[pa[keep], k] - moved[pb[keep], k], axis=1),
                       np.linalg.norm(moved[pa[keep], k + 1] - moved[pb[keep], k + 1], axis=1))
    parted = width > contacts.strips.max_width
    near = [trimesh.triangles.closest_point(flat[tris[2 * qq + s]], flat[vv]) for s in (0, 1)]
    d = [np.linalg.norm(c - flat[vv], axis=1) for c in near]
    second = d[1] < d[0]
    tt = 2 * qq + second
    dist = np.minimum(d[0], d[1])
    bary = trimesh.triangles.points_to_barycentric(flat[tris[tt]], np.where(second[:, None], near[1], near[0]))
    owned = _quad_owned(bary, tt, FEATURE_TOL)
    align = 1.0 - np.abs(np.sum(_vertex_tangents(moved)[vv] * _face_directions(moved, pairs)[qq], axis=1))
    assert (~owned & (dist < THRESHOLD)).any()  # the detection keeps pairs whose point lies on a strand
    dist = np.where((align >= cutoff) & ~parted, dist, np.inf)
    clear = (np.abs(dist - THRESHOLD) > BOUNDARY_BAND) & (np.abs(align - cutoff) > ALIGN_BAND)
    clear &= np.abs(d[0] - d[1]) > BOUNDARY_BAND  # which triangle is nearer
    clear &= np.abs(width - contacts.strips.max_width) > BOUNDARY_BAND
    assert parted.sum() < 0.5 * len(parted)
    expected = set(zip(vv[(dist < THRESHOLD) & clear].tolist(), tt[(dist < THRESHOLD) & clear].tolist(), strict=True))
    ambiguous = set(zip(vv[~clear].tolist(), qq[~clear].tolist(), strict=True))
    vf = found["kind"] == CONTACT_VERTEX_FACE
    got = list(zip(found["a"][vf].tolist(), found["b"][vf].tolist(), strict=True))
    assert len({(v, t // 2) for v, t in got}) == len(got)  # one contact per vertex and quad
    assert len(expected) > 10
    assert {(v, t) for v, t in got if (v, t // 2) not in ambiguous} == expected

    # The stored barycentric weights give trimesh's closest point.
    w = found["w"][vf].astype(np.float64)
    t_found = found["b"][vf]
    point = np.einsum("ni,nij->nj", w, flat[tris[t_found]])
    ref = trimesh.triangles.closest_point(flat[tris[t_found]], flat[found["a"][vf]])
    np.testing.assert_allclose(point, ref, atol=POINT_TOL)


def _vertex_tangents(verts):
    """Unit tangent at every vertex (G*(S+1), 3): central differences, one-sided at the root and the tip."""
    t = np.empty_like(verts)
    t[:, 1:-1] = verts[:, 2:] - verts[:, :-2]
    t[:, 0] = verts[:, 1] - verts[:, 0]
    t[:, -1] = verts[:, -1] - verts[:, -2]
    t = t.reshape(-1, 3)
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def _face_directions(verts, pairs):
    """The along-strand direction of every strip quad ``S p + k``: the sum of its two strands' segments, normalised."""
    d = np.diff(verts, axis=1)
    t = (d[pairs[:, 0]] + d[pairs[:, 1]]).reshape(-1, 3)
    return t / np.linalg.norm(t, axis=1, keepdims=True)


def _quad_owned(w, tri, tol):
    """Whether a closest point with barycentric weights w in triangle ``tri`` belongs to the triangle's quad.

    Triangle 2q = (a_k, b_k, a_{k+1}) puts the point at u = w_1 across the quad (0 on strand a, 1 on strand b) and
    v = w_2 along it; triangle 2q + 1 = (b_k, b_{k+1}, a_{k+1}) at u = 1 - w_2, v = 1 - w_0. Points on a strand
    (u = 0 or 1) belong to segment-segment contacts, the top edge (v = 1) to the next quad, except at the tip.
    Weights within ``tol`` of 0 or 1 count as 0 or 1.
    """
    first = tri % 2 == 0
    u = np.where(first, w[:, 1], 1.0 - w[:, 2])
    v = np.where(first, w[:, 2], 1.0 - w[:, 0])
    tip = (tri % (2 * S)) // 2 == S - 1
    return (u > tol) & (u < 1.0 - tol) & ((v < 1.0 - tol) | tip)


def _pair(a0, a1, b0, b1):
    """Two single-segment strands."""
    return np.array([[a0, a1], [b0, b1]], dtype=np.float64)


@pytest.mark.parametrize("angle", [0.0, np.pi, 1.0e-8])
def test_repulsion_vanishes_for_parallel_segments(angle):
    """Aligned (or anti-aligned) hairs overlapping and approaching each other exchange no force."""
    gap = 0.5 * THRESHOLD
    direction = np.array([np.sin(angle), 0.0, -np.cos(angle)])
    verts = _pair([0, 0, 0], [0, 0, -SEG_LEN], [gap, 0, 0], np.array([gap, 0, 0]) + SEG_LEN * direction)
    vel = np.zeros_like(verts)
    vel[0] = [0.1, 0.05, 0.0]
    vel[1] = [-0.1, 0.0, 0.02]
    contacts = _force_law(verts, threshold=THRESHOLD, stiffness=10.0, damping=0.1, friction=0.5,
                                  capacity=8, alignment_cutoff=0.0, rest_gaps=False)
    force, torque, mass = _apply(contacts, _model(2, 1), _state(verts, vel))
    assert contacts.contact_count() == 1
    assert np.abs(force).max() < 1e-6 * 10.0 * THRESHOLD
    assert np.abs(torque).max() < 1e-6 * 10.0 * THRESHOLD * SEG_LEN
    np.testing.assert_allclose(mass, 0.0, atol=1e-12)
    # With the default cutoff such a pair is not even stored.
    default = _force_law(verts, threshold=THRESHOLD, stiffness=10.0, capacity=8, rest_gaps=False)
    _apply(default, _model(2, 1), _state(verts, vel))
    assert default.contact_count() == 0


def test_crossing_segments_closed_form():
    """Perpendicular crossing segments at distance delta: F = k (thr - delta) - c v_n along the separation, the damper
    ``c`` at most the pair's reduced mass over the step (these 2 mg segments': 1e-3 N s/m at h = 1 ms, a tenth of the
    0.01 asked; ``test_normal_damping_in_the_free_step_never_reverses_the_approach``)."""
    k, h, delta = 10.0, 1.0e-3, 0.0008
    c = min(0.01, 0.5 * MASS / h)
    a0, a1 = np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, -SEG_LEN])
    b0, b1 = np.array([-0.003, delta, -0.002]), np.array([0.003, delta, -0.002])
    verts = _pair(a0, a1, b0, b1)
    vel = np.zeros_like(verts)
    vel[1] = [0.0, -0.05, 0.0]  # b approaches a
    contacts = _force_law(verts, threshold=THRESHOLD, stiffness=k, damping=0.01, capacity=4, rest_gaps=False)
    force, torque, mass = _apply(contacts, _model(2, 1), _state(verts, vel), dt=h)
    fn = k * (THRESHOLD - delta) + c * 0.05  # n = -y (from b to a); approaching adds damping
    np.testing.assert_allclose(force[0], [0.0, -fn, 0.0], rtol=FORCE_RTOL, atol=FORCE_RTOL * fn)
    np.testing.assert_allclose(force[1], [0.0, fn, 0.0], rtol=FORCE_RTOL, atol=FORCE_RTOL * fn)
    # Both act at the midpoint (0, delta/2, -0.002); torques about each segment's origin.
    point = np.array([0.0, 0.5 * delta, -0.002])
    tol = FORCE_RTOL * fn * SEG_LEN
    np.testing.assert_allclose(torque[0], np.cross(point - a0, force[0]), rtol=FORCE_RTOL, atol=tol)
    np.testing.assert_allclose(torque[1], np.cross(point - b0, force[1]), rtol=FORCE_RTOL, atol=tol)
    # h^2 k + h c at each end, as a centre-of-mass mass with at least the point's inertia about the segment's joint:
    # b's contact point lies 3.03 mm from its origin, beyond its half length (3 mm).
    lever = [max(1.0, np.sum((point - o) ** 2) / (0.5 * SEG_LEN) ** 2) for o in (a0, b0)]
    assert lever[0] == 1.0 and lever[1] > 1.0
    # The solver gets the part beyond each segment's own mass (the rest the explicit step carries).
    np.testing.assert_allclose(mass, (h * h * k + h * c) * np.array(lever) - MASS, rtol=1e-5)


def _strip_scene():
    """Strands 0 and 1 span a strip in the plane y = 0 (12 mm apart at the roots, 8 mm at the tips, segments
    12 mm long); strand 2 runs along -y and ends 0.8 mm in front of the face (a_1, b_1, a_2), at its incentre,
    so no other triangle comes within the threshold. As a 1 x 3 grid, strand 2 is a root neighbour of strand 1,
    so these scenes keep the neighbours' strips (``skip_neighbour_strips=False``)."""
    z = np.array([0.0, -0.012, -0.024])
    s0 = np.stack([np.zeros(3), np.zeros(3), z], axis=1)
    s1 = np.stack([[0.012, 0.010, 0.008], np.zeros(3), z], axis=1)
    tip = np.array([0.0032, 0.0008, -0.0152])
    s2 = np.stack([tip + [0.0, 0.024, 0.0], tip + [0.0, 0.012, 0.0], tip], axis=0)
    return np.stack([s0, s1, s2])


def test_stored_pairs_with_margin():
    """Detected once with a margin, a pair not yet within the threshold is kept and pushes once it comes closer,
    without a new detection (``detect_each_step=False``)."""
    k = 10.0
    a0, a1 = np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, -SEG_LEN])
    far = _pair(a0, a1, [-0.003, 0.0025, -0.002], [0.003, 0.0025, -0.002])
    contacts = _force_law(far, threshold=THRESHOLD, stiffness=k, capacity=4, margin=0.001,
                                  detect_each_step=False, rest_gaps=False)
    model = _model(2, 1)
    contacts.detect(model, _state(far))
    assert contacts.contact_count() == 1
    force, _, mass = _apply(contacts, model, _state(far))
    assert np.abs(force).max() == 0.0 and np.abs(mass).max() == 0.0  # 2.5 mm apart: beyond the threshold
    near = _pair(a0, a1, [-0.003, 0.0008, -0.002], [0.003, 0.0008, -0.002])
    force, _, _ = _apply(contacts, model, _state(near))
    fn = k * (THRESHOLD - 0.0008)
    np.testing.assert_allclose(force[0], [0.0, -fn, 0.0], rtol=FORCE_RTOL, atol=FORCE_RTOL * fn)
    assert contacts.contact_count() == 1


def test_vertex_face_closed_form_with_density_scale():
    """A strand tip 0.8 mm in front of a strip face, crossing it at right angles: F = k0 (s0 / s) (thr - 0.8 mm), the
    density factor s0 / s blended from the quad's lower edge (10 mm) to its upper edge (8 mm) by the point's
    weights, times the vertex's segment length over ``REFERENCE_SEGMENT_LENGTH``."""
    k, S2 = 10.0, 2
    verts = _strip_scene()
    strips = TriangleStrips.build(verts, grid_shape=(1, 3))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=k, capacity=16,
                                  segment_segment=False, skip_neighbour_strips=False, rest_gaps=False)
    force, torque, _ = _apply(contacts, _model(3, S2), _state(verts))
    found = contacts.contact_list()
    assert list(found["kind"]) == [CONTACT_VERTEX_FACE]
    assert found["a"][0] == 2 * (S2 + 1) + 2  # the tip of strand 2
    tri = found["b"][0]
    assert tri == 2  # pair (0, 1), segment 1, first triangle: its horizontal edge a_1 b_1 is 10 mm
    assert contacts.strips.tri_width[tri] == pytest.approx(0.010)
    assert contacts.strips.tri_width[tri + 1] == pytest.approx(0.008)
    w = found["w"][0].astype(np.float64)  # of (a_1, b_1, a_2)
    scale = contacts.strips.width_ref * ((w[0] + w[1]) / 0.010 + w[2] / 0.008)
    assert scale != pytest.approx(1.0)
    # and the vertex's segment length over the reference length (one contact a vertex)
    expected = k * scale * (SEG_LEN / REFERENCE_SEGMENT_LENGTH) * (THRESHOLD - 0.0008)
    np.testing.assert_allclose(force[2 * S2 + 1], [0.0, expected, 0.0], rtol=FORCE_RTOL,
                               atol=FORCE_RTOL * expected)
    np.testing.assert_allclose(force.sum(axis=0), 0.0, atol=1e-6 * expected)


@pytest.mark.parametrize("offset", [0.0008, 0.0004, 0.0001, 0.0, -0.0001, -0.0004])
def test_vertex_face_force_is_continuous_through_the_strip(offset):
    """The strip scene's tip at ``offset`` [m] in front of the face (behind it where negative): beyond
    ``PLANE_RAMP`` times the reach from the plane the push is k (thr - d), closer it falls linearly to none at the
    plane, k (thr - r) d / r, r = ramp * thr, always away from the plane on the tip's side. So the force does not
    flip from +k thr to -k thr as the tip passes through the strip, which cost the step's order of convergence
    (docs/interactions.md)."""
    k, S2 = 10.0, 2
    verts = _strip_scene()
    verts[2, :, 1] += offset - 0.0008
    strips = TriangleStrips.build(verts, grid_shape=(1, 3))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=k, capacity=16,
                          segment_segment=False, skip_neighbour_strips=False, rest_gaps=False)
    force, _, _ = _apply(contacts, _model(3, S2), _state(verts))
    found = contacts.contact_list()
    w = found["w"][0].astype(np.float64)  # as the closed-form test: the density factor at the tip's face point
    scale = contacts.strips.width_ref * ((w[0] + w[1]) / 0.010 + w[2] / 0.008)
    k_eff = k * scale * (SEG_LEN / REFERENCE_SEGMENT_LENGTH)
    ramp = PLANE_RAMP * THRESHOLD
    d = abs(offset)
    depth = THRESHOLD - d if d >= ramp else (THRESHOLD - ramp) * d / ramp
    expected = np.sign(offset) * k_eff * depth
    peak = k_eff * (THRESHOLD - ramp)
    # the force's float32 round-off (the closed-form test's), and at the plane (no side) none at all within it
    np.testing.assert_allclose(force[2 * S2 + 1], [0.0, expected, 0.0], rtol=FORCE_RTOL, atol=FORCE_RTOL * peak)
    np.testing.assert_allclose(force.sum(axis=0), 0.0, atol=1e-6 * peak)
    # solved after the free step, the pair's force over the step takes the same depth: without damping its
    # target separation speed is depth / h, along the normal from the face to the tip (k depth / (h k) in float32:
    # the force's round-off, FORCE_RTOL)
    h = 1.0e-3
    solved = HairContacts.build(verts, strips, threshold=THRESHOLD, stiffness=k, capacity=16, segment_segment=False,
                                skip_neighbour_strips=False, rest_gaps=False, response=True)
    _apply(solved, _model(3, S2), _state(verts), dt=h)
    response = solved._response_buffer
    along = response.target.numpy()[0] * response.normal.numpy()[0][1]
    np.testing.assert_allclose(along, np.sign(offset) * depth / h, rtol=FORCE_RTOL, atol=FORCE_RTOL * THRESHOLD / h)


@pytest.mark.parametrize("z", [-0.0100, -0.0115, -0.0119, -0.0121, -0.0125, -0.0140])
def test_flat_strip_pushes_with_each_quad_within_reach(z):
    """A tip 0.8 mm in front of a flat strip of constant width, at heights on both sides of the edge its two quads
    share (z = -12 mm): each quad within reach pushes it, k0 (s0 / s) (l / l0) (thr - d_q) along the tip's offset
    from its closest point on quad q, d_q its distance from the quad (0.8 mm over the quad, or to the edge beside
    it): the force is continuous across the edge and, the strip's width constant, the gradient of the quads' energy.
    (A rule that gave the shared edge to the upper quad pushed the tip 1.99 times as hard 0.1 mm to the root's side
    of the edge as 0.1 mm to the tip's.)"""
    k, d, edge = 10.0, 0.0008, -0.012
    zs = np.array([0.0, edge, -0.024])
    s0 = np.stack([np.zeros(3), np.zeros(3), zs], axis=1)
    s1 = np.stack([np.full(3, 0.010), np.zeros(3), zs], axis=1)
    tip = np.array([0.005, d, z])
    s2 = np.stack([tip + [0.0, 0.024, 0.0], tip + [0.0, 0.012, 0.0], tip], axis=0)
    verts = np.stack([s0, s1, s2])
    strips = TriangleStrips.build(verts, grid_shape=(1, 3))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=k, capacity=16, segment_segment=False,
                          skip_neighbour_strips=False, rest_gaps=False)
    force, _, _ = _apply(contacts, _model(3, 2), _state(verts))
    k_eff = k * (contacts.strips.width_ref / 0.010) * (SEG_LEN / REFERENCE_SEGMENT_LENGTH)
    expected = np.zeros(3)
    for top, bottom in ((0.0, edge), (edge, -0.024)):  # the quads' closest points, in float64
        closest = np.array([tip[0], 0.0, np.clip(z, bottom, top)])
        offset = tip - closest
        dist = np.linalg.norm(offset)
        if dist < THRESHOLD:
            expected += k_eff * (THRESHOLD - dist) * offset / dist
    if abs(z - edge) < 0.001:
        assert len(contacts.contact_list()["kind"]) == 2  # both quads of the strip are within reach of the tip
    scale = np.linalg.norm(expected)
    np.testing.assert_allclose(force[2 * 2 + 1], expected, rtol=FORCE_RTOL, atol=FORCE_RTOL * scale)
    # the face's shares cancel the vertex's force in float32: a residual of a few ulps of it
    np.testing.assert_allclose(force.sum(axis=0), 0.0, atol=1e-6 * scale)


def test_parting_strip_fades_out():
    """A strip quad stretched to 7/8 of the strips' max_width pushes with half its force: the stiffness fades out
    over the last quarter before a quad stops being a contact surface, so no force switches off between two
    detections."""
    k = 10.0
    verts = _strip_scene()
    strips = TriangleStrips.build(verts, grid_shape=(1, 3))
    moved = verts.copy()
    widest = 0.875 * strips.max_width
    moved[1, :, 0] = widest  # strand 1 moved out: every quad of the strip is 7/8 of max_width wide

    def push(max_width):
        contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=k, capacity=16,
                                      segment_segment=False, skip_neighbour_strips=False, rest_gaps=False,
                                      implicit_springs=False)
        contacts.strips.max_width = max_width
        force, _, _ = _apply(contacts, _model(3, 2), _state(moved))
        assert contacts.contact_count() >= 1
        return force

    built = strips.max_width
    faded, full = push(built), push(1.0e3)
    assert np.abs(full).max() > 0.0
    np.testing.assert_allclose(faded, 0.5 * full, rtol=1e-4, atol=1e-4 * np.abs(full).max())


@pytest.mark.parametrize("x", [0.0001, 0.0003, 0.00049, 0.001])
def test_vertex_face_push_fades_in_from_a_strands_line(x):
    """The strip scene's tip moved across the strip to ``x`` [m] from strand 0 (0.8 mm in front of the face): the
    push is the closed-form test's ``k_eff (thr - 0.8 mm)`` times ``min(x / (EDGE_RAMP thr), 1)``, its distance from
    the strand over the ramp (``strand_edge_fade``)."""
    k, S2 = 10.0, 2
    verts = _strip_scene()
    verts[2, :, 0] = x
    strips = TriangleStrips.build(verts, grid_shape=(1, 3))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=k, capacity=16, segment_segment=False,
                          skip_neighbour_strips=False, rest_gaps=False)
    force, _, _ = _apply(contacts, _model(3, S2), _state(verts))
    found = contacts.contact_list()
    assert list(found["kind"]) == [CONTACT_VERTEX_FACE]
    w = found["w"][0].astype(np.float64)
    scale = contacts.strips.width_ref * ((w[0] + w[1]) / 0.010 + w[2] / 0.008)
    k_eff = k * scale * (SEG_LEN / REFERENCE_SEGMENT_LENGTH)
    expected = k_eff * (THRESHOLD - 0.0008) * min(x / (EDGE_RAMP * THRESHOLD), 1.0)
    np.testing.assert_allclose(force[2 * S2 + 1], [0.0, expected, 0.0], rtol=FORCE_RTOL,
                               atol=FORCE_RTOL * k_eff * (THRESHOLD - 0.0008))


def test_push_is_continuous_where_a_vertex_crosses_a_strands_line():
    """The strip scene's tip 0.8 mm in front of the strip, moved across strand 0's line in steps of 0.02 mm, with both
    kinds of contact: the vertex-face push hands over to the segment-segment contact without a jump. Between two
    neighbouring places the tip's force changes by at most a tenth of the face's push ``k_eff (thr - 0.8 mm)``, more
    than the two contacts' slopes allow (the fade's ``k_eff (thr - d) / (EDGE_RAMP thr)`` per metre and the segment
    pair's ``k`` by 0.02 mm: 5 % of it); a vertex-face push that switched off at the line changed it by the whole
    push."""
    k, S2 = 10.0, 2
    pushes = []
    for x in np.arange(-0.0006, 0.00061, 0.00002):
        verts = _strip_scene()
        verts[2, :, 0] = x
        strips = TriangleStrips.build(verts, grid_shape=(1, 3))
        contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=k, capacity=16,
                              skip_neighbour_strips=False, rest_gaps=False)
        force, _, _ = _apply(contacts, _model(3, S2), _state(verts))
        pushes.append(force[2 * S2 + 1])
    # the density factor's largest on the quads the tip meets (their narrowest edge is 8 mm)
    k_eff = k * (SEG_LEN / REFERENCE_SEGMENT_LENGTH) * strips.width_ref / 0.008
    face_push = k_eff * (THRESHOLD - 0.0008)
    assert np.abs(pushes).max() > 0.5 * face_push
    assert np.linalg.norm(np.diff(pushes, axis=0), axis=1).max() < 0.1 * face_push


def test_vertex_beside_a_strand_is_a_segment_contact():
    """A tip 0.8 mm beside strand 0, outside the strip: the strip's strand edge is left to segment-segment contacts,
    so the tip is pushed once, not once per strip triangle along that strand. The strip's vertex-face pairs are
    stored (the point may come inside the quad before the next detection) but push nothing: the forces are those
    of the segment-segment contact alone."""
    verts = _strip_scene()
    tip = np.array([-0.0008, 0.0, -0.018])
    verts[2] = [tip + [0.0, 0.024, 0.0], tip + [0.0, 0.012, 0.0], tip]
    strips = TriangleStrips.build(verts, grid_shape=(1, 3))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=10.0, capacity=16,
                                  skip_neighbour_strips=False, rest_gaps=False)
    force, torque, mass = _apply(contacts, _model(3, 2), _state(verts))
    found = contacts.contact_list()
    ee = found["kind"] == CONTACT_SEGMENT_SEGMENT
    assert ee.sum() == 1 and (~ee).any()
    assert (found["a"][ee][0], found["b"][ee][0]) == (1, 5)  # strand 0's lower segment, strand 2's last segment
    alone = _force_law(verts, None, threshold=THRESHOLD, stiffness=10.0, capacity=16, rest_gaps=False)
    force_ee, torque_ee, mass_ee = _apply(alone, _model(3, 2), _state(verts))
    assert np.abs(force_ee).max() > 0.0
    np.testing.assert_array_equal(force, force_ee)
    np.testing.assert_array_equal(torque, torque_ee)
    np.testing.assert_array_equal(mass, mass_ee)


@pytest.mark.parametrize("seed", [3, 4])
def test_net_force_and_torque_vanish(seed):
    verts, rng = _tangled(seed)
    vel = rng.normal(0.0, 0.3, verts.shape)
    strips = TriangleStrips.build(verts, grid_shape=(ROWS, COLS))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=5.0, damping=0.01, friction=0.4,
                                  capacity=20000, rest_gaps=False)
    force, torque, _ = _apply(contacts, _model(G, S), _state(verts, vel))
    assert contacts.contact_count() > 20
    # Any number of force threads striding over the buffer gives the same sums.
    contacts.force_threads = 7
    again = _apply(contacts, _model(G, S), _state(verts, vel))[0]
    np.testing.assert_array_equal(again, force)  # each segment sums its contacts in slot order
    # The GPU's way, each contact adding to its segments with atomics, sums the same terms in another order.
    contacts.scatter = True
    scattered, scattered_torque, scattered_mass = _apply(contacts, _model(G, S), _state(verts, vel))
    np.testing.assert_allclose(scattered, force, atol=MOMENTUM_RTOL * np.abs(force).max())
    np.testing.assert_allclose(scattered_torque, torque, atol=MOMENTUM_RTOL * np.abs(torque).max())
    origin = verts[:, :-1].reshape(-1, 3)
    magnitude = np.linalg.norm(force, axis=1).sum()
    assert magnitude > 0.0
    assert np.linalg.norm(force.sum(axis=0)) <= MOMENTUM_RTOL * magnitude
    total_torque = (torque + np.cross(origin, force)).sum(axis=0)
    moment_scale = (np.linalg.norm(force, axis=1) * np.linalg.norm(origin, axis=1)).sum()
    assert np.linalg.norm(total_torque) <= MOMENTUM_RTOL * moment_scale


def _explicit_step(contacts, verts, vel, model, mass, h, owner):
    """One explicit step of the system seen as translating point masses, one per segment.

    ``owner`` maps each vertex to its segment; every vertex of a segment moves with it. Returns the forces and
    the vertex velocities after the step.
    """
    force, _, _ = _apply(contacts, model, _state(verts, vel), dt=h)
    seg_v = np.zeros((model.seg_count, 3))
    seg_v[owner] = vel.reshape(-1, 3)
    vel_new = (seg_v + h * force / mass)[owner].reshape(vel.shape)
    return force, vel_new


def _tangential(v_rel, n):
    return v_rel - np.dot(v_rel, n) * n


@pytest.mark.parametrize("speed", [1.0e-5, 1.0e-3, 0.05, 0.5, 5.0])
@pytest.mark.parametrize("mu", [0.3, 50.0])
def test_friction_never_reverses_segment_pair(speed, mu):
    """Two crossing segments sliding past each other: one explicit step never increases |v_t| of the pair.

    The geometry is dyadic (exact in float32), so the normal force has no tangential round-off and the tangential
    velocity change is friction alone: the regularised Coulomb force, or, where that would reverse the slip in
    one step, the cap that brings it exactly to rest.
    """
    h, mass, k, c, slip = 2.0e-3, 1.0e-4, 10.0, 0.01, 1.0e-3
    delta, zb, half = 2.0**-11, -(2.0**-9), 2.0**-8
    verts = _pair([0, 0, 0], [0, 0, -(2.0**-7)], [-half, delta, zb], [half, delta, zb])
    rng = np.random.default_rng(int(speed * 1e6) + int(mu))
    slide = rng.normal(size=3)
    slide[1] = 0.0
    vel = np.zeros_like(verts)
    vel[0] = speed * slide / np.linalg.norm(slide)
    vel[1] = [0.0, -0.01, 0.0]
    contacts = _force_law(verts, threshold=THRESHOLD, stiffness=k, damping=c, friction=mu,
                                  slip_velocity=slip, capacity=4, rest_gaps=False)
    force, vel_new = _explicit_step(contacts, verts, vel, _model(2, 1, mass), mass, h, [0, 0, 1, 1])
    n = np.array([0.0, -1.0, 0.0])
    vt = _tangential(vel[0, 0] - vel[1, 0], n)
    before = np.linalg.norm(vt)
    after = np.linalg.norm(_tangential(vel_new[0, 0] - vel_new[1, 0], n))
    assert after <= before * (1.0 + 1e-6)

    fn = k * (THRESHOLD - delta) + c * 0.01
    m_eff = 0.5 * mass
    coulomb = mu * fn * before / np.hypot(before, slip)
    cap = m_eff * before / h
    np.testing.assert_allclose(force[0], fn * n - min(coulomb, cap) * vt / before, rtol=1e-4, atol=1e-4 * fn)
    if coulomb >= cap:
        assert after <= 1e-4 * before  # the cap stops the slip, without reversing it
    else:
        np.testing.assert_allclose(after, before - h * coulomb / m_eff, rtol=1e-4)


@pytest.mark.parametrize("damping", [0.01, 0.1, 10.0, 1.0e6])
def test_normal_damping_in_the_free_step_never_reverses_the_approach(damping):
    """Two crossing segments closing in along their normal, taken in the free step: the damper's force is
    ``min(c, m_eff / h) v``, the closed form, so one explicit step at most stops the approach. Uncapped, a damper past
    the pair's reduced mass over the step sent the pair apart faster than it came (both sides answer it whole), and
    ``long_hair`` with ``interactions.damping`` of 1.5 N s/m or more blew up at any step (the scene test below).

    The geometry is dyadic as in the friction tests; the spring's share (tiny here) is the closed form's as well."""
    h, mass, k, v = 2.0e-3, 1.0e-4, 1.0e-3, 0.25
    delta, zb, half = 2.0**-11, -(2.0**-9), 2.0**-8
    verts = _pair([0, 0, 0], [0, 0, -(2.0**-7)], [-half, delta, zb], [half, delta, zb])
    vel = np.zeros_like(verts)
    vel[1] = [0.0, -v, 0.0]  # b closes in on a along -y
    contacts = _force_law(verts, threshold=THRESHOLD, stiffness=k, damping=damping, friction=0.0, capacity=4,
                          rest_gaps=False)
    force, vel_new = _explicit_step(contacts, verts, vel, _model(2, 1, mass), mass, h, [0, 0, 1, 1])
    n = np.array([0.0, -1.0, 0.0])  # from b to a
    m_eff = 0.5 * mass
    damper = min(damping, m_eff / h) * v
    # float32 force from exact (dyadic) inputs through a few roundings: 1.4e-8 relative, measured
    np.testing.assert_allclose(force[0], (k * (THRESHOLD - delta) + damper) * n, rtol=1e-5)
    spring = h * k * (THRESHOLD - delta) / m_eff
    closing = np.dot(vel_new[0, 0] - vel_new[1, 0], n)  # -v before: closing
    # the force's round-off moves a stopped approach by 1.4e-8 v (3.6e-9 m/s, measured); the bound leaves it 7e-9
    assert -v <= closing <= spring * (1.0 + 1e-4) + 1e-9
    if damping >= m_eff / h:
        np.testing.assert_allclose(closing, spring, rtol=1e-3, atol=1e-6 * v)  # the approach stopped, not reversed


@pytest.mark.parametrize("speed", [1.0e-4, 0.05, 5.0])
def test_friction_never_reverses_vertex_face(speed):
    """A strand tip sliding on a strip face: one explicit step never increases |v_t| of vertex against face."""
    h, mu, mass, S2 = 2.0e-3, 50.0, 1.0e-4, 2
    verts = _strip_scene()
    vel = np.zeros_like(verts)
    vel[2] = [speed, 0.0, 0.3 * speed]  # strand 2 slides in the face's plane
    strips = TriangleStrips.build(verts, grid_shape=(1, 3))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=10.0, friction=mu,
                                  capacity=16, segment_segment=False, skip_neighbour_strips=False, rest_gaps=False)
    owner = [g * S2 + max(k - 1, 0) for g in range(3) for k in range(S2 + 1)]
    _, vel_new = _explicit_step(contacts, verts, vel, _model(3, S2, mass), mass, h, owner)
    found = contacts.contact_list()
    assert list(found["kind"]) == [CONTACT_VERTEX_FACE]
    tri, w = found["b"][0], found["w"][0].astype(np.float64)
    corners = contacts.strips.indices.numpy().reshape(-1, 3)[tri]
    n = np.array([0.0, 1.0, 0.0])

    def rel(v):
        flat = v.reshape(-1, 3)
        return flat[found["a"][0]] - w @ flat[corners]

    before = np.linalg.norm(_tangential(rel(vel), n))
    after = np.linalg.norm(_tangential(rel(vel_new), n))
    assert after <= before * (1.0 + 1e-5)
    assert after < 0.5 * before


def test_captured_step_follows_the_state():
    """A graph captured once (Warp captures on the CPU too) refits both BVHs on replay: after the vertices move,
    the replay finds the same contacts and forces as a direct call."""
    verts, rng = _tangled(3)
    vel = rng.normal(0.0, 0.3, verts.shape)
    strips = TriangleStrips.build(verts, grid_shape=(ROWS, COLS))
    contacts = _force_law(verts, strips, threshold=THRESHOLD, stiffness=5.0, damping=0.01, friction=0.4,
                                  capacity=20000, rest_gaps=False)
    model, state = _model(G, S), _state(verts, vel)
    n = model.seg_count
    force, torque, mass = wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=wp.vec3), wp.zeros(n, dtype=float)
    dt = wp.array([1.0e-3], dtype=float)
    contacts.apply(model, state, dt, force, torque, mass)  # load the module outside the capture
    with wp.ScopedCapture(device=state.vertex_positions.device) as capture:
        force.zero_()
        torque.zero_()
        mass.zero_()
        contacts.apply(model, state, dt, force, torque, mass)
    moved, _ = _tangled(7)
    state.vertex_positions.assign(moved.reshape(-1, 3))
    wp.capture_launch(capture.graph)
    replayed, count = force.numpy().copy(), contacts.contact_count()
    direct = _apply(contacts, model, state)[0]
    assert count == contacts.contact_count() > 20
    np.testing.assert_allclose(replayed, direct, atol=MOMENTUM_RTOL * np.abs(direct).max())


def test_overflow_sets_flags():
    verts, _ = _tangled(5)
    strips = TriangleStrips.build(verts, grid_shape=(ROWS, COLS))
    model = _model(G, S)
    roomy = _force_law(verts, strips, threshold=THRESHOLD, stiffness=1.0, capacity=20000)
    state = _state(verts)
    _apply(roomy, model, state)
    total = roomy.contact_count()
    assert total > 8 and not roomy.overflowed() and state.fault.numpy()[0] == 0

    tight = _force_law(verts, strips, threshold=THRESHOLD, stiffness=1.0, capacity=8)
    _apply(tight, model, state)
    assert tight.contact_count() == total  # still counted, only the first 8 stored
    assert len(tight.contact_list()["kind"]) == 8
    assert tight.overflowed()
    assert state.fault.numpy()[0] & int(Fault.CONTACT_OVERFLOW)
    tight.reset_overflow()
    assert not tight.overflowed()


def test_strip_adjacency():
    """Grid pairs are the rows and columns; a Delaunay of jittered grid coordinates keeps those and drops the
    long hull edges; the convex-hull fallback on a spherical cap gives every root neighbours."""
    verts, rng = _tangled(6)
    grid = TriangleStrips.build(verts, grid_shape=(ROWS, COLS))
    assert grid.pair_count == ROWS * (COLS - 1) + (ROWS - 1) * COLS
    assert grid.tri_count == 2 * S * grid.pair_count
    tri = grid.indices.numpy().reshape(-1, 3)
    a, b = grid.pairs[0]
    np.testing.assert_array_equal(tri[0], [a * (S + 1), b * (S + 1), a * (S + 1) + 1])
    np.testing.assert_array_equal(tri[1], [b * (S + 1), b * (S + 1) + 1, a * (S + 1) + 1])

    c, r = np.meshgrid(np.arange(COLS), np.arange(ROWS))
    uv = np.stack([c.ravel(), r.ravel()], axis=1) + rng.uniform(-0.05, 0.05, (G, 2))
    uv[:, 0] *= 1.0 + 0.001 * uv[:, 1] ** 2  # no exact co-circularity
    delaunay = TriangleStrips.build(verts, root_uv=uv, max_edge_ratio=1.3)
    pairs = {tuple(p) for p in delaunay.pairs.tolist()}
    assert {tuple(p) for p in grid.pairs.tolist()} <= pairs
    length = np.linalg.norm(uv[delaunay.pairs[:, 0]] - uv[delaunay.pairs[:, 1]], axis=1)
    assert length.max() < 1.3 * 1.5

    theta, phi = np.meshgrid(np.linspace(0.2, 1.2, 6), np.linspace(0.0, 2 * np.pi, 12, endpoint=False))
    cap = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    cap_verts = np.stack([cap, 1.1 * cap], axis=1)
    hull = TriangleStrips.build(cap_verts)
    degree = np.bincount(hull.pairs.ravel(), minlength=len(cap))
    assert degree.min() >= 2
    with pytest.raises(InteractionError, match="grid_shape"):
        TriangleStrips.build(verts, grid_shape=(3, 3))


def test_hair_contacts_refuse_stiffness_damping_and_friction_that_are_not_finite():
    """The contacts' stiffness, damping and friction coefficient must be finite and >= 0, each named in one line."""
    verts = np.zeros((2, 3, 3))
    verts[:, :, 2] = -np.arange(3)[None]
    verts[1, :, 0] = 0.01
    good = {"threshold": 0.002, "stiffness": 7.0, "damping": 0.0035, "friction": 0.3, "capacity": 64}
    HairContacts.build(verts, **good)
    for name in ("stiffness", "damping", "friction"):
        for value in (-1.0, np.inf, np.nan):
            with pytest.raises(InteractionError, match=f"{name} must be a finite number >= 0, got {value}"):
                HairContacts.build(verts, **{**good, name: value})


# -- the response inside the step ----------------------------------------------------------------------------------


def _crossing_pendulums(delta, L=0.02):
    """Two one-segment strands (ball-jointed at their roots, no joint springs, no gravity) whose midpoints cross
    ``delta`` apart: A hangs along -z at y = -delta/2, B lies along +x at y = +delta/2, z = -L/2. Returns the Solver
    (semi-implicit: no joint armature), its contacts, the model and its control."""
    import hairwarp as hw
    from hairwarp.model import Model, StrandParams
    from hairwarp.solver import Solver

    verts = np.array([[[0.0, -delta / 2, 0.0], [0.0, -delta / 2, -L]],
                      [[-L / 2, delta / 2, -L / 2], [L / 2, delta / 2, -L / 2]]])
    params = StrandParams(density=1300.0, radius=1.0e-3, bend_stiffness=0.0, twist_stiffness=0.0, damping=0.0,
                          drag=0.0)
    model = Model.build(verts, params, segments=1, gravity=(0.0, 0.0, 0.0))
    contacts = HairContacts.build(verts, threshold=THRESHOLD, stiffness=10.0, damping=0.01, friction=0.0,
                                  capacity=4, rest_gaps=False, segment_segment=True, response=True)
    solver = Solver(model, hw.Integrator.SEMI_IMPLICIT, contacts=contacts, threads=1)
    return solver, contacts, model, model.control()


def _with_point_velocities(solver, model, control, point_velocity, L):
    """A state at rest pose whose segments turn about their roots so that their midpoints move at
    ``point_velocity[g]`` (perpendicular to the segment)."""
    state = model.state()
    xf = state.seg_xform.numpy()
    w = np.zeros((model.seg_count, 3))
    for g in range(model.strand_count):
        R = Rotation.from_quat(xf[g, 3:7])
        axis = R.apply([0.0, 0.0, -1.0])
        omega = np.cross(axis * (L / 2), point_velocity[g]) / (L / 2) ** 2  # omega x r = v for v perpendicular to r
        w[g] = R.inv().apply(omega)
    state.joint_qd.assign(w.astype(np.float32))
    solver.forward_kinematics(state, control)
    return state


def _midpoints_velocity(state, start, L):
    """World velocities of the two midpoints from ``state``'s joint velocities in the frames of ``start`` (the
    response is solved there; its position update then turns the segments by h dw)."""
    xf = start.seg_xform.numpy().astype(np.float64)
    w = state.joint_qd.numpy().astype(np.float64)
    return np.array([Rotation.from_quat(xf[g, 3:7]).apply(np.cross(w[g], [0.0, 0.0, -L / 2])) for g in range(2)])


@pytest.mark.parametrize("speed", [0.5, 0.0, -0.01, -0.5])
def test_response_is_the_backward_euler_pair(speed):
    """Two pendulums whose midpoints meet (``speed`` > 0: approaching, each at that speed): the response gives each
    midpoint the normal velocity of the pair's backward-Euler force ``k d - D v_n'`` taken as a damper 2 D toward the
    pair's mean velocity, with the pendulum's effective mass at its midpoint, ``I_root / (L/2)^2``, in closed form.
    A pair that the free step sends apart faster than ``k d / D`` is left alone (a contact never pulls)."""
    L, delta, h, k, c = 0.02, 0.001, 1.0 / 60.0, 10.0, 0.01
    solver, contacts, model, control = _crossing_pendulums(delta, L)
    solver.set_dt(h)
    start = model.state()
    free = _with_point_velocities(solver, model, control, [[0.0, speed, 0.0], [0.0, -speed, 0.0]], L)
    contacts.detect(model, start)
    contacts.apply_forces(model, start, solver.dt)
    solver._respond(start, free, control)
    v = _midpoints_velocity(free, start, L)

    m = float(model.seg_mass.numpy()[0])
    inertia = model.seg_inertia.numpy()[0].astype(np.float64)
    m_eff = (inertia[0] + m * (L / 2) ** 2) / (L / 2) ** 2
    D = h * k + c
    vn = -2.0 * speed  # n from B to A is -y
    push = k * (THRESHOLD - delta) - D * vn
    dv = h * max(push, 0.0) / (m_eff + 2.0 * h * D)
    # float32 state and solve (a few dozen rounded operations on the speeds, ~1e-6 relative each): 1e-5 of the
    # speeds involved, and 1e-9 m/s for the resting case
    tol = 1e-5 * (abs(speed) + dv) + 1e-9
    np.testing.assert_allclose(v[0], [0.0, speed - dv, 0.0], atol=tol)
    np.testing.assert_allclose(v[1], [0.0, -speed + dv, 0.0], atol=tol)
    if push <= 0.0:
        assert dv == 0.0 and np.abs(v[0, 1] - speed) <= tol


def test_response_of_unequal_ends_is_the_backward_euler_pair():
    """A short pendulum meets a three times longer one at both midpoints (effective masses 1 : 3): each side, solved
    with its own strand alone, takes the pair's backward-Euler force ``(k d - D v_n) / (1 + h D (1/m_a + 1/m_b))``
    exactly, equal and opposite, with the effective masses ``I_root / lever^2`` in closed form. Split as a damper
    2 D toward the unweighted mean (the rule for equal ends), the short one took 1.5x the force the long one gave
    back: momentum, and energy, from nowhere."""
    import hairwarp as hw
    from hairwarp.model import Model, StrandParams
    from hairwarp.solver import Solver

    L, Lb, delta, h, k, c, speed = 0.02, 0.06, 0.001, 1.0 / 30.0, 10.0, 0.01, 0.3
    verts = [np.array([[0.0, -delta / 2, 0.0], [0.0, -delta / 2, -L]]),
             np.array([[-Lb / 2, delta / 2, -L / 2], [Lb / 2, delta / 2, -L / 2]])]
    params = StrandParams(density=1300.0, radius=1.0e-3, bend_stiffness=0.0, twist_stiffness=0.0, damping=0.0,
                          drag=0.0)
    model = Model.build(verts, params, segments=1, gravity=(0.0, 0.0, 0.0))
    contacts = HairContacts.build(verts, threshold=THRESHOLD, stiffness=k, damping=c, friction=0.0, capacity=4,
                                  rest_gaps=False, segment_segment=True, response=True)
    solver = Solver(model, hw.Integrator.SEMI_IMPLICIT, contacts=contacts, threads=1)
    control = model.control()
    solver.set_dt(h)
    start = model.state()
    free = model.state()
    xf = start.seg_xform.numpy()
    levers = (L / 2, Lb / 2)
    w = np.zeros((2, 3))
    for g, v in enumerate(([0.0, speed, 0.0], [0.0, -speed, 0.0])):  # the midpoints approach, each at speed
        R = Rotation.from_quat(xf[g, 3:7])
        r = R.apply([0.0, 0.0, -levers[g]])
        w[g] = R.inv().apply(np.cross(r, v) / levers[g] ** 2)
    free.joint_qd.assign(w.astype(np.float32))
    solver.forward_kinematics(free, control)
    contacts.detect(model, start)
    contacts.apply_forces(model, start, solver.dt)
    solver._respond(start, free, control)
    w = free.joint_qd.numpy().astype(np.float64)
    v = [Rotation.from_quat(xf[g, 3:7]).apply(np.cross(w[g], [0.0, 0.0, -levers[g]])) for g in range(2)]

    m = model.seg_mass.numpy().astype(np.float64)
    inertia = model.seg_inertia.numpy().astype(np.float64)
    inv_mass = [levers[g] ** 2 / (inertia[g, 0] + m[g] * levers[g] ** 2) for g in range(2)]
    assert 2.9 < inv_mass[0] / inv_mass[1] < 3.1
    D = h * k + c
    push = k * (THRESHOLD - delta) + D * 2.0 * speed
    F = push / (1.0 + h * D * (inv_mass[0] + inv_mass[1]))
    # float32 state and solve: 1e-5 of the speeds involved (as for the equal pair above)
    tol = 1e-5 * speed
    np.testing.assert_allclose(v[0], [0.0, speed - h * inv_mass[0] * F, 0.0], atol=tol)
    np.testing.assert_allclose(v[1], [0.0, -speed + h * inv_mass[1] * F, 0.0], atol=tol)


def test_response_friction_never_reverses_the_slip():
    """The same pendulums sliding past each other along x as they meet: the friction damper takes slip out and never
    reverses it, and takes no more than the cone allows over the step, ``h mu f_n / m_eff`` of each midpoint, ``f_n``
    the normal force the step's solve gives the pair, ``(k d - D v_n) / (1 + h D (1/m_a + 1/m_b))``. (Bounded by the
    force on the free velocities, ``k d - D v_n``, instead, friction at one step a frame held strands 7 times as hard
    as the cone allows: ``h D / m_eff`` of a contact is large there, and the stuck strands stretched their links.)"""
    L, delta, h, mu = 0.02, 0.001, 1.0 / 60.0, 0.5
    solver, contacts, model, control = _crossing_pendulums(delta, L)
    contacts._response_buffer.friction = mu
    solver.set_dt(h)
    start = model.state()
    for slide in (1e-4, 0.01, 1.0):
        free = _with_point_velocities(solver, model, control, [[0.0, 0.1, 0.0], [0.0, 0.0, slide]], L)
        contacts.detect(model, start)
        contacts.apply_forces(model, start, solver.dt)
        before = _midpoints_velocity(free, start, L)
        solver._respond(start, free, control)
        after = _midpoints_velocity(free, start, L)
        slip_before = (before[0] - before[1])[2]
        slip_after = (after[0] - after[1])[2]
        # float32: the slip read back carries ~1e-7 relative round-off, the cone bound a few float32 products
        assert 0.0 <= slip_after * np.sign(slip_before) <= abs(slip_before) * (1 + 1e-6)
        assert abs(slip_after) < abs(slip_before)
        m = float(model.seg_mass.numpy()[0])
        inertia = model.seg_inertia.numpy()[0].astype(np.float64)
        m_eff = (inertia[0] + m * (L / 2) ** 2) / (L / 2) ** 2
        D = h * 10.0 + 0.01
        fn = (10.0 * (THRESHOLD - delta) + D * 0.1) / (1.0 + h * D * 2.0 / m_eff)
        assert abs(after[1, 2] - before[1, 2]) <= h * mu * fn / m_eff * (1 + 1e-4)
        if slide == 1.0:  # sliding fast: most of the cone (a damper on the slip it leaves: 0.93 of it here)
            assert abs(after[1, 2] - before[1, 2]) >= 0.8 * h * mu * fn / m_eff


def test_link_response_converges_to_the_backward_euler_pair():
    """The same pendulums tied at their midpoints by a link (slack at rest) and moving apart along y at ``speed``
    each. The links' response is Gauss-Seidel sweeps over the two strands from the free step (``link_sweep``).
    Against the pair's backward-Euler step solved as one coupled system in closed form (the link's force ``-h k u'``
    with the end-of-step relative velocity; damping acts along the link, which has no direction while slack): the
    error falls with every sweep (the sweeps minimise the step's quadratic energy) and reaches float32 round-off."""
    import hairwarp as hw
    from hairwarp.interactions import StaticLinks
    from hairwarp.solver import Solver

    L, delta, h, k, speed = 0.02, 0.001, 1.0 / 60.0, 5.0, 0.3
    _, _, model, control = _crossing_pendulums(delta, L)
    # The turn rates each link end answers to, and its velocity per unit of each (rows): A's end carries the rest
    # offset (it sits on B's axis, delta off A's) and turns A about x only; B's end, on B's axis, turns B about z
    # (along y) and about y (along z, the offset's share).
    m = float(model.seg_mass.numpy()[0])
    inertia = model.seg_inertia.numpy()[0].astype(np.float64)
    i_root = inertia[0] + m * (L / 2) ** 2
    J0, J1 = np.array([[0.0, L / 2, delta]]), np.array([[0.0, L / 2, 0.0], [0.0, 0.0, -L / 2]])
    r0, r1 = np.array([-speed / (L / 2)]), np.array([speed / (L / 2), 0.0])
    # I (r' - r) = h J f at each end, f = -/+ h k (J0^T r0' - J1^T r1'): one symmetric positive definite system
    c = h * h * k
    lhs = np.block([[i_root * np.eye(1) + c * J0 @ J0.T, -c * J0 @ J1.T],
                    [-c * J1 @ J0.T, i_root * np.eye(2) + c * J1 @ J1.T]])
    exact = np.linalg.solve(lhs, i_root * np.concatenate([r0, r1]))
    expect = [J0.T @ exact[:1] * [1.0, 1.0, 0.0], J1.T @ exact[1:]]

    errors = []
    for sweeps in (1, 4, 16, 64, 256):
        links = StaticLinks.build(model.rest_vertex_positions, neighbours=1, radius=0.01,
                                  stiffness=k * REFERENCE_SEGMENT_LENGTH / L,  # a link of k between segments L long
                                  damping=0.01, break_length=1.0, response=True, sweeps=sweeps)
        assert links.link_count == 1 and links.seg_a[0] == 0
        assert len(links.color_views) == 2
        solver = Solver(model, hw.Integrator.SEMI_IMPLICIT, links=links, threads=1)
        solver.set_dt(h)
        start = model.state()
        free = _with_point_velocities(solver, model, control, [[0.0, -speed, 0.0], [0.0, speed, 0.0]], L)
        links.apply_forces(model, start, solver.dt, solver.seg_force, solver.seg_torque)
        solver._respond(start, free, control)
        v = _midpoints_velocity(free, start, L)
        errors.append(max(np.abs(v[g] - expect[g]).max() for g in range(2)))
    # ends this stiff (h^2 k / m_eff ~ 50) converge slowly: the first strand solved goes nearly all the way to its
    # partner's free velocity, and the sweeps bring the pair back to its common velocity only by degrees (at this
    # step, which starts cold, ``sweeps`` n runs 16 n: 0.086 m/s off of the 0.3 after 16, 0.0023 after 64); more
    # sweeps get nearer, down to round-off from 256 on: float32's 6e-8 times the pair's condition, about
    # h^2 k / m_eff ~ 50, is 3e-6 of the speed (the floor measured 1.3e-6 and 2.1e-6 of it as the blocks' sums were
    # ordered one way and another)
    assert all(b < a or b < 4e-6 * speed for a, b in zip(errors, errors[1:])), errors
    # float32 state and solve against float64: 1e-5 of the speed (as in the contact pair above)
    assert errors[-1] < 1e-5 * speed, errors


def test_sweeps_converge_a_link_and_a_contact_to_their_coupled_backward_euler_step():
    """The same pendulums, tied at their midpoints by a link and meeting there (a segment-segment contact), each
    midpoint approaching the other at ``speed``. Link and contact both act on the two strands: the sweeps solve both,
    the contact with its whole damper toward the other strand's latest answer (``kernels.contacts.sweep_entry_force``).
    Against the step of the two solved as one coupled system in closed form (the link's ``-h k u'``; the contact's
    ``k_c d - D v_n'`` along the normal, in contact throughout), the error falls with the sweeps to float32 round-off
    (0.23, 0.17, 0.026, then 1.6e-5 and 2.8e-7 m/s at 32 and 128 sweeps: from the free step the first strand solved
    goes nearly all the way to its partner's free velocity). Held through the sweeps as a damper split between the
    two sides (the GPU's form, without contact lists per segment), the contact keeps each midpoint's answer to the
    other's free velocity, and the error stops at 2.2e-5 m/s from 8 sweeps on."""
    import hairwarp as hw
    from hairwarp.interactions import StaticLinks
    from hairwarp.solver import Solver

    L, delta, h, k, kc, c, speed = 0.02, 0.001, 1.0 / 240.0, 5.0, 10.0, 0.01, 0.3
    _, _, model, control = _crossing_pendulums(delta, L)
    m = float(model.seg_mass.numpy()[0])
    inertia = model.seg_inertia.numpy()[0].astype(np.float64)
    i_root = inertia[0] + m * (L / 2) ** 2
    # turn rates: A about x, B about z and about y (the link test's); the link's rows as there
    J0, J1 = np.array([[0.0, L / 2, delta]]), np.array([[0.0, L / 2, 0.0], [0.0, 0.0, -L / 2]])
    r = np.array([speed / (L / 2), -speed / (L / 2), 0.0])  # the midpoints approach along y
    link = h * h * k * np.block([[J0 @ J0.T, -J0 @ J1.T], [-J1 @ J0.T, J1 @ J1.T]])
    # the contact along n = -y (from B to A): v_n = -(g . r), its force on the rates -g (k_c d + D g . r)
    g = np.array([L / 2, -L / 2, 0.0])
    D = h * kc + c
    lhs = i_root * np.eye(3) + link + h * D * np.outer(g, g)
    exact = np.linalg.solve(lhs, i_root * r - h * kc * (THRESHOLD - delta) * g)
    assert kc * (THRESHOLD - delta) + D * (g @ exact) > 0.0  # in contact at the end of the step
    expect = [J0.T @ exact[:1] * [1.0, 1.0, 0.0], J1.T @ exact[1:]]

    errors, held = [], []
    for sweeps in (1, 2, 8, 32, 128):
        for scatter in (False, True):
            links = StaticLinks.build(model.rest_vertex_positions, neighbours=1, radius=0.01,
                                      stiffness=k * REFERENCE_SEGMENT_LENGTH / L,  # a link of k between segments L long
                                      damping=0.0, break_length=1.0, response=True, sweeps=sweeps)
            contacts = HairContacts.build(model.rest_vertex_positions, threshold=THRESHOLD, stiffness=kc, damping=c,
                                          friction=0.0, capacity=4, rest_gaps=False, segment_segment=True,
                                          response=True)
            contacts.scatter = scatter  # the GPU's form: no contact lists per segment, the contacts held
            assert contacts.sweeps_contacts == (not scatter)
            solver = Solver(model, hw.Integrator.SEMI_IMPLICIT, links=links, contacts=contacts, threads=1)
            # a warm step 4 ** WARM_SWEEP_GROWTH as many at 4 h; at 1/30 s those of SWEEP_GROWTH_STEP (1/45 s,
            # 5.33 h)
            assert links.sweeps_at(h) == sweeps and links.sweeps_at(4.0 * h) == 16 * sweeps
            longest = math.ceil(sweeps * (240 / 45) ** 2)
            assert links.sweeps_at(8.0 * h) == links.sweeps_at(240.0 / 45.0 * h) == longest
            # a step that starts cold (without the links' last force) twice as many, 4 ** SWEEP_GROWTH times those at
            # 4 h: 25 for 1 at one step a frame
            assert links.sweeps_at(h, cold=True) == 2 * sweeps and links.sweeps_at(4.0 * h, cold=True) == 16 * sweeps
            assert links.sweeps_at(8.0 * h, cold=True) == math.ceil(2 * sweeps * (240 / 45) ** 1.5)
            solver.set_dt(h)
            start = model.state()
            free = _with_point_velocities(solver, model, control, [[0.0, speed, 0.0], [0.0, -speed, 0.0]], L)
            links.apply_forces(model, start, solver.dt, solver.seg_force, solver.seg_torque)
            contacts.detect(model, start)
            contacts.apply_forces(model, start, solver.dt)
            solver._respond(start, free, control)
            v = _midpoints_velocity(free, start, L)
            (held if scatter else errors).append(max(np.abs(v[q] - expect[q]).max() for q in range(2)))
    assert all(b < a or b < 1e-6 * speed for a, b in zip(errors, errors[1:])), errors
    # float32 state and solve against float64: 1e-5 of the speed (as in the pairs above)
    assert errors[-1] < 1e-5 * speed, errors
    # held (0.043, 6.0e-3, then 2.2e-5 from 8 sweeps on), the sweeps converge to another answer: the contact's
    # as its split damper gives it
    assert abs(held[-1] - held[-2]) < 1e-6 * speed and held[-1] > 30.0 * errors[-1], (held, errors)


PENDULUM_LENGTH = 0.02  # [m], the segments of ``_pendulum_grid``


def _pendulum_grid():
    """A 3 x 4 grid of one-segment pendulums (2 cm, 4 mm apart, tilted at random so that links meet them at single
    points; no gravity, no joint springs, damping or drag): the model."""
    from hairwarp.model import Model, StrandParams

    L = PENDULUM_LENGTH
    roots = np.array([[c * 0.004, r * 0.004, 0.0] for r in range(3) for c in range(4)])
    dirs = np.array([0.0, 0.0, -1.0]) + np.random.default_rng(11).uniform(-0.35, 0.35, (12, 3)) * [1.0, 1.0, 0.0]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    params = StrandParams(density=1300.0, radius=1.0e-3, bend_stiffness=0.0, twist_stiffness=0.0, damping=0.0,
                          drag=0.0)
    return Model.build(np.stack([roots, roots + L * dirs], axis=1), params, segments=1, gravity=(0.0, 0.0, 0.0))


def _tied_lattice(k: float, sweeps: int, w0, h: float):
    """A 3 x 4 grid of one-segment pendulums (2 cm, 4 mm apart, tilted at random so that their links meet them at
    single points; no gravity, no joint springs) tied by links of stiffness ``k`` (no damping), turning at ``w0``:
    one step of ``h``. Returns the kinetic plus the links' energy ``1/2 k |l|^2`` before and after, and ``h^2 k /
    m_eff`` of a pendulum's tip."""
    import hairwarp as hw
    from hairwarp.interactions import StaticLinks
    from hairwarp.solver import Solver

    L = PENDULUM_LENGTH
    model = _pendulum_grid()
    links = StaticLinks.build(model.rest_vertex_positions, neighbours=2, radius=0.006,
                              stiffness=k * REFERENCE_SEGMENT_LENGTH / L, damping=0.0,
                              break_length=1.0, response=True)
    solver = Solver(model, hw.Integrator.SEMI_IMPLICIT, links=links, threads=1)
    links.sweeps_at = lambda dt, cold=False: sweeps  # the step's sweeps, exactly
    control = model.control()
    m = float(model.seg_mass.numpy()[0])
    inertia = model.seg_inertia.numpy()[0].astype(np.float64)
    i_bend, i_spin = inertia[0] + m * (L / 2) ** 2, inertia[2]

    def energy(state):
        w = state.joint_qd.numpy().astype(np.float64)
        kinetic = 0.5 * (i_bend * (w[:, 0] ** 2 + w[:, 1] ** 2) + i_spin * w[:, 2] ** 2).sum()
        links.apply_forces(model, state, solver.dt, solver.seg_force, solver.seg_torque)  # the ends, in response mode
        gap = links.link_point_b.numpy().astype(np.float64) - links.link_point_a.numpy().astype(np.float64)
        # each link's k: about k, its segments a little longer than L
        return kinetic + 0.5 * (links.stiffness * links.scale * (gap ** 2).sum(axis=1)).sum()

    start = model.state()
    start.joint_qd.assign(np.asarray(w0, dtype=np.float32))
    solver.forward_kinematics(start, control)
    end = model.state()
    solver.set_dt(h)
    before = energy(start)
    solver.step(start, end, control, h)
    assert int(end.fault.numpy()[0]) == 0
    return before, energy(end), h * h * k * L * L / (4.0 * i_bend)


@pytest.mark.parametrize("k", [1.0, 5.0])
def test_link_sweeps_take_energy_out_of_a_lattice(k):
    """Over one step of 1/60 s a tied lattice's kinetic plus link energy must not rise (the links' backward-Euler
    step only dissipates). A Jacobi pass between strands, each strand answering its links as if their other ends
    held still (the response's first pass until 2026-12-05), multiplied it by 2.3 (k = 1, h^2 k / m_eff 2.5) and 8.1
    (k = 5, 12.7). The sweeps from the free step take energy out from the first: one sweep leaves 0.48 and 0.81 of
    it, 8 (``sweeps`` = 1 at this step, ``sweeps_at``) 0.45 and 0.20, 16 (the default 2) 0.45 and 0.18, and more
    settle on the coupled backward-Euler step's 0.449 and 0.177 (64 and 512 sweeps within 1e-3 of each other). The
    sweeps lower the step's quadratic energy at every one, not this energy, which can rise a little between them
    (0.4487 at 16 sweeps, 0.4492 at 64). Turn rates about 1 rad/s keep the step's turns near 1/60 rad, where the
    step's linearisation holds (the residual is second order in it)."""
    w0 = np.zeros((12, 3))
    w0[:, :2] = np.random.default_rng(3).normal(0.0, 1.0, (12, 2))
    h = 1.0 / 60.0
    ratio = {}
    for sweeps in (1, 8, 16, 64, 512):
        before, after, stiff = _tied_lattice(k, sweeps, w0, h)
        ratio[sweeps] = after / before
    assert 2.0 < stiff < 15.0
    assert max(ratio.values()) < 0.9, ratio
    # converged: float32 energies of ~1e-7 J carry ~1e-6 relative round-off, the solve's residual more
    assert abs(ratio[64] - ratio[512]) < 1e-3 * ratio[512], ratio
    # nearer the converged step with more sweeps
    gap = {n: abs(r - ratio[512]) for n, r in ratio.items()}
    assert gap[1] > gap[8] > gap[64], ratio


def _stretched_lattice(h: float, steps: int, warm_start, amplitude: float):
    """A 3 x 4 grid of one-segment pendulums (as ``_tied_lattice``'s, ``implicit_joints``) tied by links of 2 N/m and
    0.002 N s/m, released with its joints turned at random by about ``amplitude`` [rad], run ``steps`` steps of ``h``
    with 64 sweeps a step (converged), the links' force of the last step in the free step or not
    (``Solver._warm_start``), or ``"gated"`` the share of it that ``WARM_GATE_SPEED`` keeps.
    Returns the tips [m], the joint velocities [rad/s] and the links' free-step rate at ``h``."""
    import hairwarp as hw
    from hairwarp.interactions import StaticLinks
    from hairwarp.solver import Solver

    L = PENDULUM_LENGTH
    model = _pendulum_grid()
    links = StaticLinks.build(model.rest_vertex_positions, neighbours=2, radius=0.006,
                              stiffness=2.0 * REFERENCE_SEGMENT_LENGTH / L, damping=0.002, break_length=1.0,
                              response=True)
    links.sweeps_at = lambda dt, cold=False: 64
    solver = Solver(model, hw.Integrator.IMPLICIT_JOINTS, links=links, threads=1)
    if warm_start != True:  # noqa: E712 (True, False or "gated")
        solver._warm_start = lambda dt, gated=False: warm_start == "gated" and gated
    # the whole force where asked: the pendulums' joints are limp, which would take it gated (WARM_START_BEND_RATE)
    solver._bend_rate_per_second = lambda: math.inf
    turn = Rotation.from_rotvec(np.random.default_rng(5).normal(0.0, amplitude, (12, 3)) * [1.0, 1.0, 0.0])
    control = model.control()
    state, other = model.state(), model.state()
    state.joint_q.assign((turn * Rotation.from_quat(state.joint_q.numpy())).as_quat().astype(np.float32))
    solver.forward_kinematics(state, control)
    for _ in range(steps):
        solver.step(state, other, control, h)
        state, other = other, state
    assert links.warm_start is bool(warm_start) and (links.warm_gate > 0.0) is (warm_start == "gated")
    assert int(state.fault.numpy()[0]) == 0
    tips = state.vertex_positions.numpy().astype(np.float64).reshape(12, 2, 3)[:, 1]
    return tips, state.joint_qd.numpy().astype(np.float64), links.free_step_rate(model.seg_mass.numpy(), h)


def test_links_warm_start_gives_the_same_steps(monkeypatch):
    """Links solved after the free step put their force of the last step into it (``Solver._warm_start``) and the
    response solves the change: without body contacts, for the linear part of a step the same system, so the same
    answer. A stretched lattice (``_stretched_lattice``), three steps of 1/960 s (the first starts cold): the joint
    velocities agree with the whole force solved in the response to 1e-4 of their largest change (measured 4e-6). At
    1/240 s the free step's turns part the two, by a term that falls with the step faster than its square, and both
    are as near the answer of steps of 1/7680 s over three steps (tips 78.7 and 78.6 um from it). Any share of the
    last force gives that answer: so does the gated one of long steps (``WARM_GATE_SPEED``), each link's falling off
    with the speed its ends part at (measured 2e-6).

    The linear parts are compared without the links' geometric stiffness (``StaticLinks.geometric_stiffness``), which
    is no force: it slows the turn under the whole force where a step starts cold and under the change where it
    starts warm, which parts the two by 4e-3 of the change. With it, both steps of 1/240 s stay as near the fine
    answer (warm 83.0 um, cold 96.5: the price of the term on so stretched a lattice)."""
    monkeypatch.setattr(StaticLinks, "geometric_stiffness", 0.0)
    one = {warm: _stretched_lattice(1.0 / 960.0, 3, warm, 0.01) for warm in (True, False, "gated")}
    change = np.abs(one[False][1]).max()  # from rest
    assert change > 0.1  # the stretched links set the lattice moving
    np.testing.assert_allclose(one[True][1], one[False][1], rtol=0.0, atol=1e-4 * change)
    np.testing.assert_allclose(one["gated"][1], one[False][1], rtol=0.0, atol=1e-4 * change)
    monkeypatch.undo()
    fine = _stretched_lattice(1.0 / 7680.0, 96, False, 0.05)[0]
    error = {warm: np.sqrt(np.sum((_stretched_lattice(1.0 / 240.0, 3, warm, 0.05)[0] - fine) ** 2, axis=1).mean())
             for warm in (True, False)}
    # no less accurate (83.0 against 96.5 um; without the geometric stiffness 78.7 and 78.6, where 10 % leaves room for
    # the float32 sums of 96 fine steps)
    assert error[True] <= 1.1 * error[False], error


@pytest.mark.parametrize("with_contacts, h, break_length", [
    (False, 1.0 / 60.0, 1.0), (True, 1.0 / 60.0, 1.0), (True, 1.0 / 240.0, 2.0e-4)])
def test_captured_step_with_link_sweeps_replays_the_eager_step(with_contacts, h, break_length):
    """A step with the links' sweeps captured in a Warp graph on the CPU (one thread) and replayed gives the eager
    step's bits, with what the sweeps keep between their launches spoilt before the replay: nothing of the step
    happens on the host, and the colours' launches are fixed. ``with_contacts``: hair contacts detected in the step
    and solved in the sweeps too, their per-step list spoilt as well. At 1/240 s with links that break within the
    step (``BREAK_SOLVED_STEP``), the sweep that solves their strands again runs in the capture whatever it finds,
    its unmarked strands returning at once, where the eager step runs it only when a link broke."""
    from hairwarp.interactions import StaticLinks
    from hairwarp.model import Model, StrandParams
    from hairwarp.solver import Solver

    roots = np.array([[c * 0.004, r * 0.004, 0.0] for r in range(3) for c in range(4)])
    dirs = np.array([0.0, 0.0, -1.0]) + np.random.default_rng(11).uniform(-0.35, 0.35, (12, 3)) * [1.0, 1.0, 0.0]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    params = StrandParams(density=1300.0, radius=1.0e-3, bend_stiffness=1e-6, damping=0.0, drag=0.0)
    model = Model.build(np.stack([roots, roots + 0.01 * dirs, roots + 0.02 * dirs], axis=1), params, segments=2)
    links = StaticLinks.build(model.rest_vertex_positions, neighbours=2, radius=0.006, stiffness=5.0, damping=0.01,
                              break_length=break_length, response=True, sweeps=2)
    contacts = None
    if with_contacts:
        contacts = HairContacts.build(model.rest_vertex_positions, threshold=0.004, stiffness=20.0, damping=0.01,
                                      friction=0.3, capacity=256, rest_gaps=False, segment_segment=True,
                                      response=True)
    solver = Solver(model, "implicit_joints", links=links, contacts=contacts, threads=1)
    assert solver.link_sweeps and len(links.color_views) > 1
    control = model.control()
    start = model.state()
    start.joint_qd.assign(np.random.default_rng(3).normal(0.0, 1.0, (model.seg_count, 3)).astype(np.float32))
    solver.forward_kinematics(start, control)
    eager, replayed = model.state(), model.state()
    warm = (contacts.warm_force, contacts.warm_torque) if with_contacts else ()  # their force of the last step
    kept = {a: a.numpy().copy() for a in (links.link_broken, links.link_broken_total, links.link_warm, *warm)}
    solver.step(start, eager, control, h)
    broken = links.link_broken.numpy().copy()
    if break_length < 1.0:  # links broke within the step, and their strands were solved again
        assert 0 < broken.sum() < links.link_count and links.link_broken_total.numpy()[0] == broken.sum()
        assert links.strand_redo.numpy().sum() > 0
    for a, value in kept.items():  # the replay starts where the eager step did
        a.assign(value)
    with wp.ScopedCapture(device=model.device) as capture:
        solver.step(start, replayed, control, h)
    replayed.joint_q.zero_()
    replayed.joint_qd.zero_()
    for a, value in kept.items():
        a.assign(value)
    # what the sweeps keep between their launches, spoilt: the replay must make it again
    spoilt = [solver.free_q, solver.free_qd, solver.free_velocities, solver.answered_velocities, solver.swept.force,
              solver.swept.C, solver.solved.force, solver.solved.C, solver.dampers.C, links.strand_redo,
              *solver.answered_sweeps]
    if with_contacts:
        listed = contacts.sweep_contacts.end.numpy() - contacts.seg_entry_start.numpy()[:-1]
        assert contacts.sweeps_contacts and listed.sum() > 0  # the sweeps solved contacts
        sweep = contacts.sweep_contacts
        spoilt += [contacts.contact_counter, sweep.end, sweep.friction, sweep.free]
    for a in spoilt:
        a.fill_(1)
    wp.capture_launch(capture.graph)
    assert not np.array_equal(eager.joint_qd.numpy(), start.joint_qd.numpy())  # the step did something
    for key in ("joint_q", "joint_qd", "vertex_positions", "vertex_velocities"):
        np.testing.assert_array_equal(getattr(replayed, key).numpy(), getattr(eager, key).numpy())
    np.testing.assert_array_equal(links.link_broken.numpy(), broken)


def test_fault_names_the_response_stage():
    """Links that stop two strands meeting at 20 m/s within one frame-rate step change their joints by more than
    half a turn in the response: its own bit is set, not the free dynamics', and the message names the response."""
    import hairwarp as hw
    from hairwarp.interactions import StaticLinks
    from hairwarp.solver import SimulationFault, Solver

    L, h = 0.02, 1.0 / 30.0
    _, _, model, control = _crossing_pendulums(0.001, L)
    links = StaticLinks.build(model.rest_vertex_positions, neighbours=1, radius=0.01, stiffness=1.0e4, damping=0.0,
                              break_length=1.0, response=True)
    solver = Solver(model, hw.Integrator.SEMI_IMPLICIT, links=links, threads=1)
    start = _with_point_velocities(solver, model, control, [[0.0, -10.0, 0.0], [0.0, 10.0, 0.0]], L)
    end = model.state()
    solver.step(start, end, control, h)
    bits = int(end.fault.numpy()[0])
    assert bits & int(Fault.INTERACTION_RESPONSE)
    assert not bits & int(Fault.JOINT_SPEED | Fault.COLLISION_SPEED)
    with pytest.raises(SimulationFault, match="in links and hair contacts.*links.response") as info:
        solver.check(end, frame=1)
    assert info.value.stage.startswith("links and hair contacts")
