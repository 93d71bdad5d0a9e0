"""Dynamic hair-hair interactions: vertex-face and segment-segment contacts (DESIGN §4.4).

Seed slides, "Dynamic interactions": pairs closer than a threshold get a repulsion ``F_s = k d (1 - |T_a . T_b|)``
along their separation (``d`` = threshold - distance; it vanishes as hairs line up) and Coulomb friction
``F_fric = -mu F_N v_t / |v_t|`` in the contact plane. A face's share of the force is split by the barycentric
weights of the nearer of its quad's two triangles between the quad's two segments. Detection (once a frame, with a
margin, or every step) writes fixed-capacity contact buffers; ``contact_forces`` reads them at every step. Whatever
the detection decides once for the frame - the pair, its quad, its rest gap - changes no force by itself: the
nearer triangle, whether the point belongs to the quad, the alignment factor and a parting quad's fade are taken
anew at every step, and the last two fall to zero where the detection drops a pair. Forces that switched at the
frame boundaries kept hair at rest rocking in cycles locked to the frame (docs/interactions.md, "At rest").

Both sides of a contact receive their force at the same world point (the midpoint of the two closest points),
so every contact is an equal and opposite pair with no net torque.

Each contact carries a gap: the distance of its two elements (two segments, or a vertex and a strip quad) in the
rest pose. A pair repels only below ``min(threshold, gap)``, so hair that lies closer than the threshold in the
groom (dense or clumped guides) is not pushed apart at rest, nor when it slides along its neighbours: the groom is
an equilibrium of the contacts, as it is of the links.
"""

import warp as wp

from hairwarp.kernels.articulated import (
    InteractionResponse,
    add_damper,
    articulated_inverse_mass,
    point_damper_blocks,
    shared_inverse_mass,
    spin_free_torque,
    split_factor,
)
from hairwarp.kernels.links import add_gathered, lever_scaled_mass
from hairwarp.kernels.types import REFERENCE_SEGMENT_LENGTH, Fault

wp.set_module_options({"enable_backward": False})

CONTACT_VERTEX_FACE = wp.constant(0)
CONTACT_SEGMENT_SEGMENT = wp.constant(1)
CONTACT_OVERFLOW = wp.constant(int(Fault.CONTACT_OVERFLOW))

# Squared edge length [m^2] below which closest_point_edge_edge treats an edge as a point.
_DEGENERATE_EDGE_SQ = wp.constant(1.0e-14)
# Separation [m] below which the direction between the two closest points is round-off.
_MIN_SEPARATION = wp.constant(1.0e-9)

# Detection queries the BVHs once per block of consecutive vertices (segments) of a strand, against blocks of
# consecutive quads of a strip (segments of a strand): neighbours along a strand see nearly the same things, so a
# block pays one tree traversal where single elements would pay several, and its members are then tested against
# the found block's members with plain box tests. Blocks of 4 keep the boxes tight along hanging hair: the default
# scene's vertex-face detection took 8.6-11.1 ms on one thread against 11.1-13.0 ms with blocks of 8 (3 interleaved
# rounds; the Ratboy mohawk 7.0 against 7.6 ms).
VERTEX_BLOCK = wp.constant(4)
QUAD_BLOCK = wp.constant(4)
SEG_BLOCK = wp.constant(4)


@wp.func
def vertex_segment(vertex: int, seg_per_strand: int) -> int:
    """Segment that carries a guide vertex: vertex k >= 1 is the end of segment k-1, the root belongs to segment 0."""
    strand = vertex // (seg_per_strand + 1)
    k = vertex - strand * (seg_per_strand + 1)
    return strand * seg_per_strand + wp.max(k - 1, 0)


@wp.func
def closest_point_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3) -> wp.vec3:
    """Barycentric weights (of a, b, c) of the point of triangle abc closest to p (Ericson, RTCD 5.1.5)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= 0.0 and d2 <= 0.0:
        return wp.vec3(1.0, 0.0, 0.0)
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= 0.0 and d4 <= d3:
        return wp.vec3(0.0, 1.0, 0.0)
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return wp.vec3(1.0 - v, v, 0.0)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= 0.0 and d5 <= d6:
        return wp.vec3(0.0, 0.0, 1.0)
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return wp.vec3(1.0 - w, 0.0, w)
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return wp.vec3(0.0, 1.0 - w, w)
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return wp.vec3(1.0 - v - w, v, w)


@wp.func
def vertex_tangent(vertex: int, seg_per_strand: int, vertex_positions: wp.array(dtype=wp.vec3)) -> wp.vec3:
    """Unit strand tangent at an interior or tip vertex (central difference; one-sided at the tip)."""
    strand = vertex // (seg_per_strand + 1)
    k = vertex - strand * (seg_per_strand + 1)
    hi = vertex + wp.where(k < seg_per_strand, 1, 0)
    lo = vertex - wp.where(k > 0, 1, 0)
    return wp.normalize(vertex_positions[hi] - vertex_positions[lo])


@wp.func
def strip_quad_origins(quad: int, seg_per_strand: int, strip_pairs: wp.array(dtype=wp.vec2i)):
    """Vertices ``a_k`` and ``b_k`` (indices ``g*(S+1) + k``) of strip quad ``quad`` = pair P, level k, from the strip's
    pair: a small table, where the triangle list is six times the size and read at random."""
    pair = quad // seg_per_strand
    k = quad - pair * seg_per_strand
    ab = strip_pairs[pair]
    return ab[0] * (seg_per_strand + 1) + k, ab[1] * (seg_per_strand + 1) + k


@wp.func
def strip_face_direction(
    tri: int, seg_per_strand: int, strip_pairs: wp.array(dtype=wp.vec2i), vertex_positions: wp.array(dtype=wp.vec3)
) -> wp.vec3:
    """Unit "vertical" (along-strand) direction of a strip triangle: the mean of its two strands' segments."""
    ia, ib = strip_quad_origins(tri // 2, seg_per_strand, strip_pairs)
    d = (vertex_positions[ia + 1] - vertex_positions[ia]) + (vertex_positions[ib + 1] - vertex_positions[ib])
    return wp.normalize(d)


#: Within this share of its reach from a strip's plane a vertex-face contact's depth falls linearly to none
#: (``contact_depth``): the push is ``k (reach - d)`` beyond, ``k (reach - r) d / r`` within (``r`` the ramp), so
#: it does not flip from ``+k reach`` to ``-k reach`` as a vertex passes through the strip. The flip cost the step's
#: order of convergence: ``long_hair`` over 2 s, successive halvings of the step (16-32, 32-64, 64-128 substeps)
#: 0.612, 0.309, 0.237 mm without the ramp, 0.578, 0.308, 0.187 with it (docs/interactions.md, "The vertex-face push
#: falls to none at the strip's plane"; on segment pairs, which flip as well, it measured no better). The barrier a
#: contact puts up, its energy from the reach to the plane, is ``k reach (reach - r) / 2``: three quarters of what it
#: was, at a quarter.
PLANE_RAMP = wp.constant(0.25)


#: Share of a contact's reach from a strip's strand lines over which a vertex-face push fades in (``strand_edge_fade``):
#: continuous where a vertex crosses a line, and the push whole over most of a strip (a quad 10 mm wide, a 3 mm reach:
#: 92 % of its width on average, one 5 mm wide 85 %). Faded over the whole reach, a dense strip 5 mm wide pushed with
#: 0.83 of its stiffness at most.
EDGE_RAMP = wp.constant(0.25)


@wp.func
def contact_depth(dist: float, reach: float) -> float:
    """How deep [m] a vertex at distance ``dist`` from a strip is within its ``reach``, as its spring takes it:
    ``reach - dist``, falling linearly to zero at the strip within ``PLANE_RAMP`` times the reach."""
    ramp = PLANE_RAMP * reach
    if dist < ramp:
        return (reach - ramp) * dist / ramp
    return reach - dist


@wp.func
def quad_feature_owned(second: int, w: wp.vec3) -> bool:
    """Whether the closest point of a strip quad, weights w in its triangle, belongs to this quad's contacts: off
    both of the strip's strands.

    With ``(u, v)`` the point's place on the quad (u across, from strand a to strand b; v along, from level k to
    k+1), points on either strand (u = 0 or 1) are segment-segment contacts: otherwise a vertex beside a strand
    would be pushed once per quad along it. The quad's push fades in from those lines (``strand_edge_fade``), so the
    hand-over is continuous. Along the strip every quad within reach pushes, the edge two quads share
    included: the force is the sum of the quads' penalties, continuous, and where the stiffness factors are constant
    the gradient of their energy. A rule that gave the shared edge to the upper quad dropped the lower quad's force
    at once as a vertex crossed it (0.8 mm in front of a flat strip, 1.99 times as hard 0.1 mm to the root's side of
    the edge as 0.1 mm to the tip's); only the nearer quad pushing, as a plane would, made the force jump in
    direction where a folded strip's two quads are equally near, and ``fast_turn``'s hair resting on the head moved
    0.141 mm a frame (0.004 mm with every quad pushing; ``test_flat_strip_pushes_with_each_quad_within_reach``,
    docs/interactions.md).
    """
    u = w[1]
    if second != 0:
        # (b_k, b_{k+1}, a_{k+1})
        u = 1.0 - w[2]
    return u > 0.0 and u < 1.0


@wp.func
def segment_distance(p: wp.vec3, a: wp.vec3, b: wp.vec3) -> float:
    """Distance [m] of point ``p`` from the segment ``a b``."""
    d = b - a
    t = wp.clamp(wp.dot(p - a, d) / wp.max(wp.dot(d, d), _DEGENERATE_EDGE_SQ), 0.0, 1.0)
    return wp.length(p - (a + t * d))


@wp.func
def strand_edge_fade(x: wp.vec3, a0: wp.vec3, b0: wp.vec3, a1: wp.vec3, b1: wp.vec3, reach: float) -> float:
    """The factor on a vertex-face contact's stiffness at the point ``x`` of quad (a0, b0, a1, b1): its distance from
    the nearer of the quad's two strand segments (a0 a1, b0 b1) over ``EDGE_RAMP`` times ``reach``, at most 1. A vertex
    whose closest point leaves the quad over a strand's line is the segment-segment contacts' (``quad_feature_owned``);
    without the fade its push fell there from ``k (reach - d)`` to none at once, and in the free step a vertex near a
    root crossing that line back and forth jittered for good (``character`` with its head still: 0.096 mm a frame, a
    cycle of four steps; 0.0007 with the fade; docs/interactions.md)."""
    edge = wp.min(segment_distance(x, a0, a1), segment_distance(x, b0, b1))
    return wp.clamp(edge / (EDGE_RAMP * reach), 0.0, 1.0)


@wp.func
def closest_point_quad(p: wp.vec3, a0: wp.vec3, b0: wp.vec3, a1: wp.vec3, b1: wp.vec3):
    """Nearer of the two triangles of quad (a0, b0, a1, b1) to p: (0 or 1, barycentric weights in that triangle,
    squared distance [m^2]); triangle 0 = (a0, b0, a1), triangle 1 = (b0, b1, a1); a tie goes to triangle 0."""
    w0 = closest_point_triangle(p, a0, b0, a1)
    d0 = p - (w0[0] * a0 + w0[1] * b0 + w0[2] * a1)
    w1 = closest_point_triangle(p, b0, b1, a1)
    d1 = p - (w1[0] * b0 + w1[1] * b1 + w1[2] * a1)
    dd0 = wp.dot(d0, d0)
    dd1 = wp.dot(d1, d1)
    if dd1 < dd0:
        return 1, w1, dd1
    return 0, w0, dd0


@wp.func
def strand_in_ring(strand: int, a: int, b: int, neighbour_start: wp.array(dtype=wp.int32),
                   neighbours: wp.array(dtype=wp.int32)) -> bool:
    """Whether strand a or b is ``strand`` or one of its root neighbours (the strips around it)."""
    if a == strand or b == strand:
        return True
    for j in range(neighbour_start[strand], neighbour_start[strand + 1]):
        n = neighbours[j]
        if n == a or n == b:
            return True
    return False


@wp.func
def box_contains(lower: wp.vec3, upper: wp.vec3, p: wp.vec3) -> bool:
    """Whether the closed box [lower, upper] holds p."""
    return (p[0] >= lower[0] and p[1] >= lower[1] and p[2] >= lower[2]
            and p[0] <= upper[0] and p[1] <= upper[1] and p[2] <= upper[2])


@wp.func
def boxes_overlap(lo_a: wp.vec3, hi_a: wp.vec3, lo_b: wp.vec3, hi_b: wp.vec3) -> bool:
    """Whether two closed boxes overlap."""
    return (lo_a[0] <= hi_b[0] and lo_a[1] <= hi_b[1] and lo_a[2] <= hi_b[2]
            and lo_b[0] <= hi_a[0] and lo_b[1] <= hi_a[1] and lo_b[2] <= hi_a[2])


# Alignment cones. A pair more nearly parallel than the alignment cutoff is no contact (1 - |T_a . T_b| below it:
# angles under ``acos(1 - cutoff)``, 8.1 degrees at the default 0.01). Hair lies mostly along its neighbours, so most
# of the elements a detection query meets are such pairs. A block's directions lie within a cone (the unit axis of
# their sum, and the largest angle of one from it), and where two blocks' cones lie within that angle of each other
# (the angle of their axes plus both spreads) every pair between them is aligned: the block is passed over whole,
# before its elements' box tests. Exact: the contacts found are the same, the elements skipped being only those the
# per-pair test would reject; CONE_SLACK [rad] is taken off the angle for the float32 round-off of the spreads (an
# acos near 1 is off by up to ~5e-4 rad) and of the dot products.
# On the default scene's state 12 frames in, 25 % of the quad blocks its vertex blocks meet are passed over so.
CONE_SLACK = wp.constant(4.0e-3)


@wp.func
def cone_spread(axis: wp.vec3, d: wp.vec3) -> float:
    """The angle [rad] of unit direction ``d`` from a cone's unit ``axis`` (pi / 2 for a zero vector: no prune)."""
    return wp.acos(wp.clamp(wp.dot(axis, d), -1.0, 1.0))


@wp.func
def direction_cone(dirs: wp.array(dtype=wp.vec3), first: int, last: int):
    """The cone of unit directions ``dirs[first:last]``: its unit axis (their sum's direction) and its spread [rad],
    the largest angle of one from the axis."""
    axis = wp.vec3()
    for i in range(first, last):
        axis += dirs[i]
    axis = wp.normalize(axis)
    spread = float(0.0)
    for i in range(first, last):
        spread = wp.max(spread, cone_spread(axis, dirs[i]))
    return axis, spread


@wp.func
def cone_budget(contact_alignment_cutoff: float, spread: float):
    """What is left of the alignment angle for another cone, given a block's ``spread`` [rad]: its cosine and sine
    ``(cos b, sin b)``, or ``(2, 0)`` where nothing is left (no cosine exceeds 2: nothing is passed over)."""
    budget = wp.acos(1.0 - contact_alignment_cutoff) - spread - CONE_SLACK
    if contact_alignment_cutoff <= 0.0 or budget <= 0.0:
        return wp.vec2(2.0, 0.0)
    return wp.vec2(wp.cos(budget), wp.sin(budget))


@wp.func
def cones_aligned(axis: wp.vec3, budget: wp.vec2, axes: wp.array(dtype=wp.vec3), spreads: wp.array(dtype=wp.vec2),
                  other: int) -> bool:
    """Whether every direction of a block with ``axis`` and ``budget`` (``cone_budget``) lies within the alignment
    angle of every direction of block ``other``'s cone (``axes``, and the cosines and sines of the ``spreads``),
    either way along it: the axes' angle under the budget less the other spread, ``|a . b| > cos(budget -
    spread)``. A block with no budget left reads nothing (curly hair's blocks spread wide)."""
    if budget[0] > 1.0:
        return False
    other_spread = spreads[other]
    if budget[0] >= other_spread[0]:  # the other spread uses up the budget
        return False
    return wp.abs(wp.dot(axis, axes[other])) > budget[0] * other_spread[0] + budget[1] * other_spread[1]


@wp.struct
class ContactBuffer:
    """Stored contact pairs, fixed capacity: per slot the ``kind`` (``CONTACT_VERTEX_FACE`` or
    ``CONTACT_SEGMENT_SEGMENT``), the sides ``a`` and ``b`` (vertex and strip triangle, or two segments), the weights
    ``w`` (barycentric in the triangle, or the two segment parameters), the rest ``gap`` [m]; ``counter[0]`` pairs
    found (more than ``capacity`` when some were dropped) and the sticky ``overflow[0]`` flag."""

    capacity: int
    kind: wp.array(dtype=wp.int32)
    a: wp.array(dtype=wp.int32)
    b: wp.array(dtype=wp.int32)
    w: wp.array(dtype=wp.vec3)
    gap: wp.array(dtype=float)
    counter: wp.array(dtype=wp.int32)
    overflow: wp.array(dtype=wp.int32)


#: The rate ``h^2 k (W_a + W_b)`` (the pair's stiffness over the step against the inverse masses of its sides'
#: segments) up to which a hair contact solved after the free step takes its stiffness: a stiffer one is taken at it.
#: At that rate the step's backward-Euler solve already takes 99.9 % of a lone pair's approach to its target (``rate /
#: (1 + rate)``), so a stiffer contact would act no differently within the step; but stacks of such contacts, each
#: solved apart from the others (split between strands, or Jacobi within a sweep's colour), blew up: on the stability
#: benchmark's turn (150 guides, contacts alone) at one step a frame 300 N/m held (pair rates to 10,500, 3,500 at the
#: 99th percentile), 1,000 N/m blew up at 1.33 s and 3,000 at 0.23 s. Taken at 1,000 they hold to 30,000 N/m (at
#: 3,000: 3,000 N/m blew up at 1.33 s). The shipped scenes' contacts stay below it at every step (at one step a frame
#: their largest rates are 250-800) and run the same bits.
CONTACT_RESPONSE_RATE_LIMIT = 1000.0


@wp.struct
class ContactResponse:
    """What ``contact_force`` leaves for the step's second half, the contacts' velocity response inside the strands'
    dynamics (``contact_response_gather``, then ``kernels.articulated.interaction_response``); ``enabled`` = 0: the
    forces are explicit, damping included, and nothing is stored (the arrays may then hold one element).

    Per slot: ``normal`` (world, unit, from side b to side a), ``coef`` ``D = h k + c`` [N s/m], the contact's
    backward-Euler coefficient (zero: no response), ``target`` [m/s] ``k d / D``, the separation speed at which the
    contact's force ``k d - D v_n`` falls to zero (a pair the free step sends apart faster is left alone: a contact
    only pushes), ``weights`` the points' weights
    (a vertex-face contact's quad corners a_k, b_k, a_k+1, b_k+1; a segment pair's (s, t, 0, 0)). Per entry
    ``4 slot + e``, as the force's entries: the world ``point`` and the signed ``share`` (+1 side a; -1, or the
    face's corner weights, side b; 0 none). ``friction`` and ``slip_velocity`` [m/s]: the contacts' Coulomb
    coefficient and its regularisation. ``split``: the two sides' split factors of the step's response and the
    share of the force on the free velocities that the step's solve leaves the pair, ``1 / (1 + h D (W_a + W_b))``,
    which bounds its friction (``contact_response_split``). ``rate_limit``: the pair's rate ``h^2 k (W_a + W_b)``
    (its sides' segments' inverse masses) up to which its stiffness counts (``CONTACT_RESPONSE_RATE_LIMIT``)."""


    enabled: int
    friction: float
    slip_velocity: float
    rate_limit: float
    normal: wp.array(dtype=wp.vec3)
    coef: wp.array(dtype=float)
    target: wp.array(dtype=float)
    weights: wp.array(dtype=wp.vec4)
    point: wp.array(dtype=wp.vec3)
    share: wp.array(dtype=float)
    split: wp.array(dtype=wp.vec3)


@wp.struct
class SweepContacts:
    """The hair contacts the links' sweeps solve in a step (``sweep_entry_force``), listed once a step by
    ``contact_response_gather``: per segment, at ``seg_entry_start[seg]`` up to ``end[seg]``, the entries in
    contact at the free step (``entries``), each with its friction coefficient ``friction`` [N s/m] and ``free``,
    its own strand's share of the pair's relative velocity at the free step [m/s] (the part no sweep changes)."""

    entries: wp.array(dtype=wp.int32)
    end: wp.array(dtype=wp.int32)
    friction: wp.array(dtype=float)
    free: wp.array(dtype=wp.vec3)


@wp.func
def push_contact(buf: ContactBuffer, kind: int, a: int, b: int, w: wp.vec3, gap: float,
                 fault: wp.array(dtype=wp.int32)):
    """Append one contact; past the capacity, count it, drop it and raise the overflow flags."""
    slot = wp.atomic_add(buf.counter, 0, 1)
    if slot < buf.capacity:
        buf.kind[slot] = kind
        buf.a[slot] = a
        buf.b[slot] = b
        buf.w[slot] = w
        buf.gap[slot] = gap
    else:
        buf.overflow[0] = 1
        wp.atomic_or(fault, 0, CONTACT_OVERFLOW)


@wp.kernel
def segment_bounds(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    contact_threshold: float,
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Out:
    seg_lowers: wp.array(dtype=wp.vec3),
    seg_uppers: wp.array(dtype=wp.vec3),
    seg_dir: wp.array(dtype=wp.vec3),
    block_lowers: wp.array(dtype=wp.vec3),
    block_uppers: wp.array(dtype=wp.vec3),
    block_axes: wp.array(dtype=wp.vec3),
    block_spreads: wp.array(dtype=wp.vec2),
):
    """One thread per block of ``SEG_BLOCK`` consecutive segments of a strand: each segment's world box [m] grown by
    the contact reach and its unit direction, their boxes' union, the block's box in the segment-block BVH, and the
    cone of their directions (axis, and the cosine and sine of its spread: see ``CONE_SLACK``)."""
    blk = tid_offset + wp.tid()
    blocks = (seg_per_strand + SEG_BLOCK - 1) // SEG_BLOCK
    strand = blk // blocks
    k0 = (blk - strand * blocks) * SEG_BLOCK
    k1 = wp.min(k0 + SEG_BLOCK, seg_per_strand)
    grow = wp.vec3(contact_threshold)
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for k in range(k0, k1):
        seg = strand * seg_per_strand + k
        v = seg + strand
        x0 = vertex_positions[v]
        x1 = vertex_positions[v + 1]
        seg_lo = wp.min(x0, x1) - grow
        seg_hi = wp.max(x0, x1) + grow
        seg_lowers[seg] = seg_lo
        seg_uppers[seg] = seg_hi
        seg_dir[seg] = wp.normalize(x1 - x0)
        lo = wp.min(lo, seg_lo)
        hi = wp.max(hi, seg_hi)
    block_lowers[blk] = lo
    block_uppers[blk] = hi
    axis, spread = direction_cone(seg_dir, strand * seg_per_strand + k0, strand * seg_per_strand + k1)
    block_axes[blk] = axis
    block_spreads[blk] = wp.vec2(wp.cos(spread), wp.sin(spread))


@wp.kernel
def segment_segment_contacts(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    contact_threshold: float,
    contact_alignment_cutoff: float,
    repel_distance: float,
    rest_gaps: int,
    seg_block_bvh: wp.uint64,
    rest_positions: wp.array(dtype=wp.vec3),
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Scratch:
    seg_lowers: wp.array(dtype=wp.vec3),
    seg_uppers: wp.array(dtype=wp.vec3),
    seg_dir: wp.array(dtype=wp.vec3),
    seg_block_axes: wp.array(dtype=wp.vec3),
    seg_block_spreads: wp.array(dtype=wp.vec2),
    # Out:
    contacts: ContactBuffer,
    fault: wp.array(dtype=wp.int32),
):
    """One thread per segment block I: every segment pair (i in I, j in a later block of another strand) closer than
    the threshold [m].

    One BVH query per block (of ``SEG_BLOCK`` segments) with its box; a block found whose every pair with I the
    alignment cutoff rejects is passed over (``cones_aligned``), the others tested segment by segment against the
    reach-grown segment boxes before the exact closest points. Appends (i, j, (s, t, 0)) with the
    closest-point parameters along each segment (0 at the segment origin, 1 at its end), and as the gap the distance
    of the two segments in the rest pose (``rest_gaps``) or ``repel_distance``. Pairs more nearly parallel
    than the alignment cutoff (``1 - |T_a . T_b|`` below it) are left out: their repulsion is negligible.
    """
    blk = tid_offset + wp.tid()
    blocks = (seg_per_strand + SEG_BLOCK - 1) // SEG_BLOCK
    strand = blk // blocks
    k0 = (blk - strand * blocks) * SEG_BLOCK
    k1 = wp.min(k0 + SEG_BLOCK, seg_per_strand)
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for k in range(k0, k1 + 1):
        x = vertex_positions[strand * (seg_per_strand + 1) + k]
        lo = wp.min(lo, x)
        hi = wp.max(hi, x)
    spread = seg_block_spreads[blk]
    budget = cone_budget(contact_alignment_cutoff, wp.atan2(spread[1], spread[0]))
    axis = seg_block_axes[blk]
    query = wp.bvh_query_aabb(seg_block_bvh, lo, hi)
    other = int(0)
    while wp.bvh_query_next(query, other):
        other_strand = other // blocks
        if other <= blk or other_strand == strand:
            continue
        if cones_aligned(axis, budget, seg_block_axes, seg_block_spreads, other):
            continue
        m0 = (other - other_strand * blocks) * SEG_BLOCK
        m1 = wp.min(m0 + SEG_BLOCK, seg_per_strand)
        for m in range(m0, m1):
            j = other_strand * seg_per_strand + m
            j_lo = seg_lowers[j]
            j_hi = seg_uppers[j]
            vj = j + other_strand
            q0 = vertex_positions[vj]
            q1 = vertex_positions[vj + 1]
            tb = seg_dir[j]
            for k in range(k0, k1):
                i = strand * seg_per_strand + k
                vi = i + strand
                p0 = vertex_positions[vi]
                p1 = vertex_positions[vi + 1]
                if not boxes_overlap(wp.min(p0, p1), wp.max(p0, p1), j_lo, j_hi):
                    continue
                if contact_alignment_cutoff > 0.0:
                    if 1.0 - wp.abs(wp.dot(seg_dir[i], tb)) < contact_alignment_cutoff:
                        continue
                st = wp.closest_point_edge_edge(p0, p1, q0, q1, _DEGENERATE_EDGE_SQ)
                if st[2] < contact_threshold:
                    gap = repel_distance
                    if rest_gaps != 0:
                        gap = wp.closest_point_edge_edge(rest_positions[vi], rest_positions[vi + 1],
                                                         rest_positions[vj], rest_positions[vj + 1],
                                                         _DEGENERATE_EDGE_SQ)[2]
                    push_contact(contacts, CONTACT_SEGMENT_SEGMENT, i, j, wp.vec3(st[0], st[1], 0.0), gap, fault)


@wp.kernel
def strip_bounds(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    contact_threshold: float,
    strip_max_width: float,
    strip_pairs: wp.array(dtype=wp.vec2i),
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Out:
    quad_lowers: wp.array(dtype=wp.vec3),
    quad_uppers: wp.array(dtype=wp.vec3),
    quad_plane: wp.array(dtype=wp.vec4),
    quad_slab: wp.array(dtype=float),
    quad_dir: wp.array(dtype=wp.vec3),
    block_lowers: wp.array(dtype=wp.vec3),
    block_uppers: wp.array(dtype=wp.vec3),
    block_axes: wp.array(dtype=wp.vec3),
    block_spreads: wp.array(dtype=wp.vec2),
):
    """One thread per block of ``QUAD_BLOCK`` consecutive quads of a strip: each quad's world box [m] grown by the
    reach; its mean plane (unit normal n, offset n.c) and, in ``quad_slab``, the reach plus the corners' largest
    distance from that plane (a slab holding every point within the reach of the quad); its unit along-strand
    direction; and the block's box, for the quad-block BVH, and the cone of its quads' directions (axis, and the
    cosine and sine of its spread: see ``CONE_SLACK``). A quad wider than ``strip_max_width`` [m] (its strands
    have parted) gets an empty box: it is no contact surface until they come back together."""
    blk = tid_offset + wp.tid()
    blocks = (seg_per_strand + QUAD_BLOCK - 1) // QUAD_BLOCK
    pair = blk // blocks
    k0 = (blk - pair * blocks) * QUAD_BLOCK
    k1 = wp.min(k0 + QUAD_BLOCK, seg_per_strand)
    ab = strip_pairs[pair]
    grow = wp.vec3(contact_threshold)
    lo = wp.vec3(1.0e30)
    hi = wp.vec3(-1.0e30)
    for k in range(k0, k1):
        quad = pair * seg_per_strand + k
        ia = ab[0] * (seg_per_strand + 1) + k
        ib = ab[1] * (seg_per_strand + 1) + k
        a0 = vertex_positions[ia]
        a1 = vertex_positions[ia + 1]
        b0 = vertex_positions[ib]
        b1 = vertex_positions[ib + 1]
        q_lo = wp.min(wp.min(a0, a1), wp.min(b0, b1)) - grow
        q_hi = wp.max(wp.max(a0, a1), wp.max(b0, b1)) + grow
        width_sq = wp.max(wp.length_sq(b0 - a0), wp.length_sq(b1 - a1))
        if width_sq > strip_max_width * strip_max_width:
            q_lo = wp.vec3(1.0e30)
            q_hi = wp.vec3(-1.0e30)
        quad_lowers[quad] = q_lo
        quad_uppers[quad] = q_hi
        lo = wp.min(lo, q_lo)
        hi = wp.max(hi, q_hi)
        # Normal of the diagonals; a degenerate quad gets n = 0 and a slab that passes every point.
        n = wp.normalize(wp.cross(b1 - a0, a1 - b0))
        c = 0.25 * (a0 + a1 + b0 + b1)
        off = wp.max(wp.max(wp.abs(wp.dot(a0 - c, n)), wp.abs(wp.dot(a1 - c, n))),
                     wp.max(wp.abs(wp.dot(b0 - c, n)), wp.abs(wp.dot(b1 - c, n))))
        quad_plane[quad] = wp.vec4(n[0], n[1], n[2], wp.dot(n, c))
        quad_dir[quad] = wp.normalize((a1 - a0) + (b1 - b0))
        quad_slab[quad] = off + contact_threshold
    block_lowers[blk] = lo
    block_uppers[blk] = hi
    axis, spread = direction_cone(quad_dir, pair * seg_per_strand + k0, pair * seg_per_strand + k1)
    block_axes[blk] = axis
    block_spreads[blk] = wp.vec2(wp.cos(spread), wp.sin(spread))


@wp.kernel
def vertex_tangents(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Out:
    tangents: wp.array(dtype=wp.vec3),
):
    """One thread per guide vertex: its unit strand tangent (``vertex_tangent``), for the alignment cutoff of
    vertex-face detection."""
    vertex = tid_offset + wp.tid()
    tangents[vertex] = vertex_tangent(vertex, seg_per_strand, vertex_positions)


@wp.kernel
def vertex_face_contacts(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    contact_threshold: float,
    contact_alignment_cutoff: float,
    repel_distance: float,
    rest_gaps: int,
    skip_neighbour_strips: int,
    quad_block_bvh: wp.uint64,
    rest_positions: wp.array(dtype=wp.vec3),
    strip_pairs: wp.array(dtype=wp.vec2i),
    strand_neighbour_start: wp.array(dtype=wp.int32),
    strand_neighbours: wp.array(dtype=wp.int32),
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Scratch:
    quad_lowers: wp.array(dtype=wp.vec3),
    quad_uppers: wp.array(dtype=wp.vec3),
    quad_plane: wp.array(dtype=wp.vec4),
    quad_slab: wp.array(dtype=float),
    quad_dir: wp.array(dtype=wp.vec3),
    quad_block_axes: wp.array(dtype=wp.vec3),
    quad_block_spreads: wp.array(dtype=wp.vec2),
    vertex_tangents: wp.array(dtype=wp.vec3),
    # Out:
    contacts: ContactBuffer,
    fault: wp.array(dtype=wp.int32),
):
    """One thread per block of ``VERTEX_BLOCK`` consecutive guide vertices of a strand (roots skipped): every strip
    quad of other strands closer than the threshold [m] to one of them.

    One BVH query per block with its box; strips of the vertex's own strand, and with ``skip_neighbour_strips`` of
    its root neighbours, are dropped per quad block found, and quad blocks and quads whose every pair with the block's
    vertices the alignment cutoff rejects (``cones_aligned``); then per quad a box test against the block's box, and per
    vertex a box test, a slab test against the quad's plane, the alignment cutoff (``vertex_tangents``) and the
    exact closest point of the quad. Appends (vertex, triangle, barycentric weights) for the nearer of the quad's two
    triangles, and as the gap the distance of the vertex from the quad in the rest pose (``rest_gaps``) or
    ``repel_distance``. Whether the quad pushes the vertex is the force's test at every step
    (``quad_feature_owned``)."""
    blk = tid_offset + wp.tid()
    blocks = (seg_per_strand + VERTEX_BLOCK - 1) // VERTEX_BLOCK
    strand = blk // blocks
    base = strand * (seg_per_strand + 1)
    k0 = 1 + (blk - strand * blocks) * VERTEX_BLOCK
    k1 = wp.min(k0 + VERTEX_BLOCK, seg_per_strand + 1)
    lo = vertex_positions[base + k0]
    hi = lo
    for k in range(k0 + 1, k1):
        lo = wp.min(lo, vertex_positions[base + k])
        hi = wp.max(hi, vertex_positions[base + k])
    # the cone of the block's tangents, and what it leaves of the alignment angle (CONE_SLACK); without a cutoff
    # none (the tangents are not computed then)
    axis = wp.vec3()
    budget = cone_budget(contact_alignment_cutoff, 0.0)
    if contact_alignment_cutoff > 0.0:
        axis, spread = direction_cone(vertex_tangents, base + k0, base + k1)
        budget = cone_budget(contact_alignment_cutoff, spread)
    quad_blocks = (seg_per_strand + QUAD_BLOCK - 1) // QUAD_BLOCK
    query = wp.bvh_query_aabb(quad_block_bvh, lo, hi)
    found = int(0)
    while wp.bvh_query_next(query, found):
        pair = found // quad_blocks
        ab = strip_pairs[pair]
        if skip_neighbour_strips != 0:
            if strand_in_ring(strand, ab[0], ab[1], strand_neighbour_start, strand_neighbours):
                continue
        elif ab[0] == strand or ab[1] == strand:
            continue
        if cones_aligned(axis, budget, quad_block_axes, quad_block_spreads, found):
            continue
        j0 = (found - pair * quad_blocks) * QUAD_BLOCK
        j1 = wp.min(j0 + QUAD_BLOCK, seg_per_strand)
        for j in range(j0, j1):
            quad = pair * seg_per_strand + j
            q_lo = quad_lowers[quad]
            q_hi = quad_uppers[quad]
            if not boxes_overlap(lo, hi, q_lo, q_hi):
                continue
            for k in range(k0, k1):
                vertex = base + k
                p = vertex_positions[vertex]
                if not box_contains(q_lo, q_hi, p):
                    continue
                plane = quad_plane[quad]
                if wp.abs(p[0] * plane[0] + p[1] * plane[1] + p[2] * plane[2] - plane[3]) > quad_slab[quad]:
                    continue
                if contact_alignment_cutoff > 0.0:
                    if 1.0 - wp.abs(wp.dot(vertex_tangents[vertex], quad_dir[quad])) < contact_alignment_cutoff:
                        continue
                ia = ab[0] * (seg_per_strand + 1) + j
                ib = ab[1] * (seg_per_strand + 1) + j
                second, w, dist_sq = closest_point_quad(p, vertex_positions[ia], vertex_positions[ib],
                                                        vertex_positions[ia + 1], vertex_positions[ib + 1])
                if dist_sq < contact_threshold * contact_threshold:
                    gap = repel_distance
                    if rest_gaps != 0:
                        rest_second, rest_w, rest_sq = closest_point_quad(
                            rest_positions[vertex], rest_positions[ia], rest_positions[ib], rest_positions[ia + 1],
                            rest_positions[ib + 1])
                        gap = wp.sqrt(rest_sq)
                    push_contact(contacts, CONTACT_VERTEX_FACE, vertex, 2 * quad + second, w, gap, fault)


@wp.func
def put_wrench(
    entry: int,
    seg: int,
    seg_per_strand: int,
    point: wp.vec3,
    f: wp.vec3,
    extra_mass: float,
    seg_length: wp.array(dtype=float),
    vertex_positions: wp.array(dtype=wp.vec3),
    entry_force: wp.array(dtype=wp.vec3),
    entry_torque: wp.array(dtype=wp.vec3),
    entry_mass: wp.array(dtype=float),
):
    """Store in ``entry`` the force f at a world point on a segment: the force, its torque about the segment's origin
    (vertex k) and its lever-scaled implicit mass (``contact_gather`` adds them to the segment)."""
    v = seg + seg // seg_per_strand
    origin = vertex_positions[v]
    entry_force[entry] = f
    entry_torque[entry] = wp.cross(point - origin, f)
    if extra_mass > 0.0:
        entry_mass[entry] = lever_scaled_mass(extra_mass, point - origin, 0.5 * seg_length[seg])


@wp.func
def contact_segments(slot: int, seg_per_strand: int, strip_pairs: wp.array(dtype=wp.vec2i), contacts: ContactBuffer):
    """The segments the contact in ``slot`` pushes, one per entry ``4 slot + e``: a vertex-face contact's vertex and
    its quad's two segments (the level-k segments of the strip's strands, then -1), or a segment pair (then -1, -1);
    the features are fixed at detection."""
    ia = contacts.a[slot]
    ib = contacts.b[slot]
    if contacts.kind[slot] == CONTACT_VERTEX_FACE:
        pair = ib // (2 * seg_per_strand)
        k = ib // 2 - pair * seg_per_strand
        ab = strip_pairs[pair]
        return wp.vec4i(vertex_segment(ia, seg_per_strand), ab[0] * seg_per_strand + k, ab[1] * seg_per_strand + k,
                        -1)
    return wp.vec4i(ia, ib, -1, -1)


@wp.func(inline=True)
def contact_force(
    slot: int,
    seg_per_strand: int,
    seg_length: wp.array(dtype=float),
    seg_mass: wp.array(dtype=float),
    strip_pairs: wp.array(dtype=wp.vec2i),
    tri_stiffness_scale: wp.array(dtype=float),
    contact_threshold: float,
    contact_stiffness: float,
    contact_damping: float,
    contact_friction: float,
    contact_slip_velocity: float,
    contact_alignment_cutoff: float,
    strip_max_width: float,
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    h: float,
    implicit_springs: int,
    contacts: ContactBuffer,
    response: ContactResponse,
    entry_force: wp.array(dtype=wp.vec3),
    entry_torque: wp.array(dtype=wp.vec3),
    entry_mass: wp.array(dtype=float),
):
    """Forces of the contact in one buffer slot (see ``contact_forces``), stored in its entries ``4 slot + e``."""
    if response.enabled != 0:  # the entries are not read (``HairContacts.gather`` adds nothing)
        response.coef[slot] = 0.0
        for e in range(4):
            response.share[4 * slot + e] = 0.0
    else:
        for e in range(4):
            entry_force[4 * slot + e] = wp.vec3()
            entry_torque[4 * slot + e] = wp.vec3()
            entry_mass[4 * slot + e] = 0.0
    kind = contacts.kind[slot]
    ia = contacts.a[slot]
    ib = contacts.b[slot]
    reach = wp.min(contact_threshold, contacts.gap[slot])

    # Positions first: most stored pairs (detected with a margin) are beyond the threshold and stop here.
    xa = wp.vec3()
    xb = wp.vec3()
    w = wp.vec3()  # a segment pair's closest-point parameters
    qa = int(0)
    qb = int(0)
    corner = wp.vec4()
    va0 = int(0)
    vb0 = int(0)
    # The closest points are taken anew from the positions of this step: a pair found once per frame keeps its
    # features, but weights frozen at the detection make the force depart from the distance's gradient as the hair
    # moves, and that pumped energy into hair at rest (tips at 5 mm/s for good; 0.1 mm/s detected every step). A
    # vertex-face contact keeps its quad, not the triangle found at the detection: the nearer of the quad's two
    # triangles is taken anew too, so the face point moves continuously across the diagonal. (With the triangle
    # kept for the frame, a vertex near the diagonal of the Ratboy mohawk's strips was pushed by one triangle in a
    # frame and the other in the next, and its strand rocked 1 mm a frame for good.)
    if kind == CONTACT_VERTEX_FACE:
        qa, qb = strip_quad_origins(ib // 2, seg_per_strand, strip_pairs)
        xa = vertex_positions[ia]
        second, wt, dsq = closest_point_quad(xa, vertex_positions[qa], vertex_positions[qb], vertex_positions[qa + 1],
                                             vertex_positions[qb + 1])
        # weights of the quad's corners (a_k, b_k, a_{k+1}, b_{k+1})
        corner = wp.vec4(wt[0], wt[1], wt[2], 0.0)
        if second != 0:
            corner = wp.vec4(0.0, wt[0], wt[2], wt[1])
        if not quad_feature_owned(second, wt):
            return
        xb = (corner[0] * vertex_positions[qa] + corner[1] * vertex_positions[qb] + corner[2] * vertex_positions[qa + 1]
              + corner[3] * vertex_positions[qb + 1])
    else:
        va0 = ia + ia // seg_per_strand
        vb0 = ib + ib // seg_per_strand
        st = wp.closest_point_edge_edge(vertex_positions[va0], vertex_positions[va0 + 1], vertex_positions[vb0],
                                        vertex_positions[vb0 + 1], _DEGENERATE_EDGE_SQ)
        w = wp.vec3(st[0], st[1], 0.0)
        xa = wp.lerp(vertex_positions[va0], vertex_positions[va0 + 1], w[0])
        xb = wp.lerp(vertex_positions[vb0], vertex_positions[vb0 + 1], w[1])
    delta = xa - xb
    dist_sq = wp.dot(delta, delta)
    if dist_sq >= reach * reach:
        return
    dist = wp.sqrt(dist_sq)

    k = contact_stiffness
    # a vertex-face contact's factor on its stiffness and damping: the length of hair at the vertex over
    # REFERENCE_SEGMENT_LENGTH (each vertex near a strip makes one). A segment-segment contact keeps 1: two hairs
    # crossing meet in one pair of segments however finely they are cut (segments longer than the threshold; scaled
    # by their mean length, the Ratboy mohawk's tips at 16 and 31 segments ran 7.2 mm RMS apart, 7.1 without)
    length_scale = float(1.0)
    va = wp.vec3()
    vb = wp.vec3()
    ta = wp.vec3()
    tb = wp.vec3()
    inv_mass_a = float(0.0)
    inv_mass_b = float(0.0)
    if kind == CONTACT_VERTEX_FACE:
        va = vertex_velocities[ia]
        vb = (corner[0] * vertex_velocities[qa] + corner[1] * vertex_velocities[qb]
              + corner[2] * vertex_velocities[qa + 1] + corner[3] * vertex_velocities[qb + 1])
        ta = vertex_tangent(ia, seg_per_strand, vertex_positions)
        tb = strip_face_direction(ib, seg_per_strand, strip_pairs, vertex_positions)
        # The density factor, blended from the quad's lower edge (its first triangle's) to its upper edge (its
        # second's): continuous across the diagonal and from quad to quad.
        quad = ib // 2
        k = contact_stiffness * ((corner[0] + corner[1]) * tri_stiffness_scale[2 * quad]
                                 + (corner[2] + corner[3]) * tri_stiffness_scale[2 * quad + 1])
        # A quad wider than the strips' largest width is no contact surface (``strip_bounds``); the stiffness fades
        # out over the last quarter before it, so a quad crossing that width between detections does not switch.
        width = wp.sqrt(wp.max(wp.length_sq(vertex_positions[qb] - vertex_positions[qa]),
                               wp.length_sq(vertex_positions[qb + 1] - vertex_positions[qa + 1])))
        k *= wp.clamp(4.0 * (strip_max_width - width) / strip_max_width, 0.0, 1.0)
        # Near a strand's line the quad hands the vertex over to the segment-segment contacts (``quad_feature_owned``):
        # its stiffness fades in over a quarter of the reach from each strand, so the push does not switch off there.
        k *= strand_edge_fade(xb, vertex_positions[qa], vertex_positions[qb], vertex_positions[qa + 1],
                              vertex_positions[qb + 1], reach)
        inv_mass_a = 1.0 / seg_mass[vertex_segment(ia, seg_per_strand)]
        length_scale = seg_length[vertex_segment(ia, seg_per_strand)] / REFERENCE_SEGMENT_LENGTH
        # sum w_i / m_i bounds the face point's response sum w_i^2 / m_i from above, so the friction cap below stays
        # on the safe side.
        seg_fa = vertex_segment(qa + 1, seg_per_strand)
        seg_fb = vertex_segment(qb + 1, seg_per_strand)
        inv_mass_b = (corner[0] + corner[2]) / seg_mass[seg_fa] + (corner[1] + corner[3]) / seg_mass[seg_fb]
    else:
        va = wp.lerp(vertex_velocities[va0], vertex_velocities[va0 + 1], w[0])
        vb = wp.lerp(vertex_velocities[vb0], vertex_velocities[vb0 + 1], w[1])
        ta = wp.normalize(vertex_positions[va0 + 1] - vertex_positions[va0])
        tb = wp.normalize(vertex_positions[vb0 + 1] - vertex_positions[vb0])
        inv_mass_a = 1.0 / seg_mass[ia]
        inv_mass_b = 1.0 / seg_mass[ib]

    n = wp.vec3()
    if dist > _MIN_SEPARATION:
        n = delta / dist
    else:
        # Touching: separate along the normal of the plane of the two directions.
        c = wp.cross(ta, tb)
        if wp.length(c) <= 0.0:
            return
        n = wp.normalize(c)

    # Seed: repulsion k d (1 - |T_a . T_b|); the same factor on the normal damping so aligned hairs do not interact.
    # The factor falls to zero at the detection's alignment cutoff (a ~1 % change elsewhere), so a pair crossing
    # the cutoff between two detections is not switched on or off at a finite force: on the Ratboy mohawk at rest
    # that switch kept strands in cycles locked to the frame (tip RMS 0.83 mm/s, 0.50 with the fade).
    align = wp.max(1.0 - wp.abs(wp.dot(ta, tb)) - contact_alignment_cutoff, 0.0) / (1.0 - contact_alignment_cutoff)
    k_eff = k * length_scale * align
    c_eff = contact_damping * length_scale * align
    if response.enabled != 0:
        # past the step's rate limit a stiffer pair acts no differently in the step (see CONTACT_RESPONSE_RATE_LIMIT)
        k_eff = wp.min(k_eff, response.rate_limit / ((inv_mass_a + inv_mass_b) * h * h))
    if response.enabled == 0:
        # In the free step the damper acts explicitly, each side slowed by its own implicit mass h c: past the pair's
        # reduced mass over the step it would reverse the approach it damps (both sides answer it whole), and hair
        # pressed together by several such pairs blew up at any step (long_hair with interactions.damping >= 1.5 N
        # s/m, 400 times its own). Capped there, as the friction below is, it at most stops the approach in a step.
        c_eff = wp.min(c_eff, 1.0 / ((inv_mass_a + inv_mass_b) * h))
    vrel = va - vb
    vn = wp.dot(vrel, n)
    # a vertex-face contact's depth falls to none at the strip's plane, so its push does not flip there
    # (``PLANE_RAMP``); two segments crossing keep reach - d
    depth = reach - dist
    if kind == CONTACT_VERTEX_FACE:
        depth = contact_depth(dist, reach)
    fn = k_eff * depth - c_eff * vn
    if response.enabled != 0:
        # the contact's force is the response's, over the step (``contact_response_gather``)
        if k_eff + c_eff > 0.0:
            e0 = 4 * slot
            response.normal[slot] = n
            response.coef[slot] = h * k_eff + c_eff
            response.target[slot] = k_eff * depth / (h * k_eff + c_eff)
            if kind == CONTACT_VERTEX_FACE:
                response.weights[slot] = corner
                response.point[e0] = 0.5 * (xa + xb)
                response.share[e0] = 1.0
                shift = 0.5 * (xa - xb)
                wa = corner[0] + corner[2]
                wb = corner[1] + corner[3]
                if wa > 0.0:
                    response.point[e0 + 1] = (corner[0] * vertex_positions[qa] + corner[2] * vertex_positions[qa + 1]) \
                        / wa + shift
                    response.share[e0 + 1] = -wa
                if wb > 0.0:
                    response.point[e0 + 2] = (corner[1] * vertex_positions[qb] + corner[3] * vertex_positions[qb + 1]) \
                        / wb + shift
                    response.share[e0 + 2] = -wb
            else:
                response.weights[slot] = wp.vec4(w[0], w[1], 0.0, 0.0)
                response.point[e0] = 0.5 * (xa + xb)
                response.share[e0] = 1.0
                response.point[e0 + 1] = 0.5 * (xa + xb)
                response.share[e0 + 1] = -1.0
        return
    f = fn * n
    if fn <= 0.0:
        return

    # Coulomb friction in the plane normal to the separation (the plane of the two segments, or of the face),
    # regularised near v_t = 0 and capped at the impulse that brings the pair's tangential velocity to rest.
    vt = vrel - vn * n
    vt_len = wp.length(vt)
    if contact_friction > 0.0 and vt_len > 0.0:
        m_eff = 1.0 / (inv_mass_a + inv_mass_b)
        slip = wp.sqrt(vt_len * vt_len + contact_slip_velocity * contact_slip_velocity)
        mag = wp.min(contact_friction * fn * vt_len / slip, m_eff * vt_len / h)
        f = f - (mag / vt_len) * vt

    point = 0.5 * (xa + xb)
    extra = float(0.0)
    if implicit_springs != 0 and response.enabled == 0:
        extra = h * h * k_eff + h * c_eff
    e0 = 4 * slot
    if kind == CONTACT_VERTEX_FACE:
        put_wrench(e0, vertex_segment(ia, seg_per_strand), seg_per_strand, point, f, extra, seg_length,
                   vertex_positions, entry_force, entry_torque, entry_mass)
        # The face's share goes to its two segments (the quad's level-k segments, a_k a_{k+1} and b_k b_{k+1}), each
        # at the weighted point of its two corners shifted by (point - xb): the shares sum to -f at the common point,
        # with no net torque, and land on the same segments whichever triangle is the nearer.
        shift = point - xb
        wa = corner[0] + corner[2]
        wb = corner[1] + corner[3]
        if wa > 0.0:
            put_wrench(e0 + 1, seg_fa, seg_per_strand,
                       (corner[0] * vertex_positions[qa] + corner[2] * vertex_positions[qa + 1]) / wa + shift, -wa * f,
                       wa * extra, seg_length, vertex_positions, entry_force, entry_torque, entry_mass)
        if wb > 0.0:
            put_wrench(e0 + 2, seg_fb, seg_per_strand,
                       (corner[1] * vertex_positions[qb] + corner[3] * vertex_positions[qb + 1]) / wb + shift, -wb * f,
                       wb * extra, seg_length, vertex_positions, entry_force, entry_torque, entry_mass)
    else:
        put_wrench(e0, ia, seg_per_strand, point, f, extra, seg_length, vertex_positions, entry_force, entry_torque,
                   entry_mass)
        put_wrench(e0 + 1, ib, seg_per_strand, point, -f, extra, seg_length, vertex_positions, entry_force,
                   entry_torque, entry_mass)


@wp.kernel
def contact_forces(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    seg_length: wp.array(dtype=float),
    seg_mass: wp.array(dtype=float),
    strip_pairs: wp.array(dtype=wp.vec2i),
    tri_stiffness_scale: wp.array(dtype=float),
    contact_threshold: float,
    contact_stiffness: float,
    contact_damping: float,
    contact_friction: float,
    contact_slip_velocity: float,
    contact_alignment_cutoff: float,
    strip_max_width: float,
    thread_count: int,
    contiguous: int,
    implicit_springs: int,
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    # Control:
    dt: wp.array(dtype=float),
    # Scratch:
    contacts: ContactBuffer,
    response: ContactResponse,
    # Out:
    entry_force: wp.array(dtype=wp.vec3),
    entry_torque: wp.array(dtype=wp.vec3),
    entry_mass: wp.array(dtype=float),
):
    """Each of ``thread_count`` threads takes every thread_count-th stored contact (``contiguous``: a run of
    consecutive ones): repulsion, normal damping and regularised Coulomb friction.

    The repulsion acts below ``min(threshold, gap)`` [m]. +F goes to side a and -F to side b (a face's share split
    by barycentric weight between its quad's two segments) at the midpoint of the closest points: force [N], torque
    [N m] about the segment's origin (world) and, with ``implicit_springs``, ``h^2 k + h c`` [kg] (lever-scaled) in
    the contact's entries ``4 slot + e`` of ``entry_force``, ``entry_torque``, ``entry_mass`` (zero where it does not
    act), which ``contact_gather`` adds to the segments: no two threads write one element, so the sums are the same
    bits however the threads are split. Friction is capped so one explicit step cannot reverse the slip.
    """
    # A fixed thread count covers however many contacts this step found (the count is only on the device): on a GPU
    # thread t takes slots t, t + n, ... (neighbouring threads read neighbouring slots), on a CPU, where the threads
    # run one after the other, a contiguous run of slots (one pass over the buffer instead of n).
    t = tid_offset + wp.tid()
    count = wp.min(contacts.counter[0], contacts.capacity)
    h = dt[0]
    slot = t
    stride = thread_count
    end = count
    if contiguous != 0:
        run = (count + thread_count - 1) // thread_count
        slot = t * run
        stride = 1
        end = wp.min(slot + run, count)
    while slot < end:
        contact_force(
            slot, seg_per_strand, seg_length, seg_mass, strip_pairs, tri_stiffness_scale,
            contact_threshold, contact_stiffness, contact_damping, contact_friction, contact_slip_velocity,
            contact_alignment_cutoff, strip_max_width, vertex_positions, vertex_velocities, h, implicit_springs,
            contacts, response, entry_force, entry_torque, entry_mass,
        )
        slot += stride


@wp.kernel
def contact_segment_lists(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    seg_count: int,
    strip_pairs: wp.array(dtype=wp.vec2i),
    # Scratch:
    contacts: ContactBuffer,
    seg_cursor: wp.array(dtype=wp.int32),
    # Out:
    seg_entry_start: wp.array(dtype=wp.int32),
    seg_entries: wp.array(dtype=wp.int32),
):
    """One thread: list, per segment, the entries of the stored contacts that push it (``contact_segments``), in slot
    order: segment s's are ``seg_entries[seg_entry_start[s]]`` to ``seg_entries[seg_entry_start[s + 1] - 1]``. A
    counting sort over the contacts, run once per detection (its features do not change until the next)."""
    count = wp.min(contacts.counter[0], contacts.capacity)
    for s in range(seg_count + 1):
        seg_entry_start[s] = 0
    for slot in range(count):
        segs = contact_segments(slot, seg_per_strand, strip_pairs, contacts)
        for e in range(4):
            if segs[e] >= 0:
                seg_entry_start[segs[e] + 1] = seg_entry_start[segs[e] + 1] + 1
    total = int(0)
    for s in range(seg_count + 1):
        total += seg_entry_start[s]
        seg_entry_start[s] = total
    for s in range(seg_count):
        seg_cursor[s] = seg_entry_start[s]
    for slot in range(count):
        segs = contact_segments(slot, seg_per_strand, strip_pairs, contacts)
        for e in range(4):
            if segs[e] >= 0:
                seg_entries[seg_cursor[segs[e]]] = 4 * slot + e
                seg_cursor[segs[e]] = seg_cursor[segs[e]] + 1


@wp.kernel
def contact_gather(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_mass: wp.array(dtype=float),
    implicit_springs: int,
    # Scratch:
    seg_entry_start: wp.array(dtype=wp.int32),
    seg_entries: wp.array(dtype=wp.int32),
    entry_force: wp.array(dtype=wp.vec3),
    entry_torque: wp.array(dtype=wp.vec3),
    entry_mass: wp.array(dtype=float),
    seg_spring_mass: wp.array(dtype=float),
    # Out:
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
    seg_implicit_mass: wp.array(dtype=float),
):
    """One thread per segment: add the entries ``contact_forces`` left for it (``contact_segment_lists``, in slot
    order) to ``seg_force`` [N] and ``seg_torque`` [N m]; with ``implicit_springs``, their masses [kg] to its
    ``seg_spring_mass``, passed on as ``kernels.links.add_excess_mass`` does."""
    seg = tid_offset + wp.tid()
    first = seg_entry_start[seg]
    last = seg_entry_start[seg + 1]
    force = wp.vec3()
    torque = wp.vec3()
    mass = float(0.0)
    for j in range(first, last):
        e = seg_entries[j]
        force += entry_force[e]
        torque += entry_torque[e]
        mass += entry_mass[e]
    add_gathered(seg, last - first, force, torque, mass, implicit_springs, seg_mass, seg_spring_mass, seg_force,
                 seg_torque, seg_implicit_mass)


@wp.func
def contact_vertices(slot: int, seg_per_strand: int, strip_pairs: wp.array(dtype=wp.vec2i), contacts: ContactBuffer):
    """The vertices of the contact in ``slot``: side a's two (a vertex-face contact's vertex twice, a segment's
    ends) and side b's four (the strip quad's corners in ``response.weights`` order, or a segment's ends, the first
    twice more)."""
    ia = contacts.a[slot]
    ib = contacts.b[slot]
    if contacts.kind[slot] == CONTACT_VERTEX_FACE:
        qa, qb = strip_quad_origins(ib // 2, seg_per_strand, strip_pairs)
        return wp.vec2i(ia, ia), wp.vec4i(qa, qb, qa + 1, qb + 1)
    va0 = ia + ia // seg_per_strand
    vb0 = ib + ib // seg_per_strand
    return wp.vec2i(va0, va0 + 1), wp.vec4i(vb0, vb0 + 1, vb0, vb0)


@wp.func
def contact_relative_velocity(slot: int, seg_per_strand: int, strip_pairs: wp.array(dtype=wp.vec2i),
                              contacts: ContactBuffer, response: ContactResponse,
                              vertex_velocities: wp.array(dtype=wp.vec3)) -> wp.vec3:
    """Velocity [m/s] of side a relative to side b of the contact in ``slot``, at the points that ``contact_force``
    took at the step's start, from ``vertex_velocities``."""
    a, b = contact_vertices(slot, seg_per_strand, strip_pairs, contacts)
    wt = response.weights[slot]
    va = wp.vec3()
    vb = wp.vec3()
    if contacts.kind[slot] == CONTACT_VERTEX_FACE:
        va = vertex_velocities[a[0]]
        vb = (wt[0] * vertex_velocities[b[0]] + wt[1] * vertex_velocities[b[1]] + wt[2] * vertex_velocities[b[2]]
              + wt[3] * vertex_velocities[b[3]])
    else:
        va = wp.lerp(vertex_velocities[a[0]], vertex_velocities[a[1]], wt[0])
        vb = wp.lerp(vertex_velocities[b[0]], vertex_velocities[b[1]], wt[1])
    return va - vb


@wp.func
def others_velocity(v: int, strand: int, seg_per_strand: int, answered: wp.array(dtype=wp.vec3),
                    answered_before: wp.array(dtype=wp.vec3), colors: wp.array(dtype=wp.int32)):
    """Vertex ``v``'s velocity as ``strand``'s sweep sees it: zero where it is ``strand``'s own (that part is
    ``SweepContacts.free``); from ``answered_before`` (the last sweep's answers) where its strand has ``strand``'s
    colour and is solved at the same time, so that no strand reads what another writes; else from ``answered``."""
    other = v // (seg_per_strand + 1)
    if other == strand:
        return wp.vec3()
    if colors[other] == colors[strand]:
        return answered_before[v]
    return answered[v]


@wp.func
def others_relative_velocity(slot: int, strand: int, seg_per_strand: int, strip_pairs: wp.array(dtype=wp.vec2i),
                             contacts: ContactBuffer, response: ContactResponse, answered: wp.array(dtype=wp.vec3),
                             answered_before: wp.array(dtype=wp.vec3), colors: wp.array(dtype=wp.int32)) -> wp.vec3:
    """The other strands' share of ``contact_relative_velocity`` (``others_velocity``); ``strand``'s own vertices
    count zero."""
    S = seg_per_strand
    a, b = contact_vertices(slot, S, strip_pairs, contacts)
    wt = response.weights[slot]
    # each side's weights, as contact_relative_velocity takes them
    wa = wp.vec2(1.0, 0.0)
    wb = wt
    if contacts.kind[slot] != CONTACT_VERTEX_FACE:
        wa = wp.vec2(1.0 - wt[0], wt[0])
        wb = wp.vec4(1.0 - wt[1], wt[1], 0.0, 0.0)
    va = wa[0] * others_velocity(a[0], strand, S, answered, answered_before, colors) \
        + wa[1] * others_velocity(a[1], strand, S, answered, answered_before, colors)
    vb = wb[0] * others_velocity(b[0], strand, S, answered, answered_before, colors) \
        + wb[1] * others_velocity(b[1], strand, S, answered, answered_before, colors) \
        + wb[2] * others_velocity(b[2], strand, S, answered, answered_before, colors) \
        + wb[3] * others_velocity(b[3], strand, S, answered, answered_before, colors)
    return va - vb


@wp.func
def sweep_entry_force(j: int, strand: int, seg_per_strand: int, strip_pairs: wp.array(dtype=wp.vec2i),
                      contacts: ContactBuffer, response: ContactResponse, sweep: SweepContacts,
                      answered_velocities: wp.array(dtype=wp.vec3), answered_before: wp.array(dtype=wp.vec3),
                      colors: wp.array(dtype=wp.int32)) -> wp.vec3:
    """The force [N, world] of the ``j``-th of ``sweep``'s entries on ``strand``'s free velocities in a sweep
    (``kernels.sweeps.link_sweep``): the contact's damper as ``response_entry`` takes it (in contact
    or not, and its friction coefficient, from the free step) on the velocity of ``strand``'s side from its free
    step relative to the other side's latest answer. With the whole damper as its point inertia
    (``contact_response_gather``) that is ``strand``'s block of the contacts' backward-Euler step, the other strands
    held: Gauss-Seidel, as the links'. Linear in the velocities through the sweeps (the contact is neither dropped
    nor taken up between them), so the factors of the first sweep serve every later one."""
    entry = sweep.entries[j]
    v = sweep.free[j] + others_relative_velocity(entry // 4, strand, seg_per_strand, strip_pairs, contacts, response,
                                                 answered_velocities, answered_before, colors)
    return swept_entry_force(entry, sweep.friction[j], response, v)


@wp.func
def swept_entry_force(entry: int, friction: float, response: ContactResponse, v: wp.vec3) -> wp.vec3:
    """The force [N, world] of the contact entry ``entry`` as the links' sweeps solve it, at its pair's relative
    velocity ``v``: the backward-Euler push ``D (target - v_n)`` along the normal and the damper ``friction`` [N s/m]
    on the slip, by the entry's share (``sweep_entry_force``, ``contact_warm_forces``)."""
    slot = entry // 4
    n = response.normal[slot]
    vn = wp.dot(v, n)
    return response.share[entry] * (response.coef[slot] * (response.target[slot] - vn) * n - friction * (v - vn * n))


@wp.func
def response_entry(entry: int, h: float, seg: int, seg_xform: wp.array(dtype=wp.transform), seg_per_strand: int,
                   strip_pairs: wp.array(dtype=wp.vec2i), contacts: ContactBuffer, response: ContactResponse,
                   vertex_velocities: wp.array(dtype=wp.vec3), whole: int):
    """One entry's damper on its segment ``seg``, in the segment's frame at the step's start: ``(r, M, f, D_t, v)``,
    the point, the point inertia [kg] (zero: none; the side's split share of it, or with ``whole`` the damper unsplit,
    as the links' sweeps solve it), the force [N] on the free velocities, the friction coefficient [N s/m] and the
    pair's relative velocity [m/s, world] (``contact_relative_velocity``).

    The contact's backward-Euler normal force over the step is ``k d - D v_n'``, ``v_n'`` the pair's normal velocity
    at its end; each side takes it as a damper ``s D`` toward the pair's centre-of-mass velocity (Jacobi between
    strands) on the free step's ``v_n``: ``-D (v_n - target)`` on side a and its shares on side b, while positive,
    with the point inertia ``s h D |share|``, ``s`` the side's split factor (``contact_response_split``). A face
    corner's inertia takes its weight w, not w^2: an upper bound, on the stable side."""
    slot = entry // 4
    D = response.coef[slot]
    share = response.share[entry]
    if D <= 0.0 or share == 0.0:
        return wp.vec3(), wp.mat33(), wp.vec3(), 0.0, wp.vec3()
    n = response.normal[slot]
    split = response.split[slot]
    s = float(1.0)
    if whole == 0:
        s = split[1]
        if share > 0.0:
            s = split[0]
    vrel = contact_relative_velocity(slot, seg_per_strand, strip_pairs, contacts, response, vertex_velocities)
    vn = wp.dot(vrel, n)
    push = D * (response.target[slot] - vn)  # the force over the step, k d - D v_n, on the free velocities
    if push <= 0.0:
        # the pair leaves faster than its spring explains: no contact
        return wp.vec3(), wp.mat33(), wp.vec3(), 0.0, vrel
    # Coulomb friction as a damper on the tangential velocity, its coefficient the cone's over the free step's slip
    # (regularised below slip_velocity): the damper's force, D_t |v_t'| <= D_t |v_t| <= mu f_n, stays in the cone,
    # and a damper never reverses the slip it acts on, however many contacts share a segment. f_n is the normal force
    # the pair keeps once solved, push / (1 + h D W): push itself, at long steps h D W times larger, held strands
    # against each other far past the cone (the mohawk at 2 substeps tore 14 more links).
    vt = vrel - vn * n
    vt_sq = wp.dot(vt, vt)
    Dt = response.friction * push * split[2] / wp.sqrt(vt_sq + response.slip_velocity * response.slip_velocity)
    xf = seg_xform[seg]
    R = wp.transform_get_rotation(xf)
    nl = wp.quat_rotate_inv(R, n)
    r = wp.quat_rotate_inv(R, response.point[entry] - wp.transform_get_translation(xf))
    a = wp.abs(share)
    M = (s * h * a) * ((D - Dt) * wp.outer(nl, nl) + Dt * wp.identity(n=3, dtype=float))
    f = share * wp.quat_rotate_inv(R, push * n - Dt * vt)
    return r, M, f, Dt, vrel


@wp.kernel
def contact_response_split(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    strip_pairs: wp.array(dtype=wp.vec2i),
    # Scratch:
    contacts: ContactBuffer,
    seg_entry_start: wp.array(dtype=wp.int32),
    # State: the step's start (frames)
    seg_xform: wp.array(dtype=wp.transform),
    # Control:
    dt: wp.array(dtype=float),
    dampers: InteractionResponse,
    # In and out:
    response: ContactResponse,
):
    """One thread per buffer slot: the split factors ``(s_a, s_b)`` of the contact's two sides and the share of its
    force on the free velocities that the pair keeps once solved, ``1 / (1 + h D (W_a + W_b))`` (``response.split``),
    from their effective masses along the normal in their strands (``articulated_inverse_mass``; a face point's, its
    corners' segments' by their weights squared): ``split_factor``, the other side's inverse mass shared among its
    segments' contacts where it is the lighter and the contact holds it (``shared_inverse_mass``; counts from
    ``seg_entry_start`` when it holds the segments' lists, one contact a segment where it has one element). 2 for
    equal sides."""
    slot = tid_offset + wp.tid()
    if slot >= wp.min(contacts.counter[0], contacts.capacity):
        return
    D = response.coef[slot]
    if D <= 0.0:
        return
    n = response.normal[slot]
    segs = contact_segments(slot, seg_per_strand, strip_pairs, contacts)
    w_a = float(0.0)  # inverse masses of the two sides
    w_b = float(0.0)
    shared_a = float(0.0)  # ... each segment's times the contacts it has
    shared_b = float(0.0)
    for e in range(3):
        other = segs[e]
        weight = response.share[4 * slot + e]
        if other >= 0 and weight != 0.0:
            w = weight * weight * articulated_inverse_mass(dampers, other, seg_xform[other],
                                                           response.point[4 * slot + e], n)
            count = float(1.0)
            if seg_entry_start.shape[0] > other + 1:
                count = float(seg_entry_start[other + 1] - seg_entry_start[other])
            if weight > 0.0:
                w_a += w
                shared_a += count * w
            else:
                w_b += w
                shared_b += count * w
    stiffness = dt[0] * D
    response.split[slot] = wp.vec3(
        split_factor(w_a, shared_inverse_mass(w_a, w_b, shared_b / wp.max(w_b, 1.0e-30), stiffness)),
        split_factor(w_b, shared_inverse_mass(w_b, w_a, shared_a / wp.max(w_a, 1.0e-30), stiffness)),
        1.0 / (1.0 + stiffness * (w_a + w_b)))


@wp.kernel
def contact_response_gather(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    strip_pairs: wp.array(dtype=wp.vec2i),
    # Scratch:
    contacts: ContactBuffer,
    response: ContactResponse,
    seg_entry_start: wp.array(dtype=wp.int32),
    seg_entries: wp.array(dtype=wp.int32),
    # State: the step's start (frames), the free step's end (velocities)
    seg_xform: wp.array(dtype=wp.transform),
    vertex_velocities: wp.array(dtype=wp.vec3),
    # Control:
    dt: wp.array(dtype=float),
    sweeping: int,
    colors: wp.array(dtype=wp.int32),
    # In and out:
    dampers: InteractionResponse,
    # Out: with ``sweeping``, the blocks of the sweeps' dampers and their contacts
    sweep_blocks: InteractionResponse,
    sweep: SweepContacts,
):
    """One thread per segment: add the dampers of the contacts that push it (``response_entry``, its entries in slot
    order) to its ``InteractionResponse`` blocks, for ``kernels.articulated.interaction_response``; with
    ``sweeping``, instead store the blocks of the same dampers whole (split factor 1) in ``sweep_blocks``, which the
    links' gather adds to and ``kernels.sweeps.link_sweep`` solves with, and list the contacts in ``sweep`` (the
    sweeps read neither the split blocks nor their forces)."""
    seg = tid_offset + wp.tid()
    h = dt[0]
    A = wp.mat33()
    B = wp.mat33()
    C = wp.mat33()
    force = wp.vec3()
    torque = wp.vec3()
    strand = seg // seg_per_strand
    listed = seg_entry_start[seg]
    for j in range(seg_entry_start[seg], seg_entry_start[seg + 1]):
        entry = seg_entries[j]
        r, M, f, Dt, vrel = response_entry(entry, h, seg, seg_xform, seg_per_strand, strip_pairs, contacts,
                                           response, vertex_velocities, sweeping)
        if wp.trace(M) > 0.0:
            Ap, Bp = point_damper_blocks(r, M)
            A += Ap
            B += Bp
            C += M
            if sweeping != 0:
                sweep.entries[listed] = entry
                sweep.friction[listed] = Dt
                sweep.free[listed] = vrel - others_relative_velocity(
                    entry // 4, strand, seg_per_strand, strip_pairs, contacts, response, vertex_velocities,
                    vertex_velocities, colors)
                listed += 1
            else:
                force += f
                torque += spin_free_torque(r, f)
    if sweeping != 0:
        # the sweeps solve the contacts with their whole dampers and forces of their own (``sweep_entry_force``):
        # the split dampers are not read
        sweep_blocks.A[seg] = A
        sweep_blocks.B[seg] = B
        sweep_blocks.C[seg] = C
        sweep.end[seg] = listed
    else:
        add_damper(dampers, seg, A, B, C, force, torque)


@wp.kernel
def contact_response_scatter(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    strip_pairs: wp.array(dtype=wp.vec2i),
    # Scratch:
    contacts: ContactBuffer,
    response: ContactResponse,
    # State: the step's start (frames), the free step's end (velocities)
    seg_xform: wp.array(dtype=wp.transform),
    vertex_velocities: wp.array(dtype=wp.vec3),
    # Control:
    dt: wp.array(dtype=float),
    # In and out:
    dampers: InteractionResponse,
):
    """One thread per buffer slot (on a GPU): ``contact_response_gather`` with atomics, in any order."""
    slot = tid_offset + wp.tid()
    if slot >= wp.min(contacts.counter[0], contacts.capacity):
        return
    h = dt[0]
    segs = contact_segments(slot, seg_per_strand, strip_pairs, contacts)
    for e in range(4):
        seg = segs[e]
        if seg >= 0:
            r, M, f, Dt, vrel = response_entry(4 * slot + e, h, seg, seg_xform, seg_per_strand, strip_pairs,
                                               contacts, response, vertex_velocities, 0)
            if wp.trace(M) > 0.0:
                Ap, Bp = point_damper_blocks(r, M)
                wp.atomic_add(dampers.A, seg, Ap)
                wp.atomic_add(dampers.B, seg, Bp)
                wp.atomic_add(dampers.C, seg, M)
                wp.atomic_add(dampers.force, seg, f)
                wp.atomic_add(dampers.torque, seg, spin_free_torque(r, f))


@wp.kernel
def contact_scatter(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    strip_pairs: wp.array(dtype=wp.vec2i),
    # Scratch:
    contacts: ContactBuffer,
    entry_force: wp.array(dtype=wp.vec3),
    entry_torque: wp.array(dtype=wp.vec3),
    entry_mass: wp.array(dtype=float),
    # Out:
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
    seg_spring_mass: wp.array(dtype=float),
):
    """One thread per buffer slot (on a GPU, where atomics are atomic and a one-thread list per detection would
    stall): add the entries of the stored contact to its segments (``contact_segments``), in any order."""
    slot = tid_offset + wp.tid()
    if slot >= wp.min(contacts.counter[0], contacts.capacity):
        return
    segs = contact_segments(slot, seg_per_strand, strip_pairs, contacts)
    for e in range(4):
        seg = segs[e]
        if seg >= 0:
            wp.atomic_add(seg_force, seg, entry_force[4 * slot + e])
            wp.atomic_add(seg_torque, seg, entry_torque[4 * slot + e])
            wp.atomic_add(seg_spring_mass, seg, entry_mass[4 * slot + e])


@wp.kernel
def contact_warm_forces(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    # The contacts the links' sweeps solved (``SweepContacts``, as ``kernels.sweeps.link_sweep`` reads them):
    strip_pairs: wp.array(dtype=wp.vec2i),
    contacts: ContactBuffer,
    response: ContactResponse,
    seg_entry_start: wp.array(dtype=wp.int32),
    sweep: SweepContacts,
    # State: the step's start (frames); every strand's answer after the sweeps, linearised at the start
    seg_xform: wp.array(dtype=wp.transform),
    answered: wp.array(dtype=wp.vec3),
    # Speed [m/s] of the pair's relative motion at which a contact keeps half its force (0: the whole force)
    gate: float,
    # Out: each segment's hair contact force [N, world] and torque about its origin [N m, world] in the answer
    warm_force: wp.array(dtype=wp.vec3),
    warm_torque: wp.array(dtype=wp.vec3),
):
    """One thread per strand: the force its segments' hair contacts put on them in the links' sweeps' answer, each
    entry's force as the sweeps solve it (``sweep_entry_force``) with both sides at their answer, which the next step's
    free step takes (``contact_warm_add``; ``hairwarp.HairContacts.warm_start``), the sweeps then solving the change.
    Each contact keeps ``1 / (1 + |u|^2 / gate^2)`` of its force, ``u`` the pair's relative velocity in the answer: a
    contact at rest carries its force whole, one that slides or parts fast starts cold, as before."""
    strand = tid_offset + wp.tid()
    S = seg_per_strand
    for k in range(S):
        seg = strand * S + k
        xf = seg_xform[seg]
        R = wp.transform_get_rotation(xf)
        origin = wp.transform_get_translation(xf)
        force = wp.vec3()
        torque = wp.vec3()
        for j in range(seg_entry_start[seg], sweep.end[seg]):
            entry = sweep.entries[j]
            u = contact_relative_velocity(entry // 4, S, strip_pairs, contacts, response, answered)
            f = swept_entry_force(entry, sweep.friction[j], response, u)
            if gate > 0.0:
                f = f / (1.0 + wp.dot(u, u) / (gate * gate))
            f_local = wp.quat_rotate_inv(R, f)
            force += f_local
            torque += spin_free_torque(wp.quat_rotate_inv(R, response.point[entry] - origin), f_local)
        warm_force[seg] = wp.quat_rotate(R, force)
        warm_torque[seg] = wp.quat_rotate(R, torque)


@wp.kernel
def contact_warm_add(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Each segment's hair contact force and torque of the last step (``contact_warm_forces``)
    warm_force: wp.array(dtype=wp.vec3),
    warm_torque: wp.array(dtype=wp.vec3),
    # In and out: the free step's loads
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
):
    """One thread per segment: add its hair contact force of the last step to the free step's loads."""
    seg = tid_offset + wp.tid()
    seg_force[seg] = seg_force[seg] + warm_force[seg]
    seg_torque[seg] = seg_torque[seg] + warm_torque[seg]
