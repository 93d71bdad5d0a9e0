"""Head motions: analytic velocities and accelerations against central differences, keys, smooth starts.

The reference is independent of the module's quaternion algebra: rotations go through SciPy's
``Rotation`` and the angular velocity is recovered from ``omega = 2 (dq/dt conj(q)).vec`` with a
central difference of the sampled quaternions.
"""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hairwarp.motion import (
    Compose,
    HeadMotion,
    Keyframes,
    Nod,
    Shake,
    Still,
    Translate,
    Turn,
    euler_xyz_deg_to_quat,
)

# Central-difference step [s]: truncation ~ h^2 * (third derivative) ~ 1e-8 * (2 pi / 0.7)^3 ~ 1e-5 relative,
# round-off ~ 1e-16 / h ~ 1e-12.
FD_STEP = 1.0e-4
# Relative tolerance of a derivative against its central difference (truncation above, with margin).
FD_RTOL = 1.0e-5
# Absolute floor of that comparison, for components that are zero [per unit of the derivative].
FD_ATOL = 1.0e-7
# Unit-norm and pass-through-key tolerance (float64 algebra).
EXACT_TOL = 1.0e-12

PIVOT = np.array([0.01, -0.02, 1.49])
REST = np.array([0.0, 0.03, 0.05])


def _keyframes():
    return Keyframes.from_keys(
        [
            {"time": 0.1},
            {"time": 0.6, "rotate_deg": [10.0, -20.0, 60.0], "translate": [0.02, 0.0, -0.01]},
            {"time": 1.0, "axis": [0.3, 1.0, 0.2], "angle_deg": -35.0, "translate": [-0.03, 0.05, 0.0]},
            {"time": 1.9, "rotate_deg": [0.0, 0.0, 170.0]},
            {"time": 2.3, "rotate_deg": [-30.0, 15.0, 100.0], "translate": [0.0, 0.0, 0.04]},
        ],
        pivot=PIVOT,
        rest_position=REST,
    )


MOTIONS = {
    "still": lambda: Still(rest_position=REST),
    "turn": lambda: Turn(40.0, period=1.3, start=0.1, ramp=0.4, pivot=PIVOT, rest_position=REST),
    "nod": lambda: Nod(25.0, period=0.9, start=0.0, ramp=0.3, pivot=PIVOT, rest_position=REST),
    "shake": lambda: Shake(-30.0, period=0.7, start=0.2, ramp=0.25, axis=(0.1, 0.2, 1.0), pivot=PIVOT),
    "translate": lambda: Translate(0.04, period=1.1, start=0.05, ramp=0.5, axis=(1.0, 1.0, 0.0), rest_position=REST),
    "keyframes": _keyframes,
    "compose": lambda: Compose(Turn(50.0, period=1.7, ramp=0.6, pivot=PIVOT, rest_position=REST),
                               Compose(Translate(0.03, period=0.8, axis=(0, 1, 0)),
                                       Nod(20.0, period=0.6, ramp=0.2, pivot=PIVOT, rest_position=REST))),
}
# Times inside the ramps, after them, and (keyframes) inside intervals, away from the keys where the
# acceleration of a C1 spline jumps.
TIMES = (0.23, 0.37, 0.81, 1.27, 2.05, 2.71)


def _sample(m, t):
    s = m.evaluate(t)
    return s.position, Rotation.from_quat(s.rotation), s


def _omega_from_quats(q_minus, q, q_plus, h):
    """World angular velocity from a central difference of quaternions: 2 (dq/dt * conj(q)).vec."""
    if np.dot(q_minus, q) < 0.0:
        q_minus = -q_minus
    if np.dot(q_plus, q) < 0.0:
        q_plus = -q_plus
    qd = (q_plus - q_minus) / (2.0 * h)
    # Hamilton product qd * conj(q), vector part, with SciPy-independent algebra written out.
    x1, y1, z1, w1 = qd
    x2, y2, z2, w2 = -q[0], -q[1], -q[2], q[3]
    vec = np.array([
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])
    return 2.0 * vec


def _close(actual, expected, scale):
    np.testing.assert_allclose(actual, expected, rtol=FD_RTOL, atol=FD_ATOL + FD_RTOL * scale)


@pytest.mark.parametrize("kind", sorted(MOTIONS))
@pytest.mark.parametrize("t", TIMES)
def test_derivatives_match_central_differences(kind, t):
    m = MOTIONS[kind]()
    h = FD_STEP
    sm, s0, sp = m.evaluate(t - h), m.evaluate(t), m.evaluate(t + h)

    v_fd = (sp.position - sm.position) / (2.0 * h)
    _close(s0.linear_velocity, v_fd, np.abs(v_fd).max())

    w_fd = _omega_from_quats(sm.rotation, s0.rotation, sp.rotation, h)
    _close(s0.angular_velocity, w_fd, np.abs(w_fd).max())

    a_fd = (sp.linear_velocity - sm.linear_velocity) / (2.0 * h)
    _close(s0.linear_acceleration, a_fd, np.abs(a_fd).max())
    # Second difference of positions: independent of the analytic velocity.
    a_fd2 = (sp.position - 2.0 * s0.position + sm.position) / (h * h)
    np.testing.assert_allclose(s0.linear_acceleration, a_fd2, rtol=1e-4, atol=1e-5 * (1.0 + np.abs(a_fd2).max()))

    al_fd = (sp.angular_velocity - sm.angular_velocity) / (2.0 * h)
    _close(s0.angular_acceleration, al_fd, np.abs(al_fd).max())


@pytest.mark.parametrize("kind", sorted(MOTIONS))
def test_rotation_is_unit_and_matrix_consistent(kind):
    m = MOTIONS[kind]()
    for t in np.linspace(-0.5, 3.0, 71):
        s = m.evaluate(t)
        assert abs(np.linalg.norm(s.rotation) - 1.0) < EXACT_TOL
        M = s.matrix()
        np.testing.assert_allclose(M[:3, :3], Rotation.from_quat(s.rotation).as_matrix(), atol=EXACT_TOL)
        np.testing.assert_allclose(M[:3, 3], s.position, atol=EXACT_TOL)
        np.testing.assert_allclose(M[3], [0, 0, 0, 1])


@pytest.mark.parametrize("kind", ["turn", "nod", "shake", "translate", "keyframes", "compose"])
def test_smooth_start(kind):
    """At rest before the motion starts; zero velocity at t = 0 and at the start; bounded acceleration."""
    m = MOTIONS[kind]()
    s0 = m.evaluate(0.0)
    for v in (s0.linear_velocity, s0.angular_velocity):
        np.testing.assert_allclose(v, 0.0, atol=EXACT_TOL)
    # Acceleration stays finite and continuous through the start: no jump between just before and just after.
    start = getattr(m, "start", 0.0)
    before, after = m.evaluate(start - 1e-9), m.evaluate(start + 1e-9)
    np.testing.assert_allclose(after.linear_acceleration, before.linear_acceleration, atol=1e-6)
    np.testing.assert_allclose(after.angular_acceleration, before.angular_acceleration, atol=1e-6)


def test_still_is_rest_pose():
    s = Still(rest_position=REST).evaluate(1.7)
    np.testing.assert_allclose(s.matrix(), np.block([[np.eye(3), REST[:, None]], [np.zeros((1, 3)), 1.0]]))


def test_turn_closed_form():
    """Turn is a yaw about the pivot by A (1 - cos(2 pi tau / P)) / 2 once the ramp is over."""
    A, P, start, ramp = 40.0, 1.3, 0.1, 0.4
    m = Turn(A, period=P, start=start, ramp=ramp, pivot=PIVOT, rest_position=REST)
    t = 1.0
    angle = math.radians(A) * 0.5 * (1.0 - math.cos(2.0 * math.pi * (t - start) / P))
    R = Rotation.from_rotvec([0.0, 0.0, angle])
    s = m.evaluate(t)
    np.testing.assert_allclose(Rotation.from_quat(s.rotation).as_matrix(), R.as_matrix(), atol=EXACT_TOL)
    np.testing.assert_allclose(s.position, PIVOT + R.apply(REST - PIVOT), atol=EXACT_TOL)
    rate = math.radians(A) * 0.5 * (2.0 * math.pi / P) * math.sin(2.0 * math.pi * (t - start) / P)
    np.testing.assert_allclose(s.angular_velocity, [0.0, 0.0, rate], atol=EXACT_TOL)


@pytest.mark.parametrize("cls", [Turn, Nod, Shake])
def test_axis_turns_in_closed_form_match_the_quaternion_derivatives(cls):
    """Turn, nod and shake sample themselves in closed form (Rodrigues' formula, ``omega = a' k``) at every step;
    the general path differentiates the quaternion ``exp(a k / 2)``. Both agree to float64 round-off (1e-13 of the
    largest value: a dozen products and sums), over the ramp, before the start, at tiny and large angles, about a
    tilted axis, and so do the poses the teleport test reads."""
    from hairwarp.motion import _PivotMotion

    for amplitude in (45.0, -30.0, 1.0e-3, 170.0):
        m = cls(amplitude, period=1.3, start=0.2, ramp=0.4, axis=(1.0, 0.2, -0.3), pivot=(0.1, -0.2, 1.4),
                rest_position=(0.0, 0.05, 1.6))
        for t in np.linspace(0.0, 3.0, 61):
            fast, general = m.evaluate(t), _PivotMotion.evaluate(m, t)
            for name in ("position", "rotation", "linear_velocity", "angular_velocity", "linear_acceleration",
                         "angular_acceleration"):
                want = getattr(general, name)
                np.testing.assert_allclose(getattr(fast, name), want, rtol=0.0,
                                           atol=1e-13 * max(1.0, float(np.abs(want).max())), err_msg=name)
            position, rotation = m.pose(t)
            want_position, want_rotation = _PivotMotion.pose(m, t)
            np.testing.assert_allclose(position, want_position, rtol=0.0, atol=1e-13)
            np.testing.assert_allclose(rotation, want_rotation, rtol=0.0, atol=1e-13)


@pytest.mark.parametrize("interpolation", ["smooth", "monotone", "linear"])
def test_keyframes_in_plain_floats_match_their_numpy_curves(interpolation):
    """Keyframes sample themselves in plain floats (the runner asks for a sample and a pose around every step); the
    general path composes the numpy curves ``_rotation`` and ``_translation``. Both agree to float64 round-off (1e-12
    of the largest value: the accelerations divide by the interval's square and sum a few dozen products), inside
    the intervals, at and just past the keys, and held before and after them; so do the poses."""
    from hairwarp.motion import _PivotMotion

    m = _keyframes()
    m = Keyframes(m.times, m.translations, m.rotations, pivot=PIVOT, rest_position=REST, interpolation=interpolation)
    times = np.concatenate([np.linspace(-0.5, 3.0, 141), m.times, m.times + 1e-9, m.times - 1e-9])
    for t in times:
        fast, general = m.evaluate(t), _PivotMotion.evaluate(m, t)
        for name in ("position", "rotation", "linear_velocity", "angular_velocity", "linear_acceleration",
                     "angular_acceleration"):
            want = getattr(general, name)
            got = getattr(fast, name)
            assert got.shape == want.shape and got.dtype == want.dtype
            np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-12 * max(1.0, float(np.abs(want).max())),
                                       err_msg=f"{name} at t = {t}")
        position, rotation = m.pose(t)
        want_position, want_rotation = _PivotMotion.pose(m, t)
        np.testing.assert_allclose(position, want_position, rtol=0.0, atol=1e-13)
        np.testing.assert_allclose(rotation, want_rotation, rtol=0.0, atol=1e-13)


def test_nod_swings_about_the_pivot():
    """A nod about a pivot below the head moves the head origin; the distance to the pivot is kept."""
    m = Nod(30.0, period=1.0, ramp=0.0, pivot=PIVOT, rest_position=REST)
    s = m.evaluate(0.25)  # the peak of sin
    assert np.linalg.norm(s.position - REST) > 0.01
    assert abs(np.linalg.norm(s.position - PIVOT) - np.linalg.norm(REST - PIVOT)) < EXACT_TOL
    np.testing.assert_allclose(Rotation.from_quat(s.rotation).as_rotvec(), [math.radians(30.0), 0, 0], atol=1e-12)


def test_keyframes_pass_through_keys():
    keys = [
        {"time": 0.1},
        {"time": 0.6, "rotate_deg": [10.0, -20.0, 60.0], "translate": [0.02, 0.0, -0.01]},
        {"time": 1.0, "axis": [0.3, 1.0, 0.2], "angle_deg": -35.0, "translate": [-0.03, 0.05, 0.0]},
        {"time": 1.9, "rotate_deg": [0.0, 0.0, 170.0]},
        {"time": 2.3, "rotate_deg": [-30.0, 15.0, 100.0], "translate": [0.0, 0.0, 0.04]},
    ]
    m = _keyframes()
    for key in keys:
        if "rotate_deg" in key:
            R = Rotation.from_euler("xyz", key["rotate_deg"], degrees=True)
        elif "axis" in key:
            axis = np.asarray(key["axis"]) / np.linalg.norm(key["axis"])
            R = Rotation.from_rotvec(axis * math.radians(key["angle_deg"]))
        else:
            R = Rotation.identity()
        d = np.asarray(key.get("translate", [0.0, 0.0, 0.0]))
        s = m.evaluate(key["time"])
        np.testing.assert_allclose(Rotation.from_quat(s.rotation).as_matrix(), R.as_matrix(), atol=EXACT_TOL)
        np.testing.assert_allclose(s.position, PIVOT + d + R.apply(REST - PIVOT), atol=EXACT_TOL)
    # Held before the first and after the last key, at rest.
    for t in (-1.0, 0.0, 2.3, 5.0):
        s = m.evaluate(t)
        np.testing.assert_allclose(s.spatial_velocity(), 0.0, atol=EXACT_TOL)
        np.testing.assert_allclose(s.spatial_acceleration(), 0.0, atol=EXACT_TOL)


def test_keyframes_are_c1_at_keys():
    """Linear and angular velocity are continuous across every inner key (the spline is C1)."""
    m = _keyframes()
    for t in m.times[1:-1]:
        a, b = m.evaluate(t - 1e-9), m.evaluate(t + 1e-9)
        np.testing.assert_allclose(a.angular_velocity, b.angular_velocity, atol=1e-6)
        np.testing.assert_allclose(a.linear_velocity, b.linear_velocity, atol=1e-6)
        assert np.linalg.norm(a.angular_velocity) > 0.1  # the head moves through the key, it does not stop


def test_euler_convention_matches_scipy():
    rng = np.random.default_rng(3)
    for angles in rng.uniform(-180, 180, size=(10, 3)):
        q = euler_xyz_deg_to_quat(angles)
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(),
                                   Rotation.from_euler("xyz", angles, degrees=True).as_matrix(), atol=EXACT_TOL)


def test_from_config_kinds_and_defaults():
    assert isinstance(HeadMotion.from_config({}), Still)
    m = HeadMotion.from_config({"kind": "nod", "period": 0.8, "amplitude_deg": 15.0, "distance": 0.1},
                               pivot=PIVOT)
    assert isinstance(m, Nod) and m.period == 0.8
    np.testing.assert_allclose(m.axis, [1.0, 0.0, 0.0])
    np.testing.assert_allclose(m.pivot, PIVOT)
    m = HeadMotion.from_config({"kind": "shake", "pivot": [0.0, 0.0, 1.0]}, pivot=PIVOT)
    np.testing.assert_allclose(m.pivot, [0.0, 0.0, 1.0])  # the table's pivot wins
    np.testing.assert_allclose(m.axis, [0.0, 0.0, 1.0])
    m = HeadMotion.from_config({"kind": "keyframes", "keys": [{"time": 0.0}, {"time": 1.0, "rotate_deg": [0, 0, 90]}]})
    assert isinstance(m, Keyframes)


@pytest.mark.parametrize(
    "cfg, match",
    [
        ({"kind": "wobble"}, "head.motion.kind"),
        ({"kind": "turn", "perod": 1.0}, "perod"),
        ({"kind": "turn", "period": 0.0}, "period"),
        ({"kind": "nod", "axis": [0, 0, 0]}, "axis"),
        ({"kind": "keyframes"}, "keys"),
        ({"kind": "keyframes", "keys": [{"time": 1.0}, {"time": 0.5}]}, r"keys\[1\]\.time"),
        ({"kind": "keyframes", "keys": [{"time": 0.0}, {"time": 1.0, "rotate_deg": [0, 0, 180]}]}, "180"),
    ],
)
def test_from_config_errors(cfg, match):
    with pytest.raises(ValueError, match=match):
        HeadMotion.from_config(cfg)


def _translation_keys(values, times):
    return Keyframes(times, [[v, 0.0, 0.0] for v in values], [[0.0, 0.0, 0.0, 1.0]] * len(times),
                     interpolation="monotone")


def test_monotone_keyframes_match_pchip_and_never_overshoot():
    """Monotone keys take SciPy's PCHIP (Fritsch-Carlson) tangents at the inner keys and stay within each interval's
    ends; the smooth (Catmull-Rom) curve drifts backwards before a jump."""
    from scipy.interpolate import PchipInterpolator

    times = np.array([0.0, 1.0, 1.1, 1.5, 2.5])
    values = np.array([0.0, 0.0, 0.5, 0.55, 0.2])  # held, a jump, a slow rise, back down
    m = _translation_keys(values, times)
    ref = PchipInterpolator(times, values).derivative()
    for i in range(1, len(times) - 1):
        # the motion's velocity just past the key is the key's tangent
        np.testing.assert_allclose(m.evaluate(times[i]).linear_velocity[0], ref(times[i]), rtol=1e-12, atol=1e-12)
    for a, b, va, vb in zip(times[:-1], times[1:], values[:-1], values[1:]):
        x = np.array([m.evaluate(t).position[0] for t in np.linspace(a, b, 201)])
        assert x.min() >= min(va, vb) - 1e-12 and x.max() <= max(va, vb) + 1e-12
        assert np.all(np.diff(x) * np.sign(vb - va) >= -1e-12)  # monotone within the interval
    smooth = Keyframes(times, [[v, 0.0, 0.0] for v in values], [[0.0, 0.0, 0.0, 1.0]] * len(times))
    drift = min(smooth.evaluate(t).position[0] for t in np.linspace(0.0, 1.0, 101))
    assert drift < -1e-3  # the overshoot that "monotone" removes


def test_linear_keyframes_move_at_constant_speed():
    times, values = [0.0, 1.0, 3.0], [0.0, 0.2, -0.2]
    m = Keyframes(times, [[v, 0.0, 0.0] for v in values],
                  [euler_xyz_deg_to_quat((0.0, 0.0, a)) for a in (0.0, 30.0, 90.0)], interpolation="linear")
    # 30 deg in the first second, 60 deg in the next two: 30 deg/s throughout
    for t, v in ((0.3, 0.2), (0.9, 0.2), (1.5, -0.2), (2.7, -0.2)):
        s = m.evaluate(t)
        np.testing.assert_allclose(s.position[0] - m.evaluate(t - 1e-6).position[0], v * 1e-6, rtol=1e-5)
        np.testing.assert_allclose(s.angular_velocity, (0.0, 0.0, math.radians(30.0)), atol=1e-12)
        np.testing.assert_allclose(s.linear_acceleration, 0.0, atol=1e-12)


def test_keyframe_interpolation_is_checked():
    with pytest.raises(ValueError, match="interpolation"):
        Keyframes([0.0, 1.0], [[0.0] * 3] * 2, [[0.0, 0.0, 0.0, 1.0]] * 2, interpolation="cubic")
