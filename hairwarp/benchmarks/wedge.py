"""What the Dask engine of ``hairwarp wedge`` costs and buys on this machine.

:func:`suite_wedge` (``hairwarp bench wedge``) runs one 8-variant wedge of the default scene (``long_hair.toml``,
its bend stiffness times its link stiffness, frames shortened to :data:`FRAMES`) on the :data:`CONFIGS` of a local
cluster (1 and 2 worker processes with one thread per run, and 1 worker whose runs take every core's threads),
each from a fresh cluster into a fresh folder, and reports the wall time of each (the goal: at least 1.8x faster
with 2 workers than with 1 on 2 cores, one thread per run in both). From the timestamps every task record carries
(submitted and received on the client, started and ended on the worker) it takes the engine's own cost per task:
the time a task waits for a free worker beyond the previous task's end (scheduling) plus the time its result takes
back to the client (transfer), against the task's time on the worker. A round trip of an empty task on the same kind of
cluster is the floor of that cost. :func:`md_wedge` renders the report section and :func:`chart_wedge` its chart.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

from hairwarp.benchmarks.common import machine_words

# 8 variants: 4 bend stiffnesses (EI [N m^2]) x 2 link stiffnesses [N/m at 1 cm] around the shipped 2e-4 and 0.35.
PARAMS = {"strands.bend_stiffness": [1e-4, 2e-4, 4e-4, 8e-4], "links.stiffness": [0.2, 0.35]}
FRAMES = 60
"""Output frames per variant (the scene ships 90): 8 runs of 60 frames (about 7 s each) keep the suite near five
minutes while what a wedge pays once (the cluster's start and close, about 2.5 s, and each fresh worker's first
imports, about 1.3 s) stays small against the work, as in a real wedge of full-length runs."""
QUICK_PARAMS = {"strands.bend_stiffness": [1e-4, 1e-3], "strands.drag": [0.01, 0.02]}
QUICK_FRAMES = 3
CONFIGS = ((1, 1), (2, 1), (1, 0))
"""(worker processes, threads per run; 0: the engine's share, cores / workers) of the timed wedges. The first two
measure the engine with the work per worker fixed; the third is the alternative a machine's cores also allow, one
worker whose runs split their launches over every core."""
ROUNDS = 3
"""Each wedge is timed this often, the configurations interleaved; the fastest of each counts (the machine is
shared: the least disturbed run is the closest to what the engine does)."""
GOAL_SPEEDUP = 1.8
NOOP_TASKS = 40
CHART = "bench_wedge.png"


def _noop():
    return None


def _overheads(records: list[dict]) -> list[dict]:
    """Per task: seconds on the worker, of which simulating, and the engine's scheduling wait and transfer."""
    rows = []
    by_worker: dict = {}
    for r in records:
        by_worker.setdefault(r.get("worker"), []).append(r)
    for tasks in by_worker.values():
        tasks.sort(key=lambda r: r["timing"]["t_start"])
        previous_end = None
        for r in tasks:
            t = r["timing"]
            ready = t["t_submit"] if previous_end is None else max(t["t_submit"], previous_end)
            rows.append({"name": r["name"], "task_s": t["t_end"] - t["t_start"], "simulate_s": t.get("simulate_s"),
                         "scheduling_s": max(t["t_start"] - ready, 0.0), "transfer_s": t["t_received"] - t["t_end"]})
            previous_end = t["t_end"]
    return rows


def _cpu_seconds() -> tuple[float, float]:
    """(CPU seconds the whole machine has been busy, CPU seconds of this process and its reaped children)."""
    import psutil

    t = psutil.cpu_times()
    busy = sum(t) - t.idle - getattr(t, "iowait", 0.0)
    own = psutil.Process().cpu_times()
    return busy, own.user + own.system + own.children_user + own.children_system


def _timed_wedge(scene, params, overrides, workers: int, log, threads: int = 0) -> dict:
    """One wedge on a fresh local cluster of ``workers`` processes; ``threads`` per run (0: the engine's share)."""
    from hairwarp import farm
    from hairwarp.benchmarks.common import GATE, load_average

    if threads:
        overrides = [*overrides, f"sim.threads={int(threads)}"]
    else:
        threads = farm.threads_per_run(farm.local_cores(), workers)

    gate = GATE.wait()
    load_start = load_average()
    with tempfile.TemporaryDirectory(prefix="hairwarp-bench-wedge-") as tmp:
        busy0, own0 = _cpu_seconds()
        t0 = time.perf_counter()
        records = farm.wedge(scene, params, out=Path(tmp) / "w", workers=workers, overrides=overrides, sheet=False)
        wall = time.perf_counter() - t0
        busy1, own1 = _cpu_seconds()  # the cluster is closed: its worker processes are reaped children by now
    others = max(busy1 - busy0 - (own1 - own0), 0.0) / wall
    bad = [r for r in records if r["status"] != "ok"]
    if bad:
        raise RuntimeError(f"bench wedge: {bad[0]['name']} {bad[0]['status']}: {bad[0]['message']}")
    first_submit = min(r["timing"]["t_submit"] for r in records)
    last_received = max(r["timing"]["t_received"] for r in records)
    rows = _overheads(records)
    engine = [row["scheduling_s"] + row["transfer_s"] for row in rows]
    out = {"workers": workers, "threads": int(threads), "tasks": len(records), "wall_s": wall,
           "submit_to_last_result_s": last_received - first_submit, "cluster_s": wall - (last_received - first_submit),
           "task_s_mean": statistics.fmean(row["task_s"] for row in rows),
           "simulate_s_mean": statistics.fmean(row["simulate_s"] for row in rows),
           "task_s_sum": sum(row["task_s"] for row in rows),
           "engine_s_mean": statistics.fmean(engine), "engine_s_max": max(engine),
           "scheduling_s_mean": statistics.fmean(row["scheduling_s"] for row in rows),
           "transfer_s_mean": statistics.fmean(row["transfer_s"] for row in rows),
           "tasks_detail": rows, "quiet_gate": gate, "load_average_start": load_start,
           "load_average_end": load_average(), "others_busy_cores": others, "own_cpu_s": own1 - own0}
    log(f"wedge: {workers} worker(s), {threads} thread(s) a run: {wall:.1f} s for {len(records)} tasks (tasks "
        f"{out['task_s_mean']:.2f} s on average, engine {1e3 * out['engine_s_mean']:.1f} ms per task; other "
        f"programs kept {others:.2f} cores busy meanwhile)")
    return out


def noop_round_trip(workers: int = 2, tasks: int = NOOP_TASKS) -> dict:
    """Submit-to-result time of an empty task, one at a time, on a local cluster like the wedge's."""
    import logging

    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0",
                      silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
        client.submit(_noop, pure=False).result()  # the first call carries the connection set-up
        samples = []
        for _ in range(tasks):
            t0 = time.perf_counter()
            client.submit(_noop, pure=False).result()
            samples.append(time.perf_counter() - t0)
    return {"tasks": tasks, "median_s": statistics.median(samples), "max_s": max(samples)}


def suite_wedge(config, out, log=lambda message: None) -> dict:
    """The ``wedge`` suite of ``hairwarp bench``: an 8-variant wedge of the default scene (quick: 4 variants of
    tiny.toml) with 1 and 2 workers, the engine's cost per task, and an empty task's round trip."""
    from hairwarp import farm
    from hairwarp.scene import Scene

    quick = bool(config.quick)
    scene = Scene.default_path() if not quick else Path(Scene.default_path()).with_name("tiny.toml")
    params = QUICK_PARAMS if quick else PARAMS
    frames = QUICK_FRAMES if quick else FRAMES
    overrides = [f"sim.frames={frames}"]
    variants = 1
    for values in params.values():
        variants *= len(values)
    log(f"wedge: {variants} variants of {Path(scene).name}, {frames} frames each, (workers, threads) {CONFIGS}")
    all_runs = []
    for n in range(1 if quick else ROUNDS):
        for w, t in CONFIGS:
            all_runs.append({"round": n, "config": [w, t], **_timed_wedge(scene, params, overrides, w, log, t)})
    runs = [min((r for r in all_runs if r["config"] == [w, t]), key=lambda r: r["wall_s"]) for w, t in CONFIGS]
    log("wedge: round trip of an empty task")
    noop = noop_round_trip()
    speedup = runs[0]["wall_s"] / runs[1]["wall_s"]
    data = {"scene": Path(scene).name, "variants": variants, "params": params, "frames": frames,
            "frames_shipped": int(Scene.load(scene).sim.frames), "cores": farm.local_cores(), "runs": runs,
            "all_runs": all_runs,
            "noop": noop, "speedup": speedup, "goal_speedup": GOAL_SPEEDUP, "meets": speedup >= GOAL_SPEEDUP,
            "threads_key": farm._threads_key_exists()}
    chart = Path(out) / CHART
    try:
        chart_wedge(data, chart)
        data["files"] = [str(chart)]
    except (ImportError, OSError, ValueError) as exc:
        log(f"wedge: chart not drawn: {exc}")
    return data


def chart_wedge(data: dict, path: Path) -> None:
    """Wall time with 1 and 2 workers (with the ideal of 2), and one task's time split into simulation, the rest of
    the task, and the engine's scheduling and transfer."""
    from hairwarp.benchmarks.report import _pyplot

    plt = _pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(9.5, 3.6))
    runs = data["runs"]
    xs = [_label(r) for r in runs]
    a.bar(xs, [r["wall_s"] for r in runs], color="#4c72b0", label="measured")
    a.plot(xs, [runs[0]["wall_s"] / (r["workers"] * r.get("threads", 1)) for r in runs], "k--", marker="o", ms=3,
           label="ideal (1 / cores used)")
    a.set_xlabel("worker processes x threads a run")
    a.set_ylabel("wall time of the wedge [s]")
    a.set_title(f"{data['variants']} variants of {data['scene']}, {data['frames']} frames: {data['speedup']:.2f}x")
    a.legend(fontsize=7)
    parts = [("simulate", "simulate_s_mean", "#4c72b0"), ("rest of the task", None, "#dd8452"),
             ("engine: scheduling + transfer", "engine_s_mean", "#c44e52")]
    bottom = [0.0] * len(runs)
    for label, key, color in parts:
        values = [r["task_s_mean"] - r["simulate_s_mean"] if key is None else r[key] for r in runs]
        b.bar(xs, values, bottom=bottom, color=color, label=label)
        bottom = [x + v for x, v in zip(bottom, values)]
    b.set_xlabel("worker processes x threads a run")
    b.set_ylabel("mean per task [s]")
    b.set_title("one task: where its time goes")
    b.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _label(run: dict) -> str:
    return f"{run['workers']} x {run.get('threads', 1)}"


def md_wedge(data: dict) -> list[str]:
    """The report section of :func:`suite_wedge`."""
    runs = data["runs"]
    noop = data["noop"]
    keys = " × ".join(f"`{k}`" for k in data["params"])
    lines = ["## Wedges on Dask (`hairwarp bench wedge`)", "",
             f"A wedge of {data['variants']} variants of `{data['scene']}` ({keys}, every combination), frames "
             f"shortened from {data['frames_shipped']} to {data['frames']} per variant, each writing its cache, "
             "preview and stats, run by `hairwarp.farm` on a local cluster of 1 and of 2 worker processes with one "
             "thread a run, and of 1 worker whose runs take every core's threads (the engine's share, "
             f"`sim.threads` unset; {data['cores']} cores usable), each from a fresh cluster into a fresh folder. "
             "*Wall* includes starting and closing the cluster."]
    lines += ["", f"![wedge]({CHART})", "",
              "| round | workers | threads a run | wall [s] | submit → last result [s] | cluster start + close [s] "
              "| task on a worker, mean [s] | of which simulate [s] | engine per task, mean / max [ms] "
              "| other programs during the run [cores] | load average at start |",
              "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in data.get("all_runs", runs):
        load = r.get("load_average_start")
        best = "**" if r in runs else ""
        others = r.get("others_busy_cores")
        lines.append(f"| {r.get('round', 0) + 1} | {r['workers']} | {r.get('threads', 1)} "
                     f"| {best}{r['wall_s']:.1f}{best} "
                     f"| {r['submit_to_last_result_s']:.1f} | {r['cluster_s']:.1f} | {r['task_s_mean']:.2f} "
                     f"| {r['simulate_s_mean']:.2f} | {1e3 * r['engine_s_mean']:.1f} / {1e3 * r['engine_s_max']:.1f} "
                     f"| {'–' if others is None else f'{others:.2f}'} "
                     f"| {', '.join(f'{x:g}' for x in load) if load else '–'} |")
    lines += ["", "Bold: the fastest run of each configuration, which the speed-up and the chart use. *Other "
              "programs*: the machine's busy CPU time during the run less this process's and its workers', per "
              "second of wall time. The load average (over 1, 5 and 15 minutes) still holds this suite's own earlier "
              "runs."]
    one, two = runs[0], runs[1]
    every = data.get("all_runs", runs)
    max_others = max((r.get("others_busy_cores") or 0.0) for r in every)

    def spread(run: dict) -> str:
        walls = [r["wall_s"] for r in every if _label(r) == _label(run)]
        return f"{100 * (max(walls) - min(walls)) / min(walls):.0f} %" if len(walls) > 1 else "– (one round)"

    ideal = two["cluster_s"] + (one["wall_s"] - one["cluster_s"]) / 2
    share = two["engine_s_mean"] / two["task_s_mean"] if two["task_s_mean"] else float("nan")
    lines += ["",
              f"- **Speed-up with 2 workers: {data['speedup']:.2f}×** (goal ≥ {data['goal_speedup']:g}×: "
              f"{'met' if data['meets'] else 'not met'}). With the cores to itself and the tasks split evenly, the "
              f"2-worker wedge would take its cluster's start and close plus half the 1-worker run's work: "
              f"{two['cluster_s']:.1f} + {one['wall_s'] - one['cluster_s']:.1f} / 2 = {ideal:.1f} s, "
              f"{one['wall_s'] / ideal:.2f}×.",
              f"- The engine's cost per task (waiting for a worker beyond the previous task's end, plus the result's "
              f"way back) is {1e3 * two['engine_s_mean']:.1f} ms on average against {two['task_s_mean']:.2f} s of "
              f"task: {100 * share:.2f} % of it. An empty task's round trip on a 2-worker cluster takes "
              f"{1e3 * noop['median_s']:.1f} ms (median of {noop['tasks']}, max {1e3 * noop['max_s']:.1f} ms).",
              "- *Simulate* is `hairwarp.simulate` (the simulation, the cache and the preview picture); the rest of a "
              "task reads the tip travel back from the cache and writes the stats and the markers.",
              f"- The same wedge varied between rounds by {spread(one)} with 1 worker and {spread(two)} with 2, while "
              f"other programs took at most {max_others:.2f} cores (the cache writer also waits on the disk: it "
              "writes and flushes a layer per frame): the speed-up is good to about that much.",
              *_threaded(runs),
              "- The machine is shared with other work. Two workers only run twice as fast as one when nothing else "
              "needs the cores: every core-second another program takes during the 2-worker run comes out of the "
              "wedge, while the 1-worker run has a core to spare for it. Where the speed-up falls short, the "
              "*other programs* column says by how much the machine was taken."]
    sm = data.get("machine", {})
    lines += ["", f"*Suite `wedge`{' (quick sizes)' if data.get('quick') else ''}: {data.get('wall_s')} s on "
                  f"{sm.get('date')}{machine_words(sm)}, load average at the end {sm.get('load_average_end')}.*"]
    return lines


def _threaded(runs: list[dict]) -> list[str]:
    """The bullet on the one-worker wedge whose runs take every core's threads, where it was timed."""
    threaded = [r for r in runs[2:] if r.get("threads", 1) > 1]
    if not threaded:
        return []
    one, two, t = runs[0], runs[1], threaded[0]
    if two["wall_s"] < t["wall_s"]:
        verdict = ("so a wedge fills the cores faster with one single-threaded run per core: a run's threads share "
                   "its serial parts and wait for each other at every launch (`hairwarp bench threads`), runs side by "
                   "side share nothing")
    else:
        verdict = "so here one worker on every core's threads was the faster"
    return [f"- One worker whose runs take {t['threads']} threads each: {t['wall_s']:.1f} s, the speed of "
            f"{one['wall_s'] / t['wall_s']:.2f}× the one-thread worker against {one['wall_s'] / two['wall_s']:.2f}× "
            f"for {two['workers']} workers, {verdict}. The engine gives each run cores / workers threads unless the "
            "scene sets `sim.threads`."]
