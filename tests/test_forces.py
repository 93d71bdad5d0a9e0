"""Wind, air drag and a moving head against closed-form equilibria of a hinged rigid segment."""

import math

import numpy as np

from hairwarp.model import Model, StrandParams
from hairwarp.runner import Stepper
from hairwarp.solver import Solver

# Equilibria are reached to ~1e-6 rad after the damped transient; 2e-3 rad covers float32 and the
# residual swing with margin.
ANGLE_TOL = 2e-3
L, R, RHO, G = 0.1, 2e-3, 1300.0, 9.81


def hinged_segment(device, drag=0.0):
    verts = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, -L]]])
    params = StrandParams(density=RHO, radius=R, bend_stiffness=0.0, damping=2e-6, drag=drag)
    return Model.build(verts, params, segments=1, device=device)


def tilt_from_vertical(model, state):
    p = state.vertex_positions.numpy()
    d = p[1] - p[0]
    return math.atan2(math.hypot(d[0], d[1]), -d[2]), d


def test_wind_tilts_a_segment_to_the_closed_form_angle(device):
    # uniform drag load drag*wind per metre against gravity rho*A*g per metre, both at the midpoint:
    # tan(theta) = drag * wind / (rho * pi r^2 * g)
    drag, wind = 0.05, 2.0
    model = hinged_segment(device, drag=drag)
    stepper = Stepper(Solver(model, "implicit_joints"), dt=1e-3, substeps=500)
    stepper.control.set_wind((wind, 0.0, 0.0))
    for _ in range(8):
        stepper.advance_frame()
    theta, d = tilt_from_vertical(model, stepper.state)
    expected = math.atan(drag * wind / (RHO * math.pi * R * R * G))
    assert d[0] > 0.0 and abs(theta - expected) < ANGLE_TOL, (theta, expected)


def test_accelerating_head_tilts_a_segment_by_atan_a_over_g(device):
    # a head accelerating at a along +x: in its frame the segment hangs back at tan(theta) = a / g
    a = 3.0
    model = hinged_segment(device)
    stepper = Stepper(Solver(model, "implicit_joints"), dt=1e-3, substeps=500)

    def head(t, control):
        control.set_head(position=(0.5 * a * t * t, 0.0, 0.0), linear_velocity=(a * t, 0.0, 0.0),
                         linear_acceleration=(a, 0.0, 0.0))

    for _ in range(8):
        stepper.advance_frame(head)
    theta, d = tilt_from_vertical(model, stepper.state)
    assert d[0] < 0.0 and abs(theta - math.atan(a / G)) < ANGLE_TOL, (theta, math.atan(a / G))
    # the root rides on the head: it is where the head put it at the last step
    t = stepper.time
    np.testing.assert_allclose(stepper.state.vertex_positions.numpy()[0], [0.5 * a * t * t, 0, 0], rtol=1e-5)
