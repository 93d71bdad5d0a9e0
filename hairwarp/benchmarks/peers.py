"""Peer simulators on the same chains: Pinocchio, MuJoCo and Newton, each measured in a child process.

A strand is a serial chain of S solid cylinders (radius 2 mm, density 1300 kg/m^3) joined by
3-DOF ball joints; each body frame has its origin at the segment's top joint and the segment
along body -z, centre of mass at (0, 0, -L/2), explicit mass and inertia in every peer. Pinocchio,
Warp and Newton store quaternions (x, y, z, w), MuJoCo (w, x, y, z).

``run_request(request)`` is the child's entry; ``request["kind"]`` is ``throughput``,
``trajectory``, ``reference``, ``stability_mujoco``, ``stability_newton``, ``robustness_mujoco_rest``
(:func:`hairwarp.benchmarks.robustness.mujoco_rest`) or ``robustness_newton_rest``
(:func:`hairwarp.benchmarks.robustness.newton_rest`).
"""

from __future__ import annotations

import math
import time

import numpy as np

from hairwarp.benchmarks.common import (
    BENCH_DT,
    DENSITY,
    GRAVITY,
    JOINT_DAMPING,
    RADIUS,
    STRAND_LENGTH,
    root_grid,
    segment_inertia,
    segment_mass,
    straight_strands,
    tilt_direction,
    time_blocks,
)
from hairwarp.benchmarks.common import time_blocks as _time_blocks


def tilt_quat_xyzw(deg: float) -> np.ndarray:
    h = 0.5 * math.radians(deg)
    return np.array([0.0, math.sin(h), 0.0, math.cos(h)])


def _quat_rotate_xyzw(q, v):
    u, w = np.asarray(q[:3], float), float(q[3])
    v = np.asarray(v, float)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


# ---------------------------------------------------------------------------------------------
# model builders


def pinocchio_chain(segments: int, root=(0.0, 0.0, 0.0), length: float = STRAND_LENGTH):
    """One Pinocchio chain of ``segments`` spherical joints hanging along -z from ``root``."""
    import pinocchio as pin

    L, m, inertia = length / segments, segment_mass(segments, length), np.diag(segment_inertia(segments, length))
    model = pin.Model()
    parent = 0
    for k in range(segments):
        offset = np.asarray(root, float) if k == 0 else np.array([0.0, 0.0, -L])
        j = model.addJoint(parent, pin.JointModelSpherical(), pin.SE3(np.eye(3), offset), f"j{k}")
        model.appendBodyToJoint(j, pin.Inertia(m, np.array([0.0, 0.0, -L / 2]), inertia), pin.SE3.Identity())
        parent = j
    model.gravity.linear = np.array([0.0, 0.0, -GRAVITY])
    return model


def integrate_spherical(q: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``pin.integrate`` of a chain of spherical joints for a batch of strands at once: ``q`` (4 S, G) quaternions
    (x, y, z, w) per joint, ``w`` (3 S, G) rotation vectors in each joint's frame; ``q (x) exp(w)`` per joint,
    normalised (matches ``pin.integrate`` to round-off)."""
    S = q.shape[0] // 4
    qq, ww = q.reshape(S, 4, -1), w.reshape(S, 3, -1)
    theta = np.sqrt((ww * ww).sum(axis=1))
    small = theta <= 1e-12
    scale = np.where(small, 0.5 - theta * theta / 48.0, np.sin(0.5 * theta) / np.where(small, 1.0, theta))
    ev, ew = ww * scale[:, None, :], np.cos(0.5 * theta)
    qv, qw = qq[:, :3], qq[:, 3]
    out = np.empty_like(qq)
    out[:, :3] = qw[:, None] * ev + ew[:, None] * qv + np.cross(qv, ev, axis=1)
    out[:, 3] = qw * ew - (qv * ev).sum(axis=1)
    out /= np.sqrt((out * out).sum(axis=1, keepdims=True))
    return out.reshape(4 * S, -1)


def pinocchio_tip(model, data, q, segments: int, length: float = STRAND_LENGTH) -> np.ndarray:
    import pinocchio as pin

    pin.forwardKinematics(model, data, q)
    return data.oMi[segments].act(np.array([0.0, 0.0, -length / segments]))


def mujoco_chain_xml(segments: int, *, integrator: str = "Euler", dt: float = BENCH_DT, damping: float = 0.0,
                     stiffness=None, root=(0.0, 0.0, 0.0), length: float = STRAND_LENGTH) -> str:
    """MJCF of one chain: explicit inertials, no geoms, contacts off, ball joints.

    ``stiffness`` (one value per joint, N m/rad) makes the ball joints springs about ``qpos0``
    (identity, the chain hanging straight down); MuJoCo treats it explicitly.
    """
    L, m = length / segments, segment_mass(segments, length)
    inertia = segment_inertia(segments, length)

    def f(x):
        return repr(float(x))

    inertial = (f"<inertial pos='0 0 {f(-L / 2)}' mass='{f(m)}' "
                f"diaginertia='{f(inertia[0])} {f(inertia[1])} {f(inertia[2])}'/>")
    body = ""
    for k in reversed(range(segments)):
        pos = root if k == 0 else (0.0, 0.0, -L)
        spring = f" stiffness='{f(stiffness[k])}'" if stiffness is not None else ""
        joint = f"<joint type='ball' damping='{f(damping)}'{spring}/>"
        body = f"<body pos='{f(pos[0])} {f(pos[1])} {f(pos[2])}'>{joint}{inertial}{body}</body>"
    return ("<mujoco><compiler angle='radian' inertiafromgeom='false' autolimits='true'/>"
            f"<option timestep='{f(dt)}' integrator='{integrator}' gravity='0 0 {f(-GRAVITY)}'>"
            "<flag contact='disable' energy='enable'/></option>"
            f"<worldbody>{body}</worldbody></mujoco>")


def mujoco_set_tilt(model, data, deg: float):
    import mujoco

    mujoco.mj_resetData(model, data)
    q = tilt_quat_xyzw(deg)
    data.qpos[0:4] = [q[3], q[0], q[1], q[2]]
    mujoco.mj_forward(model, data)


def mujoco_tip(model, data, segments: int, length: float = STRAND_LENGTH) -> np.ndarray:
    """Tip of chain 0; recomputes kinematics (``xpos`` is stale after ``mj_step``)."""
    import mujoco

    mujoco.mj_kinematics(model, data)
    R = np.array(data.xmat[segments]).reshape(3, 3)
    return data.xpos[segments] + R @ np.array([0.0, 0.0, -length / segments])


def newton_featherstone_model(strands: int, segments: int, roots: np.ndarray, tilt_deg: float, damping: float):
    """N articulations of S links (origin at the top joint, COM (0,0,-L/2)), no shapes, on the CPU."""
    import newton
    import warp as wp

    L, m = STRAND_LENGTH / segments, segment_mass(segments)
    inertia = wp.mat33(*np.diag(segment_inertia(segments)).reshape(-1).tolist())
    builder = newton.ModelBuilder(gravity=(0.0, 0.0, -GRAVITY))
    first = []
    for g in range(strands):
        root = roots[g]
        parent, joints = -1, []
        for k in range(segments):
            link = builder.add_link(xform=wp.transform(wp.vec3(*(root - np.array([0.0, 0.0, k * L]))),
                                                       wp.quat_identity()),
                                    com=wp.vec3(0.0, 0.0, -L / 2), mass=m, inertia=inertia, lock_inertia=True)
            pxf = wp.transform(wp.vec3(*root) if k == 0 else wp.vec3(0.0, 0.0, -L), wp.quat_identity())
            joints.append(builder.add_joint_ball(parent=parent, child=link, parent_xform=pxf,
                                                 child_xform=wp.transform_identity(), armature=0.0, friction=0.0,
                                                 damping=damping))
            parent = link
        builder.add_articulation(joints)
        first.append(joints[0])
    q = tilt_quat_xyzw(tilt_deg)
    for j in first:
        s = builder.joint_q_start[j]
        builder.joint_q[s:s + 4] = q.tolist()
    return builder.finalize(device="cpu")


def _cylinder_bodies(builder, bodies, segments: int) -> None:
    """Give Newton rod bodies the mass, inertia and centred mass of the peers' solid cylinder segments."""
    import warp as wp

    m, inertia = segment_mass(segments), segment_inertia(segments)
    for b in bodies:
        builder.body_mass[b] = m
        builder.body_inv_mass[b] = 1.0 / m
        builder.body_inertia[b] = wp.mat33(*np.diag(inertia).reshape(-1).tolist())
        builder.body_inv_inertia[b] = wp.mat33(*np.diag(1.0 / inertia).reshape(-1).tolist())
        builder.body_com[b] = wp.vec3(0.0, 0.0, 0.0)


def newton_rod_model(strands: int, segments: int, roots: np.ndarray, tilt_deg: float, damping: float,
                     stretch_ke: float = 1.0e5):
    """Newton rods (``add_rod``, VBD joints) with the cylinder mass properties; no collisions.

    Returns the model and, per strand, its body indices (body origin at the segment's centre,
    local +z from root to tip).
    """
    import newton
    import warp as wp

    L = STRAND_LENGTH / segments
    builder = newton.ModelBuilder(gravity=(0.0, 0.0, -GRAVITY))
    cfg = newton.ModelBuilder.ShapeConfig(density=1300.0, has_shape_collision=False, has_particle_collision=False)
    verts = straight_strands(roots, segments, tilt_direction(tilt_deg))
    strands_bodies = []
    for g in range(strands):
        rod = newton.Rod([wp.vec3(*p) for p in verts[g]], radius=RADIUS)
        bodies, joints = builder.add_rod(rod=rod, cfg=cfg, stretch_stiffness=stretch_ke, stretch_damping=0.0,
                                         bend_stiffness=0.0, bend_damping=damping, twist_stiffness=0.0,
                                         twist_damping=damping, wrap_in_articulation=False)
        _cylinder_bodies(builder, bodies, segments)
        root_joint = builder.add_joint_ball(parent=-1, child=bodies[0],
                                            parent_xform=wp.transform(wp.vec3(*roots[g]), wp.quat_identity()),
                                            child_xform=wp.transform(wp.vec3(0.0, 0.0, -L / 2), wp.quat_identity()),
                                            armature=0.0, friction=0.0, damping=damping)
        builder.add_articulation([*joints, root_joint])
        strands_bodies.append(bodies)
    builder.color()
    return builder.finalize(device="cpu"), strands_bodies


def _newton(kind: str, strands: int, segments: int, roots, tilt_deg: float, damping: float):
    """(model, step(k), tip() of strand 0, sync) for a Newton peer."""
    import newton
    import warp as wp

    wp.config.quiet = True
    L = STRAND_LENGTH / segments
    if kind == "newton_featherstone_tile":
        model = newton_featherstone_model(strands, segments, roots, tilt_deg, damping)
        solver = newton.solvers.SolverFeatherstone(model, angular_damping=0.0, use_tile_gemm=True)
        states = [model.state(), model.state()]
        newton.eval_fk(model, model.joint_q, model.joint_qd, states[0])

        def tip():
            bq = states[0].body_q.numpy()[segments - 1]
            return bq[:3] + _quat_rotate_xyzw(bq[3:], [0.0, 0.0, -L])
    else:
        model, bodies = newton_rod_model(strands, segments, roots, tilt_deg, damping)
        solver = newton.solvers.SolverVBD(model, iterations=10)
        states = [model.state(), model.state()]

        def tip():
            bq = states[0].body_q.numpy()[bodies[0][-1]]
            return bq[:3] + _quat_rotate_xyzw(bq[3:], [0.0, 0.0, L / 2])
    control = model.control()
    clear = kind == "newton_vbd"

    def step_fn(dt):
        def step(k):
            for _ in range(k):
                if clear:
                    states[0].clear_forces()
                solver.step(states[0], states[1], control, None, dt)
                states[0], states[1] = states[1], states[0]
        return step

    return model, step_fn, tip, wp.synchronize


# ---------------------------------------------------------------------------------------------
# throughput on the canonical scene


def hairwarp_bracket(req: dict):
    """A function timing hairwarp on the request's size in this process, or None when not asked.

    ``req["bracket"]``: ``{"modes": {integrator: "launch" | "graph"}, "steps", "blocks", "warmup",
    "budget_s", "graph_block"}``; the function returns seg-steps per second per integrator.
    """
    cfg = req.get("bracket")
    if not cfg:
        return None
    from hairwarp.benchmarks.ours import canonical_model, time_solver

    model = canonical_model(int(req["G"]), int(req["S"]), "cpu")

    def measure() -> dict:
        return {integrator: time_solver(model, integrator, float(req.get("dt", BENCH_DT)), graph=mode == "graph",
                                        steps=cfg["steps"], blocks=cfg["blocks"], warmup=cfg["warmup"],
                                        budget_s=cfg["budget_s"], graph_block=cfg["graph_block"])["seg_steps_per_s"]
                for integrator, mode in cfg["modes"].items()}

    return measure


def throughput(req: dict) -> dict:
    """Time one peer on G strands x S segments of the canonical scene (the peers' protocol).

    With ``req["bracket"]`` hairwarp is timed in the same process just before and just after the
    peer's timed blocks, so that a ratio compares figures taken seconds apart.
    """
    peer, G, S = req["peer"], int(req["G"]), int(req["S"])
    dt = float(req.get("dt", BENCH_DT))
    timing = {k: req[k] for k in ("steps", "blocks", "warmup", "budget_s") if k in req}
    ours = hairwarp_bracket(req)
    bracket = {}

    def time_blocks(step, sync=lambda: None, **kw):
        if ours is not None:
            bracket["before"] = ours()
        out = _time_blocks(step, sync, **kw)
        if ours is not None:
            bracket["after"] = ours()
        return out

    t0 = time.perf_counter()
    extra = {}
    if peer == "pinocchio":
        import pinocchio as pin

        model = pinocchio_chain(S, (0.0, 0.0, 1.0))
        data = model.createData()
        q0 = pin.neutral(model)
        q0[0:4] = tilt_quat_xyzw(80.0)
        qs = [q0.copy() for _ in range(G)]
        vs = [np.zeros(model.nv) for _ in range(G)]
        aba, integrate, c = pin.aba, pin.integrate, JOINT_DAMPING
        setup = time.perf_counter() - t0

        def step(k):
            for _ in range(k):
                for i in range(G):
                    v = vs[i] + dt * aba(model, data, qs[i], vs[i], -c * vs[i])
                    vs[i] = v
                    qs[i] = integrate(model, qs[i], v * dt)

        res = time_blocks(step, **timing)
        q, v = qs[0], vs[0]
        n = int(req.get("floor_calls", 20000))
        t1 = time.perf_counter()
        for _ in range(n):
            aba(model, data, q, v, -c * v)
        aba_s = (time.perf_counter() - t1) / n
        t1 = time.perf_counter()
        for _ in range(n):
            integrate(model, q, v * dt)
        int_s = (time.perf_counter() - t1) / n
        extra = {"aba_us_per_call": aba_s * 1e6, "integrate_us_per_call": int_s * 1e6,
                 "aba_only_seg_steps_per_s": S / aba_s}
        finite = all(np.isfinite(x).all() for x in qs + vs)
        tip = pinocchio_tip(model, data, qs[0], S)
    elif peer == "pinocchio_parallel":
        import pinocchio as pin

        from hairwarp.executor import default_threads

        threads = default_threads()
        model = pinocchio_chain(S, (0.0, 0.0, 1.0))
        pool = pin.ModelPool(model, threads)
        q0 = pin.neutral(model)
        q0[0:4] = tilt_quat_xyzw(80.0)
        batch = {"q": np.asfortranarray(np.tile(q0[:, None], (1, G))), "v": np.zeros((model.nv, G), order="F"),
                 "a": np.zeros((model.nv, G), order="F")}
        aba_parallel, c = pin.abaInParallel, JOINT_DAMPING
        setup = time.perf_counter() - t0

        def step(k):
            q, v, a = batch["q"], batch["v"], batch["a"]
            for _ in range(k):
                aba_parallel(threads, pool, q, v, -c * v, a)
                v += dt * a
                q = integrate_spherical(q, v * dt)
            batch["q"] = q

        res = time_blocks(step, **timing)
        extra = {"threads": threads, "integrate": "numpy, batched over the strands (pin.integrate's arithmetic)"}
        finite = bool(np.isfinite(batch["q"]).all() and np.isfinite(batch["v"]).all())
        tip = pinocchio_tip(model, model.createData(), np.ascontiguousarray(batch["q"][:, 0]), S)
    elif peer in ("mujoco_euler", "mujoco_rollout_euler_t0", "mujoco_rollout_euler_threads"):
        import mujoco

        m = mujoco.MjModel.from_xml_string(mujoco_chain_xml(S, integrator="Euler", dt=dt, damping=JOINT_DAMPING,
                                                            root=(0.0, 0.0, 1.0)))
        if peer == "mujoco_euler":
            ds = [mujoco.MjData(m) for _ in range(G)]
            for d in ds:
                mujoco_set_tilt(m, d, 80.0)
            setup = time.perf_counter() - t0
            mj_step = mujoco.mj_step

            def step(k):
                for _ in range(k):
                    for d in ds:
                        mj_step(m, d)

            res = time_blocks(step, **timing)
            d = mujoco.MjData(m)
            c_only, n = 0.0, 250
            for _ in range(4):
                mujoco_set_tilt(m, d, 80.0)
                t1 = time.perf_counter()
                mujoco.mj_step(m, d, nstep=n)
                c_only += time.perf_counter() - t1
            c_only /= 4 * n
            extra = {"mj_step_us_per_strand_C_only": c_only * 1e6, "C_only_seg_steps_per_s": S / c_only}
            finite = all(np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all() for d in ds)
            tip = mujoco_tip(m, ds[0], S)
        else:
            from mujoco import rollout

            d = mujoco.MjData(m)
            mujoco_set_tilt(m, d, 80.0)
            spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
            x0 = np.zeros(mujoco.mj_stateSize(m, spec))
            mujoco.mj_getState(m, d, x0, spec)
            cur = [np.tile(x0, (G, 1))]
            if peer == "mujoco_rollout_euler_threads":
                from hairwarp.executor import default_threads

                nthread = default_threads()  # MuJoCo's own pool, one MjData per thread
            else:
                nthread = 0  # the calling thread
            ro = rollout.Rollout(nthread=nthread)
            datas = [mujoco.MjData(m) for _ in range(max(1, nthread))]
            buffers = {}
            setup = time.perf_counter() - t0

            def step(k):
                left = k
                while left > 0:
                    n = min(50, left)
                    buf = buffers.setdefault(n, np.empty((G, n, x0.size)))
                    ro.rollout(m, datas, cur[0], nstep=n, state=buf)
                    cur[0] = np.ascontiguousarray(buf[:, -1, :])
                    left -= n

            try:
                res = time_blocks(step, **timing)
            finally:
                ro.close()
            d.qpos[:] = cur[0][0, 1:1 + m.nq]
            finite = bool(np.isfinite(cur[0]).all())
            tip = mujoco_tip(m, d, S)
            extra = {"nthread": nthread, "nstep_per_call": 50}
    elif peer in ("newton_featherstone_tile", "newton_vbd"):
        roots = root_grid(G)
        model, step_fn, tip_fn, sync = _newton(peer, G, S, roots, 80.0, JOINT_DAMPING)
        setup = time.perf_counter() - t0
        res = time_blocks(step_fn(dt), sync, **timing)
        tip = tip_fn()
        finite = bool(np.isfinite(tip).all())
    else:
        raise ValueError(f"unknown peer {peer!r}")
    res["step_ms"] = res["step_s"] * 1e3
    res["seg_steps_per_s"] = G * S / res["step_s"]
    if bracket:
        res["hairwarp_bracket"] = bracket
    return {"peer": peer, "G": G, "S": S, "dt": dt, "setup_s": setup, "finite": bool(finite),
            "tip0": np.asarray(tip, float).tolist(), **res, "extra": extra}


# ---------------------------------------------------------------------------------------------
# trajectories of the reference strand (S = 20, root at the origin, 80 degrees, no damping)


def _samples(dt: float, duration: float, sample: float = 1e-3):
    per = int(round(sample / dt))
    if per < 1 or abs(per * dt - sample) > 1e-9:
        raise ValueError(f"dt = {dt} does not divide the 1 ms sample period")
    return per, int(round(duration / sample))


def _tips_pinocchio(dt, duration, S, method="euler"):
    import pinocchio as pin

    model = pinocchio_chain(S)
    data = model.createData()
    q = pin.neutral(model)
    q[0:4] = tilt_quat_xyzw(80.0)
    v = np.zeros(model.nv)
    tau = np.zeros(model.nv)
    per, ns = _samples(dt, duration)
    tips = [pinocchio_tip(model, data, q, S)]
    t0 = time.perf_counter()
    for _ in range(ns):
        for _ in range(per):
            if method == "euler":
                v = v + dt * pin.aba(model, data, q, v, tau)
                q = pin.integrate(model, q, v * dt)
            else:  # classical RK4 on the group: stages at q (+) c h v, as MuJoCo's RK4
                k1v, k1a = v, pin.aba(model, data, q, v, tau)
                q2 = pin.integrate(model, q, 0.5 * dt * k1v)
                k2v = v + 0.5 * dt * k1a
                k2a = pin.aba(model, data, q2, k2v, tau)
                q3 = pin.integrate(model, q, 0.5 * dt * k2v)
                k3v = v + 0.5 * dt * k2a
                k3a = pin.aba(model, data, q3, k3v, tau)
                q4 = pin.integrate(model, q, dt * k3v)
                k4v = v + dt * k3a
                k4a = pin.aba(model, data, q4, k4v, tau)
                q = pin.integrate(model, q, dt / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v))
                v = v + dt / 6.0 * (k1a + 2 * k2a + 2 * k3a + k4a)
        tips.append(pinocchio_tip(model, data, q, S))
    wall = time.perf_counter() - t0
    return np.array(tips), wall / (per * ns)


def _tips_mujoco(dt, duration, S, integrator):
    import mujoco

    m = mujoco.MjModel.from_xml_string(mujoco_chain_xml(S, integrator=integrator, dt=dt))
    d = mujoco.MjData(m)
    mujoco_set_tilt(m, d, 80.0)
    per, ns = _samples(dt, duration)
    tips = [mujoco_tip(m, d, S)]
    step_s = 0.0
    for _ in range(ns):
        t0 = time.perf_counter()
        mujoco.mj_step(m, d, nstep=per)
        step_s += time.perf_counter() - t0
        tips.append(mujoco_tip(m, d, S))
    return np.array(tips), step_s / (per * ns)


def reference(req: dict) -> dict:
    """The converged reference: MuJoCo RK4 (or, without MuJoCo, Pinocchio ABA + RK4) at a fine step."""
    dt, duration, S = float(req["dt"]), float(req["duration"]), int(req.get("S", 20))
    try:
        tips, _ = _tips_mujoco(dt, duration, S, "RK4")
        source = "mujoco RK4"
    except ModuleNotFoundError:
        tips, _ = _tips_pinocchio(dt, duration, S, method="rk4")
        source = "pinocchio ABA + RK4"
    return {"source": source, "dt": dt, "duration": duration, "S": S, "tip": tips.tolist()}


def trajectory(req: dict) -> dict:
    """Tip every 1 ms of the reference strand for each dt, and the CPU cost per strand-step."""
    peer, duration, S = req["peer"], float(req["duration"]), int(req.get("S", 20))
    runs = []
    cost = None
    for dt in req["dts"]:
        t0 = time.perf_counter()
        if peer == "pinocchio_euler":
            tips, cost = _tips_pinocchio(dt, duration, S)
        elif peer.startswith("mujoco_"):
            integrator = {"mujoco_euler": "Euler", "mujoco_implicitfast": "implicitfast", "mujoco_rk4": "RK4",
                          "mujoco_discrete": "discrete"}[peer]
            tips, cost = _tips_mujoco(dt, duration, S, integrator)
        elif peer in ("newton_featherstone_tile", "newton_vbd"):
            _, step_fn, tip_fn, _ = _newton(peer, 1, S, np.zeros((1, 3)), 80.0, 0.0)
            step = step_fn(dt)
            per, ns = _samples(dt, duration)
            tips = [tip_fn()]
            for _ in range(ns):
                step(per)
                tips.append(tip_fn())
            tips = np.array(tips)
        else:
            raise ValueError(f"unknown peer {peer!r}")
        runs.append({"dt": dt, "tip": np.asarray(tips).tolist(), "wall_s": time.perf_counter() - t0})
    if peer.startswith("newton"):
        B = int(req.get("cost_strands", 100))
        _, step_fn, _, sync = _newton(peer, B, S, root_grid(B, z=0.0), 80.0, 0.0)
        t = time_blocks(step_fn(BENCH_DT), sync, steps=10, blocks=3, warmup=2, budget_s=6.0)
        cost = t["step_s"] / B
        cost_note = f"step time of a batch of {B} strands / {B}"
    elif peer == "pinocchio_euler":
        cost_note = "ABA + integrate per strand-step from Python, measured on the trajectory runs"
    else:
        cost_note = "mj_step(nstep) C time per strand-step, measured on the trajectory runs"
    return {"peer": peer, "S": S, "runs": runs, "cost_s_per_strand_step": cost, "cost_note": cost_note}


# ---------------------------------------------------------------------------------------------
# MuJoCo stability with joint springs


def mujoco_stable(integrator: str, segments: int, stiffness, joint_damping: float, dt: float,
                  duration: float, tilt_deg: float = 60.0) -> dict:
    """One run of the stability test on MuJoCo: released from ``tilt_deg`` with ball-joint springs.

    Stable: finite, no MuJoCo instability warning, no joint turning more than 1 rad in a step
    and total energy never above its initial value by more than 10 % of (E0 - E_rest).
    """
    import mujoco

    # joint stiffness [N m/rad] per joint, as hairwarp's model sets it (a number: EI / L at every joint)
    K = list(stiffness) if np.ndim(stiffness) else [stiffness / (STRAND_LENGTH / segments)] * segments
    m = mujoco.MjModel.from_xml_string(mujoco_chain_xml(segments, integrator=integrator, dt=dt, damping=joint_damping,
                                                        stiffness=K))
    d = mujoco.MjData(m)
    mujoco.mj_resetData(m, d)
    mujoco.mj_forward(m, d)
    e_rest = float(d.energy.sum())
    mujoco_set_tilt(m, d, tilt_deg)
    e0 = float(d.energy.sum())
    bound = e0 + 0.1 * (e0 - e_rest)
    steps = int(math.ceil(duration / dt))
    chunk = max(1, int(round(2e-3 / dt)))
    done = 0
    while done < steps:
        n = min(chunk, steps - done)
        mujoco.mj_step(m, d, nstep=n)
        done += n
        mujoco.mj_forward(m, d)
        if d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number > 0:
            return {"stable": False, "why": "MuJoCo instability warning", "t": done * dt}
        if not (np.isfinite(d.qpos).all() and np.isfinite(d.qvel).all()):
            return {"stable": False, "why": "non-finite", "t": done * dt}
        if np.abs(d.qvel).reshape(-1, 3).__pow__(2).sum(axis=1).max() ** 0.5 * dt > 1.0:
            return {"stable": False, "why": "joint > 1 rad per step", "t": done * dt}
        if float(d.energy.sum()) > bound:
            return {"stable": False, "why": "energy gain", "t": done * dt}
    return {"stable": True}


def largest_stable_dt(grid, run) -> dict:
    """Largest stable step on ``grid`` (ascending [s]) by bisection, ``run(dt) -> {"stable", "why"}`` being one
    stability run: the row the stability map stores for one stiffness."""
    from hairwarp.benchmarks.stability import bisect_grid

    why = {}

    def probe(idx, items):
        r = run(grid[idx])
        why[idx] = r.get("why")
        return {0: r["stable"]}

    t0 = time.perf_counter()
    (idx,), tested = bisect_grid(len(grid), 1, probe)
    above = 0 if idx is None else idx + 1
    return {"max_stable_dt": None if idx is None else grid[idx], "grid_index": idx, "at_top": idx == len(grid) - 1,
            "fails_above_because": why.get(above), "probes": len(tested), "wall_s": time.perf_counter() - t0}


def stability_mujoco(req: dict) -> dict:
    """Largest stable dt per stiffness for MuJoCo integrators, by bisection on the shared log grid."""
    grid = [float(x) for x in req["grid"]]
    out = {}
    for integrator in req["integrators"]:
        rows = []
        for ei in req["stiffness"]:
            joint_k = req.get("joint_stiffness", {}).get(f"{ei:g}", ei)
            def run(dt, integrator=integrator, joint_k=joint_k):
                return mujoco_stable(integrator, int(req["S"]), joint_k, float(req["joint_damping"]), dt,
                                     float(req["duration"]))

            rows.append({"bend_stiffness": ei, **largest_stable_dt(grid, run)})
        out[integrator] = rows
    return {"results": out}


# ---------------------------------------------------------------------------------------------
# Newton VBD rod stability with bending springs


def newton_vbd_stable(segments: int, joint_stiffness: float, joint_damping: float, dt: float, duration: float,
                      tilt_deg: float = 60.0, iterations: int = 10) -> dict:
    """One run of the stability test on Newton's VBD rods: the strand hangs straight down at rest (``add_rod`` with
    ``bend_stiffness`` = ``twist_stiffness`` = the joint stiffness [N m/rad] of every joint between segments) and is
    released turned ``tilt_deg`` about its root. Newton 1.8 applies ball-joint stiffness in SolverMuJoCo only, so the
    root joint here is a free pivot (hairwarp and MuJoCo give it a spring).

    Stable, as for MuJoCo: finite, no segment turning more than 1 rad in a step, and the total energy (kinetic,
    gravity, the joints' springs) never above its initial value by more than 10 % of (E0 - E_rest); checked every
    2 ms.
    """
    import newton
    import warp as wp
    from scipy.spatial.transform import Rotation

    wp.config.quiet = True
    L, m = STRAND_LENGTH / segments, segment_mass(segments)
    inertia = segment_inertia(segments)
    builder = newton.ModelBuilder(gravity=(0.0, 0.0, -GRAVITY))
    cfg = newton.ModelBuilder.ShapeConfig(density=DENSITY, has_shape_collision=False, has_particle_collision=False)
    verts = straight_strands(np.zeros((1, 3)), segments, np.array([0.0, 0.0, -1.0]))
    rod = newton.Rod([wp.vec3(*p) for p in verts[0]], radius=RADIUS)
    bodies, joints = builder.add_rod(rod=rod, cfg=cfg, stretch_stiffness=1.0e5, stretch_damping=0.0,
                                     bend_stiffness=joint_stiffness, bend_damping=joint_damping,
                                     twist_stiffness=joint_stiffness, twist_damping=joint_damping,
                                     wrap_in_articulation=False)
    _cylinder_bodies(builder, bodies, segments)
    root = builder.add_joint_ball(parent=-1, child=bodies[0], parent_xform=wp.transform_identity(),
                                  child_xform=wp.transform(wp.vec3(0.0, 0.0, -L / 2), wp.quat_identity()),
                                  armature=0.0, friction=0.0, damping=joint_damping)
    builder.add_articulation([*joints, root])
    builder.color()
    model = builder.finalize(device="cpu")
    solver = newton.solvers.SolverVBD(model, iterations=iterations)
    states = [model.state(), model.state()]
    control = model.control()
    rest = states[0].body_q.numpy().astype(np.float64)

    def energy(q, qd) -> float:
        rot = Rotation.from_quat(q[:, 3:])
        w = qd[:, 3:]
        w_body = rot.inv().apply(w)
        kinetic = 0.5 * m * np.sum(qd[:, :3] ** 2) + 0.5 * np.sum(w_body ** 2 * inertia)
        bend = (rot[:-1].inv() * rot[1:]).magnitude() if segments > 1 else np.zeros(0)
        return float(kinetic + m * GRAVITY * q[:, 2].sum() + 0.5 * joint_stiffness * np.sum(bend ** 2))

    e_rest = energy(rest, np.zeros((segments, 6)))
    turn = Rotation.from_rotvec([0.0, math.radians(tilt_deg), 0.0])
    q = rest.copy()
    q[:, :3] = turn.apply(rest[:, :3])
    q[:, 3:] = (turn * Rotation.from_quat(rest[:, 3:])).as_quat()
    for s in states:
        s.body_q.assign(q.astype(np.float32))
    e0 = energy(q, np.zeros((segments, 6)))
    bound = e0 + 0.1 * (e0 - e_rest)
    steps = int(math.ceil(duration / dt))
    chunk = max(1, int(round(2e-3 / dt)))
    done = 0
    while done < steps:
        for _ in range(min(chunk, steps - done)):
            states[0].clear_forces()
            solver.step(states[0], states[1], control, None, dt)
            states[0], states[1] = states[1], states[0]
            done += 1
        q = states[0].body_q.numpy().astype(np.float64)
        qd = states[0].body_qd.numpy().astype(np.float64)
        if not (np.isfinite(q).all() and np.isfinite(qd).all()):
            return {"stable": False, "why": "non-finite", "t": done * dt}
        if np.linalg.norm(qd[:, 3:], axis=1).max() * dt > 1.0:
            return {"stable": False, "why": "segment > 1 rad per step", "t": done * dt}
        if energy(q, qd) > bound:
            return {"stable": False, "why": "energy gain", "t": done * dt}
    return {"stable": True}


def stability_newton(req: dict) -> dict:
    """Largest stable dt per bend stiffness EI for Newton's VBD rods (joint stiffness EI / L between segments), by
    bisection on the shared log grid."""
    grid = [float(x) for x in req["grid"]]
    S = int(req["S"])
    rows = [{"bend_stiffness": ei, **largest_stable_dt(grid, lambda dt, ei=ei: newton_vbd_stable(
        S, float(ei) / (STRAND_LENGTH / S), float(req["joint_damping"]), dt, float(req["duration"])))}
            for ei in req["stiffness"]]
    return {"results": {"newton_vbd": rows}, "grid_used": grid, "duration_s": float(req["duration"])}


def run_request(req: dict) -> dict:
    kind = req["kind"]
    if kind == "throughput":
        return throughput(req)
    if kind == "trajectory":
        return trajectory(req)
    if kind == "reference":
        return reference(req)
    if kind == "stability_mujoco":
        return stability_mujoco(req)
    if kind == "stability_newton":
        return stability_newton(req)
    if kind == "robustness_mujoco_rest":
        from hairwarp.benchmarks.robustness import mujoco_rest

        return mujoco_rest(req)
    if kind == "robustness_newton_rest":
        from hairwarp.benchmarks.robustness import newton_rest

        return newton_rest(req)
    raise ValueError(f"unknown request kind {kind!r}")
