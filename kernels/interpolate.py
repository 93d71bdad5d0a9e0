"""Dense hair: interpolation of guide strands and Hermite densification (DESIGN.md §4.5).

Both kernels run once per output frame, one thread per output vertex, and allocate nothing.
Vertex arrays are flat: strand ``d`` owns vertices ``d * (S + 1) + k`` (``k = 0`` at the root) and
Hermite samples ``d * P + m`` with ``P = M * S + 1``.

``dense_interpolate`` is affine in the guide vertices: every dense vertex is a fixed convex
combination of guide vertices plus a per-strand offset that is constant in the head frame. Its
velocity is therefore the same combination of guide velocities plus ``omega x (R offset)``; the
kernel computes either, selected by ``velocity``.

``dense_push_out`` is the optional last pass over the interpolated vertices (before Hermite): a
vertex inside a body collider or within its contact layer is lifted to ``thickness`` above it and
the rest of the strand follows with its segment lengths kept (seed: strand-object collision). The
collider geometry is ``hairwarp.kernels.body_collision``'s, the same the guides collide with.
"""

import warp as wp

from hairwarp.kernels.body_collision import (
    LIPSCHITZ_SLOP,
    PUSH_ITERATIONS,
    TINY_LENGTH,
    UNBOUNDED,
    ColliderShapes,
    _lift_on_sphere,
    shape_motion,
    shape_surface,
)

wp.set_module_options({"enable_backward": False})

# A lifted vertex counts as clear of a contact layer when it is at most this far below the layer's top
# [m]: float32 rounding of metre-sized coordinates and of the re-queried distance (a convex surface
# needs one lift; a pass that only fixes rounding would move the vertex by less than this).
LAYER_TOLERANCE = wp.constant(1.0e-6)


@wp.func
def _guide_point(guide_x: wp.array(dtype=wp.vec3), guide: int, seg_per_strand: int, j: int, t: float) -> wp.vec3:
    """Point at parameter ``j + t`` of a guide's polyline (vertex index units, ``0 <= t <= 1``)."""
    base = guide * (seg_per_strand + 1) + j
    return (1.0 - t) * guide_x[base] + t * guide_x[base + 1]


@wp.func
def hermite_point(p0: wp.vec3, m0: wp.vec3, p1: wp.vec3, m1: wp.vec3, t: float) -> wp.vec3:
    """Cubic Hermite segment ``p(t)`` on ``[0, 1]`` with end points ``p0, p1`` and tangents ``m0, m1``."""
    t2 = t * t
    t3 = t2 * t
    return (2.0 * t3 - 3.0 * t2 + 1.0) * p0 + (t3 - 2.0 * t2 + t) * m0 + (-2.0 * t3 + 3.0 * t2) * p1 + (t3 - t2) * m1


@wp.kernel
def dense_interpolate(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    dense_guide_index: wp.array(dtype=wp.vec4i),
    dense_guide_weight: wp.array(dtype=wp.vec4),
    dense_length_scale: wp.array(dtype=wp.float32),
    dense_clump_guide: wp.array(dtype=wp.int32),
    dense_root_offset: wp.array(dtype=wp.vec3),
    dense_tip_offset: wp.array(dtype=wp.vec3),
    clumping: float,
    apply_offsets: int,
    # State in:
    guide_x: wp.array(dtype=wp.vec3),
    velocity: int,
    # Control:
    head_xform: wp.array(dtype=wp.transform),
    head_velocity: wp.array(dtype=wp.spatial_vector),
    # Out:
    dense_x_out: wp.array(dtype=wp.vec3),
):
    """One thread per dense vertex: weighted guide vertices at the strand's scaled arc parameter [m, world].

    Writes ``dense_x_out`` (D*(S+1)); with ``velocity = 1`` ``guide_x`` holds guide velocities and the
    result is the dense velocity [m/s, world]. Length scale, clumping and head-frame offsets as in ``DenseHair``.
    """
    tid = tid_offset + wp.tid()
    n = seg_per_strand + 1
    strand = tid / n
    k = tid - strand * n

    # Length variation re-parameterises by arc length: vertex k sits at guide parameter u = s k on
    # the guides' polylines, so a shorter strand follows the guides' shape with spacing s * L <= L.
    u = dense_length_scale[strand] * float(k)
    j = wp.min(int(u), seg_per_strand - 1)
    t = wp.min(u - float(j), 1.0)

    idx = dense_guide_index[strand]
    w = dense_guide_weight[strand]
    x = w[0] * _guide_point(guide_x, idx[0], seg_per_strand, j, t)
    for i in range(1, 4):
        if w[i] != 0.0:
            x = x + w[i] * _guide_point(guide_x, idx[i], seg_per_strand, j, t)

    # Growth profile: 0 at the root, 1 at the strand's own tip.
    f = float(k) / float(seg_per_strand)
    if clumping > 0.0:
        target = _guide_point(guide_x, dense_clump_guide[strand], seg_per_strand, j, t)
        x = x + (clumping * f) * (target - x)

    if apply_offsets != 0:
        xf = head_xform[0]
        offset = wp.transform_vector(xf, dense_root_offset[strand] + f * dense_tip_offset[strand])
        if velocity != 0:
            # d/dt (R o) = omega x (R o) for an offset o fixed in the head frame.
            x = x + wp.cross(wp.spatial_top(head_velocity[0]), offset)
        else:
            x = x + offset
    dense_x_out[tid] = x


@wp.kernel
def hermite_samples(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    samples_per_segment: int,
    # State in:
    dense_x: wp.array(dtype=wp.vec3),
    # Out:
    curve_x_out: wp.array(dtype=wp.vec3),
):
    """One thread per output sample: cubic Hermite point with Catmull-Rom tangents (seed: dense hair).

    Writes ``curve_x_out`` (D*(M*S+1)); sample ``m = M*k + r`` lies at ``t = r/M`` of segment ``k``, the
    last one at the tip, so every input vertex is reproduced exactly. Units and frame of ``dense_x``.
    """
    tid = tid_offset + wp.tid()
    points = samples_per_segment * seg_per_strand + 1
    strand = tid / points
    m = tid - strand * points
    seg = m / samples_per_segment
    r = m - seg * samples_per_segment
    base = strand * (seg_per_strand + 1)

    if seg == seg_per_strand or r == 0:
        curve_x_out[tid] = dense_x[base + seg]
        return

    p0 = dense_x[base + seg]
    p1 = dense_x[base + seg + 1]
    # Catmull-Rom tangents m_k = (p_{k+1} - p_{k-1}) / 2, one-sided differences at the two ends.
    if seg == 0:
        m0 = p1 - p0
    else:
        m0 = 0.5 * (p1 - dense_x[base + seg - 1])
    if seg + 1 == seg_per_strand:
        m1 = p1 - p0
    else:
        m1 = 0.5 * (dense_x[base + seg + 2] - p0)
    t = float(r) / float(samples_per_segment)
    curve_x_out[tid] = hermite_point(p0, m0, p1, m1, t)


@wp.kernel
def dense_push_out(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    shapes: ColliderShapes,
    # Control:
    collider_xform: wp.array(dtype=wp.transform),
    collider_velocity: wp.array(dtype=wp.spatial_vector),
    head_xform: wp.array(dtype=wp.transform),
    head_velocity: wp.array(dtype=wp.spatial_vector),
    # Scratch:
    push_counts: wp.array(dtype=wp.int32),
    # Out (read and updated in place):
    dense_x: wp.array(dtype=wp.vec3),
):
    """One thread per dense strand: lift vertices 1..S out of the colliders' contact layers [m, world].

    A vertex closer than ``thickness`` (or inside) turns on the sphere of its segment about the previous
    vertex until it is ``thickness`` above the surface; where that sphere cannot reach so far it is put at
    the closest surface point plus ``thickness`` along the normal (that one segment changes length). Later
    vertices follow by the seed's rule, ``p'_{k+1} = p'_k + L_k (p_{k+1} - p'_k) / |p_{k+1} - p'_k|``.
    Rewrites ``dense_x`` of strands that moved only; adds (vertices lifted, vertices projected) to
    ``push_counts``.
    """
    strand = tid_offset + wp.tid()
    base = strand * (seg_per_strand + 1)
    X_head = head_xform[0]
    V_head = head_velocity[0]

    moved = int(0)
    lifted = int(0)
    projected = int(0)
    # Signed distances are 1-Lipschitz: ``clearance`` bounds the previous vertex's distance to every
    # collider from below, so one segment further the bound drops by the segment length at most. Far
    # vertices skip the queries, and a mesh query that finds nothing within the layer knows that a vertex
    # which cannot be that deep is outside (no ray). The root is not queried: vertex 1 starts from no bound.
    # Queries reach just past the layer: wider ones cost more than the rays they save (measured: 1.8x with
    # one more segment of reach, 20k strands on the default head).
    clearance = float(-UNBOUNDED)
    p_prev_old = dense_x[base]
    p_prev = p_prev_old
    for k in range(1, seg_per_strand + 1):
        p_old = dense_x[base + k]
        length = wp.length(p_old - p_prev_old)
        p = p_old
        if moved != 0:
            u = p_old - p_prev
            ul = wp.length(u)
            if ul > TINY_LENGTH:
                p = p_prev + (length / ul) * u
        bound = clearance - length - LIPSCHITZ_SLOP
        clearance = float(UNBOUNDED)
        pushed = int(0)
        for c in range(shapes.count):
            thickness = shapes.thickness[c]
            if bound >= thickness:
                clearance = wp.min(clearance, bound)
                continue
            max_dist = thickness + LIPSCHITZ_SLOP
            outside_known = int(0)
            if bound > -max_dist:
                outside_known = 1
            X, _vel = shape_motion(shapes, c, collider_xform, collider_velocity, X_head, V_head)
            X_inv = wp.transform_inverse(X)
            x_local = wp.transform_point(X_inv, p)
            s = shape_surface(shapes, c, x_local, max_dist, outside_known)
            if s.found == 0 or s.distance >= thickness:
                clearance = wp.min(clearance, s.distance)
                continue
            p_prev_local = wp.transform_point(X_inv, p_prev)
            for _it in range(PUSH_ITERATIONS):
                x_local = _lift_on_sphere(p_prev_local, length, x_local, s.point, s.normal, thickness)
                s = shape_surface(shapes, c, x_local, max_dist, 0)
                if s.found == 0 or s.distance >= thickness - LAYER_TOLERANCE:
                    break
            if s.found != 0 and s.distance < thickness - LAYER_TOLERANCE:
                # Out of the segment's reach (the previous vertex is deep, e.g. a root under the surface).
                x_local = s.point + thickness * s.normal
                s.distance = thickness
                projected += 1
            else:
                lifted += 1
            p = wp.transform_point(X, x_local)
            moved = 1
            pushed = 1
            # The bound held where the vertex was; the colliders after this one start from none.
            bound = -UNBOUNDED
            clearance = wp.min(clearance, s.distance)
        if pushed != 0 and shapes.count > 1:
            # Distances to the colliders queried before the push are stale.
            clearance = -UNBOUNDED
        if moved != 0:
            dense_x[base + k] = p
        p_prev = p
        p_prev_old = p_old
    if lifted != 0:
        wp.atomic_add(push_counts, 0, lifted)
    if projected != 0:
        wp.atomic_add(push_counts, 1, projected)
