"""Cost of one output frame of dense hair against the cost of simulating that frame.

:func:`bench_dense_frame` runs the default scene (``long_hair.toml``: about 300 guides of 20 segments, 8 substeps a
frame, the ellipsoid head) and times, per output frame and separately: the simulation of the guides, then for each
dense strand count the interpolation of positions and velocities, their Hermite densification, the optional push-out
from the head, the copy to the host, and :meth:`hairwarp.io.cache.CacheWriter.write_frame` of the dense curves with
velocities into a temporary file, split by the writer into checks, ``Vt`` conversion, authoring and crate saves.
:func:`bench_dense_pipeline` times whole frames (simulate, output, write) with no writer, the inline writer and the
background writer (:class:`hairwarp.io.background.BackgroundCacheWriter`), which is the honest figure once the
writing runs beside the simulation, and with :class:`SingleLayerWriter` (one crate layer saved after every frame),
the baseline that shows what the per-frame layers, their fsyncs and the root rewrites cost. The goal is a frame that
costs less to write than to simulate.
:func:`suite_dense` is ``hairwarp bench dense``; :func:`md_dense` renders its report section.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from hairwarp.benchmarks.common import machine_words

# Write times below this are within the frames' scatter: no ratio is taken of them [s].
NOISE_S = 2e-3

# Frames simulated before timing: the hair leaves its build pose and the head starts its motion.
SETTLE_FRAMES = 4


def _settled_default_scene(device, repeats: int, threads: int | None = None):
    """The default scene ``SETTLE_FRAMES`` frames in (on ``threads`` CPU threads; None: every core), and the median
    wall time of one more simulated frame: ``(scene, simulation, quiet-gate record, seconds)``."""
    import warp as wp

    from hairwarp.benchmarks.common import GATE
    from hairwarp.runner import Simulation
    from hairwarp.scene import Scene

    scene = Scene.default()
    sim = Simulation(scene, device=device, threads=threads)
    for _ in range(SETTLE_FRAMES):
        sim.advance_frame()
    gate = GATE.wait()
    return scene, sim, gate, _median_time(sim.advance_frame, lambda: wp.synchronize_device(device), repeats)


def _scene_dense(model, cfg, count: int, device):
    """``count`` dense strands on ``model``'s guides with the scene's ``[dense]`` settings ``cfg``."""
    from hairwarp.dense import DenseHair

    return DenseHair.build(
        model.rest_vertex_positions, model.root_uv, count=count, grid_shape=model.grid_shape,
        root_normal=model.root_normal, seed=int(cfg.seed), length_variation=float(cfg.length_variation),
        tip_spread=float(cfg.tip_spread), clumping=float(cfg.clumping),
        samples_per_segment=int(cfg.samples_per_segment), device=device)


def _median_time(fn, sync, repeats: int) -> float:
    """Median wall time of ``fn()`` over ``repeats`` calls after one untimed call, synchronised on both ends."""
    fn()
    sync()
    samples = []
    for _ in range(repeats):
        sync()
        t0 = time.perf_counter()
        fn()
        sync()
        samples.append(time.perf_counter() - t0)
    return float(np.median(samples))


def _time_writes(folder: Path, name: str, counts: np.ndarray, widths, basis: str, points, velocities, frames: int,
                 fps: float) -> dict:
    """Write ``frames`` frames (plus one untimed) of the curves; per-frame means of the writer's phases.

    One value changes between frames: the crate format stores identical arrays once, which would flatter the
    figures.
    """
    from hairwarp.io.cache import CacheWriter, cache_bytes

    path = folder / f"{name}.usdc"
    points, velocities = points.copy(), velocities.copy()
    wall = 0.0
    with CacheWriter(path, fps=fps) as cache:
        cache.add_curves("hair", counts, widths=widths, basis=basis)
        cache.write_frame(0, {"hair": (points, velocities)})
        before = dict(cache.timings)
        for f in range(1, frames + 1):
            points[f % len(points), 0] += 1.0e-3
            velocities[f % len(velocities), 0] += 1.0e-3
            t0 = time.perf_counter()
            cache.write_frame(f, {"hair": (points, velocities)})
            wall += time.perf_counter() - t0
        t0 = time.perf_counter()
    wall += time.perf_counter() - t0  # the close saves what is left
    phases = {k: (cache.timings[k] - before[k]) / frames for k in before}
    size = cache_bytes(path)
    path.unlink()
    return {"basis": basis, "frames": frames, "write_s": wall / frames,
            **{f"{k}_s": v for k, v in phases.items()}, "bytes_per_frame": size / (frames + 1)}


def bench_dense_frame(counts=(10_000, 100_000), quick: bool = False, device=None, *, repeats: int | None = None,
                      push_out: bool = True, threads: int | None = None) -> dict:
    """Time one output frame of dense hair, stage by stage, against one simulated frame of the default scene.

    Args:
        counts: dense strand counts.
        quick: fewer repeats (smoke runs).
        device: Warp device; the default device when None.
        repeats: timed repetitions per figure (median; for writes, frames averaged); default 5, quick 2.
        push_out: also time :meth:`hairwarp.DenseHair.push_out` from the scene's head collider.

    Returns:
        ``{"device", "guides", "segments", "substeps", "repeats", "simulate_frame_s", "load", "goal", "meets",
        "results": [{"count", "points_per_curve", "points", "load", "interpolate_s", "hermite_s", "push_out_s",
        "pushed_vertices", "download_s", "write": [{"basis", "frames", "write_s", "check_s", "convert_s", "set_s",
        "save_s", "bytes_per_frame"}, ...], "write_s", "frame_output_s", "write_over_simulate",
        "write_cheaper_than_simulate", "catmull_rom_write_s", "catmull_rom_cheaper_than_simulate"}, ...]}``,
        seconds per output frame. ``write_s`` is the scene's cache (linear curves over the Hermite samples, M per
        segment); ``frame_output_s`` adds interpolation, Hermite and the copy to the host to it; the Catmull-Rom
        cache over the interpolated vertices (``dense.basis = "catmullRom"``, which renderers evaluate as the same
        Hermite curve) has 1/M the points.
    """
    import warp as wp

    from hairwarp.benchmarks.common import GATE

    device = wp.get_device(device)
    repeats = int(repeats or (2 if quick else 5))

    def sync():
        wp.synchronize_device(device)

    scene, sim, gate, simulate_s = _settled_default_scene(device, repeats, threads)
    model = sim.model
    cfg = scene.dense
    fps = float(scene.sim.fps)
    x, v = sim.state.vertex_positions, sim.state.vertex_velocities
    hx, hv = sim.stepper.control.head_xform, sim.stepper.control.head_velocity
    results = []
    with tempfile.TemporaryDirectory(prefix="hairwarp-bench-dense-") as tmp:
        folder = Path(tmp)
        for n in counts:
            hair = _scene_dense(model, cfg, int(n), device)
            row = {"count": int(n), "points_per_curve": hair.points_per_curve,
                   "points": int(hair.curve_points.shape[0]), "load": GATE.wait()}
            row["interpolate_s"] = _median_time(lambda h=hair: h.evaluate(x, v, hx, hv, hermite=False), sync, repeats)

            def hermite(h=hair):
                h.densify()
                h.densify(h.dense_velocities, out=h.curve_velocities)

            row["hermite_s"] = _median_time(hermite, sync, repeats)
            if push_out and sim.collider_set is not None:
                samples = []
                for _ in range(repeats):
                    hair.interpolate(x, hx)
                    sync()
                    t0 = time.perf_counter()
                    hair.push_out(sim.collider_set, hx)
                    sync()
                    samples.append(time.perf_counter() - t0)
                row["push_out_s"] = float(np.median(samples))
                row["pushed_vertices"] = sum(hair.push_counts)
            else:
                row["push_out_s"], row["pushed_vertices"] = None, None
            hair.evaluate(x, v, hx, hv, colliders=sim.collider_set if push_out else None)
            row["download_s"] = _median_time(lambda h=hair: (h.curve_points.numpy(), h.curve_velocities.numpy()),
                                             sync, repeats)
            points, velocities = hair.curve_points.numpy(), hair.curve_velocities.numpy()
            width = tuple(cfg.width)
            linear = _time_writes(folder, "linear", hair.curve_vertex_counts(), width, "linear", points, velocities,
                                  repeats, fps)
            del points, velocities
            catmull_rom = _time_writes(folder, "catmull_rom", hair.curve_vertex_counts(hermite=False), width,
                                       "catmullRom", hair.dense_vertices.numpy(), hair.dense_velocities.numpy(),
                                       repeats, fps)
            row["write"] = [linear, catmull_rom]
            row["write_s"] = linear["write_s"]
            row["frame_output_s"] = row["interpolate_s"] + row["hermite_s"] + row["download_s"] + row["write_s"]
            row["write_over_simulate"] = row["write_s"] / simulate_s
            row["write_cheaper_than_simulate"] = bool(row["write_s"] < simulate_s)
            row["catmull_rom_write_s"] = catmull_rom["write_s"]
            row["catmull_rom_cheaper_than_simulate"] = bool(catmull_rom["write_s"] < simulate_s)
            results.append(row)
            del hair
    return {
        "device": str(device),
        "guides": model.strand_count,
        "segments": model.seg_per_strand,
        "substeps": int(scene.sim.substeps),
        "repeats": repeats,
        "simulate_frame_s": simulate_s,
        "load": gate,
        "goal": "writing an output frame costs less than simulating it",
        "meets": bool(all(r["write_cheaper_than_simulate"] for r in results)),
        "results": results,
    }


class SingleLayerWriter:
    """The simplest cache writer, a baseline for :class:`hairwarp.io.cache.CacheWriter`: one crate layer on disk
    whose samples grow frame by frame, saved after each (usd-core appends the new samples and rewrites the crate's
    tables), with no fsync, no per-frame file and no root to rewrite. A stop or a full disk during a save can
    leave the one file unreadable, and a frame costs its page-cache writes, not the disk's."""

    def __init__(self, path: Path, *, fps: float):
        from hairwarp.io.usd_common import _new_stage

        self.path = Path(path)
        self._layer, self._stage = _new_stage(str(self.path), up_axis="Z", meters_per_unit=1.0,
                                              doc="single-layer baseline")
        self._layer.timeCodesPerSecond = self._layer.framesPerSecond = float(fps)
        self._attrs: dict[str, tuple] = {}
        self.timings = {"check": 0.0, "convert": 0.0, "set": 0.0, "save": 0.0}

    def add_curves(self, name: str, counts, *, widths, basis: str) -> None:
        from hairwarp.io.usd_common import HAIR_PATH, _define_curves

        counts = np.asarray(counts, dtype=np.int32)
        curves = _define_curves(self._stage, f"{HAIR_PATH}/{name}", counts, np.asarray([widths[0]], np.float32),
                                "constant", basis=basis, kind="dense", purpose="default")
        self._attrs[name] = (curves.CreatePointsAttr(), curves.CreateVelocitiesAttr(), curves.CreateExtentAttr())

    def write_frame(self, frame: int, curves: dict) -> None:
        from hairwarp.io.usd_common import _vec3f

        t0 = time.perf_counter()
        values = {name: (_vec3f(p), _vec3f(v), _vec3f(np.stack([p.min(axis=0), p.max(axis=0)])))
                  for name, (p, v) in curves.items()}
        t1 = time.perf_counter()
        for name, (p, v, extent) in values.items():
            for attr, value in zip(self._attrs[name], (p, v, extent)):
                attr.Set(value, float(frame))
        t2 = time.perf_counter()
        self._layer.Save()
        t3 = time.perf_counter()
        for key, dt in (("convert", t1 - t0), ("set", t2 - t1), ("save", t3 - t2)):
            self.timings[key] += dt

    def flush(self) -> None:
        pass

    def close(self) -> Path:
        self._layer.Save()
        del self._stage
        return self.path


def _pipeline_block(sim, hair, folder: Path, basis: str, writer: str, frames: int, push_out: bool) -> dict:
    """Simulate ``frames`` frames, evaluate the dense hair after each and hand it to ``writer`` ("none", "inline",
    "background" or "single", the :class:`SingleLayerWriter` baseline); the wall time per frame of the whole loop,
    until every frame is saved.

    The writer is opened and given one untimed frame first, and closed after the clock stops: the background
    writer's process starts in about a second and the close renames the file, once per cache (``close_s``).
    """
    import warp as wp

    from hairwarp.io.background import BackgroundCacheWriter
    from hairwarp.io.cache import CacheWriter, cache_bytes

    hermite = basis == "linear"
    fps = float(sim.scene.sim.fps)
    colliders = sim.collider_set if push_out else None

    def output():
        s, c = sim.stepper.state, sim.stepper.control
        p, v = hair.evaluate(s.vertex_positions, s.vertex_velocities, c.head_xform, c.head_velocity, hermite=hermite,
                             colliders=colliders)
        return p.numpy(), v.numpy()

    cache = None
    path = folder / f"pipeline_{basis}_{writer}.usdc"
    if writer != "none":
        cls = {"background": BackgroundCacheWriter, "inline": CacheWriter, "single": SingleLayerWriter}[writer]
        cache = cls(path, fps=fps)
        cache.add_curves("hair", hair.curve_vertex_counts(hermite), widths=tuple(sim.scene.dense.width), basis=basis)
        cache.write_frame(0, {"hair": output()})
        cache.flush()  # the untimed frame is saved before the clock starts
        before = dict(cache.timings)
    wp.synchronize_device(sim.model.device)
    blocked = 0.0
    t_start = time.perf_counter()
    for f in range(1, frames + 1):
        sim.advance_frame()
        points, velocities = output()
        if cache is not None:
            t0 = time.perf_counter()
            cache.write_frame(f, {"hair": (points, velocities)})
            blocked += time.perf_counter() - t0
    if cache is not None:
        cache.flush()  # every frame complete on disk before the clock stops
    t_end = time.perf_counter()
    row = {"writer": writer, "frames": frames, "frame_s": (t_end - t_start) / frames, "blocked_s": blocked / frames}
    if cache is not None:
        t_close = time.perf_counter()
        cache.close()
        row["close_s"] = time.perf_counter() - t_close
        row.update({f"{k}_s": (cache.timings[k] - before[k]) / frames for k in before})
        row["writer_own_s"] = (sum(cache.timings[k] - before[k] for k in ("convert", "set", "save")) / frames)
        row["bytes_per_frame"] = cache_bytes(path) / (frames + 1)
        path.unlink()
    return row


def bench_dense_pipeline(counts=(10_000, 100_000), bases=("catmullRom", "linear"), quick: bool = False, device=None,
                         *, frames: int | None = None, rounds: int | None = None, push_out: bool = True,
                         threads: int | None = None) -> dict:
    """End-to-end frames of the default scene with dense output: simulate, interpolate (Hermite for linear curves,
    push-out from the head), copy to the host, write, with no writer, the inline writer and the background writer.

    Every (count, basis, writer) runs ``rounds`` blocks of ``frames`` frames, interleaved, and keeps its median block
    (blocks scatter by several milliseconds a frame: other programs share the cores, and the disk's pace varies).
    ``write_s`` of a writer is its frame time less the frame time with no writer: what writing adds to a frame.
    ``single`` is :class:`SingleLayerWriter`, the baseline of one layer saved after every frame; ``inline_over_single``
    the inline writer's write time over it (None where the baseline's is below :data:`NOISE_S`, when the ratio would be
    noise over noise). With the background writer the caller is blocked only for the checks, the copy into shared memory
    and any wait for a free slot (``blocked_s``, the close included); the writer process spends ``writer_own_s`` a frame
    on its second core, and the frame costs about max(simulate and output, writer) rather than their sum.

    Returns:
        ``{"device", "guides", "segments", "substeps", "simulate_frame_s", "frames", "rounds", "results": [{"count",
        "basis", "points", "output_frame_s", "inline": {...}, "background": {...}, "single": {...}, "inline_write_s",
        "background_write_s", "single_write_s", "inline_over_single", "blocked_s", "writer_own_s",
        "write_cheaper_than_simulate", "blocked_cheaper_than_simulate", "writer_cheaper_than_simulate"}, ...]}``,
        seconds per frame; the writer dicts hold ``frame_s``, ``blocked_s``, the writer's phases (``check_s`` ...
        ``save_s``), ``writer_own_s`` and ``bytes_per_frame``.
    """
    import warp as wp

    from hairwarp.benchmarks.common import GATE

    device = wp.get_device(device)
    frames = int(frames or (2 if quick else 4))
    rounds = int(rounds or (1 if quick else 5))
    scene, sim, gate, simulate_s = _settled_default_scene(device, 3 if quick else 5, threads)
    model = sim.model
    cfg = scene.dense
    results = []
    with tempfile.TemporaryDirectory(prefix="hairwarp-bench-pipeline-") as tmp:
        folder = Path(tmp)
        for n in counts:
            hair = _scene_dense(model, cfg, int(n), device)
            for basis in bases:
                blocks: dict[str, list] = {}
                for _ in range(rounds):
                    for writer in ("none", "background", "inline", "single"):
                        blocks.setdefault(writer, []).append(
                            _pipeline_block(sim, hair, folder, basis, writer, frames, push_out))
                # the median block of each writer (its row's phases are that block's)
                best = {w: sorted(rows, key=lambda row: row["frame_s"])[len(rows) // 2] for w, rows in blocks.items()}
                base = best["none"]["frame_s"]
                bg, inline, single = best["background"], best["inline"], best["single"]
                points = int(hair.curve_vertex_counts(basis == "linear").sum())
                results.append({
                    "count": int(n), "basis": basis, "points": points, "load": GATE.wait(),
                    "output_frame_s": base, "inline": inline, "background": bg,
                    "single": single, "single_write_s": single["frame_s"] - base,
                    "inline_write_s": inline["frame_s"] - base, "background_write_s": bg["frame_s"] - base,
                    "inline_over_single": ((inline["frame_s"] - base) / (single["frame_s"] - base)
                                           if single["frame_s"] - base > NOISE_S else None),
                    "blocked_s": bg["blocked_s"], "writer_own_s": bg["writer_own_s"],
                    "write_cheaper_than_simulate": bool(bg["frame_s"] - base < simulate_s),
                    "blocked_cheaper_than_simulate": bool(bg["blocked_s"] < simulate_s),
                    "writer_cheaper_than_simulate": bool(bg["writer_own_s"] < simulate_s),
                })
            del hair
    return {"device": str(device), "guides": model.strand_count, "segments": model.seg_per_strand,
            "substeps": int(scene.sim.substeps), "threads": sim.solver.executor.threads, "simulate_frame_s": simulate_s,
            "frames": frames, "rounds": rounds,
            "load": gate, "results": results}


def disk_write_rate(folder=None, total_bytes: int = 512 << 20, chunk_bytes: int = 8 << 20) -> float:
    """Sustained write rate [B/s] of the disk under ``folder`` (default: the temporary folder): ``total_bytes``
    written in chunks and flushed to the disk (``fsync``), as a long cache run writes once the page cache is full."""
    chunk = np.random.default_rng(0).integers(0, 255, chunk_bytes, dtype=np.uint8).tobytes()
    with tempfile.NamedTemporaryFile(dir=folder, suffix=".bin") as f:
        t0 = time.perf_counter()
        for _ in range(max(1, total_bytes // chunk_bytes)):
            f.write(chunk)
        f.flush()
        os.fsync(f.fileno())
        elapsed = time.perf_counter() - t0
    return max(1, total_bytes // chunk_bytes) * chunk_bytes / elapsed


def suite_dense(config, out, log=lambda message: None) -> dict:
    """The ``dense`` suite of ``hairwarp bench``: the cost of one output frame stage by stage
    (:func:`bench_dense_frame`) and the end-to-end frame with each writer (:func:`bench_dense_pipeline`), for
    10,000 and 100,000 dense strands (quick: 1,000), against one simulated frame of the default scene.
    ``config``: a :class:`hairwarp.benchmarks.common.BenchConfig`."""
    quick, device = bool(config.quick), config.device
    counts = (1_000,) if quick else (10_000, 100_000)
    log(f"dense: one output frame stage by stage, {', '.join(f'{n:,}' for n in counts)} strands")
    threads = int(getattr(config, "threads", 0) or 0) or None  # --threads; None: every core
    stages = bench_dense_frame(counts=counts, quick=quick, device=device, threads=threads)
    log("dense: end-to-end frames with no writer, the background writer, the inline writer and one layer saved "
        "each frame")
    pipeline = bench_dense_pipeline(counts=counts, quick=quick, device=device, threads=threads)
    verdicts = [{k: r[k] for k in ("count", "basis", "write_cheaper_than_simulate", "writer_cheaper_than_simulate")}
                for r in pipeline["results"]]
    log("dense: the disk's sustained write rate")
    disk = disk_write_rate(total_bytes=(64 if quick else 512) << 20)
    return {"goal": "writing an output frame costs less than simulating it", "quick": quick, "stages": stages,
            "pipeline": pipeline, "verdicts": verdicts, "disk_write_rate": disk}


def md_dense(data: dict) -> list[str]:
    """A report section for :func:`suite_dense`'s results."""
    pipe = data["pipeline"]
    sim_ms = 1e3 * pipe["simulate_frame_s"]
    lines = ["## Dense output: writing a frame against simulating it (`hairwarp bench dense`)", "",
             f"One simulated frame of the default scene ({pipe['guides']} guides x {pipe['segments']} segments, "
             f"{pipe['substeps']} substeps): **{sim_ms:.1f} ms** on {pipe['device']}"
             f"{_threads_text(pipe.get('threads'))}. Per output frame, "
             f"median of {pipe['rounds']} blocks of {pipe['frames']} frames; *write* = frame time with the "
             "writer less the frame time without one (noise can make it negative); *blocked* = time the "
             "simulating thread spends in the writer's `write_frame` (inline: checks, copy into `Vt` arrays, "
             "authoring, the frame layer's export, waiting for the previous frame's commit, which its thread "
             "fsyncs, renames and names in the root while the next frame simulates; background: checks and the "
             "copy into shared memory); *writer process* = extents, convert, set and save in the background "
             "writer's process; *single layer* = the same frames into one crate layer saved after every frame "
             "(`SingleLayerWriter`: no fsync, no frame file, no root rewrite, and a stop during a save can leave "
             "its one file unreadable), the baseline of what the frame layers cost. Write < simulate: inline / "
             "background.",
             ""]
    disk = data.get("disk_write_rate")
    if disk:
        lines += [f"The disk takes {disk / 1e6:.0f} MB/s sustained (written and flushed with `fsync`): the pace of a "
                  "cache longer than the page cache holds. *Disk floor* = a frame's bytes at that pace, what no "
                  "writer can go below for such a run.", ""]
    lines += ["| strands | basis | MB/frame | sim + output, no writer [ms] | inline: write [ms] | "
              "inline: blocked [ms] | "
              "background: write [ms] | background: blocked [ms] | writer process [ms] | single layer: write [ms] | "
              "inline / single layer | disk floor [ms] | write < simulate? |",
              "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in pipe["results"]:
        bg = r["background"]
        floor = f"{1e3 * bg['bytes_per_frame'] / disk:.0f}" if disk else "–"
        lines.append(
            f"| {r['count']:,} | {r['basis']} | {bg['bytes_per_frame'] / 1e6:.1f} | {1e3 * r['output_frame_s']:.0f} | "
            f"{1e3 * r['inline_write_s']:.0f} | {1e3 * r['inline']['blocked_s']:.0f} | "
            f"{1e3 * r['background_write_s']:.0f} | {1e3 * r['blocked_s']:.0f} | "
            f"{1e3 * r['writer_own_s']:.0f} | {1e3 * r['single_write_s']:.0f} | "
            f"{'–' if r['inline_over_single'] is None else format(r['inline_over_single'], '.2f')} | "
            f"{floor} | "
            f"{'yes' if r['inline_write_s'] < pipe['simulate_frame_s'] else 'no'} / "
            f"{'yes' if r['write_cheaper_than_simulate'] else 'no'} |")
    ratios = [r["inline_over_single"] for r in pipe["results"] if r["inline_over_single"] is not None]
    if ratios:
        slower = [r for r in pipe["results"] if (r["inline_over_single"] or 0.0) > 1.1]
        lines += ["", f"Frame layers against one layer saved each frame, in the same run: the inline writer takes "
                  f"{min(ratios):.2f}-{max(ratios):.2f}x the single layer's write time."]
        if slower:
            where = ", ".join(f"{r['count']:,} {r['basis']}: {1e3 * r['inline_write_s']:.0f} against "
                              f"{1e3 * r['single_write_s']:.0f} ms" for r in slower)
            lines[-1] += (f" Where it takes more than 1.1x ({where}): the frame layer, its fsyncs and the root "
                          "cost more than appending to one layer that keeps every frame's arrays in memory, whose "
                          "fresh copies outweigh them at larger frames.")
    sm = data.get("machine", {})
    lines += ["", f"*Suite `dense`{' (quick sizes)' if data.get('quick') else ''}: {data.get('wall_s')} s"
                  + (f" on {sm['date']}{machine_words(sm)}" if sm.get("date") else "") + ".*"]
    return lines


def _threads_text(threads) -> str:
    if not threads:
        return ""
    return f", {threads} thread{'' if threads == 1 else 's'}"


def bench_usd_write(counts=(10_000, 100_000), quick: bool = False, device=None, *, points_per_curve: int = 81,
                    frames: int | None = None) -> dict:
    """Time :meth:`CacheWriter.write_frame` of dense curves with velocities into a temporary ``.usdc``, per phase.

    The curves are synthetic random walks (a fresh array per frame, so the crate cannot share them between
    frames); :func:`hairwarp.benchmarks.dense.bench_dense_frame` times the same writes with simulated hair.

    Args:
        counts: curve counts.
        quick: two frames per count instead of four.
        device: not used (writing is host work); accepted so every stage hook is called alike.
        points_per_curve: vertices per curve (81: 20 segments Hermite-sampled 4 times).
        frames: timed frames per count (after one untimed frame).

    Returns:
        ``{"points_per_curve", "frames", "results": [{"count", "points", "write_s", "check_s", "convert_s", "set_s",
        "save_s", "bytes_per_frame", "megabytes_per_s"}, ...]}``, seconds per frame (mean over the timed frames).
    """
    frames = int(frames or (2 if quick else 4))
    rng = np.random.default_rng(0)
    results = []
    from hairwarp.io.cache import CacheWriter, cache_bytes

    with tempfile.TemporaryDirectory(prefix="hairwarp-bench-usd-") as tmp:
        for n in counts:
            npts = int(n) * int(points_per_curve)
            base = np.cumsum(rng.normal(scale=1e-3, size=(npts, 3)).astype(np.float32), axis=0)
            path = Path(tmp) / f"bench{n}.usdc"
            wall = 0.0
            with CacheWriter(path, fps=30.0) as cache:
                cache.add_curves("hair", np.full(int(n), int(points_per_curve)))
                for f in range(frames + 1):
                    points, velocities = base + np.float32(1e-4 * f), base * np.float32(0.01 * (f + 1))
                    if f == 1:
                        before = dict(cache.timings)
                    t0 = time.perf_counter()
                    cache.write_frame(f, {"hair": (points, velocities)})
                    wall += (time.perf_counter() - t0) if f > 0 else 0.0
            size = cache_bytes(path)
            per_frame = wall / frames
            results.append({"count": int(n), "points": npts, "write_s": per_frame,
                            **{f"{k}_s": (cache.timings[k] - before[k]) / frames for k in before},
                            "bytes_per_frame": size / (frames + 1),
                            "megabytes_per_s": 24.0 * npts / per_frame / 1e6})
    return {"points_per_curve": int(points_per_curve), "frames": frames, "results": results}
