"""Rotation and spatial-algebra helpers shared by the kernels.

Conventions, fixed for the whole project:

- Quaternions are ``wp.quat`` laid out (x, y, z, w). A joint rotation ``q`` maps child
  coordinates to parent coordinates (parent from child).
- Spatial vectors are Warp's (angular, linear), Featherstone's order: a motion vector is
  (omega, v) and a force vector is (torque, force), both about a frame's origin and in that
  frame's axes. A spherical joint's motion subspace in the child frame is ``S = [I3; 0]``.
- A symmetric spatial inertia about a point is kept as three 3x3 blocks
  ``[[A, B], [B^T, C]]`` (rotational, coupling, translational); for a rigid body of mass m
  with centre of mass c, ``A = Ic + m(|c|^2 I - c c^T)``, ``B = m [c]x``, ``C = m I``.

The permutations to Pinocchio's (linear, angular) vectors, MuJoCo's (w, x, y, z) quaternions
and USD's ``Gf.Quatf(real, i, j, k)`` live only in ``tests/_reference.py`` and ``hairwarp/io/usd_common.py``.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

# Below this rotation angle [rad] exp and log use their Taylor series: float32 keeps ~7 digits,
# and the series error at 1e-4 rad is below 1e-13.
SMALL_ANGLE = wp.constant(1.0e-4)


@wp.func
def quat_exp(v: wp.vec3):
    """Unit quaternion of the rotation vector ``v`` (axis * angle, radians)."""
    theta = wp.length(v)
    if theta < SMALL_ANGLE:
        h = 0.5 * v
        return wp.normalize(wp.quat(h[0], h[1], h[2], 1.0 - 0.125 * theta * theta))
    s = wp.sin(0.5 * theta) / theta
    return wp.quat(v[0] * s, v[1] * s, v[2] * s, wp.cos(0.5 * theta))


@wp.func
def quat_log(q: wp.quat):
    """Rotation vector (axis * angle, angle in [0, pi]) of the unit quaternion ``q``."""
    x = q[0]
    y = q[1]
    z = q[2]
    w = q[3]
    if w < 0.0:
        x = -x
        y = -y
        z = -z
        w = -w
    s = wp.sqrt(x * x + y * y + z * z)
    if s < 0.5 * SMALL_ANGLE:
        f = 2.0 / w
        return wp.vec3(x * f, y * f, z * f)
    f = 2.0 * wp.atan2(s, w) / s
    return wp.vec3(x * f, y * f, z * f)


@wp.func
def quat_between(a: wp.vec3, b: wp.vec3):
    """Minimal rotation taking unit vector ``a`` to unit vector ``b``.

    For opposite vectors the axis is any one perpendicular to ``a``.
    """
    d = wp.dot(a, b)
    if d < -0.999999:
        axis = wp.cross(wp.vec3(1.0, 0.0, 0.0), a)
        if wp.length_sq(axis) < 1.0e-6:
            axis = wp.cross(wp.vec3(0.0, 1.0, 0.0), a)
        axis = wp.normalize(axis)
        return wp.quat(axis[0], axis[1], axis[2], 0.0)
    c = wp.cross(a, b)
    return wp.normalize(wp.quat(c[0], c[1], c[2], 1.0 + d))


@wp.func
def skew(v: wp.vec3):
    """Cross-product matrix: ``skew(v) @ x == cross(v, x)``."""
    return wp.mat33(0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0)


@wp.func
def segment_inertia_blocks(mass: float, length: float, inertia_com: wp.vec3, extra_mass: float):
    """Blocks (A, B) of a segment's spatial inertia about its top end, in its own frame.

    The segment lies along body -z with its centre of mass at (0, 0, -L/2); ``inertia_com``
    holds the principal moments about the centre of mass. ``extra_mass`` [kg] is a point mass at
    the centre of mass (the semi-implicit share of interaction springs). C = (mass + extra) I.
    """
    m = mass + extra_mass
    h = 0.5 * length
    # parallel-axis shift of the transverse moments to the top end: + m h^2
    A = wp.mat33(inertia_com[0] + m * h * h, 0.0, 0.0, 0.0, inertia_com[1] + m * h * h, 0.0, 0.0, 0.0, inertia_com[2])
    B = skew(wp.vec3(0.0, 0.0, -h)) * m
    return A, B


@wp.func
def skew_z_left(M: wp.mat33, z: float):
    """``skew((0, 0, z)) @ M`` without the zero products: rows (-z M[1], z M[0], 0)."""
    return wp.mat33(-z * M[1, 0], -z * M[1, 1], -z * M[1, 2],
                    z * M[0, 0], z * M[0, 1], z * M[0, 2],
                    0.0, 0.0, 0.0)


@wp.func
def skew_z_right(M: wp.mat33, z: float):
    """``M @ skew((0, 0, z))`` without the zero products: columns (z M[:, 1], -z M[:, 0], 0)."""
    return wp.mat33(z * M[0, 1], -z * M[0, 0], 0.0,
                    z * M[1, 1], -z * M[1, 0], 0.0,
                    z * M[2, 1], -z * M[2, 0], 0.0)


@wp.func
def inertia_shift_z(A: wp.mat33, B: wp.mat33, C: wp.mat33, z: float):
    """Re-express a spatial inertia given about the point ``r = (0, 0, z)`` about the origin (same axes).

    With ``T = [[I, 0], [-[r]x, I]]`` mapping motion at the origin to motion at ``r``, the result is
    ``T^T I T``: A' = A + [r]x B^T - B [r]x - [r]x C [r]x, B' = B + [r]x C, C' = C. A child joint
    always sits on its parent's axis, so r has only a z component. Returns (A', B').
    """
    rxC = skew_z_left(C, z)
    A2 = A + skew_z_left(wp.transpose(B), z) - skew_z_right(B, z) - skew_z_right(rxC, z)
    B2 = B + rxC
    return A2, B2


@wp.func
def scale_rows(M: wp.mat33, d: wp.vec3):
    """``diag(d) M``."""
    return wp.mat33(d[0] * M[0, 0], d[0] * M[0, 1], d[0] * M[0, 2],
                    d[1] * M[1, 0], d[1] * M[1, 1], d[1] * M[1, 2],
                    d[2] * M[2, 0], d[2] * M[2, 1], d[2] * M[2, 2])


@wp.func
def transpose_scale_columns(M: wp.mat33, d: wp.vec3):
    """``M^T diag(d)``."""
    return wp.mat33(M[0, 0] * d[0], M[1, 0] * d[1], M[2, 0] * d[2],
                    M[0, 1] * d[0], M[1, 1] * d[1], M[2, 1] * d[2],
                    M[0, 2] * d[0], M[1, 2] * d[1], M[2, 2] * d[2])


@wp.func
def rotate_symmetric(R: wp.mat33, M: wp.mat33):
    """``R M R^T`` for a symmetric M: the upper triangle from ``(R M) R^T``, mirrored (45 products, not 54)."""
    RM = R * M
    xx = wp.dot(RM[0], R[0])
    xy = wp.dot(RM[0], R[1])
    xz = wp.dot(RM[0], R[2])
    yy = wp.dot(RM[1], R[1])
    yz = wp.dot(RM[1], R[2])
    zz = wp.dot(RM[2], R[2])
    return wp.mat33(xx, xy, xz, xy, yy, yz, xz, yz, zz)


@wp.func
def rotate_blocks(R: wp.mat33, A: wp.mat33, B: wp.mat33, C: wp.mat33):
    """Rotate the three inertia blocks into the frame ``R`` maps into: X -> R X R^T (A and C symmetric)."""
    return rotate_symmetric(R, A), R * B * wp.transpose(R), rotate_symmetric(R, C)
