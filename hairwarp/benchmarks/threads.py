"""The ``threads`` suite of ``hairwarp bench``: what the CPU executor (``hairwarp.executor``) buys, stage by stage and
for whole frames, on the default scene and the Ratboy mohawk, against one thread, in one run.

One thread and N threads run the same simulation (two ``Simulation`` objects, each warmed up), timed in
interleaved rounds (1, N, 1, N, ...), each stage on one thread and then on N; a speed-up is the median over the
rounds of each round's ratio, so a change of the machine's pace between rounds (one-thread timings of the same
stage spread by 1.6-2.7 ms between rounds seconds apart on a quiet 2-core machine) hits both of its timings and a
round that caught one side at its best is outvoted. (The best round of each side, divided, put
one-thread and N-thread timings of different rounds against each other: the same suite gave 1.76x and 2.22x for the
same stage in two runs.) The times shown are the medians of the rounds.
A whole frame is timed over the same frames on every side: each timing restores the run's checkpoint and runs
:data:`FRAMES_PER_TIMING` frames (timed back to back instead, the faster side ran later frames of the motion, with
other contacts).
The load average is recorded before and after: on a loaded machine the second thread may find no core free, and
the speed-up then says more about the load than about the executor.

In the same rounds N independent one-thread copies of the simulation run each stage at once, one per thread of
this process: work that needs no hand-off, no join and no shared array. Their combined throughput against one
copy alone is what the machine gives N threads of this work (cores that share a memory bus, a cache or a physical
core give less than N), and the executor's speed-up over it is its efficiency.
"""

from __future__ import annotations

import os
import statistics
import threading
import time
from pathlib import Path

import numpy as np
import warp as wp

from hairwarp.benchmarks.common import GATE

SCENES = Path(__file__).resolve().parents[2] / "scenes"
GOALS = {"dynamics": 1.9, "frame": 1.8}

#: The sweep's dynamics: the scaling suite's largest size, strands x segments (a whole groom's guides).
SWEEP_SIZE = (2228, 31)

#: Goal of the sweep at 16 threads: the dynamics of :data:`SWEEP_SIZE` at least this much faster than on one.
SWEEP_GOAL_16 = 12.0


#: The join probe's table: elements, and the sine terms each sums (about 75 us on one thread of the 2-core machine).
PROBE_SIZE = (64, 200)

#: A pair of timings waits while the join probe's speed-up is below this share of its usual value: the upper quartile
#: of every probe of the run so far (a spell's probes are a minority; one probe's outlier cannot move a quartile).
JOIN_FRACTION = 0.85

#: Probes the gate takes before it judges one against the others.
JOIN_FIRST_PROBES = 4

#: Longest wait for the probe before one pair of timings [s] (the slow spells seen last 15-60 s), and in all.
JOIN_MAX_WAIT_S, JOIN_BUDGET_S = 30.0, 240.0

#: Times a pair of timings is taken again when the probe after it is low (a spell began within it).
JOIN_RETRIES = 2


@wp.kernel
def _probe_work(tid_offset: int, terms: int, x: wp.array(dtype=float)):
    i = tid_offset + wp.tid()
    s = float(0.0)
    for k in range(terms):
        s = s + wp.sin(float(k) * 0.001 + x[i])
    x[i] = s


class JoinGate:
    """Waits, before a pair of timings, until the machine lets N threads meet at the executor's joins.

    On a virtual machine the cores can be shared with other guests: for spells of 15-60 s (seen on the 2-core
    machine of docs/benchmarks.md) N independent copies keep their throughput, 1.91-1.98x, while every stage of one
    simulation on N threads loses up to half its speed-up (the mohawk's forces 1.05x instead of 1.75x, its frame
    1.32x instead of 1.82x): a thread that waits at a join for another waits for as long as the other's core is away,
    where copies never wait. The probe is a small table of independent work (:data:`PROBE_SIZE`), timed on one
    thread and on N: 1.66-1.69x outside the spells, 1.34-1.39x within. A pair of timings starts once the probe is
    back within :data:`JOIN_FRACTION` of its usual value (:meth:`usual`), or when the wait for it (or the run's
    budget) is spent, and is taken again when the probe after it is low (:meth:`pair`); every call records what it
    saw.
    """

    def __init__(self, threads: int):
        from hairwarp.executor import Executor

        self.threads = threads
        self.one, self.many = Executor("cpu", 1), Executor("cpu", threads, min_chunk=1)
        self.x = wp.zeros(PROBE_SIZE[0], dtype=float, device="cpu")
        self.waited_s, self.probes, self.seen = 0.0, [], []
        self.redone, self.ended_low = 0, 0  # pairs timed again; pairs kept with the probe after them still low

    def probe(self, reps: int = 40, rounds: int = 5) -> float:
        """The probe's speed-up now: the median of ``rounds`` interleaved ratios, each side the mean of ``reps``
        launches of its table (about 25 ms in all)."""
        ratios = []
        for _ in range(rounds):
            times = []
            for ex in (self.one, self.many):
                ex.launch(_probe_work, PROBE_SIZE[0], [PROBE_SIZE[1]], [self.x])
                t0 = time.perf_counter()
                for _ in range(reps):
                    ex.launch(_probe_work, PROBE_SIZE[0], [PROBE_SIZE[1]], [self.x])
                times.append(time.perf_counter() - t0)
            ratios.append(times[0] / times[1])
        return statistics.median(ratios)

    def usual(self) -> float | None:
        """The upper quartile of every probe so far (None before :data:`JOIN_FIRST_PROBES`)."""
        if len(self.seen) < JOIN_FIRST_PROBES:
            return None
        return float(np.percentile(self.seen, 75))

    def _low(self, speedup: float) -> bool:
        usual = self.usual()
        return usual is not None and speedup < JOIN_FRACTION * usual

    def wait(self) -> dict:
        """Probe, and wait while the probe is low (see the class); the probe and the wait."""
        t0 = time.perf_counter()
        speedup = self.probe()
        self.seen.append(speedup)
        while (self._low(speedup) and time.perf_counter() - t0 < JOIN_MAX_WAIT_S
               and self.waited_s + time.perf_counter() - t0 < JOIN_BUDGET_S):
            time.sleep(1.0)
            speedup = self.probe()
            self.seen.append(speedup)
        waited = time.perf_counter() - t0
        self.waited_s += waited
        record = {"probe": round(speedup, 3), "waited_s": round(waited, 2), "low": self._low(speedup)}
        self.probes.append(record)
        return record

    def pair(self, measure):
        """``measure()`` (one pair of timings) once :meth:`wait` lets it start, taken again, up to
        :data:`JOIN_RETRIES` times, while the probe after it is low: a spell that began within the pair reached its
        timings (one side of it slowed, the other not); its result."""
        for attempt in range(JOIN_RETRIES + 1):
            self.wait()
            result = measure()
            after = self.probe()
            self.seen.append(after)
            low = self._low(after)
            if not low or attempt == JOIN_RETRIES:
                self.redone += attempt
                self.ended_low += int(low)
                return result

    def mark(self) -> tuple[int, int, int]:
        """Where the record stands now, for :meth:`summary` of what comes after."""
        return len(self.probes), self.redone, self.ended_low

    def summary(self, since: tuple[int, int, int] = (0, 0, 0)) -> dict:
        """What the gate saw after the :meth:`mark` ``since``: the probes before each pair (their count, the low
        ones, the wait, the probe's range and its usual value), the pairs timed again and those kept with the probe
        low after them."""
        seen = self.probes[since[0]:]
        values = [p["probe"] for p in seen]
        usual = self.usual()
        return {"pairs": len(seen), "low": sum(p["low"] for p in seen), "redone": self.redone - since[1],
                "ended_low": self.ended_low - since[2], "waited_s": round(sum(p["waited_s"] for p in seen), 1),
                "usual": None if usual is None else round(usual, 3),
                "min": min(values) if values else None, "median": statistics.median(values) if values else None,
                "fraction": JOIN_FRACTION}

    def close(self):
        self.one.close()
        self.many.close()


def _stages(sim):
    """name -> a function running that stage once on ``sim`` (state and control as the run has them)."""
    solver, stepper = sim.solver, sim.stepper
    model, control = sim.model, stepper.control
    s0, s1 = stepper.states

    stages = {"dynamics (aba + integrate)": lambda: solver._integrate(s0, s1, control)}
    if solver.has_forces:
        stages["forces (drag, links, hair contacts)"] = lambda: solver._accumulate_forces(s0, control)
    if solver.responders:
        # the response rewrites the free step's result it reads: timed with the step that makes it
        stages["dynamics + links' and contacts' response"] = lambda: (solver._integrate(s0, s1, control),
                                                                     solver._respond(s0, s1, control))
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
        # both trees fitted, then both kinds of contact found: on several threads, one set of tasks
        stages["hair contact detection (trees fitted, contacts found)"] = lambda: contacts.detect(model, s0)
    if sim.dense is not None:
        stages["dense interpolate + push-out + Hermite"] = lambda: sim.dense_curves()
    stages[FRAME_STAGE] = lambda: (sim.advance_frame(), sim.dense_curves() if sim.dense is not None else None)
    return stages


#: The stage that advances the run: timed over the same frames on every side (``_time_frames``).
FRAME_STAGE = "frame (detection, substeps, dense)"

#: Frames each timing of a whole frame runs from the checkpoint.
FRAMES_PER_TIMING = 4

#: Timings of a whole frame on each side in every round (one thread, N, the copies; then again): a frame's timing
#: lasts a few tenths of a second, the machine's pace changes over seconds, and more pairs steady the median.
FRAME_PAIRS = 3

#: Frames every simulation runs before the timings (kernels loaded, buffers sized); the checkpoint is taken there.
WARMUP_FRAMES = 2


def _time_frames(sim, saved: dict, frame_fn) -> float:
    """Seconds per frame of :data:`FRAMES_PER_TIMING` frames run from ``saved`` (a checkpoint of ``sim``), so every
    timing, on one thread or N, runs the same frames of the motion (their work varies with the contacts)."""
    sim.restore(saved)
    t0 = time.perf_counter()
    for _ in range(FRAMES_PER_TIMING):
        frame_fn()
    return (time.perf_counter() - t0) / FRAMES_PER_TIMING


def _time_frames_copies(sims, saved, frame_fns) -> float:
    """:func:`_time_copies` for whole frames: every copy runs the same :data:`FRAMES_PER_TIMING` frames from its
    checkpoint at once."""
    start = threading.Barrier(len(sims))
    spans = [0.0] * len(sims)

    def run(k):
        sims[k].restore(saved[k])
        start.wait()
        t0 = time.perf_counter()
        for _ in range(FRAMES_PER_TIMING):
            frame_fns[k]()
        spans[k] = time.perf_counter() - t0

    _on_threads(run, len(sims))
    return 1.0 / sum(FRAMES_PER_TIMING / dt for dt in spans)


def _time(fn, min_s: float) -> float:
    fn()
    n, t0 = 0, time.perf_counter()
    while True:
        fn()
        n += 1
        dt = time.perf_counter() - t0
        if dt >= min_s:
            return dt / n


def _time_copies(fns, min_s: float) -> float:
    """Seconds per call of one copy's share when every function of ``fns`` (one per independent simulation) runs
    at once on its own thread: the wall time of the calls all made over their count, so ``len(fns)`` copies
    taking as long each as one alone give ``len(fns)`` times the throughput."""
    start = threading.Barrier(len(fns))
    counts, spans = [0] * len(fns), [0.0] * len(fns)

    def run(k):
        fns[k]()
        start.wait()
        n, t0 = 0, time.perf_counter()
        while True:
            fns[k]()
            n += 1
            dt = time.perf_counter() - t0
            if dt >= min_s:
                counts[k], spans[k] = n, dt
                return

    _on_threads(run, len(fns))
    return 1.0 / sum(n / dt for n, dt in zip(counts, spans))


def _paired(one, other) -> float:
    """Median over the rounds of each round's ratio ``one / other`` (seconds of the same round)."""
    return statistics.median([a / b for a, b in zip(one, other)])


def _on_threads(run, count: int):
    """Call ``run(k)`` for k = 0 .. count - 1 at once: 0 on this thread, the others on threads of their own."""
    workers = [threading.Thread(target=run, args=(k,)) for k in range(1, count)]
    for t in workers:
        t.start()
    run(0)
    for t in workers:
        t.join()


def bench_scene(path, threads: int, *, overrides=(), rounds: int = 5, min_s: float = 0.2, device="cpu",
                join: JoinGate | None = None) -> dict:
    """Per-stage seconds on 1 and ``threads`` threads (medians of ``rounds`` interleaved rounds) and the speed-ups
    (medians of the rounds' ratios); with ``join``, each stage's pair of timings waits for the join probe and is
    taken again when the probe falls within it (:meth:`JoinGate.pair`)."""
    from hairwarp.runner import Simulation
    from hairwarp.scene import Scene

    scene = Scene.load(path, overrides=["output.preview=false", *overrides])
    sims = {t: Simulation(scene, device=device, threads=t) for t in (1, threads)}
    # the one-thread simulation and threads - 1 more: the independent copies
    copies = [sims[1], *(Simulation(scene, device=device, threads=1) for _ in range(threads - 1))]
    for sim in [*sims.values(), *copies[1:]]:
        for _ in range(WARMUP_FRAMES):
            sim.advance_frame()
    stages = {t: _stages(sim) for t, sim in sims.items()}
    copy_stages = [_stages(sim) for sim in copies]
    # every whole-frame timing starts from the same frame of the motion (checkpoints taken after the warm-up)
    saved = {id(sim): sim.checkpoint() for sim in [*sims.values(), *copies[1:]]}
    spent_in = {t: {name: [] for name in stages[t]} for t in sims}
    spent_copies = {name: [] for name in stages[1]}
    load_before = list(os.getloadavg())
    gates = []
    since = join.mark() if join is not None else None
    for _ in range(rounds):
        gates.append(GATE.wait())  # each round begins once other programs leave the cores alone (or says not)
        for name in [n for n in stages[1] for _ in range(FRAME_PAIRS if n == FRAME_STAGE else 1)]:

            def measure(name=name):
                spent = {}
                for t, sim in sims.items():
                    if name == FRAME_STAGE:
                        spent[t] = _time_frames(sim, saved[id(sim)], stages[t][name])
                    else:
                        spent[t] = _time(stages[t][name], min_s)
                if threads > 1:
                    if name == FRAME_STAGE:
                        spent["copies"] = _time_frames_copies(copies, [saved[id(c)] for c in copies],
                                                              [c[name] for c in copy_stages])
                    else:
                        spent["copies"] = _time_copies([c[name] for c in copy_stages], min_s)
                return spent

            # each pair once the machine lets threads meet at joins, and again if it stopped within it (or says so)
            gated = join is not None and device == "cpu" and threads > 1
            spent = join.pair(measure) if gated else measure()
            for t in sims:
                spent_in[t][name].append(spent[t])
            if threads > 1:
                spent_copies[name].append(spent["copies"])
    load_after = list(os.getloadavg())
    rows = []
    for name in stages[1]:
        one = spent_in[1][name]
        many = spent_in[threads][name]
        row = {"stage": name, "t1_ms": 1e3 * statistics.median(one), "tn_ms": 1e3 * statistics.median(many),
               "speedup": _paired(one, many)}
        if threads > 1:
            row["copies_speedup"] = _paired(one, spent_copies[name])
            row["efficiency"] = row["speedup"] / row["copies_speedup"]
        rows.append(row)
    m = sims[1].model
    return {"scene": Path(path).name, "guides": m.strand_count, "segments": m.seg_per_strand,
            "substeps": int(scene.sim.substeps), "threads": threads, "rounds": rounds, "rows": rows,
            "load_before": [round(x, 2) for x in load_before], "load_after": [round(x, 2) for x in load_after],
            "gate": _gate_summary(gates), **({"join": join.summary(since)} if join is not None else {})}


def _gate_summary(gates: list[dict]) -> dict:
    """What the quiet gate saw before each round: how many began with other programs busy, and their cores."""
    busy = [g["others_busy_cores"] for g in gates if g["others_busy_cores"] is not None]
    return {"rounds_under_load": sum(g["under_load"] for g in gates), "rounds": len(gates),
            "others_busy_cores_max": max(busy) if busy else None, "threshold_cores": GATE.threshold}


def suite_threads(config, out, log=lambda message: None) -> dict:
    """Speed-up of every stage and of a whole frame, default scene and Ratboy mohawk, N threads against 1."""
    from hairwarp.executor import default_threads

    threads = int(getattr(config, "threads", 0) or 0) or default_threads()
    quick = bool(config.quick)
    rounds, min_s = (2, 0.05) if quick else (7, 0.3)
    results = {"threads": threads, "cores": default_threads(), "goals": GOALS, "scenes": []}
    log(f"threads: default scene, 1 against {threads} threads, {rounds} interleaved rounds")
    over = ["groom.count=100", "dense.count=500"] if quick else []
    join = JoinGate(threads) if threads > 1 and config.quiet_gate else None
    try:
        results["scenes"].append(bench_scene(SCENES / "long_hair.toml", threads, overrides=over, rounds=rounds,
                                             min_s=min_s, device=config.device, join=join))
        ratboy = SCENES / "ratboy_mohawk.toml"
        try:
            log("threads: Ratboy mohawk")
            results["scenes"].append(bench_scene(ratboy, threads, rounds=rounds, min_s=min_s, device=config.device,
                                                 join=join))
        except (FileNotFoundError, ValueError) as e:
            results["skipped"] = f"ratboy_mohawk: {e}"
        counts = sweep_counts(threads)
        log(f"threads: sweep over {counts} threads (dynamics {SWEEP_SIZE[0]} x {SWEEP_SIZE[1]}, default scene's "
            "frame)")
        results["sweep"] = sweep(counts, rounds=rounds, min_s=min_s, overrides=over, join=join)
    finally:
        if join is not None:
            join.close()
    results["files"] = [str(chart_threads(results, Path(out) / "threads.png")),
                        str(chart_sweep(results["sweep"], Path(out) / "threads_sweep.png"))]
    return results


def sweep_counts(threads: int) -> list[int]:
    """1, 2, 4, ... up to ``threads``, and ``threads`` itself."""
    counts, n = [], 1
    while n < threads:
        counts.append(n)
        n *= 2
    return [*counts, threads]


def sweep(counts, *, rounds: int, min_s: float, overrides=(), join: JoinGate | None = None) -> dict:
    """Speed-up against one thread at each of ``counts`` threads: the dynamics step of :data:`SWEEP_SIZE` (the
    dynamics suite's canonical strands) and a whole frame of the default scene, its dense hair included, as its table
    times it (:data:`FRAME_STAGE`): medians of interleaved rounds, each speed-up the median of the rounds' ratios to
    the first count."""
    from hairwarp.benchmarks.common import BENCH_DT
    from hairwarp.benchmarks.ours import canonical_model
    from hairwarp.runner import Simulation
    from hairwarp.scene import Scene
    from hairwarp.solver import Solver

    G, S = SWEEP_SIZE
    model = canonical_model(G, S, "cpu")
    control = model.control()
    steps = {}
    for n in counts:
        solver, states = Solver(model, "implicit_joints", threads=n), [model.state(), model.state()]

        def step(solver=solver, states=states):
            solver.step(states[0], states[1], control, BENCH_DT)
            states.reverse()

        step()
        steps[n] = step
    scene = Scene.load(SCENES / "long_hair.toml", overrides=["output.preview=false", *overrides])
    sims = {n: Simulation(scene, threads=n) for n in counts}
    saved = {}
    for n, sim in sims.items():
        for _ in range(WARMUP_FRAMES):
            sim.advance_frame()
        saved[n] = sim.checkpoint()
    dyn = {n: [] for n in counts}
    frame = {n: [] for n in counts}
    gates = []
    since = join.mark() if join is not None else None
    for _ in range(rounds):
        gates.append(GATE.wait())
        def timed_dynamics():
            return {n: _time(steps[n], min_s) for n in counts}

        def timed_frames():
            return {n: _time_frames(sims[n], saved[n], _stages(sims[n])[FRAME_STAGE]) for n in counts}

        for series, measure in ((dyn, timed_dynamics), (frame, timed_frames)):
            spent = join.pair(measure) if join is not None else measure()
            for n in counts:
                series[n].append(spent[n])
    first = counts[0]
    return {"dynamics": f"{G} x {S}", "frame": "long_hair.toml",
            "guides": sims[first].model.strand_count, "gate": _gate_summary(gates),
            **({"join": join.summary(since)} if join is not None else {}), "rows": [
                {"threads": n, "dynamics_ms": 1e3 * statistics.median(dyn[n]),
                 "dynamics_speedup": _paired(dyn[first], dyn[n]),
                 "frame_ms": 1e3 * statistics.median(frame[n]), "frame_speedup": _paired(frame[first], frame[n])}
                for n in counts]}


def chart_sweep(data: dict, path: Path) -> Path:
    """Speed-up against threads, both figures of :func:`sweep`, with the ideal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["threads"] for r in data["rows"]]
    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    ax.plot(n, n, "k--", lw=0.8, label="ideal")
    ax.plot(n, [r["dynamics_speedup"] for r in data["rows"]], "o-", label=f"dynamics {data['dynamics']}")
    ax.plot(n, [r["frame_speedup"] for r in data["rows"]], "s-", label=f"frame of {data['frame']}")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log", base=2)
    ax.set_xticks(n, [str(k) for k in n])
    ax.set_xlabel("threads")
    ax.set_ylabel("speed-up against 1 thread")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def chart_threads(data: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = data["scenes"]
    fig, axes = plt.subplots(1, len(scenes), figsize=(7 * len(scenes), 4.4), squeeze=False)
    for ax, s in zip(axes[0], scenes):
        names = [r["stage"] for r in s["rows"]]
        ax.barh(names, [r["speedup"] for r in s["rows"]], color="tab:blue", label="one simulation, N threads")
        if all("copies_speedup" in r for r in s["rows"]):
            ax.plot([r["copies_speedup"] for r in s["rows"]], names, "k|", ms=14, mew=2,
                    label="N independent copies, one thread each")
        ax.axvline(1.0, color="k", lw=0.8)
        ax.axvline(s["threads"], color="tab:green", ls="--", lw=0.8, label=f"{s['threads']} threads: ideal")
        ax.set_xlabel(f"speed-up, {s['threads']} threads against 1")
        ax.set_title(f"{s['scene']} ({s['guides']} x {s['segments']}), load {s['load_before'][0]}", fontsize=10)
        ax.invert_yaxis()
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, fontsize=8, frameon=False)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def md_threads(data: dict) -> list[str]:
    """A report section for :func:`suite_threads`'s results."""
    lines = ["## Every core of the CPU (`hairwarp bench threads`)", "",
             f"N = {data['threads']} threads against 1 ({data['cores']} cores this process may use), "
             f"{_rounds_words(data)}interleaved rounds, each stage timed on one "
             "thread and then on N: a speed-up is the median of the rounds' ratios (each round's two timings taken "
             f"moments apart), the times the rounds' medians; a whole frame: the mean of frames {WARMUP_FRAMES + 1}-"
             f"{WARMUP_FRAMES + FRAMES_PER_TIMING} of the run, restored from a checkpoint for every timing so every "
             "side runs the same frames. Goals on 2 cores: dynamics >= 1.9x, a whole frame >= 1.8x. The 1-minute load "
             "average before and after each scene is part of the figure: the machine is shared (the suite's own "
             "N-thread rounds add up to N to it); so is the quiet gate's count of rounds that began with other "
             "programs busy on a share of the cores anyway (it waits up to 30 s for them before each round). On a "
             "virtual machine whose cores other guests share, one simulation on N threads also slows in spells that "
             "leave N independent copies at full speed (its threads wait for each other at every join): a *join "
             "probe*, a small table of independent work timed on one thread and on N before each pair of timings, "
             "falls then, and the pair waits up to 30 s for it to come back within "
             f"{100 * JOIN_FRACTION:.0f} % of its usual value, the upper quartile of its probes so far, and is "
             f"timed again (up to {JOIN_RETRIES} times) when the probe after it is low (`JoinGate`); its record is "
             "part of the figure too.", "",
             "![speed-up per stage](threads.png)", ""]
    copies = all("copies_speedup" in r for s in data["scenes"] for r in s["rows"])
    if copies:
        lines += ["*N copies*: N independent one-thread copies of the simulation run the stage at once, one per thread "
                  "of this process, with no hand-off, join or shared array between them: their throughput against "
                  "one copy alone is what the machine gives N threads of this work. *Efficiency*: the speed-up over "
                  "that.", ""]
    for s in data["scenes"]:
        lines += [f"### {s['scene']}: {s['guides']} guides x {s['segments']} segments, {s['substeps']} substeps "
                  f"(load {s['load_before']} before, {s['load_after']} after"
                  + (f"; {_gate_words(s['gate'])}" if s.get("gate") else "")
                  + (f"; {_join_words(s['join'])}" if s.get("join") else "") + ")", ""]
        if copies:
            lines += ["| stage | 1 thread [ms] | N threads [ms] | speed-up | N copies | efficiency |",
                      "|---|---:|---:|---:|---:|---:|"]
            lines += [f"| {r['stage']} | {r['t1_ms']:.3f} | {r['tn_ms']:.3f} | {r['speedup']:.2f}x | "
                      f"{r['copies_speedup']:.2f}x | {100 * r['efficiency']:.0f} % |" for r in s["rows"]]
        else:
            lines += ["| stage | 1 thread [ms] | N threads [ms] | speed-up |", "|---|---:|---:|---:|"]
            lines += [f"| {r['stage']} | {r['t1_ms']:.3f} | {r['tn_ms']:.3f} | {r['speedup']:.2f}x |"
                      for r in s["rows"]]
        lines.append("")
        lines += _verdicts(s, data.get("goals", GOALS))
    if data.get("skipped"):
        lines += [f"Skipped: {data['skipped']}.", ""]
    if data.get("sweep"):
        lines += md_sweep(data["sweep"])
        lines += _sweep_against_table(data)
    return lines


def _sweep_against_table(data: dict) -> list[str]:
    """A line setting the sweep's frame at N threads beside the same frame in its scene's table: the one measure
    taken twice in a run, minutes apart, which shows how far the machine drifted between them."""
    sweep = data["sweep"]
    row = next((r for r in sweep["rows"] if r["threads"] == data["threads"]), None)
    scene = next((s for s in data["scenes"] if s["scene"] == sweep["frame"]), None)
    table = next((r for r in scene["rows"] if r["stage"] == FRAME_STAGE), None) if scene else None
    if row is None or table is None or data["threads"] < 2:
        return []
    return [f"- The sweep's frame at {data['threads']} threads is the frame of the {sweep['frame']} table above, timed "
            f"again later in the run: {row['frame_speedup']:.2f}x here against {table['speedup']:.2f}x there "
            f"({row['frame_ms']:.2f} ms against {table['tn_ms']:.2f} ms on {data['threads']} threads, "
            f"{sweep['rows'][0]['frame_ms']:.2f} against {table['t1_ms']:.2f} on one). The one measure taken twice "
            "in a run shows how far the machine drifted between them (README, \"Threads\").", ""]


def md_sweep(sweep_data: dict) -> list[str]:
    """The sweep's table and its goal at 16 threads."""
    d = sweep_data
    gate = _gate_words(d.get("gate"))
    join = _join_words(d.get("join"))
    lines = [f"### Threads sweep: dynamics of {d['dynamics']} (`implicit_joints`, dt 1 ms) and a frame of "
             f"{d['frame']}", "", *([f"Quiet gate: {gate}.", ""] if gate else []),
             *([f"Join gate: {join}.", ""] if join else []),
             "![speed-up against threads](threads_sweep.png)", "",
             "| threads | dynamics [ms] | speed-up | frame [ms] | speed-up |", "|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['threads']} | {r['dynamics_ms']:.3f} | {r['dynamics_speedup']:.2f}x | {r['frame_ms']:.2f} | "
              f"{r['frame_speedup']:.2f}x |" for r in d["rows"]]
    at16 = [r for r in d["rows"] if r["threads"] == 16]
    if at16:
        met = "met" if at16[0]["dynamics_speedup"] >= SWEEP_GOAL_16 else "not met"
        lines += ["", f"- dynamics at 16 threads: {at16[0]['dynamics_speedup']:.1f}x (goal >= {SWEEP_GOAL_16:g}x: "
                      f"{met})."]
    return [*lines, ""]


def _rounds_words(data: dict) -> str:
    counts = sorted({s["rounds"] for s in data.get("scenes", []) if "rounds" in s})
    return f"{', '.join(map(str, counts))} " if counts else ""


def _gate_words(gate: dict | None) -> str:
    if not gate or not gate.get("rounds"):
        return ""
    return (f"{gate['rounds_under_load']} of {gate['rounds']} rounds began with other programs busy on "
            f">= {gate['threshold_cores']:g} cores")


def _join_words(join: dict | None) -> str:
    if not join or not join.get("pairs"):
        return ""
    return (f"the join probe {join['median']:.2f}x at the median of {join['pairs']} pairs of timings, "
            f"{join['min']:.2f}x at the lowest; {join['low']} of {join['pairs']} pairs began with it below "
            f"{100 * join['fraction']:.0f} % of its usual {join['usual']:.2f}x, after {join['waited_s']:g} s of "
            f"waiting in all; {join.get('redone', 0)} timed again after it fell within them, "
            f"{join.get('ended_low', 0)} kept with it still low")


def _verdicts(scene: dict, goals: dict) -> list[str]:
    """One bullet per goal: the speed-up, met or not, and what N independent copies reach."""
    keys = {"dynamics": "dynamics (aba + integrate)", "frame": "frame (detection, substeps, dense)"}
    rows = {r["stage"]: r for r in scene["rows"]}
    out = []
    for goal, stage in keys.items():
        r = rows.get(stage)
        if r is None or scene["threads"] != 2:
            continue
        text = (f"- {goal}: {r['speedup']:.2f}x (goal >= {goals[goal]:g}x on 2 cores: "
                f"{'met' if r['speedup'] >= goals[goal] else 'not met'})")
        if "copies_speedup" in r:
            text += f"; 2 independent copies reach {r['copies_speedup']:.2f}x, so the executor keeps " \
                    f"{100 * r['efficiency']:.0f} % of what the machine gives"
        out.append(text + ".")
    return [*out, ""] if out else []
