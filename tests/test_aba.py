"""ABA joint accelerations against Pinocchio (float64): pin.aba on a fixed base, CRBA dense solves
with a prescribed head motion and with the implicit joints' armature."""

import numpy as np
import pytest
import warp as wp
from _reference import aba_fixed_base, accelerations_dense, joint_inertia, joint_torques
from scipy.spatial.transform import Rotation

from hairwarp.model import Model, StrandParams
from hairwarp.solver import Solver

# ABA is backward stable: our float32 accelerations solve a system within a few float32 epsilons
# (6e-8) of the true one, so the normwise backward error |M (qdd - ref)| / (|M| |ref|) stays below
# 1e-6 (observed <= 1e-7 up to 32 segments). The forward error is that times the condition number
# of M, which random crumpled chains push to 1e7 at 32 segments; on chains up to 7 segments
# (cond <= 1e5) the direct error is also checked against 2e-4 of the largest |qdd| (observed 1.5e-5).
BACKWARD_TOL = 1e-6
RTOL_QDD = 2e-4
FORWARD_CHECK_MAX_S = 7


def random_chain(rng, S):
    lengths = rng.uniform(0.005, 0.02, S)
    dirs = rng.normal(size=(S, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    root = rng.uniform(-0.1, 0.1, 3)
    verts = np.concatenate([[root], root + np.cumsum(lengths[:, None] * dirs, axis=0)])
    return verts[None]


def build_case(rng, S, device):
    verts = random_chain(rng, S)
    model = Model.build(verts, StrandParams(density=1300.0, radius=rng.uniform(1e-3, 3e-3)), segments=S,
                        device=device)
    state = model.state()
    q = Rotation.random(S, random_state=rng).as_quat()
    qd = rng.normal(scale=5.0, size=(S, 3))
    rest = Rotation.random(S, random_state=rng).as_quat()
    K = rng.uniform(0.0, 0.05, (S, 3))
    C = rng.uniform(0.0, 1e-4, (S, 3))
    forces = rng.normal(scale=2e-3, size=(S, 3))
    torques = rng.normal(scale=2e-5, size=(S, 3))
    state.joint_q.assign(q.astype(np.float32))
    state.joint_qd.assign(qd.astype(np.float32))
    model.joint_rest_q.assign(rest.astype(np.float32))
    model.joint_stiffness.assign(K.astype(np.float32))
    model.joint_damping.assign(C.astype(np.float32))
    # the reference sees exactly the float32 values the kernels see
    case = dict(
        lengths=model.seg_length.numpy().astype(np.float64),
        masses=model.seg_mass.numpy().astype(np.float64),
        inertias=model.seg_inertia.numpy().astype(np.float64),
        root=model.strand_root_pos.numpy()[0].astype(np.float64),
        q=state.joint_q.numpy().astype(np.float64),
        qd=state.joint_qd.numpy().astype(np.float64),
        rest=model.joint_rest_q.numpy().astype(np.float64),
        K=model.joint_stiffness.numpy().astype(np.float64),
        C=model.joint_damping.numpy().astype(np.float64),
        forces=forces.astype(np.float32).astype(np.float64),
        torques=torques.astype(np.float32).astype(np.float64),
    )
    f_arr = wp.array(forces.astype(np.float32), dtype=wp.vec3, device=device)
    t_arr = wp.array(torques.astype(np.float32), dtype=wp.vec3, device=device)
    return model, state, case, f_arr, t_arr


def assert_close(ours, ref, M):
    e = (ours - ref).reshape(-1)
    backward = np.linalg.norm(M @ e) / (np.linalg.norm(M, 2) * np.linalg.norm(ref))
    assert backward <= BACKWARD_TOL, f"normwise backward error {backward:.3g}"
    if len(e) <= 3 * FORWARD_CHECK_MAX_S:
        scale = np.abs(ref).max()
        err = np.abs(e).max()
        assert err <= RTOL_QDD * scale, f"max |qdd - ref| = {err:.3g}, {err / scale:.3g} of max |qdd| = {scale:.3g}"


@pytest.mark.parametrize("S", [1, 2, 7, 32])
def test_aba_matches_pinocchio_fixed_base(S, device):
    rng = np.random.default_rng(100 + S)
    for _ in range(3):
        model, state, c, f_arr, t_arr = build_case(rng, S, device)
        solver = Solver(model, "semi_implicit")
        qdd = solver.joint_accelerations(state, model.control(), seg_force=f_arr, seg_torque=t_arr).numpy()
        tau = joint_torques(c["q"], c["qd"], c["rest"], c["K"], c["C"])
        ref = aba_fixed_base(c["lengths"], c["masses"], c["inertias"], c["root"], c["q"], c["qd"], tau,
                             c["forces"], c["torques"])
        assert_close(qdd, ref, joint_inertia(c["lengths"], c["masses"], c["inertias"], c["root"], c["q"]))


def random_head(rng):
    return dict(
        head_pos=rng.uniform(-0.5, 0.5, 3),
        head_quat=Rotation.random(random_state=rng).as_quat(),
        head_omega=rng.normal(scale=2.0, size=3),
        head_vel=rng.normal(scale=1.0, size=3),
        head_alpha=rng.normal(scale=10.0, size=3),
        head_acc=rng.normal(scale=5.0, size=3),
    )


def set_control(control, h):
    control.set_head(h["head_pos"], h["head_quat"], h["head_vel"], h["head_omega"], h["head_acc"], h["head_alpha"])
    # the reference sees the float32 values
    x = control.head_xform.numpy()[0].astype(np.float64)
    v = control.head_velocity.numpy()[0].astype(np.float64)
    a = control.head_acceleration.numpy()[0].astype(np.float64)
    return dict(head_pos=x[:3], head_quat=x[3:] / np.linalg.norm(x[3:]), head_omega=v[:3], head_vel=v[3:],
                head_alpha=a[:3], head_acc=a[3:])


@pytest.mark.parametrize("S", [1, 2, 7, 32])
@pytest.mark.parametrize("implicit", [False, True])
def test_aba_moving_head_matches_crba(S, implicit, device):
    rng = np.random.default_rng(200 + S + 1000 * implicit)
    h = 1.0 / 240.0
    for _ in range(2):
        model, state, c, f_arr, t_arr = build_case(rng, S, device)
        control = model.control()
        head = set_control(control, random_head(rng))
        solver = Solver(model, "implicit_joints" if implicit else "semi_implicit")
        qdd = solver.joint_accelerations(state, control, dt=h, implicit=implicit, seg_force=f_arr,
                                         seg_torque=t_arr).numpy()
        tau = joint_torques(c["q"], c["qd"], c["rest"], c["K"], c["C"])
        armature = None
        if implicit:
            tau = tau - h * c["K"] * c["qd"]
            armature = (h * c["C"] + h * h * c["K"]).reshape(-1)
        ref, M = accelerations_dense(c["lengths"], c["masses"], c["inertias"], c["root"], c["q"], c["qd"], tau,
                                     c["forces"], c["torques"], armature=armature, **head)
        assert_close(qdd, ref, M)


@pytest.mark.parametrize("S", [2, 7])
def test_implicit_spring_mass_adds_inertia_not_weight(S, device):
    # The semi-implicit share of interaction springs is inertia m_e at each centre of mass that must
    # not feel gravity: reference = Pinocchio ABA with masses m + m_e and an upward force m_e g there.
    rng = np.random.default_rng(300 + S)
    model, state, c, f_arr, t_arr = build_case(rng, S, device)
    extra = rng.uniform(0.5, 5.0, S) * c["masses"]
    extra32 = extra.astype(np.float32)
    qdd = Solver(model, "semi_implicit").joint_accelerations(
        state, model.control(), seg_force=f_arr, seg_torque=t_arr,
        seg_implicit_mass=wp.array(extra32, dtype=float, device=device)).numpy()
    extra = extra32.astype(np.float64)
    tau = joint_torques(c["q"], c["qd"], c["rest"], c["K"], c["C"])
    R = [Rotation.from_quat(q) for q in c["q"]]
    forces, torques, rot = [], [], Rotation.identity()
    for k in range(S):
        rot = rot * R[k]
        lift = -extra[k] * np.array([0.0, 0.0, -9.81])
        com_world = rot.apply([0.0, 0.0, -0.5 * c["lengths"][k]])
        forces.append(c["forces"][k] + lift)
        torques.append(c["torques"][k] + np.cross(com_world, lift))
    masses = c["masses"] + extra
    # extra mass at the centre of mass adds m_e (L/2)^2 to the transverse moments about the top end only
    ref = aba_fixed_base(c["lengths"], masses, c["inertias"], c["root"], c["q"], c["qd"], tau, forces, torques)
    assert_close(qdd, ref, joint_inertia(c["lengths"], masses, c["inertias"], c["root"], c["q"]))


# The inverse inertia is a product of O(S) float32 3x3 blocks; against the float64 J M^-1 J^T its entries agree
# within 1e-3 of the largest (observed up to 3e-4 at 7 segments without armature, where random crumpled chains make
# M worst conditioned; 5e-7 with it). The response takes mass ratios from it, which need far less.
RTOL_PHI = 1e-3


@pytest.mark.parametrize("S", [1, 2, 7])
@pytest.mark.parametrize("implicit", [0, 1])
def test_inverse_inertia_matches_pinocchio(S, implicit, device):
    """``strand_inverse_inertia``: each segment's inverse spatial inertia in its strand (the response's effective
    masses) is ``J M^-1 J^T``, J the segment's body Jacobian from Pinocchio and M its CRBA joint-space inertia, with
    the implicit joints' armature ``hC + h^2 K`` when ``implicit``."""
    import pinocchio as pin
    from _reference import chain_model

    from hairwarp.kernels import articulated

    rng = np.random.default_rng(300 + 10 * S + implicit)
    h = 1.0 / 30.0
    for _ in range(2):
        model, state, c, f_arr, t_arr = build_case(rng, S, device)
        n = model.seg_count
        out = articulated.InteractionResponse()
        for name in ("A", "B", "C", "phi_a", "phi_b", "phi_c"):
            setattr(out, name, wp.zeros(n, dtype=wp.mat33, device=device))
        out.force = wp.zeros(n, dtype=wp.vec3, device=device)
        out.torque = wp.zeros(n, dtype=wp.vec3, device=device)
        loads = Solver._loads(f_arr, t_arr, False, wp.zeros(1, dtype=float, device=device), False)
        wp.launch(articulated.strand_inverse_inertia, dim=1,
                  inputs=[0, model.chains, wp.array([h], dtype=float, device=device), implicit, loads,
                          state.joint_q, wp.zeros(1, dtype=wp.int32, device=device)], outputs=[out], device=device)
        pm = chain_model(c["lengths"], c["masses"], c["inertias"], c["root"])
        data = pm.createData()
        q = c["q"].reshape(-1)
        M = joint_inertia(c["lengths"], c["masses"], c["inertias"], c["root"], c["q"])
        if implicit:
            M = M + np.diag((h * c["C"] + h * h * c["K"]).reshape(-1))
        pin.computeJointJacobians(pm, data, q)
        Minv = np.linalg.inv(M)
        phi = [a.numpy().astype(np.float64) for a in (out.phi_a, out.phi_b, out.phi_c)]
        for k in range(S):
            J = pin.getJointJacobian(pm, data, k + 1, pin.LOCAL)
            J = np.vstack([J[3:], J[:3]])  # Pinocchio's (linear, angular) to hairwarp's (angular, linear)
            ref = J @ Minv @ J.T
            ours = np.block([[phi[0][k], phi[1][k]], [phi[1][k].T, phi[2][k]]])
            np.testing.assert_allclose(ours, ref, rtol=0.0, atol=RTOL_PHI * np.abs(ref).max())
