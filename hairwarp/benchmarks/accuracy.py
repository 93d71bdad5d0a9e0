"""Suite ``accuracy``: tip error of the reference strand against CPU cost, for each integrator and the
peers, and the error of a stiff strand's static shape against the continuum as the segment count grows."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import warp as wp

from hairwarp.benchmarks.common import DENSITY, GATE, GRAVITY, RADIUS, STRAND_LENGTH, run_child, time_blocks
from hairwarp.benchmarks.ours import StepRunner, reference_model
from hairwarp.model import Model, StrandParams
from hairwarp.solver import Solver

SAMPLE = 1.0e-3  # tip sample period [s]; every dt tested divides it


def reference_tips(cfg, out: Path, log) -> dict:
    """The converged reference (MuJoCo RK4, tip every 1 ms), from the cache in ``out`` when it matches."""
    path = Path(out) / f"accuracy_reference_S20_dt{cfg.acc_ref_dt:g}_T{cfg.acc_duration:g}.npz"
    if path.is_file():
        data = np.load(path)
        if float(data["dt"]) == cfg.acc_ref_dt and float(data["duration"]) == cfg.acc_duration:
            return {"tip": data["tip"], "source": str(data["source"]), "dt": cfg.acc_ref_dt, "cached": path.name}
    log(f"accuracy: reference (RK4 at dt = {cfg.acc_ref_dt:g} over {cfg.acc_duration:g} s) ...")
    res = run_child({"kind": "reference", "dt": cfg.acc_ref_dt, "duration": cfg.acc_duration, "S": 20},
                    max(cfg.peer_timeout_s, 600.0))
    if res.get("status") != "ok":
        return {"tip": None, "source": None, "status": res.get("status"), "message": res.get("message")}
    tip = np.asarray(res["tip"], float)
    np.savez(path, tip=tip, dt=cfg.acc_ref_dt, duration=cfg.acc_duration, source=res["source"])
    return {"tip": tip, "source": res["source"], "dt": cfg.acc_ref_dt, "cached": None, "wall_s": res.get("wall_s")}


def tip_errors(tips, ref) -> dict:
    """RMS over [0, 0.5 s], max over [0, 0.5 s] and [0, 1 s] of the tip distance [m]; inf once non-finite."""
    tips = np.asarray(tips, float)
    n = min(len(tips), len(ref))
    err = np.linalg.norm(tips[:n] - ref[:n], axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    half = int(round(0.5 / SAMPLE)) + 1
    out = {"rms_0.5": float(np.sqrt(np.mean(err[:half] ** 2))), "max_0.5": float(err[:half].max())}
    if n >= int(round(1.0 / SAMPLE)) + 1:
        out["max_1"] = float(err[: int(round(1.0 / SAMPLE)) + 1].max())
    out["finite"] = bool(np.isfinite(err).all())
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in out.items()}


def our_tips(integrator: str, dt: float, duration: float, device) -> np.ndarray:
    """Tip of the reference strand every 1 ms (graph replays of 1 ms of steps)."""
    model = reference_model(device)
    per = int(round(SAMPLE / dt))
    runner = StepRunner(model, Solver(model, integrator), dt, per, graph=True)
    S = model.seg_per_strand
    tips = [runner.current.vertex_positions.numpy()[S].astype(float)]
    for _ in range(int(round(duration / SAMPLE))):
        runner.advance(1)
        tips.append(runner.current.vertex_positions.numpy()[S].astype(float))
    return np.array(tips)


def our_cost(integrator: str, strands: int, device, cfg) -> dict:
    """CPU seconds per strand-step: the faster of launches and a graph on a batch of copies of the strand."""
    model = reference_model(device, strands=strands)
    best = {}
    for graph in (False, True):
        solver = Solver(model, integrator)
        runner = StepRunner(model, solver, 1e-3, cfg.graph_block if graph else 1, graph=graph)
        GATE.wait()
        r = time_blocks(runner.advance, lambda: wp.synchronize_device(model.device),
                        steps=max(1, 100 // runner.chunk), blocks=3, warmup=2, budget_s=cfg.ours_budget_s)
        best["graph" if graph else "launch"] = r["step_s"] / runner.chunk / strands
    mode = min(best, key=best.get)
    return {"s_per_strand_step": best[mode], "mode": mode, "strands": strands, **{f"{k}_s": v for k, v in best.items()}}


def cantilever_continuum(bend_stiffness: float, length: float = STRAND_LENGTH, nodes: int = 4001):
    """Static shape of a horizontal clamped rod under its own weight (the elastica), by ``solve_bvp``.

    ``EI theta'' = w (l - s) cos(theta)``, theta(0) = 0, theta'(l) = 0; returns a function of the
    arc length giving (x, z) [m].
    """
    from scipy.integrate import solve_bvp

    w = DENSITY * math.pi * RADIUS**2 * GRAVITY

    def rhs(s, y):
        return np.vstack([y[1], w * (length - s) * np.cos(y[0]) / bend_stiffness, np.cos(y[0]), np.sin(y[0])])

    def bc(ya, yb):
        return np.array([ya[0], yb[1], ya[2], ya[3]])

    s = np.linspace(0.0, length, nodes)
    guess = np.zeros((4, s.size))
    guess[2] = s
    sol = solve_bvp(rhs, bc, s, guess, tol=1e-10, max_nodes=200000)
    if not sol.success:
        raise RuntimeError(f"elastica solve failed: {sol.message}")
    return lambda arc: np.stack([sol.sol(arc)[2], sol.sol(arc)[3]], axis=-1)


def cantilever_static(segments: int, bend_stiffness: float, device, *, root_scale: float = 1.0, dt: float = 1e-3,
                      max_time: float = 8.0, speed_tol: float = 1e-4) -> dict:
    """Settle a horizontal strand under gravity with implicit_joints and damping near critical for its
    first mode; returns the vertices (S+1, 3) once every vertex is slower than ``speed_tol`` m/s
    (float32 round-off keeps a residual jitter of ~1e-5 m/s)."""
    area = math.pi * RADIUS**2
    omega1 = 3.516 * math.sqrt(bend_stiffness / (DENSITY * area * STRAND_LENGTH**4))
    params = StrandParams(density=DENSITY, radius=RADIUS, bend_stiffness=bend_stiffness,
                          damping=2.0 * bend_stiffness / omega1, root_stiffness_scale=root_scale)
    verts = np.zeros((1, segments + 1, 3))
    verts[0, :, 0] = np.linspace(0.0, STRAND_LENGTH, segments + 1)
    model = Model.build(verts, params, segments=segments, device=device)
    chunk = int(round(0.05 / dt))
    runner = StepRunner(model, Solver(model, "implicit_joints"), dt, chunk, graph=True)
    t, speed = 0.0, math.inf
    while t < max_time:
        runner.advance(1)
        t += chunk * dt
        speed = float(np.linalg.norm(runner.current.vertex_velocities.numpy(), axis=1).max())
        if speed < speed_tol:
            break
    return {"vertices": runner.current.vertex_positions.numpy().astype(float), "settle_time_s": t,
            "final_speed_m_s": speed}


def convergence(cfg, device, log) -> dict:
    """Static shape error against the continuum elastica as S grows (same total length).

    Two root joints: as the model builds it (stiffness 2 EI / L_0: EI over the half segment a
    clamped end's joint stands for) and half that (``root_stiffness_scale = 0.5``: EI / L_0, the
    mean-length rule of the inner joints applied at the root), which converges at first order only.
    """
    from hairwarp.benchmarks.common import fit_exponent

    EI = cfg.conv_bend_stiffness
    shape = cantilever_continuum(EI)
    exact_tip = shape(np.array([STRAND_LENGTH]))[0]
    variants = {}
    for label, root_scale in (("root 2 EI/L0 (as built)", 1.0), ("root EI/L0 (root_stiffness_scale = 0.5)", 0.5)):
        rows = []
        for S in cfg.conv_segments:
            t0 = time.perf_counter()
            r = cantilever_static(S, EI, device, root_scale=root_scale)
            v = r["vertices"]
            ref = shape(np.arange(S + 1) * STRAND_LENGTH / S)
            d = np.hypot(v[:, 0] - ref[:, 0], v[:, 2] - ref[:, 1])
            rows.append({"segments": S, "tip_error_m": float(d[-1]), "max_vertex_error_m": float(d.max()),
                         "tip": [float(v[-1, 0]), float(v[-1, 2])], "settle_time_s": r["settle_time_s"],
                         "final_speed_m_s": r["final_speed_m_s"], "wall_s": time.perf_counter() - t0})
            log(f"  {label}, S = {S}: tip error {d[-1]:.3g} m, max vertex error {d.max():.3g} m")
        order = fit_exponent([r["segments"] for r in rows], [r["max_vertex_error_m"] for r in rows])
        fewest = {}
        for tol in (1e-2, 1e-3, 1e-4):
            ok = [r["segments"] for r in rows if r["max_vertex_error_m"] <= tol]
            fewest[f"{tol:g}"] = min(ok) if ok else None
        variants[label] = {"root_stiffness_scale": root_scale, "rows": rows,
                           "fitted_order": None if order is None else -order,
                           "fewest_segments_for_max_vertex_error": fewest}
    return {"bend_stiffness": EI, "length_m": STRAND_LENGTH, "exact_tip": [float(exact_tip[0]), float(exact_tip[1])],
            "tip_deflection_m": float(-exact_tip[1]), "integrator": "implicit_joints", "variants": variants,
            "method": "static equilibrium by damped implicit_joints (damping critical for mode 1) vs the elastica "
                      "EI theta'' = w (l - s) cos theta, theta(0) = 0, theta'(l) = 0, by scipy solve_bvp (tol 1e-10)"}


def suite_accuracy(cfg, out: Path, log=lambda msg: None) -> dict:
    ref = reference_tips(cfg, out, log)
    result = {"strand": {"segments": 20, "segment_length_m": 0.015, "radius_m": RADIUS, "density": DENSITY,
                         "tilt_deg": 80.0, "damping": 0.0, "bend_stiffness": 0.0},
              "reference": {k: v for k, v in ref.items() if k != "tip"}, "duration_s": cfg.acc_duration,
              "cost_definition": "CPU seconds per simulated second of one strand = (per-strand step cost) / dt; "
                                 "per-strand step cost measured on a batch for hairwarp and Newton, per call for "
                                 "Pinocchio (Python loop) and MuJoCo (C mj_step)"}
    if ref["tip"] is None:
        result["status"] = "no reference"
        return result
    tip_ref = ref["tip"]
    methods = []
    for integrator in cfg.acc_integrators:
        log(f"accuracy: hairwarp {integrator} ...")
        cost = our_cost(integrator, cfg.acc_cost_strands, "cpu", cfg)
        runs = []
        for dt in cfg.acc_dts:
            t0 = time.perf_counter()
            tips = our_tips(integrator, dt, cfg.acc_duration, "cpu")
            e = tip_errors(tips, tip_ref)
            runs.append({"dt": dt, **e, "cpu_s_per_sim_s": cost["s_per_strand_step"] / dt,
                         "wall_s": time.perf_counter() - t0})
            log(f"  dt = {dt:g}: rms 0.5 s {e['rms_0.5']}, max 1 s {e.get('max_1')}")
        methods.append({"method": f"hairwarp {integrator}", "kind": "hairwarp", "integrator": integrator,
                        "cost": cost, "runs": runs})
    for peer, dts in cfg.acc_peer_dts.items():
        log(f"accuracy: peer {peer} ...")
        GATE.wait()
        res = run_child({"kind": "trajectory", "peer": peer, "dts": list(dts), "duration": cfg.acc_duration,
                         "S": 20, "cost_strands": cfg.acc_cost_strands}, cfg.peer_timeout_s)
        entry = {"method": peer, "kind": "peer", "status": res.get("status")}
        if res.get("status") == "ok":
            c = res["cost_s_per_strand_step"]
            entry["cost"] = {"s_per_strand_step": c, "note": res.get("cost_note")}
            entry["runs"] = [{"dt": r["dt"], **tip_errors(r["tip"], tip_ref), "cpu_s_per_sim_s": c / r["dt"],
                              "wall_s": r["wall_s"]} for r in res["runs"]]
        else:
            entry["message"] = res.get("message")
            log(f"  {res.get('status')}: {res.get('message', '')[:200]}")
        methods.append(entry)
    result["methods"] = methods
    log("accuracy: convergence with the segment count ...")
    result["convergence"] = convergence(cfg, "cpu", log)
    return result
