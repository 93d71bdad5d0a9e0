"""Suite ``scaling``: cost of the dynamics step over a grid of strand and segment counts, fitted
exponents, and the other stages through the hooks their modules expose."""

from __future__ import annotations

import importlib
import inspect
import time
from pathlib import Path

import numpy as np

from hairwarp.benchmarks.common import BENCH_DT, fit_exponent
from hairwarp.benchmarks.dynamics import cuda_device
from hairwarp.benchmarks.ours import canonical_model, time_solver

INTEGRATOR = "implicit_joints"

# Other stages: (stage, module, function, always quick). A module exposes ``bench_<stage>(quick=...,
# device=...)`` returning a JSON-able dict; it is called when importable, else the stage is reported "not
# available". The whole-scene ones run at their quick sizes even in a full run, to keep it under 15 minutes.
STAGE_HOOKS = (
    ("dense interpolation + Hermite", "hairwarp.dense", "bench_dense", False),
    ("static links + hair-hair contacts (Ratboy mohawk)", "hairwarp.benchmarks.interactions", "bench_interactions",
     True),
    ("body collision (projection)", "hairwarp.colliders", "bench_collision", False),
    ("body collision in motion (Ratboy)", "hairwarp.benchmarks.collision", "bench_collision_cost", True),
    ("USD write", "hairwarp.benchmarks.dense", "bench_usd_write", False),
)


def grid_point(G: int, S: int, device, cfg) -> dict:
    model = canonical_model(G, S, device)
    rows = {}
    for graph in (False, True):
        # many short blocks: the fastest is the one other programs disturbed least
        rows["graph" if graph else "launch"] = time_solver(
            model, INTEGRATOR, BENCH_DT, graph=graph, steps=max(1, cfg.block_steps // 2), blocks=cfg.scale_blocks,
            warmup=cfg.warmup, budget_s=cfg.scale_budget_s, graph_block=cfg.graph_block)
    best = min(("launch", "graph"), key=lambda k: rows[k]["step_s"])
    return {"G": G, "S": S, "step_s": rows[best]["step_s"], "mode": best,
            "step_s_min": min(rows[k]["step_s_min"] for k in rows),
            "launch_step_s": rows["launch"]["step_s"], "graph_step_s": rows["graph"]["step_s"],
            "seg_steps_per_s": G * S / rows[best]["step_s"], "under_load": rows[best]["gate"]["under_load"]}


def exponents(points: list[dict], key: str = "step_s") -> dict:
    """Exponent of cost vs G at each S and vs S at each G (least squares in log-log)."""
    Gs = sorted({p["G"] for p in points})
    Ss = sorted({p["S"] for p in points})
    vs_g = {S: fit_exponent([p["G"] for p in points if p["S"] == S], [p[key] for p in points if p["S"] == S])
            for S in Ss}
    vs_s = {G: fit_exponent([p["S"] for p in points if p["G"] == G], [p[key] for p in points if p["G"] == G])
            for G in Gs}
    big = [p for p in points if p["G"] >= max(Gs) / 4]
    return {"vs_strands": {str(k): v for k, v in vs_g.items()}, "vs_segments": {str(k): v for k, v in vs_s.items()},
            "vs_strands_largest_S": vs_g[Ss[-1]], "vs_segments_largest_G": vs_s[Gs[-1]],
            "vs_segments_large_G": fit_exponent([p["S"] for p in big], [p[key] for p in big])}


def call_hook(module: str, function: str, cfg, device, always_quick: bool = False) -> dict:
    try:
        fn = getattr(importlib.import_module(module), function)
    except (ImportError, AttributeError):
        return {"status": "not available", "message": f"{module}.{function} does not exist yet"}
    kwargs = {"device": device}
    params = inspect.signature(fn).parameters
    if "counts" in params:
        kwargs["counts"] = cfg.dense_counts
    if "quick" in params:
        kwargs["quick"] = cfg.quick or always_quick
    t0 = time.perf_counter()
    try:
        out = fn(**kwargs)
    except Exception as exc:  # noqa: BLE001 - another stage's failure is reported, not fatal
        return {"status": "error", "message": f"{type(exc).__name__}: {exc}"[:400]}
    return {"status": "ok", "quick": kwargs.get("quick", False), "result": out, "wall_s": time.perf_counter() - t0}


def _array_bytes(obj, seen: set) -> int:
    """Bytes of the Warp arrays an object (or a Warp struct) holds, each array counted once."""
    import warp as wp

    total = 0
    values = obj.__dict__.values() if hasattr(obj, "__dict__") else []
    for v in values:
        if isinstance(v, wp.array):
            if id(v) not in seen:
                seen.add(id(v))
                total += int(v.capacity)
        elif hasattr(v, "_cls") or type(v).__name__.startswith(("StrandChains", "SegmentLoads", "AbaScratch")):
            total += _array_bytes(v, seen)
    return total


def working_set(G: int, S: int) -> dict:
    """What one step of the scaling test touches: the model's, the solver's and two states' arrays [bytes], per
    segment and in all, and the machine's last-level cache as the kernel reports it (None where unknown)."""
    from hairwarp.benchmarks.ours import canonical_model
    from hairwarp.solver import Solver

    model = canonical_model(G, S, "cpu")
    solver = Solver(model, INTEGRATOR)
    seen: set = set()
    total = sum(_array_bytes(o, seen) for o in (model, solver, model.state(), model.state(), model.control()))
    l3 = None
    try:
        size = Path("/sys/devices/system/cpu/cpu0/cache/index3/size").read_text().strip()
        l3 = int(size.rstrip("KMG")) * {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}[size[-1]]
    except (OSError, ValueError, KeyError, IndexError):
        pass
    return {"G": G, "S": S, "bytes": total, "bytes_per_segment": total / (G * S), "l3_bytes": l3}


def suite_scaling(cfg, log=lambda msg: None) -> dict:
    devices = ["cpu"]
    cuda, cuda_reason = cuda_device(cfg.device)
    if cuda is not None:
        devices.append(str(cuda))
    per_device = {}
    for device in devices:
        best: dict = {}
        grid = [(G, S) for S in cfg.scale_segments for G in cfg.scale_strands]
        for n_pass in range(cfg.scale_passes):
            # a different order each pass, so a stretch of load from other programs hits other points
            order = grid if n_pass % 2 == 0 else grid[::-1]
            for G, S in order:
                p = grid_point(G, S, device, cfg)
                p["pass"] = n_pass + 1
                if (G, S) not in best or p["step_s_min"] < best[(G, S)]["step_s_min"]:
                    best[(G, S)] = p
                log(f"scaling {device} pass {n_pass + 1} {G} x {S}: {p['step_s_min'] * 1e3:.3g} ms/step "
                    f"(fastest block, {p['mode']})")
        points = [best[key] for key in grid]
        per_device[device] = {"points": points, "exponents": exponents(points, "step_s_min"),
                              "exponents_median": exponents(points, "step_s"),
                              "exponents_launch": exponents(points, "launch_step_s")}
    cpu = per_device["cpu"]["exponents"]
    worst = max(v for v in [*cpu["vs_strands"].values(), *cpu["vs_segments"].values()] if v is not None)
    stages = []
    for stage, module, function, always_quick in STAGE_HOOKS:
        if cfg.stages is not None and stage not in cfg.stages:
            continue
        log(f"scaling: stage {stage} ...")
        r = call_hook(module, function, cfg, "cpu", always_quick)
        stages.append({"stage": stage, "hook": f"{module}.{function}", **r})
        log(f"  {r['status']}")
    return {"integrator": INTEGRATOR, "dt": BENCH_DT, "devices": per_device, "max_exponent": worst,
            "exponent_goal": 1.1, "meets": bool(worst <= 1.1),
            "largest": {"G": max(cfg.scale_strands), "S": max(cfg.scale_segments)},
            "working_set": working_set(max(cfg.scale_strands), max(cfg.scale_segments)),
            "stages": stages, "cuda": {"device": str(cuda) if cuda is not None else None, "reason": cuda_reason},
            "note": "cost = seconds per step, the faster of plain launches and a captured graph; exponents are "
                    "fitted to the fastest timed block of each point (other programs only ever slow a block "
                    "down), and to the median block as well; "
                    f"{np.prod([len(cfg.scale_strands), len(cfg.scale_segments)])} grid points, each timed in "
                    f"{cfg.scale_passes} passes over the grid of {cfg.scale_blocks} short blocks each (the pass "
                    "with the fastest block is kept)"}
