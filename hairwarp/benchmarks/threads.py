"""The ``threads`` suite of ``hairwarp bench``: what the CPU executor (``hairwarp.executor``) buys, stage by stage and
for whole frames, on the default scene and the Ratboy mohawk, against one thread, in one run.

One thread and N threads run the same simulation (two ``Simulation`` objects, each warmed up), timed in
interleaved rounds (1, N, 1, N, ...) so a change of the machine's load hits both; each figure is the best round.
The load average is recorded before and after: on a loaded machine the second thread may find no core free, and
the speed-up then says more about the load than about the executor.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

SCENES = Path(__file__).resolve().parents[2] / "scenes"
GOALS = {"dynamics": 1.9, "frame": 1.8}


def _stages(sim):
    """name -> a function running that stage once on ``sim`` (state and control as the run has them)."""
    solver, stepper = sim.solver, sim.stepper
    model, control = sim.model, stepper.control
    s0, s1 = stepper.states

    stages = {"dynamics (aba + integrate)": lambda: solver._integrate(s0, s1, control)}
    if solver.has_forces:
        stages["forces (drag, links, hair contacts)"] = lambda: solver._accumulate_forces(s0, control)
    if solver.body_contacts.enabled:
        stages["body contact detection"] = lambda: sim.collider_set.detect(model, s0, control, solver.dt)
        stages["body push-out"] = lambda: sim.collider_set.project(model, s1, control, solver.dt, s0)
    if sim.links is not None:
        stages["links"] = lambda: sim.links.apply(model, s0, solver.dt, solver.seg_force, solver.seg_torque,
                                                  solver.seg_implicit_mass)
    if sim.contacts is not None:
        contacts = sim.contacts
        stages["hair contact BVH refit/rebuild (library, 2 trees)"] = lambda: contacts.refit(
            model, s0, rebuild=not contacts.detect_each_step)
        stages["hair contact detection"] = lambda: contacts.detect(model, s0)
    if sim.dense is not None:
        stages["dense interpolate + push-out + Hermite"] = lambda: sim.dense_curves()
    stages["frame (detection, substeps, dense)"] = lambda: (sim.advance_frame(),
                                                            sim.dense_curves() if sim.dense is not None else None)
    return stages


def _time(fn, min_s: float) -> float:
    fn()
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= min_s:
            return dt / n


def bench_scene(path, threads: int, *, overrides=(), rounds: int = 5, min_s: float = 0.2, device="cpu") -> dict:
    """Per-stage seconds on 1 and ``threads`` threads (best of ``rounds`` interleaved rounds) and the speed-ups."""
    from hairwarp.runner import Simulation
    from hairwarp.scene import Scene

    scene = Scene.load(path, overrides=["output.preview=false", *overrides])
    sims = {t: Simulation(scene, device=device, threads=t) for t in (1, threads)}
    for sim in sims.values():
        for _ in range(2):
            sim.advance_frame()
    stages = {t: _stages(sim) for t, sim in sims.items()}
    best = {t: {name: float("inf") for name in stages[t]} for t in sims}
    load_before = list(os.getloadavg())
    for _ in range(rounds):
        for name in stages[1]:
            for t in sims:
                best[t][name] = min(best[t][name], _time(stages[t][name], min_s))
    load_after = list(os.getloadavg())
    rows = [{"stage": name, "t1_ms": 1e3 * best[1][name], "tn_ms": 1e3 * best[threads][name],
             "speedup": best[1][name] / best[threads][name]} for name in stages[1]]
    m = sims[1].model
    return {"scene": Path(path).name, "guides": m.strand_count, "segments": m.seg_per_strand,
            "substeps": int(scene.sim.substeps), "threads": threads, "rounds": rounds, "rows": rows,
            "load_before": [round(x, 2) for x in load_before], "load_after": [round(x, 2) for x in load_after]}


def suite_threads(config, out, log=lambda message: None) -> dict:
    """Speed-up of every stage and of a whole frame, default scene and Ratboy mohawk, N threads against 1."""
    from hairwarp.executor import default_threads

    threads = int(getattr(config, "threads", 0) or 0) or default_threads()
    quick = bool(config.quick)
    rounds, min_s = (2, 0.05) if quick else (5, 0.3)
    results = {"threads": threads, "cores": default_threads(), "goals": GOALS, "scenes": []}
    log(f"threads: default scene, 1 against {threads} threads, {rounds} interleaved rounds")
    over = ["groom.count=100", "dense.count=500"] if quick else []
    results["scenes"].append(bench_scene(SCENES / "long_hair.toml", threads, overrides=over, rounds=rounds,
                                         min_s=min_s, device=config.device))
    ratboy = SCENES / "ratboy_mohawk.toml"
    try:
        log("threads: Ratboy mohawk")
        results["scenes"].append(bench_scene(ratboy, threads, rounds=rounds, min_s=min_s, device=config.device))
    except (FileNotFoundError, ValueError) as e:
        results["skipped"] = f"ratboy_mohawk: {e}"
    results["files"] = [str(chart_threads(results, Path(out) / "threads.png"))]
    return results


def chart_threads(data: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = data["scenes"]
    fig, axes = plt.subplots(1, len(scenes), figsize=(6 * len(scenes), 4), squeeze=False)
    for ax, s in zip(axes[0], scenes):
        names = [r["stage"] for r in s["rows"]]
        ax.barh(names, [r["speedup"] for r in s["rows"]], color="tab:blue")
        ax.axvline(1.0, color="k", lw=0.8)
        ax.axvline(s["threads"], color="tab:green", ls="--", lw=0.8, label=f"{s['threads']} threads: ideal")
        ax.set_xlabel(f"speed-up, {s['threads']} threads against 1")
        ax.set_title(f"{s['scene']} ({s['guides']} x {s['segments']}), load {s['load_before'][0]}")
        ax.invert_yaxis()
        ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def md_threads(data: dict) -> list[str]:
    """A report section for :func:`suite_threads`'s results."""
    lines = ["## Every core of the CPU (`hairwarp bench threads`)", "",
             f"N = {data['threads']} threads against 1 ({data['cores']} cores this process may use), best of "
             "interleaved rounds; goals on 2 cores: dynamics >= 1.9x, a whole frame >= 1.8x. The 1-minute load "
             "average before and after each scene is part of the figure: the machine is shared (the suite's own "
             "N-thread rounds add up to N to it).", "",
             "![speed-up per stage](threads.png)", ""]
    for s in data["scenes"]:
        lines += [f"### {s['scene']}: {s['guides']} guides x {s['segments']} segments, {s['substeps']} substeps "
                  f"(load {s['load_before']} before, {s['load_after']} after)", "",
                  "| stage | 1 thread [ms] | N threads [ms] | speed-up |", "|---|---:|---:|---:|"]
        lines += [f"| {r['stage']} | {r['t1_ms']:.3f} | {r['tn_ms']:.3f} | {r['speedup']:.2f}x |" for r in s["rows"]]
        lines.append("")
    if data.get("skipped"):
        lines += [f"Skipped: {data['skipped']}.", ""]
    return lines
