"""Static links (DESIGN §4.3) against float64 numpy evaluations of the seed's spring formula, explicit and solved
implicitly per link over the step.

The arrays a solver step passes are built here directly (chains of rigid segments from random rotations, with
rigid-body vertex velocities), independent of the Model and State classes.
"""

from types import SimpleNamespace

import numpy as np
import pytest
import warp as wp
from _reference import segment_distances
from scipy.spatial.transform import Rotation

from hairwarp.interactions import InteractionError, StaticLinks
from hairwarp.kernels.types import REFERENCE_SEGMENT_LENGTH

# Coordinates are below 0.1 m, where float32 spacing is 7.5e-9 m; the two ends of a link are about ten
# rounded operations from the stored vertices, so a link at rest measures well under 1e-7 m.
REST_LENGTH_TOL = 1.0e-7
# Per-segment sums of a few float32 products: relative error of a few 1e-7 of the largest term.
FORCE_RTOL = 1.0e-5
# Momentum sums cancel many float32 terms: allowed residual as a fraction of the sum of magnitudes.
MOMENTUM_RTOL = 1.0e-5
# Segment distances closer than this [m] are a tie (float64 round-off of equal distances).
TIE_TOL = 1.0e-12
# |l| of a link closer than this to break_length may round to either side in float32 [m].
BREAK_BAND = 1.0e-6

ROWS, COLS, S = 4, 5, 8
G = ROWS * COLS
SEG_LEN = 0.01
SPACING = 0.004
RADIUS = 0.006
K_S, K_D, DT = 20.0, 0.05, 1.0e-3
# Light enough that the implicit links' h^2 k W is of order one (0.4 to 3.5 by the arm): the implicit solve changes
# their forces by factors, not by round-off.
SEG_MASS = 1.0e-4
JOINT_BEND = 2.2e-3


def _chain(roots, rot):
    """Vertices (G, S+1, 3) of chains whose segment k has world rotation rot[g*S + k] and lies along its -z."""
    axis = rot.apply(np.tile([0.0, 0.0, -SEG_LEN], (len(rot), 1))).reshape(G, S, 3)
    verts = np.zeros((G, S + 1, 3))
    verts[:, 0] = roots
    verts[:, 1:] = roots[:, None] + np.cumsum(axis, axis=1)
    return verts


def _groom(rng, bend=0.15):
    c, r = np.meshgrid(np.arange(COLS), np.arange(ROWS))
    roots = np.stack([c.ravel() * SPACING, r.ravel() * SPACING, np.zeros(G)], axis=1)
    rot = Rotation.from_rotvec(rng.normal(0.0, bend, (G * S, 3)))
    return roots, rot


def _perpendicular_omega(rng, verts, scale):
    """Random world angular velocities (G*S, 3), perpendicular to each segment (what vertex velocities carry)."""
    d = np.diff(verts, axis=1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    w = rng.normal(0.0, scale, d.shape)
    return w - np.sum(w * d, axis=1, keepdims=True) * d


def _velocities(rng, verts, omega, scale):
    """Rigid-body vertex velocities: a random root velocity, then v_{k+1} = v_k + w_k x (x_{k+1} - x_k)."""
    d = np.diff(verts, axis=1)
    dv = np.cross(omega.reshape(G, S, 3), d)
    v = np.zeros_like(verts)
    v[:, 0] = rng.normal(0.0, scale, (G, 3))
    v[:, 1:] = v[:, :1] + np.cumsum(dv, axis=1)
    return v


def _arrays(verts, rot, vel, head=None):
    """A state: segment frames, vertices, velocities, and joints relative to ``head`` (default identity), of which the
    links read the root joints (the head rotation is the root frame times the root joint's inverse)."""
    head = Rotation.identity() if head is None else head
    xform = np.concatenate([verts[:, :-1].reshape(-1, 3), rot.as_quat()], axis=1)
    state = SimpleNamespace(
        seg_xform=wp.array(xform, dtype=wp.transform),
        joint_q=wp.array((head.inv() * rot).as_quat(), dtype=wp.quat),
        vertex_positions=wp.array(verts.reshape(-1, 3), dtype=wp.vec3),
        vertex_velocities=wp.array(vel.reshape(-1, 3), dtype=wp.vec3),
        fault=wp.zeros(1, dtype=wp.int32),
    )
    return state


def _model():
    return SimpleNamespace(
        seg_per_strand=S,
        seg_count=G * S,
        seg_length=wp.array(np.full(G * S, SEG_LEN), dtype=float),
        seg_mass=wp.array(np.full(G * S, SEG_MASS), dtype=float),
        joint_stiffness=wp.array(np.tile([JOINT_BEND, JOINT_BEND, JOINT_BEND], (G * S, 1)), dtype=wp.vec3),
    )


def _apply(links, model, state):
    force = wp.zeros(G * S, dtype=wp.vec3)
    torque = wp.zeros(G * S, dtype=wp.vec3)
    mass = wp.zeros(G * S, dtype=float)
    links.apply(model, state, wp.array([DT], dtype=float), force, torque, mass)
    return force.numpy().astype(np.float64), torque.numpy().astype(np.float64), mass.numpy().astype(np.float64)


def _reference(links, verts, rot, vel, omega, skip=None, head=None):
    """Float64 seed formula f = [k_s |l| - k_d (v . l)/|l|] l/|l| on a at x_a' and -f on b at x_b, per segment, with
    x_a' = X_a (0, 0, -f_a L) + R_min(R_head d0 -> d_a) R_head r0 (the rest offset following a's axis, not its spin).
    With ``links.implicit_springs``, the backward-Euler force of each link alone, f = k (l - h u') - c (n . u') n with
    u' = u + h W f, solved here as a 3x3 linear system; W = sum over the two ends of 1/m + |r|^2 / (m L^2 / 12), r
    from the segment's centre of mass. Either way each link's k_d is divided by h k_d times the larger of its two
    segments' sums of their links' end bounds W (scaled as the links), where that passes 1.

    The offset end's velocity and a's torque take the transport's twist too: ``-(w . g)(d x o)`` and ``-g ((d x o) .
    f)``, ``g = (d0 - (d0 . d) d) / (1 + d0 . d)`` at most 1 long.

    Returns the per-segment force and torque (the torque on a without its spin about a's axis, with the twist's
    term), the link lengths, the torques by which a's differs from the force's moment (L, 3: the spin left out, less
    the twist's term), and the implicit mass per segment (zero: the links add none).
    """
    head = Rotation.identity() if head is None else head
    a, b = links.seg_a, links.seg_b
    origin = verts[:, :-1].reshape(-1, 3)
    v_origin = vel[:, :-1].reshape(-1, 3)
    zero = np.zeros(links.link_count)
    axis = rot[a].apply(np.tile([0.0, 0.0, -1.0], (links.link_count, 1)))
    rest_axis = head.apply(links.rest_axis)
    turn = _min_rotation(rest_axis, axis)
    offset = (turn * head).apply(links.rest_offset)
    xa = origin[a] + rot[a].apply(np.stack([zero, zero, -links.frac_a * SEG_LEN], 1)) + offset
    xb = origin[b] + rot[b].apply(np.stack([zero, zero, -links.frac_b * SEG_LEN], 1))
    l_vec = xb - xa
    length = np.linalg.norm(l_vec, axis=1)
    # the least rotation's own turn about a's axis as a bends: the offset moves by -(w . g)(d x o) besides w x o
    g, m = _twist(rest_axis, axis), np.cross(axis, offset)
    va = v_origin[a] + np.cross(omega[a], xa - origin[a]) - np.sum(omega[a] * g, axis=1, keepdims=True) * m
    vb = v_origin[b] + np.cross(omega[b], xb - origin[b])
    u = va - vb
    n = l_vec / np.maximum(length, 1e-300)[:, None]
    # each link's k_s and k_d: the mean length of its two segments (all SEG_LEN here) over the reference length
    scale = SEG_LEN / REFERENCE_SEGMENT_LENGTH
    k, c = (np.full(links.link_count, value * scale) for value in (links.stiffness, links.damping))
    # each end's free-segment inverse mass, 1/m + |r|^2 / (m L^2 / 12), r from the segment's centre of mass
    com = origin + rot.apply(np.tile([0.0, 0.0, -0.5 * SEG_LEN], (G * S, 1)))
    Wa, Wb = ((1.0 + 12.0 * np.sum((x - com[s]) ** 2, axis=1) / SEG_LEN**2) / SEG_MASS for s, x in ((a, xa), (b, xb)))
    # ... a's end at its arm lengthened by the twist's lever, |r| + |g| |m|, in the solve (the damper cap's weights
    # are the rest pose's, where g = 0)
    reach_a = np.linalg.norm(xa - com[a], axis=1) + np.linalg.norm(g, axis=1) * np.linalg.norm(m, axis=1)
    Wa_solve = (1.0 + 12.0 * reach_a**2 / SEG_LEN**2) / SEG_MASS
    # the dampers of a segment's links together take at most its velocity in a step: h (h k + c) sum(scale W) <= 1,
    # h k the backward-Euler spring's own damper over the step, the cap taken from the damping alone
    weight = np.bincount(a, scale * Wa, minlength=G * S) + np.bincount(b, scale * Wb, minlength=G * S)
    busier = np.maximum(weight[a], weight[b])
    spring_load = DT * DT * links.stiffness * busier * float(links.implicit_springs)
    damper_load = DT * links.damping * busier
    over = spring_load + damper_load > 1.0
    c = c * np.where(over, np.maximum(1.0 - spring_load, 0.0) / np.where(over, damper_load, 1.0), 1.0)
    if links.implicit_springs:
        W = Wa_solve + Wb
        C = DT * k[:, None, None] * np.eye(3) + c[:, None, None] * n[:, :, None] * n[:, None, :]
        lhs = np.eye(3) + DT * W[:, None, None] * C
        f = np.linalg.solve(lhs, (k[:, None] * l_vec - np.einsum("lij,lj->li", C, u))[:, :, None])[:, :, 0]
    else:
        f = (k * length - c * np.sum(u * n, axis=1))[:, None] * n
    if skip is not None:
        f[skip] = 0.0
    torque_a = np.cross(xa - origin[a], f)
    spin = np.sum(torque_a * axis, axis=1, keepdims=True) * axis
    twist = -np.sum(m * f, axis=1, keepdims=True) * g
    force = np.zeros((G * S, 3))
    torque = np.zeros((G * S, 3))
    np.add.at(force, a, f)
    np.add.at(force, b, -f)
    np.add.at(torque, a, torque_a - spin + twist)
    np.add.at(torque, b, np.cross(xb - origin[b], -f))
    return force, torque, length, spin - twist, np.zeros(G * S)


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(7)
    roots, rot = _groom(rng)
    verts = _chain(roots, rot)
    # Shared by the tests, these links never break (apply breaks links as it goes); breaking tests build their own.
    links = StaticLinks.build(verts, neighbours=3, radius=RADIUS, stiffness=K_S, damping=K_D, break_length=1.0,
                              response=False)
    return SimpleNamespace(rng=rng, roots=roots, rot=rot, verts=verts, links=links, model=_model())


def test_builder_links_nearest_segments(setup):
    """The links are exactly the pairs in which one segment is among the other's n nearest segments of other
    strands within the radius (brute force over all pairs), each pair once, attached at its closest points."""
    links, verts = setup.links, setup.verts
    assert links.link_count > G * S  # a dense patch: more links than segments
    p0 = verts[:, :-1].reshape(-1, 3)
    p1 = verts[:, 1:].reshape(-1, 3)
    i, j = np.meshgrid(np.arange(G * S), np.arange(G * S), indexing="ij")
    dist = segment_distances(p0[i.ravel()], p1[i.ravel()], p0[j.ravel()], p1[j.ravel()]).reshape(G * S, G * S)
    dist[i // S == j // S] = np.inf
    # A closest point at a joint is as near to both segments that meet there: such ties may go either way.
    nth = np.sort(dist, axis=1)[:, 2:3]
    required = (dist < nth - TIE_TOL) & (dist <= RADIUS)
    allowed = (dist <= nth + TIE_TOL) & (dist <= RADIUS)
    linked = list(zip(links.seg_a.tolist(), links.seg_b.tolist(), strict=True))
    assert len(linked) == len(set(linked))
    is_linked = np.zeros_like(required)
    is_linked[links.seg_a, links.seg_b] = is_linked[links.seg_b, links.seg_a] = True
    assert np.all(is_linked[required])
    assert np.all(allowed[links.seg_a, links.seg_b] | allowed[links.seg_b, links.seg_a])
    xa = p0[links.seg_a] + links.frac_a[:, None] * (p1[links.seg_a] - p0[links.seg_a])
    xb = p0[links.seg_b] + links.frac_b[:, None] * (p1[links.seg_b] - p0[links.seg_b])
    np.testing.assert_allclose(np.linalg.norm(xb - xa, axis=1), dist[links.seg_a, links.seg_b], atol=1e-12)


def test_free_step_rate_sums_each_segments_links(setup):
    """``free_step_rate``: the step times sqrt(k / m), k the most link stiffness on any one segment (each link's k_s
    times its scale, counted at both its ends: a loop over the links here) and m the median segment mass."""
    links = setup.links
    rng = np.random.default_rng(3)
    mass = rng.uniform(1e-4, 4e-4, G * S)
    per = np.zeros(G * S)
    for a, b, scale in zip(links.seg_a, links.seg_b, links.scale, strict=True):
        per[a] += K_S * scale
        per[b] += K_S * scale
    dt = 1.0 / 240.0
    assert links.free_step_rate(mass, dt) == pytest.approx(dt * np.sqrt(per.max() / np.median(mass)), rel=1e-12)
    assert links.free_step_rate(mass, 2.0 * dt) == pytest.approx(2.0 * links.free_step_rate(mass, dt), rel=1e-12)
    slack = StaticLinks.build(setup.verts, neighbours=3, radius=RADIUS, stiffness=0.0, damping=K_D, break_length=1.0)
    assert slack.free_step_rate(mass, dt) == 0.0


def test_strand_colours_part_every_link(setup):
    """The sweeps' colours (``strand_colors``): no link joins two strands of one colour, every strand has one, the
    views hold each strand once in colour order, and the colours follow from the links alone (built again, the
    same)."""
    links = setup.links
    colors = links.strand_colors
    a, b = links.seg_a // S, links.seg_b // S
    assert len(colors) == G and colors.min() == 0
    assert not np.any(colors[a] == colors[b])
    # greedy: a strand takes the smallest colour its linked strands leave free, so each colour below its own is
    # taken by one of them
    for g in range(G):
        partners = set(b[a == g]) | set(a[b == g])
        assert set(range(colors[g])) <= {int(colors[p]) for p in partners}
    views = [v.numpy() for v in links.color_views]
    assert sorted(np.concatenate(views).tolist()) == list(range(G))
    assert [int(colors[v[0]]) for v in views] == list(range(len(views)))
    again = StaticLinks.build(setup.verts, neighbours=3, radius=RADIUS, stiffness=K_S, damping=K_D,
                              break_length=1.0, response=True)
    np.testing.assert_array_equal(again.strand_colors, colors)


def test_rest_pose_is_slack(setup):
    """At rest every link has zero length, so no force, to float32 round-off."""
    state = _arrays(setup.verts, setup.rot, np.zeros_like(setup.verts))
    force, torque, mass = _apply(setup.links, setup.model, state)
    counts = np.bincount(np.concatenate([setup.links.seg_a, setup.links.seg_b]), minlength=G * S)
    assert np.linalg.norm(force, axis=1).max() <= K_S * REST_LENGTH_TOL * counts.max()
    assert np.linalg.norm(torque, axis=1).max() <= K_S * REST_LENGTH_TOL * counts.max() * 2 * SEG_LEN
    assert not mass.any()  # implicit links add no inertia: their implicit part is in the force


def _twist(rest_axis, axis):
    """The twist lever ``g = (d0 - (d0 . d) d) / (1 + d0 . d)`` of offset ends, row by row, at most 1 long
    (``kernels.links.offset_twist``)."""
    c = np.sum(rest_axis * axis, axis=1, keepdims=True)
    g = (rest_axis - c * axis) / np.maximum(1.0 + c, 1e-6)
    size = np.linalg.norm(g, axis=1, keepdims=True)
    return g * np.minimum(1.0, 1.0 / np.maximum(size, 1e-300))


def _min_rotation(a, b):
    """Rodrigues: the rotations of least angle taking unit vectors a to b, row by row."""
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.arctan2(sin[:, 0], np.sum(a * b, axis=1))
    return Rotation.from_rotvec(axis / np.maximum(sin, 1e-300) * angle[:, None])


def test_head_motion_and_twist_leave_links_slack(setup):
    """A rigid motion of the whole groom with the head, and any spin of segments about their own axes, stretch no
    link: the rest offsets turn with the head and with each bend, not with a segment's twist."""
    rng = np.random.default_rng(9)
    head = Rotation.from_rotvec(rng.normal(0.0, 1.0, 3))
    twist = Rotation.from_rotvec(np.array([0.0, 0.0, 1.0]) * rng.uniform(-np.pi, np.pi, (G * S, 1)))
    rot = head * setup.rot * twist  # twist about each segment's own axis (body z)
    verts = _chain(head.apply(setup.roots) + [0.01, -0.02, 0.03], rot)
    force, torque, _ = _apply(setup.links, setup.model, _arrays(verts, rot, np.zeros_like(verts), head))
    counts = np.bincount(np.concatenate([setup.links.seg_a, setup.links.seg_b]), minlength=G * S)
    assert np.linalg.norm(force, axis=1).max() <= K_S * REST_LENGTH_TOL * counts.max()
    assert np.linalg.norm(torque, axis=1).max() <= K_S * REST_LENGTH_TOL * counts.max() * 2 * RADIUS


@pytest.mark.parametrize("implicit", [True, False])
@pytest.mark.parametrize("seed", [1, 2])
def test_forces_match_seed_formula_and_conserve_momentum(setup, seed, implicit):
    """After a rigid motion and a bend of every joint, forces match float64 numpy and sum to no net force. Explicit
    links also give no net torque (the force lies along l); an implicit link's force is its end-of-step stretch's,
    so the pair's torque is -l x f, which vanishes with the step: the total matches the reference's."""
    rng = np.random.default_rng(seed)
    links = setup.links if implicit else StaticLinks.build(setup.verts, neighbours=3, radius=RADIUS, stiffness=K_S,
                                                           damping=K_D, break_length=1.0, implicit_springs=False,
                                                           response=False)
    bend = Rotation.from_rotvec(rng.normal(0.0, 0.05, (G * S, 3)))
    rigid = Rotation.from_rotvec(rng.normal(0.0, 1.0, 3))
    shift = rng.normal(0.0, 0.02, 3)
    rot = rigid * setup.rot * bend
    verts = _chain(rigid.apply(setup.roots) + shift, rot)
    omega = _perpendicular_omega(rng, verts, 5.0)
    vel = _velocities(rng, verts, omega, 0.2)
    state = _arrays(verts, rot, vel, rigid)
    force, torque, _ = _apply(links, setup.model, state)

    ref_force, ref_torque, length, spin, _ = _reference(links, verts, rot, vel, omega, head=rigid)
    assert length.max() > 1e-4  # the perturbation stretched the links
    scale = np.abs(ref_force).max()
    np.testing.assert_allclose(force, ref_force, atol=FORCE_RTOL * scale)
    np.testing.assert_allclose(torque, ref_torque, atol=FORCE_RTOL * scale * SEG_LEN)

    # Momentum: no net force; the net torque about the world origin, with what a's torque takes besides the force's
    # moment taken back (the spin left out, the offset transport's twist term added: a reaction on the head).
    origin = verts[:, :-1].reshape(-1, 3)
    total_force = force.sum(axis=0)
    total_torque = (torque + np.cross(origin, force)).sum(axis=0) + spin.sum(axis=0)
    expected = (ref_torque + np.cross(origin, ref_force)).sum(axis=0) + spin.sum(axis=0)
    magnitude = np.linalg.norm(force, axis=1).sum()
    assert np.linalg.norm(total_force) <= MOMENTUM_RTOL * magnitude
    moment_scale = (np.linalg.norm(force, axis=1) * np.linalg.norm(origin, axis=1)).sum()
    assert np.linalg.norm(total_torque - expected) <= MOMENTUM_RTOL * moment_scale
    if not implicit:
        assert np.linalg.norm(expected) <= 1e-12 * moment_scale


def test_link_torques_are_the_gradient_of_the_links_energy(setup):
    """Explicit links without damping: the torque each segment takes is minus the derivative of the links' energy
    ``sum k s |l|^2 / 2`` in the segment's turn about its origin, across its axis (the other segments held), taken by
    central differences of the energy in float64 from the ends' geometry alone. The groom turned with the head and
    every joint bent by 0.3 rad, so its segments lie up to a quarter turn off their rest axes, where the least
    rotation carrying a link's offset turns about the segment's axis too: the torque without its twist term was off
    by up to a third (``kernels.links`` docstring)."""
    rng = np.random.default_rng(11)
    links = StaticLinks.build(setup.verts, neighbours=3, radius=RADIUS, stiffness=K_S, damping=0.0, break_length=1.0,
                              implicit_springs=False, response=False)
    head = Rotation.from_rotvec([0.3, -0.2, 0.5])
    rot = head * setup.rot * Rotation.from_rotvec(rng.normal(0.0, 0.3, (G * S, 3)))
    verts = _chain(head.apply(setup.roots), rot)
    _, torque, _ = _apply(links, setup.model, _arrays(verts, rot, np.zeros_like(verts), head))
    origin = verts[:, :-1].reshape(-1, 3)
    a, b = links.seg_a, links.seg_b
    zero = np.zeros(links.link_count)
    rest_axis = head.apply(links.rest_axis)
    k = links.stiffness * SEG_LEN / REFERENCE_SEGMENT_LENGTH

    def energy(turned):
        axis = turned[a].apply(np.tile([0.0, 0.0, -1.0], (links.link_count, 1)))
        carry = _min_rotation(rest_axis, axis) * head
        xa = origin[a] + turned[a].apply(np.stack([zero, zero, -links.frac_a * SEG_LEN], 1)) + carry.apply(
            links.rest_offset)
        xb = origin[b] + turned[b].apply(np.stack([zero, zero, -links.frac_b * SEG_LEN], 1))
        return 0.5 * k * np.sum((xb - xa) ** 2)

    turns = rot.as_rotvec()
    axis_a = rot[a].apply(np.tile([0.0, 0.0, -1.0], (links.link_count, 1)))
    assert np.degrees(np.arccos(np.clip(np.sum(rest_axis * axis_a, axis=1), -1, 1))).max() > 45.0
    eps = 1.0e-6
    largest = np.linalg.norm(torque, axis=1).max()
    checked = 0
    for seg in np.unique(np.concatenate([a, b]))[::7]:
        d = rot[seg].apply([0.0, 0.0, -1.0])
        across = np.linalg.svd(np.eye(3) - np.outer(d, d))[0][:, :2].T  # two unit directions across the axis
        for e in across:
            grads = []
            for sign in (1.0, -1.0):
                moved = turns.copy()
                moved[seg] = (Rotation.from_rotvec(sign * eps * e) * rot[seg]).as_rotvec()
                grads.append(energy(Rotation.from_rotvec(moved)))
            # the energy's derivative in float64 (round-off ~1e-16 J over 2e-6 rad; the central difference's own error
            # eps^2 of the torque) against the float32 torque, a sum over a segment's links of terms up to the largest
            # torque, each good to FORCE_RTOL: 1e-4 of the largest holds ten such terms; the twist term once missing,
            # up to a third of a torque, is thousands of times it
            np.testing.assert_allclose(torque[seg] @ e, -(grads[0] - grads[1]) / (2.0 * eps), rtol=0,
                                       atol=1.0e-4 * largest, err_msg=f"segment {seg}")
            checked += 1
    assert checked > 20


def test_damping_dissipates(setup):
    """With no stretch rate opposing it, a pure damping link removes energy: sum F . v <= 0 at the attachment points."""
    rng = np.random.default_rng(3)
    bend = Rotation.from_rotvec(rng.normal(0.0, 0.05, (G * S, 3)))
    rot = setup.rot * bend
    verts = _chain(setup.roots, rot)
    omega = _perpendicular_omega(rng, verts, 5.0)
    vel = _velocities(rng, verts, omega, 0.2)
    links = StaticLinks.build(setup.verts, radius=RADIUS, stiffness=0.0,
                              damping=K_D, break_length=1.0, response=False)
    force, torque, _ = _apply(links, setup.model, _arrays(verts, rot, vel))
    # Power of the wrenches on rigid segments: F . v_origin + tau . w.
    power = np.sum(force * vel[:, :-1].reshape(-1, 3)) + np.sum(torque * omega)
    assert power < 0.0


@pytest.mark.parametrize("via", ["break_links", "apply"])
def test_breaking_follows_numpy_and_is_permanent(setup, via):
    """Links past the break length break, in ``break_links`` and in the force pass of ``apply`` alike."""
    rng = np.random.default_rng(11)
    links = StaticLinks.build(setup.verts, radius=RADIUS, stiffness=K_S,
                              damping=K_D, break_length=0.004, response=False)
    bend = Rotation.from_rotvec(rng.normal(0.0, 0.15, (G * S, 3)))
    rot = setup.rot * bend
    verts = _chain(setup.roots, rot)
    zero = np.zeros_like(verts)
    length = _reference(links, verts, rot, zero, np.zeros((G * S, 3)))[2]
    expected = length > links.break_length
    clear = np.abs(length - links.break_length) > BREAK_BAND
    assert 0 < expected.sum() < links.link_count

    state = _arrays(verts, rot, zero)
    if via == "break_links":
        links.break_links(setup.model, state)
    else:
        _apply(links, setup.model, state)
    broken = links.link_broken.numpy()[: links.link_count].astype(bool)
    np.testing.assert_array_equal(broken[clear], expected[clear])
    assert links.broken_count() == broken.sum()

    # Broken links exert nothing, the others still match the seed formula.
    force, _, mass = _apply(links, setup.model, state)
    ref_force, _, _, _, ref_mass = _reference(links, verts, rot, zero, np.zeros((G * S, 3)), skip=broken)
    np.testing.assert_allclose(force, ref_force, atol=FORCE_RTOL * np.abs(ref_force).max())
    np.testing.assert_allclose(mass, ref_mass, rtol=1e-5, atol=1e-12)

    # Back at rest nothing mends.
    links.break_links(setup.model, _arrays(setup.verts, setup.rot, zero))
    np.testing.assert_array_equal(links.link_broken.numpy()[: links.link_count].astype(bool), broken)
    assert links.broken_count() == broken.sum()
    links.reset()
    assert links.broken_count() == 0


def test_captured_step_follows_the_state(setup):
    """Links captured in a graph once, replayed on a moved state, give the forces and breaks of a direct call."""
    links = StaticLinks.build(setup.verts, radius=RADIUS, stiffness=K_S,
                              damping=K_D, break_length=0.004, response=False)
    model = setup.model
    state = _arrays(setup.verts, setup.rot, np.zeros_like(setup.verts))
    force, torque, mass = wp.zeros(G * S, dtype=wp.vec3), wp.zeros(G * S, dtype=wp.vec3), wp.zeros(G * S, dtype=float)
    dt = wp.array([DT], dtype=float)
    links.apply(model, state, dt, force, torque, mass)
    with wp.ScopedCapture(device=force.device) as capture:
        force.zero_()
        torque.zero_()
        mass.zero_()
        links.apply(model, state, dt, force, torque, mass)
    assert links.broken_count() == 0
    rng = np.random.default_rng(5)
    rot = setup.rot * Rotation.from_rotvec(rng.normal(0.0, 0.15, (G * S, 3)))
    verts = _chain(setup.roots, rot)
    moved = _arrays(verts, rot, np.zeros_like(verts))
    for name in ("seg_xform", "joint_q", "vertex_positions", "vertex_velocities"):
        wp.copy(getattr(state, name), getattr(moved, name))
    wp.capture_launch(capture.graph)
    broken = links.link_broken.numpy()[: links.link_count].astype(bool)
    ref_force, _, length, _, _ = _reference(links, verts, rot, np.zeros_like(verts), np.zeros((G * S, 3)),
                                            skip=broken)
    np.testing.assert_allclose(force.numpy(), ref_force, atol=FORCE_RTOL * np.abs(ref_force).max())
    clear = np.abs(length - links.break_length) > BREAK_BAND
    np.testing.assert_array_equal(broken[clear], (length > links.break_length)[clear])
    assert links.broken_count() == broken.sum() > 0


def test_bad_input_is_named():
    with pytest.raises(InteractionError, match="rest_vertices"):
        StaticLinks.build(np.zeros((3, 4)), radius=1.0, stiffness=1.0, damping=0.0, break_length=1.0)
    verts = np.zeros((2, 3, 3))
    verts[:, :, 2] = -np.arange(3)[None]
    with pytest.raises(InteractionError, match="radius"):
        StaticLinks.build(verts, radius=0.0, stiffness=1.0, damping=0.0, break_length=1.0)
    for name in ("stiffness", "damping"):
        for value in (-1.0, np.inf, np.nan):
            with pytest.raises(InteractionError, match=f"{name} must be a finite number >= 0, got {value}"):
                StaticLinks.build(verts, radius=1.0, break_length=1.0, **{"stiffness": 1.0, "damping": 0.0,
                                                                         name: value})


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def test_response_damper_blocks_match_their_product_form():
    """The step's first sweep sums each segment's link-end dampers in closed form, by their moments
    (``kernels.sweeps.link_sweep``); here they are formed as the products they stand for, in float64, from the link
    ends the force pass left and the segments' frames at the step's start: at each end's point ``r`` (the segment's
    frame) the point inertia ``M = h R^T (h k I + c n n^T) R`` (k and c times the link's scale), its blocks
    ``A = J^T M J`` (and the bound of the end's geometric stiffness on the turns: ``kernels.sweeps``) and
    ``B = J^T M`` without the spin about the segment's axis, ``C = M``, with ``J = -[r]x`` at a b
    end and ``J = -[r]x - m g^T`` at an a end, its offset's transport twisting it (``m = d x o``, ``g`` from the
    segment's turn off its rest axis, both in the segment's frame; ``kernels.links.offset_twist``); and the ends' arms,
    which the first of two sweeps keeps for the second. Three strands of 4 segments, tilted at random, bent from their
    rest by 0.5 rad at every joint and turning, linked to their 2 nearest segments."""
    import hairwarp as hw
    from hairwarp.model import Model, StrandParams
    from hairwarp.solver import Solver

    rng = np.random.default_rng(7)
    S, L = 4, 0.03
    roots = np.array([[0.0, 0.0, 0.0], [0.004, 0.001, 0.0], [0.002, 0.005, 0.0]])
    dirs = np.array([0.0, 0.0, -1.0]) + rng.uniform(-0.3, 0.3, (3, 3)) * [1.0, 1.0, 0.0]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    polys = [np.stack([r + t * d for t in np.linspace(0.0, L, S + 1)]) for r, d in zip(roots, dirs)]
    model = Model.build(hw.Groom.from_polylines(polys), StrandParams(bend_stiffness=1e-4), segments=S)
    h, k, c = 1.0 / 240.0, 3.0, 0.4  # a damping of the stiffness' order over the step: both parts of P count
    links = StaticLinks.build(model.rest_vertex_positions, neighbours=2, radius=0.01, stiffness=k, damping=c,
                              break_length=1.0, response=True, sweeps=2)
    assert links.link_count > 0 and links.sweeps_at(h) == 2
    solver = Solver(model, hw.Integrator.IMPLICIT_JOINTS, links=links, threads=1)
    control = model.control()
    start, end = model.state(), model.state()
    start.joint_qd.assign(rng.normal(0.0, 2.0, (3 * S, 3)).astype(np.float32))
    bent = Rotation.from_quat(start.joint_q.numpy()) * Rotation.from_rotvec(rng.normal(0.0, 0.5, (3 * S, 3)))
    start.joint_q.assign(bent.as_quat().astype(np.float32))
    solver.forward_kinematics(start, control)
    solver.step(start, end, control, h)

    xa, xb = links.link_point_a.numpy().astype(float), links.link_point_b.numpy().astype(float)
    xform = start.seg_xform.numpy().astype(float)
    rot, origin = Rotation.from_quat(xform[:, 3:]), xform[:, :3]
    arm = links.ends.arm.numpy().astype(float)
    got = {name: getattr(solver.solved, name).numpy().astype(float) for name in ("A", "B", "C")}
    spin_free = np.diag([1.0, 1.0, 0.0])
    # each a end's twist (the head at the identity): g from a's turn off its rest axis, m = d x o, o the rest offset
    # carried by the least rotation
    axis_a = rot[links.seg_a].apply(np.tile([0.0, 0.0, -1.0], (links.link_count, 1)))
    g = _twist(links.rest_axis, axis_a)
    m = np.cross(axis_a, _min_rotation(links.rest_axis, axis_a).apply(links.rest_offset))
    assert np.linalg.norm(g, axis=1).max() > 0.1  # the bend turned the segments off their rest axes
    order = np.argsort(links.seg_b, kind="stable")  # b slots in link order of their segment b
    slot_b = np.empty(links.link_count, int)
    slot_b[order] = np.arange(links.link_count)
    for seg in range(3 * S):
        R = rot[seg].as_matrix()
        want = {name: np.zeros((3, 3)) for name in ("A", "B", "C")}
        for j in range(links.link_count):
            ends = ((links.seg_a[j], xa[j], j), (links.seg_b[j], xb[j], links.link_count + slot_b[j]))
            for side, point, slot in ends:
                if side != seg:
                    continue
                l = xb[j] - xa[j]
                n = l / np.linalg.norm(l) if np.linalg.norm(l) > 1e-7 else np.zeros(3)
                M = h * R.T @ (h * k * links.scale[j] * np.eye(3) + c * links.scale[j] * np.outer(n, n)) @ R
                r = R.T @ (point - origin[seg])
                J = -_skew(r)
                if slot == j:  # a's end: its offset's twist
                    J = J - np.outer(R.T @ m[j], spin_free @ R.T @ g[j])
                want["A"] += J.T @ M @ J
                want["B"] += J.T @ M
                want["C"] += M
                # the bound of the end's geometric stiffness on the segment's turns (its link is stretched)
                arm_length = np.linalg.norm(r)
                want["A"] += (links.geometric_stiffness * h * h * k * links.scale[j] * arm_length
                              * min(np.linalg.norm(l), links.geometric_arm_ratio * arm_length)) * np.eye(3)
                # float32 points and frames of a few cm: ~1e-8 m of round-off, well under 1e-6 of a segment
                np.testing.assert_allclose(arm[slot], r, rtol=0, atol=1e-6 * L)
        want["A"] = spin_free @ want["A"] @ spin_free
        want["B"] = spin_free @ want["B"]
        # blocks of float32 sums of a few terms of magnitude up to h^2 k |r|^2: relative 1e-5 of the largest
        for name in ("A", "B", "C"):
            scale = max(np.abs(want[name]).max(), 1e-30)
            np.testing.assert_allclose(got[name][seg], want[name], rtol=0, atol=1e-5 * scale,
                                       err_msg=f"{name}, segment {seg}")


@pytest.mark.parametrize("segments", [7, 16, 40])
def test_links_scale_with_the_length_of_hair_they_join(segments):
    """Each link's stiffness and damping are the scene's times the mean length of its two segments over
    :data:`REFERENCE_SEGMENT_LENGTH`: on two parallel strands 0.24 m and 0.12 m long, 3 mm apart, every link's factor is
    ``(0.24 + 0.12) / (2 S REFERENCE_SEGMENT_LENGTH)`` (float64 on the host, to 1e-12; float32 on the device), so
    the stiffness per metre of strand stays the same as the strands are cut into more segments, each making its
    links."""
    gap = 0.003
    verts = np.stack([np.stack([np.full(segments + 1, x), np.zeros(segments + 1),
                                np.linspace(0.0, -length, segments + 1)], axis=1)
                      for x, length in ((0.0, 0.24), (gap, 0.12))])
    links = StaticLinks.build(verts, neighbours=1, radius=0.01, stiffness=2.0, damping=0.004, break_length=1.0)
    assert links.link_count >= segments // 2  # the shorter strand's segments each make one
    np.testing.assert_allclose(links.scale, (0.24 + 0.12) / (2 * segments * REFERENCE_SEGMENT_LENGTH), rtol=1e-12)
    np.testing.assert_allclose(links.link_scale.numpy(), links.scale, rtol=1e-6)


def test_links_asked_for_but_none_built_step_as_no_links():
    """Links solved after the free step whose radius reaches no other strand build none: the run warns so, naming
    the key and the roots' spacing, and the step is then, to the bit, the step without links (the response has no
    pair to answer, and the body push-out still runs)."""
    from pathlib import Path

    import hairwarp as hw
    from hairwarp.runner import Simulation

    scene = Path(__file__).resolve().parents[1] / "scenes" / "long_hair.toml"
    base = ["groom.count=30", "dense.count=0", "output.preview=false", "interactions.enabled=false"]
    with pytest.warns(UserWarning, match=r"links.enabled: no link was built: .* links.radius = 1e-06 m \(the guides' "
                                         r"roots lie [0-9.]+ mm from their nearest\)"):
        asked = Simulation(hw.Scene.load(scene, [*base, "links.radius=1e-6", 'links.response="step"']), threads=1)
    none = Simulation(hw.Scene.load(scene, [*base, "links.enabled=false"]), threads=1)
    assert asked.links.link_count == 0 and asked.solver.responders == [asked.links]
    for _ in range(5):
        asked.advance_frame()
        none.advance_frame()
    for name in ("joint_q", "joint_qd", "vertex_positions"):
        np.testing.assert_array_equal(getattr(asked.state, name).numpy(), getattr(none.state, name).numpy())


def test_links_do_not_depend_on_the_order_candidates_are_found_in(monkeypatch):
    """Strands side by side meet many segments at one distance (a joint's two segments, the strands on either side):
    such ties go to the lower index, so the links are the same whatever order the search lists its candidates in (they
    once followed scipy's k-d tree, and sorted another way 1-2 % of the shipped scenes' links changed)."""
    from hairwarp import interactions

    S, rows = 10, 5
    verts = np.stack([np.stack([np.linspace(0.0, 0.2, S + 1), np.full(S + 1, 0.004 * g), np.full(S + 1, 0.02)],
                               axis=1) for g in range(rows)])
    p0, p1 = verts[:, :-1].reshape(-1, 3), verts[:, 1:].reshape(-1, 3)
    strand = np.repeat(np.arange(rows), S)
    plain = interactions._nearest_segment_pairs(p0, p1, strand, 2, 0.01)
    found = interactions._box_candidates
    for seed in range(3):
        def shuffled(*args, seed=seed):
            i, j = found(*args)
            order = np.random.default_rng(seed).permutation(len(i))
            return i[order], j[order]

        monkeypatch.setattr(interactions, "_box_candidates", shuffled)
        np.testing.assert_array_equal(interactions._nearest_segment_pairs(p0, p1, strand, 2, 0.01), plain)
    # the grid's ties are real: a segment has six other-strand segments at 4 mm, of which 2 are kept
    d = segment_distances(p0[:S], p1[:S], p0[S:2 * S], p1[S:2 * S])
    assert np.isclose(d, 0.004).all() and len(plain) < 2 * rows * S
