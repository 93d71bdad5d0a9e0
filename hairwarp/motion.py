"""Head motion: rigid motions of the head frame with exact velocities and accelerations.

A motion maps a time ``t`` [s] to a :class:`MotionSample`: the world pose of the head frame and
its world angular and linear velocities and (classical) accelerations, which the articulated
strands take as the prescribed motion of their base. All values are float64 numpy arrays.

Kinds (``HeadMotion.from_config`` builds them from a scene's ``[head.motion]`` table):

* :class:`Still` - the head stays at its rest pose.
* :class:`Turn` - the head turns to one side about world z and back, once per ``period``:
  ``angle = A * ramp(t) * (1 - cos(2 pi tau / period)) / 2``.
* :class:`Nod` - pitch oscillation about the head's left-right axis (world x at rest):
  ``angle = A * ramp(t) * sin(2 pi tau / period)``.
* :class:`Shake` - yaw oscillation about world z, ``angle = A * ramp(t) * sin(2 pi tau / period)``.
* :class:`Translate` - the head slides along ``axis``: ``d = distance * ramp(t) * sin(2 pi tau / period)``.
* :class:`Keyframes` - keys of (time, translation, rotation), C1-smooth: Catmull-Rom cubic Hermite on
  the translation, a cubic Hermite in the rotation's tangent space on the rotation (world angular
  velocity continuous at every key), zero velocity at the first and last key.
* :class:`Compose` - one motion carried by another.
* ``usd`` - a prim of a USD stage (a character's head xform), or a joint of a UsdSkel skeleton prim, over its
  time samples, relative to its first sample (``hairwarp.io.usd_anim.head_motion_from_usd``): keyframes
  through the samples.

Here ``tau = t - start`` and ``ramp(t)`` is the quintic smoothstep ``6x^5 - 15x^4 + 10x^3`` of
``x = tau / ramp``: the amplitude fades in over ``ramp`` seconds, so position, velocity and
acceleration are all continuous at ``start`` (zero before it) and the hair is not whipped on the
first frame. Rotations turn about ``pivot``, a world point (the neck), so a nodding head swings.

The head frame at rest is ``T(rest_position)``: with the default ``rest_position = 0`` the head
frame coincides with the world frame in which the groom was built. For a rotation ``R(t)`` about
the pivot ``p`` and a translation ``d(t)``, the head frame is ``M(t) = T(p + d) R T(-p) T(rest)``.

Quaternions are ``(x, y, z, w)``, world from local, as ``wp.quat``.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

__all__ = [
    "MOTION_KINDS",
    "Compose",
    "HeadMotion",
    "Keyframes",
    "MotionSample",
    "Nod",
    "Shake",
    "Still",
    "Translate",
    "Turn",
    "euler_xyz_deg_to_quat",
    "quat_multiply",
    "quat_rotate",
    "quat_to_matrix",
]

#: ``kind`` values understood by :meth:`HeadMotion.from_config`.
MOTION_KINDS = ("still", "turn", "nod", "shake", "translate", "keyframes", "usd")

#: How :class:`Keyframes` interpolates between keys.
KEY_INTERPOLATIONS = ("smooth", "monotone", "linear")

#: Defaults of the procedural motions' parameters (also the scene file's defaults).
DEFAULT_AMPLITUDE_DEG = 30.0
DEFAULT_PERIOD = 2.0
DEFAULT_START = 0.0
DEFAULT_RAMP = 0.5
DEFAULT_DISTANCE = 0.05
#: Default axis per kind: yaw about world z, pitch about the head's left-right axis (x).
DEFAULT_AXIS = {"turn": (0.0, 0.0, 1.0), "shake": (0.0, 0.0, 1.0), "nod": (1.0, 0.0, 0.0), "translate": (1.0, 0.0, 0.0)}

# Below this squared half-angle the exp-map functions use their Taylor series (the closed forms
# lose digits to cancellation); the series are truncated well past double precision there.
_SERIES_X = 1.0e-2

_ZERO3 = np.zeros(3)
_IDENTITY_Q = np.array([0.0, 0.0, 0.0, 1.0])


# ----------------------------------------------------------------------------------------------
# quaternion helpers (x, y, z, w), float64


def _cross(a, b) -> np.ndarray:
    """``a x b`` of two 3-vectors: ``np.cross``'s arithmetic, term for term, without its cost per call (~10 us,
    which the head motion, evaluated three times a step, paid a dozen times)."""
    a0, a1, a2 = a.tolist() if isinstance(a, np.ndarray) else a
    b0, b1, b2 = b.tolist() if isinstance(b, np.ndarray) else b
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise ``a x b`` of (..., 3) arrays (broadcast against each other): ``np.cross``'s arithmetic, term for
    term (the same bits), without its cost per call in axis handling (~25 us: the character scene's root frames paid
    it 13 times a step)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of quaternions (x, y, z, w)."""
    av, aw = a[:3], a[3]
    bv, bw = b[:3], b[3]
    return np.concatenate([aw * bv + bw * av + _cross(av, bv), [aw * bw - av @ bv]])


def _conj(q: np.ndarray) -> np.ndarray:
    return np.array([-q[0], -q[1], -q[2], q[3]])


def _cross_floats(a, b) -> list[float]:
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _quat_multiply_floats(a, b) -> list[float]:
    """:func:`quat_multiply` of two sequences of 4 floats, as a list."""
    c = _cross_floats(a, b)
    return [a[3] * b[0] + b[3] * a[0] + c[0], a[3] * b[1] + b[3] * a[1] + c[1], a[3] * b[2] + b[3] * a[2] + c[2],
            a[3] * b[3] - (a[0] * b[0] + a[1] * b[1] + a[2] * b[2])]


def rotate_floats(q, v) -> list[float]:
    """The vector ``v`` (3 floats) rotated by the unit quaternion ``q`` (x, y, z, w) in plain floats
    (:func:`quat_rotate` as a list): for the host work that runs at every step, where numpy's per-call cost is larger
    than the arithmetic."""
    t = [2.0 * c for c in _cross_floats(q, v)]
    c = _cross_floats(q, t)
    return [v[k] + q[3] * t[k] + c[k] for k in range(3)]


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate the 3-vector ``v`` by the unit quaternion ``q``."""
    qv, w = q[:3], q[3]
    t = 2.0 * _cross(qv, v)
    return v + w * t + _cross(qv, t)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit quaternions ``q`` (..., 4) (x, y, z, w); one quaternion gives 3 x 3."""
    x, y, z, w = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def _quat_axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    return np.concatenate([axis * math.sin(0.5 * angle), [math.cos(0.5 * angle)]])


def euler_xyz_deg_to_quat(angles_deg: Sequence[float]) -> np.ndarray:
    """Quaternion of extrinsic x-y-z Euler angles in degrees: ``R = Rz(c) Ry(b) Rx(a)``.

    This is SciPy's ``Rotation.from_euler("xyz", angles, degrees=True)``: turn about world x by
    ``a``, then about world y by ``b``, then about world z by ``c``.
    """
    a, b, c = (math.radians(float(v)) for v in angles_deg)
    qx = _quat_axis_angle(np.array([1.0, 0.0, 0.0]), a)
    qy = _quat_axis_angle(np.array([0.0, 1.0, 0.0]), b)
    qz = _quat_axis_angle(np.array([0.0, 0.0, 1.0]), c)
    return quat_multiply(qz, quat_multiply(qy, qx))


def _quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of a unit quaternion."""
    if q[3] < 0.0:
        q = -q
    s = float(np.linalg.norm(q[:3]))
    if s < 1.0e-12:
        return 2.0 * q[:3]
    return q[:3] * (2.0 * math.atan2(s, q[3]) / s)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors ``v`` (..., 3): ``skew(a) @ b = a x b``."""
    v = np.asarray(v, dtype=np.float64)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def right_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """Inverse right Jacobian of SO(3), (..., 3, 3) for rotation vectors ``phi`` (..., 3): body angular velocity of
    ``R0 exp(phi)`` is ``J_r(phi) dphi/dt``, and ``log(exp(phi) exp(delta)) = phi + J_r^-1(phi) delta`` to first
    order."""
    phi = np.asarray(phi, dtype=np.float64)
    th = np.linalg.norm(phi, axis=-1)[..., None, None]
    K = skew(phi)
    small = th < 1.0e-4
    safe = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0 + th * th / 720.0,
                 1.0 / (safe * safe) - (1.0 + np.cos(safe)) / (2.0 * safe * np.sin(safe)))
    return np.eye(3) + 0.5 * K + c * (K @ K)


def _exp_functions(x: float) -> tuple[float, float, float, float]:
    """``f(x) = sin(sqrt x)/sqrt x``, ``f'``, ``f''`` and ``c(x) = cos(sqrt x)``, smooth at x = 0."""
    if x < _SERIES_X:
        f = 1.0 - x / 6.0 + x * x / 120.0 - x**3 / 5040.0 + x**4 / 362880.0
        f1 = -1.0 / 6.0 + x / 60.0 - x * x / 1680.0 + x**3 / 90720.0 - x**4 / 7983360.0
        f2 = 1.0 / 60.0 - x / 840.0 + x * x / 30240.0 - x**3 / 1995840.0
        c = 1.0 - x / 2.0 + x * x / 24.0 - x**3 / 720.0 + x**4 / 40320.0 - x**5 / 3628800.0
        return f, f1, f2, c
    r = math.sqrt(x)
    f = math.sin(r) / r
    c = math.cos(r)
    f1 = (c - f) / (2.0 * x)
    f2 = (-0.5 * f - 3.0 * f1) / (2.0 * x)
    return f, f1, f2, c


def _exp_derivatives(v, vd, vdd) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit quaternion ``E = exp(v) = (sin|v| v/|v|, cos|v|)`` of a curve ``v(t)`` and its first two time derivatives.

    ``v`` is half the rotation vector. With ``x = v.v``: ``E = (f(x) v, c(x))``, ``c' = -f/2``.
    """
    x = float(v @ v)
    xd = 2.0 * float(v @ vd)
    xdd = 2.0 * float(vd @ vd + v @ vdd)
    f, f1, f2, c = _exp_functions(x)
    c1, c2 = -0.5 * f, -0.5 * f1
    q = np.concatenate([f * v, [c]])
    qd = np.concatenate([f1 * xd * v + f * vd, [c1 * xd]])
    qdd = np.concatenate(
        [f2 * xd * xd * v + f1 * xdd * v + 2.0 * f1 * xd * vd + f * vdd, [c2 * xd * xd + c1 * xdd]]
    )
    return q, qd, qdd


def _smoothstep(x: float) -> tuple[float, float, float]:
    """Quintic smoothstep ``6x^5 - 15x^4 + 10x^3`` clamped to [0, 1], with its first two derivatives."""
    if x <= 0.0:
        return 0.0, 0.0, 0.0
    if x >= 1.0:
        return 1.0, 0.0, 0.0
    return x**3 * (x * (6.0 * x - 15.0) + 10.0), 30.0 * x * x * (x - 1.0) ** 2, 60.0 * x * (2.0 * x * x - 3.0 * x + 1.0)


def _unit(axis, what: str) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(a))
    if not math.isfinite(n) or n == 0.0:
        raise ValueError(f"{what} must be a non-zero finite 3-vector, got {list(a)}")
    return a / n


def _vec3(value, what: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be a finite 3-vector, got {value!r}")
    return a


# ----------------------------------------------------------------------------------------------
# samples


@dataclass(frozen=True)
class MotionSample:
    """The head frame at one instant, everything in world coordinates.

    Attributes:
        position: world position of the frame origin [m], (3,).
        rotation: unit quaternion (x, y, z, w), world from local, (4,).
        linear_velocity: velocity of the frame origin [m/s], (3,).
        angular_velocity: [rad/s], (3,).
        linear_acceleration: classical acceleration of the frame origin [m/s^2], (3,).
        angular_acceleration: [rad/s^2], (3,).
    """

    position: np.ndarray
    rotation: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray
    linear_acceleration: np.ndarray
    angular_acceleration: np.ndarray

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform, ``p_world = M @ [p_local, 1]``."""
        M = np.eye(4)
        M[:3, :3] = quat_to_matrix(self.rotation)
        M[:3, 3] = self.position
        return M

    def spatial_velocity(self) -> np.ndarray:
        """(angular, linear) velocity as a 6-vector, Warp's ``spatial_vector`` order."""
        return np.concatenate([self.angular_velocity, self.linear_velocity])

    def spatial_acceleration(self) -> np.ndarray:
        """(angular, linear) classical acceleration as a 6-vector, Warp's ``spatial_vector`` order."""
        return np.concatenate([self.angular_acceleration, self.linear_acceleration])


def _static_sample(position, rotation=_IDENTITY_Q) -> MotionSample:
    return MotionSample(np.array(position, dtype=np.float64), np.array(rotation, dtype=np.float64),
                        _ZERO3.copy(), _ZERO3.copy(), _ZERO3.copy(), _ZERO3.copy())


def _product(a: MotionSample, b: MotionSample) -> MotionSample:
    """Frame ``A(t) B(t)``: ``b`` moves in ``a``'s local frame (rigid-body velocity and acceleration composition)."""
    Ra = quat_to_matrix(a.rotation)
    r = Ra @ b.position
    wb = Ra @ b.angular_velocity
    vb = Ra @ b.linear_velocity
    w, al = a.angular_velocity, a.angular_acceleration
    q = quat_multiply(a.rotation, b.rotation)
    return MotionSample(
        position=a.position + r,
        rotation=q / np.linalg.norm(q),
        linear_velocity=a.linear_velocity + _cross(w, r) + vb,
        angular_velocity=w + wb,
        linear_acceleration=(a.linear_acceleration + _cross(al, r) + _cross(w, _cross(w, r))
                             + 2.0 * _cross(w, vb) + Ra @ b.linear_acceleration),
        angular_acceleration=al + Ra @ b.angular_acceleration + _cross(w, wb),
    )


# ----------------------------------------------------------------------------------------------
# motions


#: The ``[head.motion]`` keys each kind reads (besides ``kind``); the others are ignored by it.
MOTION_KEYS = {
    "still": (),
    "turn": ("amplitude_deg", "period", "start", "ramp", "axis", "pivot"),
    "nod": ("amplitude_deg", "period", "start", "ramp", "axis", "pivot"),
    "shake": ("amplitude_deg", "period", "start", "ramp", "axis", "pivot"),
    "translate": ("distance", "period", "start", "ramp", "axis"),
    "keyframes": ("keys", "interpolation", "pivot"),
    "usd": ("file", "prim", "joint", "interpolation"),
}


class HeadMotion:
    """A rigid motion of the head frame; call :meth:`evaluate` (or the motion itself) with a time.

    Attributes:
        rest_position: world position of the head frame origin at rest [m], (3,).
    """

    rest_position: np.ndarray = _ZERO3

    def evaluate(self, t: float) -> MotionSample:
        """The head frame at time ``t`` [s]."""
        raise NotImplementedError

    def __call__(self, t: float) -> MotionSample:
        return self.evaluate(t)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``(position, rotation)`` of the head frame at time ``t`` [s], as :meth:`evaluate` gives them; motions
        that can find them without the derivatives do (the runner asks for poses around every step)."""
        sample = self.evaluate(t)
        return sample.position, sample.rotation

    @staticmethod
    def from_config(cfg: Mapping, *, rest_position=(0.0, 0.0, 0.0), pivot=None) -> HeadMotion:
        """Build a motion from a ``[head.motion]`` table.

        Keys (all optional except as noted; a value of ``None`` means the default):

        * ``kind``: one of :data:`MOTION_KINDS` ["still"].
        * ``amplitude_deg``: turn, nod and shake angle [deg] [30].
        * ``period``: time of one full cycle [s] [2].
        * ``start``: time the motion begins [s] [0].
        * ``ramp``: fade-in time of the amplitude [s] [0.5]; 0 starts abruptly.
        * ``axis``: rotation axis (turn, shake: (0, 0, 1); nod: (1, 0, 0)) or the translation direction
          (translate: (1, 0, 0)); normalised.
        * ``distance``: translate amplitude [m] [0.05].
        * ``pivot``: world point the head turns about [m]; overrides the ``pivot`` argument.
        * ``keys``: keyframes only, a list of tables with ``time`` [s] (required), ``translate`` [m]
          [(0, 0, 0)], and the rotation as ``rotate_deg`` (extrinsic xyz Euler angles, degrees) or as
          ``axis`` and ``angle_deg``; no rotation keeps the rest orientation.

        Args:
            cfg: the table.
            rest_position: world position of the head frame at rest [m].
            pivot: default pivot [m], world; None takes ``rest_position``.

        Raises:
            ValueError: unknown kind or key, or a bad value; the message names the key.
        """
        cfg = {k: v for k, v in dict(cfg).items() if v is not None}
        kind = cfg.pop("kind", "still")
        if kind not in MOTION_KINDS:
            raise ValueError(f"head.motion.kind: unknown kind {kind!r}; choose one of {', '.join(MOTION_KINDS)}")
        allowed = set(MOTION_KEYS[kind]) - {"pivot"}
        pivot = cfg.pop("pivot", pivot)
        extra = sorted(set(cfg) - allowed)
        common = {"amplitude_deg", "period", "start", "ramp", "axis", "distance"}
        unknown = [k for k in extra if k not in common and k not in ("keys", "interpolation", "file", "prim", "joint")]
        if unknown:
            raise ValueError(f"head.motion.{unknown[0]}: unknown key for a head motion")
        kw = {k: cfg[k] for k in allowed if k in cfg}
        if kind == "still":
            return Still(rest_position=rest_position)
        if kind == "usd":
            if "file" not in kw or "prim" not in kw:
                raise ValueError("head.motion: kind = 'usd' needs file (a USD stage) and prim (the head's prim path)")
            from hairwarp.io.usd_anim import head_motion_from_usd
            from hairwarp.io.usd_common import UsdFileError

            try:
                return head_motion_from_usd(kw["file"], kw["prim"], joint=kw.get("joint"),
                                            interpolation=kw.get("interpolation", "smooth"))
            except UsdFileError as exc:  # name the key at fault: the message says which file and prim
                raise UsdFileError(f"head.motion.{getattr(exc, 'key', None) or 'file'}: {exc}") from None
        if kind == "keyframes":
            if "keys" not in kw:
                raise ValueError("head.motion.keys: kind = 'keyframes' needs at least one [[head.motion.keys]] entry")
            return Keyframes.from_keys(kw["keys"], pivot=pivot, rest_position=rest_position,
                                       interpolation=kw.get("interpolation", "smooth"))
        cls = {"turn": Turn, "nod": Nod, "shake": Shake, "translate": Translate}[kind]
        return cls(**kw, pivot=pivot, rest_position=rest_position)


class Still(HeadMotion):
    """The head at rest, ``T(rest_position)``, for all times."""

    def __init__(self, *, rest_position=(0.0, 0.0, 0.0)):
        self.rest_position = _vec3(rest_position, "rest_position")

    def evaluate(self, t: float) -> MotionSample:
        return _static_sample(self.rest_position)

    def __repr__(self) -> str:
        return "Still()"


class _PivotMotion(HeadMotion):
    """``M(t) = T(p + d(t)) R(t) T(-p) T(rest)``: a rotation about the pivot ``p``, then a translation."""

    def __init__(self, pivot, rest_position):
        self.rest_position = _vec3(rest_position, "rest_position")
        self.pivot = self.rest_position.copy() if pivot is None else _vec3(pivot, "pivot")

    def _rotation(self, t: float):
        """(q, dq/dt, d2q/dt2), world from rest."""
        return _IDENTITY_Q, np.zeros(4), np.zeros(4)

    def _translation(self, t: float):
        """(d, dd/dt, d2d/dt2) [m], world."""
        return _ZERO3, _ZERO3, _ZERO3

    def _orientation(self, t: float) -> np.ndarray:
        """q of :meth:`_rotation`, alone."""
        return self._rotation(t)[0]

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        t = float(t)
        q = self._orientation(t)
        r = quat_rotate(q, self.rest_position - self.pivot)
        return self.pivot + self._translation(t)[0] + r, q / np.linalg.norm(q)

    def evaluate(self, t: float) -> MotionSample:
        t = float(t)
        q, qd, qdd = self._rotation(t)
        d, dd, ddd = self._translation(t)
        qc = _conj(q)
        # omega = 2 vec(dq q*); its derivative drops the scalar |dq|^2 term: alpha = 2 vec(ddq q*).
        w = 2.0 * quat_multiply(qd, qc)[:3]
        al = 2.0 * quat_multiply(qdd, qc)[:3]
        r = quat_rotate(q, self.rest_position - self.pivot)
        return MotionSample(
            position=self.pivot + d + r,
            rotation=q / np.linalg.norm(q),
            linear_velocity=dd + _cross(w, r),
            angular_velocity=w,
            linear_acceleration=ddd + _cross(al, r) + _cross(w, _cross(w, r)),
            angular_acceleration=al,
        )


class _Oscillation(_PivotMotion):
    """Shared timing of the procedural motions: ``value(t) = amplitude * ramp(t) * wave(tau)``."""

    def __init__(self, *, period, start, ramp, axis, pivot, rest_position):
        super().__init__(pivot, rest_position)
        self.period = float(period)
        self.start = float(start)
        self.ramp = float(ramp)
        if not (math.isfinite(self.period) and self.period > 0.0):
            raise ValueError(f"head.motion.period must be > 0 s, got {period!r}")
        if not math.isfinite(self.start):
            raise ValueError(f"head.motion.start must be finite, got {start!r}")
        if not (math.isfinite(self.ramp) and self.ramp >= 0.0):
            raise ValueError(f"head.motion.ramp must be >= 0 s, got {ramp!r}")
        self.axis = _unit(axis, "head.motion.axis")

    def _wave(self, tau: float) -> tuple[float, float, float]:
        raise NotImplementedError

    def _envelope(self, t: float) -> tuple[float, float, float]:
        """``ramp(t) * wave(tau)`` and its first two time derivatives (zero before ``start``)."""
        tau = t - self.start
        if tau <= 0.0:
            return 0.0, 0.0, 0.0
        if self.ramp > 0.0:
            s, s1, s2 = _smoothstep(tau / self.ramp)
            s1, s2 = s1 / self.ramp, s2 / self.ramp**2
        else:
            s, s1, s2 = 1.0, 0.0, 0.0
        f, f1, f2 = self._wave(tau)
        return s * f, s1 * f + s * f1, s2 * f + 2.0 * s1 * f1 + s * f2

    def _sine(self, tau: float) -> tuple[float, float, float]:
        k = 2.0 * math.pi / self.period
        sn, cs = math.sin(k * tau), math.cos(k * tau)
        return sn, k * cs, -k * k * sn


class _AxisRotation(_Oscillation):
    def __init__(self, *, amplitude_deg, **kw):
        super().__init__(**kw)
        self.amplitude = math.radians(float(amplitude_deg))
        if not math.isfinite(self.amplitude):
            raise ValueError(f"head.motion.amplitude_deg must be finite, got {amplitude_deg!r}")

    def _rotation(self, t: float):
        a, ad, add = (self.amplitude * e for e in self._envelope(t))
        return _exp_derivatives(0.5 * a * self.axis, 0.5 * ad * self.axis, 0.5 * add * self.axis)

    def _orientation(self, t: float) -> np.ndarray:
        v = 0.5 * (self.amplitude * self._envelope(t)[0]) * self.axis
        f, _, _, c = _exp_functions(float(v @ v))
        return np.concatenate([f * v, [c]])

    def evaluate(self, t: float) -> MotionSample:
        """The turn about a fixed axis in closed form: angle ``a``, ``omega = a' k``, ``alpha = a'' k`` and the rest
        offset turned by Rodrigues' formula: what the quaternion derivatives of the general path give (to float64
        round-off, ``tests/test_motion.py``), in plain floats. A run samples the motion at every step between the
        kernels, on one thread, and the general path's small arrays took a seventh of that serial time."""
        e, e1, e2 = self._envelope(float(t))
        A = self.amplitude
        a, ad, add = A * e, A * e1, A * e2
        kx, ky, kz = self.axis.tolist()
        px, py, pz = self.pivot.tolist()
        rx, ry, rz = (self.rest_position - self.pivot).tolist()
        sa, ca = math.sin(a), math.cos(a)
        kr = kx * rx + ky * ry + kz * rz
        cx, cy, cz = ky * rz - kz * ry, kz * rx - kx * rz, kx * ry - ky * rx  # k x r0
        # r = r0 cos a + (k x r0) sin a + k (k . r0)(1 - cos a)
        x = rx * ca + cx * sa + kx * kr * (1.0 - ca)
        y = ry * ca + cy * sa + ky * kr * (1.0 - ca)
        z = rz * ca + cz * sa + kz * kr * (1.0 - ca)
        wx, wy, wz = ad * kx, ad * ky, ad * kz
        vx, vy, vz = wy * z - wz * y, wz * x - wx * z, wx * y - wy * x  # w x r
        # alpha x r + w x (w x r)
        ux, uy, uz = ky * z - kz * y, kz * x - kx * z, kx * y - ky * x  # k x r
        gx, gy, gz = add * ux + (wy * vz - wz * vy), add * uy + (wz * vx - wx * vz), add * uz + (wx * vy - wy * vx)
        sh = math.sin(0.5 * a)
        return MotionSample(
            position=np.array([px + x, py + y, pz + z]),
            rotation=np.array([sh * kx, sh * ky, sh * kz, math.cos(0.5 * a)]),
            linear_velocity=np.array([vx, vy, vz]),
            angular_velocity=np.array([wx, wy, wz]),
            linear_acceleration=np.array([gx, gy, gz]),
            angular_acceleration=np.array([add * kx, add * ky, add * kz]),
        )

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        sample = self.evaluate(t)
        return sample.position, sample.rotation

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(amplitude_deg={math.degrees(self.amplitude):g}, period={self.period:g}, "
                f"start={self.start:g}, ramp={self.ramp:g}, axis={self.axis.tolist()}, pivot={self.pivot.tolist()})")


class Turn(_AxisRotation):
    """The head turns to one side and back once per period: ``angle = A ramp(t) (1 - cos(2 pi tau / period)) / 2``.

    Args:
        amplitude_deg: largest turn angle [deg]; negative turns the other way.
        period: duration of one turn and return [s].
        start: time the motion begins [s].
        ramp: fade-in time of the amplitude [s] (quintic smoothstep); 0 starts abruptly.
        axis: rotation axis, world (default z: a yaw).
        pivot: world point the rotation is about [m]; None takes ``rest_position``.
        rest_position: head frame origin at rest [m].
    """

    def __init__(self, amplitude_deg=DEFAULT_AMPLITUDE_DEG, period=DEFAULT_PERIOD, start=DEFAULT_START,
                 ramp=DEFAULT_RAMP, axis=DEFAULT_AXIS["turn"], *, pivot=None, rest_position=(0.0, 0.0, 0.0)):
        super().__init__(amplitude_deg=amplitude_deg, period=period, start=start, ramp=ramp, axis=axis,
                         pivot=pivot, rest_position=rest_position)

    def _wave(self, tau):
        k = 2.0 * math.pi / self.period
        return 0.5 * (1.0 - math.cos(k * tau)), 0.5 * k * math.sin(k * tau), 0.5 * k * k * math.cos(k * tau)


class Nod(_AxisRotation):
    """Pitch oscillation, ``angle = A ramp(t) sin(2 pi tau / period)`` about the head's left-right axis.

    Args:
        amplitude_deg: largest pitch angle [deg].
        period: duration of one full nod (down, up, back) [s].
        start, ramp, pivot, rest_position: as for :class:`Turn`.
        axis: pitch axis, world (default x, the left-right axis of the generated head).
    """

    def __init__(self, amplitude_deg=DEFAULT_AMPLITUDE_DEG, period=DEFAULT_PERIOD, start=DEFAULT_START,
                 ramp=DEFAULT_RAMP, axis=DEFAULT_AXIS["nod"], *, pivot=None, rest_position=(0.0, 0.0, 0.0)):
        super().__init__(amplitude_deg=amplitude_deg, period=period, start=start, ramp=ramp, axis=axis,
                         pivot=pivot, rest_position=rest_position)

    _wave = _Oscillation._sine


class Shake(_AxisRotation):
    """Yaw oscillation (a head shake), ``angle = A ramp(t) sin(2 pi tau / period)`` about world z.

    Args:
        amplitude_deg: largest yaw angle to either side [deg].
        period: duration of one full left-right cycle [s].
        start, ramp, pivot, rest_position: as for :class:`Turn`.
        axis: yaw axis, world (default z).
    """

    def __init__(self, amplitude_deg=DEFAULT_AMPLITUDE_DEG, period=DEFAULT_PERIOD, start=DEFAULT_START,
                 ramp=DEFAULT_RAMP, axis=DEFAULT_AXIS["shake"], *, pivot=None, rest_position=(0.0, 0.0, 0.0)):
        super().__init__(amplitude_deg=amplitude_deg, period=period, start=start, ramp=ramp, axis=axis,
                         pivot=pivot, rest_position=rest_position)

    _wave = _Oscillation._sine


class Translate(_Oscillation):
    """Sinusoidal slide, ``d = distance ramp(t) sin(2 pi tau / period) axis``.

    Args:
        distance: amplitude of the slide [m].
        period: duration of one back-and-forth cycle [s].
        start, ramp, rest_position: as for :class:`Turn`.
        axis: direction of the slide, world (default x).
        pivot: unused (no rotation); accepted for a uniform signature.
    """

    def __init__(self, distance=DEFAULT_DISTANCE, period=DEFAULT_PERIOD, start=DEFAULT_START, ramp=DEFAULT_RAMP,
                 axis=DEFAULT_AXIS["translate"], *, pivot=None, rest_position=(0.0, 0.0, 0.0)):
        super().__init__(period=period, start=start, ramp=ramp, axis=axis, pivot=pivot, rest_position=rest_position)
        self.distance = float(distance)
        if not math.isfinite(self.distance):
            raise ValueError(f"head.motion.distance must be finite, got {distance!r}")

    _wave = _Oscillation._sine

    def _translation(self, t: float):
        e, ed, edd = self._envelope(t)
        return self.distance * e * self.axis, self.distance * ed * self.axis, self.distance * edd * self.axis

    def __repr__(self) -> str:
        return (f"Translate(distance={self.distance:g}, period={self.period:g}, start={self.start:g}, "
                f"ramp={self.ramp:g}, axis={self.axis.tolist()})")


def _pchip_tangent(s0: np.ndarray, s1: np.ndarray, h0: float, h1: float) -> np.ndarray:
    """Fritsch-Carlson tangent at a key between slopes ``s0`` (interval length ``h0``) and ``s1`` (``h1``), per
    component: zero where they differ in sign or one is zero, else the weighted harmonic mean (PCHIP)."""
    w0, w1 = 2.0 * h1 + h0, h1 + 2.0 * h0
    out = np.zeros_like(s0)
    same = (s0 * s1) > 0.0
    out[same] = (w0 + w1) / (w0 / s0[same] + w1 / s1[same])
    return out


def hermite_basis(u: float):
    """Cubic Hermite basis (h00, h10, h01, h11) at ``u`` and its first two derivatives in ``u``."""
    u2, u3 = u * u, u * u * u
    h = (2 * u3 - 3 * u2 + 1, u3 - 2 * u2 + u, -2 * u3 + 3 * u2, u3 - u2)
    dh = (6 * u2 - 6 * u, 3 * u2 - 4 * u + 1, -6 * u2 + 6 * u, 3 * u2 - 2 * u)
    ddh = (12 * u - 6, 6 * u - 4, -12 * u + 6, 6 * u - 2)
    return h, dh, ddh


def hermite_tangents(times: np.ndarray, values: np.ndarray, interpolation: str) -> tuple[np.ndarray, np.ndarray]:
    """Slopes at the start and the end of each key interval of a cubic Hermite curve through ``values``.

    ``"smooth"``: Catmull-Rom tangents ``m_i = (d_{i+1} - d_{i-1}) / (t_{i+1} - t_{i-1})``; ``"monotone"``:
    Fritsch-Carlson (PCHIP) per component, no overshoot; ``"linear"``: each interval's own slope. Zero at the first
    and the last key, so the curve starts and stops at rest.

    Args:
        times: (N,) strictly increasing [s].
        values: (N, ...) the keyed values.
        interpolation: one of :data:`KEY_INTERPOLATIONS`.

    Returns:
        ``(tan0, tan1)``, (N-1, ...) each, in value units per second.
    """
    t = np.asarray(times, dtype=np.float64)
    d = np.asarray(values, dtype=np.float64)
    column = (-1,) + (1,) * (d.ndim - 1)
    slopes = np.diff(d, axis=0) / np.diff(t).reshape(column)
    if interpolation == "linear":
        return slopes.copy(), slopes.copy()
    key = np.zeros_like(d)
    if interpolation == "monotone":
        for i in range(1, t.size - 1):
            key[i] = _pchip_tangent(slopes[i - 1], slopes[i], t[i] - t[i - 1], t[i + 1] - t[i])
    elif t.size > 2:
        key[1:-1] = (d[2:] - d[:-2]) / (t[2:] - t[:-2]).reshape(column)
    return key[:-1].copy(), key[1:].copy()


def hermite_interval(values, tan0, tan1, i: int, u: float, h: float):
    """Value, first and second time derivative of the cubic Hermite curve of :func:`hermite_tangents` on key
    interval ``i`` (length ``h`` [s]) at ``u`` in [0, 1]."""
    d, m0, m1 = values, tan0[i], tan1[i]
    (h00, h10, h01, h11), (d00, d10, d01, d11), (e00, e10, e01, e11) = hermite_basis(u)
    p = h00 * d[i] + h10 * h * m0 + h01 * d[i + 1] + h11 * h * m1
    v = (d00 * d[i] + d10 * h * m0 + d01 * d[i + 1] + d11 * h * m1) / h
    a = (e00 * d[i] + e10 * h * m0 + e01 * d[i + 1] + e11 * h * m1) / (h * h)
    return p, v, a


class Keyframes(_PivotMotion):
    """Keyed head poses; the pose holds before the first and after the last key.

    ``interpolation = "smooth"`` (C1): translation by cubic Hermite with Catmull-Rom tangents
    ``m_i = (d_{i+1} - d_{i-1}) / (t_{i+1} - t_{i-1})``; rotation on each interval ``R(t) = R_i exp(phi(u))``
    with ``phi`` a cubic Hermite curve in the tangent space from 0 to ``log(R_i^T R_{i+1})`` whose end slopes
    give the key's world angular velocity ``w_i`` (the time-weighted mean of the two neighbouring intervals'
    constant rates; at the end slope the inverse right Jacobian of SO(3) maps it). Velocities are continuous
    at every key and zero at the first and last key; accelerations jump at keys. Catmull-Rom overshoots next to
    a jump (a head held still before a fast move drifts backwards first).

    ``"monotone"`` (C1, no overshoot): the same Hermite curves with Fritsch-Carlson tangents, per component of
    the translation (the PCHIP rule: zero where the neighbouring slopes differ in sign, else their weighted
    harmonic mean), and for the rotation the key's angular velocity is zero where the neighbouring rates turn
    opposite ways and otherwise at most the slower one's. ``"linear"``: constant velocity within each interval
    (translation and rotation), jumping at keys. Derivatives are analytic.

    Args:
        times: strictly increasing key times [s], (N,).
        translations: head translations at the keys [m], world, (N, 3).
        rotations: head rotations at the keys, quaternions (x, y, z, w), (N, 4); consecutive keys
            must differ by less than 180 degrees.
        pivot: world point the rotation is about [m]; None takes ``rest_position``.
        rest_position: head frame origin at rest [m].
        interpolation: one of :data:`KEY_INTERPOLATIONS`.
    """

    def __init__(self, times, translations, rotations, *, pivot=None, rest_position=(0.0, 0.0, 0.0),
                 interpolation: str = "smooth"):
        super().__init__(pivot, rest_position)
        if interpolation not in KEY_INTERPOLATIONS:
            raise ValueError(f"head.motion.interpolation: unknown {interpolation!r}; choose one of "
                             f"{', '.join(KEY_INTERPOLATIONS)}")
        self.interpolation = interpolation
        t = np.asarray(times, dtype=np.float64).reshape(-1)
        d = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(rotations, dtype=np.float64).reshape(-1, 4)
        n = t.size
        if n == 0:
            raise ValueError("head.motion.keys: at least one key is needed")
        if d.shape[0] != n or q.shape[0] != n:
            raise ValueError(f"head.motion.keys: {n} times, {d.shape[0]} translations, {q.shape[0]} rotations")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(d)) and np.all(np.isfinite(q))):
            raise ValueError("head.motion.keys: times, translations and rotations must be finite")
        bad = np.flatnonzero(np.diff(t) <= 0.0)
        if bad.size:
            i = int(bad[0]) + 1
            raise ValueError(f"head.motion.keys[{i}].time: key times must increase strictly, "
                             f"got {t[i - 1]:g} then {t[i]:g}")
        norms = np.linalg.norm(q, axis=1)
        if np.any(norms < 1.0e-9):
            raise ValueError("head.motion.keys: a rotation quaternion is zero")
        q = q / norms[:, None]
        self.times, self.translations, self.rotations = t, d, q

        # Translation tangents at the interval ends, zero at the first and last key so the head starts and stops at
        # rest (linear: each interval's own constant slope).
        self._tan0, self._tan1 = hermite_tangents(t, d, interpolation)

        # Rotation: interval steps log(R_i^T R_{i+1}) and world angular velocities at the keys.
        self._delta = np.zeros((max(n - 1, 0), 3))
        for i in range(n - 1):
            self._delta[i] = _quat_log(quat_multiply(_conj(q[i]), q[i + 1]))
            angle = float(np.linalg.norm(self._delta[i]))
            if angle > math.pi - 1.0e-6:
                raise ValueError(f"head.motion.keys[{i + 1}]: the rotation differs from key {i} by "
                                 f"{math.degrees(angle):.1f} deg; keep consecutive keys under 180 deg apart")
        rates = [quat_rotate(q[i], self._delta[i]) / (t[i + 1] - t[i]) for i in range(n - 1)]
        self._omega = np.zeros((n, 3))
        for i in range(1, n - 1):
            h0, h1 = t[i] - t[i - 1], t[i + 1] - t[i]
            self._omega[i] = (h0 * rates[i - 1] + h1 * rates[i]) / (h0 + h1)
            if interpolation == "monotone":
                r0, r1 = rates[i - 1], rates[i]
                if float(np.dot(r0, r1)) <= 0.0:
                    self._omega[i] = 0.0
                else:
                    cap = min(np.linalg.norm(r0), np.linalg.norm(r1))
                    size = float(np.linalg.norm(self._omega[i]))
                    if size > cap:
                        self._omega[i] *= cap / size
        # Tangent-space end slopes per interval, d(phi)/du at u = 0 and u = 1 (linear: the interval's step).
        self._slope0 = np.zeros((max(n - 1, 0), 3))
        self._slope1 = np.zeros((max(n - 1, 0), 3))
        for i in range(n - 1):
            h = t[i + 1] - t[i]
            if interpolation == "linear":
                self._slope0[i] = self._slope1[i] = self._delta[i]
                continue
            self._slope0[i] = h * quat_rotate(_conj(q[i]), self._omega[i])
            self._slope1[i] = h * (right_jacobian_inv(self._delta[i]) @ quat_rotate(_conj(q[i + 1]),
                                                                                     self._omega[i + 1]))
        # the same tables as plain floats, for _curves
        self._keys = SimpleNamespace(
            times=t.tolist(), translations=d.tolist(), rotations=q.tolist(), tan0=self._tan0.tolist(),
            tan1=self._tan1.tolist(), slope0=self._slope0.tolist(), slope1=self._slope1.tolist(),
            delta=self._delta.tolist(), pivot=self.pivot.tolist(), offset=(self.rest_position - self.pivot).tolist())

    @classmethod
    def from_keys(cls, keys: Sequence[Mapping], *, pivot=None, rest_position=(0.0, 0.0, 0.0),
                  interpolation: str = "smooth") -> Keyframes:
        """Keyframes from tables with ``time``, ``translate`` and ``rotate_deg`` or ``axis`` + ``angle_deg``."""
        times, trans, rots = [], [], []
        for i, key in enumerate(keys):
            key = {k: v for k, v in dict(key).items() if v is not None}
            where = f"head.motion.keys[{i}]"
            unknown = sorted(set(key) - {"time", "translate", "rotate_deg", "axis", "angle_deg"})
            if unknown:
                raise ValueError(f"{where}.{unknown[0]}: unknown key")
            if "time" not in key:
                raise ValueError(f"{where}.time: missing")
            times.append(float(key["time"]))
            trans.append(_vec3(key.get("translate", (0.0, 0.0, 0.0)), f"{where}.translate"))
            if "rotate_deg" in key and ("axis" in key or "angle_deg" in key):
                raise ValueError(f"{where}: give the rotation as rotate_deg or as axis and angle_deg, not both")
            if "rotate_deg" in key:
                rots.append(euler_xyz_deg_to_quat(_vec3(key["rotate_deg"], f"{where}.rotate_deg")))
            elif "axis" in key or "angle_deg" in key:
                if "axis" not in key or "angle_deg" not in key:
                    raise ValueError(f"{where}: axis and angle_deg go together")
                rots.append(_quat_axis_angle(_unit(key["axis"], f"{where}.axis"),
                                             math.radians(float(key["angle_deg"]))))
            else:
                rots.append(_IDENTITY_Q.copy())
        return cls(times, trans, rots, pivot=pivot, rest_position=rest_position, interpolation=interpolation)

    def _locate(self, t: float):
        """(interval i, u in [0, 1], interval length) or (key index, None, None) outside the keys."""
        tk = self._keys.times
        if t <= tk[0]:
            return 0, None, None
        if t >= tk[-1]:
            return len(tk) - 1, None, None
        i = bisect.bisect_right(tk, t) - 1
        h = tk[i + 1] - tk[i]
        return i, (t - tk[i]) / h, h

    def _curves(self, t: float, derivatives: bool):
        """``(q, qd, qdd, d, dd, ddd)`` at ``t`` as plain floats (lists; the derivatives None unless asked for): the
        arithmetic of :meth:`_rotation` and :meth:`_translation`, without numpy's cost per small array (the runner
        asks for a sample and a pose around every step, between the kernels, on one thread: 140 us a step in numpy,
        on the mohawk's keys)."""
        k = self._keys
        i, u, h = self._locate(t)
        if u is None:
            zero4, zero3 = [0.0] * 4, [0.0] * 3
            return k.rotations[i], zero4, zero4, k.translations[i], zero3, zero3
        (h00, h10, h01, h11), (d00, d10, d01, d11), (e00, e10, e01, e11) = hermite_basis(u)
        s0, s1, dl = k.slope0[i], k.slope1[i], k.delta[i]
        half = [0.5 * (h10 * a + h01 * b + h11 * c) for a, b, c in zip(s0, dl, s1)]
        d0, d1 = k.translations[i], k.translations[i + 1]
        m0, m1 = k.tan0[i], k.tan1[i]
        d = [h00 * a + h10 * h * b + h01 * c + h11 * h * e for a, b, c, e in zip(d0, m0, d1, m1)]
        qi = k.rotations[i]
        x = half[0] * half[0] + half[1] * half[1] + half[2] * half[2]
        f, f1, f2, c = _exp_functions(x)
        e = [f * half[0], f * half[1], f * half[2], c]
        if not derivatives:
            return _quat_multiply_floats(qi, e), None, None, d, None, None
        halfd = [0.5 * (d10 * a + d01 * b + d11 * cc) / h for a, b, cc in zip(s0, dl, s1)]
        halfdd = [0.5 * (e10 * a + e01 * b + e11 * cc) / (h * h) for a, b, cc in zip(s0, dl, s1)]
        xd = 2.0 * (half[0] * halfd[0] + half[1] * halfd[1] + half[2] * halfd[2])
        xdd = 2.0 * ((halfd[0] * halfd[0] + halfd[1] * halfd[1] + halfd[2] * halfd[2])
                     + (half[0] * halfdd[0] + half[1] * halfdd[1] + half[2] * halfdd[2]))
        c1, c2 = -0.5 * f, -0.5 * f1
        ed = [f1 * xd * v + f * vd for v, vd in zip(half, halfd)] + [c1 * xd]
        edd = [f2 * xd * xd * v + f1 * xdd * v + 2.0 * f1 * xd * vd + f * vdd
               for v, vd, vdd in zip(half, halfd, halfdd)] + [c2 * xd * xd + c1 * xdd]
        dd = [(d00 * a + d10 * h * b + d01 * cc + d11 * h * ee) / h for a, b, cc, ee in zip(d0, m0, d1, m1)]
        ddd = [(e00 * a + e10 * h * b + e01 * cc + e11 * h * ee) / (h * h) for a, b, cc, ee in zip(d0, m0, d1, m1)]
        return (_quat_multiply_floats(qi, e), _quat_multiply_floats(qi, ed), _quat_multiply_floats(qi, edd),
                d, dd, ddd)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        q, _, _, d, _, _ = self._curves(float(t), derivatives=False)
        r = rotate_floats(q, self._keys.offset)
        n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        p = self._keys.pivot
        return (np.array([p[0] + d[0] + r[0], p[1] + d[1] + r[1], p[2] + d[2] + r[2]]),
                np.array([q[0] / n, q[1] / n, q[2] / n, q[3] / n]))

    def evaluate(self, t: float) -> MotionSample:
        """As :meth:`_PivotMotion.evaluate` of :meth:`_rotation` and :meth:`_translation`, in plain floats."""
        q, qd, qdd, d, dd, ddd = self._curves(float(t), derivatives=True)
        qc = [-q[0], -q[1], -q[2], q[3]]
        w = [2.0 * v for v in _quat_multiply_floats(qd, qc)[:3]]
        al = [2.0 * v for v in _quat_multiply_floats(qdd, qc)[:3]]
        r = rotate_floats(q, self._keys.offset)
        wr = _cross_floats(w, r)
        accel = [a + b + c for a, b, c in zip(ddd, _cross_floats(al, r), _cross_floats(w, wr))]
        n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        p = self._keys.pivot
        return MotionSample(
            position=np.array([p[0] + d[0] + r[0], p[1] + d[1] + r[1], p[2] + d[2] + r[2]]),
            rotation=np.array([q[0] / n, q[1] / n, q[2] / n, q[3] / n]),
            linear_velocity=np.array([dd[0] + wr[0], dd[1] + wr[1], dd[2] + wr[2]]),
            angular_velocity=np.array(w),
            linear_acceleration=np.array(accel),
            angular_acceleration=np.array(al),
        )

    def _translation(self, t: float):
        i, u, h = self._locate(t)
        if u is None:
            return self.translations[i], _ZERO3, _ZERO3
        return hermite_interval(self.translations, self._tan0, self._tan1, i, u, h)

    def _rotation(self, t: float):
        i, u, h = self._locate(t)
        if u is None:
            return self.rotations[i], np.zeros(4), np.zeros(4)
        (_, h10, h01, h11), (_, d10, d01, d11), (_, e10, e01, e11) = hermite_basis(u)
        s0, s1, dl = self._slope0[i], self._slope1[i], self._delta[i]
        phi = h10 * s0 + h01 * dl + h11 * s1
        phid = (d10 * s0 + d01 * dl + d11 * s1) / h
        phidd = (e10 * s0 + e01 * dl + e11 * s1) / (h * h)
        e, ed, edd = _exp_derivatives(0.5 * phi, 0.5 * phid, 0.5 * phidd)
        qi = self.rotations[i]
        return quat_multiply(qi, e), quat_multiply(qi, ed), quat_multiply(qi, edd)

    def __repr__(self) -> str:
        t = self.times
        return f"Keyframes({t.size} keys, {t[0]:g}..{t[-1]:g} s, pivot={self.pivot.tolist()})"


class Compose(HeadMotion):
    """``outer`` carried on top of ``inner``: ``M(t) = M_outer(t) T(-rest_outer) M_inner(t)``.

    The outer motion's displacement from its own rest pose is applied, in the world, to the head
    that the inner motion moves; e.g. ``Compose(Translate(...), Nod(...))`` is a nodding head that
    also slides, and ``Compose(Turn(...), Nod(...))`` nods about the turned head's left-right axis.

    Args:
        outer: the carrying motion.
        inner: the carried motion; its ``rest_position`` is the composition's.
    """

    def __init__(self, outer: HeadMotion, inner: HeadMotion):
        self.outer, self.inner = outer, inner
        self.rest_position = np.asarray(inner.rest_position, dtype=np.float64)
        self._unrest = _static_sample(-np.asarray(outer.rest_position, dtype=np.float64))

    def evaluate(self, t: float) -> MotionSample:
        return _product(_product(self.outer.evaluate(t), self._unrest), self.inner.evaluate(t))

    def __repr__(self) -> str:
        return f"Compose({self.outer!r}, {self.inner!r})"
