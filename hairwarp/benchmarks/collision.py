"""Strand-object collision benchmarks: tunnelling map, collision cost on the Ratboy body, resting jitter.

* :func:`bench_tunnelling` - at what collider speed each collider kind starts to let strand vertices
  through, against the substeps per 30 fps frame, with the point test alone and with the swept test
  (``ColliderSet(swept=...)``); a JSON and a PNG chart when given ``out``.
* :func:`bench_collision_cost` - the cost per step of the collision stage against the TressFX Ratboy
  body (25,814 triangles) under its mohawk (2,219 guides x 31 segments), next to the dynamics in the same
  run; uses :func:`hairwarp.colliders.bench_collision` for the rest and perturbed states.
* :func:`bench_resting_jitter` - jitter of tips resting on the shoulders (``scenes/long_hair_shoulders``)
  over the last second, head still.
* :func:`suite_collision` - all three, the ``collision`` suite of ``hairwarp bench``.

Every figure is measured on the host in float64 from the vertex positions the solver writes, against
closed forms of the collider shapes (the mesh's own face planes for the mesh kind), not through the
kernels' own queries.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import warp as wp

from hairwarp.benchmarks.common import interleaved_medians, ratboy_assets, ratboy_mohawk_scene

# ---------------------------------------------------------------------------------------------
# tunnelling map

#: Collider kinds of the map.
TUNNEL_KINDS = ("sphere", "capsule", "plane", "mesh")
#: Collision tests compared: the end positions alone (``ColliderSet(swept=False)``), the swept test from
#: the positions the velocities imply (``Solver.step`` as it calls the projection now), and the swept
#: test given the step's start (``ColliderSet.project(..., state_in=...)``).
TUNNEL_MODES = ("point", "swept_estimate", "swept")
#: Output frame rate the substeps divide [1/s].
TUNNEL_FPS = 30.0
#: Substeps per frame (dt = 1 / (30 substeps)).
TUNNEL_SUBSTEPS = (1, 2, 4, 8, 16)
#: Collider speeds [m/s]: 0.25 to 64 in steps of sqrt(2).
TUNNEL_SPEEDS = tuple(round(0.25 * math.sqrt(2.0) ** k, 4) for k in range(17))
#: Size of the sphere (radius), of the capsule (radius; axis half length 0.1 m) and of the mesh (an
#: icosphere of this radius) [m]: the thickness a collider offers along its motion is twice this.
TUNNEL_SIZE = 0.05
# Strand field: a 5 x 5 grid of roots 2 cm apart at z = 0, strands of 0.3 m hanging straight down in
# 15 segments; colliders cross it along +x at mid height, the plane rises under it as a floor.
_FIELD_SPACING = 0.02
_FIELD_LENGTH = 0.3
_FIELD_SEGMENTS = 15
_CROSS_HEIGHT = -0.15
_CAPSULE_HALF_HEIGHT = 0.1
_FLOOR_START = -0.35
_FLOOR_STOP = -0.1
_THICKNESS = 1.0e-3
_FRICTION = 0.3
# Fault bound of the runs [rad per step], as in the shipped scenes: a scene run that exceeds it stops.
# The map records the first such step and goes on until the dynamics blow up (_BLOWUP).
_MAX_ROTATION = 1.0
_BLOWUP = 1 | 4  # Fault.NONFINITE_DYNAMICS | Fault.NONFINITE_COLLISION
#: A vertex deeper than this [m] after a step is through: float32 positions and the 10 um push margin
#: are far below it, and the mesh is measured against its own face planes (exact inside a convex mesh).
THROUGH_DEPTH = 1.0e-4
#: A vertex whose straight path relative to the collider over one step passes deeper than this fraction
#: of the collider's half thickness went through its core (pushed out on the far side). Sliding round a
#: sphere takes a relative step of 1.7 radii per step to cut that deep.
THROUGH_CORE_FRACTION = 0.5
# Samples along a vertex's relative path in one step for the core test.
_PATH_SAMPLES = 17


def _field_vertices(per_side: int) -> np.ndarray:
    """Straight hanging strands (G, S+1, 3) on a square grid of roots at z = 0, centred on the origin."""
    c = (np.arange(per_side) - 0.5 * (per_side - 1)) * _FIELD_SPACING
    gx, gy = np.meshgrid(c, c, indexing="ij")
    roots = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    z = -np.linspace(0.0, _FIELD_LENGTH, _FIELD_SEGMENTS + 1)
    verts = np.repeat(roots[:, None, :], _FIELD_SEGMENTS + 1, axis=1)
    verts[:, :, 2] = z
    return verts


def _tunnel_collider(kind: str):
    from hairwarp.colliders import Collider

    opts = {"attach": "world", "thickness": _THICKNESS, "friction": _FRICTION, "name": kind}
    if kind == "sphere":
        return Collider.sphere(TUNNEL_SIZE, **opts)
    if kind == "capsule":
        return Collider.capsule(TUNNEL_SIZE, _CAPSULE_HALF_HEIGHT, **opts)
    if kind == "plane":
        return Collider.plane(**opts)
    if kind == "mesh":
        return Collider.ellipsoid((0.0, 0.0, 0.0), (TUNNEL_SIZE,) * 3, subdivisions=3, **opts)
    raise ValueError(f"unknown collider kind {kind!r}; choose one of {', '.join(TUNNEL_KINDS)}")


def _tunnel_path(kind: str, speed: float):
    """Pose function t -> (4x4 world pose, linear velocity) and the time the crossing ends [s]."""
    rot = np.eye(4)
    if kind == "capsule":
        rot[:3, :3] = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))  # axis (local z) along world y
    if kind == "plane":
        t_stop = (_FLOOR_STOP - _FLOOR_START) / speed

        def pose(t):
            m = rot.copy()
            m[2, 3] = _FLOOR_START + speed * min(t, t_stop)
            return m, (0.0, 0.0, speed if t < t_stop else 0.0)

        return pose, t_stop + 0.05
    half = 0.5 * (_FIELD_SPACING * 4) + TUNNEL_SIZE
    x0, x1 = -(half + 0.02), half + 0.2

    def pose(t):
        m = rot.copy()
        m[:3, 3] = (x0 + speed * t, 0.0, _CROSS_HEIGHT)
        return m, (speed, 0.0, 0.0)

    return pose, (x1 - x0) / speed


class _ShapeProbe:
    """Float64 signed distances of local points to one collider shape (closed forms; the mesh's planes)."""

    def __init__(self, collider):
        from hairwarp.kernels.types import ColliderKind

        self.kind = collider.kind
        self.radius = collider.radius
        self.half_height = collider.half_height
        self.core = TUNNEL_SIZE
        if collider.kind == ColliderKind.MESH:
            mesh = collider.mesh
            self.normals = np.asarray(mesh.face_normals, dtype=float)
            self.offsets = np.einsum("ij,ij->i", self.normals, np.asarray(mesh.triangles_center, dtype=float))
            self.radius = TUNNEL_SIZE
        self._kinds = ColliderKind

    def depth(self, x: np.ndarray) -> np.ndarray:
        """How deep local points lie inside [m] (<= 0 outside); exact inside for every kind."""
        k = self._kinds
        if self.kind == k.PLANE:
            return -x[..., 2]
        if self.kind == k.MESH:
            # The icosphere lies inside the sphere through its vertices: only points within it need the planes.
            depth = -self.core_distance(x)
            near = depth > -THROUGH_DEPTH
            depth[near] = -(x[near] @ self.normals.T - self.offsets).max(axis=-1)
            return depth
        return -self.core_distance(x)

    def core_distance(self, x: np.ndarray) -> np.ndarray:
        """Signed distance to the smooth shape (sphere or capsule; the mesh as its sphere) [m]."""
        if self.kind == self._kinds.CAPSULE:
            axis = np.zeros_like(x)
            axis[..., 2] = np.clip(x[..., 2], -self.half_height, self.half_height)
            return np.linalg.norm(x - axis, axis=-1) - self.radius
        return np.linalg.norm(x, axis=-1) - self.radius


def _tunnel_run(kind: str, substeps: int, speed: float, mode: str, per_side: int, device) -> dict:
    from hairwarp.colliders import ColliderSet
    from hairwarp.model import Model, StrandParams
    from hairwarp.solver import Solver

    dt = 1.0 / (TUNNEL_FPS * substeps)
    verts = _field_vertices(per_side)
    G, S = verts.shape[0], verts.shape[1] - 1
    model = Model.build(verts, StrandParams(drag=0.01), segments=S, device=device)
    collider = _tunnel_collider(kind)
    if mode not in TUNNEL_MODES:
        raise ValueError(f"unknown mode {mode!r}; choose one of {', '.join(TUNNEL_MODES)}")
    previous = mode == "swept"
    colliders = ColliderSet([collider], device, swept=mode != "point")
    pose, t_end = _tunnel_path(kind, speed)
    m, vel = pose(0.0)
    colliders.set_pose(0, m, linear_velocity=vel)
    colliders.bind(model)
    # The solver integrates; the projection runs here as Solver.step runs it, given the step's start
    # when ``previous`` is set.
    solver = Solver(model, max_rotation_per_step=_MAX_ROTATION)
    control = model.control()
    states = [model.state(), model.state()]
    probe = _ShapeProbe(collider)
    steps = int(math.ceil(t_end / dt)) + 1
    x_prev = states[0].vertex_positions.numpy().reshape(G, S + 1, 3).astype(float)[:, 1:]
    m_prev = m
    through = np.zeros((G, S), dtype=bool)
    silent = np.zeros((G, S), dtype=bool)
    events = 0
    max_depth = 0.0
    max_core = 0.0
    fault_step = None
    blowup_step = None
    t0 = time.perf_counter()
    for n in range(steps):
        m, vel = pose((n + 1) * dt)
        colliders.set_pose(0, m, linear_velocity=vel)
        solver.step(states[0], states[1], control, dt)
        colliders.project(model, states[1], control, solver.dt, states[0] if previous else None)
        states.reverse()
        x = states[0].vertex_positions.numpy().reshape(G, S + 1, 3).astype(float)[:, 1:]
        bits = int(states[0].fault.numpy()[0])
        if bits and fault_step is None:
            # A scene run stops at the end of this frame, with a message that names the step size, and
            # never writes this step: only vertices through before it reach a cache silently.
            fault_step = n
        if bits & _BLOWUP or not np.isfinite(x).all():
            # The dynamics blew up: vertices that fly about are no test of the collision stage.
            blowup_step = n
            break
        a = (x_prev - m_prev[:3, 3]) @ m_prev[:3, :3]
        b = (x - m[:3, 3]) @ m[:3, :3]
        was_out = probe.depth(a) <= THROUGH_DEPTH
        depth = probe.depth(b)
        hit = was_out & (depth > THROUGH_DEPTH)
        if probe.kind != probe._kinds.PLANE:
            s = np.linspace(0.0, 1.0, _PATH_SAMPLES)[:, None, None, None]
            core = -probe.core_distance(a[None] + s * (b - a)[None]).min(axis=0) / probe.core
            hit |= was_out & (core > THROUGH_CORE_FRACTION)
            max_core = max(max_core, float(np.where(was_out, core, 0.0).max()))
        max_depth = max(max_depth, float(np.where(was_out, depth, 0.0).max()))
        events += int(hit.sum())
        through |= hit
        if fault_step is None:
            silent |= hit
        x_prev, m_prev = x, m
    wall = time.perf_counter() - t0
    return {"kind": kind, "substeps": substeps, "dt": dt, "speed": speed, "mode": mode, "steps": steps,
            "step_travel_m": speed * dt, "through_vertices": int(through.sum()),
            "silent_through_vertices": int(silent.sum()), "through_events": events,
            "max_depth_m": max_depth, "max_core_fraction": max_core,
            "fault_bits": int(states[0].fault.numpy()[0]), "fault_step": fault_step, "blowup_step": blowup_step,
            "wall_s": wall}


def tunnelling_thresholds(runs: list[dict]) -> dict:
    """First failing speeds: ``{mode: {kind: {substeps: {"silent", "through", "fault", "blowup"}}}}``, each
    a speed [m/s] or None: ``silent`` = a vertex got through before the solver flagged anything (what a
    scene run writes to its cache without a word), ``through`` = a vertex got through at any step before a
    blow-up (the collision test itself, were the fault bound lifted), ``fault`` = the solver flagged a joint
    turning more than 1 rad in a step (a scene run stops there with a message), ``blowup`` = the joint
    state became non-finite."""
    out = {}
    for mode in [m for m in TUNNEL_MODES if any(r["mode"] == m for r in runs)]:
        table = {}
        for kind in [k for k in TUNNEL_KINDS if any(r["kind"] == k for r in runs)]:
            row = {}
            for n in sorted({r["substeps"] for r in runs if r["kind"] == kind}):
                mine = [r for r in runs if r["kind"] == kind and r["substeps"] == n and r["mode"] == mode]
                first = {}
                for key, failed in (("silent", lambda r: r["silent_through_vertices"] > 0),
                                    ("through", lambda r: r["through_vertices"] > 0),
                                    ("fault", lambda r: r["fault_step"] is not None),
                                    ("blowup", lambda r: r["blowup_step"] is not None)):
                    speeds = [r["speed"] for r in mine if failed(r)]
                    first[key] = min(speeds) if speeds else None
                row[str(n)] = first
            table[kind] = row
        out[mode] = table
    return out


_MODE_TITLES = {"point": "point test (end positions)", "swept_estimate": "swept test, start from velocities",
                "swept": "swept test, start given (state_in)"}


def chart_tunnelling(result: dict, path) -> Path:
    """PNG, one panel per collision test: against the substeps, the first collider speed that lets a vertex
    through before the solver flags anything (filled, what reaches a cache silently) and at any step before
    a blow-up (open, dashed: the collision test alone), one marker per kind (on the top line: none up to
    the top speed), and the first speed at which the solver flags a joint turning more than 1 rad in a
    step (crosses: a scene run stops there with a message)."""
    from hairwarp.benchmarks.report import _pyplot

    plt = _pyplot()
    path = Path(path)
    modes = [m for m in TUNNEL_MODES if m in result["thresholds"]]
    fig, axes = plt.subplots(1, len(modes), figsize=(4.2 * len(modes), 5.2), sharey=True, squeeze=False)
    markers = {"sphere": "o", "capsule": "s", "plane": "^", "mesh": "D"}
    colors = {"sphere": "C0", "capsule": "C1", "plane": "C2", "mesh": "C3"}
    top = max(result["speeds"])
    ceiling = top * 1.5
    subs = sorted(result["substeps"])
    shift = {k: 2.0 ** (0.07 * (i - 1.5)) for i, k in enumerate(TUNNEL_KINDS)}
    h = np.array(subs, dtype=float)
    for ax, mode in zip(axes[0], modes):
        for kind, row in result["thresholds"][mode].items():
            xs = [n * shift[kind] for n in subs]
            ax.plot(xs, [row[str(n)]["silent"] or ceiling for n in subs], marker=markers[kind],
                    color=colors[kind], lw=1.1, ms=6, label=f"{kind}: through before any fault")
            ax.plot(xs, [row[str(n)]["through"] or ceiling for n in subs], marker=markers[kind], mfc="white",
                    color=colors[kind], lw=0.8, ls="--", ms=5, label=f"{kind}: through, fault bound lifted")
            faults = [(x, row[str(n)]["fault"]) for x, n in zip(xs, subs) if row[str(n)]["fault"] is not None]
            if faults:
                ax.scatter(*zip(*faults), marker="x", s=22, color=colors[kind], lw=0.9)
        ax.plot(h, TUNNEL_SIZE * TUNNEL_FPS * h, color="0.5", lw=0.8, ls=":",
                label=f"collider moves its radius ({TUNNEL_SIZE:g} m) per step")
        ax.axhline(ceiling, color="0.75", lw=0.6)
        ax.text(subs[0], ceiling * 1.07, f"none up to {top:g} m/s", fontsize=7, color="0.4")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xticks(subs, [str(n) for n in subs])
        ax.set_ylim(min(result["speeds"]) * 0.7, ceiling * 1.5)
        ax.set_title(_MODE_TITLES[mode], fontsize=9)
        ax.set_xlabel(f"substeps per frame at {TUNNEL_FPS:g} fps")
    axes[0][0].set_ylabel("collider speed [m/s]")
    axes[0][0].scatter([], [], marker="x", color="0.3", label="solver fault: a joint turns > 1 rad in a step")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=4, frameon=False)
    fig.suptitle("Strand-object tunnelling: 0.1 m thick colliders crossing 0.3 m hanging strands", fontsize=10)
    fig.tight_layout(rect=(0.0, 0.13, 1.0, 1.0))
    fig.savefig(path)
    plt.close(fig)
    return path


def bench_tunnelling(quick: bool = False, device=None, out=None, *, kinds=TUNNEL_KINDS, substeps=None,
                     speeds=None, modes=TUNNEL_MODES) -> dict:
    """Map the collider speed at which each collider kind starts to let strand vertices through.

    A field of hanging strands (5 x 5 guides of 0.3 m, 15 segments; 3 x 3 when ``quick``) is crossed at
    mid height along +x by a sphere, a capsule (axis across the motion) and a closed icosphere mesh,
    each 0.1 m thick along the motion, at constant speed; a floor plane rises under it at that speed and
    stops 0.1 m below the roots. After every step each vertex is checked against the collider in float64:
    it went *through* if it was outside before the step and is now deeper than :data:`THROUGH_DEPTH`, or
    its straight path relative to the collider over the step cut deeper than
    :data:`THROUGH_CORE_FRACTION` of the collider's half thickness (it was pushed out on the far side).

    Args:
        quick: 3 x 3 strands, substeps (1, 4, 16), speeds doubling from 0.25 to 64 m/s.
        device: Warp device (default: the default device).
        out: folder for ``tunnelling.json`` and ``tunnelling.png``; nothing written when None.
        kinds, substeps, speeds: subsets of the map.
        modes: the collision tests to compare, from :data:`TUNNEL_MODES`.

    Returns:
        ``{"device", "fps", "size_m", "strands", "segments", "speeds", "substeps", "runs": [...],
        "thresholds": see :func:`tunnelling_thresholds`, "files": [...]}``; each run has
        ``through_vertices`` (distinct vertices that went through before any blow-up),
        ``silent_through_vertices`` (through before the first fault), ``through_events``, ``max_depth_m``,
        ``max_core_fraction``, ``fault_bits``, ``fault_step`` (the first step the solver flagged at 1 rad
        per step, where a scene run would stop, or None),
        ``blowup_step`` (non-finite dynamics; the run stops there) and its ``wall_s``.
    """
    device = wp.get_device(device)
    per_side = 3 if quick else 5
    if substeps is None:
        substeps = (1, 4, 16) if quick else TUNNEL_SUBSTEPS
    if speeds is None:
        speeds = TUNNEL_SPEEDS[::2] if quick else TUNNEL_SPEEDS
    runs = []
    t0 = time.perf_counter()
    for mode in modes:
        for kind in kinds:
            for n in substeps:
                for v in speeds:
                    runs.append(_tunnel_run(kind, int(n), float(v), mode, per_side, device))
    result = {"device": str(device), "fps": TUNNEL_FPS, "size_m": TUNNEL_SIZE, "strands": per_side * per_side,
              "segments": _FIELD_SEGMENTS, "speeds": [float(v) for v in speeds],
              "substeps": [int(n) for n in substeps], "through_depth_m": THROUGH_DEPTH,
              "through_core_fraction": THROUGH_CORE_FRACTION, "runs": runs,
              "thresholds": tunnelling_thresholds(runs), "wall_s": time.perf_counter() - t0, "files": []}
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        chart = chart_tunnelling(result, out / "tunnelling.png")
        result["files"] = [str(out / "tunnelling.json"), str(chart)]
        (out / "tunnelling.json").write_text(json.dumps(result, indent=1))
    return result


# ---------------------------------------------------------------------------------------------
# cost on the Ratboy body


def bench_collision_cost(quick: bool = False, device=None, *, groom_path=None, body_path=None,
                         motion_frames: int | None = None, repeats: int | None = None) -> dict:
    """Cost per step of the collision stage on the Ratboy body next to the dynamics, in one run.

    The ``ratboy_mohawk`` scene with every guide (2,219 x 31 segments; ``quick``: every 5th) runs
    ``motion_frames`` frames into its turn; from that state one step is timed: the whole step as the
    scene's solver runs it (dynamics, then the body collision), the step of a solver without colliders
    (the dynamics), and the projection alone (``ColliderSet.project`` on a copy of the integrated state)
    with the point test, the swept test from velocities, and the swept test given the step's start. The
    rest and perturbed states of :func:`hairwarp.colliders.bench_collision` on the same files come with it.

    Returns:
        ``{"status": "ok", "device", "strands", "segments", "body_triangles", "dt", "in_motion": {"step_s",
        "dynamics_step_s", "project_s": {"point", "swept_estimate", "swept"}, "collision_per_dynamics",
        "vertices_moved"}, "bench_collision": {...}}``, times in seconds (median of ``repeats`` after a
        warm-up), or ``{"status": "skipped", "message"}`` when the assets are missing.
    """
    from hairwarp.colliders import bench_collision
    from hairwarp.runner import Simulation
    from hairwarp.solver import Solver

    groom_path, body_path, skipped = ratboy_assets(groom_path, body_path)
    if skipped:
        return skipped
    device = wp.get_device(device)
    if motion_frames is None:
        motion_frames = 5 if quick else 20
    if repeats is None:
        repeats = 5 if quick else 20
    # The body collision against the dynamics alone: the scene's links and contacts stay off (their cost is the
    # interactions suite's).
    scene = ratboy_mohawk_scene(groom_path, body_path, device, 450 if quick else 0,
                                ["links.enabled=false", "interactions.enabled=false"])
    sim = Simulation(scene, device=device)
    for _ in range(motion_frames):
        sim.advance_frame()
    model, stepper = sim.model, sim.stepper
    dt = stepper.dt
    s_in = model.state()
    s_in.assign(stepper.state)
    s_out = model.state()
    control = stepper.control
    full = sim.solver
    # on the simulation's threads: timed in turn with its step, a pool of its own would find the other's threads
    # still spinning after their last launch
    dynamics = Solver(model, scene.sim.integrator, max_rotation_per_step=float(scene.sim.max_rotation_per_step),
                      executor=full.executor)
    dynamics.set_dt(dt)
    full.set_dt(dt)
    integrated = model.state()
    dynamics.step(s_in, integrated, control, dt)
    work = model.state()
    cs = sim.collider_set

    def project(swept, start):
        def call():
            cs.swept = swept
            work.assign(integrated)
            cs.project(model, work, control, full.dt, start)
        return call

    times = interleaved_medians({
        "step": lambda: full.step(s_in, s_out, control, dt),
        "dynamics": lambda: dynamics.step(s_in, s_out, control, dt),
        "copy": lambda: work.assign(integrated),
        "point": project(False, None),
        "swept_estimate": project(True, None),
        "swept": project(True, s_in),
    }, device, repeats)
    cs.swept = True
    step_s, dyn_s = times["step"], times["dynamics"]
    projection = {k: max(times[k] - times["copy"], 0.0) for k in ("point", "swept_estimate", "swept")}
    moved = int(np.count_nonzero(np.any(work.vertex_positions.numpy() != integrated.vertex_positions.numpy(),
                                        axis=1)))
    rest = bench_collision(device, quick=quick, segments=31, groom_path=groom_path, body_path=body_path,
                           strands=model.strand_count)
    return {"status": "ok", "device": str(device), "strands": model.strand_count, "segments": model.seg_per_strand,
            "body_triangles": rest["body_triangles"], "dt": dt, "time_in_motion_s": motion_frames * sim.frame_dt,
            "in_motion": {"step_s": step_s, "dynamics_step_s": dyn_s, "project_s": projection,
                          "collision_per_dynamics": {k: v / dyn_s for k, v in projection.items()},
                          "vertices_moved": moved},
            "bench_collision": rest}


# ---------------------------------------------------------------------------------------------
# jitter of resting tips


def bench_resting_jitter(quick: bool = False, device=None, *, scene=None, window_s: float = 1.0,
                         overrides=()) -> dict:
    """Jitter of strand tips resting on the body colliders over the last ``window_s`` of a scene.

    Runs ``scene`` (default ``scenes/long_hair_shoulders.toml``, whose head is still for its last 1.7 s)
    and records every tip after every step of the window. A tip *rests* if it stays within the contact
    layer + 1 mm of a collider other than the head for the whole window. Figures over the resting tips
    (and over all tips): RMS and largest tip speed from step-to-step displacements, the RMS and largest
    high-pass displacement ``x_n - (x_{n-1} + x_{n+1}) / 2`` (step-scale zigzag), and the median and
    largest peak-to-peak of a tip's distance to the body.

    Args:
        quick: the window only (the run itself is the scene's).
        device: Warp device.
        scene: a :class:`hairwarp.Scene` or a path; the shipped shoulder scene when None.
        window_s: the measured window at the end of the run [s].
        overrides: ``section.key=value`` overrides of the scene.

    Returns:
        ``{"scene", "strands", "dt", "window_s", "resting_tips", "resting": {...}, "all": {...},
        "fault_bits", "wall_s"}``; speeds in m/s, displacements in m.
    """
    from hairwarp.runner import Simulation
    from hairwarp.scene import Scene

    if scene is None:
        scene = Path(Scene.default_path()).parent / "long_hair_shoulders.toml"
    if not isinstance(scene, Scene):
        scene = Scene.load(scene, list(overrides))
    elif overrides:
        scene = scene.with_overrides(list(overrides))
    t0 = time.perf_counter()
    sim = Simulation(scene, device=device)
    model, stepper, cs = sim.model, sim.stepper, sim.collider_set
    G, S = model.strand_count, model.seg_per_strand
    total = int(scene.sim.frames) * stepper.substeps
    window = min(int(round(window_s / stepper.dt)), total - 2)
    tips = []
    for n in range(total):
        sim._before_step(stepper.time + stepper.dt, stepper.control)
        stepper.step()
        if n >= total - window - 1:
            tips.append(stepper.state.vertex_positions.numpy().reshape(G, S + 1, 3)[:, S].astype(float))
    tips = np.asarray(tips)
    body = [i for i, c in enumerate(cs.colliders) if c.name != "head"]
    dist = cs.signed_distance(tips.reshape(-1, 3), sim.head_matrix(stepper.time))[0].reshape(len(tips), G, -1)
    dist = dist[:, :, body].min(axis=2)
    layer = max(cs.colliders[i].thickness for i in body)
    resting = (dist < layer + 1.0e-3).all(axis=0)
    speed = np.linalg.norm(np.diff(tips, axis=0), axis=-1) / stepper.dt
    high = np.linalg.norm(tips[1:-1] - 0.5 * (tips[:-2] + tips[2:]), axis=-1)
    ptp = np.ptp(dist, axis=0)

    def figures(sel):
        if not sel.any():
            return None
        return {"rms_speed": float(np.sqrt((speed[:, sel] ** 2).mean())), "max_speed": float(speed[:, sel].max()),
                "rms_highpass": float(np.sqrt((high[:, sel] ** 2).mean())), "max_highpass": float(high[:, sel].max()),
                "median_ptp_distance": float(np.median(ptp[sel])), "max_ptp_distance": float(ptp[sel].max())}

    return {"scene": scene.name, "strands": G, "dt": stepper.dt, "window_s": window * stepper.dt,
            "resting_tips": int(resting.sum()), "resting": figures(resting), "all": figures(np.ones(G, dtype=bool)),
            "fault_bits": int(stepper.state.fault.numpy()[0]), "wall_s": time.perf_counter() - t0}


# ---------------------------------------------------------------------------------------------
# suite


def suite_collision(config, out, log=lambda message: None) -> dict:
    """The ``collision`` suite of ``hairwarp bench``: tunnelling map (JSON + chart in ``out``), cost on
    the Ratboy body, resting jitter. ``config``: a :class:`hairwarp.benchmarks.common.BenchConfig`."""
    quick, device = bool(config.quick), config.device
    log("collision: resting jitter on the shoulders")
    jitter = bench_resting_jitter(quick=quick, device=device)
    log("collision: cost on the Ratboy body")
    cost = bench_collision_cost(quick=quick, device=device)
    log("collision: tunnelling map")
    tunnel = bench_tunnelling(quick=quick, device=device, out=out)
    tunnel_summary = {k: v for k, v in tunnel.items() if k != "runs"}
    return {"jitter": jitter, "cost": cost, "tunnelling": tunnel_summary}
