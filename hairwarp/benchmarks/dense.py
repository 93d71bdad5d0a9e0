"""Cost of one output frame of dense hair against the cost of simulating that frame.

:func:`bench_dense_frame` runs the default scene (``long_hair.toml``: about 300 guides of 20 segments, 8 substeps a
frame, the ellipsoid head) and times, per output frame and separately: the simulation of the guides, then for each
dense strand count the interpolation of positions and velocities, their Hermite densification, the optional push-out
from the head, the copy to the host, and :meth:`hairwarp.usd.CacheWriter.write_frame` of the dense curves with
velocities into a temporary file, split by the writer into checks, ``Vt`` conversion, authoring and crate saves. The
goal is a frame that costs less to write than to simulate.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import numpy as np

# Frames simulated before timing: the hair leaves its build pose and the head starts its motion.
SETTLE_FRAMES = 4


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
    from hairwarp.usd import CacheWriter

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
    size = path.stat().st_size
    path.unlink()
    return {"basis": basis, "frames": frames, "write_s": wall / frames,
            **{f"{k}_s": v for k, v in phases.items()}, "bytes_per_frame": size / (frames + 1)}


def bench_dense_frame(counts=(10_000, 100_000), quick: bool = False, device=None, *, repeats: int | None = None,
                      push_out: bool = True) -> dict:
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
    from hairwarp.dense import DenseHair
    from hairwarp.runner import Simulation
    from hairwarp.scene import Scene

    device = wp.get_device(device)
    repeats = int(repeats or (2 if quick else 5))

    def sync():
        wp.synchronize_device(device)

    scene = Scene.default()
    sim = Simulation(scene, device=device)
    model = sim.model
    for _ in range(SETTLE_FRAMES):
        sim.advance_frame()
    gate = GATE.wait()
    simulate_s = _median_time(sim.advance_frame, sync, repeats)
    cfg = scene.dense
    fps = float(scene.sim.fps)
    x, v = sim.state.vertex_positions, sim.state.vertex_velocities
    hx, hv = sim.stepper.control.head_xform, sim.stepper.control.head_velocity
    results = []
    with tempfile.TemporaryDirectory(prefix="hairwarp-bench-dense-") as tmp:
        folder = Path(tmp)
        for n in counts:
            hair = DenseHair.build(
                model.rest_vertex_positions, model.root_uv, count=int(n), grid_shape=model.grid_shape,
                root_normal=model.root_normal, seed=int(cfg.seed), length_variation=float(cfg.length_variation),
                tip_spread=float(cfg.tip_spread), clumping=float(cfg.clumping),
                samples_per_segment=int(cfg.samples_per_segment), device=device)
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
