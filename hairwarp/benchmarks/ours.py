"""Driving hairwarp's own solver in the benchmarks: models of the benchmark scenes, stepping with or
without a captured graph, the timing of a step and a per-kernel profile."""

from __future__ import annotations

import math
import time

import numpy as np
import warp as wp

from hairwarp.benchmarks.common import (
    BENCH_DT,
    DENSITY,
    GATE,
    JOINT_DAMPING,
    RADIUS,
    STRAND_LENGTH,
    canonical_vertices,
    straight_strands,
    tilt_direction,
    time_blocks,
)
from hairwarp.model import Model, StrandParams
from hairwarp.solver import Solver


def canonical_model(strands: int, segments: int, device) -> Model:
    """The canonical scene: no joint springs, joint damping 1e-10 N m s/rad (the rod damping times L)."""
    params = StrandParams(density=DENSITY, radius=RADIUS, bend_stiffness=0.0, twist_stiffness=0.0,
                          damping=JOINT_DAMPING * STRAND_LENGTH / segments)
    return Model.build(canonical_vertices(strands, segments), params, segments=segments, device=device)


def reference_model(device, strands: int = 1, segments: int = 20) -> Model:
    """The peers' accuracy strand (copied ``strands`` times): root at the origin, 80 degrees, no damping."""
    params = StrandParams(density=DENSITY, radius=RADIUS, bend_stiffness=0.0, twist_stiffness=0.0, damping=0.0)
    roots = np.zeros((strands, 3))
    roots[:, 1] = 0.01 * np.arange(strands)
    return Model.build(straight_strands(roots, segments, tilt_direction()), params, segments=segments, device=device)


def supports_capture(device) -> bool:
    """Warp captures graphs on CUDA, and on the CPU since 1.10 (``wp.capture_launch`` replays it)."""
    return hasattr(wp, "ScopedCapture") and hasattr(wp, "capture_launch")


class StepRunner:
    """Advances two swapping states by chunks of ``chunk`` steps, replaying captured graphs when asked.

    With an odd chunk the states swap parity each chunk, so two graphs are captured (one starting
    from each state). ``current`` is the state holding the latest step.
    """

    def __init__(self, model: Model, solver: Solver, dt: float, chunk: int = 1, *, graph: bool = True,
                 states=None, control=None):
        self.model, self.solver, self.dt, self.chunk = model, solver, float(dt), max(1, int(chunk))
        self.states = list(states) if states is not None else [model.state(), model.state()]
        self.control = control if control is not None else model.control()
        self.parity = 0
        self.steps = 0
        solver.set_dt(self.dt)
        self.graphs = None
        if graph and supports_capture(model.device):
            self.graphs = [self._capture(0)]
            if self.chunk % 2:
                self.graphs.append(self._capture(1))

    def _capture(self, start: int):
        with wp.ScopedCapture(device=self.model.device) as capture:
            self._plain(start)
        return capture.graph

    def _plain(self, start: int):
        a, b = self.states[start], self.states[1 - start]
        for _ in range(self.chunk):
            self.solver.step(a, b, self.control, self.dt)
            a, b = b, a

    def advance(self, chunks: int = 1):
        for _ in range(chunks):
            if self.graphs is not None:
                wp.capture_launch(self.graphs[self.parity if len(self.graphs) > 1 else 0])
            else:
                self._plain(self.parity)
            if self.chunk % 2:
                self.parity ^= 1
            self.steps += self.chunk

    @property
    def current(self):
        return self.states[self.parity]


def time_solver(model: Model, integrator: str, dt: float, *, graph: bool, steps: int, blocks: int, warmup: int,
                budget_s: float, graph_block: int = 10) -> dict:
    """Time one step of ``integrator`` on ``model`` (the peers' protocol), plain launches or a graph.

    A graph holds ``graph_block`` steps; its time per step is the replay time divided by that.
    """
    solver = Solver(model, integrator)
    device = model.device
    runner = StepRunner(model, solver, dt, graph_block if graph else 1, graph=graph)
    if graph and runner.graphs is None:
        return {"status": "unsupported", "message": "this Warp cannot capture graphs on this device"}

    def sync():
        wp.synchronize_device(device)

    per = runner.chunk
    gate = GATE.wait()
    res = time_blocks(runner.advance, sync, steps=max(1, steps // per), blocks=blocks, warmup=warmup,
                      budget_s=budget_s)
    res["gate"] = gate
    for key in ("step_s", "step_s_min", "first_step_s"):
        res[key] = res[key] / per
    res["timed_steps"] *= per
    res["block_steps"] *= per
    x = runner.current.vertex_positions.numpy()
    res["finite"] = bool(np.isfinite(x).all())
    res["status"] = "ok"
    res["mode"] = "graph" if graph else "launch"
    G, S = model.strand_count, model.seg_per_strand
    res["step_ms"] = res["step_s"] * 1e3
    res["seg_steps_per_s"] = G * S / res["step_s"]
    return res


def profile_step(model: Model, integrator: str, dt: float, steps: int = 20, repeats: int = 3) -> dict:
    """Wall time of each Warp call in a plain step (CPU launches are synchronous, so the time around a
    launch is its argument packing plus its kernel); ms per step by call, launches per step. The ``steps`` are timed
    ``repeats`` times and the fastest round is kept, its calls with it: a round in which the machine took the core
    away (another program, the test suite's other worker) read the step 30 times as long as its calls on the tiny
    model of the tests (0.44 ms against 0.014).

    On one thread, where every launch runs when it is made (with more, the executor holds a chain of launches and
    runs them at its end), timed where a launch is made: :meth:`hairwarp.executor.Executor.launch`, through which
    every CPU launch of the step passes (it replays its prepared launches without ``wp.launch``), ``wp.launch`` for
    the few made directly, and ``wp.copy``; a call made within another timed one (the executor's ``wp.launch`` on a
    GPU) counts once."""
    from hairwarp.executor import Executor

    solver = Solver(model, integrator, threads=1)
    states = [model.state(), model.state()]
    control = model.control()
    for _ in range(3):
        solver.step(states[0], states[1], control, dt)
        states.reverse()
    wp.synchronize_device(model.device)
    GATE.wait()
    acc: dict[str, list] = {}
    depth = [0]
    originals = [(wp, "launch", wp.launch), (wp, "copy", wp.copy), (Executor, "launch", Executor.launch)]

    def wrap(owner, name, orig):
        def timed(*args, **kwargs):
            if depth[0]:
                return orig(*args, **kwargs)
            depth[0] += 1
            t0 = time.perf_counter()
            try:
                out = orig(*args, **kwargs)
                wp.synchronize_device(model.device)
            finally:
                depth[0] -= 1
            kernel = args[1] if owner is Executor else args[0]
            key = getattr(kernel, "key", None) if name == "launch" else "wp.copy"
            rec = acc.setdefault(key or name, [0.0, 0])
            rec[0] += time.perf_counter() - t0
            rec[1] += 1
            return out
        return timed

    wall, kept = math.inf, {}
    try:
        for owner, name, orig in originals:
            setattr(owner, name, wrap(owner, name, orig))
        for _ in range(max(1, repeats)):
            acc.clear()
            t0 = time.perf_counter()
            for _ in range(steps):
                solver.step(states[0], states[1], control, dt)
                states.reverse()
            wp.synchronize_device(model.device)
            round_wall = (time.perf_counter() - t0) / steps
            if round_wall < wall:
                wall, kept = round_wall, {k: list(v) for k, v in acc.items()}
    finally:
        for owner, name, orig in originals:
            setattr(owner, name, orig)
    acc = kept
    calls = {k: {"ms_per_step": v[0] / steps * 1e3, "calls_per_step": v[1] / steps}
             for k, v in sorted(acc.items(), key=lambda kv: -kv[1][0])}
    return {"wall_ms_per_step": wall * 1e3, "calls": calls,
            "calls_per_step": sum(v[1] for v in acc.values()) / steps}


def aba_only_ms(model: Model, integrator: str, steps: int = 20) -> float:
    """Milliseconds of one ``aba_accelerations`` launch (the three ABA passes, no integration or
    kinematics) on ``model``'s initial state, median of ``steps`` launches, on one thread (as :func:`profile_step`)."""
    solver = Solver(model, integrator, threads=1)
    state, control = model.state(), model.control()
    implicit = integrator == "implicit_joints"
    GATE.wait()
    times = []
    for _ in range(steps + 2):
        t0 = time.perf_counter()
        solver.joint_accelerations(state, control, dt=BENCH_DT, implicit=implicit)
        wp.synchronize_device(model.device)
        times.append(time.perf_counter() - t0)
    return float(np.median(times[2:]) * 1e3)
