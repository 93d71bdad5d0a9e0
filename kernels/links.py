"""Static links: breakable zero-rest-length spring-dampers between segments of different strands.

Seed slides, "Static Links": ``f = sum_i [k_s |l_i| - k_d (v_i . l_i) / |l_i|] l_i / |l_i|``. A link joins a
point of segment ``a`` (its closest point to ``b`` at rest, plus the rest offset ``r0``) to the closest point on
segment ``b``; at rest the two coincide, so ``l = x_b - x_a'`` is zero there (DESIGN §4.3).

The rest offset follows segment ``a`` without its twist: ``r0`` and a's rest axis ``d0`` are kept in the head
frame, and ``x_a' = X_a (0, 0, -f_a L_a) + R_min(R_head d0 -> d_a) R_head r0``, with ``R_min`` the least rotation
between the two axes. So the offset turns with the head and with every bend of ``a``, but not with a's spin about
its own axis, which nothing in a link holds (the vertex velocities do not show spin, and a thin segment's spin
inertia is tiny): carried by a's full frame, a drifting twist swung the offset around the strand and dragged its
neighbours out sideways after a fast head turn. The link's energy then does not depend on that spin. As ``a`` bends
out of the plane of ``d0`` and ``d`` the least rotation turns about ``d`` too, so the offset end moves by
``-(w . g)(d x o)`` besides ``w x o`` (``w`` a's angular velocity across its axis, ``o`` the turned offset,
``g = (d0' - (d0' . d) d) / (1 + d0' . d)``, ``d0'`` the rest axis in the world: ``offset_twist``), and the torque on
``a`` is the force's moment without its component along a's axis plus ``-g (f . (d x o))``: the gradient of the links'
energy in a's turn (``tests/test_links.py``, against finite differences of the energy). Every pass takes the term:
the free step's force and its end's velocity, and the response's sweeps, in the ends' velocities and the blocks
``J^T P J`` of the end's Jacobian ``J = -[r]x - m g^T`` (``kernels.sweeps.link_sweep``). Left out until 2026-12-07,
it was 0.9 % (``long_hair``, frame 30) and 2.1 % (``fast_turn``, frame 18) of the links' torque summed over links,
6 % and 15 % at the 90th percentile of links. The head rotation is the root segment's world rotation times its
joint's inverse. The force acts along ``l`` at both ends: no net force, and no net torque but that spin component
and the twist's term, which the head takes (the offset is carried in its frame).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

# Below this length [m] (well under float32 resolution of hair coordinates) the direction of l is
# round-off, so the damping term, which acts along that direction, is left out.
LINK_MIN_LENGTH = wp.constant(1.0e-7)

#: Longest step [s] at which a link solved after the free step breaks within the step, where the sweeps' answer
#: carries its ends past its break length (``link_response_ends``, ``hairwarp.Solver``): 1/220 s, where the scenes'
#: ``response = "auto"`` hands over to the forms of long steps (8 substeps of 30 fps and more). Longer steps take
#: their breaks again at ``links.break_step`` (1/120 s) instead.
BREAK_SOLVED_STEP = wp.constant(1.0 / 220.0)

# Largest lever scale of an implicit mass: a spring at the far end of its segment, (L / (L/2))^2.
MAX_LEVER_SCALE = wp.constant(4.0)


@wp.func
def seg_first_vertex(seg: int, seg_per_strand: int) -> int:
    """Index of vertex k (the segment origin) of segment ``seg = g*S + k`` in the ``G*(S+1)`` arrays."""
    return seg + seg // seg_per_strand


@wp.func
def seg_angular_velocity(seg: int, seg_per_strand: int, vertex_positions: wp.array(dtype=wp.vec3),
                         vertex_velocities: wp.array(dtype=wp.vec3)) -> wp.vec3:
    """Angular velocity [rad/s, world] of segment ``seg`` across its axis, from its two vertex velocities
    (``seg_point_velocity``)."""
    v = seg_first_vertex(seg, seg_per_strand)
    d = vertex_positions[v + 1] - vertex_positions[v]
    return wp.cross(d, vertex_velocities[v + 1] - vertex_velocities[v]) / wp.max(wp.dot(d, d), 1.0e-20)


@wp.func
def seg_point_velocity(
    seg: int,
    seg_per_strand: int,
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    p: wp.vec3,
) -> wp.vec3:
    """Velocity [m/s] of the world point ``p`` moving rigidly with segment ``seg``.

    The angular velocity is the part perpendicular to the segment, ``w = d x (v1 - v0) / |d|^2``, the part
    that the two vertex velocities determine; spin about the segment's own axis is not seen.
    """
    v = seg_first_vertex(seg, seg_per_strand)
    w = seg_angular_velocity(seg, seg_per_strand, vertex_positions, vertex_velocities)
    return vertex_velocities[v] + wp.cross(w, p - vertex_positions[v])


@wp.func
def lever_scaled_mass(extra_mass: float, arm: wp.vec3, half_length: float) -> float:
    """Implicit mass [kg] to put at a segment's centre of mass for a spring acting at ``arm`` from its origin.

    DESIGN §4.1 adds ``h^2 k + h c`` at the spring's point; the solver takes one mass at the centre of mass
    (L/2 from the origin). Scaled by ``(|arm| / (L/2))^2``, between 1 and ``MAX_LEVER_SCALE``, it gives at least the
    inertia about the segment's joint that the mass at a point of the segment would, so springs near a segment's tip
    are not under-treated by up to a factor of four. The hair contacts use it (their points lie on their segments);
    links solve their springs implicitly instead (``link_forces``).
    """
    return extra_mass * wp.clamp(wp.dot(arm, arm) / (half_length * half_length), 1.0, MAX_LEVER_SCALE)


@wp.func
def min_rotation(a: wp.vec3, b: wp.vec3) -> wp.quat:
    """The least rotation taking unit vector a to unit vector b (a half turn about an axis normal to a if opposite)."""
    c = wp.cross(a, b)
    w = 1.0 + wp.dot(a, b)
    if w < 1.0e-6:
        c = wp.cross(a, wp.vec3(1.0, 0.0, 0.0))
        if wp.length_sq(c) < 1.0e-6:
            c = wp.cross(a, wp.vec3(0.0, 1.0, 0.0))
        w = 0.0
    return wp.normalize(wp.quat(c[0], c[1], c[2], w))


#: Largest ``|g|`` of the offset transport's twist term (``offset_twist``): ``tan(theta / 2)`` of a segment turned by
#: ``theta`` from its rest axis in the head frame, exact to a quarter turn (``|g| = 1``) and held there beyond, where
#: it grows without bound toward the half turn at which the least rotation has no limit.
TWIST_LEVER = wp.constant(1.0)


@wp.func
def offset_twist(rest_axis: wp.vec3, axis: wp.vec3) -> wp.vec3:
    """The twist lever ``g`` of a link's offset end on a segment with world axis ``axis`` and world rest axis
    ``rest_axis`` (its rest axis turned by the head): ``(d0 - (d0 . d) d) / (1 + d0 . d)``, at most ``TWIST_LEVER``
    long. As the segment turns by ``w`` across its axis the least rotation ``R_min(d0 -> d)`` turns by
    ``w - (w . g) d``, so the offset ``o`` it carries moves by ``w x o - (w . g)(d x o)`` (module docstring)."""
    c = wp.dot(rest_axis, axis)
    g = (rest_axis - c * axis) / wp.max(1.0 + c, 1.0e-6)
    length = wp.length(g)
    if length > TWIST_LEVER:
        g = g * (TWIST_LEVER / length)
    return g


@wp.func
def offset_end_velocity(seg: int, seg_per_strand: int, vertex_positions: wp.array(dtype=wp.vec3),
                        vertex_velocities: wp.array(dtype=wp.vec3), p: wp.vec3, g: wp.vec3, m: wp.vec3) -> wp.vec3:
    """Velocity [m/s] of a link's offset end at ``p`` on segment ``seg``: the segment's rigid field at ``p``
    (``seg_point_velocity``) and the transport's twist, ``-(w . g) m``, ``m = d x o`` (``offset_twist``)."""
    v = seg_first_vertex(seg, seg_per_strand)
    w = seg_angular_velocity(seg, seg_per_strand, vertex_positions, vertex_velocities)
    return vertex_velocities[v] + wp.cross(w, p - vertex_positions[v]) - wp.dot(w, g) * m


@wp.func
def point_inverse_mass(seg: int, r: wp.vec3, seg_mass: wp.array(dtype=float), seg_length: wp.array(dtype=float)):
    """An upper bound [1/kg] of the inverse mass a link meets at ``r`` from segment ``seg``'s centre of mass: the free
    segment's ``1/m + |r|^2 / (m L^2 / 12)``, the spin about its own axis left out as the link's torque leaves it out.
    The segment's joints and the rest of its strand only add inertia.

    A segment's several links each take the bound whole, not a share of it (mass splitting): the strand's inertia
    beyond the free segment's gives the margin. Measured on ``long_hair`` (a segment carries about six links): with
    shares the links were 1.5-2.8x softer at the shipped step and the style came back 11 % less far after a gust;
    without them no link breaks at one step a frame."""
    L = seg_length[seg]
    return (1.0 + 12.0 * wp.dot(r, r) / (L * L)) / seg_mass[seg]


@wp.func
def damper_cap(h: float, damping: float, spring: float, weight_a: float, weight_b: float) -> float:
    """The factor on the dampers of the links between segments a and b in the free step: 1 while the step ``h``
    times the links' whole damper over it (``spring`` + ``damping``: the stiffness's own damper of the step, ``h k``
    with backward-Euler springs, 0 with explicit ones, and the damping c [N s/m]) times each segment's damper weight
    (``StaticLinks.seg_damper_weight``: its links' scales times their ends' inverse-mass bounds) stays within 1, else
    what brings the larger to 1, taken from the damping alone (the stiffness keeps its whole force; the damping none
    where the stiffness's own damper passes 1).

    Each link's damper, solved alone, takes at most its own ends' relative velocity in the step, but the links that
    share a segment each take theirs from the same segment: where they take more than its velocity together they
    reverse it, and the dampers put energy into the hair. The Jacobi bound, ``h (h k + c) sum W <= 1`` per segment,
    keeps every damper dissipative and leaves every link whose segments stay within it exactly as it was.
    ``character``'s links alone, falling from the groom with the head still: uncapped, +1.1 mJ in a frame (at 0.01
    N s/m +4.4 mJ); with the damping alone counted (``h c sum W``), +0.34 mJ still, drawn with the seed it ships,
    where the stiffness's damper adds 0.3-0.6 of the bound; counted whole, it falls in every frame."""
    weight = wp.max(weight_a, weight_b)
    spring_load = h * spring * weight
    damper_load = h * damping * weight
    if spring_load + damper_load > 1.0:
        return wp.max(1.0 - spring_load, 0.0) / damper_load
    return 1.0


@wp.kernel
def segment_transport(
    # Model:
    seg_per_strand: int,
    seg_rest_axis: wp.array(dtype=wp.vec3),
    # State in:
    seg_xform: wp.array(dtype=wp.transform),
    joint_q: wp.array(dtype=wp.quat),
    # Out:
    seg_transport: wp.array(dtype=wp.quat),
):
    """One thread per segment: the rotation ``R_min(R_head d0 -> d) R_head`` that carries a rest offset from the head
    frame to the segment's twist-free frame (``d0`` its rest axis, ``d`` its world axis; the head rotation is the root
    segment's world rotation times its joint's inverse)."""
    seg = wp.tid()
    root = (seg // seg_per_strand) * seg_per_strand
    head = wp.transform_get_rotation(seg_xform[root]) * wp.quat_inverse(joint_q[root])
    axis = wp.quat_rotate(wp.transform_get_rotation(seg_xform[seg]), wp.vec3(0.0, 0.0, -1.0))
    seg_transport[seg] = min_rotation(wp.quat_rotate(head, seg_rest_axis[seg]), axis) * head


@wp.func
def link_ends(
    a: int,
    b: int,
    frac_a: float,
    frac_b: float,
    rest_offset: wp.vec3,
    seg_length: wp.array(dtype=float),
    seg_xform: wp.array(dtype=wp.transform),
    seg_transport: wp.array(dtype=wp.quat),
):
    """World attachment points ``(x_a', x_b)`` of a link: ``x_a' = X_a (0, 0, -f_a L_a) + T_a r0``, with ``T_a`` from
    ``segment_transport``."""
    xa = wp.transform_point(seg_xform[a], wp.vec3(0.0, 0.0, -frac_a * seg_length[a])) + wp.quat_rotate(
        seg_transport[a], rest_offset)
    xb = wp.transform_point(seg_xform[b], wp.vec3(0.0, 0.0, -frac_b * seg_length[b]))
    return xa, xb


@wp.func
def ends_relative_velocity(v0: wp.vec3, w_a: wp.vec3, x0: wp.vec3, xa: wp.vec3, b: int, seg_per_strand: int,
                           vertex_positions: wp.array(dtype=wp.vec3), vertex_velocities: wp.array(dtype=wp.vec3),
                           xb: wp.vec3):
    """Velocity [m/s] of a link's end ``xa`` on segment a (its rigid field: ``v0`` at its first vertex ``x0``,
    angular velocity ``w_a``) relative to its end ``xb`` on segment ``b`` (``seg_point_velocity``)."""
    return v0 + wp.cross(w_a, xa - x0) - seg_point_velocity(b, seg_per_strand, vertex_positions, vertex_velocities,
                                                            xb)


@wp.kernel
def link_forces(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    seg_length: wp.array(dtype=float),
    seg_mass: wp.array(dtype=float),
    seg_rest_axis: wp.array(dtype=wp.vec3),
    seg_link_start: wp.array(dtype=wp.int32),
    link_seg_b: wp.array(dtype=wp.int32),
    link_frac_a: wp.array(dtype=float),
    link_frac_b: wp.array(dtype=float),
    link_rest_offset: wp.array(dtype=wp.vec3),
    link_stiffness: float,
    link_damping: float,
    link_scale: wp.array(dtype=float),
    seg_damper_weight: wp.array(dtype=float),
    link_break_length: float,
    implicit_springs: int,
    # State in:
    seg_xform: wp.array(dtype=wp.transform),
    joint_q: wp.array(dtype=wp.quat),
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    # Control:
    dt: wp.array(dtype=float),
    link_b_slot: wp.array(dtype=wp.int32),
    response: int,
    warm_start: int,
    link_warm: wp.array(dtype=wp.vec3),
    # Out:
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
    link_broken: wp.array(dtype=wp.int32),
    link_broken_total: wp.array(dtype=wp.int32),
    b_force: wp.array(dtype=wp.vec3),
    b_torque: wp.array(dtype=wp.vec3),
    link_point_a: wp.array(dtype=wp.vec3),
    link_point_b: wp.array(dtype=wp.vec3),
    link_twist_g: wp.array(dtype=wp.vec3),
    link_twist_m: wp.array(dtype=wp.vec3),
):
    """One thread per segment a: the seed's spring-dampers of the links that hang their rest offset on a (links
    ``seg_link_start[a]`` to ``seg_link_start[a + 1] - 1``, sorted by a).

    A link stretched past ``link_break_length`` [m] breaks here for good, before it acts (``link_broken[link] = 1``,
    counted once in ``link_broken_total[0]``, as ``link_break`` does), so a step pays one pass over the links (with
    ``response`` a link also breaks within the step: ``link_response_ends``).
    Otherwise it adds +f at x_a' to segment a: to ``seg_force`` [N] and ``seg_torque`` [N m] about a's origin, world,
    the moment less its spin about a's axis and with the offset transport's twist term ``-g (m . f)``
    (``offset_twist``), so that the torque is the link energy's gradient in a's turn; the end's velocity takes the
    term's ``-(w . g) m`` too. With ``implicit_springs`` the force is the link's backward-Euler force over the
    step, ``f = k (l - h u') - c (n . u') n`` with the end-of-step relative velocity ``u' = u + h W f``, solved per
    link: ``W`` bounds the inverse masses of the two ends (``point_inverse_mass``), so however stiff the link and
    long the step, f never exceeds what stops the ends' relative motion, and the link adds no inertia to the common
    motion of the hair it ties. Without, f is the seed's explicit force. With ``response`` the link adds no force
    here (with ``warm_start`` its force of the last step, ``link_warm``): its ends go to ``link_point_a``,
    ``link_point_b``, its offset end's twist to ``link_twist_g``, ``link_twist_m``, and the response solves its force
    over the step inside the strands' dynamics. Segment b's
    share (-f at x_b) goes to slot ``link_b_slot[link]`` of ``b_force``, ``b_torque`` (zero for a broken link),
    which ``link_gather`` adds to b: every segment is written by its own thread only, so the sums are the same bits
    however the segments are split between CPU threads. The thread computes a's frame, its twist-free transport
    (``segment_transport``) and its velocity field once for all its links, and adds a's sums once.
    """
    a = tid_offset + wp.tid()
    first = seg_link_start[a]
    last = seg_link_start[a + 1]
    if first == last:
        return
    xf_a = seg_xform[a]
    rot_a = wp.transform_get_rotation(xf_a)
    oa = wp.transform_get_translation(xf_a)
    axis_a = wp.quat_rotate(rot_a, wp.vec3(0.0, 0.0, -1.0))
    root = (a // seg_per_strand) * seg_per_strand
    head = wp.transform_get_rotation(seg_xform[root]) * wp.quat_inverse(joint_q[root])
    rest_axis_a = wp.quat_rotate(head, seg_rest_axis[a])
    transport = min_rotation(rest_axis_a, axis_a) * head
    twist_a = offset_twist(rest_axis_a, axis_a)
    length_a = seg_length[a]
    # a's rigid velocity field from its two vertices (seg_point_velocity, hoisted out of the loop)
    va_vertex = seg_first_vertex(a, seg_per_strand)
    x0 = vertex_positions[va_vertex]
    v0 = vertex_velocities[va_vertex]
    w_a = seg_angular_velocity(a, seg_per_strand, vertex_positions, vertex_velocities)
    h = dt[0]
    com_a = oa + (0.5 * length_a) * axis_a
    force_a = wp.vec3()
    torque_a = wp.vec3()
    for link in range(first, last):
        slot = link_b_slot[link]
        b_force[slot] = wp.vec3()
        b_torque[slot] = wp.vec3()
        if link_broken[link] != 0:
            continue
        b = link_seg_b[link]
        xf_b = seg_xform[b]
        offset = wp.quat_rotate(transport, link_rest_offset[link])
        # the offset end's twist lever arm: it moves by -(w . g) m besides w x (xa - x0)
        twist_m = wp.cross(axis_a, offset)
        xa = wp.transform_point(xf_a, wp.vec3(0.0, 0.0, -link_frac_a[link] * length_a)) + offset
        xb = wp.transform_point(xf_b, wp.vec3(0.0, 0.0, -link_frac_b[link] * seg_length[b]))
        l = xb - xa
        length = wp.length(l)
        if length > link_break_length:
            link_broken[link] = 1
            wp.atomic_add(link_broken_total, 0, 1)
            continue

        # this link's k_s and k_d (``StaticLinks.link_scale``)
        k = link_stiffness * link_scale[link]
        hk = h * k
        # k_s |l| l/|l| = k_s l stays defined as l -> 0; the damping term needs a direction.
        f = k * l
        if response != 0:
            # the link's force is the response's, over the step (``link_response_ends``, ``kernels.sweeps``); with
            # ``warm_start`` its force of the last step acts in the free step and the response solves the change
            link_point_a[link] = xa
            link_point_b[link] = xb
            link_twist_g[link] = twist_a
            link_twist_m[link] = twist_m
            if warm_start == 0:
                continue
            f = link_warm[link]
        if response == 0:
            # the damping capped where the segments' dampers together would take more than their velocity in the
            # step (``damper_cap``; the response solves its links' dampers with their strands, and reads none here)
            c = link_damping * link_scale[link] * damper_cap(h, link_damping,
                                                             h * link_stiffness * float(implicit_springs),
                                                             seg_damper_weight[a], seg_damper_weight[b])
            # u = velocity of a's end relative to b's end: the seed's sign, which resists a change of |l|.
            u = ends_relative_velocity(v0, w_a, x0, xa, b, seg_per_strand, vertex_positions, vertex_velocities,
                                       xb) - wp.dot(w_a, twist_a) * twist_m
            if implicit_springs != 0:
                com_b = wp.transform_point(xf_b, wp.vec3(0.0, 0.0, -0.5 * seg_length[b]))
                # a's end at the arm the twist lengthens: its velocity per turn is at most |r| + |g| |m|
                arm_a = xa - com_a
                reach_a = wp.length(arm_a) + wp.length(twist_a) * wp.length(twist_m)
                W = point_inverse_mass(a, reach_a * wp.normalize(arm_a), seg_mass, seg_length) + point_inverse_mass(
                    b, xb - com_b, seg_mass, seg_length)
                # (I + h W (h k I + c n n^T)) f = k l - (h k I + c n n^T) u, along n and across it
                f = f - hk * u
                f_n = wp.vec3()
                if length > LINK_MIN_LENGTH:
                    n = l / length
                    f_n = (wp.dot(f, n) - c * wp.dot(u, n)) * n
                    f = f - wp.dot(f, n) * n
                f = f / (1.0 + h * hk * W) + f_n / (1.0 + h * (hk + c) * W)
            elif length > LINK_MIN_LENGTH:
                n = l / length
                f = f - c * wp.dot(u, n) * n

        ob = wp.transform_get_translation(xf_b)
        tau = wp.cross(xa - oa, f)
        force_a += f
        torque_a += tau - wp.dot(tau, axis_a) * axis_a - wp.dot(twist_m, f) * twist_a
        b_force[slot] = -f
        b_torque[slot] = wp.cross(xb - ob, -f)
    seg_force[a] = seg_force[a] + force_a
    seg_torque[a] = seg_torque[a] + torque_a


@wp.kernel
def link_gather(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_b_start: wp.array(dtype=wp.int32),
    # Scratch:
    b_force: wp.array(dtype=wp.vec3),
    b_torque: wp.array(dtype=wp.vec3),
    # Out:
    seg_force: wp.array(dtype=wp.vec3),
    seg_torque: wp.array(dtype=wp.vec3),
):
    """One thread per segment b: add the shares ``link_forces`` left for b (slots ``seg_b_start[b]`` to
    ``seg_b_start[b + 1] - 1``, its links as side b in link order) to ``seg_force`` [N] and ``seg_torque`` [N m]."""
    b = tid_offset + wp.tid()
    first = seg_b_start[b]
    last = seg_b_start[b + 1]
    if first == last:
        return
    force = wp.vec3()
    torque = wp.vec3()
    for slot in range(first, last):
        force += b_force[slot]
        torque += b_torque[slot]
    seg_force[b] = seg_force[b] + force
    seg_torque[b] = seg_torque[b] + torque


@wp.func
def add_gathered(seg: int, count: int, force: wp.vec3, torque: wp.vec3, mass: float, implicit_springs: int,
                 seg_mass: wp.array(dtype=float), seg_spring_mass: wp.array(dtype=float),
                 seg_force: wp.array(dtype=wp.vec3), seg_torque: wp.array(dtype=wp.vec3),
                 seg_implicit_mass: wp.array(dtype=float)):
    """Add what a gather summed for segment ``seg`` (``count`` entries): the force and torque to its loads, with
    ``implicit_springs`` the spring mass to its ``seg_spring_mass``, passed on as ``add_excess_mass`` does."""
    if count != 0:
        seg_force[seg] = seg_force[seg] + force
        seg_torque[seg] = seg_torque[seg] + torque
    if implicit_springs != 0:
        excess_mass(seg, seg_mass, seg_spring_mass[seg] + mass, seg_spring_mass, seg_implicit_mass)


@wp.func
def excess_mass(seg: int, seg_mass: wp.array(dtype=float), spring_mass: float, seg_spring_mass: wp.array(dtype=float),
                seg_implicit_mass: wp.array(dtype=float)):
    """``add_excess_mass`` for one segment whose springs sum to ``spring_mass`` [kg]."""
    excess = spring_mass - seg_mass[seg]
    if excess > 0.0:
        seg_implicit_mass[seg] = seg_implicit_mass[seg] + excess
    seg_spring_mass[seg] = 0.0


@wp.kernel
def add_excess_mass(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_mass: wp.array(dtype=float),
    # Scratch:
    seg_spring_mass: wp.array(dtype=float),
    # Out:
    seg_implicit_mass: wp.array(dtype=float),
):
    """One thread per segment: add to the solver's implicit mass [kg] the part of the springs' summed
    ``h^2 k + h c`` beyond the segment's own mass, and clear the sum.

    The semi-implicit mass is inertia without weight, and it resists every acceleration, also the common ones of
    linked hair falling or swinging together; spent whole, it slowed the hair of a 400-guide head turn about five
    times. Springs whose ``h^2 k + h c`` stays within the segment's mass are stable explicit (the explicit step
    holds ``h^2 k / m < 4`` and ``h c / m < 2``); beyond it the added mass keeps the ratio at 1.
    """
    seg = tid_offset + wp.tid()
    excess_mass(seg, seg_mass, seg_spring_mass[seg], seg_spring_mass, seg_implicit_mass)


@wp.kernel
def link_break(
    # Model:
    seg_length: wp.array(dtype=float),
    link_seg_a: wp.array(dtype=wp.int32),
    link_seg_b: wp.array(dtype=wp.int32),
    link_frac_a: wp.array(dtype=float),
    link_frac_b: wp.array(dtype=float),
    link_rest_offset: wp.array(dtype=wp.vec3),
    link_break_length: float,
    # State in:
    seg_xform: wp.array(dtype=wp.transform),
    seg_transport: wp.array(dtype=wp.quat),
    # Out:
    link_broken: wp.array(dtype=wp.int32),
    link_broken_total: wp.array(dtype=wp.int32),
):
    """One thread per link: mark the link broken for good once ``|l|`` [m] exceeds the break length.

    Writes ``link_broken[link] = 1`` and counts each newly broken link once in ``link_broken_total[0]``.
    """
    link = wp.tid()
    if link_broken[link] != 0:
        return
    a = link_seg_a[link]
    b = link_seg_b[link]
    xa, xb = link_ends(a, b, link_frac_a[link], link_frac_b[link], link_rest_offset[link], seg_length, seg_xform,
                       seg_transport)
    if wp.length(xb - xa) > link_break_length:
        link_broken[link] = 1
        wp.atomic_add(link_broken_total, 0, 1)


@wp.struct
class LinkEnds:
    """What the links' sweeps read of each link end over a step (``kernels.sweeps.link_sweep``): ``force``, the
    end's force on its own free velocities with the other end still, ``+-(k l) - P v_own`` [N, world]
    (``link_response_ends``); ``arm``, the end's point about its segment's origin in the segment's frame at the
    step's start (written by the step's first sweep); ``axis``, per link, the unit ``n`` of ``P = h k I + c n n^T``
    [world] (zero while the link has no direction); ``twist_g`` and ``twist_m``, per link, the transport's twist of
    its offset end at the step's start, ``g`` and ``m = d x o`` [world] (``offset_twist``; ``link_forces``), and
    ``kept_g``, ``kept_m`` the same in the segment's frame as the step's first sweep kept them beside ``arm``. End
    slots: side a of link ``i`` at ``i``, side b of the link in b slot ``j`` at ``link_count + j`` (``end_slot``)."""

    force: wp.array(dtype=wp.vec3)
    arm: wp.array(dtype=wp.vec3)
    axis: wp.array(dtype=wp.vec3)
    twist_g: wp.array(dtype=wp.vec3)
    twist_m: wp.array(dtype=wp.vec3)
    kept_g: wp.array(dtype=wp.vec3)
    kept_m: wp.array(dtype=wp.vec3)


@wp.func
def end_slot(j: int, a_last: int, b_first: int, link_count: int, b_slot_link: wp.array(dtype=wp.int32)):
    """The ``j``-th end of a segment whose a ends are links ``a_first .. a_last - 1`` and whose b ends are b slots
    ``b_first ..`` (``j`` from ``a_first``): its link, its side (+1 a, -1 b) and its ``LinkEnds`` slot."""
    if j < a_last:
        return j, float(1.0), j
    b = b_first + j - a_last
    return b_slot_link[b], float(-1.0), link_count + b


@wp.func
def link_axis(l: wp.vec3):
    """The unit direction of ``l``, along which a link damps; zero below ``LINK_MIN_LENGTH`` (round-off)."""
    length = wp.length(l)
    if length > LINK_MIN_LENGTH:
        return l / length
    return wp.vec3()


@wp.kernel
def link_response_ends(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    link_stiffness: float,
    link_damping: float,
    link_scale: wp.array(dtype=float),
    # Scratch: the ends the force pass left
    link_point_a: wp.array(dtype=wp.vec3),
    link_point_b: wp.array(dtype=wp.vec3),
    link_broken: wp.array(dtype=wp.int32),
    link_seg_a: wp.array(dtype=wp.int32),
    link_seg_b: wp.array(dtype=wp.int32),
    link_b_slot: wp.array(dtype=wp.int32),
    warm_start: int,
    link_warm: wp.array(dtype=wp.vec3),
    # State: the step's start (positions), the free step's end (velocities)
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    # Control:
    dt: wp.array(dtype=float),
    # 1: ``vertex_velocities`` are the sweeps' answer, linearised at the step's start, and the link's force over the
    # step at them goes to ``link_warm`` instead
    answered: int,
    # With ``answered``: 1 where a link whose ends the answer carries past ``break_length`` [m] breaks in the step
    break_solved: int,
    break_length: float,
    # With ``answered``: > 0, the speed [m/s] by which the force kept for the next free step falls off with the ends'
    # relative speed in the answer, ``1 / (1 + |u'|^2 / s^2)`` of it (``StaticLinks.warm_gate``); 0 keeps it whole
    warm_gate: float,
    # Out:
    ends: LinkEnds,
    # With ``break_solved``: the links broken (``link_broken``, counted in ``link_broken_total[0]``) and, per strand,
    # 1 where one of its links broke (``strand_redo``: stores of 1 only, the same whichever thread stores)
    link_broken_total: wp.array(dtype=wp.int32),
    strand_redo: wp.array(dtype=wp.int32),
):
    """One thread per link: what the sweeps read of its ends over the step (``LinkEnds``): each end's force on its own
    free velocities with the other end still, ``+-(k l) - P v_own`` [N, world], and the link's axis ``n``. With
    ``answered``, after the sweeps: the link's force over the step in their answer, ``k l - P u'`` [N, world, on a's
    end], into ``link_warm``, which the next step's free step takes (``link_forces``, ``warm_start``); zero for a
    broken link.

    The link's force over the step is ``k l - P u'``, ``P = h k I + c n n^T``, ``u'`` the end-of-step velocity of
    a's end relative to b's; the sweeps solve each end with the other held (``kernels.sweeps.link_sweep``), which
    adds ``P v_other`` to the end's own part. With ``warm_start`` the free step took the link's force of the last
    step already (``link_warm``, ``link_forces``), which the ends' parts leave out: the same linear answer, in which
    the free step's body contacts carry the load of the links too (``hairwarp.Solver._warm_start``). (Applied in the
    free step at one step a frame, ``k l`` kicked the hair apart, where a segment's half-dozen links are far stiffer
    than its mass allows explicitly.)

    With ``break_solved`` (steps up to :data:`BREAK_SOLVED_STEP`) a link whose ends the answer carries past its break
    length, ``|l - h u'| > break_length``, breaks within the step: it is marked broken, its force of the step is
    zero, and the strands at its two ends are marked in ``strand_redo``, which the sweeps then solve again without it
    (``hairwarp.Solver._respond``). Held through the step, such a link pulled its ends back with more than it holds
    at its break (up to 2.6 times on the shoulders' nod at 10x) and whipped a tip to 27.6 m/s. A link the answer keeps
    within its break holds, however fast its ends parted at the step's start: a look ahead at those speeds alone
    tore twice the links that fine steps tear in a 3 rev/s spin, whose links slow the parting within the step."""
    link = tid_offset + wp.tid()
    if link_broken[link] != 0:
        if answered != 0:
            link_warm[link] = wp.vec3()
        return
    h = dt[0]
    xa = link_point_a[link]
    xb = link_point_b[link]
    v_a = offset_end_velocity(link_seg_a[link], seg_per_strand, vertex_positions, vertex_velocities, xa,
                              ends.twist_g[link], ends.twist_m[link])
    v_b = seg_point_velocity(link_seg_b[link], seg_per_strand, vertex_positions, vertex_velocities, xb)
    l = xb - xa
    n = link_axis(l)
    k = link_stiffness * link_scale[link]
    if answered != 0:
        u = v_a - v_b
        if break_solved != 0:
            reach = l - h * u
            if wp.dot(reach, reach) > break_length * break_length:
                link_broken[link] = 1
                wp.atomic_add(link_broken_total, 0, 1)
                strand_redo[link_seg_a[link] // seg_per_strand] = 1
                strand_redo[link_seg_b[link] // seg_per_strand] = 1
                link_warm[link] = wp.vec3()
                return
        f = k * l - (h * k) * u - (link_damping * link_scale[link]) * wp.dot(n, u) * n
        if warm_gate > 0.0:
            f = f / (1.0 + wp.dot(u, u) / (warm_gate * warm_gate))
        link_warm[link] = f
        return
    P = (h * k) * wp.identity(n=3, dtype=float) + (link_damping * link_scale[link]) * wp.outer(n, n)
    kl = k * l
    if warm_start != 0:  # the free step took the link's force of the last step (``link_forces``)
        kl = kl - link_warm[link]
    ends.force[link] = kl - P * v_a
    ends.force[link_point_a.shape[0] + link_b_slot[link]] = -kl - P * v_b
    ends.axis[link] = n


@wp.kernel
def link_candidates(
    seg_lower: wp.array(dtype=wp.vec3),
    seg_upper: wp.array(dtype=wp.vec3),
    reach: wp.array(dtype=float),
    seg_strand: wp.array(dtype=wp.int32),
    bvh: wp.uint64,
    capacity: int,
    count: wp.array(dtype=wp.int32),
    cand_a: wp.array(dtype=wp.int32),
    cand_b: wp.array(dtype=wp.int32),
):
    """One thread per segment ``i`` (building the links, ``hairwarp.interactions``): every segment of another strand
    whose box (``seg_lower``, ``seg_upper``; a tree over them) meets ``i``'s grown by ``reach[i]``, appended as a
    pair ``(i, j)``; past ``capacity`` only counted. A segment within ``reach[i]`` of ``i`` has a point in that box,
    so the pairs hold every one; their order is left to the caller."""
    i = wp.tid()
    grow = wp.vec3(reach[i])
    query = wp.bvh_query_aabb(bvh, seg_lower[i] - grow, seg_upper[i] + grow)
    j = int(0)
    while wp.bvh_query_next(query, j):
        if seg_strand[j] != seg_strand[i]:
            slot = wp.atomic_add(count, 0, 1)
            if slot < capacity:
                cand_a[slot] = i
                cand_b[slot] = j
