"""Strand-object collision: signed distances to colliders, push-out, back to joint coordinates.

One thread per strand (``collide_strands``), after integration and forward kinematics. The method is
Chang, Jin & Yu 2002 (seed slides, "Strand-Object collision"): a vertex too close to an object takes the
object's velocity; a vertex inside is moved out and the rest of the strand follows with segment lengths
kept, ``p'_{k+1} = p'_k + L_k (p_{k+1} - p'_k) / |p_{k+1} - p'_k|``, to the tip.

Sign convention of every query here: the signed distance ``d`` is positive outside, negative inside;
the normal ``n`` is the outward unit normal at the closest surface point ``c``, pointing from the
surface towards increasing ``d``, so ``x = c + d n`` for a query point ``x``. Queries run in the
collider's local frame (rigid transforms keep distances); the kernel rotates results to world.

Collider shapes (``ColliderKind``): SPHERE of ``radius`` about the origin; CAPSULE of ``radius`` around
the local z segment ``[-half_height, half_height]``; PLANE z = 0 with +z outward; MESH, a closed
consistently wound triangle mesh (pseudo-normal sign near the surface, a ray farther away, so a vertex
deep inside is found whatever its depth).
"""

import warp as wp

from hairwarp.kernels.articulated import StrandBases, StrandChains, fk_strand
from hairwarp.kernels.types import ColliderKind, Fault

wp.set_module_options({"enable_backward": False})

# Push-out of one vertex against one collider is repeated at most this many times: each pass lifts the
# vertex above the tangent plane at the current closest point; curved or concave surfaces may need more
# than one pass, a plane or a convex body needs one.
PUSH_ITERATIONS = wp.constant(4)

# A pushed-out vertex lands this far above the surface [m] (at most the collider's thickness): clear of
# float32 sign noise at metre-sized coordinates, and no larger than the penetration a push undoes. Pushing
# to the top of the contact layer instead lets a resting vertex sink through the layer under gravity and
# jump back by the whole layer, kicking the rest of the strand every time (tips resting on a shoulder
# jittered by the layer thickness, 2 mm, at 250 mm/s RMS).
PUSH_MARGIN = wp.constant(1.0e-5)

# Collider bits of the per-vertex exemption mask (an int32 per vertex): colliders past this index are
# never exempt.
MAX_EXEMPT_COLLIDERS = wp.constant(31)

# Segment directions and normals are taken from differences shorter than this [m] only through a
# fallback: below it float32 differences at metre-sized coordinates are mostly rounding.
TINY_LENGTH = wp.constant(1.0e-12)

# A distance bound [m] "larger than any": no bound.
UNBOUNDED = wp.constant(1.0e30)

# Slack [m] on the Lipschitz bound of the distance from one vertex to the next: float32 rounding of
# positions and segment lengths at metre-sized coordinates, and of the BVH distances.
LIPSCHITZ_SLOP = wp.constant(1.0e-6)

# Inside test of points away from a mesh surface: one ray, in a direction unlikely to run along the
# edges of modelled (axis-aligned, symmetric) meshes.
RAY_DIRECTION = wp.constant(wp.vec3(0.26726124, 0.53452248, 0.80178373))
RAY_DIRECTION_CHECK = wp.constant(wp.vec3(-0.61736256, 0.46302196, -0.6359828))


@wp.struct
class SurfacePoint:
    """Result of a closest-point query in one frame.

    Attributes:
        found: 1 when ``point`` and ``normal`` are valid; 0 when the query point is outside and farther
            than the query distance (``distance`` then holds that query distance, a lower bound).
        distance: signed distance [m], > 0 outside, < 0 inside.
        point: closest surface point [m].
        normal: outward unit normal at ``point``.
    """

    found: int
    distance: float
    point: wp.vec3
    normal: wp.vec3


@wp.func
def _surface_point(found: int, distance: float, point: wp.vec3, normal: wp.vec3):
    s = SurfacePoint()
    s.found = found
    s.distance = distance
    s.point = point
    s.normal = normal
    return s


@wp.func
def _any_perpendicular(a: wp.vec3):
    """A unit vector perpendicular to the unit vector ``a``."""
    t = wp.cross(wp.vec3(1.0, 0.0, 0.0), a)
    if wp.length_sq(t) < 1.0e-6:
        t = wp.cross(wp.vec3(0.0, 1.0, 0.0), a)
    return wp.normalize(t)


@wp.func
def _min_rotation(a: wp.vec3, b: wp.vec3):
    """Minimal rotation taking unit vector ``a`` to unit vector ``b`` (axis ``a x b``, no twist about ``a``)."""
    d = wp.dot(a, b)
    if d < -0.999999:
        axis = _any_perpendicular(a)
        return wp.quat(axis[0], axis[1], axis[2], 0.0)
    c = wp.cross(a, b)
    return wp.normalize(wp.quat(c[0], c[1], c[2], 1.0 + d))


@wp.func
def sphere_surface(x: wp.vec3, radius: float):
    """Closest point on a sphere of ``radius`` centred at the origin; at the centre the normal is +z."""
    r = wp.length(x)
    n = wp.vec3(0.0, 0.0, 1.0)
    if r > TINY_LENGTH:
        n = x / r
    return _surface_point(1, r - radius, radius * n, n)


# Safeguarded Newton steps of the ellipsoid's closest point: quadratic convergence from a bracket (5 steps on
# average, 15 at most on points near and far), bisection where Newton would leave it.
ELLIPSOID_ITERATIONS = wp.constant(32)


@wp.func
def _ellipsoid_secular(t: float, ay: wp.vec3, a2: wp.vec3):
    """F(t) = sum (a_i y_i / (t + a_i^2))^2 - 1 and dF/dt."""
    r = wp.vec3(ay[0] / (t + a2[0]), ay[1] / (t + a2[1]), ay[2] / (t + a2[2]))
    f = wp.dot(r, r) - 1.0
    df = -2.0 * (r[0] * r[0] / (t + a2[0]) + r[1] * r[1] / (t + a2[1]) + r[2] * r[2] / (t + a2[2]))
    return f, df


@wp.func
def ellipsoid_surface(x: wp.vec3, radii: wp.vec3):
    """Closest point on the ellipsoid of semi-axes ``radii`` centred at the origin: signed distance (negative
    inside), point, outward normal.

    The closest point to y = |x| (componentwise) is z_i = a_i^2 y_i / (t + a_i^2), with t the root of
    F(t) = sum (a_i y_i / (t + a_i^2))^2 - 1, which decreases for t > -min a_i^2 (Eberly, *Distance from a point to
    an ellipse, an ellipsoid, or a hyperellipsoid*): t > 0 outside, t < 0 inside. Newton steps inside a shrinking
    bracket, bisection where a step would leave it; the point is then scaled onto the surface, which also places
    the rare inside point of a symmetry plane (no root) on it.
    """
    y = wp.vec3(wp.abs(x[0]), wp.abs(x[1]), wp.abs(x[2]))
    a2 = wp.cw_mul(radii, radii)
    ay = wp.cw_mul(radii, y)
    q = wp.vec3(y[0] / radii[0], y[1] / radii[1], y[2] / radii[2])
    outside = wp.dot(q, q) >= 1.0
    lo = float(0.0)
    hi = float(0.0)
    if outside:
        hi = wp.length(ay)
    else:
        lo = -wp.min(wp.min(a2[0], a2[1]), a2[2]) * (1.0 - 1.0e-6)
    t = float(0.0)
    if not outside:
        t = 0.5 * lo
    for _ in range(ELLIPSOID_ITERATIONS):
        f, df = _ellipsoid_secular(t, ay, a2)
        if f > 0.0:
            lo = t
        else:
            hi = t
        # F is a sum of O(1) terms: float32 resolves it to a few 1e-7; t's bracket to 1e-9 m^2 (t ~ 1e-3)
        if wp.abs(f) <= 4.0e-6 or hi - lo <= 1.0e-9:
            break
        step = t - f / df
        if df < 0.0 and step > lo and step < hi:
            t = step
        else:
            t = 0.5 * (lo + hi)
    z = wp.vec3(a2[0] * y[0] / (t + a2[0]), a2[1] * y[1] / (t + a2[1]), a2[2] * y[2] / (t + a2[2]))
    g = wp.vec3(z[0] / radii[0], z[1] / radii[1], z[2] / radii[2])
    gl = wp.length(g)
    if gl > TINY_LENGTH:
        z = z / gl
    p = wp.vec3(wp.sign(x[0]) * z[0], wp.sign(x[1]) * z[1], wp.sign(x[2]) * z[2])
    n = wp.vec3(p[0] / a2[0], p[1] / a2[1], p[2] / a2[2])
    nl = wp.length(n)
    if nl > TINY_LENGTH:
        n = n / nl
    else:
        n = wp.vec3(0.0, 0.0, 1.0)
    d = wp.length(x - p)
    if not outside:
        d = -d
    return _surface_point(1, d, p, n)


@wp.func
def capsule_surface(x: wp.vec3, radius: float, half_height: float):
    """Closest point on a capsule: ``radius`` around the z segment ``[-half_height, half_height]``."""
    axis_point = wp.vec3(0.0, 0.0, wp.clamp(x[2], -half_height, half_height))
    s = sphere_surface(x - axis_point, radius)
    if wp.length(x - axis_point) <= TINY_LENGTH:
        s.normal = wp.vec3(1.0, 0.0, 0.0)
        s.point = radius * s.normal
    s.point = s.point + axis_point
    return s


@wp.func
def plane_surface(x: wp.vec3):
    """Closest point on the plane z = 0, outward normal +z."""
    return _surface_point(1, x[2], wp.vec3(x[0], x[1], 0.0), wp.vec3(0.0, 0.0, 1.0))


@wp.func
def mesh_surface(mesh: wp.uint64, x: wp.vec3, bound_lo: wp.vec3, bound_hi: wp.vec3, max_dist: float,
                 far: float, outside_known: int):
    """Closest point on a closed ``wp.Mesh`` (local frame) if nearer than ``max_dist`` or inside.

    Within ``max_dist`` the sign is the angle-weighted pseudo-normal's (exact for a closed, consistently
    wound mesh). Farther, the point is outside if the caller knows it cannot be that deep
    (``outside_known``); else rays decide: from inside, the first hit is the back of a face (two rays
    must agree), and only then is the closest point searched again, unbounded (``far``), so a vertex deep
    inside is found at any depth. Points outside the mesh bounds widened by ``max_dist`` skip the BVH.
    """
    lo = bound_lo - wp.vec3(max_dist)
    hi = bound_hi + wp.vec3(max_dist)
    if x[0] < lo[0] or x[1] < lo[1] or x[2] < lo[2] or x[0] > hi[0] or x[1] > hi[1] or x[2] > hi[2]:
        return _surface_point(0, max_dist, x, wp.vec3(0.0, 0.0, 1.0))
    q = wp.mesh_query_point_sign_normal(mesh, x, max_dist)
    sign = q.sign
    if not q.result:
        if outside_known != 0:
            return _surface_point(0, max_dist, x, wp.vec3(0.0, 0.0, 1.0))
        ray = wp.mesh_query_ray(mesh, x, RAY_DIRECTION, far)
        if not ray.result or ray.sign >= 0.0:
            return _surface_point(0, max_dist, x, wp.vec3(0.0, 0.0, 1.0))
        # A ray slipping through a float32 crack between two faces would see the back of the far side;
        # a second ray must agree before a point is taken as inside.
        ray = wp.mesh_query_ray(mesh, x, RAY_DIRECTION_CHECK, far)
        if not ray.result or ray.sign >= 0.0:
            return _surface_point(0, max_dist, x, wp.vec3(0.0, 0.0, 1.0))
        sign = -1.0
        q = wp.mesh_query_point_no_sign(mesh, x, far)
        if not q.result:
            return _surface_point(0, max_dist, x, wp.vec3(0.0, 0.0, 1.0))
    c = wp.mesh_eval_position(mesh, q.face, q.u, q.v)
    delta = x - c
    r = wp.length(delta)
    n = wp.mesh_eval_face_normal(mesh, q.face)
    if r > TINY_LENGTH:
        n = delta / r
        if sign < 0.0:
            n = -n
    d = r
    if sign < 0.0:
        d = -r
    return _surface_point(1, d, c, n)


@wp.func
def collider_surface(kind: int, radius: float, half_height: float, mesh: wp.uint64, bound_lo: wp.vec3,
                     bound_hi: wp.vec3, far: float, x: wp.vec3, max_dist: float, outside_known: int):
    """Signed-distance query of one collider of ``kind`` at the local point ``x`` (see the module notes).

    ``outside_known`` = 1 promises the point is not ``max_dist`` deep inside (a mesh then skips its ray).
    """
    if kind == ColliderKind.SPHERE:
        return sphere_surface(x, radius)
    if kind == ColliderKind.CAPSULE:
        return capsule_surface(x, radius, half_height)
    if kind == ColliderKind.PLANE:
        return plane_surface(x)
    if kind == ColliderKind.ELLIPSOID:
        return ellipsoid_surface(x, bound_hi)
    return mesh_surface(mesh, x, bound_lo, bound_hi, max_dist, far, outside_known)


@wp.func
def _sphere_entry(a: wp.vec3, d: wp.vec3, center: wp.vec3, radius: float):
    """Parameter ``t`` in [0, 1] where the segment ``a + t d`` enters the sphere from outside, else 2."""
    m = a - center
    c = wp.dot(m, m) - radius * radius
    b = wp.dot(m, d)
    dd = wp.dot(d, d)
    if c <= 0.0 or b >= 0.0 or dd <= 0.0:
        return 2.0
    disc = b * b - dd * c
    if disc < 0.0:
        return 2.0
    t = (-b - wp.sqrt(disc)) / dd
    if t > 1.0:
        return 2.0
    return wp.max(t, 0.0)


@wp.func
def segment_entry(kind: int, radius: float, half_height: float, mesh: wp.uint64, radii: wp.vec3, a: wp.vec3,
                  b: wp.vec3):
    """Where the segment from ``a`` (outside) to ``b`` first enters a collider (local frame).

    ``found`` = 1 with ``distance`` = the segment parameter in [0, 1], ``point`` the entry point and
    ``normal`` the outward normal there; 0 when the segment does not enter (or ``a`` is inside). Sphere,
    capsule and ellipsoid (``radii``: a unit sphere after scaling, which keeps the segment's parameter) in closed
    form; a closed mesh by one ray, whose first hit must be a face's front.
    """
    d = b - a
    t = float(2.0)
    n = wp.vec3(0.0, 0.0, 1.0)
    if kind == ColliderKind.SPHERE:
        t = _sphere_entry(a, d, wp.vec3(0.0), radius)
        if t <= 1.0:
            n = wp.normalize(a + t * d)
    elif kind == ColliderKind.CAPSULE:
        if capsule_surface(a, radius, half_height).distance > 0.0:
            c = a[0] * a[0] + a[1] * a[1] - radius * radius
            bb = a[0] * d[0] + a[1] * d[1]
            dd = d[0] * d[0] + d[1] * d[1]
            if c > 0.0 and bb < 0.0 and dd > 0.0 and bb * bb - dd * c >= 0.0:
                tc = (-bb - wp.sqrt(bb * bb - dd * c)) / dd
                if tc <= 1.0 and wp.abs(a[2] + tc * d[2]) <= half_height:
                    t = wp.max(tc, 0.0)
                    n = wp.normalize(wp.vec3(a[0] + t * d[0], a[1] + t * d[1], 0.0))
            for end in range(2):
                cap = wp.vec3(0.0, 0.0, half_height * (2.0 * float(end) - 1.0))
                ts = _sphere_entry(a, d, cap, radius)
                if ts < t:
                    t = ts
                    n = wp.normalize(a + t * d - cap)
    elif kind == ColliderKind.ELLIPSOID:
        inv = wp.vec3(1.0 / radii[0], 1.0 / radii[1], 1.0 / radii[2])
        t = _sphere_entry(wp.cw_mul(a, inv), wp.cw_mul(d, inv), wp.vec3(0.0), 1.0)
        if t <= 1.0:
            e = a + t * d
            n = wp.normalize(wp.cw_mul(e, wp.cw_mul(inv, inv)))
    elif kind == ColliderKind.MESH:
        length = wp.length(d)
        if length > TINY_LENGTH:
            q = wp.mesh_query_ray(mesh, a, d / length, length)
            if q.result and q.sign > 0.0:
                t = q.t / length
                n = wp.normalize(wp.mesh_eval_face_normal(mesh, q.face))
    if t > 1.0:
        return _surface_point(0, 2.0, b, n)
    return _surface_point(1, t, a + t * d, n)


@wp.func
def collider_world_motion(attach_head: int, local_xform: wp.transform, xform: wp.transform,
                          velocity: wp.spatial_vector, head_xform: wp.transform, head_velocity: wp.spatial_vector):
    """World pose and spatial velocity (angular, linear velocity of the collider origin) of a collider.

    A head-attached collider rides on ``head_xform``, so it follows the Control arrays on the device;
    any other one uses its own world pose and velocity.
    """
    if attach_head == 0:
        return xform, velocity
    X = wp.transform_multiply(head_xform, local_xform)
    w = wp.spatial_top(head_velocity)
    o = wp.transform_get_translation(X) - wp.transform_get_translation(head_xform)
    v = wp.spatial_bottom(head_velocity) + wp.cross(w, o)
    return X, wp.spatial_vector(w, v)


@wp.func
def _lift_on_sphere(p_prev: wp.vec3, length: float, x: wp.vec3, c: wp.vec3, n: wp.vec3, target: float):
    """Point at ``length`` from ``p_prev``, nearest to ``x``, at least ``target`` above the plane (c, n).

    The segment ending at the vertex cannot stretch, so the vertex moves on the sphere of radius
    ``length`` about the previous vertex: its direction is turned towards ``n`` just enough to clear the
    tangent plane, or straight along ``n`` when the plane cannot be cleared.
    """
    u0 = x - p_prev
    l0 = wp.length(u0)
    u = n
    if l0 > TINY_LENGTH:
        u = u0 / l0
    c_min = wp.min((target - wp.dot(n, p_prev - c)) / wp.max(length, TINY_LENGTH), 1.0)
    un = wp.dot(u, n)
    if un >= c_min:
        return p_prev + length * u
    t = u - un * n
    tl = wp.length(t)
    if tl > 1.0e-6:
        t = t / tl
    else:
        t = _any_perpendicular(n)
    s = wp.sqrt(wp.max(1.0 - c_min * c_min, 0.0))
    return p_prev + length * (c_min * n + s * t)


@wp.struct
class ColliderShapes:
    """The colliders' fixed description, one entry per collider (``hairwarp.ColliderSet`` builds it): ``count``;
    ``kind`` (``ColliderKind``), ``attach`` (1 = head), ``local_xform``, ``radius``, ``half_height``,
    ``thickness`` [m] of the contact layer, ``friction``, ``mesh`` (``wp.Mesh`` id, 0 for primitives),
    ``bound_lo`` and ``bound_hi`` (mesh bounds in the local frame; an ellipsoid's -radii and radii) and ``far``
    (the unbounded query distance of a mesh [m])."""

    count: int
    kind: wp.array(dtype=wp.int32)
    attach: wp.array(dtype=wp.int32)
    local_xform: wp.array(dtype=wp.transform)
    radius: wp.array(dtype=float)
    half_height: wp.array(dtype=float)
    thickness: wp.array(dtype=float)
    friction: wp.array(dtype=float)
    mesh: wp.array(dtype=wp.uint64)
    bound_lo: wp.array(dtype=wp.vec3)
    bound_hi: wp.array(dtype=wp.vec3)
    far: wp.array(dtype=float)


@wp.func
def shape_surface(shapes: ColliderShapes, c: int, x: wp.vec3, max_dist: float, outside_known: int):
    """``collider_surface`` of collider ``c`` at the local point ``x``."""
    return collider_surface(shapes.kind[c], shapes.radius[c], shapes.half_height[c], shapes.mesh[c],
                            shapes.bound_lo[c], shapes.bound_hi[c], shapes.far[c], x, max_dist, outside_known)


@wp.func
def shape_motion(shapes: ColliderShapes, c: int, collider_xform: wp.array(dtype=wp.transform),
                 collider_velocity: wp.array(dtype=wp.spatial_vector), X_head: wp.transform,
                 V_head: wp.spatial_vector):
    """``collider_world_motion`` of collider ``c``: its world pose and velocity now."""
    X, vel = collider_world_motion(shapes.attach[c], shapes.local_xform[c], collider_xform[c],
                                   collider_velocity[c], X_head, V_head)
    return X, vel


@wp.kernel
def collider_distances(
    # Model:
    shapes: ColliderShapes,
    # Control:
    collider_xform: wp.array(dtype=wp.transform),
    collider_velocity: wp.array(dtype=wp.spatial_vector),
    head_xform: wp.array(dtype=wp.transform),
    head_velocity: wp.array(dtype=wp.spatial_vector),
    # State in:
    points: wp.array(dtype=wp.vec3),
    # Out:
    distance_out: wp.array2d(dtype=float),
    closest_out: wp.array2d(dtype=wp.vec3),
    normal_out: wp.array2d(dtype=wp.vec3),
):
    """One thread per (point, collider): exact signed distance [m], closest point [m] and outward normal.

    World frame in and out. Used at setup (which rest vertices start inside) and by diagnostics; the
    mesh query is unbounded here (``shapes.far``), so every entry is exact.
    """
    p, c = wp.tid()
    X, vel = shape_motion(shapes, c, collider_xform, collider_velocity, head_xform[0], head_velocity[0])
    x_local = wp.transform_point(wp.transform_inverse(X), points[p])
    s = shape_surface(shapes, c, x_local, shapes.far[c], 0)
    distance_out[p, c] = s.distance
    closest_out[p, c] = wp.transform_point(X, s.point)
    normal_out[p, c] = wp.transform_vector(X, s.normal)


@wp.kernel
def detect_body_contacts(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    seg_per_strand: int,
    seg_length: wp.array(dtype=float),
    shapes: ColliderShapes,
    gravity: wp.vec3,
    # Control:
    collider_xform: wp.array(dtype=wp.transform),
    collider_velocity: wp.array(dtype=wp.spatial_vector),
    head_xform: wp.array(dtype=wp.transform),
    head_velocity: wp.array(dtype=wp.spatial_vector),
    dt: wp.array(dtype=float),
    # State in:
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    vert_exempt: wp.array(dtype=wp.int32),
    # Read and updated:
    memo_point: wp.array(dtype=wp.vec3),
    memo_distance: wp.array(dtype=float),
    # Out:
    contact_normal: wp.array(dtype=wp.vec3),
    contact_object_velocity: wp.array(dtype=wp.vec3),
    contact_gap: wp.array(dtype=float),
    contact_friction: wp.array(dtype=float),
    start_clearance: wp.array(dtype=float),
):
    """One thread per strand: the body contact candidates of vertices 1..S for the step about to be taken.

    A vertex is a candidate of the nearest collider whose contact layer it can reach within the step: its
    distance at the step's start (``x + h v_object`` against the collider's end-of-step pose, which the
    Control holds) less the layer is at most its speed relative to the surface times ``h``, plus what gravity
    adds over the step, twice over. Writes the outward ``contact_normal`` (world; zero: none), the surface
    point's velocity at the step's end ``contact_object_velocity`` [m/s], ``contact_gap`` [m] (the start
    distance less the layer thickness), the collider's ``contact_friction`` and ``start_clearance`` [m], a lower
    bound of the vertex's distance to every collider it is not exempt from at its start point (``collide_strands``
    lets the vertices that the step cannot have taken near a collider skip their queries);
    ``articulated.body_contact_solve`` decides from the free velocities which of them hold. Vertices inside a
    collider at rest (exempt) are no candidates of it. Signed distances are 1-Lipschitz, so a vertex far from
    every collider skips the queries: the bound comes from the vertex before it along the strand, and from the
    vertex's own last query of each collider (``memo_point``, the query point in the collider's frame, and
    ``memo_distance``, a lower bound of the signed distance there; -UNBOUNDED: none), which stays a bound for good
    because a collider's shape is fixed in its own frame. The latter also proves a vertex outside, so a mesh
    skips the rays that would tell whether a point it finds no surface near is deep inside.
    """
    strand = tid_offset + wp.tid()
    S = seg_per_strand
    sbase = strand * S
    vbase = strand * (S + 1)
    h = dt[0]
    X_head = head_xform[0]
    V_head = head_velocity[0]
    fall = h * h * wp.length(gravity)
    clearance = float(-UNBOUNDED)
    for k in range(1, S + 1):
        vi = vbase + k
        x = vertex_positions[vi]
        v = vertex_velocities[vi]
        bound = clearance - seg_length[sbase + k - 1] - LIPSCHITZ_SLOP
        clearance = float(UNBOUNDED)
        at_start = float(UNBOUNDED)
        best = float(UNBOUNDED)
        normal = wp.vec3()
        v_best = wp.vec3()
        friction = float(0.0)
        exempt = vert_exempt[vi]
        for c in range(shapes.count):
            thickness = shapes.thickness[c]
            X, vel = shape_motion(shapes, c, collider_xform, collider_velocity, X_head, V_head)
            origin = wp.transform_get_translation(X)
            v_object = wp.spatial_bottom(vel) + wp.cross(wp.spatial_top(vel), x - origin)
            reach = 2.0 * (h * wp.length(v - v_object) + fall) + LIPSCHITZ_SLOP
            start = x + h * v_object
            shift = h * wp.length(v_object)
            # lower bounds of the signed distance at the start point: along the strand, and from the last query
            memo = vi * shapes.count + c
            local = wp.transform_point(wp.transform_inverse(X), start)
            known = memo_distance[memo] - wp.length(local - memo_point[memo]) - LIPSCHITZ_SLOP
            lower = wp.max(bound - shift, known)
            if lower >= thickness + reach:
                clearance = wp.min(clearance, lower + shift)
                at_start = wp.min(at_start, lower)
                continue
            if c < MAX_EXEMPT_COLLIDERS and (exempt & (1 << c)) != 0:
                # no distance known to this collider: the next vertex queries
                clearance = float(-UNBOUNDED)
                at_start = float(-UNBOUNDED)
                continue
            outside = int(0)
            if known > -(thickness + reach):
                outside = 1  # not that deep inside: no rays
            s = shape_surface(shapes, c, local, thickness + reach, outside)
            memo_point[memo] = local
            memo_distance[memo] = s.distance
            # ``clearance`` bounds the distance at the vertex (the next one's bound), ``at_start`` at its start point
            clearance = wp.min(clearance, s.distance - shift)
            at_start = wp.min(at_start, s.distance)
            if s.found == 0 or s.distance >= thickness + reach or s.distance >= best:
                continue
            best = s.distance
            normal = wp.transform_vector(X, s.normal)
            point = wp.transform_point(X, s.point)
            v_best = wp.spatial_bottom(vel) + wp.cross(wp.spatial_top(vel), point - origin)
            friction = shapes.friction[c]
            contact_gap[vi] = s.distance - thickness
        start_clearance[vi] = at_start
        contact_normal[vi] = normal
        contact_object_velocity[vi] = v_best
        contact_friction[vi] = friction


@wp.func
def relative_velocity(V_base: wp.spatial_vector, p_base: wp.vec3, x: wp.vec3, v: wp.vec3):
    """Velocity [m/s] of a point at ``x`` moving at ``v`` relative to the rigid motion ``V_base`` (angular, then
    linear at ``p_base``)."""
    return v - wp.spatial_bottom(V_base) - wp.cross(wp.spatial_top(V_base), x - p_base)


@wp.func
def segment_energy(chains: StrandChains, i: int, V_base: wp.spatial_vector, p_base: wp.vec3, x0: wp.vec3,
                   x1: wp.vec3, v0: wp.vec3, v1: wp.vec3):
    """Twice the kinetic energy [J] of segment ``i``, its ends at ``x0``, ``x1`` moving at ``v0``, ``v1``, relative to
    the base's rigid motion: its centre's and its turn across its axis (the spin about the axis, whose inertia is
    tiny and which the ends do not show, left out)."""
    r0 = relative_velocity(V_base, p_base, x0, v0)
    r1 = relative_velocity(V_base, p_base, x1, v1)
    d = x1 - x0
    w = wp.cross(d, r1 - r0) / wp.max(wp.length_sq(d), TINY_LENGTH)
    return chains.seg_mass[i] * wp.length_sq(0.5 * (r0 + r1)) + chains.seg_inertia[i][0] * wp.length_sq(w)


@wp.func
def relative_energy(chains: StrandChains, strand: int, first: int, end: int, V_base: wp.spatial_vector,
                    p_base: wp.vec3, vertex_positions: wp.array(dtype=wp.vec3),
                    vertex_velocities: wp.array(dtype=wp.vec3)):
    """Twice the kinetic energy [J] of a strand's segments ``first`` to ``end`` (exclusive) relative to its base's
    rigid motion (``segment_energy``), from its vertices."""
    S = chains.seg_per_strand
    vbase = strand * (S + 1)
    energy = float(0.0)
    for k in range(first, end):
        energy += segment_energy(chains, strand * S + k, V_base, p_base, vertex_positions[vbase + k],
                                 vertex_positions[vbase + k + 1], vertex_velocities[vbase + k],
                                 vertex_velocities[vbase + k + 1])
    return energy


@wp.kernel
def collide_strands(
    # Launch: the first element of this launch's chunk (hairwarp.executor; 0 for one whole launch)
    tid_offset: int,
    # Model:
    chains: StrandChains,
    swept: int,
    shapes: ColliderShapes,
    # Control:
    collider_xform: wp.array(dtype=wp.transform),
    collider_velocity: wp.array(dtype=wp.spatial_vector),
    head_xform: wp.array(dtype=wp.transform),
    head_velocity: wp.array(dtype=wp.spatial_vector),
    bases: StrandBases,
    dt: wp.array(dtype=float),
    # State in:
    has_previous: int,
    previous_positions: wp.array(dtype=wp.vec3),
    detected: int,
    start_clearance: wp.array(dtype=float),
    # Scratch:
    vert_exempt: wp.array(dtype=wp.int32),
    # Out (read and updated in place):
    joint_q: wp.array(dtype=wp.quat),
    joint_qd: wp.array(dtype=wp.vec3),
    seg_xform: wp.array(dtype=wp.transform),
    vertex_positions: wp.array(dtype=wp.vec3),
    vertex_velocities: wp.array(dtype=wp.vec3),
    fault: wp.array(dtype=wp.int32),
):
    """One thread per strand: push vertices 1..S that ended the step inside a collider back out.

    The velocities were settled inside the step (``articulated.body_contact_solve``); this pass only removes
    what penetration is left, with the seed's length-preserving propagation, and adds no energy: a moved strand
    gets new ``joint_q`` (minimal rotations onto the new segment directions, twist kept), ``seg_xform``,
    ``vertex_positions`` [m] and the ``vertex_velocities`` [m/s] of its ``joint_qd`` [rad/s] at the new
    configuration, those kept, or all scaled by the one factor that brings the strand's kinetic energy relative to
    its base (``relative_energy``) back to what it came in with where they would raise it. A strand clear of every
    collider is not written.

    With ``detected`` (and the step's start given), ``start_clearance`` holds what ``detect_body_contacts`` found
    of each vertex's distance at the start of its path: a path shorter than that less the layer cannot have met
    the collider, and the vertex skips its queries.
    """
    strand = tid_offset + wp.tid()
    S = chains.seg_per_strand
    sbase = strand * S
    vbase = strand * (S + 1)
    h = dt[0]
    X_head = head_xform[0]
    V_head = head_velocity[0]

    # Pass 1, root to tip: propagate upstream moves, push out. ``clearance`` bounds the smallest signed distance
    # to the colliders from below; signed distances are 1-Lipschitz, so one segment further it drops by at most
    # the segment length. It lets far vertices skip the queries, and tells a mesh query that found nothing within
    # reach that the vertex is outside (no ray needed). The root is not queried.
    moved = int(0)
    first_moved = S + 1
    clearance = float(-UNBOUNDED)
    p_prev = vertex_positions[vbase]
    b = strand * bases.per_strand
    V_base = bases.velocity[b]
    p_base = wp.transform_get_translation(bases.xform[b])
    # the moved segments' energy as they came in (the push-out may only lower the strand's): the segments before the
    # first moved vertex keep their positions and velocities
    energy_in = float(0.0)
    p_prev_old = p_prev
    for k in range(1, S + 1):
        vi = vbase + k
        length = chains.seg_length[sbase + k - 1]
        p_old = vertex_positions[vi]
        v = vertex_velocities[vi]
        if not wp.isfinite(p_old):
            # a push would put it back on the surface and hide it
            wp.atomic_or(fault, 0, int(Fault.NONFINITE_COLLISION))
        p = p_old
        if moved != 0:
            u = p_old - p_prev
            ul = wp.length(u)
            if ul > TINY_LENGTH:
                p = p_prev + (length / ul) * u
        bound = clearance - length - LIPSCHITZ_SLOP
        clearance = float(UNBOUNDED)
        pushed = int(0)
        exempt = vert_exempt[vi]
        exempt_new = exempt
        for c in range(shapes.count):
            bit = int(0)
            if c < MAX_EXEMPT_COLLIDERS:
                bit = 1 << c
            thickness = shapes.thickness[c]
            kind = shapes.kind[c]
            X, vel = shape_motion(shapes, c, collider_xform, collider_velocity, X_head, V_head)
            origin = wp.transform_get_translation(X)
            v_object = wp.spatial_bottom(vel) + wp.cross(wp.spatial_top(vel), p - origin)
            X_inv = wp.transform_inverse(X)
            x_local = wp.transform_point(X_inv, p)
            # Swept test: the vertex's path over the step relative to the collider, from its position at the start
            # of the step (given, or implied by its velocity) to where it is now.
            sweep = int(0)
            reach = float(0.0)
            x_before = x_local
            if swept != 0 and (exempt_new & bit) == 0:
                sweep = 1
                start = p - h * (v - v_object)
                if has_previous != 0:
                    # The step's own start, against the collider moved back by its velocity.
                    start = previous_positions[vi]
                    start = start + h * (wp.spatial_bottom(vel) + wp.cross(wp.spatial_top(vel), start - origin))
                x_before = wp.transform_point(X_inv, start)
                reach = wp.length(x_local - x_before)
            # From the detection at the path's start (the same point, the same pose): signed distances are
            # 1-Lipschitz, so none along the path is below this.
            path_bound = float(-UNBOUNDED)
            if sweep != 0 and detected != 0 and has_previous != 0 and exempt == 0 and pushed == 0:
                path_bound = start_clearance[vi] - reach - LIPSCHITZ_SLOP
            if bound >= thickness + reach or path_bound >= thickness:
                exempt_new = exempt_new & ~bit
                clearance = wp.min(clearance, wp.max(bound, path_bound))
                continue
            # Reach just past the layer: wider queries cost more near finely meshed surfaces than the rays they
            # would save (measured: 3x on a 20k-triangle head under combed hair).
            max_dist = thickness + LIPSCHITZ_SLOP
            outside_known = int(0)
            if wp.max(bound, path_bound) > -max_dist:
                outside_known = 1
            s = shape_surface(shapes, c, x_local, max_dist, outside_known)
            if (exempt_new & bit) != 0:
                # Inside at rest: left alone until first seen clear of the contact layer.
                if s.distance >= thickness:
                    exempt_new = exempt_new & ~bit
                clearance = wp.min(clearance, s.distance)
                continue
            # A mesh casts its ray only when the path can have met the surface: the vertex is inside, or it moved
            # further than its distance to the surface.
            if sweep != 0 and (kind != ColliderKind.MESH or s.distance < 0.0 or reach > s.distance):
                e = segment_entry(kind, shapes.radius[c], shapes.half_height[c], shapes.mesh[c], shapes.bound_hi[c],
                                  x_before, x_local)
                if e.found != 0:
                    # Resolve on the side the vertex came in from: the push starts from the tangent plane at the
                    # entry point, not from the nearest surface point (the far side when the vertex got past the
                    # middle, or none when it got through).
                    s.point = e.point
                    s.normal = e.normal
                    s.distance = wp.min(s.distance, -TINY_LENGTH)
                    s.found = 1
            if s.found == 0 or s.distance >= 0.0:
                clearance = wp.min(clearance, s.distance)
                continue
            push_target = wp.min(thickness, PUSH_MARGIN)
            p_prev_local = wp.transform_point(X_inv, p_prev)
            for _it in range(PUSH_ITERATIONS):
                x_local = _lift_on_sphere(p_prev_local, length, x_local, s.point, s.normal, push_target)
                s = shape_surface(shapes, c, x_local, max_dist, 0)
                if s.found == 0 or s.distance >= 0.0:
                    break
            p = wp.transform_point(X, x_local)
            pushed = 1
            # The bound held where the vertex was; the colliders after this one start from none.
            bound = -UNBOUNDED
            if moved == 0:
                first_moved = k
            moved = 1
            clearance = wp.min(clearance, s.distance)
        if pushed != 0 and shapes.count > 1:
            # Distances to the colliders queried before the push are stale.
            clearance = -UNBOUNDED
        if exempt_new != exempt:
            vert_exempt[vi] = exempt_new
        if moved != 0:
            vertex_positions[vi] = p
            if not wp.isfinite(p):
                wp.atomic_or(fault, 0, int(Fault.NONFINITE_COLLISION))
            energy_in += segment_energy(chains, sbase + k - 1, V_base, p_base, p_prev_old, p_old,
                                        vertex_velocities[vi - 1], v)
        p_prev = p
        p_prev_old = p_old

    if moved == 0:
        return

    # Pass 2, root to tip: minimal rotations of the old segment frames onto the new directions (twist kept), joint
    # rotations from the world rotations; then forward kinematics of the strand at its joint velocities.
    X_base = bases.xform[b]
    R_old = wp.transform_get_rotation(X_base)
    R_new = R_old
    x = wp.transform_point(X_base, chains.strand_root_pos[strand])
    for k in range(S):
        i = sbase + k
        R_parent = R_new
        R_old = R_old * joint_q[i]
        R_new = R_old
        if k + 1 >= first_moved:
            d_old = wp.quat_rotate(R_old, wp.vec3(0.0, 0.0, -1.0))
            target = vertex_positions[vbase + k + 1] - x
            tl = wp.length(target)
            d_new = d_old
            if tl > TINY_LENGTH:
                d_new = target / tl
            q = wp.normalize(wp.quat_inverse(R_parent) * (_min_rotation(d_old, d_new) * R_old))
            joint_q[i] = q
            if not wp.isfinite(q):
                wp.atomic_or(fault, 0, int(Fault.NONFINITE_COLLISION))
            R_new = R_parent * q
        x = x + wp.quat_rotate(R_new, wp.vec3(0.0, 0.0, -chains.seg_length[i]))
    fk_strand(chains, strand, X_base, V_base, joint_q, joint_qd, seg_xform, vertex_positions, vertex_velocities)
    # The same joint velocities at the moved configuration may move the strand faster (a bent chain pushed straighter
    # swings its outer part on longer arms): scale them so that the strand's kinetic energy relative to its base
    # is no more than it came in with. The motion relative to the base is linear in them, its energy quadratic.
    energy_out = relative_energy(chains, strand, first_moved - 1, S, V_base, p_base, vertex_positions,
                                 vertex_velocities)
    if energy_out > energy_in:
        kept = relative_energy(chains, strand, 0, first_moved - 1, V_base, p_base, vertex_positions, vertex_velocities)
        scale = wp.sqrt((kept + energy_in) / (kept + energy_out))
        for k in range(S):
            joint_qd[sbase + k] = scale * joint_qd[sbase + k]
        for k in range(1, S + 1):
            x_k = vertex_positions[vbase + k]
            r = relative_velocity(V_base, p_base, x_k, vertex_velocities[vbase + k])
            vertex_velocities[vbase + k] = vertex_velocities[vbase + k] - (1.0 - scale) * r
