"""Suite ``dynamics``: segment-steps per second of the strand step against the peers, in the same run."""

from __future__ import annotations

import math
import statistics

import warp as wp

from hairwarp.benchmarks.common import BENCH_DT, GATE, run_child
from hairwarp.benchmarks.ours import aba_only_ms, canonical_model, profile_step, time_solver
from hairwarp.executor import default_threads

# Acceptance goals: (peer, segments the goal applies to or None for all, least ratio hairwarp / peer).
GOALS = (
    ("pinocchio", None, 2.0),
    ("pinocchio_parallel", 20, 2.0),
    ("mujoco_euler", 20, 5.0),
    ("mujoco_rollout_euler_threads", 20, 5.0),
    ("mujoco_euler", 50, 15.0),
    ("newton_featherstone_tile", 20, 30.0),
    ("newton_vbd", 20, 30.0),
)

PEER_LABELS = {
    "pinocchio": "Pinocchio ABA + semi-implicit Euler (Python loop)",
    "pinocchio_aba_floor": "Pinocchio bare pin.aba per call (C++ floor, no integration)",
    "mujoco_euler": "MuJoCo mj_step Euler (Python loop over N MjData)",
    "mujoco_euler_c_only": "MuJoCo mj_step Euler, C only (nstep=250 on one MjData)",
    "mujoco_rollout_euler_t0": "MuJoCo rollout Euler, 1 thread",
    "pinocchio_parallel": "Pinocchio abaInParallel on every core (ModelPool) + batched Euler in numpy",
    "mujoco_rollout_euler_threads": "MuJoCo rollout Euler on every core (nthread = cores)",
    "newton_featherstone_tile": "Newton SolverFeatherstone, use_tile_gemm=True",
    "newton_vbd": "Newton SolverVBD rods, 10 iterations",
}


def goal_for(peer: str, segments: int) -> float | None:
    for name, seg, goal in GOALS:
        if name == peer and (seg is None or seg == segments):
            return goal
    return None


def cuda_device(requested: str | None):
    """The CUDA device to add a column for, or None with the reason."""
    if not requested or not str(requested).startswith("cuda"):
        return None, "not requested (run with --device cuda)"
    if not wp.is_cuda_available():
        return None, "no CUDA device on this machine (Warp found no CUDA driver)"
    return wp.get_device(requested), None


def measure_ours(G: int, S: int, device, cfg, integrators, model=None) -> dict:
    """Launch and graph timings of each integrator; ``best`` is the faster of the two."""
    model = model or canonical_model(G, S, device)
    out = {}
    for integrator in integrators:
        row = {}
        for graph in (False, True):
            try:
                row["graph" if graph else "launch"] = time_solver(
                    model, integrator, BENCH_DT, graph=graph, steps=cfg.block_steps, blocks=cfg.blocks,
                    warmup=cfg.warmup, budget_s=cfg.ours_budget_s, graph_block=cfg.graph_block)
            except Exception as exc:  # noqa: BLE001 - report a failing mode, keep the other
                row["graph" if graph else "launch"] = {"status": "error", "message": f"{type(exc).__name__}: {exc}"}
        ok = {k: v for k, v in row.items() if v.get("status") == "ok"}
        best = max(ok, key=lambda k: ok[k]["seg_steps_per_s"]) if ok else None
        row["best_mode"] = best
        row["seg_steps_per_s"] = ok[best]["seg_steps_per_s"] if best else None
        row["step_ms"] = ok[best]["step_ms"] if best else None
        out[integrator] = row
    return out


def peer_rows(G: int, S: int, cfg, log, ours) -> tuple[dict, dict]:
    """Each peer in a child process, which also times hairwarp (its faster mode) just before and just
    after the peer's timed blocks: the load of a shared machine drifts, and the geometric mean of those
    two timings (``bracket``) is hairwarp's figure for that peer's ratio.

    Returns the peers' results and, per integrator, every hairwarp figure at this size (the first
    measurement, then the brackets) with the bracket of each peer.
    """
    rows = {}
    modes = {i: r["best_mode"] for i, r in ours.items() if r.get("best_mode")}
    samples = {i: [ours[i]["seg_steps_per_s"]] for i in modes}
    brackets = {i: {} for i in modes}
    for peer in cfg.dyn_peers:
        log(f"  peer {peer} at {G} x {S} ...")
        req = {"kind": "throughput", "peer": peer, "G": G, "S": S, "dt": BENCH_DT, "steps": cfg.block_steps,
               "blocks": cfg.blocks, "warmup": cfg.warmup, "budget_s": cfg.peer_budget_s,
               "bracket": {"modes": modes, "steps": cfg.block_steps, "blocks": cfg.blocks, "warmup": cfg.warmup,
                           "budget_s": cfg.ours_budget_s / 2, "graph_block": cfg.graph_block}}
        gate = GATE.wait()
        res = run_child(req, cfg.peer_timeout_s)
        res["gate"] = gate
        rows[peer] = res
        b = res.get("hairwarp_bracket", {})
        if "before" in b and "after" in b:
            for i in modes:
                samples[i] += [b["before"][i], b["after"][i]]
                brackets[i][peer] = math.sqrt(b["before"][i] * b["after"][i])
        if res.get("status") == "ok":
            log(f"    {res['step_ms']:.3g} ms/step, {res['seg_steps_per_s']:.3g} seg-steps/s")
        else:
            log(f"    {res.get('status')}: {res.get('message', '')[:200]}")
    # the C floors reported by two of them, as peers of their own, bracketed as their parent
    pin = rows.get("pinocchio", {})
    if pin.get("status") == "ok":
        rows["pinocchio_aba_floor"] = {"status": "ok", "derived_from": "pinocchio",
                                       "seg_steps_per_s": pin["extra"]["aba_only_seg_steps_per_s"],
                                       "us_per_call": pin["extra"]["aba_us_per_call"]}
    mj = rows.get("mujoco_euler", {})
    if mj.get("status") == "ok":
        rows["mujoco_euler_c_only"] = {"status": "ok", "derived_from": "mujoco_euler",
                                       "seg_steps_per_s": mj["extra"]["C_only_seg_steps_per_s"],
                                       "us_per_strand_step": mj["extra"]["mj_step_us_per_strand_C_only"]}
    for b in brackets.values():
        for derived, parent in (("pinocchio_aba_floor", "pinocchio"), ("mujoco_euler_c_only", "mujoco_euler")):
            if parent in b:
                b[derived] = b[parent]
    summary = {i: {"samples": v, "median": statistics.median(v), "min": min(v), "max": max(v),
                   "bracket": brackets[i]} for i, v in samples.items()}
    return rows, summary


def ratios(G: int, S: int, ours: dict, peers: dict) -> list[dict]:
    """hairwarp / peer in seg-steps per second; hairwarp's figure is the bracket around that peer."""
    rows = []
    for integrator, mine in ours.items():
        for peer, res in peers.items():
            goal = goal_for(peer, S)
            row = {"G": G, "S": S, "integrator": integrator, "peer": peer, "goal": goal,
                   "ours_seg_steps_per_s": mine["bracket"].get(peer, mine["median"]),
                   "peer_seg_steps_per_s": res.get("seg_steps_per_s") if res.get("status") == "ok" else None,
                   "peer_status": res.get("status")}
            if row["ours_seg_steps_per_s"] and row["peer_seg_steps_per_s"]:
                row["ratio"] = row["ours_seg_steps_per_s"] / row["peer_seg_steps_per_s"]
                row["meets"] = None if goal is None else bool(row["ratio"] >= goal)
            else:
                row["ratio"] = None
                row["meets"] = None if goal is None else False
            rows.append(row)
    return rows


def overhead(cfg) -> dict:
    """Per-step cost of one strand with launches and with a graph: the launch overhead of a step."""
    model = canonical_model(1, 20, "cpu")
    out = {}
    for integrator in cfg.dyn_integrators:
        row = {}
        for graph in (False, True):
            r = time_solver(model, integrator, BENCH_DT, graph=graph, steps=200, blocks=3, warmup=3,
                            budget_s=cfg.ours_budget_s, graph_block=cfg.graph_block)
            row["graph_us" if graph else "launch_us"] = r["step_s_min"] * 1e6
        row["overhead_us"] = row["launch_us"] - row["graph_us"]
        out[integrator] = row
    return out


def suite_dynamics(cfg, log=lambda msg: None) -> dict:
    cuda, cuda_reason = cuda_device(cfg.device)
    configs = []
    for G, S in cfg.dyn_configs:
        log(f"dynamics {G} x {S}: hairwarp on cpu ...")
        model = canonical_model(G, S, "cpu")
        ours = measure_ours(G, S, "cpu", cfg, cfg.dyn_integrators, model)
        for integrator, row in ours.items():
            launch, graph = row.get("launch", {}), row.get("graph", {})
            log(f"  {integrator}: launch {launch.get('step_ms', float('nan')):.3g} ms, "
                f"graph {graph.get('step_ms', float('nan')):.3g} ms/step -> {row['seg_steps_per_s']:.3g} seg-steps/s")
        entry = {"G": G, "S": S, "dt": BENCH_DT, "hairwarp": {"cpu": ours}}
        if cuda is not None:
            log(f"dynamics {G} x {S}: hairwarp on {cuda} ...")
            entry["hairwarp"][str(cuda)] = measure_ours(G, S, cuda, cfg, cfg.dyn_integrators)
        entry["peers"], entry["hairwarp_over_run"] = peer_rows(G, S, cfg, log, ours)
        entry["ratios"] = ratios(G, S, entry["hairwarp_over_run"], entry["peers"])
        configs.append(entry)
    log("dynamics: profile of one step ...")
    profiles = []
    for G, S in cfg.dyn_configs:
        model = canonical_model(G, S, "cpu")
        for integrator in cfg.dyn_integrators:
            p = profile_step(model, integrator, BENCH_DT, steps=10 if cfg.quick else 30)
            p["aba_only_ms"] = aba_only_ms(model, integrator, steps=10 if cfg.quick else 30)
            profiles.append({"G": G, "S": S, "integrator": integrator, **p})
    return {
        "scene": {"length_m": 0.3, "radius_m": 2e-3, "density": 1300.0, "tilt_deg": 80.0, "root_spacing_m": 0.01,
                  "root_z_m": 1.0, "joint_damping_Nms_per_rad": 1e-10, "dt": BENCH_DT, "gravity": -9.81},
        "goals": [{"peer": p, "segments": s, "goal": g} for p, s, g in GOALS],
        "peer_labels": PEER_LABELS,
        "hairwarp_threads": default_threads(),
        "configs": configs,
        "profile": profiles,
        "overhead_1x20": overhead(cfg),
        "cuda": {"device": str(cuda) if cuda is not None else None, "reason": cuda_reason},
    }
