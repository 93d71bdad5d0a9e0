"""Independent float64 references for the strand dynamics: Pinocchio and MuJoCo models of a chain.

The permutations between hairwarp's conventions and the references live here only:
Pinocchio spatial vectors are (linear, angular), hairwarp's (angular, linear); a spherical
joint's q is (x, y, z, w) in both; MuJoCo stores quaternions (w, x, y, z).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def quat_xyzw_to_matrix(q):
    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def rotvec_of(q_xyzw):
    """Rotation vector with angle in [0, pi] (float64)."""
    return Rotation.from_quat(np.asarray(q_xyzw, dtype=np.float64)).as_rotvec()


def joint_torques(q, qd, rest_q, stiffness, damping):
    """tau = -K log(rest^-1 q) - C w, per joint (S, 3), child frame."""
    rel = Rotation.from_quat(rest_q).inv() * Rotation.from_quat(q)
    theta = rel.as_rotvec()
    return -stiffness * theta - damping * qd


def chain_model(lengths, masses, inertias, root_pos, *, free_base=False):
    """A Pinocchio model of one strand: spherical joints, bodies hanging along local -z.

    Joint 0 sits at ``root_pos`` in the base frame (the universe, or a free-flyer standing for
    the head when ``free_base``); joint k at the parent's (0, 0, -L_{k-1}). Body k: mass m_k, centre
    of mass (0, 0, -L_k/2), principal moments ``inertias[k]`` about it.
    """
    import pinocchio as pin

    model = pin.Model()
    parent = 0
    if free_base:
        parent = model.addJoint(0, pin.JointModelFreeFlyer(), pin.SE3.Identity(), "head")
        # a massless base would make the free-flyer's block singular; its motion is prescribed anyway
        model.appendBodyToJoint(parent, pin.Inertia(1.0, np.zeros(3), np.eye(3)), pin.SE3.Identity())
    for k, (L, m, I) in enumerate(zip(lengths, masses, inertias)):
        offset = np.asarray(root_pos, float) if k == 0 else np.array([0.0, 0.0, -lengths[k - 1]])
        jid = model.addJoint(parent, pin.JointModelSpherical(), pin.SE3(np.eye(3), offset), f"j{k}")
        model.appendBodyToJoint(jid, pin.Inertia(float(m), np.array([0.0, 0.0, -0.5 * L]), np.diag(I)),
                                pin.SE3.Identity())
        parent = jid
    model.gravity = pin.Motion(np.array([0.0, 0.0, -9.81]), np.zeros(3))
    return model


def local_forces(model, data, q, forces_world, torques_world, first_joint=1):
    """pin.Force per joint in its local frame from world forces and torques about each body origin."""
    import pinocchio as pin

    pin.forwardKinematics(model, data, q)
    fext = [pin.Force.Zero() for _ in range(model.njoints)]
    for k, (F, T) in enumerate(zip(forces_world, torques_world)):
        R = data.oMi[first_joint + k].rotation
        fext[first_joint + k] = pin.Force(R.T @ F, R.T @ T)
    return fext


def aba_fixed_base(lengths, masses, inertias, root_pos, q, qd, tau, forces_world, torques_world):
    """Joint accelerations (S, 3) of a chain on a fixed base by ``pinocchio.aba``."""
    import pinocchio as pin

    model = chain_model(lengths, masses, inertias, root_pos)
    data = model.createData()
    qv = np.asarray(q, float).reshape(-1)
    fext = local_forces(model, data, qv, forces_world, torques_world)
    a = pin.aba(model, data, qv, np.asarray(qd, float).reshape(-1), np.asarray(tau, float).reshape(-1), fext)
    return np.asarray(a).reshape(-1, 3)


def accelerations_dense(lengths, masses, inertias, root_pos, q, qd, tau, forces_world, torques_world, *,
                        head_pos, head_quat, head_omega, head_vel, head_alpha, head_acc, armature=None):
    """Joint accelerations (S, 3) with a prescribed head motion, by a dense solve on Pinocchio's CRBA,
    and the joint-space inertia the solve used (with the armature).

    The head is a free-flyer whose velocity is given and whose acceleration is prescribed:
    with ``a_b`` the head's spatial acceleration, ``(M_jj + armature) qdd = tau - RNEA(q, v, [a_b, 0], fext)_j``.
    ``armature`` (S*3,) is ``hC + h^2 K`` for the implicit joints.
    """
    import pinocchio as pin

    model = chain_model(lengths, masses, inertias, root_pos, free_base=True)
    data = model.createData()
    R = quat_xyzw_to_matrix(head_quat)
    w_b = R.T @ np.asarray(head_omega, float)
    v_b = R.T @ np.asarray(head_vel, float)
    a_lin = R.T @ np.asarray(head_acc, float) - np.cross(w_b, v_b)
    a_ang = R.T @ np.asarray(head_alpha, float)
    qv = np.concatenate([head_pos, head_quat, np.asarray(q, float).reshape(-1)])
    vv = np.concatenate([v_b, w_b, np.asarray(qd, float).reshape(-1)])
    av = np.concatenate([a_lin, a_ang, np.zeros(np.size(qd))])
    fext = local_forces(model, data, qv, forces_world, torques_world, first_joint=2)
    bias = pin.rnea(model, data, qv, vv, av, fext)[6:]
    M = pin.crba(model, data, qv)
    M = np.triu(M) + np.triu(M, 1).T
    Mjj = M[6:, 6:]
    if armature is not None:
        Mjj = Mjj + np.diag(armature)
    return np.linalg.solve(Mjj, np.asarray(tau, float).reshape(-1) - bias).reshape(-1, 3), Mjj


def joint_inertia(lengths, masses, inertias, root_pos, q):
    """Joint-space inertia matrix (3S, 3S) of a fixed-base chain by Pinocchio's CRBA."""
    import pinocchio as pin

    model = chain_model(lengths, masses, inertias, root_pos)
    M = pin.crba(model, model.createData(), np.asarray(q, float).reshape(-1))
    return np.triu(M) + np.triu(M, 1).T


def chain_mjcf(lengths, masses, inertias, root_pos, *, integrator="RK4", dt=1e-4, damping=0.0):
    """MJCF text of one strand with explicit inertials (no geoms), ball joints, no contacts."""

    def body(k):
        L, m, I = lengths[k], masses[k], inertias[k]
        pos = " ".join(f"{x:.17g}" for x in (root_pos if k == 0 else (0.0, 0.0, -lengths[k - 1])))
        inner = body(k + 1) if k + 1 < len(lengths) else ""
        return (f'<body name="s{k}" pos="{pos}"><joint name="j{k}" type="ball" damping="{damping:.17g}"/>'
                f'<inertial pos="0 0 {-0.5 * L:.17g}" mass="{m:.17g}" '
                f'diaginertia="{I[0]:.17g} {I[1]:.17g} {I[2]:.17g}"/>{inner}</body>')

    return (f'<mujoco><compiler inertiafromgeom="false" angle="radian"/>'
            f'<option timestep="{dt:.17g}" integrator="{integrator}" gravity="0 0 -9.81">'
            f'<flag contact="disable"/></option><worldbody>{body(0)}</worldbody></mujoco>')


def mujoco_trajectory(lengths, masses, inertias, root_pos, q0_xyzw, *, duration, dt, integrator="RK4",
                      sample_every=1):
    """Vertex positions (T, S+1, 3) of a MuJoCo run of the chain, every ``sample_every`` steps."""
    import mujoco

    m = mujoco.MjModel.from_xml_string(chain_mjcf(lengths, masses, inertias, root_pos, integrator=integrator, dt=dt))
    d = mujoco.MjData(m)
    q = np.asarray(q0_xyzw, float).reshape(-1, 4)
    d.qpos[:] = q[:, [3, 0, 1, 2]].reshape(-1)
    steps = int(round(duration / dt))
    out = []
    for n in range(steps + 1):
        if n % sample_every == 0:
            mujoco.mj_kinematics(m, d)
            pts = [d.xpos[1].copy()]
            for k in range(len(lengths)):
                pts.append(d.xpos[k + 1] + d.xmat[k + 1].reshape(3, 3) @ np.array([0.0, 0.0, -lengths[k]]))
            out.append(np.array(pts))
        if n < steps:
            mujoco.mj_step(m, d)
    return np.array(out)


def segment_distances(p0, p1, q0, q1):
    """Brute-force distance of segment pairs (N, 3): the least of the four endpoint-to-segment distances and, where
    it falls inside both segments, the length of the two lines' common perpendicular."""

    def point_segment(x, s0, s1):
        d = s1 - s0
        t = np.clip(np.sum((x - s0) * d, axis=1) / np.sum(d * d, axis=1), 0.0, 1.0)
        return np.linalg.norm(x - (s0 + t[:, None] * d), axis=1)

    best = np.minimum.reduce([point_segment(p0, q0, q1), point_segment(p1, q0, q1), point_segment(q0, p0, p1),
                              point_segment(q1, p0, p1)])
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, b, e = np.sum(d1 * d1, 1), np.sum(d1 * d2, 1), np.sum(d2 * d2, 1)
    c, f = np.sum(d1 * r, 1), np.sum(d2 * r, 1)
    det = b * b - a * e
    ok = np.abs(det) > 1e-12 * a * e
    det = np.where(ok, det, 1.0)
    s = (c * e - b * f) / det
    t = (b * c - a * f) / det
    inside = ok & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
    perp = np.linalg.norm((p0 + s[:, None] * d1) - (q0 + t[:, None] * d2), axis=1)
    return np.where(inside, np.minimum(best, perp), best)


def ellipsoid_closest(points, radii):
    """Float64 closest points on the ellipsoid of semi-axes ``radii`` centred at the origin, and signed distances
    (negative inside), by bisection on the root t of sum (a_i y_i / (t + a_i^2))^2 = 1 (y = |p|): 200 halvings of
    a bracket that holds it, [0, |a y|] outside and (-min a_i^2, 0) inside. Independent of the kernel's Newton
    steps."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64)
    y, a2 = np.abs(p), r * r
    ay = r * y
    outside = np.sum((y / r) ** 2, axis=1) >= 1.0
    lo = np.where(outside, 0.0, -a2.min() * (1.0 - 1e-15))
    hi = np.where(outside, np.linalg.norm(ay, axis=1), 0.0)
    for _ in range(200):
        t = 0.5 * (lo + hi)
        f = np.sum((ay / (t[:, None] + a2)) ** 2, axis=1) - 1.0
        lo, hi = np.where(f > 0.0, t, lo), np.where(f > 0.0, hi, t)
    z = a2 * y / ((0.5 * (lo + hi))[:, None] + a2)
    closest = np.sign(p) * z
    d = np.linalg.norm(p - closest, axis=1)
    return closest, np.where(outside, d, -d)
