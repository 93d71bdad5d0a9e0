"""Dense hair: interpolation of guide strands and Hermite densification (DESIGN.md §4.5).

Both kernels run once per output frame, one thread per output vertex, and allocate nothing.
Vertex arrays are flat: strand ``d`` owns vertices ``d * (S + 1) + k`` (``k = 0`` at the root) and
Hermite samples ``d * P + m`` with ``P = M * S + 1``.

``dense_interpolate`` is affine in the guide vertices: every dense vertex is a fixed convex
combination of guide vertices plus a per-strand offset that is constant in the head frame. Its
velocity is therefore the same combination of guide velocities plus ``omega x (R offset)``; the
kernel computes either, selected by ``velocity``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


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
    tid = wp.tid()
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
    tid = wp.tid()
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
