"""Trajectories and invariants of the strand dynamics against independent references:
MuJoCo RK4, the small-angle pendulum, energy from Pinocchio, and the known failure of explicit
joint springs."""

import math

import numpy as np
import pinocchio as pin
import pytest
from _reference import chain_model, mujoco_trajectory

from hairwarp.model import Model, StrandParams
from hairwarp.solver import SimulationFault, Solver

# The reference strand of the peers' study: 20 segments of 15 mm, r = 2 mm, rho = 1300, from 80 deg.
S_REF, L_REF, DURATION = 20, 0.015, 1.0


def reference_strand(device, *, segments=S_REF, length=L_REF, angle_deg=80.0, params=None):
    a = math.radians(angle_deg)
    d = np.array([-math.sin(a), 0.0, -math.cos(a)])
    verts = (np.arange(segments + 1)[:, None] * length * d)[None]
    params = params or StrandParams(density=1300.0, radius=0.002, bend_stiffness=0.0, damping=0.0)
    return Model.build(verts, params, segments=segments, device=device)


def run(model, integrator, dt, duration, *, sample_dt=1e-3, frame_check=None):
    """Tip positions every ``sample_dt``; with ``frame_check`` the fault check runs every that many steps."""
    solver = Solver(model, integrator)
    s0, s1, control = model.state(), model.state(), model.control()
    steps = int(round(duration / dt))
    every = max(1, int(round(sample_dt / dt)))
    S = model.seg_per_strand
    tips = [s0.vertex_positions.numpy()[S].copy()]
    for n in range(1, steps + 1):
        solver.step(s0, s1, control, dt)
        s0, s1 = s1, s0
        if frame_check and n % frame_check == 0:
            solver.check(s0, n // frame_check)
        if n % every == 0:
            tips.append(s0.vertex_positions.numpy()[S].copy())
    return np.array(tips), s0


@pytest.fixture(scope="module")
def mujoco_reference():
    """MuJoCo RK4 at dt = 1e-4 (converged to ~5e-8 m, peers' study), tip every 1 ms over 1 s."""
    model = reference_strand("cpu")
    traj = mujoco_trajectory(model.seg_length.numpy().astype(float), model.seg_mass.numpy().astype(float),
                             model.seg_inertia.numpy().astype(float), np.zeros(3), model.joint_q0.numpy(),
                             duration=DURATION, dt=1e-4, sample_every=10)
    return traj[:, -1]


def test_rk4_matches_mujoco(mujoco_reference, device):
    # float32 RK4 at the reference's own step: differences are float32 round-off amplified by the whip
    # (the tip reaches 7.3 m/s); 1 mm over the whole second bounds it with margin (measured 2e-4 m).
    tips, _ = run(reference_strand(device), "rk4", 1e-4, DURATION)
    err = np.linalg.norm(tips - mujoco_reference, axis=1)
    assert err[:501].max() < 1e-4, err[:501].max()
    assert err.max() < 1e-3, err.max()


@pytest.mark.parametrize("integrator", ["semi_implicit", "implicit_joints", "rk4"])
def test_integrators_converge_to_mujoco(mujoco_reference, integrator, device):
    # Tip error up to 0.5 s (the peers found semi-implicit Euler first order there: 20.9 mm at dt = 1e-3,
    # 1.7 mm at 1e-4). With no joint stiffness implicit_joints is the same scheme as semi_implicit.
    bounds = {"semi_implicit": (3e-2, 3e-3), "implicit_joints": (3e-2, 3e-3), "rk4": (1e-4, 1e-4)}[integrator]
    for dt, bound in zip((1e-3, 1e-4), bounds):
        tips, _ = run(reference_strand(device), integrator, dt, 0.5)
        err = np.linalg.norm(tips - mujoco_reference[: len(tips)], axis=1).max()
        assert err < bound, f"{integrator} dt={dt}: max tip error {err:.3g} m"


def successive_halvings(integrator, bend_stiffness, substeps, device):
    """A 12-segment strand of 0.35 m (``long_hair``'s) released horizontal, no damping or drag, 1 s at ``substeps``
    steps per 1/30 s: the ratio of each pair of consecutive differences between runs one halving of the step apart
    (tips every 1/30 s, RMS; 2 in a first-order method)."""
    params = StrandParams(density=1300.0, radius=0.002, bend_stiffness=bend_stiffness, damping=0.0, drag=0.0)
    model = reference_strand(device, segments=12, length=0.35 / 12, angle_deg=90.0, params=params)
    tips = [run(model, integrator, 1.0 / (30 * n), 1.0, sample_dt=1.0 / 30)[0] for n in substeps]
    diffs = [np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))) for a, b in zip(tips, tips[1:])]
    return np.array(diffs[:-1]) / np.array(diffs[1:])


@pytest.mark.parametrize("integrator, bend_stiffness, substeps", [
    # bends stiff enough that the implicit springs damp away their fast modes at every step here
    ("implicit_joints", 2e-3, (16, 32, 64, 128, 256)),
    # long_hair's bend stiffness, with the explicit springs (stable from 32 substeps)
    ("semi_implicit", 2e-4, (32, 64, 128, 256)),
])
def test_integrators_are_first_order_with_joint_springs(integrator, bend_stiffness, substeps, device):
    """Halving the step halves the difference between runs (measured ratios 1.88-1.89 and 1.91-1.99). At long_hair's
    bend stiffness implicit_joints halves it by only 1.5-1.8 from 16 to 2048 steps a frame: backward Euler damps a
    mode of frequency w by w^2 h / 2 per second, and the strand's bending modes 2 to 4 (20-110 rad/s) pass from
    damped away to kept (w^2 h T ~ 1) across those steps (``hairwarp.Integrator``). Each difference is a few tenths
    of a millimetre or more, a thousand times float32's resolution of the 0.35 m strand."""
    ratios = successive_halvings(integrator, bend_stiffness, substeps, device)
    # first order halves the difference (2); 1.75 sits below the measured 1.88-1.99 and above the 1.48-1.59 of
    # implicit_joints at long_hair's bend stiffness, whose damping of the bending modes these steps do not resolve
    assert ratios.min() > 1.75, ratios


def test_small_angle_pendulum_period(device):
    # One segment swinging 2 deg about its root: T = 2 pi sqrt(I_pivot / (m g L/2)) (closed form).
    L = 0.1
    model = reference_strand(device, segments=1, length=L, angle_deg=2.0)
    m = float(model.seg_mass.numpy()[0])
    I_pivot = float(model.seg_inertia.numpy()[0][0]) + m * (L / 2) ** 2
    period = 2 * math.pi * math.sqrt(I_pivot / (m * 9.81 * L / 2))
    dt = 1e-4
    tips, _ = run(model, "semi_implicit", dt, 2.5 * period, sample_dt=dt)
    x = tips[:, 0]
    crossings = np.flatnonzero((x[:-1] < 0) & (x[1:] >= 0))
    t = (crossings + x[crossings] / (x[crossings] - x[crossings + 1])) * dt  # linear interpolation
    measured = np.diff(t).mean()
    # small-angle formula error at 2 deg is (2 deg)^2/16 = 7.6e-5; symplectic Euler's period error is O(dt^2)
    assert abs(measured / period - 1) < 5e-4, (measured, period)


def strand_energy(model, state):
    """Total energy [J] in float64 by Pinocchio from our joint state (independent of our kernels)."""
    pm = chain_model(model.seg_length.numpy().astype(float), model.seg_mass.numpy().astype(float),
                     model.seg_inertia.numpy().astype(float), model.strand_root_pos.numpy()[0].astype(float))
    data = pm.createData()
    q = state.joint_q.numpy().astype(float).reshape(-1)
    v = state.joint_qd.numpy().astype(float).reshape(-1)
    return pin.computeKineticEnergy(pm, data, q, v) + pin.computePotentialEnergy(pm, data, q)


def test_energy_drift_bounded_semi_implicit(device):
    # Undamped semi-implicit Euler on a short chain at a small step: the energy error stays bounded.
    # 3 segments of 5 cm from 30 deg, dt = 2e-4 over 10 s: measured 0.12 % of |E0|, as float64
    # Pinocchio ABA with the same scheme (0.12 %); bound 0.5 %.
    model = reference_strand(device, segments=3, length=0.05, angle_deg=30.0)
    solver = Solver(model, "semi_implicit")
    s0, s1, control = model.state(), model.state(), model.control()
    e0 = strand_energy(model, s0)
    dt, energies = 2e-4, []
    for n in range(1, 50_001):
        solver.step(s0, s1, control, dt)
        s0, s1 = s1, s0
        if n % 2500 == 0:
            energies.append(strand_energy(model, s0))
    drift = np.abs(np.array(energies) - e0).max() / abs(e0)
    assert drift < 5e-3, drift


def test_undamped_chain_blowup_is_caught_no_earlier_than_references(device):
    # MuJoCo Euler and Pinocchio + semi-implicit Euler both blow up at t = 1.28 s on this chain at
    # dt = 1e-3 (joint rates past 1000 rad/s, then NaN); ours must last at least as long and then be
    # caught by the once-per-frame check (frames of 10 steps). Measured: caught at 1.28 s.
    model = reference_strand(device)
    with pytest.raises(SimulationFault) as info:
        run(model, "semi_implicit", 1e-3, 5.0, sample_dt=0.1, frame_check=10)
    t_fault = info.value.frame * 10 * 1e-3
    assert t_fault >= 1.2, t_fault
    # the chain has no joint springs: the advice names what it lacks, not "explicit joint springs"
    message = str(info.value)
    assert "dynamics" in message and "bend_stiffness" in message and "explicit joint springs" not in message


def stiff_strand(device):
    # 20 segments of 15 mm with EI = 5e-3 N m^2: joint stiffness 0.33 N m/rad, tip joint frequency
    # ~4000 rad/s, far beyond explicit stability (2/h = 480 rad/s at h = 1/240 s).
    params = StrandParams(bend_stiffness=5e-3, damping=1e-6)
    model = reference_strand(device, params=params, angle_deg=30.0)
    return model


def test_stiff_strand_implicit_stable_semi_implicit_caught(device):
    dt = 1.0 / 240.0
    _, state = run(stiff_strand(device), "implicit_joints", dt, 2.0, sample_dt=dt * 8, frame_check=8)
    q = state.joint_qd.numpy()
    assert np.isfinite(q).all() and np.abs(q).max() < 10.0
    with pytest.raises(SimulationFault) as info:
        run(stiff_strand(device), "semi_implicit", dt, 2.0, sample_dt=dt * 8, frame_check=8)
    message = str(info.value)
    assert info.value.frame is not None and f"frame {info.value.frame}" in message
    assert "dynamics" in message and "implicit_joints" in message and "substeps" not in message.split("dt")[0]


def test_ratboy_mohawk_loads_and_simulates_without_fault(device):
    # A real groom: 2,228 TressFX strands of 32 vertices, 9 of them shorter than 1 mm (dropped with one
    # warning); simulated at its own resolution (31 segments) for 3 frames of 8 steps under gravity.
    from conftest import require_ratboy

    from hairwarp.groom import Groom
    from hairwarp.runner import Stepper

    path = require_ratboy("Ratboy_mohawk.tfx")
    with pytest.warns(UserWarning, match="dropped 9 of 2228"):
        groom = Groom.load(path)
    assert groom.strand_count == 2219
    model = Model.build(groom, StrandParams(radius=1e-3, bend_stiffness=5e-5), segments=31, device=device)
    stepper = Stepper(Solver(model, "implicit_joints"), dt=1.0 / 240.0, substeps=8)
    rest = stepper.state.vertex_positions.numpy().copy()
    for _ in range(3):
        stepper.advance_frame()  # raises SimulationFault on a fault
    moved = np.linalg.norm(stepper.state.vertex_positions.numpy() - rest, axis=1)
    assert np.isfinite(moved).all()
    # roots stay on the (still) head; free vertices move (gravity against the rest-shape springs) but
    # no vertex travels further than the longest strand (0.295 m) and no vertex is faster than 5 m/s
    assert moved[:: model.seg_per_strand + 1].max() < 1e-6
    assert 1e-4 < moved.max() < 0.295
    assert np.linalg.norm(stepper.state.vertex_velocities.numpy(), axis=1).max() < 5.0


def _spin_run(substeps: int, seconds: float, device, revs_per_s: float = 3.0, ramp: float = 0.3):
    """Free guides (no collider, no links) on a head spun about the vertical at ``revs_per_s``, ramped up over
    ``ramp`` s; the pose, angular velocity and acceleration of each step's end. Returns the largest vertex speed
    [m/s] and the tips at the end, or raises SimulationFault."""
    import hairwarp as hw

    groom = hw.scalp_groom(count=24, length=0.3, points=13, seed=3)
    model = Model.build(groom, StrandParams(drag=0.03), segments=12, device=device)
    solver = Solver(model, "implicit_joints", threads=1)
    control = model.control()
    s0, s1 = model.state(), model.state()
    omega_max = 2.0 * math.pi * revs_per_s
    dt = 1.0 / (30.0 * substeps)
    vmax = 0.0
    for n in range(int(round(seconds / dt))):
        t = (n + 1) * dt
        if t < ramp:
            omega, alpha, angle = omega_max * t / ramp, omega_max / ramp, 0.5 * omega_max * t * t / ramp
        else:
            omega, alpha, angle = omega_max, 0.0, omega_max * (t - 0.5 * ramp)
        control.set_head(rotation=(0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)),
                         angular_velocity=(0.0, 0.0, omega), angular_acceleration=(0.0, 0.0, alpha))
        solver.step(s0, s1, control, dt)
        s0, s1 = s1, s0
        if (n + 1) % substeps == 0:
            solver.check(s0, frame=(n + 1) // substeps, substeps=substeps)
            vmax = max(vmax, float(np.linalg.norm(s0.vertex_velocities.numpy(), axis=1).max()))
    return vmax, s0.vertex_positions.numpy().reshape(model.strand_count, -1, 3)[:, -1]


def test_spinning_head_at_the_shipped_step(device):
    """A head spun at 3 rev/s, 8 steps a frame. ABA's explicit velocity terms grow a free chain's velocities by
    about 2 h Omega^2 per second in the spinning frame (3 /s here), more than drag takes out: it faulted within a
    second before the integrator split such steps (GYRO_GROWTH). Now it runs and matches 32 steps a frame: the
    tips fly out to the same radius (their phases differ with the wisps' whip), and the fastest vertex is as fast
    (13 m/s, a whip beyond the 7.7 m/s of a tip carried round at 0.41 m)."""
    vmax, tips = _spin_run(8, 1.5, device)
    fine_vmax, fine = _spin_run(32, 1.5, device)
    radius, fine_radius = np.hypot(tips[:, 0], tips[:, 1]), np.hypot(fine[:, 0], fine[:, 1])
    assert radius.mean() > 0.2  # flung out from the 0.1 m scalp, not hanging
    assert abs(radius.mean() - fine_radius.mean()) < 0.005, (radius.mean(), fine_radius.mean())
    assert abs(vmax - fine_vmax) < 0.1 * fine_vmax, (vmax, fine_vmax)


def test_implicit_joints_takes_energy_out_of_a_fast_turning_strand(device):
    # 12 segments of 3 cm, EI 1e-4, no gravity, damping or drag: kinetic energy is conserved in continuous time.
    # Joint speeds of 40 rad/s (normal, seeded) whip the tip at tens of m/s: at dt = 1/240 s the explicit velocity
    # products went NaN within 0.1 s; taken at the midpoint velocity the step turns no faster than the motion and
    # the energy (Pinocchio's, from our joint state) only falls: measured 0.27, then 0.15-0.24 of E0 (1.45 J) in
    # 1 s. Bound: never above E0 by more than float32 round-off of the state (1e-3 relative).
    S, length = 12, 0.03
    a = math.radians(80.0)
    verts = (np.arange(S + 1)[:, None] * length * np.array([-math.sin(a), 0.0, -math.cos(a)]))[None]
    params = StrandParams(density=1300.0, radius=0.002, bend_stiffness=1e-4, damping=0.0)
    model = Model.build(verts, params, segments=S, device=device, gravity=(0.0, 0.0, 0.0))
    solver = Solver(model, "implicit_joints")
    s0, s1, control = model.state(), model.state(), model.control()
    w = np.random.default_rng(1).normal(0.0, 40.0, (S, 3))
    w[:, 2] *= 0.1  # little twist: a thin segment's spin inertia is tiny
    s0.joint_qd.assign(w.astype(np.float32))
    pm = chain_model(model.seg_length.numpy().astype(float), model.seg_mass.numpy().astype(float),
                     model.seg_inertia.numpy().astype(float), model.strand_root_pos.numpy()[0].astype(float))
    data = pm.createData()

    def kinetic(state):
        q = state.joint_q.numpy().astype(float).reshape(-1)
        v = state.joint_qd.numpy().astype(float).reshape(-1)
        return pin.computeKineticEnergy(pm, data, q, v)

    e0, energies = kinetic(s0), []
    for n in range(1, 241):
        solver.step(s0, s1, control, 1.0 / 240.0)
        s0, s1 = s1, s0
        if n % 12 == 0:
            energies.append(kinetic(s0))
    solver.check(s0, 1)  # no fault bit, no NaN
    assert np.isfinite(energies).all() and max(energies) <= e0 * (1.0 + 1e-3), (e0, energies)
