"""Dynamic hair-hair interactions: vertex-face and segment-segment contacts (DESIGN §4.4).

Seed slides, "Dynamic interactions": pairs closer than a threshold get a repulsion ``F_s = k d (1 - |T_a . T_b|)``
along their separation (``d`` = threshold - distance; it vanishes as hairs line up) and Coulomb friction
``F_fric = -mu F_N v_t / |v_t|`` in the contact plane. Forces on a strip triangle are shared among its three
vertices by barycentric weights. Detection writes fixed-capacity contact buffers; ``contact_forces`` reads them.

Both sides of a contact receive their force at the same world point (the midpoint of the two closest points),
so every contact is an equal and opposite pair with no net torque.
"""

import warp as wp

from hairwarp.kernels.links import lever_scaled_mass
from hairwarp.kernels.types import Fault

wp.set_module_options({"enable_backward": False})

CONTACT_VERTEX_FACE = wp.constant(0)
CONTACT_SEGMENT_SEGMENT = wp.constant(1)
CONTACT_OVERFLOW = wp.constant(int(Fault.CONTACT_OVERFLOW))

# Squared edge length [m^2] below which closest_point_edge_edge treats an edge as a point.
_DEGENERATE_EDGE_SQ = wp.constant(1.0e-14)
# Separation [m] below which the direction between the two closest points is round-off.
_MIN_SEPARATION = wp.constant(1.0e-9)


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
def strip_face_direction(
    tri: int, seg_per_strand: int, tri_strands: wp.array(dtype=wp.vec2i), vertex_positions: wp.array(dtype=wp.vec3)
) -> wp.vec3:
    """Unit "vertical" (along-strand) direction of a strip triangle: the mean of its two strands' segments."""
    k = (tri % (2 * seg_per_strand)) // 2
    ab = tri_strands[tri]
    ia = ab[0] * (seg_per_strand + 1) + k
    ib = ab[1] * (seg_per_strand + 1) + k
    d = (vertex_positions[ia + 1] - vertex_positions[ia]) + (vertex_positions[ib + 1] - vertex_positions[ib])
    return wp.normalize(d)


@wp.func
def strip_feature_owned(w: wp.vec3, tri: int, seg_per_strand: int) -> bool:
    """Whether a vertex-face contact whose closest point has barycentric weights w belongs to triangle ``tri``.

    Closest points on a strand (a strip corner or a strand edge) are segment-segment contacts; an inner edge shared
    by two triangles of a strip belongs to one of them. Otherwise a vertex near a strand would be pushed once per
    triangle that touches it, up to eight times over.
    """
    if w[0] == 1.0 or w[1] == 1.0 or w[2] == 1.0:
        return False
    if tri % 2 == 0:
        # (a_k, b_k, a_{k+1}): a_k a_{k+1} is strand a; it owns the diagonal and the horizontal edge a_k b_k.
        return w[1] != 0.0
    # (b_k, b_{k+1}, a_{k+1}): b_k b_{k+1} is strand b, the diagonal b_k a_{k+1} belongs to the first triangle,
    # and the horizontal edge a_{k+1} b_{k+1} to the next segment's first triangle, except at the tips.
    if w[2] == 0.0 or w[1] == 0.0:
        return False
    if w[0] == 0.0:
        return (tri % (2 * seg_per_strand)) // 2 == seg_per_strand - 1
    return True


@wp.func
def push_contact(
    kind: int,
    a: int,
    b: int,
    w: wp.vec3,
    contact_capacity: int,
    contact_kind: wp.array(dtype=wp.int32),
    contact_a: wp.array(dtype=wp.int32),
    contact_b: wp.array(dtype=wp.int32),
    contact_w: wp.array(dtype=wp.vec3),
    contact_counter: wp.array(dtype=wp.int32),
    contact_overflow: wp.array(dtype=wp.int32),
    fault: wp.array(dtype=wp.int32),
):
    """Append one contact; past the capacity, count it, drop it and raise the overflow flags."""
    slot = wp.atomic_add(contact_counter, 0, 1)
    if slot < contact_capacity:
        contact_kind[slot] = kind
        contact_a[slot] = a
        contact_b[slot] = b
        contact_w[slot] = w
    else:
        contact_overflow[0] = 1
        wp.atomic_or(fault, 0, CONTACT_OVERFLOW)


@wp.kernel
def segment_bounds(
    # Model:
    seg_per_strand: int,
    contact_threshold: float,
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Out:
    seg_lowers: wp.array(dtype=wp.vec3),
    seg_uppers: wp.array(dtype=wp.vec3),
):
    """One thread per segment: its world bounding box [m] grown by the contact threshold, for the segment BVH."""
    seg = wp.tid()
    v = seg + seg // seg_per_strand
    x0 = vertex_positions[v]
    x1 = vertex_positions[v + 1]
    grow = wp.vec3(contact_threshold)
    seg_lowers[seg] = wp.min(x0, x1) - grow
    seg_uppers[seg] = wp.max(x0, x1) + grow


@wp.kernel
def segment_segment_contacts(
    # Model:
    seg_per_strand: int,
    contact_threshold: float,
    contact_capacity: int,
    contact_alignment_cutoff: float,
    seg_bvh: wp.uint64,
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Out:
    contact_kind: wp.array(dtype=wp.int32),
    contact_a: wp.array(dtype=wp.int32),
    contact_b: wp.array(dtype=wp.int32),
    contact_w: wp.array(dtype=wp.vec3),
    contact_counter: wp.array(dtype=wp.int32),
    contact_overflow: wp.array(dtype=wp.int32),
    fault: wp.array(dtype=wp.int32),
):
    """One thread per segment i: every segment j > i of another strand closer than the threshold [m].

    Queries the BVH of threshold-grown segment boxes with i's own box; appends (i, j, (s, t, 0)) with the
    closest-point parameters along each segment (0 at the segment origin, 1 at its end). Pairs more nearly
    parallel than the alignment cutoff (``1 - |T_a . T_b|`` below it) are left out: their repulsion is negligible.
    """
    i = wp.tid()
    strand = i // seg_per_strand
    vi = i + strand
    p0 = vertex_positions[vi]
    p1 = vertex_positions[vi + 1]
    ta = wp.normalize(p1 - p0)
    query = wp.bvh_query_aabb(seg_bvh, wp.min(p0, p1), wp.max(p0, p1))
    j = int(0)
    while wp.bvh_query_next(query, j):
        if j <= i or j // seg_per_strand == strand:
            continue
        vj = j + j // seg_per_strand
        q0 = vertex_positions[vj]
        q1 = vertex_positions[vj + 1]
        if contact_alignment_cutoff > 0.0:
            if 1.0 - wp.abs(wp.dot(ta, wp.normalize(q1 - q0))) < contact_alignment_cutoff:
                continue
        st = wp.closest_point_edge_edge(p0, p1, q0, q1, _DEGENERATE_EDGE_SQ)
        if st[2] < contact_threshold:
            push_contact(
                CONTACT_SEGMENT_SEGMENT, i, j, wp.vec3(st[0], st[1], 0.0), contact_capacity,
                contact_kind, contact_a, contact_b, contact_w, contact_counter, contact_overflow, fault,
            )


@wp.kernel
def strip_bounds(
    # Model:
    contact_threshold: float,
    strip_indices: wp.array(dtype=wp.int32),
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Out:
    strip_lowers: wp.array(dtype=wp.vec3),
    strip_uppers: wp.array(dtype=wp.vec3),
):
    """One thread per strip quad (two triangles): its world box [m] grown by the threshold, for the strip BVH."""
    quad = wp.tid()
    # Triangles 2q = (a_k, b_k, a_{k+1}) and 2q+1 = (b_k, b_{k+1}, a_{k+1}): corners at index slots 0, 1, 2 and 4.
    p0 = vertex_positions[strip_indices[6 * quad + 0]]
    p1 = vertex_positions[strip_indices[6 * quad + 1]]
    p2 = vertex_positions[strip_indices[6 * quad + 2]]
    p3 = vertex_positions[strip_indices[6 * quad + 4]]
    grow = wp.vec3(contact_threshold)
    strip_lowers[quad] = wp.min(wp.min(p0, p1), wp.min(p2, p3)) - grow
    strip_uppers[quad] = wp.max(wp.max(p0, p1), wp.max(p2, p3)) + grow


@wp.kernel
def vertex_face_contacts(
    # Model:
    seg_per_strand: int,
    contact_threshold: float,
    contact_capacity: int,
    contact_alignment_cutoff: float,
    strip_bvh: wp.uint64,
    strip_indices: wp.array(dtype=wp.int32),
    tri_strands: wp.array(dtype=wp.vec2i),
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    # Out:
    contact_kind: wp.array(dtype=wp.int32),
    contact_a: wp.array(dtype=wp.int32),
    contact_b: wp.array(dtype=wp.int32),
    contact_w: wp.array(dtype=wp.vec3),
    contact_counter: wp.array(dtype=wp.int32),
    contact_overflow: wp.array(dtype=wp.int32),
    fault: wp.array(dtype=wp.int32),
):
    """One thread per guide vertex (roots skipped): every strip triangle of other strands closer than the threshold.

    Queries the BVH of threshold-grown strip quads with the vertex position [m]; appends (vertex, triangle,
    barycentric weights of the closest point) when that point lies inside the strip (``strip_feature_owned``) and
    the strand crosses the strip by more than the alignment cutoff.
    """
    vertex = wp.tid()
    strand = vertex // (seg_per_strand + 1)
    if vertex == strand * (seg_per_strand + 1):
        return
    p = vertex_positions[vertex]
    ta = vertex_tangent(vertex, seg_per_strand, vertex_positions)
    query = wp.bvh_query_aabb(strip_bvh, p, p)
    quad = int(0)
    while wp.bvh_query_next(query, quad):
        ab = tri_strands[2 * quad]
        if ab[0] == strand or ab[1] == strand:
            continue
        if contact_alignment_cutoff > 0.0:
            tb = strip_face_direction(2 * quad, seg_per_strand, tri_strands, vertex_positions)
            if 1.0 - wp.abs(wp.dot(ta, tb)) < contact_alignment_cutoff:
                continue
        for j in range(2):
            tri = 2 * quad + j
            a = vertex_positions[strip_indices[3 * tri + 0]]
            b = vertex_positions[strip_indices[3 * tri + 1]]
            c = vertex_positions[strip_indices[3 * tri + 2]]
            # Cheap rejection first: a point farther than the threshold from the triangle's plane is farther from
            # the triangle (compared squared, scaled by |n|^2, to avoid a square root).
            n = wp.cross(b - a, c - a)
            h = wp.dot(p - a, n)
            if h * h > contact_threshold * contact_threshold * wp.dot(n, n):
                continue
            w = closest_point_triangle(p, a, b, c)
            q = w[0] * a + w[1] * b + w[2] * c
            if wp.length(p - q) < contact_threshold and strip_feature_owned(w, tri, seg_per_strand):
                push_contact(
                    CONTACT_VERTEX_FACE, vertex, tri, w, contact_capacity,
                    contact_kind, contact_a, contact_b, contact_w, contact_counter, contact_overflow, fault,
                )


@wp.func
def add_wrench(
    seg: int,
    seg_per_strand: int,
    point: wp.vec3,
    f: wp.vec3,
    extra_mass: float,
    vertex_positions: wp.array(dtype=wp.vec3),
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
    seg_implicit_mass: wp.array(dtype=float),
):
    """Add force f at a world point to a segment (torque about its origin, vertex k) and its lever-scaled implicit
    mass."""
    v = seg + seg // seg_per_strand
    origin = vertex_positions[v]
    wp.atomic_add(seg_force, seg, f)
    wp.atomic_add(seg_torque, seg, wp.cross(point - origin, f))
    half = 0.5 * wp.length(vertex_positions[v + 1] - origin)
    wp.atomic_add(seg_implicit_mass, seg, lever_scaled_mass(extra_mass, point - origin, half))


@wp.func
def contact_force(
    slot: int,
    seg_per_strand: int,
    seg_mass: wp.array(dtype=float),
    strip_indices: wp.array(dtype=wp.int32),
    tri_strands: wp.array(dtype=wp.vec2i),
    tri_stiffness_scale: wp.array(dtype=float),
    contact_threshold: float,
    contact_stiffness: float,
    contact_damping: float,
    contact_friction: float,
    contact_slip_velocity: float,
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    h: float,
    contact_kind: wp.array(dtype=wp.int32),
    contact_a: wp.array(dtype=wp.int32),
    contact_b: wp.array(dtype=wp.int32),
    contact_w: wp.array(dtype=wp.vec3),
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
    seg_implicit_mass: wp.array(dtype=float),
):
    """Forces of the contact in one buffer slot (see ``contact_forces``)."""
    kind = contact_kind[slot]
    ia = contact_a[slot]
    ib = contact_b[slot]
    w = contact_w[slot]

    k = contact_stiffness
    xa = wp.vec3()
    xb = wp.vec3()
    va = wp.vec3()
    vb = wp.vec3()
    ta = wp.vec3()
    tb = wp.vec3()
    inv_mass_a = float(0.0)
    inv_mass_b = float(0.0)
    i0 = int(0)
    i1 = int(0)
    i2 = int(0)
    if kind == CONTACT_VERTEX_FACE:
        i0 = strip_indices[3 * ib + 0]
        i1 = strip_indices[3 * ib + 1]
        i2 = strip_indices[3 * ib + 2]
        xa = vertex_positions[ia]
        va = vertex_velocities[ia]
        xb = w[0] * vertex_positions[i0] + w[1] * vertex_positions[i1] + w[2] * vertex_positions[i2]
        vb = w[0] * vertex_velocities[i0] + w[1] * vertex_velocities[i1] + w[2] * vertex_velocities[i2]
        ta = vertex_tangent(ia, seg_per_strand, vertex_positions)
        tb = strip_face_direction(ib, seg_per_strand, tri_strands, vertex_positions)
        k = contact_stiffness * tri_stiffness_scale[ib]
        inv_mass_a = 1.0 / seg_mass[vertex_segment(ia, seg_per_strand)]
        # sum w_i / m_i bounds the face point's response sum w_i^2 / m_i from above, also when two of the
        # triangle's vertices lie on one segment, so the friction cap below stays on the safe side.
        inv_mass_b = (
            w[0] / seg_mass[vertex_segment(i0, seg_per_strand)]
            + w[1] / seg_mass[vertex_segment(i1, seg_per_strand)]
            + w[2] / seg_mass[vertex_segment(i2, seg_per_strand)]
        )
    else:
        va0 = ia + ia // seg_per_strand
        vb0 = ib + ib // seg_per_strand
        xa = wp.lerp(vertex_positions[va0], vertex_positions[va0 + 1], w[0])
        xb = wp.lerp(vertex_positions[vb0], vertex_positions[vb0 + 1], w[1])
        va = wp.lerp(vertex_velocities[va0], vertex_velocities[va0 + 1], w[0])
        vb = wp.lerp(vertex_velocities[vb0], vertex_velocities[vb0 + 1], w[1])
        ta = wp.normalize(vertex_positions[va0 + 1] - vertex_positions[va0])
        tb = wp.normalize(vertex_positions[vb0 + 1] - vertex_positions[vb0])
        inv_mass_a = 1.0 / seg_mass[ia]
        inv_mass_b = 1.0 / seg_mass[ib]

    delta = xa - xb
    dist = wp.length(delta)
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
    align = 1.0 - wp.abs(wp.dot(ta, tb))
    k_eff = k * align
    c_eff = contact_damping * align
    vrel = va - vb
    vn = wp.dot(vrel, n)
    fn = k_eff * (contact_threshold - dist) - c_eff * vn
    if fn <= 0.0:
        return
    f = fn * n

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
    extra = h * h * k_eff + h * c_eff
    if kind == CONTACT_VERTEX_FACE:
        add_wrench(vertex_segment(ia, seg_per_strand), seg_per_strand, point, f, extra,
                   vertex_positions, seg_force, seg_torque, seg_implicit_mass)
        # Each face vertex takes its share at its own position shifted by (point - xb): the shares then sum to
        # -f at the common point, with no net torque.
        shift = point - xb
        add_wrench(vertex_segment(i0, seg_per_strand), seg_per_strand, vertex_positions[i0] + shift, -w[0] * f,
                   w[0] * extra, vertex_positions, seg_force, seg_torque, seg_implicit_mass)
        add_wrench(vertex_segment(i1, seg_per_strand), seg_per_strand, vertex_positions[i1] + shift, -w[1] * f,
                   w[1] * extra, vertex_positions, seg_force, seg_torque, seg_implicit_mass)
        add_wrench(vertex_segment(i2, seg_per_strand), seg_per_strand, vertex_positions[i2] + shift, -w[2] * f,
                   w[2] * extra, vertex_positions, seg_force, seg_torque, seg_implicit_mass)
    else:
        add_wrench(ia, seg_per_strand, point, f, extra, vertex_positions, seg_force, seg_torque, seg_implicit_mass)
        add_wrench(ib, seg_per_strand, point, -f, extra, vertex_positions, seg_force, seg_torque, seg_implicit_mass)


@wp.kernel
def contact_forces(
    # Model:
    seg_per_strand: int,
    seg_mass: wp.array(dtype=float),
    strip_indices: wp.array(dtype=wp.int32),
    tri_strands: wp.array(dtype=wp.vec2i),
    tri_stiffness_scale: wp.array(dtype=float),
    contact_threshold: float,
    contact_stiffness: float,
    contact_damping: float,
    contact_friction: float,
    contact_slip_velocity: float,
    contact_capacity: int,
    thread_count: int,
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    # Control:
    dt: wp.array(dtype=float),
    # Scratch:
    contact_kind: wp.array(dtype=wp.int32),
    contact_a: wp.array(dtype=wp.int32),
    contact_b: wp.array(dtype=wp.int32),
    contact_w: wp.array(dtype=wp.vec3),
    contact_counter: wp.array(dtype=wp.int32),
    # Out:
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
    seg_implicit_mass: wp.array(dtype=float),
):
    """Each of ``thread_count`` threads takes every thread_count-th stored contact: repulsion, normal damping and
    regularised Coulomb friction.

    Adds +F to side a and -F to side b (shared by barycentric weight among a face's vertices) at the midpoint of the
    closest points (``seg_force`` [N], ``seg_torque`` [N m] about segment origins, world), and ``h^2 k + h c`` [kg]
    (lever-scaled) to ``seg_implicit_mass``. Friction is capped so one explicit step cannot reverse the slip.
    """
    # A fixed thread count strides over however many contacts this step found (the count is only on the device).
    slot = wp.tid()
    count = wp.min(contact_counter[0], contact_capacity)
    h = dt[0]
    while slot < count:
        contact_force(
            slot, seg_per_strand, seg_mass, strip_indices, tri_strands, tri_stiffness_scale, contact_threshold,
            contact_stiffness, contact_damping, contact_friction, contact_slip_velocity, vertex_positions,
            vertex_velocities, h, contact_kind, contact_a, contact_b, contact_w, seg_force, seg_torque,
            seg_implicit_mass,
        )
        slot += thread_count
