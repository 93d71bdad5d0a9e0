"""Suite ``stability``: the largest stable step against bend stiffness, segment count and tip-to-root
mass ratio, per integrator, and for MuJoCo's integrators with the same joint springs.

The test: a strand of 0.3 m whose rest shape hangs straight down is released, straight, with its
root joint turned 60 degrees, and simulated for a fixed time. It is *stable* at a step dt when
every sample (every 2 ms or every step, whichever is longer) is finite, no joint turns more than
1 rad in a step (``|w| dt``), and the total energy (kinetic + gravity + joint springs) never rises
above its initial value by more than 10 % of the energy the strand can release (E0 - E_rest); the
root is fixed, so gravity's work is the change of its potential. The largest stable dt is found by
bisection on a log grid from 1e-5 s to 1/24 s, all strands of a sweep in one model.
"""

from __future__ import annotations

import math
import time

import numpy as np

from hairwarp.benchmarks.common import (
    DENSITY,
    GRAVITY,
    RADIUS,
    STRAND_LENGTH,
    run_child,
    straight_strands,
    tilt_direction,
)
from hairwarp.benchmarks.ours import StepRunner
from hairwarp.model import Model, StrandParams
from hairwarp.solver import Solver

DT_MIN = 1.0e-5
DT_MAX = 1.0 / 24.0
RELEASE_DEG = 60.0
ENERGY_MARGIN = 0.1
MAX_TURN = 1.0
SAMPLE = 2.0e-3


def dt_grid(bits: int) -> np.ndarray:
    """2**bits + 1 steps, geometric from DT_MIN to DT_MAX."""
    n = 2**bits
    return DT_MIN * (DT_MAX / DT_MIN) ** (np.arange(n + 1) / n)


def _log_peer(log, result: dict) -> None:
    """One line per method of a peer's stability map (or its failure)."""
    if result.get("status") != "ok":
        log(f"  {result.get('status')}: {result.get('message', '')[:200]}")
        return
    for name, rows in result["results"].items():
        log(f"  {name}: " + ", ".join(f"{r['bend_stiffness']:g}: {_fmt_dt(r['max_stable_dt'])}" for r in rows))


def bisect_grid(n_grid: int, n_items: int, probe):
    """Largest grid index at which each item is stable, assuming stability is monotone in dt.

    ``probe(index, items)`` runs the test at ``grid[index]`` and returns ``{item: stable}`` for at
    least ``items`` (more are kept). Returns ``(indices, tested)``: the index per item (None when
    unstable even at index 0) and every result ``{(item, index): stable}``.
    """
    tested: dict = {}

    def ask(pairs):
        need: dict = {}
        for item, idx in pairs:
            if (item, idx) not in tested:
                need.setdefault(idx, []).append(item)
        for idx, items in need.items():
            for item, ok in probe(idx, items).items():
                tested[(item, idx)] = bool(ok)
        return [tested[p] for p in pairs]

    top = n_grid - 1
    lo, hi = [0] * n_items, [top] * n_items
    for item, ok in enumerate(ask([(j, top) for j in range(n_items)])):
        if ok:
            lo[item] = hi[item] = top
    while True:
        pending = [(j, (lo[j] + hi[j]) // 2) for j in range(n_items) if hi[j] - lo[j] > 1]
        if not pending:
            break
        for (j, mid), ok in zip(pending, ask(pending)):
            if ok:
                lo[j] = mid
            else:
                hi[j] = mid
    final = ask([(j, lo[j]) for j in range(n_items)])
    return [lo[j] if final[j] else None for j in range(n_items)], tested


def stability_model(segments: int, stiffness, joint_damping: float, mass_ratio=None, device="cpu") -> Model:
    """One strand per entry of ``stiffness`` (EI, N m^2): rest hanging down, released from 60 degrees.

    Twist stiffness equals EI (isotropic, as MuJoCo's ball-joint springs); ``joint_damping`` is the
    damping of every joint [N m s/rad] (the rod damping is that times the segment length).

    ``mass_ratio`` (one per strand) tapers the radius geometrically from the root so that the tip
    segment's mass is that fraction of the root segment's; EI stays the same.
    """
    stiffness = np.atleast_1d(np.asarray(stiffness, float))
    G = len(stiffness) if mass_ratio is None else len(mass_ratio)
    stiffness = np.broadcast_to(stiffness, (G,))
    roots = np.zeros((G, 3))
    roots[:, 0] = 0.05 * np.arange(G)
    init = straight_strands(roots, segments, tilt_direction(RELEASE_DEG))
    rest = straight_strands(roots, segments, (0.0, 0.0, -1.0))
    params = StrandParams(density=DENSITY, radius=RADIUS, bend_stiffness=1.0, twist_stiffness=1.0,
                          damping=joint_damping * STRAND_LENGTH / segments)
    model = Model.build(init, params, segments=segments, device=device, rest_vertices=rest)
    k = model.joint_stiffness.numpy().reshape(G, segments, 3) * stiffness[:, None, None]
    model.joint_stiffness.assign(k.reshape(-1, 3))
    if mass_ratio is not None:
        L = STRAND_LENGTH / segments
        frac = np.arange(segments) / max(1, segments - 1)
        r = RADIUS * np.sqrt(np.asarray(mass_ratio, float)[:, None] ** frac[None, :])  # mass ~ r^2
        m = DENSITY * math.pi * r**2 * L
        perp = m * (3.0 * r * r + L * L) / 12.0
        model.seg_mass.assign(m.reshape(-1).astype(np.float32))
        model.seg_inertia.assign(np.stack([perp, perp, 0.5 * m * r * r], axis=-1).reshape(-1, 3).astype(np.float32))
    return model


class EnergyMeter:
    """Total energy per strand from a state: kinetic (segments as rigid bodies) + gravity + joint springs."""

    def __init__(self, model: Model):
        self.G, self.S = model.strand_count, model.seg_per_strand
        self.mass = model.seg_mass.numpy().astype(float).reshape(self.G, self.S)
        self.inertia = model.seg_inertia.numpy().astype(float).reshape(self.G, self.S, 3)
        self.K = model.joint_stiffness.numpy().astype(float).reshape(self.G, self.S, 3)
        self.rest_conj = model.joint_rest_q.numpy().astype(float).reshape(self.G, self.S, 4) * [-1, -1, -1, 1]
        rest = model.rest_vertex_positions
        self.e_rest = (self.mass * GRAVITY * 0.5 * (rest[:, :-1, 2] + rest[:, 1:, 2])).sum(axis=1)

    def __call__(self, state) -> np.ndarray:
        G, S = self.G, self.S
        x = state.vertex_positions.numpy().astype(float).reshape(G, S + 1, 3)
        v = state.vertex_velocities.numpy().astype(float).reshape(G, S + 1, 3)
        xf = state.seg_xform.numpy().astype(float).reshape(G, S, 7)
        q = state.joint_q.numpy().astype(float).reshape(G, S, 4)
        qd = state.joint_qd.numpy().astype(float).reshape(G, S, 3)
        rot = xf[..., 3:]
        w_world = np.cumsum(_rotate(rot, qd), axis=1)  # the head is at rest
        w_body = _rotate(rot * [-1, -1, -1, 1], w_world)
        v_com = 0.5 * (v[:, :-1] + v[:, 1:])
        kinetic = 0.5 * (self.mass * (v_com**2).sum(-1) + (self.inertia * w_body**2).sum(-1)).sum(axis=1)
        gravity = (self.mass * GRAVITY * 0.5 * (x[:, :-1, 2] + x[:, 1:, 2])).sum(axis=1)
        theta = _log(_qmul(self.rest_conj, q))
        spring = 0.5 * (self.K * theta**2).sum(axis=(1, 2))
        return kinetic + gravity + spring


def _rotate(q, v):
    u, w = q[..., :3], q[..., 3:4]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _qmul(a, b):
    av, aw, bv, bw = a[..., :3], a[..., 3:4], b[..., :3], b[..., 3:4]
    return np.concatenate([aw * bv + bw * av + np.cross(av, bv), aw * bw - (av * bv).sum(-1, keepdims=True)], -1)


def _log(q):
    q = np.where(q[..., 3:4] < 0.0, -q, q)
    s = np.linalg.norm(q[..., :3], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., 3:4])
    scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0)
    return q[..., :3] * scale


def run_test(model: Model, integrator: str, dt: float, duration: float, meter: EnergyMeter | None = None) -> dict:
    """Run the stability test of every strand of ``model`` at ``dt``; per strand stable flag and reason."""
    meter = meter or EnergyMeter(model)
    chunk = max(1, int(round(SAMPLE / dt)))
    runner = StepRunner(model, Solver(model, integrator, max_rotation_per_step=math.inf), dt, chunk, graph=True)
    e0 = meter(runner.current)
    bound = e0 + ENERGY_MARGIN * (e0 - meter.e_rest)
    G, S = model.strand_count, model.seg_per_strand
    why = [None] * G
    steps = int(math.ceil(duration / dt))
    while runner.steps < steps:
        runner.advance(1)
        state = runner.current
        qd = state.joint_qd.numpy().reshape(G, S, 3)
        with np.errstate(all="ignore"):
            e = meter(state)
            turn = np.linalg.norm(qd, axis=-1).max(axis=1) * dt
        for g in range(G):
            if why[g] is not None:
                continue
            if not (np.isfinite(e[g]) and np.isfinite(qd[g]).all()):
                why[g] = "non-finite"
            elif turn[g] > MAX_TURN:
                why[g] = "joint > 1 rad per step"
            elif e[g] > bound[g]:
                why[g] = "energy gain"
        if all(w is not None for w in why):
            break
    return {"stable": [w is None for w in why], "why": why}


def sweep(model_fn, n_items: int, integrator: str, duration: float, bits: int) -> dict:
    """Largest stable dt per item (strand) of ``model_fn()`` by batched bisection."""
    grid = dt_grid(bits)
    model = model_fn()
    meter = EnergyMeter(model)
    why: dict = {}

    def probe(idx, items):
        r = run_test(model, integrator, float(grid[idx]), duration, meter)
        for j in range(n_items):
            why[(j, idx)] = r["why"][j]
        return dict(enumerate(r["stable"]))

    t0 = time.perf_counter()
    indices, tested = bisect_grid(len(grid), n_items, probe)
    out = []
    for j, idx in enumerate(indices):
        above = idx + 1 if idx is not None else 0
        out.append({"max_stable_dt": None if idx is None else float(grid[idx]), "grid_index": idx,
                    "at_top": idx == len(grid) - 1,
                    "fails_above_because": why.get((j, above)) if above < len(grid) else None})
    return {"items": out, "probes": len({i for _, i in tested}), "wall_s": time.perf_counter() - t0}


def suite_stability(cfg, log=lambda msg: None) -> dict:
    grid = dt_grid(cfg.stab_grid_bits)
    hair_joint_damping = cfg.stab_hair_damping / (STRAND_LENGTH / 20)
    res = {"test": {"segments": 20, "length_m": STRAND_LENGTH, "release_deg": RELEASE_DEG,
                    "duration_s": cfg.stab_duration, "side_duration_s": cfg.stab_side_duration,
                    "joint_damping_N_m_s": cfg.stab_joint_damping, "hair_damping_N_m2_s": cfg.stab_hair_damping,
                    "hair_joint_damping_N_m_s": hair_joint_damping, "twist_stiffness": "= EI (isotropic)",
                    "criteria": "finite; |w| dt <= 1 rad; E(t) <= E0 + 0.1 (E0 - E_rest)",
                    "sample_s": SAMPLE, "dt_min": DT_MIN, "dt_max": DT_MAX, "grid_points": len(grid)}}
    rows = {}
    runs = [(i, i, cfg.stab_joint_damping) for i in cfg.stab_integrators]
    runs += [(i, f"{i}, hair damping", hair_joint_damping) for i in cfg.stab_hair_integrators]
    for integrator, label, damping in runs:
        log(f"stability vs EI: {label} ...")
        r = sweep(lambda d=damping: stability_model(20, cfg.stab_stiffness, d), len(cfg.stab_stiffness),
                  integrator, cfg.stab_duration, cfg.stab_grid_bits)
        rows[label] = [{"bend_stiffness": ei, **item} for ei, item in zip(cfg.stab_stiffness, r["items"])]
        log("  " + ", ".join(f"{ei:g}: {_fmt_dt(it['max_stable_dt'])}"
                             for ei, it in zip(cfg.stab_stiffness, r["items"])) + f" ({r['wall_s']:.1f} s)")
    res["vs_stiffness"] = rows
    log("stability vs EI: MuJoCo ...")
    # MuJoCo's ball joints get the joint stiffness hairwarp's model gives each joint (root included)
    mj_model = stability_model(20, cfg.stab_mujoco_stiffness, cfg.stab_joint_damping)
    bend = mj_model.joint_stiffness.numpy().reshape(len(cfg.stab_mujoco_stiffness), 20, 3)[:, :, 0]
    joint_k = {f"{ei:g}": bend[n].astype(float).tolist() for n, ei in enumerate(cfg.stab_mujoco_stiffness)}
    mj = run_child({"kind": "stability_mujoco", "integrators": list(cfg.stab_mujoco),
                    "stiffness": list(cfg.stab_mujoco_stiffness), "joint_stiffness": joint_k, "grid": grid.tolist(),
                    "S": 20, "joint_damping": cfg.stab_joint_damping, "duration": cfg.stab_duration},
                   max(cfg.peer_timeout_s, 600.0))
    res["mujoco"] = mj
    _log_peer(log, mj)
    log("stability vs EI: Newton VBD rods ...")
    nt = run_child({"kind": "stability_newton", "stiffness": list(cfg.stab_newton_stiffness),
                    "grid": [float(g) for g in grid if g >= cfg.stab_newton_min_dt], "min_dt": cfg.stab_newton_min_dt,
                    "S": 20, "joint_damping": cfg.stab_joint_damping,
                    "duration": min(cfg.stab_duration, cfg.stab_newton_duration)},
                   max(cfg.peer_timeout_s, 600.0))
    res["newton"] = nt
    _log_peer(log, nt)
    seg_rows = {}
    for integrator in cfg.stab_integrators[:2]:
        log(f"stability vs segments: {integrator} ...")
        seg_rows[integrator] = []
        for S in cfg.stab_segments:
            r = sweep(lambda S=S: stability_model(S, cfg.stab_segment_stiffness, cfg.stab_joint_damping),
                      len(cfg.stab_segment_stiffness), integrator, cfg.stab_side_duration, cfg.stab_grid_bits)
            seg_rows[integrator] += [{"segments": S, "bend_stiffness": ei, **it}
                                     for ei, it in zip(cfg.stab_segment_stiffness, r["items"])]
    res["vs_segments"] = seg_rows
    mass_rows = {}
    for integrator in cfg.stab_integrators[:2]:
        log(f"stability vs tip/root mass: {integrator} ...")
        r = sweep(lambda: stability_model(20, cfg.stab_mass_stiffness, cfg.stab_joint_damping, cfg.stab_mass_ratios),
                  len(cfg.stab_mass_ratios), integrator, cfg.stab_side_duration, cfg.stab_grid_bits)
        mass_rows[integrator] = [{"mass_ratio": mr, **it} for mr, it in zip(cfg.stab_mass_ratios, r["items"])]
    res["vs_mass_ratio"] = {"bend_stiffness": cfg.stab_mass_stiffness, "rows": mass_rows}
    res["findings"] = findings(res)
    return res


def _fmt_dt(dt):
    return "unstable at 1e-5" if dt is None else f"{dt:.3g}"


def findings(res: dict) -> dict:
    """Stiffnesses where implicit_joints holds a frame-rate step while semi_implicit does not, and where
    implicit_joints itself fails at 1/240 s and 1/24 s."""
    frame = 1.0 / 240.0
    tol = 1.0 - 1e-9
    semi = {r["bend_stiffness"]: r["max_stable_dt"] for r in res["vs_stiffness"].get("semi_implicit", [])}
    impl_rows = res["vs_stiffness"].get("implicit_joints", [])
    impl = {r["bend_stiffness"]: r["max_stable_dt"] for r in impl_rows}
    ok = lambda dt, bound: dt is not None and dt >= bound * tol  # noqa: E731
    return {
        "implicit_failure_reasons": {f"{r['bend_stiffness']:g}": r.get("fails_above_because") for r in impl_rows
                                     if not r.get("at_top")},
        "frame_dt": frame,
        "implicit_stable_semi_not_at_frame_dt": [ei for ei in impl if ok(impl[ei], frame) and not ok(semi.get(ei),
                                                                                                      frame)],
        "implicit_fails_at_frame_dt": [ei for ei in impl if not ok(impl[ei], frame)],
        "implicit_fails_at_1_24": [ei for ei in impl if not ok(impl[ei], DT_MAX)],
        "semi_fails_at_frame_dt": [ei for ei in semi if not ok(semi[ei], frame)],
    }
